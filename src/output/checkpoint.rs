//! The checkpoint of a study in progress: what makes a plain `kfmc run` resumable.
//!
//! A table's Parquet file cannot be reopened once its writer is gone (its footer is written
//! last), so the durable state is kept beside it: every row a [`super::TableWriter`] receives
//! is also appended to that table's **journal**, a binary log of the row's values in column
//! order, compressed as one zstd frame per cell (so that every cell boundary is a byte offset
//! a resume can cut at). Every record carries its FNV-1a 64 checksum, and every cell ends
//! with a record that numbers it and counts the rows before it, so that a resume can tell a
//! damaged journal, or an index that does not describe it, from a sound one: zstd alone
//! passes a flipped bit in a literal through as a different value. At a checkpoint (after a cell, at most every `--checkpoint-every` seconds)
//! the journals are flushed and fsynced, then [`Index`] — which cells are complete and how
//! many journal bytes hold them — replaces the previous one atomically. A kill at any moment
//! therefore leaves an index that vouches only for bytes on disk.
//!
//! Resuming replays each journal up to the index's length through a fresh writer, verifying
//! every record and that the journal ends exactly at the index's last cell: the same
//! rows in the same order, so the same row groups and the same bytes as a run that never
//! stopped. The cells after the checkpoint are then computed as usual. Nothing is merged,
//! so an uninterrupted run pays only for writing its rows a second time, unencoded.

use std::fs::File;
use std::io::{BufRead, BufReader, BufWriter, Read, Seek, Write};
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::schema::{ColumnDef, Dtype, Value};
use crate::error::OutputError;

/// The checkpoint's folder inside an output folder.
pub const CHECKPOINT_DIR: &str = ".checkpoint";

/// The index's file name inside [`CHECKPOINT_DIR`].
const INDEX_FILE: &str = "index.toml";

/// Each journal's write buffer: rows reach the file in blocks this large.
pub const JOURNAL_BUFFER_BYTES: usize = 1 << 20;

/// The journals' format: zstd frames of checksummed records, the first naming the study
/// that wrote the journal, then rows and cell ends (format 2 had no study record, format 1
/// bare rows). An index of another format is refused.
pub const JOURNAL_FORMAT: u32 = 3;

/// A journal record's first byte: a table row follows.
const TAG_ROW: u8 = 0;

/// A journal record's first byte: the end of a cell follows (cells complete, rows before it).
const TAG_CELL_END: u8 = 1;

/// A journal record's first byte: the identity of the study that writes the journal follows
/// ([`Index::identity_text`]); it is the journal's first record, and only there.
const TAG_STUDY: u8 = 2;

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
    /// The simulated world's stamp (`Plan::world_stamp`: the world's definition and the
    /// master seed).
    #[serde(default)]
    pub world_stamp: String,
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
    /// Whether its covariance, innovation, S and A columns are float32
    /// (`--export-estimates-precision f32`; absent: float64).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub export_f32: bool,
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
        let Some(text) = read_plain(output, &path)? else {
            return Ok(None);
        };
        toml::from_str(&text)
            .map(Some)
            .map_err(|e| OutputError::Format {
                path,
                message: format!(
                    "not a kfmc checkpoint index: {e}; start over with `kfmc run SPEC --restart`"
                ),
            })
    }

    /// Whether the index is coherent in itself: complete cells within its range, and one
    /// journal per table at most. (That the journals hold what it says is checked as they
    /// are replayed.)
    pub fn check(&self, output: &Path) -> Result<(), OutputError> {
        let path = dir(output).join(INDEX_FILE);
        let bad = |why: String| OutputError::Mismatch {
            path: path.clone(),
            why: format!(
                "is a damaged checkpoint index: {why}; start over with `kfmc run SPEC --restart`"
            ),
        };
        if self.first_cell > self.end_cell || self.end_cell > self.cells {
            return Err(bad(format!(
                "its cells {}..{} are not within the plan's {}",
                self.first_cell, self.end_cell, self.cells
            )));
        }
        let range = self.end_cell - self.first_cell;
        if self.cells_done > range {
            return Err(bad(format!(
                "it counts {} complete cells of {range}",
                self.cells_done
            )));
        }
        for (i, t) in self.tables.iter().enumerate() {
            if self.tables[..i].iter().any(|u| u.name == t.name) {
                return Err(bad(format!("it lists table `{}` twice", t.name)));
            }
        }
        Ok(())
    }

    /// Replaces the index atomically; the journals must already be synced.
    pub fn write(&self, output: &Path) -> Result<(), OutputError> {
        let path = dir(output).join(INDEX_FILE);
        let text = toml::to_string(self).map_err(|e| OutputError::Format {
            path: path.clone(),
            message: format!("cannot encode the checkpoint index: {e}"),
        })?;
        super::atomic::write_atomic(&path, text.as_bytes()).map_err(io("cannot write", &path))?;
        // write_atomic made the index's and the journals' entries durable in the checkpoint
        // folder; the folder's own entry in the output folder must be too, or a power cut
        // could lose the whole checkpoint.
        if let Ok(d) = File::open(output) {
            let _ = d.sync_all();
        }
        Ok(())
    }

    /// The study's identity as its journals begin with it: this index without its progress
    /// (`cells_done`, `tables`), as TOML.
    pub fn identity_text(&self) -> String {
        let identity = Index {
            cells_done: 0,
            tables: Vec::new(),
            ..self.clone()
        };
        toml::to_string(&identity).expect("an index is plain TOML")
    }

    /// What differs between this checkpoint's study and `other`'s, first difference first;
    /// `None` when a resume may continue it.
    pub fn change_from(&self, other: &Index) -> Option<String> {
        let mut changes = [
            (self.journal_format != other.journal_format).then(|| {
                format!(
                    "its journals are in format {} (this kfmc reads and writes format {})",
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
            (self.world_stamp != other.world_stamp).then(|| {
                format!(
                    "the simulated world changed (stamp {} → {})",
                    self.world_stamp, other.world_stamp
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
            (self.export_f32 != other.export_f32).then(|| {
                let p = |f32: bool| if f32 { "f32" } else { "f64" };
                format!(
                    "--export-estimates-precision changed ({} → {})",
                    p(self.export_f32),
                    p(other.export_f32)
                )
            }),
        ]
        .into_iter()
        .flatten();
        changes.next()
    }
}

/// Whether `output`'s checkpoint folder is a folder of its own (not a symbolic link, not a
/// file): `Ok(false)` when there is none.
pub fn check_dir(output: &Path) -> Result<bool, OutputError> {
    let d = dir(output);
    match std::fs::symlink_metadata(&d) {
        Ok(m) if m.file_type().is_dir() => Ok(true),
        Ok(m) => Err(OutputError::NotPlain {
            path: d,
            what: super::atomic::type_name(m.file_type()),
        }),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(false),
        Err(e) => Err(io("cannot read", &d)(e)),
    }
}

/// The text of the checkpoint file `path` of `output`, or `None` when there is none; refuses
/// a checkpoint folder or file that is a symbolic link, a FIFO or anything but a folder and a
/// regular file, without waiting on it.
fn read_plain(output: &Path, path: &Path) -> Result<Option<String>, OutputError> {
    if !check_dir(output)? {
        return Ok(None);
    }
    match std::fs::symlink_metadata(path) {
        Ok(m) if m.file_type().is_file() => {}
        Ok(m) => {
            return Err(OutputError::NotPlain {
                path: path.to_path_buf(),
                what: super::atomic::type_name(m.file_type()),
            });
        }
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(io("cannot read", path)(e)),
    }
    super::atomic::read_regular(path)
        .map(Some)
        .map_err(io("cannot read", path))
}

/// Removes `output`'s checkpoint: the index first, so a kill half-way leaves journals that
/// nothing vouches for, which the next run overwrites; then the journals, and the folder if
/// nothing else is in it (kfmc removes only the files it writes there).
pub fn remove(output: &Path) -> Result<(), OutputError> {
    let d = dir(output);
    if !check_dir(output)? {
        return Ok(());
    }
    let gone = |path: &Path, action: &'static str| match std::fs::remove_file(path) {
        Ok(()) => Ok(()),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(()),
        Err(e) => Err(io(action, path)(e)),
    };
    gone(&d.join(INDEX_FILE), "cannot remove the checkpoint index")?;
    for t in super::schema::TABLES {
        gone(
            &journal_path(output, t),
            "cannot remove the checkpoint journal",
        )?;
    }
    match std::fs::remove_dir(&d) {
        Ok(()) => Ok(()),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(()),
        // Something kfmc did not write is in it: it stays, with the folder.
        Err(e) if e.kind() == std::io::ErrorKind::DirectoryNotEmpty => Ok(()),
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
    /// Starts a journal of `study`'s rows at `path`, replacing any file there: its first
    /// record (a frame of its own) names the study, so that a resume can tell its cells from
    /// another study's whatever its index says.
    pub fn create(path: &Path, study: &Index) -> Result<Self, OutputError> {
        if let Some(d) = path.parent() {
            match std::fs::symlink_metadata(d) {
                Ok(m) if m.file_type().is_dir() => {}
                Ok(m) => {
                    return Err(OutputError::NotPlain {
                        path: d.to_path_buf(),
                        what: super::atomic::type_name(m.file_type()),
                    });
                }
                Err(_) => {
                    std::fs::create_dir(d).map_err(io("cannot create the checkpoint folder", d))?
                }
            }
        }
        let file = {
            use std::os::unix::fs::OpenOptionsExt;
            std::fs::OpenOptions::new()
                .write(true)
                .create(true)
                .truncate(true)
                .custom_flags(libc::O_NOFOLLOW | libc::O_NONBLOCK)
                .open(path)
                .map_err(io("cannot create", path))?
        };
        if !file.metadata().is_ok_and(|m| m.file_type().is_file()) {
            return Err(OutputError::NotPlain {
                path: path.to_path_buf(),
                what: "not a regular file",
            });
        }
        let mut journal = Journal::around(file, path, 0, 0);
        let text = study.identity_text();
        journal.scratch.clear();
        journal.scratch.push(TAG_STUDY);
        journal
            .scratch
            .extend_from_slice(&(text.len() as u32).to_le_bytes());
        journal.scratch.extend_from_slice(text.as_bytes());
        journal.append()?;
        journal.end_frame()?;
        Ok(journal)
    }

    /// Continues the journal at `path` after its first `bytes` bytes (`rows` rows), dropping
    /// whatever a killed run wrote after its last checkpoint.
    pub fn reopen(path: &Path, bytes: u64, rows: u64) -> Result<Self, OutputError> {
        let mut file = super::atomic::open_regular_rw(path, false)
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
        b.push(TAG_ROW);
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
        self.append()?;
        self.rows += 1;
        Ok(())
    }

    /// Ends cell number `cells` (counted from the folder's first cell, from 1) after the
    /// rows recorded so far, and the frame with it, so that the journal can be cut here;
    /// returns its (bytes, rows) at this point (durable only after [`Journal::sync`]).
    pub fn end_cell(&mut self, cells: u64) -> Result<(u64, u64), OutputError> {
        let b = &mut self.scratch;
        b.clear();
        b.push(TAG_CELL_END);
        b.extend_from_slice(&cells.to_le_bytes());
        b.extend_from_slice(&self.rows.to_le_bytes());
        self.append()?;
        self.end_frame()
    }

    /// Appends the record in `scratch` with its checksum to the frame in progress.
    fn append(&mut self) -> Result<(), OutputError> {
        let sum = crate::hash::fnv1a64(&self.scratch);
        self.scratch.extend_from_slice(&sum.to_le_bytes());
        let b = &self.scratch;
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
            .map_err(io("cannot append to", &self.path))
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

/// A journal's records as they are read back: every byte of the record in progress is kept in
/// `raw`, the bytes its checksum covers.
struct Records<'p, R: Read> {
    r: BufReader<R>,
    raw: Vec<u8>,
    path: &'p Path,
    /// The length of the journal the index vouches for (for messages).
    bytes: u64,
}

impl<R: Read> Records<'_, R> {
    fn undecodable(&self, e: std::io::Error) -> OutputError {
        damaged(self.path, format!("cannot be decoded ({e})"))
    }

    fn truncated(&self) -> OutputError {
        damaged(
            self.path,
            format!("ends inside a record before byte {}", self.bytes),
        )
    }

    /// Whether the stream ends here (at a record's start).
    fn at_end(&mut self) -> Result<bool, OutputError> {
        match self.r.fill_buf() {
            Ok(b) => Ok(b.is_empty()),
            Err(e) => Err(self.undecodable(e)),
        }
    }

    /// A failed exact read: the stream ended inside a record, or could not be decoded.
    fn short_read(&self, e: std::io::Error) -> OutputError {
        if e.kind() == std::io::ErrorKind::UnexpectedEof {
            self.truncated()
        } else {
            self.undecodable(e)
        }
    }

    /// Appends the next `n` bytes to `raw`; returns where they start.
    fn read_exact(&mut self, n: usize) -> Result<usize, OutputError> {
        let at = self.raw.len();
        self.raw.resize(at + n, 0);
        self.r
            .read_exact(&mut self.raw[at..])
            .map_err(|e| self.short_read(e))?;
        Ok(at)
    }

    fn u64_at(&self, at: usize) -> u64 {
        u64::from_le_bytes(self.raw[at..at + 8].try_into().unwrap())
    }

    /// Reads the checksum that follows the record in `raw` and compares.
    fn verify_checksum(&mut self, record: u64) -> Result<(), OutputError> {
        let mut sum = [0u8; 8];
        self.r
            .read_exact(&mut sum)
            .map_err(|e| self.short_read(e))?;
        if u64::from_le_bytes(sum) != crate::hash::fnv1a64(&self.raw) {
            return Err(damaged(
                self.path,
                format!("has a record {record} that fails its checksum"),
            ));
        }
        Ok(())
    }

    /// The rest of a cell-end record: the cell it ends, which must be `cells_seen + 1` and
    /// come after `rows` rows.
    fn cell_end(&mut self, record: u64, cells_seen: u64, rows: u64) -> Result<u64, OutputError> {
        self.read_exact(16)?;
        self.verify_checksum(record)?;
        let (cell, rows_before) = (self.u64_at(1), self.u64_at(9));
        if cell != cells_seen + 1 || rows_before != rows {
            return Err(damaged(
                self.path,
                format!(
                    "ends cell {cell} after {rows_before} rows where cell {} ends after {rows}",
                    cells_seen + 1
                ),
            ));
        }
        Ok(cell)
    }

    /// A u32 length and that many bytes, appended to `raw`: where they start and how many.
    /// The bytes are read as they come, not allocated up front: a damaged length must not
    /// reserve gigabytes before its checksum can refuse it.
    fn length_prefixed(&mut self) -> Result<(usize, usize), OutputError> {
        let at = self.read_exact(4)?;
        let n = u32::from_le_bytes(self.raw[at..at + 4].try_into().unwrap()) as usize;
        let at = self.raw.len();
        let got = (&mut self.r)
            .take(n as u64)
            .read_to_end(&mut self.raw)
            .map_err(|e| self.undecodable(e))?;
        if got < n {
            return Err(self.truncated());
        }
        Ok((at, n))
    }

    /// The rest of a study record: the identity it names, which must be `study`'s.
    fn study(&mut self, record: u64, study: &Index) -> Result<(), OutputError> {
        let (at, n) = self.length_prefixed()?;
        self.verify_checksum(record)?;
        let text = std::str::from_utf8(&self.raw[at..at + n]).unwrap_or_default();
        let written: Index = toml::from_str(text).map_err(|e| {
            damaged(
                self.path,
                format!("names its study in a form this kfmc cannot read ({e})"),
            )
        })?;
        match written.change_from(study) {
            None => Ok(()),
            Some(why) => Err(OutputError::Mismatch {
                path: self.path.to_path_buf(),
                why: format!(
                    "holds another study's cells than its checkpoint index and this run describe: {why}; start over with `kfmc run SPEC --restart`"
                ),
            }),
        }
    }

    /// The rest of a row record, decoded into `row`.
    fn row(
        &mut self,
        record: u64,
        columns: &[ColumnDef],
        row: &mut RowBuffer,
    ) -> Result<(), OutputError> {
        row.text.clear();
        row.spans.clear();
        row.decoded.clear();
        for c in columns {
            let v = self.value(c, row)?;
            row.decoded.push(v);
        }
        self.verify_checksum(record)
    }

    /// The next value, of column `c`; a string goes into `row.text` and is filled in by
    /// [`RowBuffer::values`].
    fn value(&mut self, c: &ColumnDef, row: &mut RowBuffer) -> Result<Value<'static>, OutputError> {
        Ok(match c.dtype {
            Dtype::Str => {
                let (at, n) = self.length_prefixed()?;
                let s = std::str::from_utf8(&self.raw[at..at + n]).map_err(|_| {
                    damaged(
                        self.path,
                        format!("has a column {} that is not UTF-8", c.name),
                    )
                })?;
                row.spans.push((row.text.len(), row.text.len() + n));
                row.text.push_str(s);
                Value::Str("")
            }
            // A float32 column is journaled as the f64 it was given, and rounded when written.
            Dtype::F64 | Dtype::F32 => {
                let at = self.read_exact(8)?;
                let x = f64::from_bits(self.u64_at(at));
                Value::F64((!x.is_nan()).then_some(x))
            }
            Dtype::I64 => {
                let at = self.read_exact(1)?;
                if self.raw[at] == 0 {
                    Value::I64(None)
                } else {
                    let at = self.read_exact(8)?;
                    Value::I64(Some(self.u64_at(at) as i64))
                }
            }
            Dtype::U64 => {
                let at = self.read_exact(8)?;
                Value::U64(self.u64_at(at))
            }
            Dtype::Bool => {
                let at = self.read_exact(1)?;
                Value::Bool(match self.raw[at] {
                    0 => None,
                    1 => Some(false),
                    _ => Some(true),
                })
            }
        })
    }
}

/// One replayed row: its strings decoded into one buffer, from which the row's values borrow.
struct RowBuffer {
    text: String,
    spans: Vec<(usize, usize)>,
    /// The values, each string a placeholder for its span of `text`.
    decoded: Vec<Value<'static>>,
}

impl RowBuffer {
    /// The row, its strings borrowed from `text`.
    fn values(&self) -> Vec<Value<'_>> {
        let mut row: Vec<Value<'_>> = Vec::with_capacity(self.decoded.len());
        let mut next_str = self.spans.iter();
        for v in &self.decoded {
            row.push(match v {
                Value::Str(_) => {
                    let &(a, b) = next_str.next().expect("one span per string column");
                    Value::Str(&self.text[a..b])
                }
                other => *other,
            });
        }
        row
    }
}

/// Replays the first `bytes` bytes of the journal at `path`, whose rows have `columns`,
/// calling `f` with each row in order, after verifying its checksum. The bytes must begin
/// with `study`'s identity (unless there are none) and end with the end of cell `cells`
/// (none when `cells` is 0), every cell's end in order before it: an index that does not
/// describe its journal, or a journal of another study, is refused, not followed. Returns
/// the rows replayed.
pub fn replay(
    path: &Path,
    bytes: u64,
    cells: u64,
    columns: &[ColumnDef],
    study: &Index,
    mut f: impl FnMut(&[Value<'_>]) -> Result<(), OutputError>,
) -> Result<u64, OutputError> {
    let file = super::atomic::open_regular(path)
        .map_err(io("cannot open the checkpoint journal", path))?;
    let decoder = zstd::stream::read::Decoder::new(file.take(bytes))
        .map_err(io("cannot start decompressing", path))?;
    let mut records = Records {
        r: BufReader::with_capacity(1 << 16, decoder),
        raw: Vec::with_capacity(256),
        path,
        bytes,
    };
    let mut row = RowBuffer {
        text: String::new(),
        spans: Vec::new(),
        decoded: Vec::with_capacity(columns.len()),
    };
    let mut done = 0u64;
    let mut cells_seen = 0u64;
    // Whether the last record read ended a cell (so the bytes may end here).
    let mut at_cell_end = true;
    let mut record = 0u64;
    while !records.at_end()? {
        record += 1;
        records.raw.clear();
        let at = records.read_exact(1)?;
        match records.raw[at] {
            TAG_STUDY if record == 1 => records.study(record, study)?,
            _ if record == 1 => {
                return Err(damaged(
                    path,
                    "does not begin with the identity of its study".into(),
                ));
            }
            TAG_CELL_END => {
                cells_seen = records.cell_end(record, cells_seen, done)?;
                at_cell_end = true;
            }
            TAG_ROW => {
                records.row(record, columns, &mut row)?;
                f(&row.values())?;
                done += 1;
                at_cell_end = false;
            }
            tag => {
                return Err(damaged(
                    path,
                    format!("has a record {record} of unknown kind {tag}"),
                ));
            }
        }
    }
    if !at_cell_end || cells_seen != cells {
        return Err(damaged(
            path,
            format!(
                "holds {cells_seen} complete cells{} where its checkpoint index counts {cells}",
                if at_cell_end {
                    ""
                } else {
                    " and rows after them"
                }
            ),
        ));
    }
    Ok(done)
}

#[cfg(test)]
mod tests;
