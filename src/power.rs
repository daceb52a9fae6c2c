//! `kfmc power`: how often each consistency test rejects, over independent replications of a
//! whole study.
//!
//! Whether a test "detects" a mistuning is a rate, not one master seed's outcome. `power` runs
//! the study R times with independent master seeds (replication r uses
//! `run_seed(base, "power", r)`, so the table is a function of R and the base seed alone, not
//! of the thread count), folds each replication's consistency rows and writes
//! `power.parquet`: per (cell, filter variant, test, runs, α) the rejection rate with its
//! Clopper–Pearson 95 % interval and the distribution of the statistic. Run on the spec's own
//! `q_scale`/`r_scale` variants, the row at the true Q and R is the test's false-alarm rate
//! and every other row its power against that mistuning.
//!
//! Memory is bounded by one replication's tables plus R statistics per row.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::{Instant, SystemTime, UNIX_EPOCH};

use statrs::distribution::{Beta, ContinuousCDF};

use crate::error::{KfmcError, OutputError, SpecErrors};
use crate::experiment::Plan;
use crate::experiment::plan::ConsistencyPlan;
use crate::metrics::quantile_sorted;
use crate::output::folder::StudyFolder;
use crate::output::manifest::StudyKind;
use crate::output::schema::{ColumnDef, Dtype};
use crate::output::table::read;
use crate::output::{TableWriter, Value};
use crate::runner::RunObserver;
use crate::sequential::{Decision, Gate};
use crate::sim::seed::run_seed;
use crate::study::{ExecOptions, StudyReport};

/// The master seed of replication `r` of a power study with base seed `base`.
pub fn replication_seed(base: u64, r: u64) -> u64 {
    run_seed(base, "power", r)
}

/// `power.parquet`'s columns.
pub fn columns() -> Vec<ColumnDef> {
    let c = |n: &str, dtype| ColumnDef {
        name: n.into(),
        dtype,
    };
    vec![
        c("scenario", Dtype::Str),
        c("noise_scale", Dtype::F64),
        c("filter", Dtype::Str),
        c("q_scale", Dtype::F64),
        c("r_scale", Dtype::F64),
        c("test", Dtype::Str),
        c("runs", Dtype::I64),
        c("alpha", Dtype::F64),
        c("replications", Dtype::I64),
        c("rejections", Dtype::I64),
        c("rejection_rate", Dtype::F64),
        c("rejection_ci_lo", Dtype::F64),
        c("rejection_ci_hi", Dtype::F64),
        c("statistic_mean", Dtype::F64),
        c("statistic_p05", Dtype::F64),
        c("statistic_p50", Dtype::F64),
        c("statistic_p95", Dtype::F64),
        c("direction_optimistic", Dtype::I64),
        c("direction_pessimistic", Dtype::I64),
        c("sequential", Dtype::Bool),
        c("runs_used_mean", Dtype::F64),
        c("runs_used_p05", Dtype::F64),
        c("runs_used_p95", Dtype::F64),
    ]
}

/// The exact (Clopper–Pearson) two-sided 95 % interval of a binomial rate k/n.
pub fn clopper_pearson(k: u64, n: u64) -> (f64, f64) {
    let a = 0.05;
    let beta = |p: f64, x: f64, y: f64| Beta::new(x, y).map_or(f64::NAN, |b| b.inverse_cdf(p));
    let lo = if k == 0 {
        0.0
    } else {
        beta(a / 2.0, k as f64, (n - k + 1) as f64)
    };
    let hi = if k == n {
        1.0
    } else {
        beta(1.0 - a / 2.0, (k + 1) as f64, (n - k) as f64)
    };
    (lo, hi)
}

/// What the rows of one (cell, variant, test, runs, α) accumulate.
#[derive(Default)]
struct Tally {
    order: usize,
    rejections: u64,
    seen: u64,
    statistics: Vec<f64>,
    optimistic: u64,
    pessimistic: u64,
    /// Runs each judged replication used (a sequential gate's stopping look; else `runs`).
    runs_used: Vec<f64>,
}

/// (scenario, noise-scale bits, filter, q bits, r bits, test, runs, α bits, sequential).
type Key = (String, u64, String, u64, u64, String, i64, u64, bool);

/// Runs `replications` replications of `plan` and writes `power.parquet` into `out`.
pub fn power(
    plan: &Plan,
    replications: usize,
    base_seed: u64,
    out: &Path,
    opts: &ExecOptions,
    observer: &dyn RunObserver,
) -> Result<StudyReport, KfmcError> {
    power_with(
        plan,
        replications,
        base_seed,
        out,
        opts,
        observer,
        &PowerExtras::default(),
    )
}

/// What a power study measures beyond the spec's own tests.
#[derive(Debug, Clone, Default)]
pub struct PowerExtras<'a> {
    /// A sequential gate applied to every cell and filter variant of each replication (its
    /// looks are evaluated as subsets of the same runs, so the gate sees exactly the first
    /// runs of the fixed study): a `verdict` row with `sequential` true, the gate's rejection
    /// rate and the runs it used.
    pub gate: Option<&'a Gate>,
    /// Run counts at which every test is also evaluated (on the first N runs of each cell),
    /// as the spec's `[[consistency.subsets]]` would: the power curve over N.
    pub curve: Vec<usize>,
}

/// As [`power`], measuring `extras` too.
pub fn power_with(
    plan: &Plan,
    replications: usize,
    base_seed: u64,
    out: &Path,
    opts: &ExecOptions,
    observer: &dyn RunObserver,
    extras: &PowerExtras<'_>,
) -> Result<StudyReport, KfmcError> {
    let gate = extras.gate;
    let started = Instant::now();
    let started_unix_s = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_secs());
    let folder = StudyFolder::open_with(
        out,
        StudyKind::Power,
        opts.force,
        &crate::study::inputs(plan),
    )?;
    // Each replication's study, written under a temporary name of this process's own and
    // removed once its consistency table is folded in.
    let scratch: PathBuf = out.join(crate::output::atomic::temp_name("power-replication"));
    let mut one = plan.clone();
    one.trace_runs = 0;
    one.export_estimates = false;
    one.output = scratch.clone();
    one.consistency
        .get_or_insert(ConsistencyPlan::at_level(plan.alpha));
    let consistency = one.consistency.as_mut().expect("set above");
    for &n in &extras.curve {
        let subset = (n, plan.alpha);
        if n < plan.runs && !consistency.subsets.contains(&subset) {
            consistency.subsets.push(subset);
        }
    }
    let mut look_subsets = Vec::new();
    if let Some(gate) = gate {
        for &n in &gate.looks[..gate.looks.len() - 1] {
            let subset = (n, plan.alpha);
            if !consistency.subsets.contains(&subset) {
                consistency.subsets.push(subset);
                look_subsets.push(n as i64);
            }
        }
    }
    observer.on_start((replications * plan.size().runs) as u64);
    let mut tallies: BTreeMap<Key, Tally> = BTreeMap::new();
    for r in 0..replications {
        one.master_seed = replication_seed(base_seed, r as u64);
        let report = crate::study::run(&one, opts, &Counted(observer));
        let report = match report {
            Ok(rep) => rep,
            Err(e) => {
                let _ = std::fs::remove_dir_all(&scratch);
                return Err(e);
            }
        };
        let consistency = report.output.join("consistency.parquet");
        fold(&consistency, &mut tallies, &look_subsets)?;
        if let Some(gate) = gate {
            fold_sequential(&consistency, gate, plan.alpha, &mut tallies)?;
        }
        std::fs::remove_dir_all(&scratch).map_err(|source| OutputError::Io {
            action: "cannot remove",
            path: scratch.clone(),
            source,
        })?;
    }
    observer.on_finish();

    let mut table = TableWriter::create(out, "power", columns())?;
    let mut rows: Vec<(&Key, &mut Tally)> = tallies.iter_mut().collect();
    rows.sort_by_key(|(_, t)| t.order);
    for (k, t) in rows {
        t.statistics.sort_by(f64::total_cmp);
        t.runs_used.sort_by(f64::total_cmp);
        let n = t.seen;
        let (lo, hi) = clopper_pearson(t.rejections, n);
        let mean = (!t.statistics.is_empty())
            .then(|| t.statistics.iter().sum::<f64>() / t.statistics.len() as f64);
        table.push(&[
            Value::Str(&k.0),
            Value::F64(Some(f64::from_bits(k.1))),
            Value::Str(&k.2),
            // An external filter's null multipliers were keyed as NaN: null again.
            Value::F64(Some(f64::from_bits(k.3)).filter(|v| !v.is_nan())),
            Value::F64(Some(f64::from_bits(k.4)).filter(|v| !v.is_nan())),
            Value::Str(&k.5),
            Value::I64(Some(k.6)),
            Value::F64(Some(f64::from_bits(k.7))),
            Value::I64(Some(n as i64)),
            Value::I64(Some(t.rejections as i64)),
            Value::F64(Some(t.rejections as f64 / n.max(1) as f64)),
            Value::F64(Some(lo)),
            Value::F64(Some(hi)),
            Value::F64(mean),
            Value::F64(quantile_sorted(&t.statistics, 0.05)),
            Value::F64(quantile_sorted(&t.statistics, 0.50)),
            Value::F64(quantile_sorted(&t.statistics, 0.95)),
            Value::I64(Some(t.optimistic as i64)),
            Value::I64(Some(t.pessimistic as i64)),
            Value::Bool(Some(k.8)),
            Value::F64(
                (!t.runs_used.is_empty())
                    .then(|| t.runs_used.iter().sum::<f64>() / t.runs_used.len() as f64),
            ),
            Value::F64(quantile_sorted(&t.runs_used, 0.05)),
            Value::F64(quantile_sorted(&t.runs_used, 0.95)),
        ])?;
    }
    let finished = vec![table.finish()?];
    let wall_s = started.elapsed().as_secs_f64();
    let mut manifest = crate::study::manifest_for(
        plan,
        opts,
        started_unix_s,
        wall_s,
        0..plan.scenarios.len() * plan.noise_scales.len(),
    );
    manifest.kind = Some(StudyKind::Power);
    manifest.master_seed = base_seed;
    manifest.runs = (replications * plan.size().runs) as u64;
    let tables = folder.commit(finished, manifest)?;
    Ok(StudyReport {
        output: out.to_path_buf(),
        tables,
        wall_s,
        runs: (replications * plan.size().runs) as u64,
        cells_resumed: 0,
    })
}

/// Forwards the replications' progress to one bar over all of them.
struct Counted<'a>(&'a dyn RunObserver);

impl RunObserver for Counted<'_> {
    fn on_start(&self, _units: u64) {}
    fn on_units_done(&self, n: u64) {
        self.0.on_units_done(n);
    }
    fn on_finish(&self) {}
}

/// Adds one replication's consistency rows to the tallies, leaving out the evaluations at
/// `skip_runs` (looks a sequential gate added, which the spec did not ask for).
fn fold(
    path: &Path,
    tallies: &mut BTreeMap<Key, Tally>,
    skip_runs: &[i64],
) -> Result<(), OutputError> {
    let df = read(path)?;
    let bad = |e| OutputError::Polars {
        action: "unexpected columns in",
        path: path.to_path_buf(),
        source: e,
    };
    let s = |c: &str| df.column(c).and_then(|c| c.str().cloned()).map_err(bad);
    let f = |c: &str| df.column(c).and_then(|c| c.f64().cloned()).map_err(bad);
    let (scen, filt, test, dir) = (s("scenario")?, s("filter")?, s("test")?, s("direction")?);
    let (noise, q, r, alpha, stat) = (
        f("noise_scale")?,
        f("q_scale")?,
        f("r_scale")?,
        f("alpha")?,
        f("statistic")?,
    );
    let runs = df
        .column("runs")
        .and_then(|c| c.i64().cloned())
        .map_err(bad)?;
    let pass = df
        .column("pass")
        .and_then(|c| c.bool().cloned())
        .map_err(bad)?;
    let next = tallies.len();
    for i in 0..df.height() {
        if skip_runs.contains(&runs.get(i).unwrap_or(0)) {
            continue;
        }
        let bits = |v: Option<f64>| v.unwrap_or(f64::NAN).to_bits();
        let key = (
            scen.get(i).unwrap_or("").to_string(),
            bits(noise.get(i)),
            filt.get(i).unwrap_or("").to_string(),
            bits(q.get(i)),
            bits(r.get(i)),
            test.get(i).unwrap_or("").to_string(),
            runs.get(i).unwrap_or(0),
            bits(alpha.get(i)),
            false,
        );
        let t = tallies.entry(key).or_insert_with(|| Tally {
            order: next + i,
            ..Default::default()
        });
        // A test that could not be computed (null pass) is neither a rejection nor a count.
        let Some(p) = pass.get(i) else { continue };
        t.seen += 1;
        t.rejections += u64::from(!p);
        t.runs_used.push(runs.get(i).unwrap_or(0) as f64);
        if let Some(v) = stat.get(i) {
            t.statistics.push(v);
        }
        match dir.get(i) {
            Some("optimistic") => t.optimistic += 1,
            Some("pessimistic") => t.pessimistic += 1,
            _ => {}
        }
    }
    Ok(())
}

/// Applies the sequential `gate` to one replication's verdict rows (at level `alpha`): per
/// cell and filter variant, the looks in order until one decides; a look whose verdict could
/// not be computed leaves that replication unjudged (never a pass).
fn fold_sequential(
    path: &Path,
    gate: &Gate,
    alpha: f64,
    tallies: &mut BTreeMap<Key, Tally>,
) -> Result<(), OutputError> {
    let df = read(path)?;
    let bad = |e| OutputError::Polars {
        action: "unexpected columns in",
        path: path.to_path_buf(),
        source: e,
    };
    let s = |c: &str| df.column(c).and_then(|c| c.str().cloned()).map_err(bad);
    let f = |c: &str| df.column(c).and_then(|c| c.f64().cloned()).map_err(bad);
    let (scen, filt, test, dir) = (s("scenario")?, s("filter")?, s("test")?, s("direction")?);
    let (noise, q, r, a, p) = (
        f("noise_scale")?,
        f("q_scale")?,
        f("r_scale")?,
        f("alpha")?,
        f("p_value")?,
    );
    let runs = df
        .column("runs")
        .and_then(|c| c.i64().cloned())
        .map_err(bad)?;
    let bits = |v: Option<f64>| v.unwrap_or(f64::NAN).to_bits();
    // Per (cell, variant): the verdict's p-value (None: not computed) and direction per look.
    type Looks = Vec<Option<(Option<f64>, Option<String>)>>;
    let mut cells: Vec<(Key, Looks)> = Vec::new();
    for i in 0..df.height() {
        if test.get(i) != Some(crate::metrics::consistency::VERDICT)
            || a.get(i).map(f64::to_bits) != Some(alpha.to_bits())
        {
            continue;
        }
        let n = runs.get(i).unwrap_or(0);
        let Some(look) = gate.looks.iter().position(|&l| l as i64 == n) else {
            continue;
        };
        let key = (
            scen.get(i).unwrap_or("").to_string(),
            bits(noise.get(i)),
            filt.get(i).unwrap_or("").to_string(),
            bits(q.get(i)),
            bits(r.get(i)),
            crate::metrics::consistency::VERDICT.to_string(),
            *gate.looks.last().expect("a gate has looks") as i64,
            alpha.to_bits(),
            true,
        );
        let at = match cells.iter().position(|(k, _)| *k == key) {
            Some(at) => at,
            None => {
                cells.push((key, vec![None; gate.looks.len()]));
                cells.len() - 1
            }
        };
        cells[at].1[look] = Some((p.get(i), dir.get(i).map(str::to_string)));
    }
    let next = tallies.len();
    for (order, (key, looks)) in cells.into_iter().enumerate() {
        let t = tallies.entry(key).or_insert_with(|| Tally {
            order: next + order,
            ..Default::default()
        });
        for (k, look) in looks.iter().enumerate() {
            // A look without a verdict (missing or not computable): unjudged.
            let Some((Some(verdict_p), direction)) = look else {
                break;
            };
            match gate.decide(k, *verdict_p) {
                Decision::Continue => continue,
                decision => {
                    t.seen += 1;
                    t.runs_used.push(gate.looks[k] as f64);
                    t.statistics.push(*verdict_p);
                    if decision == Decision::Reject {
                        t.rejections += 1;
                        match direction.as_deref() {
                            Some("optimistic") => t.optimistic += 1,
                            Some("pessimistic") => t.pessimistic += 1,
                            _ => {}
                        }
                    }
                    break;
                }
            }
        }
    }
    Ok(())
}

/// A power study as `kfmc power` (and Python's `kfmc.power`) asks for it, beyond the plan.
#[derive(Debug, Clone, Default)]
pub struct PowerRequest {
    /// Independent replications of the whole study (at least 1).
    pub replications: usize,
    /// The folder of power.parquet; `None`: `<the plan's output>/power`.
    pub out: Option<PathBuf>,
    /// Accept a study larger than the limits on filter steps.
    pub allow_large: bool,
    /// A group-sequential gate measured beside the fixed verdict (built by the front end from
    /// its flags or keywords, which it names in its errors).
    pub gate: Option<Gate>,
    /// How many runs are needed for a power against a variant: the tests are also evaluated
    /// on the first N/10, 2N/10, … runs of each cell, and the answer read off the curve.
    pub target: Option<PowerTarget>,
}

/// "What N reaches this power against this variant?" (`--target-power P --against …`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PowerTarget {
    /// The power wanted, in (0, 1).
    pub power: f64,
    /// The mistuned variant it is wanted against.
    pub against: Against,
}

impl PowerTarget {
    /// A target of `power` against `against`; `power` must lie in (0, 1).
    pub fn new(power: f64, against: Against) -> Result<Self, String> {
        if power > 0.0 && power < 1.0 {
            Ok(Self { power, against })
        } else {
            Err(format!("must lie in (0, 1); got {power}"))
        }
    }
}

/// A filter variant by its multipliers, `q_scale=0.9[,r_scale=1]`; an axis not named
/// matches any value.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Against {
    /// The variant's Q multiplier, if named.
    pub q_scale: Option<f64>,
    /// The variant's R multiplier, if named.
    pub r_scale: Option<f64>,
}

impl Against {
    /// Whether a variant with these multipliers is the one meant.
    pub fn matches(&self, q_scale: Option<f64>, r_scale: Option<f64>) -> bool {
        let axis = |want: Option<f64>, got: Option<f64>| want.is_none_or(|w| got == Some(w));
        axis(self.q_scale, q_scale) && axis(self.r_scale, r_scale)
    }
}

impl std::str::FromStr for Against {
    type Err = String;

    fn from_str(text: &str) -> Result<Self, String> {
        let mut against = Against::default();
        for pair in text.split(',') {
            let (key, value) = pair
                .split_once('=')
                .ok_or_else(|| format!("`{pair}` is not KEY=VALUE (e.g. q_scale=0.9)"))?;
            let number: f64 = value
                .trim()
                .parse()
                .ok()
                .filter(|v: &f64| v.is_finite() && *v > 0.0)
                .ok_or_else(|| format!("`{value}` is not a positive number"))?;
            match key.trim() {
                "q_scale" => against.q_scale = Some(number),
                "r_scale" => against.r_scale = Some(number),
                other => {
                    return Err(format!(
                        "unknown key `{other}` (expected q_scale or r_scale)"
                    ));
                }
            }
        }
        Ok(against)
    }
}

impl std::fmt::Display for Against {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let named: Vec<String> = [("q_scale", self.q_scale), ("r_scale", self.r_scale)]
            .into_iter()
            .filter_map(|(key, v)| v.map(|v| format!("{key}={v}")))
            .collect();
        if named.is_empty() {
            f.write_str("any variant")
        } else {
            f.write_str(&named.join(","))
        }
    }
}

/// What [`run`] measured.
#[derive(Debug, Clone)]
pub struct PowerOutcome {
    /// The power study's folder, tables and timing.
    pub report: StudyReport,
    /// With a [`PowerTarget`]: the power curves of the variants it names.
    pub runs_needed: Option<RunsNeeded>,
}

/// The answer to a [`PowerTarget`]: each matching variant's power curve over N. Its
/// `Display` is the text `kfmc power --target-power` prints.
#[derive(Debug, Clone, PartialEq)]
pub struct RunsNeeded {
    /// The question.
    pub target: PowerTarget,
    /// One curve per (cell, variant) the target names, with at least one point.
    pub curves: Vec<PowerCurve>,
}

impl std::fmt::Display for RunsNeeded {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let (target, against) = (self.target.power, self.target.against);
        for c in &self.curves {
            let noise = if c.noise_scale == 1.0 {
                String::new()
            } else {
                format!(", noise ×{}", c.noise_scale)
            };
            writeln!(
                f,
                "{} ({against}), scenario {}{noise}: power of the verdict by runs per cell",
                c.filter, c.scenario
            )?;
            for p in &c.points {
                writeln!(
                    f,
                    "  N = {:>6}: {:.3} [{:.3}, {:.3}] over {} replications",
                    p.runs, p.rate, p.interval.0, p.interval.1, p.replications
                )?;
            }
            let (point, sure) = c.smallest_runs(target);
            match point {
                Some(p) => write!(
                    f,
                    "  smallest N with power ≥ {target}: {} (rate {:.3} [{:.3}, {:.3}])",
                    p.runs, p.rate, p.interval.0, p.interval.1
                )?,
                None => write!(
                    f,
                    "  power {target} is not reached at the spec's {} runs: raise `runs`",
                    c.points.last().map_or(0, |p| p.runs)
                )?,
            }
            match (point, sure) {
                (Some(_), Some(q)) => writeln!(
                    f,
                    "; its interval's lower end reaches {target} at N = {}",
                    q.runs
                )?,
                (Some(_), None) => writeln!(f, "; no N here has its interval above the target")?,
                _ => writeln!(f)?,
            }
        }
        Ok(())
    }
}

/// Runs a power study as `kfmc power` does: checks the request against the plan (at least
/// one replication, within the limits unless `allow_large`, a target's variant present among
/// the plan's filters) before any run, measures the replications (with the gate and the
/// target's curve), writes power.parquet into the request's folder and, with a target, reads
/// the runs needed off it.
pub fn run(
    plan: &Plan,
    request: &PowerRequest,
    exec: &ExecOptions,
    observer: &dyn RunObserver,
) -> Result<PowerOutcome, KfmcError> {
    let replications = request.replications;
    if replications == 0 {
        return Err(SpecErrors(vec![plan.err(
            "replications",
            "must be at least 1 (`--replications`, `-R`)",
        )])
        .into());
    }
    crate::study::check_replications(plan, replications, request.allow_large)?;
    if let Some(target) = &request.target
        && !plan.filters.iter().any(|f| {
            let (q, r) = f.multipliers().unzip();
            target.against.matches(q, r)
        })
    {
        return Err(SpecErrors(vec![plan.err(
            "filters",
            format!(
                "no filter variant has {}: add it to a filter's q_scale / r_scale list \
                 (`--against` names a variant the power is wanted against)",
                target.against
            ),
        )])
        .into());
    }
    let out = request
        .out
        .clone()
        .unwrap_or_else(|| plan.output.join("power"));
    let mut plan = plan.clone();
    plan.output = out.clone();
    let extras = PowerExtras {
        gate: request.gate.as_ref(),
        curve: match request.target {
            Some(_) => crate::sequential::default_looks(plan.runs, 10),
            None => Vec::new(),
        },
    };
    let report = power_with(
        &plan,
        replications,
        plan.master_seed,
        &out,
        exec,
        observer,
        &extras,
    )?;
    let runs_needed = match request.target {
        Some(target) => Some(RunsNeeded {
            target,
            curves: power_curves(&report.output.join("power.parquet"), target.against)?,
        }),
        None => None,
    };
    Ok(PowerOutcome {
        report,
        runs_needed,
    })
}

/// The fixed verdict's rejection rate at one run count, from `power.parquet`.
#[derive(Debug, Clone, PartialEq)]
pub struct CurvePoint {
    /// Runs per cell.
    pub runs: usize,
    /// Replications judged.
    pub replications: u64,
    /// Rejection rate of the verdict.
    pub rate: f64,
    /// Its Clopper–Pearson 95 % interval.
    pub interval: (f64, f64),
}

/// One filter variant's power curve over the run counts of a power table.
#[derive(Debug, Clone, PartialEq)]
pub struct PowerCurve {
    /// Scenario.
    pub scenario: String,
    /// Noise scale.
    pub noise_scale: f64,
    /// Filter label.
    pub filter: String,
    /// The variant's Q multiplier (null for an outside filter).
    pub q_scale: Option<f64>,
    /// The variant's R multiplier.
    pub r_scale: Option<f64>,
    /// The verdict's rejection rate at each run count, increasing.
    pub points: Vec<CurvePoint>,
}

impl PowerCurve {
    /// The smallest run count whose rate reaches `target`, and the smallest whose interval's
    /// lower end does (the conservative answer).
    pub fn smallest_runs(&self, target: f64) -> (Option<&CurvePoint>, Option<&CurvePoint>) {
        (
            self.points.iter().find(|p| p.rate >= target),
            self.points.iter().find(|p| p.interval.0 >= target),
        )
    }
}

/// The fixed verdict's power curves in `power.parquet` of the variants whose `q_scale` and
/// `r_scale` equal `against` (a `None` matches any).
pub fn power_curves(path: &Path, against: Against) -> Result<Vec<PowerCurve>, OutputError> {
    let df = read(path)?;
    let bad = |e| OutputError::Polars {
        action: "unexpected columns in",
        path: path.to_path_buf(),
        source: e,
    };
    let s = |c: &str| df.column(c).and_then(|c| c.str().cloned()).map_err(bad);
    let f = |c: &str| df.column(c).and_then(|c| c.f64().cloned()).map_err(bad);
    let i = |c: &str| df.column(c).and_then(|c| c.i64().cloned()).map_err(bad);
    let (scen, filt, test) = (s("scenario")?, s("filter")?, s("test")?);
    let (noise, q, r, rate, lo, hi) = (
        f("noise_scale")?,
        f("q_scale")?,
        f("r_scale")?,
        f("rejection_rate")?,
        f("rejection_ci_lo")?,
        f("rejection_ci_hi")?,
    );
    let (runs, reps) = (i("runs")?, i("replications")?);
    let sequential = df
        .column("sequential")
        .and_then(|c| c.bool().cloned())
        .map_err(bad)?;
    let mut curves: Vec<PowerCurve> = Vec::new();
    for k in 0..df.height() {
        if test.get(k) != Some(crate::metrics::consistency::VERDICT)
            || sequential.get(k) != Some(false)
            || !against.matches(q.get(k), r.get(k))
        {
            continue;
        }
        let (Some(rate), Some(lo), Some(hi)) = (rate.get(k), lo.get(k), hi.get(k)) else {
            continue;
        };
        let key = (
            scen.get(k).unwrap_or("").to_string(),
            noise.get(k).unwrap_or(f64::NAN),
            filt.get(k).unwrap_or("").to_string(),
            q.get(k),
            r.get(k),
        );
        let point = CurvePoint {
            runs: runs.get(k).unwrap_or(0) as usize,
            replications: reps.get(k).unwrap_or(0) as u64,
            rate,
            interval: (lo, hi),
        };
        match curves.iter_mut().find(|c| {
            (
                &c.scenario,
                c.noise_scale.to_bits(),
                &c.filter,
                c.q_scale,
                c.r_scale,
            ) == (&key.0, key.1.to_bits(), &key.2, key.3, key.4)
        }) {
            Some(c) => c.points.push(point),
            None => curves.push(PowerCurve {
                scenario: key.0,
                noise_scale: key.1,
                filter: key.2,
                q_scale: key.3,
                r_scale: key.4,
                points: vec![point],
            }),
        }
    }
    for c in &mut curves {
        c.points.sort_by_key(|p| p.runs);
        c.points.dedup_by_key(|p| p.runs);
    }
    Ok(curves)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn clopper_pearson_matches_its_closed_forms_at_the_ends() {
        // k = 0: hi = 1 − (α/2)^(1/n); k = n: lo = (α/2)^(1/n).
        let n = 20;
        let (lo, hi) = clopper_pearson(0, n);
        assert_eq!(lo, 0.0);
        assert!((hi - (1.0 - 0.025f64.powf(1.0 / n as f64))).abs() < 1e-10);
        let (lo, hi) = clopper_pearson(n, n);
        assert_eq!(hi, 1.0);
        assert!((lo - 0.025f64.powf(1.0 / n as f64)).abs() < 1e-10);
        // k = 1 of 20: the tabulated exact interval [0.00127, 0.2487].
        let (lo, hi) = clopper_pearson(1, n);
        assert!((lo - 0.001265).abs() < 1e-6 && (hi - 0.248733).abs() < 1e-6);
    }
}
