//! `kfmc ulog`: calibrated NIS verdicts from PX4 flight logs, as library functions.
//!
//! [`nis`] reads one log or a folder of logs ([`extract`]), builds each source's series for
//! the selected EKF instances (the primary's, split where it changes; every instance; or one),
//! leaves out the ground, each instance's first seconds and the seconds after its resets, and
//! judges every axis's NIS = ν²/S by batch means ([`crate::metrics::batch_means`]). It writes
//! `ulog_samples.parquet` (every sample, with why it was left out) and `ulog_summary.parquet`
//! (a row per log × instance × source × axis × test, and a verdict row per log) into a
//! locked, manifest-committed folder, and returns `kfmc check`'s cases: the per-axis tests at
//! α/k (Bonferroni over the k judged tests of a log, as `check`'s verdict row), incomplete
//! series as incomplete cases, and with a baseline the regression cases of [`gate`].

pub mod calibration;
pub mod extract;
pub mod gate;
pub mod inspect;
pub mod simulate;

use std::path::{Path, PathBuf};

use crate::check::CaseResult;
use crate::error::OutputError;
use crate::exchange::ulog::UlogError;
use crate::metrics::batch_means;
use crate::output::folder::StudyFolder;
use crate::output::manifest::{Manifest, StudyKind};
use crate::output::schema::{self, Value};
use crate::output::table::TableWriter;
use extract::{Extract, SourceSeries};

/// Seconds left out after an instance starts and after each of its resets, by default.
pub const DEFAULT_HOLDOFF_S: f64 = 5.0;

/// The relative growth of a mean NIS that the regression gate tolerates, by default.
pub const DEFAULT_TOLERANCE: f64 = 0.2;

/// The test of one axis's mean NIS against 1 (χ²₁: exact per axis).
pub const TEST_NIS_MEAN: &str = "nis_mean";
/// The test of the fraction of samples beyond the gate against P(χ²₁ > γ²).
pub const TEST_REJECTION_RATE: &str = "rejection_rate";
/// The mean of the NIS summed over a source's axes against their count: only the diagonal
/// of S is logged, so the sum is χ² only approximately; descriptive, not in the verdict.
pub const TEST_NIS_SUM: &str = "nis_sum_approximate";
/// A log's verdict row: Bonferroni over its judged tests.
pub const TEST_VERDICT: &str = "verdict";

/// Effective samples a series needs for a verdict: [`batch_means::BATCHES`] batches of at
/// least [`batch_means::TAU_MULTIPLE`] integrated autocorrelation times each.
pub fn batch_means_minimum() -> usize {
    (batch_means::BATCHES as f64 * batch_means::TAU_MULTIPLE) as usize
}

/// Which EKF instances' innovations are judged (`--instance`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum InstanceSelection {
    /// The primary's: each sample from the instance that was primary at its time, the series
    /// split where the primary changes.
    Primary,
    /// Every instance, each on its own.
    All,
    /// This instance.
    One(u8),
}

impl std::str::FromStr for InstanceSelection {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s.trim() {
            "primary" => Ok(InstanceSelection::Primary),
            "all" => Ok(InstanceSelection::All),
            n => n
                .parse::<u8>()
                .map(InstanceSelection::One)
                .map_err(|_| format!("`{s}` is not `primary`, `all` or an instance number 0-255")),
        }
    }
}

impl std::fmt::Display for InstanceSelection {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            InstanceSelection::Primary => write!(f, "primary"),
            InstanceSelection::All => write!(f, "all"),
            InstanceSelection::One(n) => write!(f, "{n}"),
        }
    }
}

/// The settings of [`nis`].
#[derive(Clone, Debug, PartialEq)]
pub struct NisOptions {
    /// The instances judged.
    pub instance: InstanceSelection,
    /// Only these sources (`gnss_vel`, `baro_hgt`, …); empty: every source.
    pub sensors: Vec<String>,
    /// The family-wise level of each log's verdict.
    pub alpha: f64,
    /// Seconds left out after an instance starts and after each of its resets.
    pub holdoff_s: f64,
    /// Judge samples on the ground too.
    pub include_ground: bool,
    /// A stored `ulog_summary.parquet` to compare with (the regression gate).
    pub baseline: Option<PathBuf>,
    /// The relative growth of a mean NIS the gate tolerates.
    pub tolerance: f64,
    /// The output folder.
    pub out: PathBuf,
    /// Replace a folder of another kind, or a non-empty folder that is not kfmc's.
    pub force: bool,
}

impl NisOptions {
    /// The defaults, writing to `out`.
    pub fn new(out: PathBuf) -> Self {
        NisOptions {
            instance: InstanceSelection::Primary,
            sensors: Vec::new(),
            alpha: 0.05,
            holdoff_s: DEFAULT_HOLDOFF_S,
            include_ground: false,
            baseline: None,
            tolerance: DEFAULT_TOLERANCE,
            out,
            force: false,
        }
    }
}

/// Why `ulog nis` could not run.
#[derive(Debug, thiserror::Error)]
pub enum NisError {
    /// A setting is out of range (exit 2).
    #[error("invalid {flag}: {message}")]
    Usage {
        /// The flag.
        flag: &'static str,
        /// What is wrong.
        message: String,
    },
    /// No `.ulg` file under the path.
    #[error("{path}: no .ulg log there")]
    NoLogs {
        /// The path given.
        path: PathBuf,
    },
    /// A log could not be read.
    #[error(transparent)]
    Log(#[from] UlogError),
    /// The tables could not be written, or the baseline read.
    #[error(transparent)]
    Output(#[from] OutputError),
    /// The baseline is not a `ulog_summary` table.
    #[error("{path}: not a ulog_summary table: {why}")]
    Baseline {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        why: String,
    },
}

/// What [`nis`] found.
#[derive(Clone, Debug)]
pub struct NisOutcome {
    /// The check cases (per-axis tests, incomplete series, regressions).
    pub cases: Vec<CaseResult>,
    /// The summary rows written.
    pub rows: Vec<SummaryRow>,
    /// Tables written and their row counts.
    pub tables: Vec<(String, u64)>,
    /// Logs judged.
    pub logs: usize,
    /// Wall-clock seconds.
    pub seconds: f64,
}

impl NisOutcome {
    /// (failed, incomplete) cases.
    pub fn tally(&self) -> (usize, usize) {
        crate::check::tally(&self.cases)
    }
    /// The readable report.
    pub fn render(&self) -> String {
        crate::check::render("kfmc", "ulog nis", &self.cases)
    }
    /// JUnit XML of the cases.
    pub fn junit(&self) -> String {
        crate::check::junit("kfmc", "ulog nis", &self.cases, self.seconds)
    }
}

/// One row of `ulog_summary.parquet` ([`schema::ulog_summary`]).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SummaryRow {
    /// The log's name (its path under the folder given, or its file name).
    pub log: String,
    /// The EKF instance; `None` for the primary's series and the verdict row.
    pub instance: Option<u8>,
    /// Whether the row judges the primary's series.
    pub primary: bool,
    /// The aid source (empty on the verdict row).
    pub source: String,
    /// The axis (`None` on sums and the verdict row).
    pub axis: Option<usize>,
    /// [`TEST_NIS_MEAN`], [`TEST_REJECTION_RATE`], [`TEST_NIS_SUM`] or [`TEST_VERDICT`].
    pub test: String,
    /// Samples of the series.
    pub samples: usize,
    /// Samples judged (not left out).
    pub samples_included: usize,
    /// Stretches of judged samples.
    pub stretches: usize,
    /// τ̂ (samples).
    pub tau: Option<f64>,
    /// Judged samples / τ̂.
    pub effective_samples: Option<f64>,
    /// Batches.
    pub batches: Option<usize>,
    /// Samples per batch.
    pub batch_length: Option<usize>,
    /// The statistic: the mean tested (the Bonferroni p-value on the verdict row).
    pub statistic: Option<f64>,
    /// Its expected value for a consistent filter.
    pub expected: Option<f64>,
    /// Acceptance band at `level`.
    pub lower: Option<f64>,
    /// Its upper end.
    pub upper: Option<f64>,
    /// Degrees of freedom of the t reference.
    pub dof: Option<f64>,
    /// Two-sided p-value.
    pub p_value: Option<f64>,
    /// The level the row is judged at (α/k).
    pub level: Option<f64>,
    /// The family-wise α.
    pub alpha: f64,
    /// `pass`, `fail`, `incomplete` or `not_judged`.
    pub verdict: String,
    /// `optimistic` (NIS too large: S too small) or `pessimistic`, on a failure.
    pub direction: String,
    /// The gate γ.
    pub gate: Option<f64>,
    /// Where γ came from (a parameter's name, or `test_ratio` when inferred from it).
    pub gate_from: String,
    /// Fraction of judged samples beyond the gate.
    pub rejected_fraction: Option<f64>,
    /// P(χ²₁ > γ²).
    pub rejection_expected: Option<f64>,
    /// The instance's pairing rate of innovations with variances (innovations topics).
    pub pairing_rate: Option<f64>,
    /// `aid_src` or `innovations`.
    pub family: String,
    /// The firmware, when logged.
    pub firmware: String,
    /// Why a row is incomplete or not judged, and notes.
    pub detail: String,
}

impl SummaryRow {
    fn values(&self) -> Vec<Value<'_>> {
        let i = |v: Option<usize>| Value::I64(v.map(|v| v as i64));
        vec![
            Value::Str(&self.log),
            Value::I64(self.instance.map(i64::from)),
            Value::Bool(Some(self.primary)),
            Value::Str(&self.source),
            i(self.axis),
            Value::Str(&self.test),
            i(Some(self.samples)),
            i(Some(self.samples_included)),
            i(Some(self.stretches)),
            Value::F64(self.tau),
            Value::F64(self.effective_samples),
            i(self.batches),
            i(self.batch_length),
            Value::F64(self.statistic),
            Value::F64(self.expected),
            Value::F64(self.lower),
            Value::F64(self.upper),
            Value::F64(self.dof),
            Value::F64(self.p_value),
            Value::F64(self.level),
            Value::F64(Some(self.alpha)),
            Value::Str(&self.verdict),
            Value::Str(&self.direction),
            Value::F64(self.gate),
            Value::Str(&self.gate_from),
            Value::F64(self.rejected_fraction),
            Value::F64(self.rejection_expected),
            Value::F64(self.pairing_rate),
            Value::Str(&self.family),
            Value::Str(&self.firmware),
            Value::Str(&self.detail),
        ]
    }

    /// The case name: `nis_mean[LOG primary gnss_vel[2]]`.
    pub fn case_name(&self) -> String {
        let inst = self
            .instance
            .map_or_else(|| "primary".to_string(), |i| format!("instance {i}"));
        let axis = self.axis.map_or(String::new(), |a| format!("[{a}]"));
        format!("{}[{} {inst} {}{axis}]", self.test, self.log, self.source)
    }
}

/// The `.ulg` files at `path` (itself, or every one under it, sorted) with their names.
pub fn list_logs(path: &Path) -> Result<Vec<(String, PathBuf)>, NisError> {
    let meta = std::fs::metadata(path).map_err(|source| OutputError::Io {
        action: "cannot read",
        path: path.to_path_buf(),
        source,
    })?;
    if !meta.is_dir() {
        let name = path.file_name().map_or_else(
            || path.display().to_string(),
            |n| n.to_string_lossy().into_owned(),
        );
        return Ok(vec![(name, path.to_path_buf())]);
    }
    let mut out = Vec::new();
    let mut stack = vec![path.to_path_buf()];
    while let Some(dir) = stack.pop() {
        let entries = std::fs::read_dir(&dir).map_err(|source| OutputError::Io {
            action: "cannot list",
            path: dir.clone(),
            source,
        })?;
        for e in entries.flatten() {
            let p = e.path();
            // Symbolic links are not followed: a link to a parent would loop.
            let Ok(t) = e.file_type() else { continue };
            if t.is_dir() {
                stack.push(p);
            } else if t.is_file() && p.extension().is_some_and(|x| x.eq_ignore_ascii_case("ulg")) {
                let name = p
                    .strip_prefix(path)
                    .unwrap_or(&p)
                    .to_string_lossy()
                    .into_owned();
                out.push((name, p));
            }
        }
    }
    out.sort();
    if out.is_empty() {
        return Err(NisError::NoLogs {
            path: path.to_path_buf(),
        });
    }
    Ok(out)
}

/// The last value at or before `t` of a time-ordered list, else the first.
fn at<T: Copy>(list: &[(u64, T)], t: u64) -> Option<T> {
    let i = list.partition_point(|(ts, _)| *ts <= t);
    if i == 0 {
        list.first().map(|x| x.1)
    } else {
        Some(list[i - 1].1)
    }
}

/// One sample of a judged series.
#[derive(Clone, Debug)]
struct Point<'a> {
    instance: u8,
    primary: bool,
    t_us: u64,
    in_air: bool,
    included: bool,
    stretch: Option<usize>,
    record: &'a extract::Record,
}

/// Whether the vehicle was in the air at `t`: before the first land-detector record it is on
/// the ground; a log without the land detector counts as in the air throughout.
fn in_air(x: &Extract, t: u64) -> bool {
    if x.landed.is_empty() {
        return true;
    }
    let i = x.landed.partition_point(|(ts, _)| *ts <= t);
    i > 0 && !x.landed[i - 1].1
}

/// The series of `source` for `selection`, with each sample's flags and stretches.
fn series_points<'a>(
    x: &'a Extract,
    of_source: &[&'a SourceSeries],
    selection: Option<u8>,
    opts: &NisOptions,
) -> Vec<Point<'a>> {
    let primary_at = |t: u64| at(&x.primary, t).unwrap_or(0);
    let hold = (opts.holdoff_s * 1e6) as u64;
    let mut pts: Vec<Point<'a>> = Vec::new();
    for s in of_source {
        if selection.is_some_and(|i| i != s.instance) {
            continue;
        }
        let start = x.first_seen.get(&s.instance).copied().unwrap_or(x.start_us);
        let resets = x.resets.get(&s.instance).map_or(&[][..], Vec::as_slice);
        for r in &s.records {
            let primary = primary_at(r.t_us) == s.instance;
            if selection.is_none() && !primary {
                continue;
            }
            let air = in_air(x, r.t_us);
            let settled = r.t_us >= start.saturating_add(hold)
                && !resets
                    .iter()
                    .any(|&z| (z..z.saturating_add(hold)).contains(&r.t_us));
            pts.push(Point {
                instance: s.instance,
                primary,
                t_us: r.t_us,
                in_air: air,
                included: (air || opts.include_ground) && settled,
                stretch: None,
                record: r,
            });
        }
    }
    pts.sort_by_key(|p| (p.t_us, p.instance));
    let mut stretch = 0usize;
    let mut prev: Option<(bool, u8)> = None;
    for p in &mut pts {
        if p.included {
            if prev != Some((true, p.instance)) {
                stretch += 1;
            }
            p.stretch = Some(stretch - 1);
        }
        prev = Some((p.included, p.instance));
    }
    pts
}

/// P(χ²₁ > γ²).
fn chi2_1_tail(gate: f64) -> f64 {
    2.0 * (1.0 - statrs::function::erf::erfc(-gate / std::f64::consts::SQRT_2) / 2.0)
}

/// A row whose test is still to be decided at the log's Bonferroni level.
struct Pending {
    row: SummaryRow,
    means: Vec<f64>,
}

/// Judges one series of values `y` (stretches) against `mu0`, filling `row`.
fn judge(
    row: &mut SummaryRow,
    y: &[Vec<f64>],
    w: &[Vec<f64>],
    mu0: f64,
    alpha: f64,
) -> Option<Vec<f64>> {
    let ys: Vec<&[f64]> = y.iter().map(Vec::as_slice).collect();
    let ws: Vec<&[f64]> = w.iter().map(Vec::as_slice).collect();
    let plan = batch_means::plan(&ys, &ws);
    row.samples_included = plan.samples;
    row.stretches = y.len();
    row.tau = Some(plan.tau);
    row.effective_samples = Some(plan.effective_samples());
    row.expected = Some(mu0);
    row.batch_length = plan.batch_length;
    if let Some(why) = plan.incomplete {
        row.verdict = "incomplete".into();
        row.detail = why;
        return None;
    }
    let m = plan.batch_length.expect("a complete plan has batches");
    let means = batch_means::batch_means(&ys, m);
    row.batches = Some(means.len());
    row.statistic = Some(means.iter().sum::<f64>() / means.len() as f64);
    match batch_means::t_test(&means, mu0, alpha) {
        Some(t) => {
            row.p_value = Some(t.p_value);
            row.dof = Some(t.dof);
            Some(means)
        }
        None => {
            row.verdict = "incomplete".into();
            row.detail = "the batch means have no spread: the test cannot be computed".into();
            None
        }
    }
}

/// Rows of one log, and its sample rows written to `samples`.
fn judge_log(
    name: &str,
    x: &Extract,
    opts: &NisOptions,
    samples: &mut TableWriter,
) -> Result<Vec<SummaryRow>, OutputError> {
    let firmware = x.firmware.clone().unwrap_or_default();
    let mut sources: Vec<&str> = x.series.iter().map(|s| s.source.as_str()).collect();
    sources.sort_unstable();
    sources.dedup();
    if !opts.sensors.is_empty() {
        sources.retain(|s| opts.sensors.iter().any(|w| w == s));
    }
    let selections: Vec<Option<u8>> = match opts.instance {
        InstanceSelection::Primary => vec![None],
        InstanceSelection::One(n) => vec![Some(n)],
        InstanceSelection::All => {
            let mut v: Vec<u8> = x.series.iter().map(|s| s.instance).collect();
            v.sort_unstable();
            v.dedup();
            v.into_iter().map(Some).collect()
        }
    };
    let mut pending: Vec<Pending> = Vec::new();
    let t0 = x.start_us;
    for sel in &selections {
        for source in &sources {
            let of: Vec<&SourceSeries> = x.series.iter().filter(|s| s.source == *source).collect();
            let pts = series_points(x, &of, *sel, opts);
            if pts.is_empty() {
                continue;
            }
            let axes = pts.iter().map(|p| p.record.axes.len()).min().unwrap_or(0);
            let (gate, gate_from) = gate_of(x, source, &pts);
            let family = match of[0].family {
                extract::Family::AidSource => "aid_src",
                extract::Family::Innovations => "innovations",
            };
            let pairing_rate = sel
                .or_else(|| pts.first().map(|p| p.instance))
                .and_then(|i| x.pairing.get(&i))
                .and_then(extract::Pairing::rate)
                .filter(|_| family == "innovations");
            let stretches = pts
                .iter()
                .filter_map(|p| p.stretch)
                .max()
                .map_or(0, |s| s + 1);
            let base = SummaryRow {
                log: name.to_string(),
                instance: *sel,
                primary: sel.is_none(),
                source: source.to_string(),
                samples: pts.len(),
                alpha: opts.alpha,
                gate,
                gate_from: gate_from.clone(),
                pairing_rate,
                family: family.into(),
                firmware: firmware.clone(),
                ..SummaryRow::default()
            };
            for p in &pts {
                for (a, v) in p.record.axes.iter().enumerate().take(axes) {
                    let nis = v.innovation * v.innovation / v.variance;
                    samples.push(&[
                        Value::Str(name),
                        Value::I64(Some(i64::from(p.instance))),
                        Value::Bool(Some(p.primary)),
                        Value::Str(source),
                        Value::I64(Some(a as i64)),
                        Value::F64(Some(p.t_us.saturating_sub(t0) as f64 * 1e-6)),
                        Value::F64(Some(v.innovation)),
                        Value::F64(Some(v.variance)),
                        Value::F64(Some(nis)),
                        Value::F64(v.test_ratio),
                        Value::F64(gate),
                        Value::Bool(v.rejected),
                        Value::Bool(v.fused),
                        Value::Bool(Some(p.in_air)),
                        Value::Bool(Some(p.included)),
                        Value::I64(p.stretch.map(|s| s as i64)),
                    ])?;
                }
            }
            // Per-stretch values of each axis.
            let per_axis = |f: &dyn Fn(&extract::AxisValue) -> f64, a: usize| -> Vec<Vec<f64>> {
                let mut out: Vec<Vec<f64>> = vec![Vec::new(); stretches];
                for p in &pts {
                    if let Some(s) = p.stretch {
                        out[s].push(f(&p.record.axes[a]));
                    }
                }
                out.retain(|v| !v.is_empty());
                out
            };
            for a in 0..axes {
                let w = per_axis(&|v| v.innovation / v.variance.sqrt(), a);
                let y: Vec<Vec<f64>> = w
                    .iter()
                    .map(|s| s.iter().map(|w| w * w).collect())
                    .collect();
                let mut row = SummaryRow {
                    axis: Some(a),
                    test: TEST_NIS_MEAN.into(),
                    ..base.clone()
                };
                let means = judge(&mut row, &y, &w, 1.0, opts.alpha);
                let included: usize = y.iter().map(Vec::len).sum();
                if let (Some(g), true) = (gate, included > 0) {
                    let p0 = chi2_1_tail(g);
                    let beyond = y.iter().flatten().filter(|v| **v > g * g).count();
                    row.rejected_fraction = Some(beyond as f64 / included as f64);
                    row.rejection_expected = Some(p0);
                }
                let rejection = rejection_row(&row, &y, gate);
                pending.push(Pending {
                    row,
                    means: means.unwrap_or_default(),
                });
                if let Some(r) = rejection {
                    pending.push(r);
                }
            }
            if axes > 1 {
                let mut sums: Vec<Vec<f64>> = vec![Vec::new(); stretches];
                for p in &pts {
                    if let Some(s) = p.stretch {
                        sums[s].push(
                            p.record.axes[..axes]
                                .iter()
                                .map(|v| v.innovation * v.innovation / v.variance)
                                .sum(),
                        );
                    }
                }
                sums.retain(|v| !v.is_empty());
                let mut row = SummaryRow {
                    test: TEST_NIS_SUM.into(),
                    ..base.clone()
                };
                if let Some(means) = judge(&mut row, &sums, &[], axes as f64, opts.alpha) {
                    decide(&mut row, &means, opts.alpha);
                }
                row.detail = format!(
                    "approximate: only the diagonal of S is logged, so the sum over {axes} axes is χ²({axes}) only if their innovations are uncorrelated; descriptive, not part of the verdict{}",
                    if row.detail.is_empty() {
                        String::new()
                    } else {
                        format!("; {}", row.detail)
                    }
                );
                pending.push(Pending {
                    row,
                    means: Vec::new(),
                });
            }
        }
    }
    // Bonferroni over the judged tests of this log.
    let judged = pending
        .iter()
        .filter(|p| !p.means.is_empty() && p.row.test != TEST_NIS_SUM)
        .count();
    let level = opts.alpha / judged.max(1) as f64;
    let mut rows = Vec::with_capacity(pending.len() + 1);
    let mut min_p = f64::INFINITY;
    for Pending { mut row, means } in pending {
        if !means.is_empty() && row.test != TEST_NIS_SUM {
            decide(&mut row, &means, level);
            min_p = min_p.min(row.p_value.unwrap_or(1.0));
        }
        rows.push(row);
    }
    let mut verdict = SummaryRow {
        log: name.to_string(),
        primary: opts.instance == InstanceSelection::Primary,
        test: TEST_VERDICT.into(),
        alpha: opts.alpha,
        level: Some(opts.alpha),
        samples: rows
            .iter()
            .filter(|r| r.test == TEST_NIS_MEAN)
            .map(|r| r.samples)
            .sum(),
        samples_included: rows
            .iter()
            .filter(|r| r.test == TEST_NIS_MEAN)
            .map(|r| r.samples_included)
            .sum(),
        firmware,
        ..SummaryRow::default()
    };
    if judged == 0 {
        verdict.verdict = "incomplete".into();
        verdict.detail = if rows.is_empty() {
            "no innovations of the selected sources and instances in this log".into()
        } else {
            "no series of this log could be judged".into()
        };
    } else {
        let p = (judged as f64 * min_p).min(1.0);
        verdict.statistic = Some(p);
        verdict.p_value = Some(p);
        verdict.lower = Some(opts.alpha);
        verdict.verdict = if p > opts.alpha { "pass" } else { "fail" }.into();
        verdict.detail = format!(
            "Bonferroni p-value min(1, {judged}·min p) over the {judged} judged tests of the log"
        );
    }
    rows.push(verdict);
    Ok(rows)
}

/// Decides a judged row at `level`: band, verdict and direction.
fn decide(row: &mut SummaryRow, means: &[f64], level: f64) {
    let mu0 = row.expected.unwrap_or(1.0);
    if let Some(t) = batch_means::t_test(means, mu0, level) {
        row.lower = Some(t.lower);
        row.upper = Some(t.upper);
        row.level = Some(level);
        let pass = t.p_value > level;
        row.verdict = if pass { "pass" } else { "fail" }.into();
        row.direction = if pass {
            String::new()
        } else if t.mean > mu0 {
            "optimistic".into()
        } else {
            "pessimistic".into()
        };
    }
}

/// The rejection-rate test of an axis: the fraction of NIS beyond γ² in the same batches,
/// against P(χ²₁ > γ²); judged when each batch expects at least 5 rejections.
fn rejection_row(nis_row: &SummaryRow, y: &[Vec<f64>], gate: Option<f64>) -> Option<Pending> {
    let g = gate?;
    let p0 = chi2_1_tail(g);
    let mut row = SummaryRow {
        test: TEST_REJECTION_RATE.into(),
        statistic: nis_row.rejected_fraction,
        expected: Some(p0),
        lower: None,
        upper: None,
        p_value: None,
        verdict: String::new(),
        detail: String::new(),
        ..nis_row.clone()
    };
    let m = match (nis_row.verdict.as_str(), nis_row.batch_length) {
        ("incomplete", _) | (_, None) => {
            row.verdict = "not_judged".into();
            row.detail = "the series is too short for batches (see its nis_mean row)".into();
            return Some(Pending {
                row,
                means: Vec::new(),
            });
        }
        (_, Some(m)) => m,
    };
    if (m as f64) * p0 < 5.0 {
        row.verdict = "not_judged".into();
        row.detail = format!(
            "too rare to test: a batch of {m} samples expects {:.2} rejections at γ = {g} (needs ≥ 5)",
            m as f64 * p0
        );
        return Some(Pending {
            row,
            means: Vec::new(),
        });
    }
    let ind: Vec<Vec<f64>> = y
        .iter()
        .map(|s| s.iter().map(|v| f64::from(u8::from(*v > g * g))).collect())
        .collect();
    let ys: Vec<&[f64]> = ind.iter().map(Vec::as_slice).collect();
    let means = batch_means::batch_means(&ys, m);
    match batch_means::t_test(&means, p0, 0.05) {
        Some(t) => {
            row.p_value = Some(t.p_value);
            row.dof = Some(t.dof);
            row.batches = Some(means.len());
            Some(Pending { row, means })
        }
        None => {
            row.verdict = "not_judged".into();
            row.detail = "the batches' rejection fractions have no spread".into();
            Some(Pending {
                row,
                means: Vec::new(),
            })
        }
    }
}

/// The gate γ of a source: its `EKF2_*_GATE` parameter, else inferred from the logged test
/// ratios (ν²/S = test ratio · γ²: the median of NIS/test ratio is γ²).
fn gate_of(x: &Extract, source: &str, pts: &[Point<'_>]) -> (Option<f64>, String) {
    for p in extract::gate_parameters(source) {
        if let Some(&g) = x.parameters.get(*p)
            && g > 0.0
            && g.is_finite()
        {
            // Parameters are f32 in the log: 2.6 arrives as 2.5999999; 7 digits are all it has.
            return (Some((g * 1e6).round() / 1e6), (*p).to_string());
        }
    }
    let mut q: Vec<f64> = pts
        .iter()
        .flat_map(|p| p.record.axes.iter())
        .filter_map(|v| {
            let r = v.test_ratio?;
            (r > 1e-9).then(|| v.innovation * v.innovation / v.variance / r)
        })
        .filter(|g2| g2.is_finite() && *g2 > 0.0)
        .collect();
    if q.is_empty() {
        return (None, String::new());
    }
    q.sort_by(f64::total_cmp);
    let g = q[q.len() / 2].sqrt();
    (Some((g * 1e4).round() / 1e4), "test_ratio".into())
}

/// The case of a summary row, if it is one.
fn case_of(row: &SummaryRow) -> Option<CaseResult> {
    let fmt = |v: Option<f64>| v.map_or("—".into(), |v| format!("{v:.4}"));
    match (row.test.as_str(), row.verdict.as_str()) {
        (TEST_NIS_SUM | TEST_VERDICT, _) | (_, "not_judged") => None,
        (_, "incomplete") => Some(CaseResult {
            kind: row.test.clone(),
            name: row.case_name(),
            pass: false,
            incomplete: true,
            detail: format!("incomplete: {}", row.detail),
        }),
        (_, v) => Some(CaseResult {
            kind: row.test.clone(),
            name: row.case_name(),
            pass: v == "pass",
            incomplete: false,
            detail: format!(
                "mean {} {} [{}, {}] over {} batches of {} (τ̂ = {}, {} effective samples), p = {} (fails at p ≤ {} = α/{}){}",
                fmt(row.statistic),
                if v == "pass" { "in" } else { "outside" },
                fmt(row.lower),
                fmt(row.upper),
                row.batches.unwrap_or(0),
                row.batch_length.unwrap_or(0),
                fmt(row.tau),
                row.effective_samples
                    .map_or("—".into(), |e| format!("{e:.0}")),
                fmt(row.p_value),
                fmt(row.level),
                row.level.map_or(1.0, |l| (row.alpha / l).round()),
                if row.direction.is_empty() {
                    String::new()
                } else {
                    format!(", {}", row.direction)
                }
            ),
        }),
    }
}

/// Judges the log or folder of logs at `path` and writes the tables into `opts.out`.
/// `progress(i, n)` is called before each log.
pub fn nis(
    path: &Path,
    opts: &NisOptions,
    mut progress: impl FnMut(usize, usize),
) -> Result<NisOutcome, NisError> {
    let started = std::time::Instant::now();
    if opts.alpha <= 0.0 || opts.alpha >= 1.0 || opts.alpha.is_nan() {
        return Err(NisError::Usage {
            flag: "--alpha",
            message: format!("{} is not in (0, 1)", opts.alpha),
        });
    }
    if !(0.0..1e9).contains(&opts.holdoff_s) {
        return Err(NisError::Usage {
            flag: "--holdoff",
            message: format!("{} is not a number of seconds ≥ 0", opts.holdoff_s),
        });
    }
    if !(opts.tolerance >= 0.0 && opts.tolerance.is_finite()) {
        return Err(NisError::Usage {
            flag: "--tolerance",
            message: format!("{} is not a relative tolerance ≥ 0", opts.tolerance),
        });
    }
    let logs = list_logs(path)?;
    // The baseline is read before the folder is touched: it may live in the folder.
    let baseline = opts
        .baseline
        .as_deref()
        .map(gate::read_baseline)
        .transpose()?;
    let folder = StudyFolder::open(&opts.out, StudyKind::Ulog, opts.force)?;
    let mut samples = TableWriter::create(folder.dir(), "ulog_samples", schema::ulog_samples())?;
    let mut rows: Vec<SummaryRow> = Vec::new();
    let n = logs.len();
    for (i, (name, file)) in logs.iter().enumerate() {
        if crate::runner::interrupted() {
            return Err(OutputError::Interrupted.into());
        }
        progress(i, n);
        let x = extract::read(file)?;
        rows.extend(judge_log(name, &x, opts, &mut samples)?);
    }
    progress(n, n);
    let mut summary = TableWriter::create(folder.dir(), "ulog_summary", schema::ulog_summary())?;
    for r in &rows {
        summary.push(&r.values())?;
    }
    let mut cases: Vec<CaseResult> = rows.iter().filter_map(case_of).collect();
    for r in rows
        .iter()
        .filter(|r| r.test == TEST_VERDICT && r.verdict == "incomplete")
    {
        cases.push(CaseResult {
            kind: TEST_VERDICT.into(),
            name: format!("verdict[{}]", r.log),
            pass: false,
            incomplete: true,
            detail: format!("incomplete: {}", r.detail),
        });
    }
    if let Some(b) = &baseline {
        cases.extend(gate::compare(&rows, b, opts));
    }
    let tables = vec![samples.finish()?, summary.finish()?];
    let wall = started.elapsed().as_secs_f64();
    let total_samples: usize = rows
        .iter()
        .filter(|r| r.test == TEST_NIS_MEAN)
        .map(|r| r.samples)
        .sum();
    let spec = format!(
        "# kfmc ulog nis\npath = {:?}\ninstance = \"{}\"\nsensors = {:?}\nalpha = {}\nholdoff_s = {}\ninclude_ground = {}\nbaseline = {:?}\ntolerance = {}\n",
        path.display().to_string(),
        opts.instance,
        opts.sensors,
        opts.alpha,
        opts.holdoff_s,
        opts.include_ground,
        opts.baseline
            .as_ref()
            .map(|b| b.display().to_string())
            .unwrap_or_default(),
        opts.tolerance
    );
    let manifest = Manifest {
        format: Some(crate::output::manifest::FORMAT.into()),
        kfmc_version: env!("CARGO_PKG_VERSION").into(),
        program: None,
        program_version: None,
        experiment: format!("ulog nis {}", path.display()),
        system: "ulog".into(),
        kind: Some(StudyKind::Ulog),
        quantities: Vec::new(),
        inputs: Vec::new(),
        measurements: Vec::new(),
        dt_s: 0.0,
        spec_path: path.display().to_string(),
        spec_hash: format!("{:016x}", crate::hash::fnv1a64(spec.as_bytes())),
        world_stamp: String::new(),
        master_seed: 0,
        runs_per_cell: 1,
        cells: n as u64,
        runs: n as u64,
        filter_runs: n as u64,
        filter_steps: total_samples as u64,
        threads: 1,
        lanes: None,
        isa: None,
        started_unix_s: std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_secs()),
        wall_s: wall,
        runs_per_s: n as f64 / wall.max(1e-9),
        tables: Vec::new(),
        files: Vec::new(),
        folders: Vec::new(),
        replacing: None,
        exchange: None,
        shard: None,
        sequential: None,
        spec,
    };
    let tables = folder.commit(tables, manifest)?;
    Ok(NisOutcome {
        cases,
        rows,
        tables,
        logs: n,
        seconds: started.elapsed().as_secs_f64(),
    })
}
