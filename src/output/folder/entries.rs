//! The entries of a result folder: which names it keeps, which entries kfmc wrote (as its
//! manifest lists them, or beside any study), and removing or refusing them.

use std::io::Read;
use std::path::{Component, Path, PathBuf};

use crate::error::OutputError;
use crate::output::atomic::type_name;
use crate::output::checkpoint::CHECKPOINT_DIR;
use crate::output::manifest::{Found, Listed, Manifest, TableEntry};
use crate::output::schema;

use super::verify::checksum_file;
use super::{DESCRIBE_FORMAT_LINE, LOCK_FILE, MANIFEST, io};

/// The table a file name is the file of (`runs` for `runs.parquet`).
pub(super) fn table_of(name: &str) -> Option<&'static str> {
    let stem = name.strip_suffix(".parquet")?;
    schema::TABLES.iter().copied().find(|t| *t == stem)
}

/// Whether `rel` is a plain relative path inside a folder (`figures/rmse.png`): no root, no
/// `..`, no `.`, no empty component.
pub(super) fn is_inside_path(rel: &str) -> bool {
    !rel.is_empty()
        && !rel.starts_with('/')
        && rel
            .split('/')
            .all(|c| !c.is_empty() && c != "." && c != "..")
}

/// What a manifest lists, keeping only entries that can name something inside the folder: a
/// listed path with `..` or a root is not kfmc's, whatever the file says.
pub(super) fn sanitized(mut l: Listed) -> Listed {
    l.tables
        .retain(|t| table_of(&format!("{}.parquet", t.name)).is_some());
    l.files.retain(|f| is_inside_path(f));
    l.folders.retain(|f| is_inside_path(f) && !f.contains('/'));
    l
}

/// The metadata of `dir/rel`, not following a symbolic link at any component below `dir`:
/// `None` when it (or a folder on the way) is absent; refused when a component on the way is
/// not a folder of its own.
pub(super) fn lstat_under(dir: &Path, rel: &str) -> Result<Option<std::fs::Metadata>, OutputError> {
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
pub(super) fn reserved(rel: &str, listed_folders: &[String]) -> Option<&'static str> {
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
    crate::output::atomic::open_regular(path)
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
pub(super) fn written_beside_studies(path: &Path, name: &str, t: std::fs::FileType) -> bool {
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
pub(super) fn check_tables(dir: &Path, tables: &[TableEntry]) -> Result<(), String> {
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
pub(super) fn legacy_tune_stages(dir: &Path) -> Vec<String> {
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
pub(super) fn refuse_inputs(dir: &Path, inputs: &[PathBuf]) -> Result<(), OutputError> {
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
pub(super) fn check_listed_table(
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
pub(super) fn still_matching(dir: &Path, mut listed: Listed) -> Listed {
    listed
        .tables
        .retain(|t| check_tables(dir, std::slice::from_ref(t)).is_ok());
    listed
}

/// Removes the listed file `rel` of the folder, if it is there as a regular file; refuses one
/// that is something else now; then removes the folders on its way that it left empty.
pub(super) fn remove_listed_file(dir: &Path, rel: &str) -> Result<(), OutputError> {
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
