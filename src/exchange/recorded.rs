//! Tables kfmc did not simulate, keyed as `kfmc simulate` keys its own: a user's truth
//! (`truth_<q>` columns) or measurements (`z_<component>`, `u_<input>`), one row per
//! (`scenario`, `noise_scale`, `run`, `step`) with its time `t`.
//!
//! One reader serves every such table: the caller says which value columns it expects
//! ([`ValueGroup`]: a prefix, the names the spec declares, whether null is allowed) and
//! which keys exist ([`RecordedKeys`]: the spec's scenarios with their K, noise scales and
//! runs). The reader refuses, naming the file (or table) and the column or key, a column of
//! the wrong type, a value column the spec does not declare, a declared one that is absent,
//! a key outside the declared ones, a duplicate row, a null where nulls are not allowed, and
//! a run with some of its steps missing; a run left out whole is **missing**
//! ([`RecordedTable::missing_runs`]), as a run an outside filter's estimates leave out is.
//!
//! The rows are held in memory, (K + 1) × width f64 per run (a 1,000-run × 1,000-step table
//! of 4 quantities is 32 MB), in key order, whatever the file's row order.
//!
//! [`RecordedTable::content_hash`] hashes the keys, `t` and the declared values in key order,
//! never the file's bytes: the same data in another row order, row grouping, compression or
//! float width (float32 values are read as f64, exactly) has the same hash; one changed value
//! gives another. A recorded study's estimates carry it as their world stamp.

use std::path::{Path, PathBuf};

use polars::prelude::*;

use crate::error::OutputError;
use crate::score::format_err;

/// The key columns, in `kfmc simulate`'s order; `t` follows them.
pub const KEY_COLUMNS: [&str; 4] = ["scenario", "noise_scale", "run", "step"];

/// The time column (seconds); hashed, not checked against step · Δt (real runs need not be
/// evenly sampled).
pub const TIME_COLUMN: &str = "t";

/// One group of value columns a table holds: `<prefix><name>` for every declared name.
#[derive(Clone, Debug, PartialEq)]
pub struct ValueGroup {
    /// The column prefix (`truth_`, `z_`, `u_`).
    pub prefix: String,
    /// The declared names, in the spec's order.
    pub names: Vec<String>,
    /// Whether null means something (a sensor that did not report); otherwise a null or
    /// non-finite value is an error.
    pub nullable: bool,
    /// What the names are, for messages (`quantity`, `measurement component`).
    pub what: String,
}

impl ValueGroup {
    /// The truth of the evaluated quantities: `truth_<q>`, never null.
    pub fn truth(quantities: &[&str]) -> Self {
        ValueGroup {
            prefix: "truth_".into(),
            names: quantities.iter().map(|s| s.to_string()).collect(),
            nullable: false,
            what: "quantity".into(),
        }
    }

    /// The measurements: `z_<component>`, null where the component did not report.
    pub fn measurements(components: &[&str]) -> Self {
        ValueGroup {
            prefix: "z_".into(),
            names: components.iter().map(|s| s.to_string()).collect(),
            nullable: true,
            what: "measurement component".into(),
        }
    }

    /// The inputs: `u_<input>`, never null.
    pub fn inputs(inputs: &[&str]) -> Self {
        ValueGroup {
            prefix: "u_".into(),
            names: inputs.iter().map(|s| s.to_string()).collect(),
            nullable: false,
            what: "input".into(),
        }
    }
}

/// Which rows and columns a table may hold.
#[derive(Clone, Debug, PartialEq)]
pub struct RecordedKeys {
    /// What the table is, for messages (`truth`, `measurements`).
    pub table: String,
    /// (name, transitions K) of each scenario, in spec order.
    pub scenarios: Vec<(String, usize)>,
    /// The noise multipliers, ascending.
    pub noise_scales: Vec<f64>,
    /// Runs per cell.
    pub runs: usize,
    /// The value columns, in order.
    pub groups: Vec<ValueGroup>,
    /// Prefixes of columns read past without a look (`world_` of `kfmc simulate`'s truth).
    pub ignored_prefixes: Vec<String>,
}

impl RecordedKeys {
    fn width(&self) -> usize {
        self.groups.iter().map(|g| g.names.len()).sum()
    }

    /// The value columns, in storage order.
    pub fn value_columns(&self) -> Vec<String> {
        self.groups
            .iter()
            .flat_map(|g| g.names.iter().map(move |n| format!("{}{n}", g.prefix)))
            .collect()
    }

    fn cells(&self) -> usize {
        self.scenarios.len() * self.noise_scales.len()
    }

    fn samples(&self, cell: usize) -> usize {
        self.scenarios[cell / self.noise_scales.len()].1 + 1
    }

    fn cell_name(&self, cell: usize) -> String {
        let s = self.noise_scales.len();
        format!(
            "scenario = {:?}, noise_scale = {}",
            self.scenarios[cell / s].0,
            self.noise_scales[cell % s]
        )
    }
}

/// A table being read, file by file or batch by batch.
#[derive(Debug)]
pub struct RecordedReader {
    keys: RecordedKeys,
    /// Per cell: the first row index.
    bases: Vec<usize>,
    values: Vec<f64>,
    t: Vec<f64>,
    present: Vec<bool>,
    sources: Vec<PathBuf>,
}

impl RecordedReader {
    /// A reader for tables of `keys`.
    pub fn new(keys: RecordedKeys) -> Self {
        let mut bases = Vec::with_capacity(keys.cells());
        let mut total = 0;
        for c in 0..keys.cells() {
            bases.push(total);
            total += keys.runs * keys.samples(c);
        }
        RecordedReader {
            values: vec![f64::NAN; total * keys.width()],
            t: vec![f64::NAN; total],
            present: vec![false; total],
            bases,
            sources: Vec::new(),
            keys,
        }
    }

    /// Reads a Parquet file row group by row group.
    pub fn file(&mut self, path: &Path) -> Result<(), OutputError> {
        let file = crate::output::atomic::open_input(path).map_err(|source| OutputError::Io {
            action: "cannot open",
            path: path.to_path_buf(),
            source,
        })?;
        if !crate::output::table::starts_as_parquet(&file) {
            return Err(format_err(
                path,
                format!(
                    "the {} table must be Parquet (got a CSV?): the file does not begin with Parquet's `PAR1` marker",
                    self.keys.table
                ),
            ));
        }
        let mut reader = ParquetReader::new(file);
        let schema = reader.schema().map_err(|source| OutputError::Polars {
            action: "cannot read",
            path: path.to_path_buf(),
            source,
        })?;
        let names: Vec<String> = schema.iter_names().map(|n| n.to_string()).collect();
        self.columns(path, &names)?;
        for (name, field) in schema.iter() {
            crate::score::check_arrow_column(path, name, &field.dtype)?;
        }
        self.sources.push(path.to_path_buf());
        crate::output::table::for_each_row_group(path, |df| self.rows(path, &df))?;
        Ok(())
    }

    /// Reads a table in memory (a Python user's DataFrame), named `name` in messages.
    pub fn frame(&mut self, name: &str, df: &DataFrame) -> Result<(), OutputError> {
        let path = PathBuf::from(name);
        let names: Vec<String> = df
            .get_column_names()
            .iter()
            .map(|n| n.to_string())
            .collect();
        self.columns(&path, &names)?;
        crate::score::check_frame_columns(&path, df)?;
        self.sources.push(path.clone());
        self.rows(&path, df)
    }

    /// Refuses a table without a key or a declared value column, or with a column the spec
    /// does not declare.
    fn columns(&self, path: &Path, names: &[String]) -> Result<(), OutputError> {
        let k = &self.keys;
        for key in KEY_COLUMNS.iter().chain([&TIME_COLUMN]) {
            if !names.iter().any(|n| n == key) {
                return Err(format_err(
                    path,
                    format!(
                        "missing column `{key}`: a {} table has the keys scenario, noise_scale, run, step and the time t, as `kfmc simulate` writes them",
                        k.table
                    ),
                ));
            }
        }
        for g in &k.groups {
            for n in &g.names {
                let col = format!("{}{n}", g.prefix);
                if !names.contains(&col) {
                    return Err(format_err(
                        path,
                        format!(
                            "missing column `{col}`: the spec declares the {} `{n}`",
                            g.what
                        ),
                    ));
                }
            }
        }
        for n in names {
            if KEY_COLUMNS.contains(&n.as_str())
                || n == TIME_COLUMN
                || k.ignored_prefixes.iter().any(|p| n.starts_with(p.as_str()))
            {
                continue;
            }
            let group = k.groups.iter().find(|g| n.starts_with(g.prefix.as_str()));
            let declared =
                group.is_some_and(|g| g.names.iter().any(|q| **n == format!("{}{q}", g.prefix)));
            if declared {
                continue;
            }
            let why = match group {
                Some(g) => format!(
                    "the spec declares no {} `{}` (declared: {})",
                    g.what,
                    &n[g.prefix.len()..],
                    g.names.join(", ")
                ),
                None => format!(
                    "a {} table holds the keys, t and {}",
                    k.table,
                    k.groups
                        .iter()
                        .map(|g| format!("{}<{}>", g.prefix, g.what))
                        .collect::<Vec<_>>()
                        .join(", ")
                ),
            };
            return Err(format_err(path, format!("unexpected column `{n}`: {why}")));
        }
        Ok(())
    }

    fn rows(&mut self, path: &Path, df: &DataFrame) -> Result<(), OutputError> {
        let frame = crate::score::FrameColumns { path, df };
        let floats = |name: &str| frame.floats(name);
        let ints = |name: &str| frame.ints(name);
        let scenario = frame.strings("scenario")?;
        let (noise, run, step, t) = (
            floats("noise_scale")?,
            ints("run")?,
            ints("step")?,
            floats(TIME_COLUMN)?,
        );
        let columns = self.keys.value_columns();
        let nullable: Vec<bool> = (self.keys.groups.iter())
            .flat_map(|g| g.names.iter().map(|_| g.nullable))
            .collect();
        let values: Vec<Float64Chunked> = columns
            .iter()
            .map(|c| floats(c))
            .collect::<Result<_, _>>()?;
        let width = columns.len();
        let k = &self.keys;
        let mut last: Option<(String, u64, usize)> = None;
        for i in 0..df.height() {
            let key = || {
                format!(
                    "scenario = {}, noise_scale = {}, run = {}, step = {}",
                    scenario.get(i).map_or("null".into(), |s| format!("{s:?}")),
                    noise.get(i).map_or("null".into(), |v| v.to_string()),
                    run.get(i).map_or("null".into(), |v| v.to_string()),
                    step.get(i).map_or("null".into(), |v| v.to_string()),
                )
            };
            let bad = |column: &str, why: String| {
                format_err(path, format!("column `{column}`: {why} at {}", key()))
            };
            let (Some(s), Some(ns)) = (scenario.get(i), noise.get(i)) else {
                return Err(bad("scenario", "a null key".into()));
            };
            let cell = match &last {
                Some((ls, lb, c)) if ls == s && *lb == ns.to_bits() => *c,
                _ => {
                    let Some(si) = k.scenarios.iter().position(|(n, _)| n == s) else {
                        return Err(bad(
                            "scenario",
                            format!(
                                "`{s}` is not a scenario of the spec (declared: {}; a spec without [[scenarios]] has the one scenario `recorded`)",
                                k.scenarios
                                    .iter()
                                    .map(|(n, _)| n.as_str())
                                    .collect::<Vec<_>>()
                                    .join(", ")
                            ),
                        ));
                    };
                    let Some(ni) = k.noise_scales.iter().position(|v| *v == ns) else {
                        return Err(bad(
                            "noise_scale",
                            format!(
                                "{ns} is not a noise scale of the spec (declared: {:?}; default [1.0])",
                                k.noise_scales
                            ),
                        ));
                    };
                    let c = si * k.noise_scales.len() + ni;
                    last = Some((s.to_string(), ns.to_bits(), c));
                    c
                }
            };
            let samples = k.samples(cell);
            let r = match run.get(i) {
                Some(r) if r >= 0 && (r as u64) < k.runs as u64 => r as usize,
                _ => {
                    return Err(bad(
                        "run",
                        format!("outside 0..{} (the spec's `runs` = {})", k.runs, k.runs),
                    ));
                }
            };
            let st = match step.get(i) {
                Some(st) if st >= 0 && (st as u64) < samples as u64 => st as usize,
                _ => {
                    return Err(bad(
                        "step",
                        format!(
                            "outside 0..={} (the spec's K for {})",
                            samples - 1,
                            k.cell_name(cell)
                        ),
                    ));
                }
            };
            let row = self.bases[cell] + r * samples + st;
            if self.present[row] {
                return Err(format_err(path, format!("duplicate row {}", key())));
            }
            self.present[row] = true;
            self.t[row] = match t.get(i) {
                Some(v) if v.is_finite() => v,
                other => {
                    return Err(bad(
                        TIME_COLUMN,
                        format!(
                            "{} (t must be a finite number)",
                            other.map_or("null".into(), |v| v.to_string())
                        ),
                    ));
                }
            };
            for (j, c) in values.iter().enumerate() {
                let v = c.get(i);
                match v {
                    Some(v) if v.is_finite() => self.values[row * width + j] = v,
                    None if nullable[j] => {}
                    _ => {
                        return Err(bad(
                            &columns[j],
                            format!(
                                "{} ({})",
                                v.map_or("null".into(), |v| v.to_string()),
                                if nullable[j] {
                                    "null means did not report; NaN or infinite is an error"
                                } else {
                                    "every value must be a finite number"
                                }
                            ),
                        ));
                    }
                }
            }
        }
        Ok(())
    }

    /// The table, once every source is read: a run's rows cover every step 0..=K or none.
    pub fn finish(self) -> Result<RecordedTable, OutputError> {
        let k = &self.keys;
        let name = self
            .sources
            .first()
            .cloned()
            .unwrap_or_else(|| PathBuf::from(format!("--{}", k.table)));
        for c in 0..k.cells() {
            let samples = k.samples(c);
            for r in 0..k.runs {
                let first = self.bases[c] + r * samples;
                let given = self.present[first..first + samples]
                    .iter()
                    .filter(|p| **p)
                    .count();
                if given == 0 || given == samples {
                    continue;
                }
                let step = (0..samples)
                    .find(|s| !self.present[first + s])
                    .unwrap_or_default();
                return Err(format_err(
                    &name,
                    format!(
                        "{}, run = {r}: no row for step {step} ({given} of its {samples} steps 0..={} are given); a run's rows cover every step from 0, or the run is left out whole (the spec's K of the scenario is its `steps`)",
                        k.cell_name(c),
                        samples - 1
                    ),
                ));
            }
        }
        if !self.present.iter().any(|p| *p) {
            return Err(format_err(
                &name,
                format!("the {} table has no rows", k.table),
            ));
        }
        Ok(RecordedTable {
            keys: self.keys,
            bases: self.bases,
            values: self.values,
            t: self.t,
            present: self.present,
            sources: self.sources,
        })
    }
}

/// A table read and checked ([`RecordedReader`]).
#[derive(Debug)]
pub struct RecordedTable {
    keys: RecordedKeys,
    bases: Vec<usize>,
    values: Vec<f64>,
    t: Vec<f64>,
    present: Vec<bool>,
    sources: Vec<PathBuf>,
}

/// One run's rows: `values` row-major, `width` per step, NaN where null.
#[derive(Clone, Copy, Debug)]
pub struct RecordedRun<'a> {
    /// The values of steps 0..=K, [`RecordedKeys::value_columns`] per step.
    pub values: &'a [f64],
    /// t of steps 0..=K.
    pub t: &'a [f64],
    /// Values per step.
    pub width: usize,
}

impl RecordedTable {
    /// Reads `files` and then the tables in memory `frames` (name, rows) for `keys`.
    pub fn read(
        keys: RecordedKeys,
        files: &[PathBuf],
        frames: &[(String, DataFrame)],
    ) -> Result<Self, OutputError> {
        let mut reader = RecordedReader::new(keys);
        for f in files {
            reader.file(f)?;
        }
        for (name, df) in frames {
            reader.frame(name, df)?;
        }
        reader.finish()
    }

    /// What the table was read for.
    pub fn keys(&self) -> &RecordedKeys {
        &self.keys
    }

    /// The files (or tables' names) it was read from.
    pub fn sources(&self) -> &[PathBuf] {
        &self.sources
    }

    /// Run `run` of cell `cell` (scenario-major, as the spec orders them), or `None` when the
    /// table leaves it out.
    pub fn run(&self, cell: usize, run: usize) -> Option<RecordedRun<'_>> {
        let samples = self.keys.samples(cell);
        let first = self.bases[cell] + run * samples;
        let width = self.keys.width();
        self.present[first].then(|| RecordedRun {
            values: &self.values[first * width..(first + samples) * width],
            t: &self.t[first..first + samples],
            width,
        })
    }

    /// The runs left out whole: (cell, run), cells scenario-major.
    pub fn missing_runs(&self) -> Vec<(usize, usize)> {
        let k = &self.keys;
        (0..k.cells())
            .flat_map(|c| (0..k.runs).map(move |r| (c, r)))
            .filter(|&(c, r)| !self.present[self.bases[c] + r * k.samples(c)])
            .collect()
    }

    /// 16 hex digits: FNV-1a 64 of the declared value columns' names and, in key order, every
    /// row's keys, t and values (null as one fixed pattern). Independent of the row order,
    /// row groups, compression and float width of the files; changed by any value.
    pub fn content_hash(&self) -> String {
        let mut h = crate::hash::Fnv1a::new();
        h.write(format!("kfmc recorded 1\n{}\n", self.keys.table).as_bytes());
        for c in self.keys.value_columns() {
            h.write(c.as_bytes());
            h.write(b"\n");
        }
        let width = self.keys.width();
        let s = self.keys.noise_scales.len();
        for c in 0..self.keys.cells() {
            let samples = self.keys.samples(c);
            let scenario = &self.keys.scenarios[c / s].0;
            let noise = self.keys.noise_scales[c % s];
            for r in 0..self.keys.runs {
                for step in 0..samples {
                    let row = self.bases[c] + r * samples + step;
                    if !self.present[row] {
                        continue;
                    }
                    h.write(scenario.as_bytes());
                    h.write(&[0]);
                    h.write(&noise.to_bits().to_le_bytes());
                    h.write(&(r as u64).to_le_bytes());
                    h.write(&(step as u64).to_le_bytes());
                    h.write(&self.t[row].to_bits().to_le_bytes());
                    for v in &self.values[row * width..(row + 1) * width] {
                        // Null is stored as NaN; every NaN hashes alike.
                        let bits = if v.is_nan() { u64::MAX } else { v.to_bits() };
                        h.write(&bits.to_le_bytes());
                    }
                }
            }
        }
        format!("{:016x}", h.finish())
    }
}
