//! A streaming, atomic Parquet table writer on top of polars.

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

use polars::prelude::*;

pub use super::schema::Value;
use super::schema::{ColumnDef, Dtype};
use crate::error::OutputError;

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

enum Buffer {
    Str(Vec<String>),
    F64(Vec<Option<f64>>),
    F32(Vec<Option<f32>>),
    I64(Vec<Option<i64>>),
    U64(Vec<u64>),
    Bool(Vec<Option<bool>>),
}

/// Rows per Parquet row group; bounds the writer's memory.
pub const FLUSH_ROWS: usize = 65_536;

/// Values (rows × columns) per row group of `estimates`, the one wide table whose rows come
/// from every run: a row holds each quantity's covariance and error transition (77 values
/// on the planar quadrotor, hundreds on the drone), so [`FLUSH_ROWS`] of them would buffer
/// over 100 MB before the encoder's copies. The other tables keep [`FLUSH_ROWS`], and with
/// it their bytes.
pub const ESTIMATES_GROUP_VALUES: usize = 1 << 20;

/// Rows per row group of the table `name` with `columns` columns.
fn rows_per_group(name: &str, columns: usize) -> usize {
    if name == "estimates" {
        (ESTIMATES_GROUP_VALUES / columns.max(1)).clamp(1, FLUSH_ROWS)
    } else {
        FLUSH_ROWS
    }
}

/// Writes one table to a temporary file beside `<dir>/<name>.parquet`
/// (`.kfmc-<token>-<n>.<name>.parquet.partial`, [`super::atomic::temp_name`]) and renames it
/// to `<name>.parquet` on [`TableWriter::commit`]. Dropped without a commit, it deletes its
/// temporary file.
pub struct TableWriter {
    name: String,
    path: PathBuf,
    tmp: PathBuf,
    columns: Vec<ColumnDef>,
    buffers: Vec<Buffer>,
    buffered: usize,
    /// Rows per row group ([`rows_per_group`]).
    flush_rows: usize,
    rows: u64,
    writer: Option<polars::io::parquet::write::BatchedWriter<SharedFile>>,
    /// The buffered file under the writer: polars encodes page headers and the footer in
    /// writes of a few bytes (about 10,000 system calls for a 4,000-run study), and its
    /// writer never gives its `W` back, so the buffer is shared to flush it, with its
    /// error, after the footer.
    file: SharedFile,
    /// Whether the file was finished whole (then it is the caller's, or already in place).
    ended: bool,
    /// The checkpoint journal every pushed row is also appended to, when the study is
    /// resumable ([`super::checkpoint`]).
    journal: Option<super::checkpoint::Journal>,
}

impl TableWriter {
    /// Starts a table `name` in `dir` with the given columns.
    pub fn create(dir: &Path, name: &str, columns: Vec<ColumnDef>) -> Result<Self, OutputError> {
        Self::create_with_metadata(dir, name, columns, &[])
    }

    /// Starts a table as [`TableWriter::create`] does, whose footer will carry these
    /// file-level key-value pairs (the stamp of an estimates file, say). Without pairs the
    /// file is the one `create` writes.
    pub fn create_with_metadata(
        dir: &Path,
        name: &str,
        columns: Vec<ColumnDef>,
        metadata: &[(String, String)],
    ) -> Result<Self, OutputError> {
        let path = dir.join(format!("{name}.parquet"));
        let (tmp, file) =
            super::atomic::create_temp_beside(&path).map_err(|source| OutputError::Io {
                action: "cannot create a temporary file beside",
                path: path.clone(),
                source,
            })?;
        let schema = Schema::from_iter(columns.iter().map(|c| {
            let dt = match c.dtype {
                Dtype::Str => DataType::String,
                Dtype::F64 => DataType::Float64,
                Dtype::F32 => DataType::Float32,
                Dtype::I64 => DataType::Int64,
                Dtype::U64 => DataType::UInt64,
                Dtype::Bool => DataType::Boolean,
            };
            Field::new(c.name.as_str().into(), dt)
        }));
        let file = SharedFile(Arc::new(Mutex::new(BufWriter::with_capacity(
            1 << 16,
            file,
        ))));
        let key_value = (!metadata.is_empty())
            .then(|| polars::io::parquet::write::KeyValueMetadata::from_static(metadata.to_vec()));
        let writer = ParquetWriter::new(file.clone())
            .with_compression(ParquetCompression::Zstd(None))
            .with_key_value_metadata(key_value)
            .batched(&schema)
            .map_err(|source| OutputError::Polars {
                action: "cannot start writing",
                path: tmp.clone(),
                source,
            })?;
        let buffers = columns
            .iter()
            .map(|c| match c.dtype {
                Dtype::Str => Buffer::Str(Vec::new()),
                Dtype::F64 => Buffer::F64(Vec::new()),
                Dtype::F32 => Buffer::F32(Vec::new()),
                Dtype::I64 => Buffer::I64(Vec::new()),
                Dtype::U64 => Buffer::U64(Vec::new()),
                Dtype::Bool => Buffer::Bool(Vec::new()),
            })
            .collect();
        Ok(TableWriter {
            name: name.to_string(),
            path,
            tmp,
            flush_rows: rows_per_group(name, columns.len()),
            columns,
            buffers,
            buffered: 0,
            rows: 0,
            writer: Some(writer),
            file,
            ended: false,
            journal: None,
        })
    }

    /// Starts the table as [`TableWriter::create`] does, journaling every row of `study`
    /// into `journal` from now on. With `resume_from = Some((bytes, rows, cells))`, the
    /// journal's first `bytes` bytes, which must be `study`'s and hold `cells` complete
    /// cells, are first replayed (and verified) into the table, each row also handed to
    /// `on_row`, and the journal continues after them: the table receives exactly the rows,
    /// in the order, of the run that wrote the journal.
    #[allow(
        clippy::too_many_arguments,
        reason = "the table's own arguments, then its journal's: where, whose, and from where"
    )]
    pub(crate) fn journaled(
        dir: &Path,
        name: &str,
        columns: Vec<ColumnDef>,
        metadata: &[(String, String)],
        journal: &Path,
        study: &super::checkpoint::Index,
        resume_from: Option<(u64, u64, u64)>,
        mut on_row: impl FnMut(&[Value<'_>]) -> Result<(), OutputError>,
    ) -> Result<Self, OutputError> {
        let mut w = TableWriter::create_with_metadata(dir, name, columns, metadata)?;
        w.journal = Some(match resume_from {
            None => super::checkpoint::Journal::create(journal, study)?,
            Some((bytes, rows, cells)) => {
                let columns = w.columns.clone();
                let replayed =
                    super::checkpoint::replay(journal, bytes, cells, &columns, study, |row| {
                        w.push(row)?;
                        on_row(row)
                    })?;
                if replayed != rows {
                    return Err(OutputError::Mismatch {
                        path: journal.to_path_buf(),
                        why: format!(
                            "is a damaged checkpoint journal: it holds {replayed} rows, its checkpoint {rows}; start over with `kfmc run SPEC --restart`"
                        ),
                    });
                }
                if bytes == 0 {
                    // Nothing was vouched for, not even the study's record: begin anew.
                    super::checkpoint::Journal::create(journal, study)?
                } else {
                    super::checkpoint::Journal::reopen(journal, bytes, rows)?
                }
            }
        });
        Ok(w)
    }

    /// Makes the journal durable up to the last pushed row; returns its (bytes, rows).
    pub(crate) fn sync_journal(&mut self) -> Result<Option<(u64, u64)>, OutputError> {
        self.journal.as_mut().map(|j| j.sync()).transpose()
    }

    /// Ends cell number `cells` (from 1) in the journal after the last pushed row; returns
    /// its (bytes, rows) there.
    pub(crate) fn end_journal_cell(
        &mut self,
        cells: u64,
    ) -> Result<Option<(u64, u64)>, OutputError> {
        self.journal.as_mut().map(|j| j.end_cell(cells)).transpose()
    }

    /// Appends one row; values must follow the column order and types.
    ///
    /// # Panics
    /// On a row of the wrong length or type: a programming error in the caller, whose rows
    /// are built from the same schema.
    pub fn push(&mut self, row: &[Value<'_>]) -> Result<(), OutputError> {
        assert_eq!(
            row.len(),
            self.columns.len(),
            "row length must match the schema"
        );
        for (i, (b, v)) in self.buffers.iter_mut().zip(row).enumerate() {
            match (b, v) {
                (Buffer::Str(b), Value::Str(s)) => b.push((*s).to_string()),
                (Buffer::F64(b), Value::F64(x)) => b.push(x.filter(|x| !x.is_nan())),
                (Buffer::F32(b), Value::F64(x)) => {
                    b.push(x.filter(|x| !x.is_nan()).map(|x| x as f32))
                }
                (Buffer::I64(b), Value::I64(x)) => b.push(*x),
                (Buffer::U64(b), Value::U64(x)) => b.push(*x),
                (Buffer::Bool(b), Value::Bool(x)) => b.push(*x),
                _ => panic!(
                    "value of the wrong type for column {}",
                    self.columns[i].name
                ),
            }
        }
        if let Some(j) = self.journal.as_mut() {
            j.record(row)?;
        }
        self.buffered += 1;
        if self.buffered >= self.flush_rows {
            self.flush()?;
        }
        Ok(())
    }

    fn flush(&mut self) -> Result<(), OutputError> {
        if self.buffered == 0 {
            return Ok(());
        }
        let cols: Vec<Column> = self
            .columns
            .iter()
            .zip(self.buffers.iter_mut())
            .map(|(c, b)| {
                let name: PlSmallStr = c.name.as_str().into();
                match b {
                    Buffer::Str(v) => Column::new(name, std::mem::take(v)),
                    Buffer::F64(v) => Column::new(name, std::mem::take(v)),
                    Buffer::F32(v) => Column::new(name, std::mem::take(v)),
                    Buffer::I64(v) => Column::new(name, std::mem::take(v)),
                    Buffer::U64(v) => Column::new(name, std::mem::take(v)),
                    Buffer::Bool(v) => Column::new(name, std::mem::take(v)),
                }
            })
            .collect();
        let polars_err = |source| OutputError::Polars {
            action: "cannot write",
            path: self.tmp.clone(),
            source,
        };
        let df = DataFrame::new(self.buffered, cols).map_err(polars_err)?;
        self.writer
            .as_mut()
            .expect("the writer lives until commit")
            .write_batch(&df)
            .map_err(polars_err)?;
        self.rows += self.buffered as u64;
        self.buffered = 0;
        Ok(())
    }

    /// Finishes the file under its temporary name, for a [`super::folder::StudyFolder`] to
    /// move into place with the others.
    pub fn finish(mut self) -> Result<FinishedTable, OutputError> {
        self.flush()?;
        self.end_file()?;
        self.ended = true;
        Ok(FinishedTable {
            name: std::mem::take(&mut self.name),
            tmp: std::mem::take(&mut self.tmp),
            rows: self.rows,
        })
    }

    /// Finishes the file and renames it into place; returns its path and row count.
    pub fn commit(mut self) -> Result<(PathBuf, u64), OutputError> {
        self.flush()?;
        self.end_file()?;
        super::atomic::sync_file(&self.tmp).map_err(|source| OutputError::Io {
            action: "cannot sync",
            path: self.tmp.clone(),
            source,
        })?;
        std::fs::rename(&self.tmp, &self.path).map_err(|source| OutputError::Io {
            action: "cannot move the finished table to",
            path: self.path.clone(),
            source,
        })?;
        self.ended = true;
        Ok((self.path.clone(), self.rows))
    }

    /// Writes the footer and flushes the file's buffer.
    fn end_file(&mut self) -> Result<(), OutputError> {
        let writer = self.writer.take().expect("the writer lives until commit");
        writer.finish().map_err(|source| OutputError::Polars {
            action: "cannot finish",
            path: self.tmp.clone(),
            source,
        })?;
        drop(writer);
        self.file.flush().map_err(|source| OutputError::Io {
            action: "cannot write",
            path: self.tmp.clone(),
            source,
        })
    }

    /// Appends every row of `df`, whose columns must be this table's (as read back from a
    /// table kfmc wrote with the same schema). The rows pass through the same buffers and
    /// row groups as rows pushed one by one, so the file is byte-identical.
    pub fn append_frame(&mut self, df: &DataFrame, origin: &Path) -> Result<(), OutputError> {
        let columns = self.columns.clone();
        for_each_row(df, &columns, origin, |row| self.push(row))
    }

    /// The table's name (`runs`, `steps`, …).
    pub fn name(&self) -> &str {
        &self.name
    }

    /// The final path of the table.
    pub fn path(&self) -> &Path {
        &self.path
    }
}

impl Drop for TableWriter {
    fn drop(&mut self) {
        if !self.ended {
            // Not committed (or its footer or buffer could not be written): leave nothing
            // that could be mistaken for a result.
            let _ = std::fs::remove_file(&self.tmp);
        }
    }
}

/// A buffered file that the Parquet writer and the [`TableWriter`] both hold.
#[derive(Clone)]
struct SharedFile(Arc<Mutex<BufWriter<File>>>);

impl SharedFile {
    fn lock(&self) -> std::sync::MutexGuard<'_, BufWriter<File>> {
        // A panic while writing leaves the buffer as it was; the table is then dropped
        // uncommitted anyway.
        self.0
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    }
}

impl Write for SharedFile {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.lock().write(buf)
    }
    fn write_all(&mut self, buf: &[u8]) -> std::io::Result<()> {
        self.lock().write_all(buf)
    }
    fn flush(&mut self) -> std::io::Result<()> {
        self.lock().flush()
    }
}

/// The column definitions of a table kfmc wrote, read back from its frame.
pub fn columns_of(df: &DataFrame, origin: &Path) -> Result<Vec<ColumnDef>, OutputError> {
    df.columns()
        .iter()
        .map(|c| {
            let dtype = match c.dtype() {
                DataType::String => Dtype::Str,
                DataType::Float64 => Dtype::F64,
                DataType::Float32 => Dtype::F32,
                DataType::Int64 => Dtype::I64,
                DataType::UInt64 => Dtype::U64,
                DataType::Boolean => Dtype::Bool,
                other => {
                    return Err(OutputError::Format {
                        path: origin.to_path_buf(),
                        message: format!(
                            "column {} has type {other}, not one kfmc writes",
                            c.name()
                        ),
                    });
                }
            };
            Ok(ColumnDef {
                name: c.name().to_string(),
                dtype,
            })
        })
        .collect()
}

/// Calls `f` with every row of `df` in order, as the values of `columns` (looked up by name,
/// in that order): the rows a table kfmc wrote with these columns was given, read back
/// (`kfmc merge` appends them, and rebuilds the divergence trackers from them). A missing
/// column or one of another type is an error naming `origin`.
pub fn for_each_row(
    df: &DataFrame,
    columns: &[ColumnDef],
    origin: &Path,
    mut f: impl FnMut(&[Value<'_>]) -> Result<(), OutputError>,
) -> Result<(), OutputError> {
    let bad = |e: PolarsError| OutputError::Polars {
        action: "unexpected columns in",
        path: origin.to_path_buf(),
        source: e,
    };
    enum Col<'a> {
        Str(&'a StringChunked),
        F64(&'a Float64Chunked),
        F32(&'a Float32Chunked),
        I64(&'a Int64Chunked),
        U64(&'a UInt64Chunked),
        Bool(&'a BooleanChunked),
    }
    let mut cols = Vec::with_capacity(columns.len());
    for c in columns {
        let col = df.column(c.name.as_str()).map_err(bad)?;
        cols.push(match c.dtype {
            Dtype::Str => Col::Str(col.str().map_err(bad)?),
            Dtype::F64 => Col::F64(col.f64().map_err(bad)?),
            Dtype::F32 => Col::F32(col.f32().map_err(bad)?),
            Dtype::I64 => Col::I64(col.i64().map_err(bad)?),
            Dtype::U64 => Col::U64(col.u64().map_err(bad)?),
            Dtype::Bool => Col::Bool(col.bool().map_err(bad)?),
        });
    }
    let mut row = Vec::with_capacity(cols.len());
    for i in 0..df.height() {
        row.clear();
        for c in &cols {
            row.push(match c {
                Col::Str(a) => Value::Str(a.get(i).unwrap_or("")),
                Col::F64(a) => Value::F64(a.get(i)),
                Col::F32(a) => Value::F64(a.get(i).map(f64::from)),
                Col::I64(a) => Value::I64(a.get(i)),
                Col::U64(a) => Value::U64(a.get(i).unwrap_or(0)),
                Col::Bool(a) => Value::Bool(a.get(i)),
            });
        }
        f(&row)?;
    }
    Ok(())
}

/// Reads a Parquet table one row group at a time, so memory is bounded by a row group
/// whatever the table's size (`kfmc merge`, `kfmc score`). Returns the file's metadata
/// (its key-value pairs, say) after the last group.
pub fn for_each_row_group(
    path: &Path,
    mut f: impl FnMut(DataFrame) -> Result<(), OutputError>,
) -> Result<polars::io::parquet::read::FileMetadata, OutputError> {
    let open = || {
        super::atomic::open_input(path).map_err(|source| OutputError::Io {
            action: "cannot open",
            path: path.to_path_buf(),
            source,
        })
    };
    let bad = |source| OutputError::Polars {
        action: "cannot read",
        path: path.to_path_buf(),
        source,
    };
    let meta = ParquetReader::new(open()?)
        .get_metadata()
        .map_err(bad)?
        .clone();
    let mut offset = 0;
    for rg in &meta.row_groups {
        let height = rg.num_rows();
        let mut reader = ParquetReader::new(open()?).with_slice(Some((offset, height)));
        reader.set_metadata(meta.clone());
        f(reader.finish().map_err(bad)?)?;
        offset += height;
    }
    Ok(std::sync::Arc::unwrap_or_clone(meta))
}

/// Whether a file begins with Parquet's `PAR1` marker: a file that does not is no Parquet
/// file at all (a CSV, say), while one that does but is damaged is left for the reader's
/// own message.
pub fn starts_as_parquet(file: &File) -> bool {
    use std::os::unix::fs::FileExt;
    let mut head = [0u8; 4];
    file.read_exact_at(&mut head, 0).is_ok() && &head == b"PAR1"
}

/// Reads a whole Parquet table, refusing one with two rows of one key
/// ([`unique_keys`]).
pub fn read(path: &Path) -> Result<DataFrame, OutputError> {
    let file = super::atomic::open_input(path).map_err(|source| OutputError::Io {
        action: "cannot open",
        path: path.to_path_buf(),
        source,
    })?;
    let df = ParquetReader::new(file)
        .finish()
        .map_err(|source| OutputError::Polars {
            action: "cannot read",
            path: path.to_path_buf(),
            source,
        })?;
    unique_keys(&df, path)?;
    Ok(df)
}

/// Refuses a table read from `path` that has two rows of one key: the key columns are those
/// of its name ([`super::schema::row_keys`]); a table of another name, or without all of its
/// key columns (the columns of a partial read), is not checked.
pub fn unique_keys(df: &DataFrame, path: &Path) -> Result<(), OutputError> {
    use std::collections::HashMap;
    use std::hash::{Hash, Hasher};
    let Some(keys) = path
        .file_stem()
        .and_then(|s| s.to_str())
        .and_then(super::schema::row_keys)
    else {
        return Ok(());
    };
    let Ok(cols) = keys
        .iter()
        .map(|k| df.column(k).map(|c| c.as_materialized_series().clone()))
        .collect::<PolarsResult<Vec<Series>>>()
    else {
        return Ok(());
    };
    // Each key column as exact ids: strings interned, numbers by their bits, null apart.
    let ids: Vec<Vec<Option<u64>>> = cols
        .iter()
        .map(|c| -> Vec<Option<u64>> {
            let mut interned: HashMap<Option<&str>, u64> = HashMap::new();
            match c.dtype() {
                DataType::String => c
                    .str()
                    .map(|a| {
                        a.iter()
                            .map(|v| {
                                let n = interned.len() as u64;
                                Some(*interned.entry(v).or_insert(n))
                            })
                            .collect()
                    })
                    .unwrap_or_default(),
                DataType::Float64 => c
                    .f64()
                    .map(|a| a.iter().map(|v| v.map(f64::to_bits)).collect())
                    .unwrap_or_default(),
                _ => c
                    .cast(&DataType::Int64)
                    .ok()
                    .and_then(|c| {
                        c.i64()
                            .ok()
                            .map(|a| a.iter().map(|v| v.map(|x| x as u64)).collect())
                    })
                    .unwrap_or_default(),
            }
        })
        .collect();
    if ids.iter().any(|v| v.len() != df.height()) {
        return Ok(());
    }
    let same = |i: usize, j: usize| ids.iter().all(|c| c[i] == c[j]);
    let hash_row = |i: usize| {
        let mut h = std::collections::hash_map::DefaultHasher::new();
        for c in &ids {
            c[i].hash(&mut h);
        }
        h.finish()
    };
    let mut seen: HashMap<u64, usize> = HashMap::with_capacity(df.height());
    for i in 0..df.height() {
        let j = *seen.entry(hash_row(i)).or_insert(i);
        if j != i && same(i, j) {
            let key: Vec<String> = keys
                .iter()
                .zip(&cols)
                .map(|(k, c)| format!("{k} = {}", c.get(i).map_or("?".into(), |v| v.to_string())))
                .collect();
            return Err(OutputError::Format {
                path: path.to_path_buf(),
                message: format!(
                    "rows {j} and {i} have one key ({}): a kfmc table has one row per key; the file was altered or assembled by hand",
                    key.join(", ")
                ),
            });
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::output::schema::{ColumnDef, Dtype};

    fn cols() -> Vec<ColumnDef> {
        vec![
            ColumnDef {
                name: "a".into(),
                dtype: Dtype::Str,
            },
            ColumnDef {
                name: "b".into(),
                dtype: Dtype::F64,
            },
        ]
    }

    #[test]
    fn an_uncommitted_table_leaves_no_file_behind() {
        let dir = tempfile::tempdir().unwrap();
        {
            let mut w = TableWriter::create(dir.path(), "t", cols()).unwrap();
            w.push(&[Value::Str("x"), Value::F64(Some(1.0))]).unwrap();
            // Dropped mid-way, as on an error later in the study.
        }
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
    }

    #[test]
    fn committed_tables_round_trip_with_nulls_across_row_groups() {
        let dir = tempfile::tempdir().unwrap();
        let mut w = TableWriter::create(dir.path(), "t", cols()).unwrap();
        let n = FLUSH_ROWS + 10; // two row groups
        for i in 0..n {
            let v = if i % 3 == 0 { None } else { Some(i as f64) };
            w.push(&[Value::Str("x"), Value::F64(v)]).unwrap();
        }
        w.push(&[Value::Str("nan"), Value::F64(Some(f64::NAN))])
            .unwrap();
        let (path, rows) = w.commit().unwrap();
        assert_eq!(rows, n as u64 + 1);
        let df = read(&path).unwrap();
        assert_eq!(df.height(), n + 1);
        let b = df.column("b").unwrap().f64().unwrap();
        assert_eq!(b.get(0), None);
        assert_eq!(b.get(1), Some(1.0));
        assert_eq!(b.get(n - 1), Some((n - 1) as f64));
        assert_eq!(b.get(n), None, "NaN is written as null");
        let left: Vec<_> = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .filter(|n| n.ends_with(".partial"))
            .collect();
        assert!(left.is_empty(), "{left:?}");
    }

    fn summary_cols() -> Vec<ColumnDef> {
        let c = |name: &str, dtype| ColumnDef {
            name: name.into(),
            dtype,
        };
        vec![
            c("scenario", Dtype::Str),
            c("noise_scale", Dtype::F64),
            c("filter", Dtype::Str),
            c("q_scale", Dtype::F64),
            c("r_scale", Dtype::F64),
            c("state", Dtype::Str),
            c("rmse_mean", Dtype::F64),
        ]
    }

    fn summary_with(rows: &[(&str, f64, &str, f64)]) -> (tempfile::TempDir, PathBuf) {
        let dir = tempfile::tempdir().unwrap();
        let mut w = TableWriter::create(dir.path(), "summary", summary_cols()).unwrap();
        for (scenario, noise, state, v) in rows {
            w.push(&[
                Value::Str(scenario),
                Value::F64(Some(*noise)),
                Value::Str("kf"),
                Value::F64(Some(1.0)),
                Value::F64(Some(1.0)),
                Value::Str(state),
                Value::F64(Some(*v)),
            ])
            .unwrap();
        }
        let (path, _) = w.commit().unwrap();
        (dir, path)
    }

    #[test]
    fn a_table_with_two_rows_of_one_key_is_refused_when_read() {
        // Rows that differ in any key column are distinct, whatever their values.
        let (_d, ok) = summary_with(&[
            ("a", 1.0, "x", 0.5),
            ("a", 1.0, "y", 0.5),
            ("a", 2.0, "x", 0.5),
            ("b", 1.0, "x", 0.5),
        ]);
        assert_eq!(read(&ok).unwrap().height(), 4);
        // A forged second row of one key: the reader would otherwise keep one of the two.
        let (_d, forged) = summary_with(&[
            ("a", 1.0, "x", 0.5),
            ("a", 1.0, "y", 0.5),
            ("a", 1.0, "x", 0.9),
        ]);
        let err = read(&forged).unwrap_err().to_string();
        assert!(err.contains("rows 0 and 2 have one key"), "{err}");
        assert!(err.contains("state = "), "{err}");
        assert!(err.contains("summary.parquet"), "{err}");
    }

    #[test]
    fn estimates_row_groups_are_bounded_by_values_and_other_tables_by_rows() {
        // The planar quadrotor's estimates: 5 keys and 72 values.
        assert_eq!(rows_per_group("estimates", 77), (1 << 20) / 77);
        assert_eq!(rows_per_group("estimates", 3), FLUSH_ROWS);
        assert_eq!(rows_per_group("traces", 77), FLUSH_ROWS);
    }
}
