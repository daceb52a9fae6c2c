//! Every table's columns, defined once. Names match the TOML keys and the docs:
//! `scenario, noise_scale, filter, run, seed, status, rmse_<state>, …`.

/// Column types.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Dtype {
    /// UTF-8 string.
    Str,
    /// 64-bit float, nullable.
    F64,
    /// 32-bit float, nullable: given as [`Value::F64`] and rounded to the nearest f32 when
    /// written (`kfmc run --export-estimates-precision f32`); read back as f64, exactly.
    F32,
    /// 64-bit signed integer, nullable.
    I64,
    /// 64-bit unsigned integer.
    U64,
    /// Boolean, nullable.
    Bool,
}

/// One cell value. `None` is written as a Parquet null.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Value<'a> {
    /// String.
    Str(&'a str),
    /// Nullable float (NaN is stored as null too: "not defined").
    F64(Option<f64>),
    /// Nullable integer.
    I64(Option<i64>),
    /// Unsigned integer.
    U64(u64),
    /// Nullable boolean.
    Bool(Option<bool>),
}

/// A column definition.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ColumnDef {
    /// Column name.
    pub name: String,
    /// Type.
    pub dtype: Dtype,
}

fn col(name: impl Into<String>, dtype: Dtype) -> ColumnDef {
    ColumnDef {
        name: name.into(),
        dtype,
    }
}

fn per<'a>(
    prefix: &'a str,
    names: &'a [&str],
    dtype: Dtype,
) -> impl Iterator<Item = ColumnDef> + 'a {
    names
        .iter()
        .map(move |n| col(format!("{prefix}{n}"), dtype))
}

/// The key columns shared by every per-cell table: (scenario, truth-noise multiplier,
/// filter label, the filter's Q and R multipliers).
fn cell_keys() -> Vec<ColumnDef> {
    vec![
        col("scenario", Dtype::Str),
        col("noise_scale", Dtype::F64),
        col("filter", Dtype::Str),
        col("q_scale", Dtype::F64),
        col("r_scale", Dtype::F64),
    ]
}

/// An estimates file's columns `cols` with the variant columns after `filter`: `q_scale` and
/// `r_scale`, each where `axes` says a filter's rows name their variant on that axis (an
/// external filter declaring variants, or kfmc's own exported).
pub fn with_variant_columns(mut cols: Vec<ColumnDef>, axes: [bool; 2]) -> Vec<ColumnDef> {
    let at = cols
        .iter()
        .position(|c| c.name == "filter")
        .map_or(0, |i| i + 1);
    let variant = ["q_scale", "r_scale"]
        .into_iter()
        .zip(axes)
        .filter(|(_, keyed)| *keyed)
        .map(|(name, _)| col(name, Dtype::F64));
    cols.splice(at..at, variant);
    cols
}

/// The key columns of per-(scenario, filter variant) tables.
fn filter_keys() -> Vec<ColumnDef> {
    vec![
        col("scenario", Dtype::Str),
        col("filter", Dtype::Str),
        col("q_scale", Dtype::F64),
        col("r_scale", Dtype::F64),
    ]
}

/// Table names, in the order they are documented.
pub const TABLES: [&str; 20] = [
    "runs",
    "steps",
    "run_steps",
    "summary",
    "sensors",
    "consistency",
    "sequential",
    "divergence",
    "divergence_runs",
    "traces",
    "tuning",
    "tuned",
    "tune_trace",
    "estimates",
    "truth",
    "measurements",
    "initial",
    "power",
    "ulog_samples",
    "ulog_summary",
];

/// The columns that identify a row of the table `name` (`runs`, `steps`, …): a table kfmc
/// wrote has one row per key, so readers refuse a table with two (an edited or forged file
/// would otherwise be drawn and judged with one of the rows silently winning). `None` for a
/// table kfmc does not write.
pub fn row_keys(name: &str) -> Option<&'static [&'static str]> {
    const CELL: [&str; 5] = ["scenario", "noise_scale", "filter", "q_scale", "r_scale"];
    Some(match name {
        "runs" => &const { concat5(CELL, "run") },
        "steps" => &const { concat5(CELL, "step") },
        "run_steps" => &[
            "scenario",
            "noise_scale",
            "filter",
            "q_scale",
            "r_scale",
            "run",
            "step",
        ],
        "summary" => &const { concat5(CELL, "state") },
        "consistency" | "power" => &[
            "scenario",
            "noise_scale",
            "filter",
            "q_scale",
            "r_scale",
            "test",
            "runs",
            "alpha",
        ],
        "traces" => &[
            "scenario",
            "noise_scale",
            "filter",
            "q_scale",
            "r_scale",
            "run",
            "step",
        ],
        "sequential" => &const { concat5(CELL, "look") },
        "sensors" => &["scenario", "noise_scale", "metric"],
        "divergence" => &["scenario", "filter", "q_scale", "r_scale", "state"],
        "divergence_runs" => &["scenario", "filter", "q_scale", "r_scale", "run", "state"],
        "tuning" => &[
            "stage",
            "scenario",
            "noise_scale",
            "filter",
            "q_scale",
            "r_scale",
        ],
        "tuned" => &["element"],
        "tune_trace" => &["start", "iteration"],
        "estimates" => &["scenario", "noise_scale", "run", "step", "filter"],
        "truth" | "measurements" => &["scenario", "noise_scale", "run", "step"],
        "initial" => &["scenario", "noise_scale", "run"],
        "ulog_samples" => &["log", "instance", "source", "axis", "t_sample"],
        "ulog_summary" => &["log", "instance", "primary", "source", "axis", "test"],
        _ => return None,
    })
}

const fn concat5(a: [&'static str; 5], b: &'static str) -> [&'static str; 6] {
    [a[0], a[1], a[2], a[3], a[4], b]
}

/// `runs.parquet`: one row per scenario × noise scale × filter × run.
pub fn runs(states: &[&str]) -> Vec<ColumnDef> {
    let mut c = cell_keys();
    c.extend([
        col("run", Dtype::I64),
        col("seed", Dtype::U64),
        col("status", Dtype::Str),
        col("status_step", Dtype::I64),
        col("status_detail", Dtype::Str),
    ]);
    c.extend(per("rmse_", states, Dtype::F64));
    c.extend([
        col("nees_mean", Dtype::F64),
        col("nis_mean", Dtype::F64),
        col("covariance_repairs", Dtype::I64),
    ]);
    c
}

/// `steps.parquet`: one row per cell × filter × step. `blocks`: the layout's blocks of
/// quantities when the study has a `[consistency]` section, which adds the credibility
/// columns ([`credibility_steps`]).
pub fn steps(states: &[&str], blocks: Option<&[&str]>) -> Vec<ColumnDef> {
    let mut c = cell_keys();
    c.extend([
        col("step", Dtype::I64),
        col("t", Dtype::F64),
        col("runs", Dtype::I64),
        col("anees", Dtype::F64),
        col("anees_lo", Dtype::F64),
        col("anees_hi", Dtype::F64),
        col("anees_inside", Dtype::Bool),
        col("anis", Dtype::F64),
        col("anis_lo", Dtype::F64),
        col("anis_hi", Dtype::F64),
        col("anis_inside", Dtype::Bool),
    ]);
    c.extend(per("mse_", states, Dtype::F64));
    // Quantiles of |e| across runs, grouped by quantile then state (metrics::ABS_ERR_QUANTILES).
    for q in ["p05", "p50", "p95"] {
        c.extend(
            states
                .iter()
                .map(|s| col(format!("abs_err_{q}_{s}"), Dtype::F64)),
        );
    }
    if let Some(b) = blocks {
        c.extend(credibility_steps(b));
    }
    c
}

/// The credibility columns of `steps.parquet` (studies with `[consistency]`): per block of
/// quantities its ANEES and per-step χ² band at the study's α, then Li and Zhao's NCI and
/// inclination (dB) and what a credible filter scores at the step's run count
/// ([`crate::metrics::credibility`]).
pub fn credibility_steps(blocks: &[&str]) -> Vec<ColumnDef> {
    let mut c = Vec::new();
    for b in blocks {
        c.extend([
            col(format!("block_anees_{b}"), Dtype::F64),
            col(format!("block_anees_{b}_lo"), Dtype::F64),
            col(format!("block_anees_{b}_hi"), Dtype::F64),
            col(format!("block_anees_{b}_inside"), Dtype::Bool),
        ]);
    }
    c.extend(credibility_indices());
    c
}

fn credibility_indices() -> [ColumnDef; 4] {
    [
        col("nci", Dtype::F64),
        col("inclination", Dtype::F64),
        col("nci_credible_reference", Dtype::F64),
        col("inclination_credible_reference", Dtype::F64),
    ]
}

/// `consistency.parquet`: one row per cell × filter × test. `blocks`: the layout's blocks of
/// quantities (`None`: no credibility columns).
pub fn consistency(blocks: Option<&[&str]>) -> Vec<ColumnDef> {
    let mut c = cell_keys();
    c.extend([
        col("test", Dtype::Str),
        col("statistic", Dtype::F64),
        col("lower", Dtype::F64),
        col("upper", Dtype::F64),
        col("dof", Dtype::F64),
        col("p_value", Dtype::F64),
        col("pass", Dtype::Bool),
        col("direction", Dtype::Str),
        col("alpha", Dtype::F64),
        col("runs", Dtype::I64),
        col("burn_in_steps", Dtype::I64),
    ]);
    if let Some(b) = blocks {
        // Time averages over the steps after the burn-in, on the rows of the whole cell (null
        // on the subsets' rows).
        for b in b {
            c.extend([
                col(format!("block_anees_{b}"), Dtype::F64),
                col(format!("block_anees_{b}_lo"), Dtype::F64),
                col(format!("block_anees_{b}_hi"), Dtype::F64),
                col(format!("block_anees_{b}_inside_fraction"), Dtype::F64),
            ]);
        }
        c.extend(credibility_indices());
    }
    c
}

/// `sequential.parquet` (`kfmc check` with a sequential gate): one row per cell × filter ×
/// look the gate took for it, up to the look that decided.
pub fn sequential() -> Vec<ColumnDef> {
    let mut c = cell_keys();
    c.extend([
        col("look", Dtype::I64),
        col("runs", Dtype::I64),
        col("p_value", Dtype::F64),
        col("efficacy_z", Dtype::F64),
        col("futility_z", Dtype::F64),
        col("reject_p", Dtype::F64),
        col("accept_p", Dtype::F64),
        col("decision", Dtype::Str),
        col("direction", Dtype::Str),
        col("alpha", Dtype::F64),
    ]);
    c
}

/// `run_steps.parquet` (`consistency.per_step_runs`): one row per cell × filter × run × step
/// the run reached: its NEES and NIS (null where not defined) and the NIS degrees of freedom.
pub fn run_steps() -> Vec<ColumnDef> {
    let mut c = cell_keys();
    c.extend([
        col("run", Dtype::I64),
        col("step", Dtype::I64),
        col("time_s", Dtype::F64),
        col("nees", Dtype::F64),
        col("nis", Dtype::F64),
        col("nis_dof", Dtype::I64),
    ]);
    c
}

/// `summary.parquet`: one row per cell × filter × state.
pub fn summary() -> Vec<ColumnDef> {
    let mut c = cell_keys();
    c.extend([
        col("state", Dtype::Str),
        col("runs", Dtype::I64),
        col("runs_failed", Dtype::I64),
        col("rmse_mean", Dtype::F64),
        col("rmse_std", Dtype::F64),
        col("rmse_p05", Dtype::F64),
        col("rmse_p50", Dtype::F64),
        col("rmse_p95", Dtype::F64),
    ]);
    c
}

/// `sensors.parquet` (worlds that report metrics of their own sensors): one row per
/// (scenario, noise scale) × metric, over the cell's runs — e.g. each raw sensor's RMSE
/// against the truth, to set beside the filters' RMSE in `summary`.
pub fn sensors() -> Vec<ColumnDef> {
    vec![
        col("scenario", Dtype::Str),
        col("noise_scale", Dtype::F64),
        col("metric", Dtype::Str),
        col("runs", Dtype::I64),
        col("mean", Dtype::F64),
        col("std", Dtype::F64),
        col("p05", Dtype::F64),
        col("p50", Dtype::F64),
        col("p95", Dtype::F64),
    ]
}

/// `divergence.parquet`: one row per scenario × filter × state.
pub fn divergence() -> Vec<ColumnDef> {
    let mut c = filter_keys();
    c.extend([
        col("state", Dtype::Str),
        col("threshold", Dtype::F64),
        col("max_noise_scale", Dtype::F64),
        col("mc_divergence_scale", Dtype::F64),
        col("runs", Dtype::I64),
        col("runs_diverged", Dtype::I64),
        col("run_divergence_p05", Dtype::F64),
        col("run_divergence_p50", Dtype::F64),
        col("run_divergence_p95", Dtype::F64),
    ]);
    c
}

/// `divergence_runs.parquet`: one row per scenario × filter × run × state.
pub fn divergence_runs() -> Vec<ColumnDef> {
    let mut c = filter_keys();
    c.extend([
        col("run", Dtype::I64),
        col("state", Dtype::Str),
        col("divergence_scale", Dtype::F64),
        // The run never crossed at any multiplier tried (its divergence_scale is null, or the
        // largest multiplier with `divergence.never_crossed = "largest_scale"`).
        col("never_crossed", Dtype::Bool),
    ]);
    c
}

/// `tuning.parquet`: one row per tuning stage × cell × candidate (q_scale, r_scale).
pub fn tuning(states: &[&str]) -> Vec<ColumnDef> {
    let mut c = vec![
        col("stage", Dtype::Str),
        col("scenario", Dtype::Str),
        col("noise_scale", Dtype::F64),
        col("filter", Dtype::Str),
        col("q_scale", Dtype::F64),
        col("r_scale", Dtype::F64),
        col("anees", Dtype::F64),
        col("anis", Dtype::F64),
    ];
    c.extend(per("rmse_", states, Dtype::F64));
    c.push(col("objective", Dtype::F64));
    c
}

/// `tuned.parquet` (`kfmc tune --method ml` and `--method truth`): one row per tuned element of Q or R, with its
/// standard error and 95 % interval (null where the element is not identified).
pub fn tuned() -> Vec<ColumnDef> {
    vec![
        col("element", Dtype::Str),
        col("estimate", Dtype::F64),
        col("std_error", Dtype::F64),
        col("ci_low", Dtype::F64),
        col("ci_high", Dtype::F64),
        col("method", Dtype::Str),
        col("identifiable", Dtype::Bool),
    ]
}

/// `tune_trace.parquet` (`kfmc tune --method ml` and `--method truth`): every iteration of
/// every start of the search, with its objective and each element's value (a column per element, named as in `tuned`).
pub fn tune_trace(elements: &[&str]) -> Vec<ColumnDef> {
    let mut c = vec![
        col("start", Dtype::I64),
        col("iteration", Dtype::I64),
        col("objective", Dtype::F64),
    ];
    c.extend(elements.iter().map(|e| col(*e, Dtype::F64)));
    c
}

/// `traces.parquet`: one row per traced run × filter × step.
pub fn traces(states: &[&str], inputs: &[&str], meas: &[&str], world: &[&str]) -> Vec<ColumnDef> {
    let mut c = cell_keys();
    c.extend([
        col("run", Dtype::I64),
        col("step", Dtype::I64),
        col("t", Dtype::F64),
    ]);
    c.extend(per("u_", inputs, Dtype::F64));
    c.extend(per("truth_", states, Dtype::F64));
    c.extend(per("z_", meas, Dtype::F64));
    c.extend(per("world_", world, Dtype::F64));
    c.extend(per("est_", states, Dtype::F64));
    c.extend(per("var_", states, Dtype::F64));
    c.extend(covariance_columns(states));
    c
}

/// The lower triangle of a covariance over `names`, row by row: `P_<qi>_<qj>` with qi at or
/// after qj in the quantity order ((0,0), (1,0), (1,1), (2,0), …).
pub fn covariance_columns(names: &[&str]) -> Vec<ColumnDef> {
    let mut c = Vec::with_capacity(names.len() * (names.len() + 1) / 2);
    for (i, qi) in names.iter().enumerate() {
        for qj in &names[..=i] {
            c.push(col(format!("P_{qi}_{qj}"), Dtype::F64));
        }
    }
    c
}

/// The keys of `kfmc simulate`'s per-step tables.
fn run_step_keys() -> Vec<ColumnDef> {
    vec![
        col("scenario", Dtype::Str),
        col("noise_scale", Dtype::F64),
        col("run", Dtype::I64),
        col("step", Dtype::I64),
        col("t", Dtype::F64),
    ]
}

/// `truth.parquet` (`kfmc simulate`): per run and step, the true evaluated quantities and the
/// world's own states.
pub fn truth(states: &[&str], world: &[&str]) -> Vec<ColumnDef> {
    let mut c = run_step_keys();
    c.extend(per("truth_", states, Dtype::F64));
    c.extend(per("world_", world, Dtype::F64));
    c
}

/// `measurements.parquet` (`kfmc simulate`): per run and step, what a filter receives: the
/// measurement components (null where a sensor did not report) and the inputs.
pub fn measurements(meas: &[&str], inputs: &[&str]) -> Vec<ColumnDef> {
    let mut c = run_step_keys();
    c.extend(per("z_", meas, Dtype::F64));
    c.extend(per("u_", inputs, Dtype::F64));
    c
}

/// `initial.parquet` (`kfmc simulate`): per run, its seed and the prior x̂_0, P_0 kfmc's own
/// filters start from.
pub fn initial(states: &[&str]) -> Vec<ColumnDef> {
    let mut c = vec![
        col("scenario", Dtype::Str),
        col("noise_scale", Dtype::F64),
        col("run", Dtype::I64),
        col("seed", Dtype::U64),
    ];
    c.extend(per("est_", states, Dtype::F64));
    c.extend(covariance_columns(states));
    c
}

/// `ulog_samples.parquet` (`kfmc ulog nis`): one row per log × instance × source × axis ×
/// sample of the judged series: the innovation, its variance S, NIS = ν²/S, PX4's test ratio,
/// the gate and its flags, and whether the sample entered the verdict (`included`: in the air,
/// after the instance's start and resets' hold-off) in which `stretch`.
pub fn ulog_samples() -> Vec<ColumnDef> {
    vec![
        col("log", Dtype::Str),
        col("instance", Dtype::I64),
        col("primary", Dtype::Bool),
        col("source", Dtype::Str),
        col("axis", Dtype::I64),
        col("t_sample", Dtype::F64),
        col("innovation", Dtype::F64),
        col("innovation_variance", Dtype::F64),
        col("nis", Dtype::F64),
        col("test_ratio", Dtype::F64),
        col("gate", Dtype::F64),
        col("rejected", Dtype::Bool),
        col("fused", Dtype::Bool),
        col("in_air", Dtype::Bool),
        col("included", Dtype::Bool),
        col("stretch", Dtype::I64),
    ]
}

/// `ulog_summary.parquet` (`kfmc ulog nis`): one row per log × instance × source × axis ×
/// test (`nis_mean`, `rejection_rate`; `nis_sum_approximate` per source) and a `verdict` row
/// per log; the batch-means test's numbers and the verdict.
pub fn ulog_summary() -> Vec<ColumnDef> {
    vec![
        col("log", Dtype::Str),
        col("instance", Dtype::I64),
        col("primary", Dtype::Bool),
        col("source", Dtype::Str),
        col("axis", Dtype::I64),
        col("test", Dtype::Str),
        col("samples", Dtype::I64),
        col("samples_included", Dtype::I64),
        col("stretches", Dtype::I64),
        col("tau", Dtype::F64),
        col("effective_samples", Dtype::F64),
        col("batches", Dtype::I64),
        col("batch_length", Dtype::I64),
        col("statistic", Dtype::F64),
        col("expected", Dtype::F64),
        col("lower", Dtype::F64),
        col("upper", Dtype::F64),
        col("dof", Dtype::F64),
        col("p_value", Dtype::F64),
        col("level", Dtype::F64),
        col("alpha", Dtype::F64),
        col("verdict", Dtype::Str),
        col("direction", Dtype::Str),
        col("gate", Dtype::F64),
        col("gate_from", Dtype::Str),
        col("rejected_fraction", Dtype::F64),
        col("rejection_expected", Dtype::F64),
        col("pairing_rate", Dtype::F64),
        col("family", Dtype::Str),
        col("firmware", Dtype::Str),
        col("detail", Dtype::Str),
    ]
}
