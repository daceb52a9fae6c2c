//! The folder's lock: an advisory `flock` on `.kfmc.lock`, and the record in it of who
//! holds it and which killed writers' temporary files are still to be removed.

use std::io::Read;
use std::os::unix::fs::{FileExt, MetadataExt};
use std::path::{Path, PathBuf};
use std::sync::Mutex;

use crate::error::OutputError;
use crate::output::atomic::{process_token, temp_token, type_name};

use super::{LOCK_FILE, io};

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
            if crate::output::atomic::is_token(t)
                && t != process_token()
                && !out.iter().any(|o| o == t)
            {
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
            let mut file = crate::output::atomic::open_regular_rw(&path, true)
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

    pub(super) fn orphans(&self) -> std::sync::MutexGuard<'_, Vec<String>> {
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
    pub(super) fn clear_orphans(&self, dir: &Path) {
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
