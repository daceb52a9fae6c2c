//! One study per folder, committed once.
//!
//! A writer takes an exclusive lock on its output folder ([`StudyFolder::open`]): a second
//! writer is refused, and a lock left by a process that no longer runs is taken over. Tables
//! are written under temporary names; [`StudyFolder::commit`] then invalidates the old
//! manifest, moves every table into place, removes tables of an earlier study that this one
//! did not write, and writes the new manifest **last**, listing every table with its size, row
//! count and checksum. The manifest is the commit record: a reader ([`verify`]) accepts a
//! folder only when every table it lists is there and matches. A kill at any moment therefore
//! leaves either the old study (killed before the commit), the new one (after it), or — for
//! the few renames in between — a folder without a manifest, which every reader refuses;
//! never a mix that looks complete.

use std::io::{Read, Write};
use std::path::{Path, PathBuf};

use super::manifest::Manifest;
use super::schema;
use crate::error::OutputError;

/// The lock file's name inside an output folder.
pub const LOCK_FILE: &str = ".kfmc.lock";

/// An output folder held exclusively by this process until dropped.
#[derive(Debug)]
pub struct StudyFolder {
    dir: PathBuf,
    lock: PathBuf,
}

/// A table written in full under its temporary name, ready to be moved into place.
#[derive(Debug)]
pub struct FinishedTable {
    /// Table name (`runs`, `steps`, …).
    pub name: String,
    /// Its temporary file.
    pub tmp: PathBuf,
    /// Rows.
    pub rows: u64,
}

fn io<'a>(action: &'static str, path: &'a Path) -> impl FnOnce(std::io::Error) -> OutputError + 'a {
    move |source| OutputError::Io {
        action,
        path: path.to_path_buf(),
        source,
    }
}

/// Whether a process with this id runs on this machine. Where that cannot be told (no
/// `/proc`), every lock counts as held: refusing is the safe side.
fn process_alive(pid: u32) -> bool {
    if !Path::new("/proc/self").exists() {
        return true;
    }
    Path::new(&format!("/proc/{pid}")).exists()
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

impl StudyFolder {
    /// Creates (if needed) and locks `dir` for writing a study. Refused when another live
    /// kfmc holds it, or when `dir` is not empty and is not a kfmc study (unless `force`).
    pub fn open(dir: &Path, force: bool) -> Result<Self, OutputError> {
        std::fs::create_dir_all(dir).map_err(io("cannot create the output folder", dir))?;
        let lock = dir.join(LOCK_FILE);
        for attempt in 0..2 {
            match std::fs::OpenOptions::new()
                .write(true)
                .create_new(true)
                .open(&lock)
            {
                Ok(mut f) => {
                    let _ = writeln!(f, "{}", std::process::id());
                    break;
                }
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists && attempt == 0 => {
                    let mut text = String::new();
                    let _ =
                        std::fs::File::open(&lock).and_then(|mut f| f.read_to_string(&mut text));
                    match text.trim().parse::<u32>() {
                        Ok(pid) if pid != std::process::id() && process_alive(pid) => {
                            return Err(OutputError::Locked {
                                path: dir.to_path_buf(),
                                pid,
                            });
                        }
                        // A lock of a process that is gone (or unreadable because it died
                        // while writing it): take it over.
                        _ => {
                            std::fs::remove_file(&lock)
                                .map_err(io("cannot remove the stale lock", &lock))?;
                        }
                    }
                }
                Err(e) => return Err(io("cannot lock the output folder with", &lock)(e)),
            }
        }
        let folder = StudyFolder {
            dir: dir.to_path_buf(),
            lock,
        };
        let mut foreign = Vec::new();
        for entry in std::fs::read_dir(dir).map_err(io("cannot list", dir))? {
            let entry = entry.map_err(io("cannot list", dir))?;
            let name = entry.file_name().to_string_lossy().into_owned();
            if name.starts_with('.') && name.ends_with(".partial") {
                // Left by a writer that was killed; we hold the lock, so it is an orphan.
                let _ = std::fs::remove_file(entry.path());
            } else if !is_kfmc_file(&name) {
                foreign.push(name);
            }
        }
        let is_study = dir.join("manifest.toml").exists();
        if !foreign.is_empty() && !is_study && !force {
            foreign.sort();
            return Err(OutputError::Foreign {
                path: dir.to_path_buf(),
                example: foreign[0].clone(),
                count: foreign.len(),
            });
        }
        Ok(folder)
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
        mut manifest: Manifest,
    ) -> Result<Vec<(String, u64)>, OutputError> {
        let manifest_path = self.dir.join("manifest.toml");
        if manifest_path.exists() {
            std::fs::remove_file(&manifest_path)
                .map_err(io("cannot invalidate the old manifest", &manifest_path))?;
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

impl Drop for StudyFolder {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.lock);
    }
}

/// FNV-1a 64 of a file's bytes, and its size.
pub fn checksum_file(path: &Path) -> Result<(u64, String), OutputError> {
    let mut f = std::fs::File::open(path).map_err(io("cannot open", path))?;
    let mut buf = vec![0u8; 1 << 16];
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    let mut n = 0u64;
    loop {
        let k = f.read(&mut buf).map_err(io("cannot read", path))?;
        if k == 0 {
            break;
        }
        n += k as u64;
        for b in &buf[..k] {
            h ^= *b as u64;
            h = h.wrapping_mul(0x0100_0000_01b3);
        }
    }
    Ok((n, format!("{h:016x}")))
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

/// Writes `bytes` to `path` atomically: a temporary file beside it, flushed to disk (fsync),
/// then a rename and an fsync of the folder, so a full disk, a kill or a power cut never leaves
/// a truncated file under the real name.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    let tmp = temp_beside(path);
    let result = (|| {
        let mut f = std::fs::File::create(&tmp)?;
        f.write_all(bytes)?;
        f.sync_all()?;
        drop(f);
        std::fs::rename(&tmp, path)?;
        // The rename is durable once the folder's entry is; not every platform can open a
        // folder for syncing, and the file is already complete either way.
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty())
            && let Ok(d) = std::fs::File::open(dir)
        {
            let _ = d.sync_all();
        }
        Ok(())
    })();
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result
}

/// Flushes a written file's data and metadata to the disk.
pub fn sync_file(path: &Path) -> std::io::Result<()> {
    std::fs::File::open(path)?.sync_all()
}

/// The temporary name used for `path` while it is written: `.<name>.partial` beside it.
pub fn temp_beside(path: &Path) -> PathBuf {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    path.with_file_name(format!(".{name}.partial"))
}
