//! Reading a result folder: its manifest final, and every table it lists there with the
//! recorded size and checksum.

use std::io::Read;
use std::path::Path;

use crate::error::OutputError;
use crate::output::atomic::type_name;
use crate::output::manifest::{FORMAT, Found, Manifest};
use crate::output::schema;

use super::io;

/// FNV-1a 64 of a file's bytes, and its size.
pub fn checksum_file(path: &Path) -> Result<(u64, String), OutputError> {
    let mut f = crate::output::atomic::open_regular(path).map_err(io("cannot open", path))?;
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
