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

use std::io::Read;
use std::os::unix::fs::{FileExt, MetadataExt};
use std::path::{Component, Path, PathBuf};
use std::sync::Mutex;

use super::atomic::{process_token, temp_token, type_name};
pub use super::atomic::{sync_file, temp_beside, write_atomic};
use super::checkpoint::CHECKPOINT_DIR;
use super::manifest::{FORMAT, Found, Listed, Manifest, StudyKind, TableEntry};
use super::schema;
pub use super::table::FinishedTable;
use crate::error::OutputError;

/// The lock file's name inside an output folder.
pub const LOCK_FILE: &str = ".kfmc.lock";

/// The manifest's name inside a result folder.
const MANIFEST: &str = "manifest.toml";

/// The first line of every `describe.toml` kfmc writes: what tells it from a user's file of
/// that name, in a folder whose manifest does not list it.
pub const DESCRIBE_FORMAT_LINE: &str = "format = \"kfmc-describe/1\"";

/// The line that ends a lock file's record: a record cut short by a kill is followed by the
/// tail of the one before it, which readers ignore.
const RECORD_END: &str = "# end";

/// An exclusive, operating-system-held lock on a folder, released when dropped or when the
/// process dies.
#[derive(Debug)]
pub struct FolderLock {
    path: PathBuf,
    // Holds the `flock`; closing it (on drop, or by the kernel at exit) releases it.
    file: std::fs::File,
    /// The tokens of killed writers whose temporary files may still be in the folder, as the
    /// lock file named them when this writer took it; emptied once those files are removed.
    orphans: Mutex<Vec<String>>,
    /// When this writer took the lock (Unix seconds), for its record.
    started_unix_s: u64,
    // A writer holding a folder stops cleanly on a signal (its partial files removed).
    _stop: crate::runner::StopSection,
}

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

/// The table a file name is the file of (`runs` for `runs.parquet`).
fn table_of(name: &str) -> Option<&'static str> {
    let stem = name.strip_suffix(".parquet")?;
    schema::TABLES.iter().copied().find(|t| *t == stem)
}

/// Whether `rel` is a plain relative path inside a folder (`figures/rmse.png`): no root, no
/// `..`, no `.`, no empty component.
fn is_inside_path(rel: &str) -> bool {
    !rel.is_empty()
        && !rel.starts_with('/')
        && rel
            .split('/')
            .all(|c| !c.is_empty() && c != "." && c != "..")
}

/// What a manifest lists, keeping only entries that can name something inside the folder: a
/// listed path with `..` or a root is not kfmc's, whatever the file says.
fn sanitized(mut l: Listed) -> Listed {
    l.tables
        .retain(|t| table_of(&format!("{}.parquet", t.name)).is_some());
    l.files.retain(|f| is_inside_path(f));
    l.folders.retain(|f| is_inside_path(f) && !f.contains('/'));
    l
}

/// The metadata of `dir/rel`, not following a symbolic link at any component below `dir`:
/// `None` when it (or a folder on the way) is absent; refused when a component on the way is
/// not a folder of its own.
fn lstat_under(dir: &Path, rel: &str) -> Result<Option<std::fs::Metadata>, OutputError> {
    let mut path = dir.to_path_buf();
    let parts: Vec<&str> = rel.split('/').collect();
    for (i, c) in parts.iter().enumerate() {
        path.push(c);
        let meta = match std::fs::symlink_metadata(&path) {
            Ok(m) => m,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(io("cannot read", &path)(e)),
        };
        if i + 1 == parts.len() {
            return Ok(Some(meta));
        }
        if !meta.file_type().is_dir() {
            return Err(OutputError::NotPlain {
                path,
                what: type_name(meta.file_type()),
            });
        }
    }
    Ok(None)
}

/// Whether `rel`, a path kfmc would write inside a result folder, is a name the folder keeps
/// for something else (its manifest, lock or checkpoint, a table, a whole sub-folder).
fn reserved(rel: &str, listed_folders: &[String]) -> Option<&'static str> {
    let top = rel.split('/').next().unwrap_or(rel);
    if top == MANIFEST {
        Some("the folder's manifest")
    } else if top == LOCK_FILE || top == CHECKPOINT_DIR {
        Some("kept for kfmc's lock and checkpoint")
    } else if rel == top && table_of(top).is_some() {
        Some("the name of a kfmc table")
    } else if listed_folders.iter().any(|f| f == top) {
        Some("inside a sub-folder of the study")
    } else {
        None
    }
}

/// Whether the `describe.toml` at `path` is one kfmc wrote (it starts with
/// [`DESCRIBE_FORMAT_LINE`]).
pub fn is_kfmc_describe(path: &Path) -> bool {
    let mut head = Vec::new();
    super::atomic::open_regular(path)
        .and_then(|f| {
            f.take(DESCRIBE_FORMAT_LINE.len() as u64)
                .read_to_end(&mut head)
        })
        .is_ok()
        && head == DESCRIBE_FORMAT_LINE.as_bytes()
}

/// An entry that kfmc writes outside any study's manifest and that therefore does not make a
/// folder count as someone else's: the parts of a sharded study and the Slurm scripts
/// (folders of those names), a `describe.toml` kfmc wrote, and a result folder of its own
/// nested inside (`score/`, `power/`). None of them is ever replaced or removed by a study.
fn written_beside_studies(path: &Path, name: &str, t: std::fs::FileType) -> bool {
    match name {
        "parts" | "slurm" if t.is_dir() => true,
        "describe.toml" if t.is_file() => is_kfmc_describe(path),
        _ if t.is_dir() => matches!(Manifest::inspect(path), Ok(Found::Kfmc(_))),
        _ => false,
    }
}

/// Checks that every table `tables` lists is a regular file with its recorded size and
/// checksum: the condition on which a manifest from an earlier kfmc is trusted. Says which
/// one does not.
fn check_tables(dir: &Path, tables: &[TableEntry]) -> Result<(), String> {
    for t in tables {
        let path = dir.join(format!("{}.parquet", t.name));
        match std::fs::symlink_metadata(&path) {
            Ok(m) if m.file_type().is_file() => {}
            Ok(m) => {
                return Err(format!(
                    "{} is {}",
                    path.display(),
                    type_name(m.file_type())
                ));
            }
            Err(_) => return Err(format!("{} is missing", path.display())),
        }
        let (bytes, checksum) = checksum_file(&path).map_err(|e| e.to_string())?;
        if bytes != t.bytes || checksum != t.checksum {
            return Err(format!(
                "{} does not match it ({bytes} bytes, checksum {checksum}; it records {} bytes, {})",
                path.display(),
                t.bytes,
                t.checksum
            ));
        }
    }
    Ok(())
}

/// The sub-folders a tuning search of an earlier kfmc wrote (whose manifest did not list
/// them): its `tune_*` folders that are kfmc result folders themselves.
fn legacy_tune_stages(dir: &Path) -> Vec<String> {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return Vec::new();
    };
    entries
        .flatten()
        .filter(|e| e.file_type().is_ok_and(|t| t.is_dir()))
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| {
            n.starts_with("tune_") && matches!(Manifest::inspect(&dir.join(n)), Ok(Found::Kfmc(_)))
        })
        .collect()
}

/// The relative path of `path` inside `dir` (`figures` for `dir/figures`, empty for `dir`
/// itself), following symbolic links on both sides as far as they exist; `None` when it
/// lies outside.
pub fn relative_inside(dir: &Path, path: &Path) -> Option<String> {
    let root = std::fs::canonicalize(dir).ok()?;
    let absolute = std::path::absolute(path).ok()?;
    // The deepest ancestor that exists, canonical, and the rest below it as written.
    let mut existing = absolute.as_path();
    let mut rest = Vec::new();
    let base = loop {
        if let Ok(c) = std::fs::canonicalize(existing) {
            break c;
        }
        rest.push(existing.file_name()?.to_os_string());
        existing = existing.parent()?;
    };
    let mut full = base;
    for c in rest.iter().rev() {
        full.push(c);
    }
    let rel = full.strip_prefix(&root).ok()?;
    let parts: Vec<String> = rel
        .components()
        .map(|c| match c {
            Component::Normal(s) => Some(s.to_string_lossy().into_owned()),
            _ => None,
        })
        .collect::<Option<_>>()?;
    Some(parts.join("/"))
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

/// The tokens of killed writers a lock file's record names: its writer's and the orphans it
/// carried.
fn orphan_tokens(record: &str) -> Vec<String> {
    let mut out: Vec<String> = Vec::new();
    for line in record.lines() {
        if line.trim() == RECORD_END {
            break;
        }
        let Some((key, value)) = line.split_once('=') else {
            continue;
        };
        let tokens: Vec<&str> = match key.trim() {
            "token" => vec![value],
            "orphans" => value
                .trim()
                .trim_start_matches('[')
                .trim_end_matches(']')
                .split(',')
                .collect(),
            _ => continue,
        };
        for t in tokens {
            let t = t.trim().trim_matches('"');
            if super::atomic::is_token(t) && t != process_token() && !out.iter().any(|o| o == t) {
                out.push(t.to_string());
            }
        }
    }
    out
}

impl FolderLock {
    /// Creates (if needed) `dir` and takes its lock, or refuses naming the holder. Never
    /// waits, and refuses a `.kfmc.lock` that is not a regular file (a symbolic link, a FIFO).
    pub fn acquire(dir: &Path) -> Result<Self, OutputError> {
        std::fs::create_dir_all(dir).map_err(io("cannot create the output folder", dir))?;
        let path = dir.join(LOCK_FILE);
        loop {
            if let Ok(m) = std::fs::symlink_metadata(&path)
                && !m.file_type().is_file()
            {
                return Err(OutputError::NotPlain {
                    path,
                    what: type_name(m.file_type()),
                });
            }
            let mut file = super::atomic::open_regular_rw(&path, true)
                .map_err(io("cannot open the lock file", &path))?;
            match file.try_lock() {
                Ok(()) => {}
                Err(std::fs::TryLockError::WouldBlock) => {
                    let mut text = Vec::new();
                    let _ = file.read_to_end(&mut text);
                    return Err(OutputError::Locked {
                        path: dir.to_path_buf(),
                        holder: describe_holder(&String::from_utf8_lossy(&text)),
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
            let same = match (std::fs::symlink_metadata(&path), file.metadata()) {
                (Ok(a), Ok(b)) => a.dev() == b.dev() && a.ino() == b.ino(),
                _ => false,
            };
            if !same {
                continue;
            }
            // What the last holder recorded: a killed writer's token names its temporary files.
            let mut old = Vec::new();
            let _ = file.read_to_end(&mut old);
            let lock = FolderLock {
                path,
                file,
                orphans: Mutex::new(orphan_tokens(&String::from_utf8_lossy(&old))),
                started_unix_s: std::time::SystemTime::now()
                    .duration_since(std::time::UNIX_EPOCH)
                    .map_or(0, |d| d.as_secs()),
                _stop: crate::runner::StopSection::open(),
            };
            lock.write_record();
            return Ok(lock);
        }
    }

    fn orphans(&self) -> std::sync::MutexGuard<'_, Vec<String>> {
        self.orphans.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Writes who holds the lock (for the message of the writers it refuses; not part of the
    /// lock), the token of this process's temporary files, and the killed writers' tokens not
    /// yet cleared.
    fn write_record(&self) {
        let orphans = self
            .orphans()
            .iter()
            .map(|t| format!("\"{t}\""))
            .collect::<Vec<_>>()
            .join(", ");
        let text = format!(
            "host = \"{}\"\npid = {}\nstarted_unix_s = {}\ntoken = \"{}\"\norphans = [{orphans}]\n{RECORD_END}\n",
            host_name(),
            std::process::id(),
            self.started_unix_s,
            process_token()
        );
        // Written over the old record and then cut to length, never emptied first: a kill in
        // between leaves this record, its end line, and the old one's tail.
        let _ = self
            .file
            .write_all_at(text.as_bytes(), 0)
            .and_then(|()| self.file.set_len(text.len() as u64));
    }

    /// Removes the temporary files and folders that killed writers left in `dir` and in its
    /// sub-folders (named with a token the lock file recorded), and no other entry.
    fn clear_orphans(&self, dir: &Path) {
        let mut orphans = self.orphans();
        if orphans.is_empty() {
            return;
        }
        let mut folders = vec![dir.to_path_buf()];
        if let Ok(entries) = std::fs::read_dir(dir) {
            folders.extend(
                entries
                    .flatten()
                    .filter(|e| e.file_type().is_ok_and(|t| t.is_dir()))
                    .map(|e| e.path()),
            );
        }
        for folder in folders {
            let Ok(entries) = std::fs::read_dir(&folder) else {
                continue;
            };
            for e in entries.flatten() {
                let name = e.file_name().to_string_lossy().into_owned();
                if !temp_token(&name).is_some_and(|t| orphans.iter().any(|o| o == t)) {
                    continue;
                }
                let _ = if e.file_type().is_ok_and(|t| t.is_dir()) {
                    std::fs::remove_dir_all(e.path())
                } else {
                    std::fs::remove_file(e.path())
                };
            }
        }
        orphans.clear();
        drop(orphans);
        self.write_record();
    }
}

impl Drop for FolderLock {
    fn drop(&mut self) {
        // Unlinked while still held (the file closes after this body), so a writer that
        // opened it in the meantime sees it is no longer the lock file and opens a new one.
        // A lock file that still names killed writers' temporary files stays, for the next
        // writer that accepts the folder to remove them.
        if self.orphans().is_empty() {
            let _ = std::fs::remove_file(&self.path);
        }
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

/// Refuses `path` when it is a symbolic link (or anything but a folder): a folder inside a
/// result folder that a writer goes into (`parts`). Nothing there is fine.
pub fn refuse_link(path: &Path) -> Result<(), OutputError> {
    match std::fs::symlink_metadata(path) {
        Ok(m) if !m.file_type().is_dir() => Err(OutputError::NotPlain {
            path: path.to_path_buf(),
            what: type_name(m.file_type()),
        }),
        _ => Ok(()),
    }
}

/// Refuses the first of `inputs` that lies inside `dir`.
fn refuse_inputs(dir: &Path, inputs: &[PathBuf]) -> Result<(), OutputError> {
    let Ok(root) = std::fs::canonicalize(dir) else {
        return Ok(());
    };
    for input in inputs {
        if let Ok(p) = std::fs::canonicalize(input)
            && p.starts_with(&root)
        {
            return Err(OutputError::InputInOutput {
                input: input.clone(),
                folder: dir.to_path_buf(),
            });
        }
    }
    Ok(())
}

/// Refuses a file with a table's name that the accepted manifest does not list as a table
/// still as kfmc wrote it (a regular file of the recorded size).
fn check_listed_table(
    path: &Path,
    t: std::fs::FileType,
    listed: &Listed,
    table: &str,
    is_kfmc: bool,
) -> Result<(), OutputError> {
    let recorded: Vec<u64> = listed
        .tables
        .iter()
        .filter(|e| e.name == table)
        .map(|e| e.bytes)
        .collect();
    let why = if recorded.is_empty() {
        format!(
            "has the name of a kfmc table, but {}: kfmc did not write it, and readers would take it for a table",
            if is_kfmc {
                "manifest.toml does not list it"
            } else {
                "the folder has no kfmc manifest to list it"
            }
        )
    } else if !t.is_file() {
        format!("is {} where kfmc wrote a table", type_name(t))
    } else {
        let len = std::fs::symlink_metadata(path).map_or(0, |m| m.len());
        if recorded.contains(&len) {
            return Ok(());
        }
        format!(
            "has changed since kfmc wrote it ({len} bytes; manifest.toml records {})",
            recorded[0]
        )
    };
    Err(OutputError::NotOurs {
        path: path.to_path_buf(),
        why,
    })
}

/// What a manifest that cannot be trusted as a whole lists, keeping only the tables that still
/// match their recorded size and checksum (those are provably kfmc's bytes).
fn still_matching(dir: &Path, mut listed: Listed) -> Listed {
    listed
        .tables
        .retain(|t| check_tables(dir, std::slice::from_ref(t)).is_ok());
    listed
}

/// Removes the listed file `rel` of the folder, if it is there as a regular file; refuses one
/// that is something else now; then removes the folders on its way that it left empty.
fn remove_listed_file(dir: &Path, rel: &str) -> Result<(), OutputError> {
    let path = dir.join(rel);
    match lstat_under(dir, rel)? {
        None => return Ok(()),
        Some(m) if m.file_type().is_file() => {
            std::fs::remove_file(&path).map_err(io("cannot remove the earlier study's", &path))?
        }
        Some(m) => {
            return Err(OutputError::NotOurs {
                path,
                why: format!("is {} where kfmc wrote a file", type_name(m.file_type())),
            });
        }
    }
    // A folder kfmc made for its files (`figures`) goes when the last of them does; one that
    // holds anything else stays.
    let mut parent = Path::new(rel).parent();
    while let Some(p) = parent.filter(|p| !p.as_os_str().is_empty()) {
        if std::fs::remove_dir(dir.join(p)).is_err() {
            break;
        }
        parent = p.parent();
    }
    Ok(())
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

/// FNV-1a 64 of a file's bytes, and its size.
pub fn checksum_file(path: &Path) -> Result<(u64, String), OutputError> {
    let mut f = super::atomic::open_regular(path).map_err(io("cannot open", path))?;
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

/// Reads the manifest of a result folder and checks that it is final, that every table it
/// lists is there (a regular file) with the recorded size and checksum, and that no table it
/// does not list is present. Readers (`summary`, `plot`, `report`, `check`, `tune`) call this
/// before trusting a folder.
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
        other => match Manifest::inspect(dir) {
            Ok(Found::Foreign(why)) => OutputError::NotAStudy {
                path: dir.to_path_buf(),
                why: format!("its manifest.toml is not a kfmc manifest ({why})"),
            },
            _ => other,
        },
    })?;
    if manifest.replacing.is_some() {
        return Err(OutputError::NotAStudy {
            path: dir.to_path_buf(),
            why: "a writer was stopped while it committed a study here (its manifest.toml is not final); run the command again".into(),
        });
    }
    if let Some(f) = manifest.format.as_deref().filter(|f| *f != FORMAT) {
        return Err(OutputError::NotAStudy {
            path: dir.to_path_buf(),
            why: format!(
                "its manifest.toml is of format `{f}`, which this kfmc does not read ({FORMAT})"
            ),
        });
    }
    for t in &manifest.tables {
        let path = dir.join(format!("{}.parquet", t.name));
        match std::fs::symlink_metadata(&path) {
            Ok(m) if m.file_type().is_file() => {}
            Ok(m) => {
                return Err(OutputError::Mismatch {
                    path,
                    why: format!(
                        "is {}, where manifest.toml lists a table",
                        type_name(m.file_type())
                    ),
                });
            }
            Err(_) => {
                return Err(OutputError::Mismatch {
                    path,
                    why: "listed in manifest.toml but missing".into(),
                });
            }
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
        if std::fs::symlink_metadata(&path).is_ok() && !manifest.tables.iter().any(|e| e.name == t)
        {
            return Err(OutputError::Mismatch {
                path,
                why: "present but not listed in manifest.toml (left by another study)".into(),
            });
        }
    }
    Ok(manifest)
}
