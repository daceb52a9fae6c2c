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

use std::collections::HashMap;
use std::fs::File;
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};

use polars::prelude::*;

use crate::error::OutputError;
use crate::filter::{Filter, FilterError, Innovation};
use crate::linalg::so3::{self, EulerRotation};
use crate::linalg::{Matrix, SmallCholesky, Vector};
use crate::model::{Availability, Measurement, Model};
use crate::output::schema::{ColumnDef, Dtype, covariance_columns};
use crate::step_loop::{Evaluate, FilterOutput, Prior, RunContext, Unit, run_filter};

mod rotation;
use rotation::euler_columns;
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

/// How an estimates file gives the covariance. Each form has n(n + 1)/2 columns. A Cholesky
/// factor however rounded (to float32, say) still gives a positive semi-definite P = L Lᵀ,
/// and its rounding moves the NEES by about √κ times the rounding where P's entries move it
/// by about κ times (κ the condition number of P's correlation matrix); the correlations are
/// the form people read, σ and ρ.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CovarianceForm {
    /// `P_<qi>_<qj>`, the lower triangle.
    Lower,
    /// `L_<i>_<j>`, a lower Cholesky factor: P = L Lᵀ.
    Cholesky,
    /// `var_<q>`, the diagonal, and `corr_<qi>_<qj>`, the correlations below it:
    /// P_ij = corr_ij √(var_i var_j).
    Correlation,
}

impl CovarianceForm {
    /// The column of entry (i, j), i ≥ j, of the covariance's lower triangle in this form.
    fn column(self, q: &[&str], i: usize, j: usize) -> String {
        match self {
            CovarianceForm::Lower => format!("P_{}_{}", q[i], q[j]),
            CovarianceForm::Cholesky => format!("L_{i}_{j}"),
            CovarianceForm::Correlation if i == j => format!("var_{}", q[i]),
            CovarianceForm::Correlation => format!("corr_{}_{}", q[i], q[j]),
        }
    }

    /// This form's columns for these quantities, in the order of the lower triangle
    /// (row by row): what a file gives in place of the `P_` columns.
    pub fn columns(self, quantities: &[&str]) -> Vec<String> {
        (0..quantities.len())
            .flat_map(|i| (0..=i).map(move |j| (i, j)))
            .map(|(i, j)| self.column(quantities, i, j))
            .collect()
    }

    /// Whether a column name belongs to this form (by its prefix).
    fn owns(self, name: &str) -> bool {
        match self {
            CovarianceForm::Lower => name.starts_with("P_"),
            CovarianceForm::Cholesky => name.starts_with("L_"),
            CovarianceForm::Correlation => name.starts_with("var_") || name.starts_with("corr_"),
        }
    }

    /// Every form.
    pub const ALL: [CovarianceForm; 3] = [
        CovarianceForm::Lower,
        CovarianceForm::Cholesky,
        CovarianceForm::Correlation,
    ];
}

/// The covariance forms and the float32 columns a file may use instead of what
/// [`estimate_columns`] lists, for a study with these quantities: the lines `kfmc schema
/// estimates` prints.
pub fn covariance_forms_text(quantities: &[&str]) -> String {
    let n = quantities.len();
    let list = |form: CovarianceForm| {
        let all = form.columns(quantities);
        if all.len() > 4 {
            format!("{}, {}, …, {}", all[0], all[1], all[all.len() - 1])
        } else {
            all.join(", ")
        }
    };
    format!(
        "\ncovariance, one form per file (n(n+1)/2 = {} columns each):\n  P_<qi>_<qj>: the lower triangle, as listed above\n  L_<i>_<j> (0-based, i >= j): a lower Cholesky factor, P = L L^T: {}\n  var_<q> and corr_<qi>_<qj> (qi after qj): the diagonal and the correlations, P_ij = corr_ij sqrt(var_i var_j): {}\nvalue columns may be float32, read as float64 exactly (keys stay as listed); keep est_ and quat_ float64, since the error truth - estimate needs the estimate's every digit; a float32 L_ still gives a positive semi-definite P = L L^T\n",
        n * (n + 1) / 2,
        list(CovarianceForm::Cholesky),
        list(CovarianceForm::Correlation),
    )
}

/// The columns an estimates file has, beyond the keys.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct EstimateColumns {
    /// Evaluated quantities.
    pub quantities: Vec<String>,
    /// Measurement components.
    pub measurements: Vec<String>,
    /// The covariance form.
    pub covariance: CovarianceForm,
    /// Whether `nu_*` and `S_*` are present.
    pub innovations: bool,
    /// Whether `A_*` is present.
    pub transition: bool,
    /// The rotations given as quaternions (their `est_` columns are formed from them on
    /// reading, and their covariance is already the rotation error's).
    pub quaternions: Vec<EulerRotation>,
}

impl EstimateColumns {
    fn nq(&self) -> usize {
        self.quantities.len()
    }
    fn nz(&self) -> usize {
        self.measurements.len()
    }
    fn ntri(&self) -> usize {
        self.nq() * (self.nq() + 1) / 2
    }
    fn ztri(&self) -> usize {
        self.nz() * (self.nz() + 1) / 2
    }
    /// f64 values per row in the spill file.
    fn width(&self) -> usize {
        self.nq()
            + self.ntri()
            + if self.innovations {
                self.nz() + self.ztri()
            } else {
                0
            }
            + if self.transition {
                self.nq() * self.nq()
            } else {
                0
            }
    }

    /// The columns a file has: [`EstimateColumns::value_columns`] with each quaternion
    /// rotation's three `est_` columns replaced by its four `quat_` ones.
    pub fn file_columns(&self) -> Vec<String> {
        let mut c = self.value_columns();
        for r in self.quaternions.iter().rev() {
            c.splice(
                r.first..r.first + 3,
                quaternion_columns(&self.quantities, r),
            );
        }
        c
    }

    /// The value columns in spill order.
    pub fn value_columns(&self) -> Vec<String> {
        let q: Vec<&str> = self.quantities.iter().map(String::as_str).collect();
        let z: Vec<&str> = self.measurements.iter().map(String::as_str).collect();
        let mut c: Vec<String> = q.iter().map(|n| format!("est_{n}")).collect();
        match self.covariance {
            CovarianceForm::Lower => c.extend(covariance_columns(&q).into_iter().map(|d| d.name)),
            form => {
                for i in 0..q.len() {
                    for j in 0..=i {
                        c.push(form.column(&q, i, j));
                    }
                }
            }
        }
        if self.innovations {
            c.extend(z.iter().map(|n| format!("nu_{n}")));
            for (i, zi) in z.iter().enumerate() {
                for zj in &z[..=i] {
                    c.push(format!("S_{zi}_{zj}"));
                }
            }
        }
        if self.transition {
            for qi in &q {
                for qj in &q {
                    c.push(format!("A_{qi}_{qj}"));
                }
            }
        }
        c
    }
}

/// Every column of an estimates file for a study with these quantities and measurements, in
/// the order `kfmc run --export-estimates` writes them (`kfmc schema estimates`).
pub fn estimate_columns(quantities: &[&str], measurements: &[&str]) -> Vec<ColumnDef> {
    estimate_columns_with(quantities, measurements, &[])
}

/// The precision of the value columns kfmc exports (`kfmc run --export-estimates-precision`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum EstimatePrecision {
    /// Every value column float64 (the default).
    #[default]
    F64,
    /// The covariance, innovation, S and A columns float32, rounded to nearest; the
    /// estimates (`est_`, `quat_`) stay float64, since the error truth − estimate needs
    /// every digit of the estimate. About half the bytes; read back as f64, exactly.
    F32,
}

/// [`estimate_columns`] for a study whose layout has `rotations`: kfmc writes each as a
/// quaternion with the rotation error's covariance.
pub fn estimate_columns_with(
    quantities: &[&str],
    measurements: &[&str],
    rotations: &[EulerRotation],
) -> Vec<ColumnDef> {
    estimate_columns_in(quantities, measurements, rotations, EstimatePrecision::F64)
}

/// [`estimate_columns_with`] in a precision: with [`EstimatePrecision::F32`] every value
/// column but the estimates is float32.
pub fn estimate_columns_in(
    quantities: &[&str],
    measurements: &[&str],
    rotations: &[EulerRotation],
    precision: EstimatePrecision,
) -> Vec<ColumnDef> {
    let cols = EstimateColumns {
        quantities: quantities.iter().map(|s| s.to_string()).collect(),
        measurements: measurements.iter().map(|s| s.to_string()).collect(),
        covariance: CovarianceForm::Lower,
        innovations: true,
        transition: true,
        quaternions: rotations.to_vec(),
    };
    let mut c = key_columns();
    c.push(ColumnDef {
        name: FAILED_COLUMN.into(),
        dtype: Dtype::Bool,
    });
    c.extend(cols.file_columns().into_iter().map(|name| {
        let estimate = name.starts_with("est_") || name.starts_with("quat_");
        let dtype = match precision {
            EstimatePrecision::F32 if !estimate => Dtype::F32,
            _ => Dtype::F64,
        };
        ColumnDef { name, dtype }
    }));
    c
}

/// The key columns of an estimates file.
pub fn key_columns() -> Vec<ColumnDef> {
    [
        ("scenario", Dtype::Str),
        ("noise_scale", Dtype::F64),
        ("run", Dtype::I64),
        ("step", Dtype::I64),
        ("filter", Dtype::Str),
    ]
    .into_iter()
    .map(|(n, dtype)| ColumnDef {
        name: n.into(),
        dtype,
    })
    .collect()
}

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

fn format_err(path: &Path, message: impl Into<String>) -> OutputError {
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

/// Which value columns a file has, checked against the study's layout: every column must be
/// a key or a known value column, and each group complete.
fn detect_columns(
    path: &Path,
    names: &[String],
    quantities: &[&str],
    measurements: &[&str],
    rotations: &[EulerRotation],
) -> Result<EstimateColumns, OutputError> {
    let has = |n: &str| names.iter().any(|c| c == n);
    let owned: Vec<String> = quantities.iter().map(|s| s.to_string()).collect();
    let mut quaternions = Vec::new();
    for r in rotations {
        let quat = quaternion_columns(&owned, r);
        if quat.iter().any(|c| has(c)) {
            if let Some(e) = owned[r.first..r.first + 3]
                .iter()
                .map(|q| format!("est_{q}"))
                .find(|e| has(e))
            {
                return Err(format_err(
                    path,
                    format!(
                        "both `{e}` and `{}`: give the rotation one way, as Euler angles est_* (with their covariance) or as a quaternion quat_* (with the rotation error's covariance)",
                        quat[0]
                    ),
                ));
            }
            quaternions.push(*r);
        }
    }
    let base = |covariance, innovations, transition| EstimateColumns {
        quantities: owned.clone(),
        measurements: measurements.iter().map(|s| s.to_string()).collect(),
        covariance,
        innovations,
        transition,
        quaternions: quaternions.clone(),
    };
    // The first column of each covariance form the file has: one form only.
    let forms: Vec<(CovarianceForm, &String)> = CovarianceForm::ALL
        .into_iter()
        .filter_map(|f| names.iter().find(|c| f.owns(c)).map(|c| (f, c)))
        .collect();
    if let [(_, a), (_, b), ..] = forms[..] {
        return Err(format_err(
            path,
            format!(
                "both `{a}` and `{b}`: give the covariance one way, as the lower triangle P_<qi>_<qj>, a lower Cholesky factor L_<i>_<j>, or the variances var_<q> with the correlations corr_<qi>_<qj>"
            ),
        ));
    }
    let covariance = forms.first().map_or(CovarianceForm::Lower, |(f, _)| *f);
    let innovations = names
        .iter()
        .any(|c| c.starts_with("nu_") || c.starts_with("S_"));
    let transition = names.iter().any(|c| c.starts_with("A_"));
    let cols = base(covariance, innovations, transition);
    let expected = cols.file_columns();
    for k in key_columns() {
        if !has(&k.name) {
            return Err(format_err(path, format!("missing key column `{}`", k.name)));
        }
    }
    for e in &expected {
        if !has(e) {
            return Err(format_err(
                path,
                format!(
                    "missing column `{e}` (the file has {} value columns, this study's format {}; `kfmc schema estimates SPEC` lists them)",
                    names
                        .iter()
                        .filter(|n| !key_columns().iter().any(|k| k.name == **n)
                            && !VARIANT_COLUMNS.contains(&n.as_str())
                            && n.as_str() != FAILED_COLUMN)
                        .count(),
                    expected.len()
                ),
            ));
        }
    }
    let mut keys: Vec<String> = key_columns().into_iter().map(|c| c.name).collect();
    keys.extend(VARIANT_COLUMNS.map(String::from));
    keys.push(FAILED_COLUMN.into());
    if let Some(extra) = names
        .iter()
        .find(|n| !keys.contains(n) && !expected.contains(n))
    {
        return Err(format_err(
            path,
            format!(
                "unexpected column `{extra}` (not a key nor a value column of this study; `kfmc schema estimates SPEC` lists them)"
            ),
        ));
    }
    Ok(cols)
}

/// What a column holds, as far as the estimates format is concerned.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum ColumnClass {
    /// float64, float32.
    Float,
    /// Any integer width, signed or not.
    Integer,
    /// Strings.
    Text,
    /// No values at all (a column of nulls).
    Null,
    /// Booleans (the `failed` column).
    Bool,
    /// Anything else: decimal, map, struct, list, dates, binary, dictionary, …
    Other,
}

/// An Arrow type's class and its name for messages.
fn arrow_class(dtype: &ArrowDataType) -> (ColumnClass, String) {
    use ArrowDataType as A;
    let class = match dtype {
        A::Float32 | A::Float64 => ColumnClass::Float,
        A::Int8 | A::Int16 | A::Int32 | A::Int64 | A::UInt8 | A::UInt16 | A::UInt32 | A::UInt64 => {
            ColumnClass::Integer
        }
        A::Utf8 | A::LargeUtf8 | A::Utf8View => ColumnClass::Text,
        A::Null => ColumnClass::Null,
        A::Boolean => ColumnClass::Bool,
        _ => ColumnClass::Other,
    };
    let name = match dtype {
        A::Boolean => "bool".to_string(),
        A::Int8 => "int8".into(),
        A::Int16 => "int16".into(),
        A::Int32 => "int32".into(),
        A::Int64 => "int64".into(),
        A::UInt8 => "uint8".into(),
        A::UInt16 => "uint16".into(),
        A::UInt32 => "uint32".into(),
        A::UInt64 => "uint64".into(),
        A::Utf8 | A::LargeUtf8 | A::Utf8View => "string".into(),
        A::Float16 => "float16".into(),
        A::Float32 => "float32".into(),
        A::Float64 => "float64".into(),
        A::Decimal(p, s) | A::Decimal32(p, s) | A::Decimal64(p, s) | A::Decimal256(p, s) => {
            format!("decimal({p}, {s})")
        }
        A::Map(..) => "map".into(),
        A::Struct(_) => "struct".into(),
        A::List(_) | A::LargeList(_) | A::FixedSizeList(..) => "list".into(),
        A::Dictionary(..) => "dictionary (categorical)".into(),
        A::Binary | A::LargeBinary | A::BinaryView | A::FixedSizeBinary(_) => "binary".into(),
        A::Extension(e) => format!("extension `{}`", e.name),
        other => format!("{other:?}").to_lowercase(),
    };
    (class, name)
}

/// A polars type's class and its name for messages.
fn polars_class(dtype: &DataType) -> (ColumnClass, String) {
    let class = if dtype.is_float() {
        ColumnClass::Float
    } else if dtype.is_integer() {
        ColumnClass::Integer
    } else if dtype.is_string() {
        ColumnClass::Text
    } else if dtype.is_null() {
        ColumnClass::Null
    } else if dtype.is_bool() {
        ColumnClass::Bool
    } else {
        ColumnClass::Other
    };
    (class, dtype.to_string())
}

/// Refuses a column whose type the estimates format does not take, naming the file, the
/// column and its type. The keys keep their documented types (`scenario` and `filter`
/// strings, `run` and `step` integers, `noise_scale`, `q_scale` and `r_scale` numbers,
/// `failed` bool); a value column is float64 or float32 (or all null): a bool, integer or string there is a
/// writer's mistake that a conversion would hide (`True` scored as 1.0), and a decimal, map
/// or other nested column is not a number at all.
fn check_column_class(
    path: &Path,
    name: &str,
    (class, type_name): (ColumnClass, String),
) -> Result<(), OutputError> {
    use ColumnClass::*;
    let (ok, wanted) = match name {
        "scenario" | "filter" => (matches!(class, Text | Null), "a string column"),
        "run" | "step" => (matches!(class, Integer | Null), "an integer column"),
        "noise_scale" | "q_scale" | "r_scale" => {
            (matches!(class, Float | Integer | Null), "a float64 column")
        }
        FAILED_COLUMN => (matches!(class, Bool | Null), "a bool column"),
        _ => (
            matches!(class, Float | Null),
            "a value column: float64 or float32",
        ),
    };
    if ok {
        return Ok(());
    }
    Err(format_err(
        path,
        format!(
            "column `{name}` holds {type_name} values; it must be {wanted} (kfmc converts no other type; `kfmc schema estimates SPEC` lists the columns and their types)"
        ),
    ))
}

/// Refuses an Arrow column (of a Parquet file's schema, or of a table handed over through
/// the Arrow C stream interface) whose type the estimates format does not take, before any
/// of its values is read, naming `path`, the column and its type: the keys keep their
/// documented types (`scenario` and `filter` strings, `run` and `step` integers,
/// `noise_scale`, `q_scale` and `r_scale` numbers), and a value column is float64 or float32
/// (or all null).
pub fn check_arrow_column(
    path: &Path,
    name: &str,
    dtype: &ArrowDataType,
) -> Result<(), OutputError> {
    check_column_class(path, name, arrow_class(dtype))
}

/// [`check_arrow_column`] for every column of a table already in memory.
fn check_frame_columns(path: &Path, df: &DataFrame) -> Result<(), OutputError> {
    for c in df.columns() {
        check_column_class(path, c.name(), polars_class(c.dtype()))?;
    }
    Ok(())
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

    fn unit_rows(&self, filter: usize, unit: &Unit) -> Option<UnitRows<'_>> {
        let e = &self.externals[self.by_filter.get(filter).copied().flatten()?];
        let (base, samples) = self.cells[unit.scenario * self.n_scales + unit.scale];
        let first = base + (unit.run * samples) as u64;
        let width = e.columns.width();
        let mut values = vec![0f64; samples * width];
        let read = e.spill.read_exact_at(
            bytemuck::cast_slice_mut(&mut values),
            first * width as u64 * 8,
        );
        let bit = |bits: &[u64], k: u64| {
            let row = first + k;
            bits[(row / 64) as usize] & (1 << (row % 64)) != 0
        };
        let present: Vec<bool> = (0..samples as u64).map(|k| bit(&e.present, k)).collect();
        let failed_at = (0..samples as u64)
            .find(|&k| bit(&e.failed, k))
            .map(|k| k as usize);
        // A spill shorter than this run (its last rows never written) reads as absent rows.
        if read.is_err() {
            values.fill(f64::NAN);
            for (k, p) in present.iter().enumerate() {
                let row = &mut values[k * width..(k + 1) * width];
                if *p
                    && e.spill
                        .read_exact_at(
                            bytemuck::cast_slice_mut(row),
                            (first + k as u64) * width as u64 * 8,
                        )
                        .is_err()
                {
                    row.fill(f64::NAN);
                }
            }
        }
        Some(UnitRows {
            columns: &e.columns,
            values,
            present,
            failed_at,
            width,
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

/// A study's keys as indexes: what every row of an estimates file is checked against.
struct KeyIndex<'a> {
    study: &'a StudyKeys<'a>,
    /// External filter label → the study's filter indexes of its variants.
    label_of: HashMap<&'a str, Vec<usize>>,
    scenario_of: HashMap<&'a str, usize>,
    /// A noise multiplier's bits → its index (the values must be the simulation's exactly).
    scale_of: HashMap<u64, usize>,
    /// Per cell (scenario-major): the first row index and the samples K + 1 per run.
    cells: Vec<(u64, usize)>,
    /// Rows of every cell together.
    total: u64,
}

impl<'a> KeyIndex<'a> {
    fn new(study: &'a StudyKeys<'a>) -> Self {
        let n_scales = study.noise_scales.len();
        let mut cells = Vec::with_capacity(study.scenarios.len() * n_scales);
        let mut total = 0u64;
        for &(_, steps) in &study.scenarios {
            for _ in 0..n_scales {
                cells.push((total, steps + 1));
                total += (study.runs * (steps + 1)) as u64;
            }
        }
        KeyIndex {
            label_of: study
                .filters
                .iter()
                .enumerate()
                .filter(|(_, f)| f.external)
                .fold(
                    HashMap::new(),
                    |mut m: HashMap<&str, Vec<usize>>, (i, f)| {
                        m.entry(f.label).or_default().push(i);
                        m
                    },
                ),
            scenario_of: study
                .scenarios
                .iter()
                .enumerate()
                .map(|(i, (name, _))| (*name, i))
                .collect(),
            scale_of: study
                .noise_scales
                .iter()
                .enumerate()
                .map(|(i, s)| (s.to_bits(), i))
                .collect(),
            cells,
            total,
            study,
        }
    }

    /// The study filter index of row `i`'s label, which must be an external filter's, and of
    /// its variant: the `q_scale`/`r_scale` columns name it when the label declares variants.
    fn filter(&self, path: &Path, rows: &RowGroup, i: usize) -> Result<usize, OutputError> {
        let label = rows.filter.get(i).ok_or_else(|| {
            format_err(
                path,
                format!("column `filter`: null at row {}", rows.first_row + i),
            )
        })?;
        let variants = self.label_of.get(label).ok_or_else(|| {
            let declared = self.study.filters.iter().any(|f| f.label == label);
            format_err(
                path,
                if declared {
                    format!(
                        "column `filter`: `{label}` is one of kfmc's filters, not an external one (set kind = \"external\" in the spec to score it from a file) at {}",
                        rows.key(i)
                    )
                } else {
                    format!(
                        "column `filter`: `{label}` is not a filter of the spec; declare it with [[filters]] label = \"{label}\", kind = \"external\" (at {})",
                        rows.key(i)
                    )
                },
            )
        })?;
        self.variant(path, rows, i, label, variants)
    }

    /// Which of `label`'s variants (study filter indexes) row `i` names. A label without
    /// declared variants takes rows whose `q_scale` and `r_scale` are null (or absent); one
    /// with them needs a column for each axis it declares, with one of the declared values
    /// (exactly), and 1 or null on an axis it does not declare.
    fn variant(
        &self,
        path: &Path,
        rows: &RowGroup,
        i: usize,
        label: &str,
        variants: &[usize],
    ) -> Result<usize, OutputError> {
        let first = &self.study.filters[variants[0]];
        let keyed = first.multipliers.is_some();
        let mut want = [1.0f64; 2];
        for (axis, (name, declared, column)) in [
            ("q_scale", first.q_column, rows.q_scale.as_ref()),
            ("r_scale", first.r_column, rows.r_scale.as_ref()),
        ]
        .into_iter()
        .enumerate()
        {
            let of = |f: &StudyFilter| f.multipliers.map_or(1.0, |m| [m.0, m.1][axis]);
            let mut declared_values: Vec<f64> = variants
                .iter()
                .map(|&v| of(&self.study.filters[v]))
                .collect();
            declared_values.sort_by(f64::total_cmp);
            declared_values.dedup();
            let list = declared_values
                .iter()
                .map(|v| v.to_string())
                .collect::<Vec<_>>()
                .join(", ");
            let value = column.and_then(|c| c.get(i));
            match (declared, column, value) {
                (true, None, _) => {
                    return Err(format_err(
                        path,
                        format!(
                            "missing column `{name}`: filter `{label}` declares {name} variants ({name} = {list}) in the spec, so its rows name their variant in a `{name}` column (first row of `{label}`: {})",
                            rows.key(i)
                        ),
                    ));
                }
                (true, Some(_), None) => {
                    return Err(format_err(
                        path,
                        format!(
                            "column `{name}`: null at {}; filter `{label}` declares {name} = {list}, and each of its rows names its variant",
                            rows.key(i)
                        ),
                    ));
                }
                (true, Some(_), Some(v)) => {
                    if !declared_values.iter().any(|d| d.to_bits() == v.to_bits()) {
                        return Err(format_err(
                            path,
                            format!(
                                "column `{name}`: {v} is not a variant of filter `{label}`, which declares {name} = {list} (the values exactly; add {v} to the spec's list to score it) at {}",
                                rows.key(i)
                            ),
                        ));
                    }
                    want[axis] = v;
                }
                (false, _, Some(v)) if !keyed || v != 1.0 => {
                    return Err(format_err(
                        path,
                        format!(
                            "column `{name}`: {v} at {}, but filter `{label}` declares no {name} variants (list {name} = [...] in its [[filters]] entry to score variants; else leave `{name}` null for its rows)",
                            rows.key(i)
                        ),
                    ));
                }
                (false, _, _) => {}
            }
        }
        if !keyed {
            return Ok(variants[0]);
        }
        Ok(variants
            .iter()
            .copied()
            .find(|&v| {
                self.study.filters[v].multipliers.is_some_and(|(q, r)| {
                    q.to_bits() == want[0].to_bits() && r.to_bits() == want[1].to_bits()
                })
            })
            .expect("the variants are every declared (q_scale, r_scale) pair"))
    }

    /// The cell of row `i`'s (scenario, noise scale): its first row index and its samples
    /// K + 1 per run.
    fn cell(&self, path: &Path, rows: &RowGroup, i: usize) -> Result<(u64, usize), OutputError> {
        let si = rows
            .scenario
            .get(i)
            .and_then(|s| self.scenario_of.get(s).copied())
            .ok_or_else(|| {
                format_err(
                    path,
                    format!(
                        "column `scenario`: not a scenario of this study at {}",
                        rows.key(i)
                    ),
                )
            })?;
        let sj = rows
            .noise
            .get(i)
            .and_then(|v| self.scale_of.get(&v.to_bits()).copied())
            .ok_or_else(|| {
                format_err(path, format!("column `noise_scale`: not a noise scale of this study (values must be the simulation's exactly) at {}", rows.key(i)))
            })?;
        Ok(self.cells[si * self.study.noise_scales.len() + sj])
    }

    /// The row index of row `i`'s (run, step) among every cell's rows, in its `cell`
    /// ([`KeyIndex::cell`]).
    fn row(
        &self,
        path: &Path,
        rows: &RowGroup,
        i: usize,
        (base, samples): (u64, usize),
    ) -> Result<u64, OutputError> {
        let runs = self.study.runs;
        let r = rows
            .run
            .get(i)
            .filter(|r| (0..runs as i64).contains(r))
            .ok_or_else(|| {
                format_err(
                    path,
                    format!("column `run`: outside 0..{runs} at {}", rows.key(i)),
                )
            })?;
        let k = rows
            .step
            .get(i)
            .filter(|k| (0..samples as i64).contains(k))
            .ok_or_else(|| {
                format_err(
                    path,
                    format!(
                        "column `step`: outside 0..={} at {}",
                        samples - 1,
                        rows.key(i)
                    ),
                )
            })?;
        Ok(base + r as u64 * samples as u64 + k as u64)
    }
}

/// An estimates file's columns, as they are read.
struct FileColumns {
    columns: EstimateColumns,
    /// The value columns in spill order.
    names: Vec<String>,
    /// Values per row.
    width: usize,
    /// Where null means "not given" and a non-finite number is an error: the innovation and
    /// the error transition.
    innovation: std::ops::Range<usize>,
    transition: std::ops::Range<usize>,
}

impl FileColumns {
    fn new(columns: EstimateColumns) -> Self {
        let width = columns.width();
        let nu_at = columns.nq() + columns.ntri();
        FileColumns {
            names: columns.value_columns(),
            innovation: if columns.innovations {
                nu_at..nu_at + columns.nz()
            } else {
                0..0
            },
            transition: if columns.transition {
                width - columns.nq() * columns.nq()..width
            } else {
                0..0
            },
            width,
            columns,
        }
    }

    /// Row `i`'s values into `buf` (NaN where null), refusing a non-finite innovation or
    /// transition entry and a transition given in part.
    fn values(
        &self,
        path: &Path,
        rows: &RowGroup,
        i: usize,
        buf: &mut Vec<f64>,
    ) -> Result<(), OutputError> {
        let values = &rows.values;
        buf.clear();
        buf.extend(values.iter().map(|c| c.get(i).unwrap_or(f64::NAN)));
        let non_finite = |t: &usize| values[*t].get(i).is_some_and(|v| !v.is_finite());
        if let Some(t) = self
            .innovation
            .clone()
            .chain(self.transition.clone())
            .find(non_finite)
        {
            return Err(format_err(
                path,
                format!(
                    "column `{}`: {} at {} (null means not given; a NaN or infinite value is an error)",
                    self.names[t],
                    buf[t],
                    rows.key(i)
                ),
            ));
        }
        let a = self.transition.clone();
        let given = a.clone().filter(|t| values[*t].get(i).is_some()).count();
        if given != 0 && given != a.len() {
            let t = a
                .clone()
                .find(|t| values[*t].get(i).is_none())
                .expect("some entry is null");
            return Err(format_err(
                path,
                format!(
                    "column `{}`: null at {} where the row gives {given} other A_ entries (give the whole error transition of a step, or none)",
                    self.names[t],
                    rows.key(i)
                ),
            ));
        }
        Ok(())
    }
}

/// Rows the reader checks and spills at once: a file's row group or a table's batch is
/// read in blocks of at most this many rows, so a table handed over as one batch of
/// millions of rows costs no more memory than a file's row group (a block's values, row by
/// row, are 4,096 × the row's width × 8 bytes: 2.4 MB for L1's 72 values).
const BLOCK_ROWS: usize = 4096;

/// One block of rows of a row group or batch: its key and value columns, typed, and the
/// values row by row as the spill holds them.
struct RowGroup {
    /// The file row of the group's first row (for messages).
    first_row: usize,
    scenario: StringChunked,
    filter: StringChunked,
    noise: Float64Chunked,
    run: Int64Chunked,
    step: Int64Chunked,
    /// The variant columns, when the file has them.
    q_scale: Option<Float64Chunked>,
    r_scale: Option<Float64Chunked>,
    /// The `failed` column, when the file has it.
    failed: Option<BooleanChunked>,
    values: Vec<Float64Chunked>,
    /// The values row by row (`width` per row, the spill's order), NaN where null.
    table: Vec<f64>,
    /// Rows with a non-null, non-finite innovation or transition entry: an error, whose
    /// message [`FileColumns::values`] forms when the row is reached.
    flagged: Vec<bool>,
}

impl RowGroup {
    fn new(
        path: &Path,
        df: &DataFrame,
        first_row: usize,
        columns: &FileColumns,
    ) -> Result<Self, OutputError> {
        let col_err =
            |name: &str, e: PolarsError| format_err(path, format!("column `{name}`: {e}"));
        let strs = |name: &str| -> Result<StringChunked, OutputError> {
            let c = df.column(name).map_err(|e| col_err(name, e))?;
            Ok(c.str().map_err(|e| col_err(name, e))?.clone())
        };
        let floats = |name: &str| -> Result<Float64Chunked, OutputError> {
            let c = df
                .column(name)
                .and_then(|c| c.cast(&DataType::Float64))
                .map_err(|e| col_err(name, e))?;
            Ok(c.f64().map_err(|e| col_err(name, e))?.clone())
        };
        let ints = |name: &str| -> Result<Int64Chunked, OutputError> {
            let c = df.column(name).map_err(|e| col_err(name, e))?;
            if !c.dtype().is_integer() {
                return Err(format_err(
                    path,
                    format!("column `{name}` must be an integer, not {}", c.dtype()),
                ));
            }
            let c = c.cast(&DataType::Int64).map_err(|e| col_err(name, e))?;
            Ok(c.i64().map_err(|e| col_err(name, e))?.clone())
        };
        let optional = |name: &str| -> Result<Option<Float64Chunked>, OutputError> {
            if df.schema().contains(name) {
                floats(name).map(Some)
            } else {
                Ok(None)
            }
        };
        // A rotation given as a quaternion is read as the Euler angles its `est_` columns
        // would hold.
        let cols = &columns.columns;
        let mut from_quaternions = HashMap::new();
        for r in &cols.quaternions {
            let quat: Vec<Float64Chunked> = quaternion_columns(&cols.quantities, r)
                .iter()
                .map(|n| floats(n))
                .collect::<Result<_, _>>()?;
            for (j, e) in euler_columns(r, &quat).into_iter().enumerate() {
                from_quaternions.insert(format!("est_{}", cols.quantities[r.first + j]), e);
            }
        }
        let values: Vec<Float64Chunked> = columns
            .names
            .iter()
            .map(|n| from_quaternions.remove(n).map_or_else(|| floats(n), Ok))
            .collect::<Result<_, _>>()?;
        // Column by column into rows: one pass over each column's contiguous values, where
        // reading row by row would look every value up through its chunk.
        let (height, width) = (df.height(), columns.width);
        let mut table = vec![f64::NAN; height * width];
        let mut flagged = vec![false; height];
        for (t, column) in values.iter().enumerate() {
            let checked = columns.innovation.contains(&t) || columns.transition.contains(&t);
            let mut i = 0;
            for array in column.downcast_iter() {
                let given = array.validity();
                for (k, v) in array.values().iter().enumerate() {
                    if given.is_none_or(|g| g.get_bit(k)) {
                        table[(i + k) * width + t] = *v;
                        if checked && !v.is_finite() {
                            flagged[i + k] = true;
                        }
                    }
                }
                i += array.len();
            }
        }
        Ok(RowGroup {
            first_row,
            scenario: strs("scenario")?,
            filter: strs("filter")?,
            noise: floats("noise_scale")?,
            run: ints("run")?,
            step: ints("step")?,
            q_scale: optional("q_scale")?,
            r_scale: optional("r_scale")?,
            failed: match df.column(FAILED_COLUMN) {
                Ok(c) if c.dtype() == &DataType::Boolean => {
                    Some(c.bool().map_err(|e| col_err(FAILED_COLUMN, e))?.clone())
                }
                Ok(c) => {
                    return Err(format_err(
                        path,
                        format!(
                            "column `{FAILED_COLUMN}` must be boolean (true from the step at which the filter failed), not {}",
                            c.dtype()
                        ),
                    ));
                }
                Err(_) => None,
            },
            values,
            table,
            flagged,
        })
    }

    /// Whether row `i` gives its innovation and transition as the format asks: finite
    /// where not null, and the transition whole or not at all. A row that does not is one
    /// [`FileColumns::values`] refuses.
    fn row_is_clean(&self, columns: &FileColumns, i: usize) -> bool {
        if self.flagged[i] {
            return false;
        }
        // No entry of the transition is a non-null NaN (the row is not flagged), so NaN
        // there is null.
        let row = &self.table[i * columns.width..(i + 1) * columns.width];
        let a = &row[columns.transition.clone()];
        let given = a.iter().filter(|v| !v.is_nan()).count();
        given == 0 || given == a.len()
    }

    /// Whether row `i` has the same filter, variant, scenario and noise scale as row `j`.
    fn same_cell_and_filter(&self, i: usize, j: usize) -> bool {
        let bits = |c: &Float64Chunked, k: usize| c.get(k).map(f64::to_bits);
        let variant =
            |c: &Option<Float64Chunked>| c.as_ref().is_none_or(|c| bits(c, i) == bits(c, j));
        self.filter.get(i).is_some()
            && self.filter.get(i) == self.filter.get(j)
            && self.scenario.get(i).is_some()
            && self.scenario.get(i) == self.scenario.get(j)
            && bits(&self.noise, i).is_some()
            && bits(&self.noise, i) == bits(&self.noise, j)
            && variant(&self.q_scale)
            && variant(&self.r_scale)
    }

    /// Row `i`'s key, for messages.
    fn key(&self, i: usize) -> String {
        let o = |v: Option<String>| v.unwrap_or_else(|| "null".into());
        let mut key = format!(
            "scenario = {}, noise_scale = {}, run = {}, step = {}, filter = {}",
            o(self.scenario.get(i).map(|s| format!("{s:?}"))),
            o(self.noise.get(i).map(|v| v.to_string())),
            o(self.run.get(i).map(|v| v.to_string())),
            o(self.step.get(i).map(|v| v.to_string())),
            o(self.filter.get(i).map(|s| format!("{s:?}"))),
        );
        for (name, c) in [("q_scale", &self.q_scale), ("r_scale", &self.r_scale)] {
            if let Some(c) = c {
                key.push_str(&format!(
                    ", {name} = {}",
                    o(c.get(i).map(|v| v.to_string()))
                ));
            }
        }
        key
    }
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
struct Reading<'a> {
    keys: KeyIndex<'a>,
    /// Per study filter: index into `externals`, once a file gave a row of it.
    by_filter: Vec<Option<usize>>,
    externals: Vec<External>,
    unstamped: Vec<PathBuf>,
    /// The names of the tables in memory read.
    tables: Vec<PathBuf>,
}

impl<'a> Reading<'a> {
    fn new(study: &'a StudyKeys<'a>) -> Self {
        Reading {
            by_filter: vec![None; study.filters.len()],
            keys: KeyIndex::new(study),
            externals: Vec::new(),
            unstamped: Vec::new(),
            tables: Vec::new(),
        }
    }

    /// Reads one file: its stamp and columns, then its row groups into the filters' spills.
    fn file(&mut self, path: &PathBuf) -> Result<(), OutputError> {
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
    fn table(
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
    fn finish(self, files: &[PathBuf]) -> Result<EstimateSet, OutputError> {
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

/// One run's rows of one external filter.
struct UnitRows<'a> {
    columns: &'a EstimateColumns,
    values: Vec<f64>,
    present: Vec<bool>,
    /// The first step whose `failed` flag is true.
    failed_at: Option<usize>,
    width: usize,
}

impl UnitRows<'_> {
    fn row(&self, k: usize) -> &[f64] {
        &self.values[k * self.width..(k + 1) * self.width]
    }
    fn mean<const NQ: usize>(&self, k: usize) -> Vector<NQ> {
        Vector::<NQ>::from_column_slice(&self.row(k)[..NQ])
    }
    fn covariance<const NQ: usize>(&self, k: usize) -> Matrix<NQ, NQ> {
        let tri = &self.row(k)[NQ..NQ + NQ * (NQ + 1) / 2];
        let mut m = Matrix::<NQ, NQ>::zeros();
        let mut t = 0;
        for i in 0..NQ {
            for j in 0..=i {
                m[(i, j)] = tri[t];
                if self.columns.covariance != CovarianceForm::Cholesky {
                    m[(j, i)] = tri[t];
                }
                t += 1;
            }
        }
        match self.columns.covariance {
            CovarianceForm::Lower => m,
            CovarianceForm::Cholesky => m * m.transpose(),
            CovarianceForm::Correlation => {
                // m holds the variances on its diagonal and the correlations off it.
                let sd: [f64; NQ] = std::array::from_fn(|i| m[(i, i)].sqrt());
                Matrix::<NQ, NQ>::from_fn(|i, j| {
                    if i == j {
                        m[(i, i)]
                    } else {
                        m[(i, j)] * sd[i] * sd[j]
                    }
                })
            }
        }
    }
    /// Why row k cannot be used, if it cannot.
    fn problem<const NQ: usize>(&self, k: usize) -> Option<String> {
        if !self.present[k] {
            return Some(format!("estimates: no row for step {k}"));
        }
        if self.failed_at.is_some_and(|f| f <= k) {
            return Some(format!(
                "estimates: the filter failed at step {k} (`{FAILED_COLUMN}` = true)"
            ));
        }
        let row = self.row(k);
        let names = &self.columns.quantities;
        if let Some(i) = (0..NQ).find(|&i| !row[i].is_finite()) {
            if let Some(r) = self
                .columns
                .quaternions
                .iter()
                .find(|r| (r.first..r.first + 3).contains(&i))
            {
                return Some(format!(
                    "estimates: the quaternion {} is null, zero or non-finite",
                    quaternion_columns(names, r)[..].join(", ")
                ));
            }
            return Some(format!("estimates: est_{} is null or non-finite", names[i]));
        }
        let tri = &row[NQ..NQ + NQ * (NQ + 1) / 2];
        if tri.iter().any(|v| !v.is_finite()) {
            return Some("estimates: a covariance entry is null or non-finite".into());
        }
        if self.columns.covariance == CovarianceForm::Correlation {
            let q: Vec<&str> = names.iter().map(String::as_str).collect();
            let mut t = 0;
            for i in 0..NQ {
                for j in 0..=i {
                    let v = tri[t];
                    t += 1;
                    let bad = if i == j { v < 0.0 } else { v.abs() > 1.0 };
                    if bad {
                        let what = if i == j {
                            "is negative"
                        } else {
                            "is outside [-1, 1]"
                        };
                        return Some(format!(
                            "estimates: {} = {v} {what}",
                            CovarianceForm::Correlation.column(&q, i, j)
                        ));
                    }
                }
            }
        }
        None
    }
}

/// The filter that replays a file's rows: its belief is the step.
struct Replay<'a> {
    rows: &'a UnitRows<'a>,
}

impl<const NQ: usize, const NU: usize, const NZ: usize, M: Model<NQ, NU, NZ>> Filter<NQ, NU, NZ, M>
    for Replay<'_>
{
    type Belief = usize;

    fn init(&self, _: &M, _: &Vector<NQ>, _: &Matrix<NQ, NQ>, _: &Measurement<NZ>) -> usize {
        0
    }

    fn predict(&self, _: &M, k: &mut usize, _: &Vector<NU>) -> Result<(), FilterError> {
        *k += 1;
        match self.rows.problem::<NQ>(*k) {
            Some(why) => Err(FilterError::Estimates(why)),
            None => Ok(()),
        }
    }

    fn update(
        &self,
        _: &M,
        k: &mut usize,
        _: &Vector<NU>,
        _: &Measurement<NZ>,
    ) -> Result<Option<Innovation<NZ>>, FilterError> {
        let cols = self.rows.columns;
        if !cols.innovations {
            return Ok(None);
        }
        let row = self.rows.row(*k);
        let at = NQ + NQ * (NQ + 1) / 2;
        let nu_row = &row[at..at + NZ];
        let s_row = &row[at + NZ..at + NZ + NZ * (NZ + 1) / 2];
        let mut available = 0u32;
        let mut nu = Vector::<NZ>::zeros();
        for (i, v) in nu_row.iter().enumerate() {
            if v.is_finite() {
                available |= 1 << i;
                nu[i] = *v;
            }
        }
        let available = Availability(available);
        if available.count() == 0 {
            return Ok(None);
        }
        // Components that did not report get identity rows, as the EKF masks them, so the
        // factor and the whitened innovation equal the in-process ones.
        let mut s = Matrix::<NZ, NZ>::identity();
        let mut t = 0;
        for i in 0..NZ {
            for j in 0..=i {
                if available.has(i) && available.has(j) {
                    if !s_row[t].is_finite() {
                        return Err(FilterError::Estimates(format!(
                            "estimates: S_{}_{} is null or non-finite where nu reported",
                            cols.measurements[i], cols.measurements[j]
                        )));
                    }
                    s[(i, j)] = s_row[t];
                    s[(j, i)] = s_row[t];
                }
                t += 1;
            }
        }
        let chol = SmallCholesky::new(&s).ok_or(FilterError::NotPositiveDefinite {
            which: "innovation covariance S",
        })?;
        let whitened = chol.solve_lower(&nu);
        Ok(Some(
            Innovation::new(nu, whitened, available).with_covariance(s),
        ))
    }

    fn mean(&self, k: &usize) -> Vector<NQ> {
        self.rows.mean(*k)
    }

    fn covariance(&self, k: &usize) -> Option<Matrix<NQ, NQ>> {
        Some(self.rows.covariance(*k))
    }

    fn error_transition(&self, k: &usize) -> Option<Matrix<NQ, NQ>> {
        let cols = self.rows.columns;
        if !cols.transition {
            return None;
        }
        let row = self.rows.row(*k);
        let at = row.len() - NQ * NQ;
        let a = &row[at..];
        a.iter()
            .all(|v| v.is_finite())
            .then(|| Matrix::<NQ, NQ>::from_fn(|i, j| a[i * NQ + j]))
    }
}

/// Scores study filter `filter` (an external one, labelled `label`) on one run from its rows
/// in `estimates`: the same step loop, metrics and record as an in-process filter. `model` is
/// only there to satisfy the step loop's types; the replay never evaluates it.
pub fn replay<const NQ: usize, const NU: usize, const NZ: usize, M: Model<NQ, NU, NZ>>(
    estimates: Option<&EstimateSet>,
    filter: usize,
    label: &str,
    model: &M,
    ctx: &RunContext<'_, NQ, NU, NZ>,
) -> FilterOutput {
    let rows = estimates.and_then(|set| set.unit_rows(filter, &ctx.unit));
    let fail = |why: String| FilterOutput::failed_at_start(ctx, why);
    let Some(rows) = rows else {
        return fail(format!(
            "no estimates were given for the external filter `{label}`"
        ));
    };
    // A run left out whole was not run: missing, which no tolerance for failures covers.
    if !rows.present.iter().any(|&p| p) {
        return FilterOutput::missing(
            ctx,
            format!("the estimates of `{label}` leave this run out"),
        );
    }
    if let Some(why) = rows.problem::<NQ>(0) {
        return fail(why);
    }
    let (x0, p0) = (rows.mean::<NQ>(0), rows.covariance::<NQ>(0));
    // Rotations the file gives as Euler angles have an Euler-angle covariance to map.
    let charts: Vec<EulerRotation> = ctx
        .rotations
        .iter()
        .filter(|r| !rows.columns.quaternions.contains(r))
        .copied()
        .collect();
    run_filter(
        model,
        &Replay { rows: &rows },
        &Charted { charts: &charts },
        &Prior {
            x0_hat: &x0,
            p0: &p0,
        },
        ctx,
    )
}

/// The replay's evaluation: the identity, except that each rotation given as Euler angles
/// has its covariance (and error transition) mapped into the rotation error's tangent space
/// by the chart Jacobian at the estimate.
struct Charted<'a> {
    charts: &'a [EulerRotation],
}

impl Charted<'_> {
    fn blocks<const N: usize>(&self, x: &Vector<N>) -> Vec<(usize, Matrix<3, 3>)> {
        self.charts
            .iter()
            .map(|r| (r.first, r.chart_jacobian(x.as_slice())))
            .collect()
    }
}

impl<const N: usize> Evaluate<N, N> for Charted<'_> {
    fn mean(&self, x: &Vector<N>) -> Vector<N> {
        *x
    }
    fn covariance(&self, x: &Vector<N>, p: &Matrix<N, N>) -> Matrix<N, N> {
        so3::transform_blocks(p, &self.blocks(x))
    }
    fn covariance_ref<'p>(&self, p: &'p Matrix<N, N>) -> Option<&'p Matrix<N, N>> {
        self.charts.is_empty().then_some(p)
    }
    fn transition(&self, a: &Matrix<N, N>) -> Option<Matrix<N, N>> {
        self.charts.is_empty().then_some(*a)
    }
    fn transition_at(&self, x: &Vector<N>, a: &Matrix<N, N>) -> Option<Matrix<N, N>> {
        so3::conjugate_blocks(a, &self.blocks(x))
    }
}
/// The model a world system's external filters are replayed on: kfmc does not know their
/// model, and the replay never asks it anything; it only carries Δt.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Unmodelled {
    /// Sample time Δt in seconds.
    pub dt_s: f64,
}

impl<const NX: usize, const NU: usize, const NZ: usize> Model<NX, NU, NZ> for Unmodelled {
    fn dt_s(&self) -> f64 {
        self.dt_s
    }
    fn propagate(&self, x: &Vector<NX>, _: &Vector<NU>) -> Vector<NX> {
        *x
    }
    fn transition_jacobian(&self, _: &Vector<NX>, _: &Vector<NU>) -> Matrix<NX, NX> {
        Matrix::<NX, NX>::identity()
    }
    fn measure(&self, _: &Vector<NX>, _: &Vector<NU>) -> Vector<NZ> {
        Vector::<NZ>::zeros()
    }
    fn measurement_jacobian(&self, _: &Vector<NX>, _: &Vector<NU>) -> Matrix<NZ, NX> {
        Matrix::<NZ, NX>::zeros()
    }
}
