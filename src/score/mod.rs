//! Estimates from outside kfmc: the exchange format that `kfmc score` and `kfmc check
//! --estimates` read, and the replay that turns its rows into the very filter records an
//! in-process filter produces.
//!
//! An estimates file has one row per (scenario, noise scale, run, step) and filter label:
//!
//! | column | meaning |
//! |---|---|
//! | `scenario`, `noise_scale`, `run`, `step` | the keys of `kfmc simulate`'s tables (integers are never matched by time) |
//! | `filter` | the label of a `[[filters]]` entry with `kind = "external"` |
//! | `failed` | optional, boolean: true from the step at which the filter failed on; the run counts as a numerical failure there (null: false) |
//! | `est_<q>` | the estimate of every evaluated quantity q |
//! | `P_<qi>_<qj>` | its covariance, lower triangle (qi at or after qj in the quantity order), or |
//! | `L_<i>_<j>` | a lower Cholesky factor of it (0-based indices, i ≥ j), or |
//! | `var_<q>`, `corr_<qi>_<qj>` | its diagonal and the correlations below it (qi after qj) |
//! | `nu_<z>`, `S_<zi>_<zj>` | optional: the innovation (null where z did not report) and its covariance, lower triangle: enable the NIS and whiteness tests |
//! | `A_<qi>_<qj>` | optional: the error transition (row qi, column qj): enables the calibrated NEES verdict |
//!
//! The error convention is e = truth − estimate, angle quantities wrapped; a rotation's
//! quantities (a [`crate::linalg::so3::EulerRotation`] of the study's layout) are scored by the
//! rotation error. Such a rotation is given either as its Euler angles `est_<q>` with their
//! covariance (as for any quantity: kfmc maps it into the rotation error's tangent space by
//! the chart Jacobian at the estimate), or, as kfmc writes it, as a unit quaternion
//! `quat_<q1>_<q2>_<q3>_w|x|y|z` in place of the three `est_` columns, and then its rows and
//! columns of the covariance are the rotation error's, in the quantities' unit.
//!
//! The file's stamp is two file-level metadata keys: `kfmc.world_stamp` (the study's
//! [`crate::experiment::Plan::world_stamp`], the hash of everything that makes run i's truth, measurements and
//! prior) and `kfmc.master_seed`. kfmc writes both into every estimates file; a file whose
//! keys name another world is refused, naming the simulation it belongs to, and a file
//! without a stamp is read but reported ([`EstimateSet::unstamped`]) for `kfmc score` to warn
//! and `kfmc check` to refuse. A table in memory is held to the same rule through its
//! metadata (an Arrow schema's: a pyarrow Table read from a stamped file keeps the stamp).
//!
//! A file gives the covariance in one of the three forms ([`CovarianceForm`]); one with
//! columns of two forms is refused, naming a column of each. Value columns may be float32
//! (or any float or integer type): they are read as f64, exactly.
//!
//! A run's rows cover every step 0..=K or none (a run left out): a run with some steps
//! missing, or a step outside 0..=K, is an error naming the run and the step, raised before
//! anything is scored. A run left out is **missing** (status `missing` in `runs.parquet`):
//! no statistic counts it, and a case judged on the runs the spec declares is incomplete
//! without it, whatever `check.max_failed_runs` allows. A run the filter failed on is
//! **failed**: its rows say so in the `failed` column (true from the failing step on, where
//! the estimate may be null), and only such runs count against `check.max_failed_runs`. So is a NaN or infinite innovation or error-transition entry: null
//! there means "not given", never NaN.
//!
//! Reading streams the files row group by row group into one fixed-width spill file per
//! external filter (unlinked at once, so nothing is left behind even after a kill), indexed
//! by its keys; each run then reads its rows back with one positioned read. Memory stays
//! bounded by a row group, whatever the file's order and size.

use std::fs::File;
use std::path::{Path, PathBuf};

use polars::prelude::*;

use crate::error::OutputError;
use crate::linalg::so3::EulerRotation;

mod column_types;
mod columns;
mod frame;
mod index;
mod reading;
mod replay;
mod rotation;
mod rows;

pub use column_types::{check_arrow_column, check_frame_columns};
pub use columns::{
    CovarianceForm, EstimateColumns, EstimatePrecision, covariance_forms_text, estimate_columns,
    estimate_columns_in, estimate_columns_with, key_columns,
};
pub(crate) use frame::FrameColumns;
use reading::Reading;
pub use replay::{Unmodelled, replay};
pub use rotation::quaternion_columns;

/// Version of the exchange format (`truth`, `measurements`, `initial`, estimates).
pub const SCHEMA_VERSION: u32 = 1;

/// The error convention every table uses, written into the simulation manifest.
pub const ERROR_CONVENTION: &str = "e = truth - estimate; angle quantities wrapped";

/// The metadata key of an estimates file's world stamp ([`crate::experiment::Plan::world_stamp`]).
pub const STAMP_KEY: &str = "kfmc.world_stamp";

/// The metadata key of the master seed the file's runs were simulated with.
pub const SEED_KEY: &str = "kfmc.master_seed";

/// The stamp an estimates file made from the runs of a study carries: its two metadata keys
/// and their values, for the study's world stamp and master seed.
pub fn stamp_metadata(world_stamp: &str, master_seed: u64) -> Vec<(String, String)> {
    vec![
        (STAMP_KEY.into(), world_stamp.to_string()),
        (SEED_KEY.into(), master_seed.to_string()),
    ]
}

/// What reading estimates needs of the study they are scored in: the keys their rows may
/// take and the world the files must belong to. The experiment layer makes it from a plan.
#[derive(Clone, Debug)]
pub struct StudyKeys<'a> {
    /// The experiment's name (for messages).
    pub experiment: &'a str,
    /// The study's world stamp: a file stamped with another is refused.
    pub world_stamp: String,
    /// The study's master seed: a file recording another is refused.
    pub master_seed: u64,
    /// The evaluated quantities, in order.
    pub quantities: Vec<&'a str>,
    /// The measurement components, in order.
    pub measurements: Vec<&'a str>,
    /// The rotations among the quantities ([`crate::linalg::so3::EulerRotation`]): a file may
    /// give each as a quaternion instead of its three Euler angles.
    pub rotations: Vec<EulerRotation>,
    /// (name, transitions K) of each scenario, in study order.
    pub scenarios: Vec<(&'a str, usize)>,
    /// The truth-noise multipliers, ascending.
    pub noise_scales: &'a [f64],
    /// Runs per cell.
    pub runs: usize,
    /// Each filter variant, in study order.
    pub filters: Vec<StudyFilter<'a>>,
}

/// A filter variant of the study, as reading estimates sees it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StudyFilter<'a> {
    /// Its label (the `filter` column).
    pub label: &'a str,
    /// Whether it is outside kfmc (`kind = "external"`): only those are read from files.
    pub external: bool,
    /// Its (q_scale, r_scale) as the tables key it; `None` for an external filter that
    /// declares no variants.
    pub multipliers: Option<(f64, f64)>,
    /// Whether an external filter's entry lists `q_scale`: its estimates then carry a
    /// `q_scale` column naming each row's variant.
    pub q_column: bool,
    /// Whether it lists `r_scale`, and its estimates carry an `r_scale` column.
    pub r_column: bool,
}

impl StudyFilter<'_> {
    /// The variant as messages name it: `` `mine` `` or `` `mine` (q_scale = 2) ``, with the
    /// multipliers its estimates name.
    pub fn name(&self) -> String {
        let (q, r) = self.multipliers.unzip();
        let mut parts = Vec::new();
        if let (true, Some(q)) = (self.q_column, q) {
            parts.push(format!("q_scale = {q}"));
        }
        if let (true, Some(r)) = (self.r_column, r) {
            parts.push(format!("r_scale = {r}"));
        }
        if parts.is_empty() {
            format!("`{}`", self.label)
        } else {
            format!("`{}` ({})", self.label, parts.join(", "))
        }
    }
}

/// The optional key columns of an estimates file: the multipliers naming the variant of a
/// filter that declares `q_scale` or `r_scale` variants in the spec.
pub const VARIANT_COLUMNS: [&str; 2] = ["q_scale", "r_scale"];

/// The optional boolean column of an estimates file that marks a failed run: true on the
/// rows from the step at which the filter failed (its estimate there may be null), false or
/// null before. A run marked failed is a numerical failure at its first marked step; a run
/// with no rows at all is missing, never a failure.
pub const FAILED_COLUMN: &str = "failed";

/// One external filter variant's estimates, spilled to a fixed-width file indexed by its
/// keys.
#[derive(Debug)]
struct External {
    /// The variant as messages name it ([`StudyFilter::name`]).
    label: String,
    files: Vec<PathBuf>,
    columns: EstimateColumns,
    spill: File,
    /// One bit per (cell, run, step) row: whether a file gave it.
    present: Vec<u64>,
    /// One bit per row: whether its `failed` flag is true.
    failed: Vec<u64>,
}

/// The estimates of a plan's external filters, read and checked.
#[derive(Debug)]
pub struct EstimateSet {
    /// Per plan filter: index into `externals`.
    by_filter: Vec<Option<usize>>,
    externals: Vec<External>,
    /// Per cell (scenario-major): the first row index and the samples K + 1 per run.
    cells: Vec<(u64, usize)>,
    /// Noise multipliers per scenario (cells are scenario-major).
    n_scales: usize,
    runs: usize,
    /// The files and tables read that carry no world stamp.
    unstamped: Vec<PathBuf>,
    /// The names of the tables in memory read.
    tables: Vec<PathBuf>,
}

/// A table that breaks the format: `path` and what is wrong with it. Shared with the reader of
/// other recorded tables ([`crate::exchange::recorded`]).
pub(crate) fn format_err(path: &Path, message: impl Into<String>) -> OutputError {
    OutputError::Format {
        path: path.to_path_buf(),
        message: message.into(),
    }
}

fn polars_err(path: &Path, source: PolarsError) -> OutputError {
    OutputError::Polars {
        action: "cannot read",
        path: path.to_path_buf(),
        source,
    }
}

impl EstimateSet {
    /// Reads `files` for the external filters of a study. File-level trouble (an undeclared
    /// label, a key outside the plan, a duplicate row, a wrong column, a foreign study) is an
    /// error naming the file, the column and the first offending key; missing rows and
    /// non-finite values are left for the runs' status.
    pub fn load(study: &StudyKeys<'_>, files: &[PathBuf]) -> Result<Self, OutputError> {
        Self::load_with_tables(study, files, &[])
    }

    /// [`EstimateSet::load`] with tables already in memory besides the files (read after
    /// them, with the same checks and messages, each named by its [`InMemoryTable::name`]).
    pub fn load_with_tables(
        study: &StudyKeys<'_>,
        files: &[PathBuf],
        tables: &[InMemoryTable],
    ) -> Result<Self, OutputError> {
        let sources = (files.iter().cloned().map(EstimatesSource::File))
            .chain(tables.iter().cloned().map(EstimatesSource::Table))
            .map(Ok);
        Self::load_from(study, sources)
    }

    /// [`EstimateSet::load`] from sources taken one at a time: each is read into the
    /// filters' spills and dropped before the next is asked for, so a producer that makes
    /// its tables as it goes (a filter loop yielding each run's estimates) is never held
    /// whole. An `Err` from the sources ends the reading with that error.
    pub fn load_from(
        study: &StudyKeys<'_>,
        sources: impl IntoIterator<Item = Result<EstimatesSource, OutputError>>,
    ) -> Result<Self, OutputError> {
        let mut reading = Reading::new(study);
        let mut files = Vec::new();
        for source in sources {
            match source? {
                EstimatesSource::File(path) => {
                    reading.file(&path)?;
                    files.push(path);
                }
                EstimatesSource::Table(table) => reading.table(
                    &table.name,
                    &table.metadata,
                    table.batches.iter().cloned().map(Ok),
                )?,
                EstimatesSource::Stream(stream) => {
                    reading.table(&stream.name, &stream.metadata, stream.batches)?
                }
            }
        }
        reading.finish(&files)
    }

    /// Per external filter variant whose estimates leave runs out: those runs are missing
    /// (status `missing`), so a case judged on the declared runs is incomplete.
    pub fn missing_runs(&self) -> Vec<MissingRuns> {
        let mut out = Vec::new();
        for e in &self.externals {
            let has = |row: u64| e.present[(row / 64) as usize] & (1 << (row % 64)) != 0;
            let mut m = MissingRuns {
                filter: e.label.clone(),
                runs: 0,
                of: self.runs * self.cells.len(),
                first: None,
            };
            for (ci, &(base, samples)) in self.cells.iter().enumerate() {
                for r in 0..self.runs {
                    if !has(base + (r * samples) as u64) {
                        m.runs += 1;
                        m.first.get_or_insert((ci, r));
                    }
                }
            }
            if m.runs > 0 {
                out.push(m);
            }
        }
        out
    }

    /// The files and tables read that carry no world stamp (a table by its name): nothing
    /// ties them to this study's runs.
    pub fn unstamped(&self) -> &[PathBuf] {
        &self.unstamped
    }

    /// Whether `name` (of [`EstimateSet::unstamped`]) is a table in memory, not a file.
    pub fn is_table(&self, name: &Path) -> bool {
        self.tables.iter().any(|t| t == name)
    }

    /// The filter variants read (as messages name them, [`StudyFilter::name`]) and the files
    /// each came from.
    pub fn sources(&self) -> Vec<(String, Vec<PathBuf>)> {
        self.externals
            .iter()
            .map(|e| (e.label.clone(), e.files.clone()))
            .collect()
    }

    /// The first external filter variant (as messages name it) whose estimates give run
    /// `run` of cell `cell` (scenario-major), with its first file.
    pub fn gives_run(&self, cell: usize, run: usize) -> Option<(String, PathBuf)> {
        let (base, samples) = *self.cells.get(cell)?;
        let row = base + (run * samples) as u64;
        self.externals
            .iter()
            .find(|e| e.present[(row / 64) as usize] & (1 << (row % 64)) != 0)
            .map(|e| {
                (
                    e.label.clone(),
                    e.files.first().cloned().unwrap_or_default(),
                )
            })
    }

    /// Runs per cell the set was read for.
    pub fn runs(&self) -> usize {
        self.runs
    }
}

/// The runs an external filter variant's estimates leave out ([`EstimateSet::missing_runs`]).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct MissingRuns {
    /// The variant, as messages name it ([`StudyFilter::name`]).
    pub filter: String,
    /// Runs left out, over every cell.
    pub runs: usize,
    /// Runs the study declares for the filter, over every cell.
    pub of: usize,
    /// The first left out: (cell index, scenario-major; run).
    pub first: Option<(usize, usize)>,
}

/// Estimates already in memory (a Python user's DataFrames, read through the Arrow C stream
/// interface): the table's batches in order, and the table's key-value metadata (an Arrow
/// schema's), where its world stamp is looked for as in a file's: a table stamped with
/// another world is refused, and one without a stamp is listed as unstamped
/// ([`EstimateSet::unstamped`]) for `kfmc check` to refuse, as it refuses such a file.
#[derive(Clone, Debug)]
pub struct InMemoryTable {
    /// A name for messages (`<estimates 0>`).
    pub name: String,
    /// The batches, each with the same columns.
    pub batches: Vec<DataFrame>,
    /// The table's metadata (key, value): `kfmc.world_stamp` and `kfmc.master_seed` when
    /// it is stamped.
    pub metadata: Vec<(String, String)>,
}

/// A table in memory whose batches are taken one at a time (a Python user's table read
/// through the Arrow C stream interface): each is read and let go before the next is asked
/// for, as a file's row groups are, so a producer that makes its batches as they are asked
/// for (a database query, a dataset scanner) is never held whole. Its stamp is checked as
/// an [`InMemoryTable`]'s.
pub struct TableStream {
    /// A name for messages (`<estimates 0>`).
    pub name: String,
    /// The batches, each with the same columns; an `Err` ends the reading with it.
    pub batches: Box<dyn Iterator<Item = Result<DataFrame, OutputError>>>,
    /// The table's metadata (key, value), as [`InMemoryTable::metadata`].
    pub metadata: Vec<(String, String)>,
}

impl std::fmt::Debug for TableStream {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("TableStream")
            .field("name", &self.name)
            .finish_non_exhaustive()
    }
}

/// One source of estimates: a Parquet file or a table in memory.
#[derive(Debug)]
pub enum EstimatesSource {
    /// A file (its world stamp is checked).
    File(PathBuf),
    /// A table in memory.
    Table(InMemoryTable),
    /// A table in memory, batch by batch.
    Stream(TableStream),
}
