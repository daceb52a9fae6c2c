//! Self-deleting temporary folders for kfmc's tests, with the two calls of the `tempfile`
//! crate they use (`tempdir()`, `TempDir::path`).
//!
//! Why not `tempfile`: it turns on rustix's `fs` feature, which the main build does not, so
//! cargo's feature unification rebuilt rustix and everything above it (crossterm,
//! comfy-table, polars-core, polars-io, polars-ops, polars) for `cargo test` after
//! `cargo build`. This crate uses std alone, so the test build reuses the main build.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{SystemTime, UNIX_EPOCH};

/// A folder under the system's temporary directory, removed with its contents on drop.
#[derive(Debug)]
pub struct TempDir {
    path: PathBuf,
}

impl TempDir {
    /// The folder.
    pub fn path(&self) -> &Path {
        &self.path
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.path);
    }
}

/// Creates a fresh, empty folder. The name joins the process id, a per-process counter and
/// the clock, and `create_dir` refuses an existing folder, so concurrent tests (threads or
/// processes) never share one.
pub fn tempdir() -> std::io::Result<TempDir> {
    static NEXT: AtomicU64 = AtomicU64::new(0);
    let base = std::env::temp_dir();
    let nanos = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.subsec_nanos());
    for _ in 0..1000 {
        let n = NEXT.fetch_add(1, Ordering::Relaxed);
        let path = base.join(format!(".kfmc-test-{}-{n}-{nanos:09}", std::process::id()));
        match std::fs::create_dir(&path) {
            Ok(()) => return Ok(TempDir { path }),
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => continue,
            Err(e) => return Err(e),
        }
    }
    Err(std::io::Error::new(
        std::io::ErrorKind::AlreadyExists,
        "no free temporary folder name after 1000 tries",
    ))
}

#[cfg(test)]
mod tests {
    #[test]
    fn folders_are_distinct_and_removed_on_drop() {
        let a = super::tempdir().unwrap();
        let b = super::tempdir().unwrap();
        assert_ne!(a.path(), b.path());
        std::fs::write(a.path().join("f"), b"x").unwrap();
        std::fs::create_dir(a.path().join("d")).unwrap();
        let p = a.path().to_path_buf();
        drop(a);
        assert!(!p.exists());
        assert!(b.path().is_dir());
    }
}
