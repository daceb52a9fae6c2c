//! Reading estimates, file by file and table by table, into one spill per external filter
//! variant: the stamp, columns and keys of every row checked on the way.

use std::fs::File;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};

use polars::prelude::*;

use crate::error::OutputError;

use super::column_types::{check_arrow_column, check_frame_columns};
use super::columns::{EstimateColumns, detect_columns};
use super::index::KeyIndex;
use super::rows::{BLOCK_ROWS, FileColumns, RowGroup};
use super::{EstimateSet, External, SEED_KEY, STAMP_KEY, StudyKeys, format_err, polars_err};

/// Creates an unlinked scratch file: the data lives while the handle does, and a killed
/// process leaves nothing behind.
fn scratch_file() -> Result<File, OutputError> {
    use std::sync::atomic::{AtomicU64, Ordering};
    static COUNTER: AtomicU64 = AtomicU64::new(0);
    let path = std::env::temp_dir().join(format!(
        ".kfmc-estimates-{}-{}.spill",
        std::process::id(),
        COUNTER.fetch_add(1, Ordering::Relaxed)
    ));
    let io = |source| OutputError::Io {
        action: "cannot create the scratch file",
        path: path.clone(),
        source,
    };
    let file = std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .create_new(true)
        .open(&path)
        .map_err(io)?;
    std::fs::remove_file(&path).map_err(io)?;
    Ok(file)
}

/// Consecutive rows of a block waiting to be written to one external filter's spill, at
/// consecutive spill rows.
struct PendingRows {
    external: usize,
    /// The spill row of the first.
    first_row: u64,
    /// The block row of the first.
    block_row: usize,
    rows: usize,
}

impl PendingRows {
    fn write(
        &self,
        externals: &[External],
        rows: &RowGroup,
        width: usize,
    ) -> Result<(), OutputError> {
        let data = &rows.table[self.block_row * width..(self.block_row + self.rows) * width];
        write_rows(&externals[self.external], self.first_row, data, width)
    }
}

/// An estimate set being read, file by file.
pub(super) struct Reading<'a> {
    keys: KeyIndex<'a>,
    /// Per study filter: index into `externals`, once a file gave a row of it.
    by_filter: Vec<Option<usize>>,
    externals: Vec<External>,
    unstamped: Vec<PathBuf>,
    /// The names of the tables in memory read.
    tables: Vec<PathBuf>,
}

impl<'a> Reading<'a> {
    pub(super) fn new(study: &'a StudyKeys<'a>) -> Self {
        Reading {
            by_filter: vec![None; study.filters.len()],
            keys: KeyIndex::new(study),
            externals: Vec::new(),
            unstamped: Vec::new(),
            tables: Vec::new(),
        }
    }

    /// Reads one file: its stamp and columns, then its row groups into the filters' spills.
    pub(super) fn file(&mut self, path: &PathBuf) -> Result<(), OutputError> {
        let file = crate::output::atomic::open_input(path).map_err(|source| OutputError::Io {
            action: "cannot open",
            path: path.clone(),
            source,
        })?;
        if !crate::output::table::starts_as_parquet(&file) {
            return Err(format_err(
                path,
                "estimates must be Parquet (got a CSV?): the file does not begin with Parquet's `PAR1` marker; `kfmc schema estimates SPEC` lists the columns to write",
            ));
        }
        let mut reader = ParquetReader::new(file);
        let meta = reader
            .get_metadata()
            .map_err(|e| polars_err(path, e))?
            .clone();
        let get = |key: &str| {
            meta.key_value_metadata()
                .iter()
                .flatten()
                .find(|kv| kv.key == key)
                .map(|kv| kv.value.clone().unwrap_or_default())
        };
        if !check_stamp(path, get, self.keys.study)? {
            self.unstamped.push(path.clone());
        }
        let schema = reader.schema().map_err(|e| polars_err(path, e))?;
        let names: Vec<String> = schema.iter_names().map(|n| n.to_string()).collect();
        let study = self.keys.study;
        let columns = FileColumns::new(detect_columns(
            path,
            &names,
            &study.quantities,
            &study.measurements,
            &study.rotations,
        )?);
        // Before a row group is read: polars cannot hold some Arrow types (a decimal or a
        // map column stops it outright), and would convert others.
        for (name, field) in schema.iter() {
            check_arrow_column(path, name, &field.dtype)?;
        }
        let mut offset = 0usize;
        crate::output::table::for_each_row_group(path, |df| {
            self.rows(path, &columns, &df, offset)?;
            offset += df.height();
            Ok(())
        })?;
        Ok(())
    }

    /// Reads a table already in memory, batch by batch as they come, as a file's row groups;
    /// its stamp is looked for in `metadata` as a file's is in its key-value metadata.
    pub(super) fn table(
        &mut self,
        name: &str,
        metadata: &[(String, String)],
        batches: impl IntoIterator<Item = Result<DataFrame, OutputError>>,
    ) -> Result<(), OutputError> {
        let path = PathBuf::from(name);
        self.tables.push(path.clone());
        let get = |key: &str| {
            metadata
                .iter()
                .find(|(k, _)| k == key)
                .map(|(_, v)| v.clone())
        };
        if !check_stamp(&path, get, self.keys.study)? {
            self.unstamped.push(path.clone());
        }
        let mut batches = batches.into_iter();
        let Some(first) = batches.next().transpose()? else {
            return Err(format_err(
                &path,
                "an empty table (no batch, so no columns)",
            ));
        };
        let names: Vec<String> = first
            .get_column_names()
            .iter()
            .map(|n| n.to_string())
            .collect();
        let study = self.keys.study;
        let columns = FileColumns::new(detect_columns(
            &path,
            &names,
            &study.quantities,
            &study.measurements,
            &study.rotations,
        )?);
        check_frame_columns(&path, &first)?;
        self.rows(&path, &columns, &first, 0)?;
        let mut offset = first.height();
        drop(first);
        for df in batches {
            let df = df?;
            check_frame_columns(&path, &df)?;
            self.rows(&path, &columns, &df, offset)?;
            offset += df.height();
        }
        Ok(())
    }

    /// Reads one row group of a file or one batch of a table (whose first row is row
    /// `first_row` of the file or table), block by block ([`BLOCK_ROWS`]).
    fn rows(
        &mut self,
        path: &PathBuf,
        columns: &FileColumns,
        df: &DataFrame,
        first_row: usize,
    ) -> Result<(), OutputError> {
        let mut at = 0;
        while at < df.height() {
            let n = BLOCK_ROWS.min(df.height() - at);
            let block = df.slice(at as i64, n);
            let rows = RowGroup::new(path, &block, first_row + at, columns)?;
            self.row_group(path, columns, &rows)?;
            at += n;
        }
        Ok(())
    }

    /// Checks every row of a block against the study's keys and writes its values.
    fn row_group(
        &mut self,
        path: &PathBuf,
        columns: &FileColumns,
        rows: &RowGroup,
    ) -> Result<(), OutputError> {
        let width = columns.width;
        // Consecutive rows of one filter usually land in consecutive spill rows: they are
        // written in one call, straight from the block's rows.
        let mut pending: Option<PendingRows> = None;
        // The last row whose filter and cell were looked up: a row with the same keys has
        // the same filter, external and cell (the lookups hash strings and compare columns).
        let mut last: Option<(usize, usize, (u64, usize))> = None;
        let mut buf = Vec::with_capacity(width);
        for i in 0..rows.filter.len() {
            let (ext, cell) = match last {
                Some((j, ext, cell)) if rows.same_cell_and_filter(i, j) => (ext, cell),
                _ => {
                    let fi = self.keys.filter(path, rows, i)?;
                    let ext = self.external(fi, path, &columns.columns)?;
                    let cell = self.keys.cell(path, rows, i)?;
                    last = Some((i, ext, cell));
                    (ext, cell)
                }
            };
            let row = self.keys.row(path, rows, i, cell)?;
            let e = &mut self.externals[ext];
            let (word, bit) = ((row / 64) as usize, row % 64);
            if e.present[word] & (1 << bit) != 0 {
                return Err(format_err(path, format!("duplicate row {}", rows.key(i))));
            }
            e.present[word] |= 1 << bit;
            if rows.failed.as_ref().is_some_and(|f| f.get(i) == Some(true)) {
                e.failed[word] |= 1 << bit;
            }
            if !rows.row_is_clean(columns, i) {
                // The exact check, for its message.
                columns.values(path, rows, i, &mut buf)?;
            }
            match &mut pending {
                Some(p) if p.external == ext && p.first_row + p.rows as u64 == row => {
                    p.rows += 1;
                }
                _ => {
                    if let Some(p) = pending.take() {
                        p.write(&self.externals, rows, width)?;
                    }
                    pending = Some(PendingRows {
                        external: ext,
                        first_row: row,
                        block_row: i,
                        rows: 1,
                    });
                }
            }
        }
        if let Some(p) = pending.take() {
            p.write(&self.externals, rows, width)?;
        }
        Ok(())
    }

    /// The external of study filter `fi`, made on its first row; every file of one filter
    /// must give the same columns.
    fn external(
        &mut self,
        fi: usize,
        path: &PathBuf,
        columns: &EstimateColumns,
    ) -> Result<usize, OutputError> {
        let ext = match self.by_filter[fi] {
            Some(e) => e,
            None => {
                self.externals.push(External {
                    label: self.keys.study.filters[fi].name(),
                    files: Vec::new(),
                    columns: columns.clone(),
                    spill: scratch_file()?,
                    present: vec![0; self.keys.total.div_ceil(64) as usize],
                    failed: vec![0; self.keys.total.div_ceil(64) as usize],
                });
                self.by_filter[fi] = Some(self.externals.len() - 1);
                self.externals.len() - 1
            }
        };
        let e = &mut self.externals[ext];
        if e.columns != *columns {
            return Err(format_err(
                path,
                format!(
                    "filter {} has other columns here than in {}; give every file of one filter the same columns",
                    e.label,
                    e.files
                        .first()
                        .map_or(String::new(), |p| p.display().to_string())
                ),
            ));
        }
        if !e.files.contains(path) {
            e.files.push(path.clone());
        }
        Ok(ext)
    }

    /// The set, once every file is read: a run's rows cover every step or none, and every
    /// external filter of the study has rows.
    pub(super) fn finish(self, files: &[PathBuf]) -> Result<EstimateSet, OutputError> {
        let study = self.keys.study;
        for e in &self.externals {
            check_steps(e, study, &self.keys.cells)?;
        }
        if let Some((_, f)) = study
            .filters
            .iter()
            .enumerate()
            .find(|(i, f)| f.external && self.by_filter[*i].is_none())
        {
            return Err(format_err(
                files
                    .first()
                    .map_or(Path::new("--estimates"), |p| p.as_path()),
                format!(
                    "no rows for the external filter {} in any of the estimate files",
                    f.name()
                ),
            ));
        }
        Ok(EstimateSet {
            by_filter: self.by_filter,
            externals: self.externals,
            n_scales: study.noise_scales.len(),
            cells: self.keys.cells,
            runs: study.runs,
            unstamped: self.unstamped,
            tables: self.tables,
        })
    }
}

/// Writes rows to a spill. The spill lives and dies with this process, so its values are
/// in the machine's byte order, written and read back without conversion.
fn write_rows(e: &External, start: u64, data: &[f64], width: usize) -> Result<(), OutputError> {
    e.spill
        .write_all_at(bytemuck::cast_slice(data), start * width as u64 * 8)
        .map_err(|source| OutputError::Io {
            action: "cannot write the scratch file for",
            path: e.files.last().cloned().unwrap_or_default(),
            source,
        })
}

/// Checks a run's rows of one external filter cover every step or none: a run with some
/// steps missing is an error naming the file, the cell, the run and the first missing step.
/// (A run with no rows at all is left for the runs' status: the study counts it missing.)
fn check_steps(
    e: &External,
    study: &StudyKeys<'_>,
    cells: &[(u64, usize)],
) -> Result<(), OutputError> {
    let n_scales = study.noise_scales.len();
    let has = |row: u64| e.present[(row / 64) as usize] & (1 << (row % 64)) != 0;
    for (ci, &(base, samples)) in cells.iter().enumerate() {
        for r in 0..study.runs as u64 {
            let first = base + r * samples as u64;
            let given = (0..samples as u64).filter(|k| has(first + k)).count();
            if given == 0 || given == samples {
                continue;
            }
            let k = (0..samples as u64)
                .find(|k| !has(first + k))
                .expect("a step is missing");
            let path = e
                .files
                .first()
                .map_or(Path::new("--estimates"), |p| p.as_path());
            return Err(format_err(
                path,
                format!(
                    "filter {}, scenario = {:?}, noise_scale = {}, run = {r}: no row for step {k} ({given} of its {samples} steps 0..={} are given); a run's rows cover every step from 0, the prior, or the run is left out whole{}",
                    e.label,
                    study.scenarios[ci / n_scales].0,
                    study.noise_scales[ci % n_scales],
                    samples - 1,
                    if e.files.len() > 1 {
                        format!(" (rows of {} read from {} files)", e.label, e.files.len())
                    } else {
                        String::new()
                    }
                ),
            ));
        }
    }
    Ok(())
}

/// Checks a file's or a table's stamp (its metadata, looked up by `get`) against the
/// study's world: returns whether it is stamped (carries `kfmc.world_stamp`), and refuses
/// one whose stamp or master seed names another simulation, saying which.
fn check_stamp(
    path: &Path,
    get: impl Fn(&str) -> Option<String>,
    study: &StudyKeys<'_>,
) -> Result<bool, OutputError> {
    let (stamp, seed) = (get(STAMP_KEY), get(SEED_KEY));
    let ours = &study.world_stamp;
    let foreign = stamp.as_ref().is_some_and(|s| s != ours)
        || seed
            .as_ref()
            .is_some_and(|s| *s != study.master_seed.to_string());
    if foreign {
        let theirs: Vec<String> = [(STAMP_KEY, &stamp), (SEED_KEY, &seed)]
            .into_iter()
            .filter_map(|(k, v)| v.as_ref().map(|v| format!("{k} = {v}")))
            .collect();
        return Err(format_err(
            path,
            format!(
                "these estimates were made on another simulation: the file belongs to the world {}, this study simulates world {ours} with master seed {} (experiment `{}`); score them against the simulation they were made from, or estimate again from this study's `kfmc simulate` tables",
                theirs.join(", "),
                study.master_seed,
                study.experiment
            ),
        ));
    }
    Ok(stamp.is_some())
}
