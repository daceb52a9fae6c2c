//! The checkpoint of a study in progress: what makes a plain `kfmc run` resumable.
//!
//! A table's Parquet file cannot be reopened once its writer is gone (its footer is written
//! last), so the durable state is kept beside it: every row a [`super::TableWriter`] receives
//! is also appended to that table's **journal**, a binary log of the row's values in column
//! order, compressed as one zstd frame per cell (so that every cell boundary is a byte offset
//! a resume can cut at). At a checkpoint (after a cell, at most every `--checkpoint-every` seconds)
//! the journals are flushed and fsynced, then [`Index`] — which cells are complete and how
//! many journal bytes hold them — replaces the previous one atomically. A kill at any moment
//! therefore leaves an index that vouches only for bytes on disk.
//!
//! Resuming replays each journal up to the index's length through a fresh writer: the same
//! rows in the same order, so the same row groups and the same bytes as a run that never
//! stopped. The cells after the checkpoint are then computed as usual. Nothing is merged,
//! so an uninterrupted run pays only for writing its rows a second time, unencoded.

use std::fs::File;
use std::io::{BufRead, BufReader, BufWriter, Read, Seek, Write};
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::schema::{ColumnDef, Dtype};
use super::table::Value;
use crate::error::OutputError;

/// The checkpoint's folder inside an output folder.
pub const CHECKPOINT_DIR: &str = ".checkpoint";

/// The index's file name inside [`CHECKPOINT_DIR`].
const INDEX_FILE: &str = "index.toml";

/// Each journal's write buffer: rows reach the file in blocks this large.
pub const JOURNAL_BUFFER_BYTES: usize = 1 << 20;

/// The journals' format: zstd frames of rows. An index of another format is refused.
pub const JOURNAL_FORMAT: u32 = 1;

/// zstd's level for the journals: its fastest regular level, as the journal is written once
/// and read only by a resume.
const JOURNAL_ZSTD_LEVEL: i32 = 1;

/// How an F64 null is journaled: NaN, which the table writes as null too.
const NULL_F64: u64 = 0x7ff8_0000_0000_0000;

fn io<'a>(action: &'static str, path: &'a Path) -> impl FnOnce(std::io::Error) -> OutputError + 'a {
    move |source| OutputError::Io {
        action,
        path: path.to_path_buf(),
        source,
    }
}

/// The checkpoint folder of an output folder.
pub fn dir(output: &Path) -> PathBuf {
    output.join(CHECKPOINT_DIR)
}

/// The journal file of table `name`.
pub fn journal_path(output: &Path, name: &str) -> PathBuf {
    dir(output).join(format!("{name}.journal"))
}

/// One table's durable journal prefix.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct JournalEntry {
    /// Table name.
    pub name: String,
    /// Journal bytes that hold the complete cells' rows.
    pub bytes: u64,
    /// Rows in those bytes.
    pub rows: u64,
}

/// What a checkpoint vouches for, and the identity of the study it belongs to.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Index {
    /// kfmc that wrote it: another version may compute other rows.
    pub kfmc_version: String,
    /// Hash of the spec text.
    pub spec_hash: String,
    /// Master seed (after `--seed`).
    pub master_seed: u64,
    /// Runs per cell (after `--runs`).
    pub runs_per_cell: u64,
    /// Cells of the whole plan.
    pub cells: u64,
    /// The cells this folder computes: `[first_cell, end_cell)` (a part's, or all).
    pub first_cell: u64,
    /// One past the last.
    pub end_cell: u64,
    /// Runs per cell traced into traces.parquet.
    pub trace_runs: u64,
    /// Whether estimates.parquet is written.
    pub export_estimates: bool,
    /// [`JOURNAL_FORMAT`] of the journals (0: an index from before the field existed).
    #[serde(default)]
    pub journal_format: u32,
    /// Cells complete, counted from `first_cell`.
    pub cells_done: u64,
    /// Every journaled table.
    pub tables: Vec<JournalEntry>,
}

impl Index {
    /// Reads the index of `output`'s checkpoint, if there is one.
    pub fn read(output: &Path) -> Result<Option<Index>, OutputError> {
        let path = dir(output).join(INDEX_FILE);
        let text = match std::fs::read_to_string(&path) {
            Ok(t) => t,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(io("cannot read", &path)(e)),
        };
        toml::from_str(&text)
            .map(Some)
            .map_err(|e| OutputError::Format {
                path,
                message: format!("not a kfmc checkpoint index: {e}"),
            })
    }

    /// Replaces the index atomically; the journals must already be synced.
    pub fn write(&self, output: &Path) -> Result<(), OutputError> {
        let path = dir(output).join(INDEX_FILE);
        let text = toml::to_string(self).map_err(|e| OutputError::Format {
            path: path.clone(),
            message: format!("cannot encode the checkpoint index: {e}"),
        })?;
        super::folder::write_atomic(&path, text.as_bytes()).map_err(io("cannot write", &path))?;
        // write_atomic made the index's and the journals' entries durable in the checkpoint
        // folder; the folder's own entry in the output folder must be too, or a power cut
        // could lose the whole checkpoint.
        if let Ok(d) = File::open(output) {
            let _ = d.sync_all();
        }
        Ok(())
    }

    /// What differs between this checkpoint's study and `other`'s, first difference first;
    /// `None` when a resume may continue it.
    pub fn change_from(&self, other: &Index) -> Option<String> {
        let mut changes = [
            (self.journal_format != other.journal_format).then(|| {
                format!(
                    "its journals are in format {} (this kfmc writes {})",
                    self.journal_format, other.journal_format
                )
            }),
            (self.kfmc_version != other.kfmc_version).then(|| {
                format!(
                    "it was written by kfmc {} (this is {})",
                    self.kfmc_version, other.kfmc_version
                )
            }),
            (self.spec_hash != other.spec_hash).then(|| {
                format!(
                    "the spec changed since the checkpoint (hash {} → {})",
                    self.spec_hash, other.spec_hash
                )
            }),
            (self.master_seed != other.master_seed).then(|| {
                format!(
                    "the master seed changed ({} → {})",
                    self.master_seed, other.master_seed
                )
            }),
            (self.runs_per_cell != other.runs_per_cell).then(|| {
                format!(
                    "the runs per cell changed ({} → {})",
                    self.runs_per_cell, other.runs_per_cell
                )
            }),
            ((self.cells, self.first_cell, self.end_cell)
                != (other.cells, other.first_cell, other.end_cell))
                .then(|| {
                    format!(
                        "the cells changed (cells {}..{} of {} → {}..{} of {})",
                        self.first_cell,
                        self.end_cell,
                        self.cells,
                        other.first_cell,
                        other.end_cell,
                        other.cells
                    )
                }),
            (self.trace_runs != other.trace_runs).then(|| {
                format!(
                    "--trace-runs changed ({} → {})",
                    self.trace_runs, other.trace_runs
                )
            }),
            (self.export_estimates != other.export_estimates).then(|| {
                format!(
                    "--export-estimates changed ({} → {})",
                    self.export_estimates, other.export_estimates
                )
            }),
        ]
        .into_iter()
        .flatten();
        changes.next()
    }
}

/// Removes `output`'s checkpoint: the index first, so a kill half-way leaves journals that
/// nothing vouches for, which the next run overwrites.
pub fn remove(output: &Path) -> Result<(), OutputError> {
    let d = dir(output);
    match std::fs::remove_file(d.join(INDEX_FILE)) {
        Ok(()) => {}
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
        Err(e) => return Err(io("cannot remove the checkpoint index in", &d)(e)),
    }
    match std::fs::remove_dir_all(&d) {
        Ok(()) => Ok(()),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(()),
        Err(e) => Err(io("cannot remove the checkpoint", &d)(e)),
    }
}

/// A writer that counts the bytes it passed on: the journal's length at a frame's end.
struct Counted {
    inner: BufWriter<File>,
    bytes: u64,
}

impl Write for Counted {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        let n = self.inner.write(buf)?;
        self.bytes += n as u64;
        Ok(n)
    }

    fn flush(&mut self) -> std::io::Result<()> {
        self.inner.flush()
    }
}

/// An append-only log of one table's rows.
pub struct Journal {
    /// The frame being written, if a row came since the last frame's end.
    frame: Option<zstd::stream::write::Encoder<'static, Counted>>,
    /// The file between frames.
    idle: Option<Counted>,
    path: PathBuf,
    rows: u64,
    scratch: Vec<u8>,
}

impl Journal {
    /// Starts an empty journal at `path`, replacing any file there.
    pub fn create(path: &Path) -> Result<Self, OutputError> {
        if let Some(d) = path.parent() {
            std::fs::create_dir_all(d).map_err(io("cannot create the checkpoint folder", d))?;
        }
        let file = File::create(path).map_err(io("cannot create", path))?;
        Ok(Journal::around(file, path, 0, 0))
    }

    /// Continues the journal at `path` after its first `bytes` bytes (`rows` rows), dropping
    /// whatever a killed run wrote after its last checkpoint.
    pub fn reopen(path: &Path, bytes: u64, rows: u64) -> Result<Self, OutputError> {
        let mut file = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .open(path)
            .map_err(io("cannot open the checkpoint journal", path))?;
        let len = file
            .metadata()
            .map_err(io("cannot read the size of", path))?
            .len();
        if len < bytes {
            return Err(damaged(
                path,
                format!("holds {len} bytes, its checkpoint vouches for {bytes}"),
            ));
        }
        file.set_len(bytes).map_err(io("cannot truncate", path))?;
        file.seek(std::io::SeekFrom::Start(bytes))
            .map_err(io("cannot seek in", path))?;
        Ok(Journal::around(file, path, bytes, rows))
    }

    fn around(file: File, path: &Path, bytes: u64, rows: u64) -> Self {
        Journal {
            frame: None,
            idle: Some(Counted {
                inner: BufWriter::with_capacity(JOURNAL_BUFFER_BYTES, file),
                bytes,
            }),
            path: path.to_path_buf(),
            rows,
            scratch: Vec::with_capacity(256),
        }
    }

    /// Appends one row (already checked against the table's columns by its writer).
    pub fn record(&mut self, row: &[Value<'_>]) -> Result<(), OutputError> {
        let b = &mut self.scratch;
        b.clear();
        for v in row {
            match *v {
                Value::Str(s) => {
                    b.extend_from_slice(&(s.len() as u32).to_le_bytes());
                    b.extend_from_slice(s.as_bytes());
                }
                Value::F64(x) => {
                    let bits = x.filter(|x| !x.is_nan()).map_or(NULL_F64, f64::to_bits);
                    b.extend_from_slice(&bits.to_le_bytes());
                }
                Value::I64(None) => b.push(0),
                Value::I64(Some(x)) => {
                    b.push(1);
                    b.extend_from_slice(&x.to_le_bytes());
                }
                Value::U64(x) => b.extend_from_slice(&x.to_le_bytes()),
                Value::Bool(x) => b.push(x.map_or(0, |x| 1 + x as u8)),
            }
        }
        let frame = match self.frame.as_mut() {
            Some(f) => f,
            None => {
                let out = self.idle.take().expect("idle between frames");
                let enc = zstd::stream::write::Encoder::new(out, JOURNAL_ZSTD_LEVEL)
                    .map_err(io("cannot start compressing", &self.path))?;
                self.frame.insert(enc)
            }
        };
        frame
            .write_all(b)
            .map_err(io("cannot append to", &self.path))?;
        self.rows += 1;
        Ok(())
    }

    /// Ends the frame in progress, so that the journal can be cut here; returns its (bytes,
    /// rows) at this point (durable only after [`Journal::sync`]).
    pub fn end_frame(&mut self) -> Result<(u64, u64), OutputError> {
        if let Some(frame) = self.frame.take() {
            let out = frame.finish().map_err(io("cannot append to", &self.path))?;
            self.idle = Some(out);
        }
        let bytes = self.idle.as_ref().expect("idle after a frame").bytes;
        Ok((bytes, self.rows))
    }

    /// Ends the frame in progress, flushes and fsyncs; returns the durable (bytes, rows).
    pub fn sync(&mut self) -> Result<(u64, u64), OutputError> {
        let at = self.end_frame()?;
        let out = self.idle.as_mut().expect("idle after a frame");
        out.inner.flush().map_err(io("cannot write", &self.path))?;
        out.inner
            .get_ref()
            .sync_data()
            .map_err(io("cannot sync", &self.path))?;
        Ok(at)
    }
}

fn damaged(path: &Path, why: String) -> OutputError {
    OutputError::Mismatch {
        path: path.to_path_buf(),
        why: format!(
            "is a damaged checkpoint journal: it {why}; start over with `kfmc run SPEC --restart`"
        ),
    }
}

/// Replays the first `bytes` bytes of the journal at `path`, whose rows have `columns`,
/// calling `f` with each row in order. Returns the rows replayed.
pub fn replay(
    path: &Path,
    bytes: u64,
    columns: &[ColumnDef],
    mut f: impl FnMut(&[Value<'_>]) -> Result<(), OutputError>,
) -> Result<u64, OutputError> {
    let file = File::open(path).map_err(io("cannot open the checkpoint journal", path))?;
    let decoder = zstd::stream::read::Decoder::new(file.take(bytes))
        .map_err(io("cannot start decompressing", path))?;
    let mut r = BufReader::with_capacity(1 << 16, decoder);
    let undecodable = |e: std::io::Error| damaged(path, format!("cannot be decoded ({e})"));
    let read_exact = |r: &mut BufReader<_>, buf: &mut [u8]| -> Result<(), OutputError> {
        r.read_exact(buf).map_err(|e| {
            if e.kind() == std::io::ErrorKind::UnexpectedEof {
                damaged(path, format!("ends inside a row before byte {bytes}"))
            } else {
                undecodable(e)
            }
        })
    };
    // Strings are decoded into one buffer per row; the row's values borrow from it.
    let mut text = String::new();
    let mut spans: Vec<(usize, usize)> = Vec::new();
    let mut decoded: Vec<Value<'static>> = Vec::with_capacity(columns.len());
    let mut done = 0u64;
    let mut u8b = [0u8; 1];
    let mut u32b = [0u8; 4];
    let mut u64b = [0u8; 8];
    // Rows until the stream ends at a row's start.
    while !r.fill_buf().map_err(undecodable)?.is_empty() {
        text.clear();
        spans.clear();
        decoded.clear();
        for c in columns {
            let v = match c.dtype {
                Dtype::Str => {
                    read_exact(&mut r, &mut u32b)?;
                    let n = u32::from_le_bytes(u32b) as usize;
                    let mut s = vec![0u8; n];
                    read_exact(&mut r, &mut s)?;
                    let s = String::from_utf8(s).map_err(|_| {
                        damaged(path, format!("has a column {} that is not UTF-8", c.name))
                    })?;
                    spans.push((text.len(), text.len() + n));
                    text.push_str(&s);
                    // Filled in below, once `text` no longer grows.
                    Value::Str("")
                }
                Dtype::F64 => {
                    read_exact(&mut r, &mut u64b)?;
                    let x = f64::from_bits(u64::from_le_bytes(u64b));
                    Value::F64((!x.is_nan()).then_some(x))
                }
                Dtype::I64 => {
                    read_exact(&mut r, &mut u8b)?;
                    if u8b[0] == 0 {
                        Value::I64(None)
                    } else {
                        read_exact(&mut r, &mut u64b)?;
                        Value::I64(Some(i64::from_le_bytes(u64b)))
                    }
                }
                Dtype::U64 => {
                    read_exact(&mut r, &mut u64b)?;
                    Value::U64(u64::from_le_bytes(u64b))
                }
                Dtype::Bool => {
                    read_exact(&mut r, &mut u8b)?;
                    Value::Bool(match u8b[0] {
                        0 => None,
                        1 => Some(false),
                        _ => Some(true),
                    })
                }
            };
            decoded.push(v);
        }
        let mut row: Vec<Value<'_>> = Vec::with_capacity(columns.len());
        let mut next_str = spans.iter();
        for v in &decoded {
            row.push(match v {
                Value::Str(_) => {
                    let &(a, b) = next_str.next().expect("one span per string column");
                    Value::Str(&text[a..b])
                }
                other => *other,
            });
        }
        f(&row)?;
        done += 1;
    }
    Ok(done)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cols() -> Vec<ColumnDef> {
        [
            ("s", Dtype::Str),
            ("x", Dtype::F64),
            ("i", Dtype::I64),
            ("u", Dtype::U64),
            ("b", Dtype::Bool),
        ]
        .into_iter()
        .map(|(n, d)| ColumnDef {
            name: n.into(),
            dtype: d,
        })
        .collect()
    }

    fn rows() -> Vec<Vec<Value<'static>>> {
        vec![
            vec![
                Value::Str("basic"),
                Value::F64(Some(-0.0)),
                Value::I64(Some(-7)),
                Value::U64(u64::MAX),
                Value::Bool(Some(true)),
            ],
            vec![
                Value::Str(""),
                Value::F64(None),
                Value::I64(None),
                Value::U64(0),
                Value::Bool(None),
            ],
            vec![
                Value::Str("ωθ"),
                Value::F64(Some(f64::INFINITY)),
                Value::I64(Some(i64::MIN)),
                Value::U64(3),
                Value::Bool(Some(false)),
            ],
        ]
    }

    /// Values and nulls come back bit for bit (−0.0, ∞, extremes, UTF-8, empty strings), and
    /// a NaN comes back as the null the table stores for it.
    #[test]
    fn rows_replay_exactly_and_a_reopened_journal_drops_the_unsynced_tail() {
        let d = tempfile::tempdir().unwrap();
        let path = d.path().join("t.journal");
        let mut j = Journal::create(&path).unwrap();
        for r in rows() {
            j.record(&r).unwrap();
        }
        let (bytes, rows_done) = j.sync().unwrap();
        assert_eq!(rows_done, 3);
        j.record(&[
            Value::Str("lost"),
            Value::F64(Some(f64::NAN)),
            Value::I64(None),
            Value::U64(1),
            Value::Bool(None),
        ])
        .unwrap();
        j.sync().unwrap();
        drop(j);

        let mut back: Vec<String> = Vec::new();
        let n = replay(&path, bytes, &cols(), |r| {
            back.push(format!("{r:?}"));
            Ok(())
        })
        .unwrap();
        assert_eq!(n, 3);
        let want: Vec<String> = rows().iter().map(|r| format!("{r:?}")).collect();
        assert_eq!(back, want);
        let mut neg_zero = None;
        replay(&path, bytes, &cols(), |r| {
            if let Value::F64(Some(x)) = r[1] {
                neg_zero.get_or_insert(x.to_bits());
            }
            Ok(())
        })
        .unwrap();
        assert_eq!(neg_zero, Some((-0.0f64).to_bits()));

        let mut j = Journal::reopen(&path, bytes, 3).unwrap();
        assert_eq!(std::fs::metadata(&path).unwrap().len(), bytes);
        j.record(&rows()[1]).unwrap();
        let (b2, r2) = j.sync().unwrap();
        assert_eq!(r2, 4);
        let mut last = String::new();
        assert_eq!(
            replay(&path, b2, &cols(), |r| {
                last = format!("{r:?}");
                Ok(())
            })
            .unwrap(),
            4
        );
        assert_eq!(last, format!("{:?}", rows()[1]));
    }

    #[test]
    fn a_journal_shorter_than_its_checkpoint_is_refused_as_damaged() {
        let d = tempfile::tempdir().unwrap();
        let path = d.path().join("t.journal");
        let mut j = Journal::create(&path).unwrap();
        j.record(&rows()[0]).unwrap();
        let (bytes, _) = j.sync().unwrap();
        drop(j);
        let err = Journal::reopen(&path, bytes + 5, 2)
            .err()
            .unwrap()
            .to_string();
        assert!(err.contains("damaged checkpoint journal"), "{err}");
        // Bytes lost inside the frame the checkpoint vouches for.
        std::fs::OpenOptions::new()
            .write(true)
            .open(&path)
            .unwrap()
            .set_len(bytes - 3)
            .unwrap();
        let err = replay(&path, bytes, &cols(), |_| Ok(()))
            .err()
            .unwrap()
            .to_string();
        assert!(err.contains("damaged checkpoint journal"), "{err}");
    }
}
