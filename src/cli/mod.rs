//! The command-line interface (clap derive). Errors print their whole cause chain.
//!
//! Exit codes:
//! * 0 — success;
//! * 1 — a runtime failure (I/O, an unreadable result folder);
//! * 2 — an invalid spec or invalid command-line usage;
//! * 3 — `kfmc check`: the study ran and at least one assertion failed;
//! * 4 — `kfmc check`: no assertion failed, but at least one case could not be judged on the
//!   runs the spec declares (runs missing, numerical failures beyond `check.max_failed_runs`,
//!   a test that could not be computed): incomplete, never a pass;
//! * 130 — interrupted by SIGINT or SIGTERM (nothing committed, partial files removed; `kfmc
//!   run` keeps its checkpoint for `--resume`).

pub mod progress;
pub mod summary;
use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand};

use crate::error::KfmcError;
use crate::experiment::{self, Overrides, Plan};
use crate::plot::{FigureKind, Format, PlotOptions};
use crate::runner::lanes::LanesMode;
use crate::system::{Program, Registry};
use progress::ProgressObserver;

/// Exit code: success.
pub const EXIT_OK: u8 = 0;
/// Exit code: runtime failure.
pub const EXIT_FAILURE: u8 = 1;
/// Exit code: invalid spec or usage.
pub const EXIT_INVALID_SPEC: u8 = 2;
/// Exit code: `kfmc check` found a failing assertion.
pub const EXIT_CHECK_FAILED: u8 = crate::check::EXIT_CHECK_FAILED;
/// Exit code: `kfmc check` found no failing assertion, but a case it could not judge on the
/// runs the spec declares (incomplete).
pub const EXIT_CHECK_INCOMPLETE: u8 = crate::check::EXIT_CHECK_INCOMPLETE;
/// Exit code: stopped by SIGINT or SIGTERM (128 + SIGINT's number, as shells report it);
/// nothing of the interrupted run was committed.
pub const EXIT_INTERRUPTED: u8 = 130;

/// A command line that names a value kfmc cannot use (exit 2), outside any spec.
#[derive(Debug, thiserror::Error)]
#[error("invalid {flag}: {message}")]
pub struct UsageError {
    /// The flag (or variable) at fault, e.g. `--shard`.
    pub flag: String,
    /// What is wrong with its value.
    pub message: String,
}

/// A failed or incomplete `kfmc check` (its report is already printed).
#[derive(Debug, thiserror::Error)]
#[error("{failed} of {total} check cases failed, {incomplete} incomplete")]
pub struct CheckFailed {
    failed: usize,
    incomplete: usize,
    total: usize,
}

/// kfmc — judge state estimators statistically with seeded Monte Carlo studies.
#[derive(Debug, Parser)]
#[command(name = "kfmc", version, about, long_about = None, after_help = "Exit codes: 0 success, 1 runtime failure, 2 invalid spec or usage, 3 a `check` assertion failed, 4 a `check` case incomplete (judged on fewer runs than declared, or a test not computed) and none failed, 130 interrupted (SIGINT/SIGTERM; nothing committed; `run --resume` continues).")]
pub struct Cli {
    /// The command.
    #[command(subcommand)]
    pub command: Command,
}

/// The spec and the overrides shared by every command that runs a study.
#[derive(Debug, clap::Args)]
pub struct StudyArgs {
    /// The experiment spec (TOML).
    pub spec: PathBuf,
    /// Output folder (overrides the spec's `output`).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Runs per cell (overrides `runs`).
    #[arg(long)]
    pub runs: Option<usize>,
    /// Worker threads; 0 = all cores. Results do not depend on it.
    #[arg(long, default_value_t = 0)]
    pub threads: usize,
    /// Master seed (overrides `master_seed`).
    #[arg(long)]
    pub seed: Option<u64>,
    /// No progress bar and no report.
    #[arg(long, short)]
    pub quiet: bool,
    /// Write into a non-empty output folder that is not a kfmc result folder, or replace a
    /// folder that holds another command's result.
    #[arg(long)]
    pub force: bool,
    /// Run a plan above the documented memory, disk or step limits.
    #[arg(long)]
    pub allow_large: bool,
    /// Runs of a cell in groups (`auto`, the default unless `KFMC_LANES` says otherwise) or
    /// one at a time (`off`, the per-unit scalar path). Results do not depend on it.
    #[arg(long, value_parser = lanes_mode, value_name = "auto|off")]
    pub lanes: Option<LanesMode>,
}

/// clap's value parser for `--lanes`.
fn lanes_mode(text: &str) -> Result<LanesMode, String> {
    LanesMode::parse(text)
}

/// The lanes mode of a command: `--lanes` when given, else `KFMC_LANES` (a usage error
/// naming the variable when it holds anything but `auto` or `off`), else auto.
pub(crate) fn lanes(flag: Option<LanesMode>) -> Result<LanesMode, UsageError> {
    LanesMode::resolve(flag).map_err(|message| usage(crate::runner::lanes::ENV, message))
}

impl StudyArgs {
    /// Loads and validates the spec and applies the overrides.
    fn plan(&self, registry: &Registry, trace_runs: Option<usize>) -> anyhow::Result<Plan> {
        let lanes = lanes(self.lanes)?;
        let mut plan = self.load(registry, trace_runs)?;
        plan.lanes = lanes;
        Ok(plan)
    }

    /// [`StudyArgs::plan`] before the lanes mode is applied.
    fn load(&self, registry: &Registry, trace_runs: Option<usize>) -> Result<Plan, KfmcError> {
        let mut plan = experiment::load_with(&self.spec, registry)?;
        plan.apply(&Overrides {
            runs: self.runs,
            master_seed: self.seed,
            output: self.out.clone(),
            trace_runs,
        })?;
        crate::study::check_limits(&plan, self.allow_large)?;
        Ok(plan)
    }

    /// The worker threads to use: more than the machine's logical CPUs only adds contention
    /// (and thousands of threads can stall a shared host), so the count is clamped, saying so.
    fn threads(&self, quiet: bool) -> usize {
        let cpus = std::thread::available_parallelism().map_or(1, |n| n.get());
        if self.threads > cpus {
            if !quiet {
                eprintln!(
                    "note: --threads {} is more than the {cpus} logical CPUs; using {cpus}",
                    self.threads
                );
            }
            cpus
        } else {
            self.threads
        }
    }
}

/// A number of seconds ≥ 0 (clap's value parser for durations).
fn seconds(text: &str) -> Result<f64, String> {
    match text.parse::<f64>() {
        Ok(s) if std::time::Duration::try_from_secs_f64(s).is_ok() => Ok(s),
        Ok(s) if s.is_finite() && s >= 0.0 => Err(format!(
            "`{text}` seconds is longer than kfmc can wait (at most {:.3e})",
            std::time::Duration::MAX.as_secs_f64()
        )),
        _ => Err(format!("`{text}` is not a number of seconds ≥ 0")),
    }
}

/// A count of at least 1 (`--cpus`).
fn at_least_one(text: &str) -> Result<usize, String> {
    match text.trim().parse::<usize>() {
        Ok(n) if n >= 1 => Ok(n),
        _ => Err(format!("`{text}` is not an integer ≥ 1")),
    }
}

/// The group-sequential gate's settings (`kfmc power --sequential`).
#[derive(clap::Args, Debug, Clone)]
pub struct SequentialArgs {
    /// A group-sequential gate on the consistency verdicts (`check`: each cell stops at the
    /// look that settles its verdicts; `power`: the gate is measured beside the fixed-N
    /// verdict).
    #[arg(long)]
    pub sequential: bool,
    /// The looks: a count of even looks (default 10), or the run counts of the looks
    /// (`10,25,50,100`; the last must be the study's runs per cell).
    #[arg(long, value_name = "COUNT|N1,N2,...")]
    pub looks: Option<String>,
    /// How α is spent over the looks (default: obrien-fleming).
    #[arg(long, value_enum)]
    pub spending: Option<SpendingArg>,
    /// Stop a consistent filter early: non-binding futility bounds spending β (power 1 − β
    /// at the design's drift), by a quadratic β-spending function.
    #[arg(long, value_name = "BETA", alias = "futility-beta")]
    pub futility: Option<f64>,
    /// The exponent ρ of the futility bounds' β-spending β·t^ρ: 2 (default, quadratic) or 1
    /// (linear: a consistent filter stops earlier, at some power near the truth).
    #[arg(long, value_name = "RHO", requires = "futility")]
    pub futility_rho: Option<f64>,
}

/// An α-spending function.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum SpendingArg {
    /// Lan–DeMets O'Brien–Fleming type: early looks stop only on overwhelming evidence.
    #[value(alias = "obrien_fleming")]
    ObrienFleming,
    /// Lan–DeMets Pocock type: nearly constant boundaries.
    Pocock,
}

fn usage(flag: &str, message: impl Into<String>) -> UsageError {
    UsageError {
        flag: flag.into(),
        message: message.into(),
    }
}

impl SequentialArgs {
    /// The gate's settings: `None` without `--sequential` (and without `spec`'s), else the
    /// flags given over `spec`'s settings (`[check]`'s keys) over the defaults.
    pub fn settings(
        &self,
        spec: Option<&crate::sequential::GateSettings>,
    ) -> Result<Option<crate::sequential::GateSettings>, UsageError> {
        use crate::sequential::{GateOverrideError, GateOverrides, GateSetting, Looks, Spending};
        let looks = match self.looks.as_deref().map(str::trim) {
            None => None,
            Some(text) if !text.contains(',') => Some(Looks::Count(
                at_least_one(text).map_err(|e| usage("--looks", e))?,
            )),
            Some(text) => Some(Looks::RunCounts(
                text.split(',')
                    .map(|v| {
                        v.trim()
                            .parse::<usize>()
                            .map_err(|_| usage("--looks", format!("`{v}` is not a run count ≥ 2")))
                    })
                    .collect::<Result<Vec<_>, _>>()?,
            )),
        };
        let overrides = GateOverrides {
            sequential: self.sequential,
            looks,
            spending: self.spending.map(|s| match s {
                SpendingArg::ObrienFleming => Spending::OBrienFleming,
                SpendingArg::Pocock => Spending::Pocock,
            }),
            futility_beta: self.futility,
            futility_rho: self.futility_rho,
        };
        overrides.apply(spec).map_err(|e| match e {
            GateOverrideError::NotSequential(setting) => usage(
                match setting {
                    GateSetting::Looks => "--looks",
                    GateSetting::Spending => "--spending",
                    GateSetting::Futility => "--futility",
                    GateSetting::FutilityRho => "--futility-rho",
                },
                "is a setting of the sequential gate: add --sequential",
            ),
            GateOverrideError::RhoWithoutFutility => usage(
                "--futility-rho",
                "is the exponent of the futility bounds' β-spending: add --futility",
            ),
        })
    }

    /// The gate for a study of `runs` runs per cell at level `alpha`, or `None` without
    /// `--sequential`.
    pub fn gate(
        &self,
        runs: usize,
        alpha: f64,
    ) -> Result<Option<crate::sequential::Gate>, UsageError> {
        let Some(settings) = self.settings(None)? else {
            return Ok(None);
        };
        settings
            .gate(runs, alpha)
            .map(Some)
            .map_err(|e| usage(gate_flag(&e), e.to_string()))
    }
}

/// The flag a gate's error is about.
fn gate_flag(e: &crate::sequential::GateError) -> &'static str {
    use crate::sequential::GateError;
    match e {
        GateError::Looks(_) => "--looks",
        GateError::Futility(_) => "--futility",
        GateError::FutilityRho(_) => "--futility-rho",
        GateError::Design(_) => "--sequential",
    }
}

/// A number of parts, 1 to [`crate::study::MAX_SHARDS`] (`kfmc slurm --shards`).
fn shard_count(text: &str) -> Result<usize, String> {
    match text.trim().parse::<usize>() {
        Ok(n) if (1..=crate::study::MAX_SHARDS).contains(&n) => Ok(n),
        _ => Err(format!(
            "`{text}` is not a number of parts from 1 to {}",
            crate::study::MAX_SHARDS
        )),
    }
}

/// kfmc's commands.
#[derive(Debug, Subcommand)]
pub enum Command {
    /// Run a Monte Carlo study and write its Parquet tables.
    Run(run::Run),
    /// Write every run's world for an estimator outside kfmc: truth.parquet,
    /// measurements.parquet, initial.parquet and a manifest saying what they mean. The runs
    /// are those `kfmc run` gives its own filters.
    Simulate(simulate::Simulate),
    /// Score estimates made outside kfmc against a `kfmc simulate` folder: writes the tables
    /// `kfmc run` writes (runs, steps, summary, consistency, divergence), with kfmc's own
    /// filters of the spec run beside them on the same runs.
    Score(score::Score),
    /// Stamp estimates files with the truth table they were made on (a user's own runs,
    /// `model.kind = "recorded"`): the truth's content hash as their world stamp.
    Stamp(stamp::Stamp),
    /// Run the study R times with independent master seeds and write power.parquet: per
    /// (cell, filter variant, test) the rejection rate with its 95 % interval and the
    /// statistic's distribution — the false-alarm rate at the true Q and R, the power against
    /// every q_scale/r_scale variant.
    Power(power::Power),
    /// Print the columns of an exchange table for a spec.
    Schema(schema::Schema),
    /// Combine the parts of a sharded study (`run --shard i/n`) into the tables one process
    /// would have written, byte for byte.
    Merge(merge::Merge),
    /// Write Slurm job scripts for a sharded study: an array job (one part per task), a merge
    /// job to run after it (`--dependency=afterok`), and `submit.sh` that submits both.
    Slurm(slurm::Slurm),
    /// Show which parts of a sharded study are complete.
    Status(status::Status),
    /// Run a study and evaluate its `[check]` assertions (consistency verdicts, RMSE bounds,
    /// whiteness) for CI. Exit 0 when all hold, 3 when one fails, 4 when none fails but one
    /// could not be judged on the runs the spec declares (incomplete), 2 for an invalid spec.
    Check(check::Check),
    /// Search a filter's Q scale (and R scale with --tune-r) for consistency or minimum RMSE:
    /// a coarse log grid, then a refinement; writes tuning.parquet.
    Tune(tune::Tune),
    /// Check a spec and print the plan size and its estimated memory and disk, without
    /// running it. Plans above the documented limits are refused (exit 2).
    Validate(validate::Validate),
    /// Print a system's analysis for a spec and write it as TOML: per scenario F, G, H, Q
    /// and R along the clean trajectory, the observability ranks (whole sensor set, each
    /// component, each sensor group), the steady-state gain and its poles, and per filter the
    /// NEES variance inflation ρ and the tests' effective degrees of freedom.
    Describe(describe::Describe),
    /// Print the RMSE summary (and divergence points) of a result folder.
    Summary(summary::Summary),
    /// Draw every figure the tables of a result folder support (read from the Parquet files).
    Plot(plot::Plot),
    /// Write one self-contained HTML report (spec, provenance, tables, figures).
    Report(report::Report),
    /// List the registered systems with their sensors, scenarios and filter kinds.
    List,
    /// PX4 flight logs (ULog): inspect a log, or judge its innovations' NIS with a calibrated
    /// verdict and a regression gate over a folder of flights.
    Ulog(ulog::Ulog),
}

/// The exchange tables `kfmc schema` describes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum SchemaTable {
    /// The estimates file an outside estimator writes.
    Estimates,
    /// `truth.parquet` of the `simulate` command.
    Truth,
    /// `measurements.parquet` of the `simulate` command.
    Measurements,
    /// `initial.parquet` of the `simulate` command.
    Initial,
}

fn schema_text(table: SchemaTable, plan: &Plan) -> String {
    use crate::output::schema::{self, Dtype};
    let l = plan.layout();
    let (q, z, u, w) = (
        l.quantity_names(),
        l.measurement_names(),
        l.input_names(),
        l.world_state_names(),
    );
    let cols = match table {
        SchemaTable::Estimates => plan.estimate_schema(),
        SchemaTable::Truth => schema::truth(&q, &w),
        SchemaTable::Measurements => schema::measurements(&z, &u),
        SchemaTable::Initial => schema::initial(&q),
    };
    let mut s = String::new();
    let mut noted = std::collections::BTreeSet::new();
    for c in &cols {
        // Keys identify a row: a null there is refused, as a value's null means "not given".
        let key =
            ["scenario", "noise_scale", "run", "step", "t", "filter"].contains(&c.name.as_str());
        let ty = match c.dtype {
            Dtype::Str => "string",
            Dtype::F64 if key => "float64",
            Dtype::F64 => "float64 (nullable)",
            Dtype::F32 => "float32 (nullable)",
            Dtype::I64 => "int64",
            Dtype::U64 => "uint64",
            Dtype::Bool => "bool",
        };
        let group = c.name.split('_').next().unwrap_or("");
        let first = noted.insert(group.to_string());
        let variants;
        let note = match (table, group) {
            (SchemaTable::Estimates, "q" | "r") => {
                variants = format!(
                    "  the variant of {}; null for a filter without {} variants",
                    plan.external_variants_text(&c.name).join(", "),
                    c.name
                );
                variants.as_str()
            }
            _ if !first => "",
            (SchemaTable::Estimates, "nu" | "S") => {
                "  optional: the NIS and whiteness tests; nu null where z did not report (NaN is an error)"
            }
            (SchemaTable::Estimates, "A") => {
                "  optional: the calibrated NEES verdict; a step's entries all given or all null"
            }
            (SchemaTable::Estimates, "step") => {
                "  every step 0..=K of a run (0: the prior), or none of them"
            }
            (SchemaTable::Estimates, "P") => "  or L_<i>_<j>, a lower Cholesky factor",
            (SchemaTable::Estimates, "filter") => "  a [[filters]] label with kind = \"external\"",
            (SchemaTable::Estimates, "failed") => {
                "  optional: true from the step the filter failed at (the run is a numerical failure there); a run left out whole is missing, not failed"
            }
            (SchemaTable::Estimates, "quat") => "  a rotation as a unit quaternion (see below)",
            (SchemaTable::Measurements, "z") => {
                "  null where the sensor did not report; null at step 0 (a run starts from its prior, with no measurement)"
            }
            (SchemaTable::Measurements, "u") => {
                "  u_k drives the step from k-1 to k (u_0 drives nothing)"
            }
            _ => "",
        };
        s.push_str(&format!("{:<24} {ty}{note}\n", c.name));
    }
    // The estimates' stamp stays last: a writer reads it off the last two lines.
    s.push_str(&convention_text(
        &crate::system::filter_model::convention_of(plan.system.as_ref()),
    ));
    if table == SchemaTable::Estimates {
        s.push_str(&format!(
            "\nerror convention: {}\nfile metadata (the stamp; kfmc score warns and kfmc check refuses without it): {} = {}, {} = {}\n",
            crate::score::ERROR_CONVENTION,
            crate::score::STAMP_KEY,
            if plan.system.recorded() {
                // A recorded world's stamp is its truth table's content hash.
                "<the truth table's content hash: kfmc stamp --truth TRUTH --spec SPEC FILE>"
                    .to_string()
            } else {
                plan.world_stamp()
            },
            crate::score::SEED_KEY,
            plan.master_seed
        ));
        let names: Vec<String> = q.iter().map(|n| n.to_string()).collect();
        for r in l.rotations() {
            let three = &names[r.first..r.first + 3];
            let quat = crate::score::quaternion_columns(&names, &r);
            let (error, axes) = match r.side {
                crate::linalg::so3::ErrorSide::Right => ("log(R̂ᵀR)", "body"),
                crate::linalg::so3::ErrorSide::Left => ("log(RR̂ᵀ)", "navigation"),
            };
            s.push_str(&format!(
                "rotation {}: {}..{} is the estimate as a unit quaternion (Hamilton, scalar first, body → navigation frame, R = R_z({}) R_y({}) R_x({})); the P_* rows and columns of {} are then the covariance of the rotation error {error} ({} error, {axes} axes) in {}. Instead of the quaternion a file may give est_{}, est_{}, est_{} (ZYX Euler angles) with their Euler-angle covariance, as before rotations were scored: kfmc maps it by the chart Jacobian at the estimate\n",
                three.join(", "),
                quat[0],
                quat[3],
                three[2],
                three[1],
                three[0],
                three.join(", "),
                r.side.name(),
                if r.degrees { "degrees" } else { "radians" },
                three[0],
                three[1],
                three[2],
            ));
        }
    }
    s
}

/// The step convention as `kfmc schema` prints it (and `manifest.toml` records it).
fn convention_text(c: &crate::output::manifest::StepConvention) -> String {
    let list = |v: &[String]| {
        if v.is_empty() {
            "none".to_string()
        } else {
            v.join(", ")
        }
    };
    let mut s = format!(
        "\nstep convention:\n  {}\n  {}\n  {}\n  errors wrapped (angle quantities): {}\n",
        c.transition,
        c.measurement,
        c.row_0,
        list(&c.wrapped_errors)
    );
    if !c.rotation_errors.is_empty() {
        s.push_str(&format!(
            "  rotations (error = rotation vector, not wrapped angle differences): {}\n",
            list(&c.rotation_errors)
        ));
    }
    if !c.continuous_angles.is_empty() {
        s.push_str(&format!(
            "  continuous angles (truth, z and error not wrapped): {}\n",
            list(&c.continuous_angles)
        ));
    }
    if !c.wrapped_innovations.is_empty() {
        s.push_str(&format!(
            "  innovations kfmc's filters wrap to [-pi, pi) (nu_<z> of an estimates file is taken as given): {}\n",
            list(&c.wrapped_innovations)
        ));
    }
    s
}

/// The shard of `--shard i/n`, `--shards n` or the scheduler's environment; a bad value is a
/// usage error at `--shard`.
fn shard_arg(
    spec: &std::path::Path,
    shard: Option<&str>,
    shards: Option<usize>,
) -> anyhow::Result<Option<crate::study::Shard>> {
    crate::merge::shard_from(shard, shards, &|k| std::env::var(k).ok()).map_err(|message| {
        anyhow::Error::from(UsageError {
            flag: "--shard".into(),
            message,
        })
        .context(format!("running {}", spec.display()))
    })
}

use crate::check::Unstamped;

/// Reads the external filters' estimates into `plan`, naming the files on trouble.
fn attach_estimates(
    plan: &mut Plan,
    files: &[PathBuf],
    unstamped: Unstamped,
) -> anyhow::Result<()> {
    crate::check::attach_estimates(plan, files, unstamped)
        .map_err(|e| anyhow::Error::from(e).context("reading the estimates"))
}

/// Each filter label once, in spec order, with its kind and how many variants (q_scale ×
/// r_scale) it runs: a label with variants is one filter of the spec, not several.
fn filter_labels(plan: &Plan) -> Vec<String> {
    let mut seen: Vec<(&str, &str, usize)> = Vec::new();
    for f in &plan.filters {
        match seen.iter_mut().find(|(label, _, _)| *label == f.label) {
            Some((_, _, n)) => *n += 1,
            None => seen.push((&f.label, &f.kind, 1)),
        }
    }
    seen.into_iter()
        .map(|(label, kind, n)| match n {
            1 => format!("{label} ({kind})"),
            n => format!("{label} ({kind}, {n} variants)"),
        })
        .collect()
}

fn describe(plan: &Plan) -> String {
    let size = plan.size();
    let filters = filter_labels(plan);
    let scales = match plan.noise_scales.as_slice() {
        [one] => format!("{one}"),
        s => format!("{} values from {} to {}", s.len(), s[0], s[s.len() - 1]),
    };
    format!(
        "{name}: {cells} cells × {runs} runs = {total} runs, {fr} filter runs, {steps} filter steps\n  {resources}\n  scenarios: {scen}\n  filters: {filters}\n  noise scales: {scales}\n  master seed: {seed}\n  output: {out}",
        resources = crate::study::resources(plan).describe(),
        name = plan.name,
        cells = size.cells,
        runs = plan.runs,
        total = size.runs,
        fr = size.filter_runs,
        steps = size.filter_steps,
        scen = plan
            .scenarios
            .iter()
            .map(|s| s.name.as_str())
            .collect::<Vec<_>>()
            .join(", "),
        filters = filters.join(", "),
        seed = plan.master_seed,
        out = plan.output.display(),
    )
}

fn list(registry: &Registry) -> String {
    let mut s = String::from("systems (model.kind):\n");
    for sys in registry.systems() {
        s.push_str(&format!("  {:<18} {}\n", sys.kind(), sys.catalogue().about));
    }
    for sys in registry.systems() {
        let cat = sys.catalogue();
        s.push_str(&format!("\n{} — {}\n", sys.kind(), cat.about));
        for (title, entries) in &cat.sections {
            s.push_str(&format!("  {title}:\n"));
            let width = entries
                .iter()
                .map(|(n, _)| n.chars().count())
                .max()
                .unwrap_or(0);
            for (name, about) in entries {
                s.push_str(&format!("    {name:<width$}  {about}\n"));
            }
        }
    }
    s
}

/// The plan `kfmc score DIR` runs: [`crate::simulate::scoring_plan`].
#[deprecated(note = "use kfmc::simulate::scoring_plan")]
pub fn score_plan(
    dir: &std::path::Path,
    out: Option<PathBuf>,
    registry: &Registry,
) -> anyhow::Result<Plan> {
    Ok(crate::simulate::scoring_plan(dir, out, registry)?)
}

/// The whole command line for the systems of `registry`: parses the process's arguments,
/// runs the command and returns the exit code. A downstream crate's `main` is
/// `kfmc::cli::main_with(kfmc::systems::builtin().with(MySystem))`.
/// The command line takes the registry's name and version ([`Registry::named`], kfmc's own
/// unless set).
pub fn main_with(registry: Registry) -> ExitCode {
    use clap::FromArgMatches;
    let cli = match Cli::from_arg_matches(&command_of(registry.program()).get_matches()) {
        Ok(cli) => cli,
        Err(e) => e.exit(),
    };
    crate::runner::stop_on_signals();
    run(cli, &registry)
}

/// kfmc's command line under `program`'s name and version: every "kfmc" of its help (the
/// commands' and the arguments' texts, the usage line) names the program instead, and
/// `--version` prints the program's version with kfmc's in parentheses.
pub fn command_of(program: Program) -> clap::Command {
    use clap::CommandFactory;
    if program == Program::KFMC {
        return Cli::command();
    }
    // clap keeps borrowed strings for the program's lifetime; this runs once per process.
    let version: &'static str = Box::leak(
        format!("{} (kfmc {})", program.version, env!("CARGO_PKG_VERSION")).into_boxed_str(),
    );
    renamed(Cli::command(), program.name)
        .name(program.name)
        .bin_name(program.name)
        .display_name(program.name)
        .version(version)
}

/// `cmd` with "kfmc" as a word (not `kfmc.world_stamp`, `kfmc-result`) replaced by `name` in
/// its texts, its arguments' and its subcommands', recursively.
fn renamed(mut cmd: clap::Command, name: &str) -> clap::Command {
    let text = |s: &clap::builder::StyledStr| rename_word(&s.to_string(), "kfmc", name);
    if let Some(t) = cmd.get_about().map(text) {
        cmd = cmd.about(t);
    }
    if let Some(t) = cmd.get_long_about().map(text) {
        cmd = cmd.long_about(t);
    }
    if let Some(t) = cmd.get_before_help().map(text) {
        cmd = cmd.before_help(t);
    }
    if let Some(t) = cmd.get_after_help().map(text) {
        cmd = cmd.after_help(t);
    }
    if let Some(t) = cmd.get_after_long_help().map(text) {
        cmd = cmd.after_long_help(t);
    }
    cmd = cmd.mut_args(|mut a| {
        if let Some(t) = a.get_help().map(text) {
            a = a.help(t);
        }
        if let Some(t) = a.get_long_help().map(text) {
            a = a.long_help(t);
        }
        a
    });
    let subcommands: Vec<String> = cmd
        .get_subcommands()
        .map(|c| c.get_name().to_string())
        .collect();
    for sub in subcommands {
        cmd = cmd.mut_subcommand(sub, |c| renamed(c, name));
    }
    cmd
}

/// `text` with every whole word `word` replaced by `by`: a word is not part of a longer
/// identifier, a file name or a dotted key (`kfmc.world_stamp`, `kfmc-result`, `kfmc_x`).
fn rename_word(text: &str, word: &str, by: &str) -> String {
    let joins = |c: char| c.is_alphanumeric() || matches!(c, '_' | '.' | '-' | '/');
    let mut out = String::with_capacity(text.len());
    let mut rest = text;
    let mut before: Option<char> = None;
    while let Some(i) = rest.find(word) {
        let head = &rest[..i];
        let prev = head.chars().next_back().or(before);
        let tail = &rest[i + word.len()..];
        // A sentence may end with the word: "." followed by a space or the end is not a key.
        let next = tail.chars().next();
        let dotted_key = next == Some('.')
            && tail[1..]
                .chars()
                .next()
                .is_some_and(|c| c.is_alphanumeric() || c == '_');
        let continues = next.is_some_and(|c| c.is_alphanumeric() || matches!(c, '_' | '-' | '/'));
        let whole = !(prev.is_some_and(joins) || continues || dotted_key);
        out.push_str(head);
        out.push_str(if whole { by } else { word });
        before = Some(word.chars().next_back().unwrap_or(' '));
        rest = tail;
    }
    out.push_str(rest);
    out
}

/// [`main_with`] for a downstream binary with its own name and version:
/// `kfmc::cli::main_as(Program { name: "mytool", version: env!("CARGO_PKG_VERSION") }, registry)`.
///
/// The registry's plans then carry `program` ([`Registry::named`]): the manifests, the
/// report's "reproduce" line and the `check`/`tune` headers name it.
pub fn main_as(program: Program, registry: Registry) -> ExitCode {
    main_with(registry.named(program))
}

/// The whole command line from `args` (the program name first, as `std::env::args`), for an
/// embedding that is not `main` (the Python module's `kfmc` script): parses with clap's
/// `try_parse_from`, so help, version and usage errors are printed exactly as the binary
/// prints them but returned as an exit code instead of ending the process, runs the command
/// with the binary's signal handling, flushes stdout and returns the binary's exit code.
pub fn main_from_args<I, T>(args: I, registry: &Registry) -> u8
where
    I: IntoIterator<Item = T>,
    T: Into<std::ffi::OsString> + Clone,
{
    use std::io::Write;
    let code = match Cli::try_parse_from(args) {
        Ok(cli) => {
            crate::runner::stop_on_signals();
            run_code(cli, registry)
        }
        Err(e) => {
            // Help and version go to stdout with code 0, usage errors to stderr with code 2,
            // as `Error::exit` does.
            let _ = e.print();
            u8::try_from(e.exit_code()).unwrap_or(EXIT_INVALID_SPEC)
        }
    };
    let _ = std::io::stdout().flush();
    let _ = std::io::stderr().flush();
    code
}

/// Runs a parsed command line and returns the process exit code.
pub fn run(cli: Cli, registry: &Registry) -> ExitCode {
    ExitCode::from(run_code(cli, registry))
}

/// [`run()`], returning the exit code as a number.
pub fn run_code(cli: Cli, registry: &Registry) -> u8 {
    match dispatch(cli, registry) {
        Ok(()) => EXIT_OK,
        Err(e) => {
            if let Some(c) = e.downcast_ref::<CheckFailed>() {
                // The report already said what failed: a judged failure outranks a case that
                // could not be judged.
                return if c.failed > 0 {
                    EXIT_CHECK_FAILED
                } else {
                    EXIT_CHECK_INCOMPLETE
                };
            }
            let code = match e.downcast_ref::<KfmcError>() {
                _ if e.downcast_ref::<UsageError>().is_some() => EXIT_INVALID_SPEC,
                Some(KfmcError::Spec(_)) => EXIT_INVALID_SPEC,
                Some(KfmcError::Output(
                    crate::error::OutputError::Interrupted
                    | crate::error::OutputError::InterruptedCheckpointed { .. },
                )) => EXIT_INTERRUPTED,
                _ => EXIT_FAILURE,
            };
            eprintln!("error: {e:#}");
            code
        }
    }
}

/// Writes to stdout; a reader that went away (`kfmc summary DIR | head -1`) is not an error,
/// the rest of the output is simply not wanted.
fn emit(text: &str) {
    use std::io::Write;
    let mut out = std::io::stdout().lock();
    let _ = out.write_all(text.as_bytes()).and_then(|()| out.flush());
}

macro_rules! outln {
    ($($arg:tt)*) => {
        emit(&format!("{}\n", format!($($arg)*)))
    };
}

// One file per command: its arguments and what it does (parse → library call → print).
pub mod check;
pub mod describe;
pub mod list;
pub mod merge;
pub mod plot;
pub mod power;
pub mod report;
pub mod run;
pub mod schema;
pub mod score;
pub mod simulate;
pub mod slurm;
pub mod stamp;
pub mod status;
pub mod tune;
pub mod ulog;
pub mod validate;

/// Lists the tables a command wrote with their row counts.
fn print_tables(tables: &[(String, u64)]) {
    for (name, rows) in tables {
        outln!("  {name}.parquet  {rows} rows");
    }
}

fn plot_dir(dir: &std::path::Path, opts: &PlotOptions) -> anyhow::Result<Vec<PathBuf>> {
    crate::plot::plot_all(dir, opts)
        .map_err(KfmcError::from)
        .map_err(|e| anyhow::Error::from(e).context(format!("plotting {}", dir.display())))
}

fn dispatch(cli: Cli, registry: &Registry) -> anyhow::Result<()> {
    match cli.command {
        Command::Run(c) => c.execute(registry),
        Command::Simulate(c) => c.execute(registry),
        Command::Score(c) => c.execute(registry),
        Command::Stamp(c) => c.execute(registry),
        Command::Power(c) => c.execute(registry),
        Command::Schema(c) => c.execute(registry),
        Command::Merge(c) => c.execute(registry),
        Command::Slurm(c) => c.execute(registry),
        Command::Status(c) => c.execute(),
        Command::Check(c) => c.execute(registry),
        Command::Tune(c) => c.execute(registry),
        Command::Validate(c) => c.execute(registry),
        Command::Describe(c) => c.execute(registry),
        Command::Summary(c) => c.execute(),
        Command::Plot(c) => c.execute(),
        Command::Report(c) => c.execute(),
        Command::List => list::execute(registry),
        Command::Ulog(c) => c.execute(),
    }
}
