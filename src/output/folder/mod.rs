//! One study per folder, committed once; nothing in it that kfmc did not write is replaced or
//! removed.
//!
//! A writer holds an exclusive lock on its output folder for its whole life
//! ([`StudyFolder::open`], [`FolderLock`]): an advisory `flock` on `.kfmc.lock` that the
//! operating system releases when the process ends, however it ends, so a second writer is
//! refused while the first lives and nothing has to guess whether a lock is stale. The lock is
//! taken before anything in the folder is read or touched.
//!
//! A folder belongs to kfmc only by its manifest ([`Manifest::inspect`]): `format =
//! "kfmc-result/1"` with a kind, or a manifest of an earlier kfmc whose tables all still match
//! it. The manifest lists every table, file and sub-folder kfmc wrote there, and a writer
//! replaces or removes only those, after it has accepted the folder
//! ([`StudyFolder::prepare`]): a command replaces only a folder of its own kind unless forced,
//! and even forced it refuses to replace a file the manifest does not list. A user's file
//! that has a table's name, a `.partial` suffix or the name `manifest.toml` stays the user's.
//! Nothing inside the folder is opened through a symbolic link (the folder itself may be
//! one), and a command's input never lies inside the folder it writes.
//!
//! Tables are written under temporary names of kfmc's own ([`super::atomic::temp_name`]);
//! [`StudyFolder::commit`] then replaces the old manifest by one that lists the new study and,
//! under `replacing`, what the old one listed; removes what the old study listed that the new
//! one does not write; moves the new tables and folders into place; and writes the final
//! manifest **last**, listing every table with its size, row count and checksum. The manifest
//! is the commit record: a reader ([`verify`]) accepts a folder only when its manifest is
//! final and every table it lists is there and matches. A kill at any moment therefore leaves
//! either the old study (killed before the commit), the new one (after it), or — for the few
//! renames in between — a manifest in the middle of its commit, which every reader refuses and
//! the next writer takes over; never a mix that looks complete.
//!
//! A writer killed before its commit leaves temporary files. Their names carry its token
//! ([`super::atomic::process_token`]), which it recorded in the lock file; the next writer
//! that accepts the folder removes those files, and no other `.partial` entry.

use std::path::{Path, PathBuf};
use std::sync::Mutex;

use crate::error::OutputError;
use crate::output::atomic::{process_token, temp_token, type_name};
pub use crate::output::atomic::{sync_file, temp_beside, write_atomic};
use crate::output::checkpoint::CHECKPOINT_DIR;
use crate::output::manifest::{FORMAT, Found, Listed, Manifest, StudyKind, TableEntry};
use crate::output::schema;
pub use crate::output::table::FinishedTable;

mod entries;
mod lock;
mod verify;

use entries::{
    check_listed_table, check_tables, is_inside_path, legacy_tune_stages, lstat_under,
    refuse_inputs, remove_listed_file, reserved, sanitized, still_matching, table_of,
    written_beside_studies,
};
pub use entries::{is_kfmc_describe, refuse_link, relative_inside};
pub use lock::FolderLock;
pub use verify::{checksum_file, verify};

/// The lock file's name inside an output folder.
pub const LOCK_FILE: &str = ".kfmc.lock";

/// The manifest's name inside a result folder.
const MANIFEST: &str = "manifest.toml";

/// The first line of every `describe.toml` kfmc writes: what tells it from a user's file of
/// that name, in a folder whose manifest does not list it.
pub const DESCRIBE_FORMAT_LINE: &str = "format = \"kfmc-describe/1\"";

/// An output folder held exclusively by this process until dropped.
#[derive(Debug)]
pub struct StudyFolder {
    dir: PathBuf,
    lock: FolderLock,
    /// What [`StudyFolder::prepare`] accepted: the kind of study and what kfmc wrote there.
    accepted: Mutex<Option<Accepted>>,
}

/// A folder a writer accepted.
#[derive(Clone, Debug)]
struct Accepted {
    kind: StudyKind,
    /// What its manifest lists (and, for a manifest from an earlier kfmc, the tables that
    /// matched it): all that a commit may replace or remove.
    listed: Listed,
}

/// A sub-folder of a study (a tuning stage) written in full under a temporary path, moved
/// into place by the study's commit.
#[derive(Debug)]
pub struct FinishedFolder {
    /// Its name inside the study folder.
    pub name: String,
    /// Where it was written.
    pub tmp: PathBuf,
}

fn io<'a>(action: &'static str, path: &'a Path) -> impl FnOnce(std::io::Error) -> OutputError + 'a {
    move |source| OutputError::Io {
        action,
        path: path.to_path_buf(),
        source,
    }
}

impl StudyFolder {
    /// Locks `dir` (creating it if needed) and readies it for a study of `kind`: refused when
    /// another kfmc holds it, when it holds another kind of result or a damaged manifest, or
    /// when it is not empty and is not a kfmc result folder (those three unless `force`);
    /// and, forced or not, when it would replace a file kfmc did not write.
    pub fn open(dir: &Path, kind: StudyKind, force: bool) -> Result<Self, OutputError> {
        Self::open_with(dir, kind, force, &[])
    }

    /// [`StudyFolder::open`] for a study that reads `inputs` (its spec, estimates files):
    /// refused as well when one of them lies inside `dir`.
    pub fn open_with(
        dir: &Path,
        kind: StudyKind,
        force: bool,
        inputs: &[PathBuf],
    ) -> Result<Self, OutputError> {
        let folder = Self::lock(dir)?;
        folder.prepare_with(kind, force, inputs)?;
        Ok(folder)
    }

    /// Locks `dir` (creating it if needed) without looking at what it holds: for a writer that
    /// must read the folder (under the lock) before it knows its kind, which then calls
    /// [`StudyFolder::prepare`], and for one that adds files to a committed study
    /// ([`StudyFolder::claim_files`]).
    pub fn lock(dir: &Path) -> Result<Self, OutputError> {
        Ok(StudyFolder {
            dir: dir.to_path_buf(),
            lock: FolderLock::acquire(dir)?,
            accepted: Mutex::new(None),
        })
    }

    /// Checks that the held folder may receive a study of `kind` and accepts it; then removes
    /// the temporary files that killed writers left there.
    pub fn prepare(&self, kind: StudyKind, force: bool) -> Result<(), OutputError> {
        self.prepare_with(kind, force, &[])
    }

    /// [`StudyFolder::prepare`] of a study that reads `inputs`.
    pub fn prepare_with(
        &self,
        kind: StudyKind,
        force: bool,
        inputs: &[PathBuf],
    ) -> Result<(), OutputError> {
        let dir = &self.dir;
        let (listed, is_kfmc) = self.written_by_kfmc(kind, force)?;
        let orphans = self.lock.orphans().clone();
        let mut foreign = Vec::new();
        for entry in std::fs::read_dir(dir).map_err(io("cannot list", dir))? {
            let entry = entry.map_err(io("cannot list", dir))?;
            let name = entry.file_name().to_string_lossy().into_owned();
            let path = entry.path();
            let t = entry.file_type().map_err(io("cannot read", &path))?;
            if name == LOCK_FILE || name == MANIFEST {
                continue;
            }
            if temp_token(&name)
                .is_some_and(|tok| tok == process_token() || orphans.iter().any(|o| o == tok))
            {
                // This process's or a killed writer's temporary file.
                continue;
            }
            if name == CHECKPOINT_DIR {
                if !t.is_dir() {
                    return Err(OutputError::NotPlain {
                        path,
                        what: type_name(t),
                    });
                }
                continue;
            }
            if let Some(table) = table_of(&name) {
                check_listed_table(&path, t, &listed, table, is_kfmc)?;
                continue;
            }
            let listed_as = |kind: &str| -> Result<(), OutputError> {
                Err(OutputError::NotOurs {
                    path: path.clone(),
                    why: format!("is {} where kfmc wrote {kind}", type_name(t)),
                })
            };
            if listed.folders.contains(&name) {
                if !t.is_dir() {
                    listed_as("a folder")?;
                }
                continue;
            }
            if listed.files.contains(&name) {
                if !t.is_file() {
                    listed_as("a file")?;
                }
                continue;
            }
            if listed
                .files
                .iter()
                .any(|f| f.strip_prefix(&name).is_some_and(|r| r.starts_with('/')))
            {
                if !t.is_dir() {
                    listed_as("a folder of files")?;
                }
                continue;
            }
            if !written_beside_studies(&path, &name, t) {
                foreign.push(name);
            }
        }
        if !foreign.is_empty() && !is_kfmc && !force {
            foreign.sort();
            return Err(OutputError::Foreign {
                path: dir.to_path_buf(),
                example: foreign[0].clone(),
                count: foreign.len(),
            });
        }
        refuse_inputs(dir, inputs)?;
        *self.accepted.lock().unwrap_or_else(|e| e.into_inner()) = Some(Accepted { kind, listed });
        self.lock.clear_orphans(dir);
        Ok(())
    }

    /// What the folder's manifest says kfmc wrote there, and whether it has a manifest of
    /// kfmc's at all; refuses another kind, a damaged manifest (those two unless `force`) and
    /// a manifest kfmc did not write.
    fn written_by_kfmc(&self, kind: StudyKind, force: bool) -> Result<(Listed, bool), OutputError> {
        let dir = &self.dir;
        let path = dir.join(MANIFEST);
        let damaged = |why: String| OutputError::DamagedManifest {
            path: path.clone(),
            why,
        };
        match Manifest::inspect(dir)? {
            Found::Absent => Ok((Listed::default(), false)),
            Found::NotAFile(what) => Err(OutputError::NotPlain { path, what }),
            Found::Foreign(why) => Err(OutputError::ForeignManifest { path, why }),
            Found::Damaged { why, listed } => {
                if !force {
                    return Err(damaged(why));
                }
                Ok((still_matching(dir, sanitized(listed)), true))
            }
            Found::Kfmc(m) => {
                let legacy = m.format.is_none();
                if legacy && let Err(why) = check_tables(dir, &m.tables) {
                    if !force {
                        return Err(damaged(format!(
                            "it was written by an earlier kfmc, whose manifest is trusted only when every table it lists matches it, and {why}"
                        )));
                    }
                    return Ok((still_matching(dir, sanitized(Listed::of(&m))), true));
                }
                if m.kind() != kind && !force {
                    let tables: Vec<String> = m
                        .tables
                        .iter()
                        .map(|t| format!("{}.parquet", t.name))
                        .collect();
                    return Err(OutputError::OtherKind {
                        path: dir.to_path_buf(),
                        holds: m.kind().holds(),
                        experiment: m.experiment.clone(),
                        tables: if tables.is_empty() {
                            "no tables".into()
                        } else {
                            tables.join(", ")
                        },
                        command: kind.command(),
                    });
                }
                let mut listed = Listed::of(&m);
                if legacy && m.kind() == StudyKind::Tune {
                    listed.folders.extend(legacy_tune_stages(dir));
                }
                Ok((sanitized(listed), true))
            }
        }
    }

    /// Refuses `folders` (the sub-folders a study will write) where something kfmc did not
    /// write has the name: checked before the study runs, so that it is not refused only at
    /// its commit.
    pub fn refuse_unlisted(&self, folders: &[String]) -> Result<(), OutputError> {
        let accepted = self.accepted();
        for name in folders {
            self.target_free(&accepted, name, true)?;
        }
        Ok(())
    }

    fn accepted(&self) -> Accepted {
        self.accepted
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .clone()
            .expect("StudyFolder::prepare accepts the folder before anything is written into it")
    }

    /// Refuses a target of the commit where something other than kfmc's own entry is.
    fn target_free(
        &self,
        accepted: &Accepted,
        name: &str,
        folder: bool,
    ) -> Result<(), OutputError> {
        let path = self.dir.join(name);
        let meta = match std::fs::symlink_metadata(&path) {
            Ok(m) => m,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(()),
            Err(e) => return Err(io("cannot read", &path)(e)),
        };
        let t = meta.file_type();
        let ours = if folder {
            t.is_dir() && accepted.listed.folders.iter().any(|f| f == name)
        } else {
            t.is_file()
                && table_of(name)
                    .is_some_and(|table| accepted.listed.tables.iter().any(|e| e.name == table))
        };
        if ours {
            Ok(())
        } else {
            Err(OutputError::NotOurs {
                path,
                why: format!(
                    "is {} that manifest.toml does not list, where this study writes its {}",
                    type_name(t),
                    if folder { "folder" } else { "table" }
                ),
            })
        }
    }

    /// The folder.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Commits a study: replaces the old manifest by one in the middle of the commit, removes
    /// what the earlier study listed that this one does not write, moves `tables` into place,
    /// and writes `manifest` (with the tables' checksums filled in) last.
    pub fn commit(
        &self,
        tables: Vec<FinishedTable>,
        manifest: Manifest,
    ) -> Result<Vec<(String, u64)>, OutputError> {
        self.commit_with_folders(tables, Vec::new(), manifest)
    }

    /// [`StudyFolder::commit`] of a study that also has sub-folders: the earlier study's
    /// listed sub-folders go, and `folders` are moved into place, so the sub-folders change
    /// with the study, never apart from it.
    pub fn commit_with_folders(
        &self,
        tables: Vec<FinishedTable>,
        folders: Vec<FinishedFolder>,
        mut manifest: Manifest,
    ) -> Result<Vec<(String, u64)>, OutputError> {
        let dir = &self.dir;
        let accepted = self.accepted();
        for t in &tables {
            self.target_free(&accepted, &format!("{}.parquet", t.name), false)?;
        }
        for f in &folders {
            self.target_free(&accepted, &f.name, true)?;
        }
        let mut entries = Vec::with_capacity(tables.len());
        for t in &tables {
            let (bytes, checksum) = checksum_file(&t.tmp)?;
            // The manifest written last vouches for these bytes: they must be on disk before it,
            // or a power loss could leave a listed table empty under its real name.
            sync_file(&t.tmp).map_err(io("cannot sync", &t.tmp))?;
            entries.push(TableEntry {
                name: t.name.clone(),
                rows: t.rows,
                bytes,
                checksum,
            });
        }
        entries.sort_by_key(|e| schema::TABLES.iter().position(|t| *t == e.name));
        // What the study does not rewrite and keeps: the description of its spec.
        let mut kept: Vec<String> = Vec::new();
        for f in &accepted.listed.files {
            if f == "describe.toml" && !kept.contains(f) {
                kept.push(f.clone());
            }
        }
        manifest.format = Some(FORMAT.into());
        manifest.kind.get_or_insert(accepted.kind);
        manifest.tables = entries;
        manifest.folders = folders.iter().map(|f| f.name.clone()).collect();
        manifest.files = kept.clone();
        manifest.replacing = None;
        // From here until the final manifest, readers refuse the folder and the next writer
        // knows both studies' entries as kfmc's.
        let mut pending = manifest.clone();
        pending.replacing = Some(accepted.listed.clone());
        pending.write(dir)?;
        for e in &accepted.listed.tables {
            if !tables.iter().any(|t| t.name == e.name) {
                remove_listed_file(dir, &format!("{}.parquet", e.name))?;
            }
        }
        for f in &accepted.listed.files {
            if !kept.contains(f) {
                remove_listed_file(dir, f)?;
            }
        }
        for name in &accepted.listed.folders {
            let path = dir.join(name);
            match std::fs::symlink_metadata(&path) {
                Ok(m) if m.file_type().is_dir() => std::fs::remove_dir_all(&path)
                    .map_err(io("cannot remove the earlier study's", &path))?,
                Ok(m) => {
                    return Err(OutputError::NotOurs {
                        path,
                        why: format!("is {} where kfmc wrote a folder", type_name(m.file_type())),
                    });
                }
                Err(_) => {}
            }
        }
        for f in &folders {
            let path = dir.join(&f.name);
            std::fs::rename(&f.tmp, &path)
                .map_err(io("cannot move the finished folder to", &path))?;
        }
        for t in &tables {
            let path = dir.join(format!("{}.parquet", t.name));
            std::fs::rename(&t.tmp, &path)
                .map_err(io("cannot move the finished table to", &path))?;
        }
        manifest.write(dir)?;
        Ok(manifest
            .tables
            .iter()
            .map(|t| (t.name.clone(), t.rows))
            .collect())
    }

    /// Lists `files` (paths relative to the folder, with `/`) in the manifest of the committed
    /// study this writer holds, before it writes them (figures, the report, `describe.toml`):
    /// each must be absent, already listed, or one `ours` says kfmc wrote; none may be
    /// reached through a symbolic link. A kill after this leaves them listed and absent or
    /// whole (they are written atomically), never present and unlisted.
    pub fn claim_files(
        &self,
        files: &[String],
        ours: &dyn Fn(&Path) -> bool,
    ) -> Result<(), OutputError> {
        let dir = &self.dir;
        let path = dir.join(MANIFEST);
        let mut m = match Manifest::inspect(dir)? {
            Found::Kfmc(m) if m.replacing.is_none() => *m,
            _ => {
                return Err(OutputError::NotAStudy {
                    path: dir.to_path_buf(),
                    why: "it holds no complete kfmc manifest to list the file in".into(),
                });
            }
        };
        if m.format.is_none() {
            check_tables(dir, &m.tables).map_err(|why| OutputError::DamagedManifest {
                path: path.clone(),
                why,
            })?;
        }
        for rel in files {
            let target = dir.join(rel);
            if !is_inside_path(rel) {
                return Err(OutputError::NotOurs {
                    path: target,
                    why: "is not a path inside the result folder".into(),
                });
            }
            if let Some(what) = reserved(rel, &m.folders) {
                return Err(OutputError::NotOurs {
                    path: target,
                    why: format!("is {what}, not a file kfmc adds to a study"),
                });
            }
            match lstat_under(dir, rel)? {
                None => {}
                Some(meta)
                    if meta.file_type().is_file() && (m.files.contains(rel) || ours(&target)) => {}
                Some(meta) if meta.file_type().is_file() => {
                    return Err(OutputError::NotOurs {
                        path: target,
                        why: "was not written by kfmc (manifest.toml does not list it) and would be replaced".into(),
                    });
                }
                Some(meta) => {
                    return Err(OutputError::NotPlain {
                        path: target,
                        what: type_name(meta.file_type()),
                    });
                }
            }
        }
        let listed = m.files.len();
        for rel in files {
            if !m.files.contains(rel) {
                m.files.push(rel.clone());
            }
        }
        if m.files.len() != listed || m.format.is_none() {
            m.format = Some(FORMAT.into());
            m.write(dir)?;
        }
        self.lock.clear_orphans(dir);
        Ok(())
    }
}

/// Writes `bytes` to `target` (a `describe.toml`, a report given `--out`) under the lock of
/// its folder: listed in the folder's manifest when the folder is a kfmc result folder, and
/// refused wherever it would replace a file that kfmc did not write (one the manifest does
/// not list and `ours` does not recognise).
pub fn write_file(
    target: &Path,
    bytes: &[u8],
    ours: &dyn Fn(&Path) -> bool,
) -> Result<(), OutputError> {
    let parent = target
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    let name = target
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .ok_or_else(|| OutputError::NotOurs {
            path: target.to_path_buf(),
            why: "is not a file name".into(),
        })?;
    let held = StudyFolder::lock(parent)?;
    match Manifest::inspect(parent)? {
        Found::Kfmc(m) if m.replacing.is_none() => held.claim_files(&[name], ours)?,
        _ => {
            if name == MANIFEST || name == LOCK_FILE {
                return Err(OutputError::NotOurs {
                    path: target.to_path_buf(),
                    why: "is a name kfmc keeps for its result folders".into(),
                });
            }
            match std::fs::symlink_metadata(target) {
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
                Err(e) => return Err(io("cannot read", target)(e)),
                Ok(m) if m.file_type().is_file() && ours(target) => {}
                Ok(m) if m.file_type().is_file() => {
                    return Err(OutputError::NotOurs {
                        path: target.to_path_buf(),
                        why: "was not written by kfmc and would be replaced".into(),
                    });
                }
                Ok(m) => {
                    return Err(OutputError::NotPlain {
                        path: target.to_path_buf(),
                        what: type_name(m.file_type()),
                    });
                }
            }
            held.lock.clear_orphans(parent);
        }
    }
    write_atomic(target, bytes).map_err(io("cannot write", target))
}

impl Drop for FinishedTable {
    fn drop(&mut self) {
        // Moved into place by a commit, this finds nothing; otherwise the study failed or was
        // interrupted, and the file must not outlive it.
        let _ = std::fs::remove_file(&self.tmp);
    }
}
