//! Durable file writes: a file appears under its name complete or not at all.
//!
//! The lowest file of `output/`: the checkpoint journals, the tables, the manifest and the
//! study folder all write through it.

use std::io::Write;
use std::path::{Path, PathBuf};

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

/// Opens `path` for reading when it is a regular file (or a symlink to one), and refuses
/// anything else before opening it: opening a FIFO blocks until a writer comes, reading one
/// (or a terminal) blocks until it writes, and a device may never end. Every file kfmc reads
/// (a spec, estimates, a study's tables, manifests and checkpoints) goes through here.
pub fn open_input(path: &Path) -> std::io::Result<std::fs::File> {
    use std::os::unix::fs::FileTypeExt;
    let kind = std::fs::metadata(path)?.file_type();
    let what = if kind.is_file() {
        None
    } else if kind.is_dir() {
        Some("a folder")
    } else if kind.is_fifo() {
        Some("a FIFO (named pipe)")
    } else if kind.is_socket() {
        Some("a socket")
    } else if kind.is_char_device() || kind.is_block_device() {
        Some("a device")
    } else {
        Some("neither a file nor a folder")
    };
    if let Some(what) = what {
        return Err(std::io::Error::new(
            std::io::ErrorKind::InvalidInput,
            format!("it is {what}, not a regular file"),
        ));
    }
    std::fs::File::open(path)
}

/// Reads the whole of the regular file at `path` as UTF-8 text ([`open_input`]).
pub fn read_input_to_string(path: &Path) -> std::io::Result<String> {
    use std::io::Read;
    let mut text = String::new();
    open_input(path)?.read_to_string(&mut text)?;
    Ok(text)
}
