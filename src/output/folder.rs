//! One study per folder, committed once.
//!
//! A writer holds an exclusive lock on its output folder for its whole life
//! ([`StudyFolder::open`], [`FolderLock`]): an advisory `flock` on `.kfmc.lock` that the
//! operating system releases when the process ends, however it ends, so a second writer is
//! refused while the first lives and nothing has to guess whether a lock is stale. The lock is
//! taken before anything in the folder is read or touched. A writer replaces only a folder of
//! its own kind ([`StudyKind`]) unless forced.
//!
//! Tables are written under temporary names; [`StudyFolder::commit`] then invalidates the old
//! manifest, moves every table into place, removes tables of an earlier study that this one
//! did not write, and writes the new manifest **last**, listing every table with its size, row
//! count and checksum. The manifest is the commit record: a reader ([`verify`]) accepts a
//! folder only when every table it lists is there and matches. A kill at any moment therefore
//! leaves either the old study (killed before the commit), the new one (after it), or — for
//! the few renames in between — a folder without a manifest, which every reader refuses;
//! never a mix that looks complete.

use std::io::{Read, Write};
use std::os::unix::fs::MetadataExt;
use std::path::{Path, PathBuf};

pub use super::atomic::{sync_file, temp_beside, write_atomic};
use super::manifest::{Manifest, StudyKind};
use super::schema;
pub use super::table::FinishedTable;
use crate::error::OutputError;

/// The lock file's name inside an output folder.
pub const LOCK_FILE: &str = ".kfmc.lock";

/// An exclusive, operating-system-held lock on a folder, released when dropped or when the
/// process dies.
#[derive(Debug)]
pub struct FolderLock {
    path: PathBuf,
    // Holds the `flock`; closing it (on drop, or by the kernel at exit) releases it.
    _file: std::fs::File,
    // A writer holding a folder stops cleanly on a signal (its partial files removed).
    _stop: crate::runner::StopSection,
}

/// An output folder held exclusively by this process until dropped.
#[derive(Debug)]
pub struct StudyFolder {
    dir: PathBuf,
    // Held, not read: dropping it releases the folder.
    _lock: FolderLock,
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

/// The names a study may leave in its folder besides its tables.
fn is_kfmc_file(name: &str) -> bool {
    name == "manifest.toml"
        || name == LOCK_FILE
        || name == "figures"
        || name == "report.html"
        || name == "describe.toml"
        || name.starts_with("tune_")
        || name == "parts"
        || name == super::checkpoint::CHECKPOINT_DIR
        || name == "slurm"
        || name == "score"
        || name == "power"
        || name == ".power-replication"
        || name == "tuning.parquet"
        || (name.starts_with('.') && name.ends_with(".partial"))
        || schema::TABLES
            .iter()
            .any(|t| name == format!("{t}.parquet"))
}

/// This machine's name, as the kernel knows it.
fn host_name() -> String {
    ["/proc/sys/kernel/hostname", "/etc/hostname"]
        .iter()
        .find_map(|p| {
            std::fs::read_to_string(p)
                .ok()
                .map(|s| s.trim().to_string())
                .filter(|s| !s.is_empty())
        })
        .unwrap_or_else(|| "an unknown host".into())
}

/// `YYYY-MM-DD HH:MM:SS UTC` of a Unix time (the civil-from-days algorithm of H. Hinnant).
fn utc(unix_s: u64) -> String {
    let (days, rem) = ((unix_s / 86_400) as i64, unix_s % 86_400);
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1_460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let m = if mp < 10 { mp + 3 } else { mp - 9 };
    let y = yoe + era * 400 + i64::from(m <= 2);
    format!(
        "{y:04}-{m:02}-{d:02} {:02}:{:02}:{:02} UTC",
        rem / 3_600,
        rem / 60 % 60,
        rem % 60
    )
}

/// The holder a lock file names, for the refusal message.
fn describe_holder(text: &str) -> String {
    let field = |key: &str| {
        text.lines().find_map(|l| {
            let (k, v) = l.split_once('=')?;
            (k.trim() == key).then(|| v.trim().trim_matches('"').to_string())
        })
    };
    match (field("pid"), field("host"), field("started_unix_s")) {
        (Some(pid), Some(host), Some(t)) => {
            let since = t.parse::<u64>().map_or(t.clone(), utc);
            format!("pid {pid} on host {host}, since {since}")
        }
        // The holder locks first and writes its name after: caught in between.
        _ => "a process that has just taken the lock".into(),
    }
}

impl FolderLock {
    /// Creates (if needed) `dir` and takes its lock, or refuses naming the holder. Never
    /// waits.
    pub fn acquire(dir: &Path) -> Result<Self, OutputError> {
        std::fs::create_dir_all(dir).map_err(io("cannot create the output folder", dir))?;
        let path = dir.join(LOCK_FILE);
        loop {
            let mut file = std::fs::OpenOptions::new()
                .read(true)
                .write(true)
                .create(true)
                .truncate(false)
                .open(&path)
                .map_err(io("cannot open the lock file", &path))?;
            match file.try_lock() {
                Ok(()) => {}
                Err(std::fs::TryLockError::WouldBlock) => {
                    let mut text = String::new();
                    let _ = file.read_to_string(&mut text);
                    return Err(OutputError::Locked {
                        path: dir.to_path_buf(),
                        holder: describe_holder(&text),
                    });
                }
                Err(std::fs::TryLockError::Error(e)) => {
                    return Err(io("cannot lock the output folder with", &path)(e));
                }
            }
            // A holder unlinks the lock file before it lets go of it. A file opened just
            // before that unlink is locked once the holder is gone, but it is no longer the
            // folder's lock file (another writer may hold a new one): only a lock on the file
            // still at the path counts.
            let same = match (std::fs::metadata(&path), file.metadata()) {
                (Ok(a), Ok(b)) => a.dev() == b.dev() && a.ino() == b.ino(),
                _ => false,
            };
            if !same {
                continue;
            }
            // Who holds it, for the message of the writers it refuses; not part of the lock.
            let started = std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0, |d| d.as_secs());
            let text = format!(
                "host = \"{}\"\npid = {}\nstarted_unix_s = {started}\n",
                host_name(),
                std::process::id()
            );
            let _ = file
                .set_len(0)
                .and_then(|()| file.write_all(text.as_bytes()));
            return Ok(FolderLock {
                path,
                _file: file,
                _stop: crate::runner::StopSection::open(),
            });
        }
    }
}

impl Drop for FolderLock {
    fn drop(&mut self) {
        // Unlinked while still held (the file closes after this body), so a writer that
        // opened it in the meantime sees it is no longer the lock file and opens a new one.
        let _ = std::fs::remove_file(&self.path);
    }
}

impl StudyFolder {
    /// Locks `dir` (creating it if needed) and readies it for a study of `kind`: refused when
    /// another kfmc holds it, when it holds another kind of result, or when it is not empty
    /// and is not a kfmc study (the last two unless `force`).
    pub fn open(dir: &Path, kind: StudyKind, force: bool) -> Result<Self, OutputError> {
        let folder = Self::lock(dir)?;
        folder.prepare(kind, force)?;
        Ok(folder)
    }

    /// Locks `dir` (creating it if needed) without looking at what it holds: for a writer that
    /// must read the folder (under the lock) before it knows its kind; it then calls
    /// [`StudyFolder::prepare`].
    pub fn lock(dir: &Path) -> Result<Self, OutputError> {
        Ok(StudyFolder {
            dir: dir.to_path_buf(),
            _lock: FolderLock::acquire(dir)?,
        })
    }

    /// Checks that the held folder may receive a study of `kind` and removes what killed
    /// writers left (`.<name>.partial`).
    pub fn prepare(&self, kind: StudyKind, force: bool) -> Result<(), OutputError> {
        let dir = &self.dir;
        let mut foreign = Vec::new();
        for entry in std::fs::read_dir(dir).map_err(io("cannot list", dir))? {
            let entry = entry.map_err(io("cannot list", dir))?;
            let name = entry.file_name().to_string_lossy().into_owned();
            if name.starts_with('.') && name.ends_with(".partial") {
                // Left by a writer that was killed; we hold the lock, so it is an orphan.
                if entry.file_type().is_ok_and(|t| t.is_dir()) {
                    let _ = std::fs::remove_dir_all(entry.path());
                } else {
                    let _ = std::fs::remove_file(entry.path());
                }
            } else if !is_kfmc_file(&name) {
                foreign.push(name);
            }
        }
        let manifest_path = dir.join("manifest.toml");
        let is_study = manifest_path.exists();
        if is_study
            && !force
            && let Ok(old) = Manifest::read(dir)
            && old.kind() != kind
        {
            let tables: Vec<String> = old
                .tables
                .iter()
                .map(|t| format!("{}.parquet", t.name))
                .collect();
            return Err(OutputError::OtherKind {
                path: dir.to_path_buf(),
                holds: old.kind().holds(),
                experiment: old.experiment.clone(),
                tables: if tables.is_empty() {
                    "no tables".into()
                } else {
                    tables.join(", ")
                },
                command: kind.command(),
            });
        }
        if !foreign.is_empty() && !is_study && !force {
            foreign.sort();
            return Err(OutputError::Foreign {
                path: dir.to_path_buf(),
                example: foreign[0].clone(),
                count: foreign.len(),
            });
        }
        Ok(())
    }

    /// The folder.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Commits a study: invalidates the old manifest, moves `tables` into place, removes
    /// tables of an earlier study that are not among them, and writes `manifest` (with the
    /// tables' checksums filled in) last.
    pub fn commit(
        &self,
        tables: Vec<FinishedTable>,
        manifest: Manifest,
    ) -> Result<Vec<(String, u64)>, OutputError> {
        self.commit_with_folders(tables, Vec::new(), |_| false, manifest)
    }

    /// [`StudyFolder::commit`] of a study that also has sub-folders: once the old manifest is
    /// invalidated, every entry for which `replaced` holds (the earlier study's sub-folders)
    /// is removed and `folders` are moved into place, so the sub-folders change with the
    /// study, never apart from it.
    pub fn commit_with_folders(
        &self,
        tables: Vec<FinishedTable>,
        folders: Vec<FinishedFolder>,
        replaced: impl Fn(&str) -> bool,
        mut manifest: Manifest,
    ) -> Result<Vec<(String, u64)>, OutputError> {
        let manifest_path = self.dir.join("manifest.toml");
        if manifest_path.exists() {
            std::fs::remove_file(&manifest_path)
                .map_err(io("cannot invalidate the old manifest", &manifest_path))?;
        }
        for entry in std::fs::read_dir(&self.dir).map_err(io("cannot list", &self.dir))? {
            let entry = entry.map_err(io("cannot list", &self.dir))?;
            let name = entry.file_name().to_string_lossy().into_owned();
            if replaced(&name) && entry.file_type().is_ok_and(|t| t.is_dir()) {
                std::fs::remove_dir_all(entry.path())
                    .map_err(io("cannot remove the earlier study's", &entry.path()))?;
            }
        }
        for f in &folders {
            let path = self.dir.join(&f.name);
            std::fs::rename(&f.tmp, &path)
                .map_err(io("cannot move the finished folder to", &path))?;
        }
        let mut entries = Vec::with_capacity(tables.len());
        for t in &tables {
            let path = self.dir.join(format!("{}.parquet", t.name));
            let (bytes, checksum) = checksum_file(&t.tmp)?;
            // The manifest written last vouches for these bytes: they must be on disk before it,
            // or a power loss could leave a listed table empty under its real name.
            sync_file(&t.tmp).map_err(io("cannot sync", &t.tmp))?;
            std::fs::rename(&t.tmp, &path)
                .map_err(io("cannot move the finished table to", &path))?;
            entries.push(super::manifest::TableEntry {
                name: t.name.clone(),
                rows: t.rows,
                bytes,
                checksum,
            });
        }
        for t in schema::TABLES {
            if !tables.iter().any(|w| w.name == t) {
                let stale = self.dir.join(format!("{t}.parquet"));
                if stale.exists() {
                    std::fs::remove_file(&stale)
                        .map_err(io("cannot remove the stale table", &stale))?;
                }
            }
        }
        entries.sort_by_key(|e| schema::TABLES.iter().position(|t| *t == e.name));
        manifest.tables = entries;
        manifest.write(&self.dir)?;
        Ok(manifest
            .tables
            .iter()
            .map(|t| (t.name.clone(), t.rows))
            .collect())
    }
}

impl Drop for FinishedTable {
    fn drop(&mut self) {
        // Moved into place by a commit, this finds nothing; otherwise the study failed or was
        // interrupted, and the file must not outlive it.
        let _ = std::fs::remove_file(&self.tmp);
    }
}

/// FNV-1a 64 of a file's bytes, and its size.
pub fn checksum_file(path: &Path) -> Result<(u64, String), OutputError> {
    let mut f = super::atomic::open_input(path).map_err(io("cannot open", path))?;
    let mut buf = vec![0u8; 1 << 16];
    let mut h = crate::hash::Fnv1a::new();
    let mut n = 0u64;
    loop {
        let k = f.read(&mut buf).map_err(io("cannot read", path))?;
        if k == 0 {
            break;
        }
        n += k as u64;
        h.write(&buf[..k]);
    }
    Ok((n, format!("{:016x}", h.finish())))
}

/// Reads the manifest of a result folder and checks that every table it lists is there with
/// the recorded size and checksum, and that no table it does not list is present. Readers
/// (`summary`, `plot`, `report`, `check`, `tune`) call this before trusting a folder.
pub fn verify(dir: &Path) -> Result<Manifest, OutputError> {
    if !dir.is_dir() {
        return Err(OutputError::NotAStudy {
            path: dir.to_path_buf(),
            why: "no such folder".into(),
        });
    }
    let manifest = Manifest::read(dir).map_err(|e| match e {
        OutputError::Io { source, .. } if source.kind() == std::io::ErrorKind::NotFound => {
            OutputError::NotAStudy {
                path: dir.to_path_buf(),
                why: "it has no manifest.toml (not a kfmc result folder, or a run that did not finish)".into(),
            }
        }
        other => other,
    })?;
    for t in &manifest.tables {
        let path = dir.join(format!("{}.parquet", t.name));
        if !path.exists() {
            return Err(OutputError::Mismatch {
                path,
                why: "listed in manifest.toml but missing".into(),
            });
        }
        let (bytes, checksum) = checksum_file(&path)?;
        if bytes != t.bytes || checksum != t.checksum {
            return Err(OutputError::Mismatch {
                path,
                why: format!(
                    "does not match manifest.toml ({bytes} bytes, checksum {checksum}; recorded {} bytes, {})",
                    t.bytes, t.checksum
                ),
            });
        }
    }
    for t in schema::TABLES {
        let path = dir.join(format!("{t}.parquet"));
        if path.exists() && !manifest.tables.iter().any(|e| e.name == t) {
            return Err(OutputError::Mismatch {
                path,
                why: "present but not listed in manifest.toml (left by another study)".into(),
            });
        }
    }
    Ok(manifest)
}
