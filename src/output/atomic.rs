//! Durable file writes: a file appears under its name complete or not at all; and how kfmc
//! opens what lies inside a result folder.
//!
//! The lowest file of `output/`: the checkpoint journals, the tables, the manifest and the
//! study folder all write through it. Inside a result folder nothing is opened through a
//! symbolic link (`O_NOFOLLOW`), no open waits on a FIFO (`O_NONBLOCK`, then anything but a
//! regular file is refused), and a temporary file is created under a name no other program's
//! file can have (`.kfmc-<token>-<n>.<name>.partial`, created exclusively): a user's
//! `.x.partial` is never opened, truncated or removed as one of kfmc's.

use std::fs::{File, OpenOptions};
use std::io::Write;
use std::os::unix::fs::OpenOptionsExt;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;
use std::sync::atomic::{AtomicU64, Ordering};

/// What every temporary name kfmc gives starts with.
const TEMP_PREFIX: &str = ".kfmc-";

/// What every temporary name kfmc gives ends with.
const TEMP_SUFFIX: &str = ".partial";

/// Hex digits of a process token.
const TOKEN_LEN: usize = 16;

/// This process's token: 64 random bits (from the standard library's per-process hash keys,
/// the pid and the clock), in every temporary name the process gives. A writer records it in
/// its folder's lock file, so that the next writer knows which temporary files a killed one
/// left, and removes those and nothing else.
pub fn process_token() -> &'static str {
    static TOKEN: OnceLock<String> = OnceLock::new();
    TOKEN.get_or_init(|| {
        use std::hash::{BuildHasher, Hasher};
        let mut h = std::collections::hash_map::RandomState::new().build_hasher();
        h.write_u32(std::process::id());
        if let Ok(d) = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH) {
            h.write_u128(d.as_nanos());
        }
        format!("{:016x}", h.finish())
    })
}

/// A fresh temporary name for a file or folder that will be `name`:
/// `.kfmc-<token>-<n>.<name>.partial`, with this process's token and a counter.
pub fn temp_name(name: &str) -> String {
    static NEXT: AtomicU64 = AtomicU64::new(0);
    format!(
        "{TEMP_PREFIX}{}-{}.{name}{TEMP_SUFFIX}",
        process_token(),
        NEXT.fetch_add(1, Ordering::Relaxed)
    )
}

/// The token of the process that named the temporary entry `name`, when `name` is one of
/// kfmc's temporary names.
pub fn temp_token(name: &str) -> Option<&str> {
    let rest = name.strip_prefix(TEMP_PREFIX)?;
    if !name.ends_with(TEMP_SUFFIX) {
        return None;
    }
    let (token, _) = rest.split_once('-')?;
    is_token(token).then_some(token)
}

/// Whether `s` has the form of a process token.
pub fn is_token(s: &str) -> bool {
    s.len() == TOKEN_LEN && s.bytes().all(|b| b.is_ascii_hexdigit())
}

/// A fresh temporary path beside `path` ([`temp_name`] of its file name).
pub fn temp_beside(path: &Path) -> PathBuf {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    path.with_file_name(temp_name(&name))
}

/// Creates a new file at `path` for writing; fails if anything is there already, a symbolic
/// link included.
pub fn create_new(path: &Path) -> std::io::Result<File> {
    OpenOptions::new()
        .write(true)
        .create_new(true)
        .custom_flags(libc::O_NOFOLLOW)
        .open(path)
}

/// Creates a temporary file beside `path` under a fresh name; returns its path and the file.
pub fn create_temp_beside(path: &Path) -> std::io::Result<(PathBuf, File)> {
    let mut tries = 0;
    loop {
        let tmp = temp_beside(path);
        match create_new(&tmp) {
            Ok(f) => return Ok((tmp, f)),
            // Another file already has the name: take the next.
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists && tries < 64 => tries += 1,
            Err(e) => return Err(e),
        }
    }
}

/// What a file type is, for messages: "a symbolic link", "a FIFO", …
pub fn type_name(t: std::fs::FileType) -> &'static str {
    use std::os::unix::fs::FileTypeExt;
    if t.is_symlink() {
        "a symbolic link"
    } else if t.is_dir() {
        "a folder"
    } else if t.is_fifo() {
        "a FIFO (named pipe)"
    } else if t.is_socket() {
        "a socket"
    } else if t.is_block_device() || t.is_char_device() {
        "a device"
    } else {
        "a regular file"
    }
}

/// The error of an open that met something other than a regular file.
fn not_a_file(what: &str) -> std::io::Error {
    std::io::Error::new(
        std::io::ErrorKind::InvalidInput,
        format!(
            "it is {what}; kfmc opens only regular files inside a result folder, and none through a symbolic link"
        ),
    )
}

/// Maps the error of an `O_NOFOLLOW` open of a symbolic link to a message that says so.
fn followed(e: std::io::Error) -> std::io::Error {
    if e.raw_os_error() == Some(libc::ELOOP) {
        not_a_file("a symbolic link")
    } else {
        e
    }
}

/// Checks that an opened file is a regular file.
fn regular(f: File) -> std::io::Result<File> {
    let t = f.metadata()?.file_type();
    if t.is_file() {
        Ok(f)
    } else {
        Err(not_a_file(type_name(t)))
    }
}

/// Opens the regular file at `path` for reading: never through a symbolic link, never waiting
/// on a FIFO, and refusing anything but a regular file.
pub fn open_regular(path: &Path) -> std::io::Result<File> {
    OpenOptions::new()
        .read(true)
        .custom_flags(libc::O_NOFOLLOW | libc::O_NONBLOCK)
        .open(path)
        .map_err(followed)
        .and_then(regular)
}

/// Opens the regular file at `path` for reading and writing, creating it if `create`, with
/// the same guards as [`open_regular`] (a lock file, a journal).
pub fn open_regular_rw(path: &Path, create: bool) -> std::io::Result<File> {
    OpenOptions::new()
        .read(true)
        .write(true)
        .create(create)
        .truncate(false)
        .custom_flags(libc::O_NOFOLLOW | libc::O_NONBLOCK)
        .open(path)
        .map_err(followed)
        .and_then(regular)
}

/// Reads the regular file at `path` as text, as [`open_regular`] opens it.
pub fn read_regular(path: &Path) -> std::io::Result<String> {
    use std::io::Read;
    let mut text = String::new();
    open_regular(path)?.read_to_string(&mut text)?;
    Ok(text)
}

/// Writes `bytes` to `path` atomically: a temporary file beside it, flushed to disk (fsync),
/// then a rename and an fsync of the folder, so a full disk, a kill or a power cut never leaves
/// a truncated file under the real name.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    let (tmp, mut f) = create_temp_beside(path)?;
    let result = (|| {
        f.write_all(bytes)?;
        f.sync_all()?;
        drop(f);
        std::fs::rename(&tmp, path)?;
        // The rename is durable once the folder's entry is; not every platform can open a
        // folder for syncing, and the file is already complete either way.
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty())
            && let Ok(d) = File::open(dir)
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
    open_regular(path)?.sync_all()
}

/// Opens an input file the user named (a spec, an estimates file, a table to read) for
/// reading: a symbolic link is followed (the user chose the path), but the open never waits
/// on a FIFO (`O_NONBLOCK`) and anything but a regular file is refused once opened (a FIFO,
/// a terminal or a device may never end). Inside a result folder use [`open_regular`], which
/// follows no link.
pub fn open_input(path: &Path) -> std::io::Result<File> {
    OpenOptions::new()
        .read(true)
        .custom_flags(libc::O_NONBLOCK)
        .open(path)
        .and_then(|f| {
            let t = f.metadata()?.file_type();
            if t.is_file() {
                Ok(f)
            } else {
                Err(std::io::Error::new(
                    std::io::ErrorKind::InvalidInput,
                    format!("it is {}, not a regular file", type_name(t)),
                ))
            }
        })
}

/// Reads the whole of the regular file at `path` as UTF-8 text ([`open_input`]).
pub fn read_input_to_string(path: &Path) -> std::io::Result<String> {
    use std::io::Read;
    let mut text = String::new();
    open_input(path)?.read_to_string(&mut text)?;
    Ok(text)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn temporary_names_are_kfmc_s_own_and_tell_their_token() {
        let a = temp_name("runs.parquet");
        let b = temp_name("runs.parquet");
        assert_ne!(a, b);
        assert!(
            a.starts_with(".kfmc-") && a.ends_with(".runs.parquet.partial"),
            "{a}"
        );
        assert_eq!(temp_token(&a), Some(process_token()));
        for user in [
            ".runs.parquet.partial",
            ".backup.partial",
            ".kfmc-x-1.a.partial",
        ] {
            assert_eq!(temp_token(user), None, "{user}");
        }
    }

    #[test]
    fn nothing_is_opened_through_a_link_or_a_fifo() {
        let d = tempfile::tempdir().unwrap();
        let target = d.path().join("target");
        std::fs::write(&target, "keep").unwrap();
        let link = d.path().join("link");
        std::os::unix::fs::symlink(&target, &link).unwrap();
        let e = open_regular(&link).unwrap_err().to_string();
        assert!(e.contains("symbolic link"), "{e}");
        let e = open_regular_rw(&link, true).unwrap_err().to_string();
        assert!(e.contains("symbolic link"), "{e}");
        assert!(create_new(&link).is_err());
        let fifo = d.path().join("fifo");
        assert!(
            std::process::Command::new("mkfifo")
                .arg(&fifo)
                .status()
                .unwrap()
                .success()
        );
        let e = open_regular_rw(&fifo, true).unwrap_err().to_string();
        assert!(e.contains("FIFO"), "{e}");
        let e = open_regular(&fifo).unwrap_err().to_string();
        assert!(e.contains("FIFO"), "{e}");
        assert_eq!(std::fs::read_to_string(&target).unwrap(), "keep");
    }
}
