//! Chi-square consistency statistics: acceptance bands, p-values and the calibrated verdict.
//!
//! Notation: n state dimension, p measurement dimension, N runs, K steps.
//!
//! * **Per-step bands.** N·ANEES_k ~ χ²(N·n) for a consistent filter, so the two-sided band
//!   is [χ²⁻¹(α/2, N·n)/N, χ²⁻¹(1−α/2, N·n)/N]; likewise ANIS with the reported components.
//! * **Why a per-step band is not a verdict.** Steps are correlated in time, so "≥ 1−α of
//!   the steps inside" has no known false-alarm rate. kfmc reports it as a
//!   description only.
//! * **Calibrated verdict**:
//!   - *NIS, exact.* A consistent filter's innovations are white, so Σ NIS over runs and steps
//!     ~ χ²(Σ p).
//!   - *NEES, effective dof.* The time-summed NEES has variance 2nK·ρ with
//!     ρ = 1 + (2/(nK)) Σ_k tr(P_k⁻¹ W_k), W_k = A_k(W_{k−1} + P_{k−1})A_kᵀ and
//!     A_k = (I − K_k H_k)F_k. The run-and-time average Ā is therefore tested as
//!     Ā·ν/n ~ χ²(ν) with ν = N·K·n/ρ (moment matching).
//!   - *Combined.* The verdict is "consistent" when both two-sided tests pass at α/2 each
//!     (Bonferroni), so its false-alarm rate is at most α. The book
//!     (`docs/src/statistics/consistency.md`) reports the rate measured by
//!     `examples/calibration.rs`.
//!
//! # Reference
//! Bar-Shalom, Li & Kirubarajan, *Estimation with Applications to Tracking and Navigation*
//! (2001), §5.4 (NEES/NIS tests, whiteness test).

use std::collections::HashMap;
use std::path::Path;

use statrs::distribution::{ChiSquared, ContinuousCDF, Normal, StudentsT};

use super::RunConsistency;
use crate::error::OutputError;
use crate::spill::{SPILL_ROWS, Spill};

/// A two-sided acceptance interval.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Band {
    /// Lower bound.
    pub lo: f64,
    /// Upper bound.
    pub hi: f64,
}

impl Band {
    /// Whether `x` lies inside (bounds included).
    pub fn contains(&self, x: f64) -> bool {
        x >= self.lo && x <= self.hi
    }
}

/// The two-sided band for the average of `runs` independent χ²(`dof_per_run`) variables,
/// i.e. [χ²⁻¹(α/2, N·d)/N, χ²⁻¹(1−α/2, N·d)/N]. `None` for zero runs or dof.
pub fn average_chi2_band(dof_per_run: f64, runs: f64, alpha: f64) -> Option<Band> {
    let total = dof_per_run * runs;
    let chi = ChiSquared::new(total).ok()?;
    Some(Band {
        lo: chi.inverse_cdf(alpha / 2.0) / runs,
        hi: chi.inverse_cdf(1.0 - alpha / 2.0) / runs,
    })
}

/// Two-sided p-value of `x` under χ²(`dof`).
pub fn chi2_two_sided_p(x: f64, dof: f64) -> Option<f64> {
    let chi = ChiSquared::new(dof).ok()?;
    let c = chi.cdf(x);
    Some((2.0 * c.min(1.0 - c)).min(1.0))
}

/// Two-sided p-value of a standard normal statistic.
pub fn normal_two_sided_p(z: f64) -> f64 {
    let n = Normal::new(0.0, 1.0).expect("the standard normal is valid");
    2.0 * n.cdf(-z.abs())
}

/// The standard normal quantile z_q.
pub fn normal_quantile(q: f64) -> f64 {
    Normal::new(0.0, 1.0)
        .expect("the standard normal is valid")
        .inverse_cdf(q)
}

/// Two-sided p-value of a Student-t statistic with `dof` degrees of freedom.
pub fn t_two_sided_p(t: f64, dof: f64) -> Option<f64> {
    let d = StudentsT::new(0.0, 1.0, dof).ok()?;
    Some(2.0 * d.cdf(-t.abs()))
}

/// The Student-t quantile t_q with `dof` degrees of freedom.
pub fn t_quantile(q: f64, dof: f64) -> Option<f64> {
    Some(StudentsT::new(0.0, 1.0, dof).ok()?.inverse_cdf(q))
}

/// Memoises per-step bands: most steps share (runs, dof), and an inverse χ² CDF costs
/// microseconds, so a sweep of thousands of cells would otherwise spend seconds here.
#[derive(Debug, Default)]
pub struct BandCache {
    alpha: f64,
    cache: HashMap<(u64, u64), Option<Band>>,
}

impl BandCache {
    /// A cache for significance level `alpha`.
    pub fn new(alpha: f64) -> Self {
        BandCache {
            alpha,
            cache: HashMap::new(),
        }
    }
    /// The band for the average over `runs` runs of χ² variables with `total_dof` dof in all
    /// (`total_dof / runs` per run).
    pub fn band(&mut self, total_dof: u64, runs: u64) -> Option<Band> {
        let alpha = self.alpha;
        *self.cache.entry((total_dof, runs)).or_insert_with(|| {
            (runs > 0 && total_dof > 0).then(|| {
                let chi = ChiSquared::new(total_dof as f64).ok()?;
                Some(Band {
                    lo: chi.inverse_cdf(alpha / 2.0) / runs as f64,
                    hi: chi.inverse_cdf(1.0 - alpha / 2.0) / runs as f64,
                })
            })?
        })
    }
}

/// Which way an inconsistent filter errs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Direction {
    /// The statistic is too large: the filter's covariance is too small.
    Optimistic,
    /// The statistic is too small: the filter's covariance is too large.
    Pessimistic,
}

impl Direction {
    /// The `direction` column value.
    pub fn label(self) -> &'static str {
        match self {
            Direction::Optimistic => "optimistic",
            Direction::Pessimistic => "pessimistic",
        }
    }
}

/// The outcome of one statistical test.
#[derive(Clone, Debug, PartialEq)]
pub struct TestResult {
    /// Test name (the `test` column).
    pub test: String,
    /// The statistic.
    pub statistic: f64,
    /// Acceptance region's lower bound (when two-sided).
    pub lower: Option<f64>,
    /// Acceptance region's upper bound.
    pub upper: Option<f64>,
    /// Degrees of freedom of the reference distribution.
    pub dof: Option<f64>,
    /// Two-sided p-value.
    pub p_value: Option<f64>,
    /// Whether the statistic lies in the acceptance region.
    pub pass: bool,
    /// Which way it errs when it fails.
    pub direction: Option<Direction>,
}

/// The χ²-average test: `mean` is an average whose scaled value `mean·ν/d` ~ χ²(ν).
/// `d` is the expected value of one term (n for NEES, p for NIS).
pub fn scaled_chi2_test(test: &str, mean: f64, d: f64, nu: f64, alpha: f64) -> Option<TestResult> {
    let chi = ChiSquared::new(nu).ok()?;
    let lo = d * chi.inverse_cdf(alpha / 2.0) / nu;
    let hi = d * chi.inverse_cdf(1.0 - alpha / 2.0) / nu;
    let pass = mean >= lo && mean <= hi;
    Some(TestResult {
        test: test.to_string(),
        statistic: mean,
        lower: Some(lo),
        upper: Some(hi),
        dof: Some(nu),
        p_value: chi2_two_sided_p(mean * nu / d, nu),
        pass,
        direction: (!pass).then_some({
            if mean > hi {
                Direction::Optimistic
            } else {
                Direction::Pessimistic
            }
        }),
    })
}

/// A one-sample t-test of `values` against `mu` (two-sided). For per-run time averages of
/// NEES (against n) or normalised errors (against 0): runs are independent, so the test is
/// calibrated whatever the correlation in time.
pub fn t_test(
    test: &str,
    values: &[f64],
    mu: f64,
    alpha: f64,
    high_is_optimistic: bool,
) -> Option<TestResult> {
    let n = values.len();
    if n < 2 {
        return None;
    }
    let nf = n as f64;
    let mean = values.iter().sum::<f64>() / nf;
    let var = values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (nf - 1.0);
    t_test_of(test, nf, mean, var, mu, alpha, high_is_optimistic)
}

/// The t-test of `nf` (≥ 2) values with this mean and sample variance.
fn t_test_of(
    test: &str,
    nf: f64,
    mean: f64,
    var: f64,
    mu: f64,
    alpha: f64,
    high_is_optimistic: bool,
) -> Option<TestResult> {
    let se = (var / nf).sqrt();
    let t = if se > 0.0 { (mean - mu) / se } else { 0.0 };
    let crit = t_quantile(1.0 - alpha / 2.0, nf - 1.0)?;
    let pass = t.abs() <= crit;
    Some(TestResult {
        test: test.to_string(),
        statistic: t,
        lower: Some(-crit),
        upper: Some(crit),
        dof: Some(nf - 1.0),
        p_value: t_two_sided_p(t, nf - 1.0),
        pass,
        direction: (!pass).then_some({
            if (t > 0.0) == high_is_optimistic {
                Direction::Optimistic
            } else {
                Direction::Pessimistic
            }
        }),
    })
}

/// The name of the combined test row.
pub const VERDICT: &str = "verdict";

/// Every test name [`cell_tests`] can produce for these quantities (the `test` column of
/// consistency.parquet), so a spec's `test = "…"` can be checked before anything runs.
pub fn test_names(state_names: &[&str]) -> Vec<String> {
    let mut out: Vec<String> = [
        "nees_time_average",
        "nis_time_average",
        "initial_nees",
        "nees_run_average_t",
        "anees_steps_inside",
        "anis_steps_inside",
        "innovation_whiteness",
    ]
    .map(String::from)
    .to_vec();
    out.extend(state_names.iter().map(|s| format!("bias_{s}")));
    out.push(VERDICT.into());
    out
}

/// Every test of one cell and filter from its runs' sums, the verdict last.
///
/// `steps_inside` are the fractions of steps whose ANEES / ANIS lie in their per-step bands
/// (descriptive: pass when ≥ 1 − α, but no false-alarm rate is claimed for them).
///
/// The runs are read twice (the t-tests' variances are about the mean); a study folds its
/// runs into a [`ConsistencyFold`] instead, which gives the same tests in bounded memory.
pub fn cell_tests(
    runs: &[RunConsistency],
    n: usize,
    state_names: &[&str],
    alpha: f64,
    steps_inside: (Option<f64>, Option<f64>),
) -> Vec<TestResult> {
    let mut sums = CellSums::new(n, state_names.len());
    for r in runs {
        sums.push(r);
    }
    let mut row = vec![0.0; sums.row_width()];
    for r in runs {
        if CellSums::per_run_row(r, &mut row) {
            sums.push_deviations(&row);
        }
    }
    sums.tests(state_names, alpha, steps_inside)
}

/// The sums over one evaluation's runs that the tests of [`cell_tests`] need, folded one run
/// at a time in run order, in memory independent of the number of runs.
///
/// Runs without NEES steps (`nees_n = 0`) count in [`CellSums::runs`] and the burn-in but in
/// no test. Every sum has the terms of [`cell_tests`]'s in the same order and starts where
/// `Iterator::sum` does (−0.0), so the tests are bit-identical.
///
/// The t-tests (`nees_run_average_t`, `bias_<state>`) need the sum of squared deviations of
/// per-run values from their mean, known only after the last run: a second pass gives
/// [`CellSums::push_deviations`] each counted run's [`CellSums::per_run_row`] again, in the
/// same order ([`ConsistencyFold`] keeps those rows in a [`Spill`]).
#[derive(Clone, Debug, PartialEq)]
pub struct CellSums {
    /// State dimension (the NEES dof per step).
    n: usize,
    runs: usize,
    burn_in: Option<usize>,
    /// Runs with `nees_n > 0`: those the tests use.
    used: usize,
    nees_n: u64,
    nees_sum: f64,
    /// Σ ρ_r over the runs, `None` once a run has no error transition.
    rho: Option<f64>,
    nis_n: u64,
    nis_dof: u64,
    nis_sum: f64,
    /// Σ initial NEES, `None` once a run has none.
    initial: Option<f64>,
    w_sq: f64,
    /// Per lag, sized by the first counted run.
    lag_prod: Option<Vec<f64>>,
    lag_pairs: Vec<u64>,
    /// Per [`CellSums::per_run_row`] column: Σ over the runs.
    per_run_sum: Vec<f64>,
    /// Per column: Σ (value − mean)², from the second pass.
    deviations: Vec<f64>,
    /// Per column: the mean the deviations are taken from (set by the first deviation row).
    means: Vec<f64>,
    deviation_rows: usize,
}

impl CellSums {
    /// No runs yet, for `n` states of which `bias_states` get a bias test (the first ones).
    pub fn new(n: usize, bias_states: usize) -> Self {
        CellSums {
            n,
            runs: 0,
            burn_in: Some(0),
            used: 0,
            nees_n: 0,
            nees_sum: -0.0,
            rho: Some(-0.0),
            nis_n: 0,
            nis_dof: 0,
            nis_sum: -0.0,
            initial: Some(-0.0),
            w_sq: -0.0,
            lag_prod: None,
            lag_pairs: Vec::new(),
            per_run_sum: vec![-0.0; 1 + bias_states],
            deviations: vec![-0.0; 1 + bias_states],
            means: Vec::new(),
            deviation_rows: 0,
        }
    }

    /// Width of a [`CellSums::per_run_row`]: the run's NEES average, then each bias state's
    /// average normalised error.
    pub fn row_width(&self) -> usize {
        self.per_run_sum.len()
    }

    /// Runs pushed, counted or not (the `runs` column).
    pub fn runs(&self) -> usize {
        self.runs
    }

    /// Steps of 1..K dropped before the sums start (step 0, the prior itself, is never a test
    /// step): the largest over the runs, 0 when every step counts, `None` when some run never
    /// forgot its prior.
    pub fn burn_in(&self) -> Option<usize> {
        self.burn_in
    }

    /// Adds one run (first pass), in run order.
    pub fn push(&mut self, r: &RunConsistency) {
        self.runs += 1;
        self.burn_in = self
            .burn_in
            .and_then(|m| r.first_step.map(|s| m.max(s.saturating_sub(1))));
        if r.nees_n == 0 {
            return;
        }
        self.used += 1;
        let nf = self.n as f64;
        self.nees_n += r.nees_n;
        self.nees_sum += r.nees_sum;
        // NEES effective dof: ρ_r = 1 + (2/(n·K_r)) Σ tr(P⁻¹W), averaged over the runs.
        self.rho = self.rho.and_then(|a| {
            r.rho_sum
                .map(|s| a + (1.0 + 2.0 * s / (nf * r.nees_n as f64)))
        });
        self.nis_n += r.nis_n;
        self.nis_dof += r.nis_dof;
        self.nis_sum += r.nis_sum;
        self.initial = self.initial.and_then(|a| r.initial_nees.map(|x| a + x));
        self.w_sq += r.w_sq;
        let prod = self.lag_prod.get_or_insert_with(|| {
            self.lag_pairs = vec![0; r.lag_prod.len()];
            vec![-0.0; r.lag_prod.len()]
        });
        for (a, x) in prod.iter_mut().zip(&r.lag_prod) {
            *a += x;
        }
        for (a, x) in self.lag_pairs.iter_mut().zip(&r.lag_pairs) {
            *a += x;
        }
        let k = r.nees_n as f64;
        self.per_run_sum[0] += r.nees_sum / k;
        for (a, e) in self.per_run_sum[1..].iter_mut().zip(&r.nme_sum) {
            *a += e / k;
        }
    }

    /// Writes the run's per-run values into `row` ([`CellSums::row_width`] long); `false`
    /// (and `row` untouched) for a run the tests do not count.
    pub fn per_run_row(r: &RunConsistency, row: &mut [f64]) -> bool {
        if r.nees_n == 0 {
            return false;
        }
        let k = r.nees_n as f64;
        row[0] = r.nees_sum / k;
        for (v, e) in row[1..].iter_mut().zip(&r.nme_sum) {
            *v = e / k;
        }
        true
    }

    /// Adds one counted run's row (second pass, after every run was pushed, in run order).
    pub fn push_deviations(&mut self, row: &[f64]) {
        if self.deviation_rows == 0 {
            let m = self.used as f64;
            self.means = self.per_run_sum.iter().map(|s| s / m).collect();
        }
        self.deviation_rows += 1;
        for ((d, v), mean) in self.deviations.iter_mut().zip(row).zip(&self.means) {
            *d += (v - mean).powi(2);
        }
    }

    /// The t-test of per-run column `c`, as [`t_test`] of the values gives it.
    fn t_test(&self, c: usize, test: &str, mu: f64, alpha: f64) -> Option<TestResult> {
        if self.used < 2 {
            return None;
        }
        assert_eq!(
            self.deviation_rows, self.used,
            "the second pass gives every counted run's row"
        );
        let m = self.used as f64;
        let mean = self.per_run_sum[c] / m;
        t_test_of(
            test,
            m,
            mean,
            self.deviations[c] / (m - 1.0),
            mu,
            alpha,
            true,
        )
    }

    /// Every test of the runs pushed, the verdict last; see [`cell_tests`].
    pub fn tests(
        &self,
        state_names: &[&str],
        alpha: f64,
        steps_inside: (Option<f64>, Option<f64>),
    ) -> Vec<TestResult> {
        let mut out = Vec::new();
        if self.used == 0 {
            return out;
        }
        let nf = self.n as f64;
        let a_bar = self.nees_sum / self.nees_n as f64;

        // NEES, run-and-time average with effective dof ν = N·K·n/ρ.
        let rho = self.rho.map(|s| s / self.used as f64);
        let nees = rho.and_then(|rho| {
            scaled_chi2_test(
                "nees_time_average",
                a_bar,
                nf,
                nf * self.nees_n as f64 / rho,
                alpha,
            )
        });
        out.extend(nees.clone());

        // NIS, exact: Σ NIS ~ χ²(Σ p).
        let nis = (self.nis_n > 0 && self.nis_dof > 0)
            .then(|| {
                let p_bar = self.nis_dof as f64 / self.nis_n as f64;
                scaled_chi2_test(
                    "nis_time_average",
                    self.nis_sum / self.nis_n as f64,
                    p_bar,
                    self.nis_dof as f64,
                    alpha,
                )
            })
            .flatten();
        out.extend(nis.clone());

        // The initial estimate: N independent x̂_0 errors, so Σ NEES_0 ~ χ²(N·n) exactly.
        if let Some(sum) = self.initial {
            let mean = sum / self.used as f64;
            out.extend(scaled_chi2_test(
                "initial_nees",
                mean,
                nf,
                nf * self.used as f64,
                alpha,
            ));
        }

        // Model-free NEES check: runs are independent, so a t-test of their averages is valid.
        out.extend(self.t_test(0, "nees_run_average_t", nf, alpha));

        for (name, frac) in [
            ("anees_steps_inside", steps_inside.0),
            ("anis_steps_inside", steps_inside.1),
        ] {
            if let Some(f) = frac {
                out.push(TestResult {
                    test: name.into(),
                    statistic: f,
                    lower: Some(1.0 - alpha),
                    upper: None,
                    dof: None,
                    p_value: None,
                    pass: f >= 1.0 - alpha,
                    direction: None,
                });
            }
        }

        // Whiteness: z_l = Σ wᵀw_{+l}/√pairs ~ N(0, 1) per lag; Bonferroni over the lags.
        let lag_prod = self.lag_prod.as_deref().unwrap_or(&[]);
        let lags = lag_prod.len();
        let w_sq = self.w_sq;
        if lags > 0 && w_sq > 0.0 {
            let crit = normal_quantile(1.0 - alpha / (2.0 * lags as f64));
            let mut worst: Option<(f64, f64, f64)> = None; // (|z|, ρ, ρ bound)
            for (&prod, &pairs) in lag_prod.iter().zip(&self.lag_pairs) {
                if pairs == 0 {
                    continue;
                }
                let z = prod / (pairs as f64).sqrt();
                let rho_l = prod / w_sq;
                let bound = crit * (pairs as f64).sqrt() / w_sq;
                if worst.is_none_or(|(wz, _, _)| z.abs() > wz) {
                    worst = Some((z.abs(), rho_l, bound));
                }
            }
            if let Some((z, rho_l, bound)) = worst {
                out.push(TestResult {
                    test: "innovation_whiteness".into(),
                    statistic: rho_l,
                    lower: Some(-bound),
                    upper: Some(bound),
                    dof: Some(lags as f64),
                    p_value: Some((normal_two_sided_p(z) * lags as f64).min(1.0)),
                    pass: z <= crit,
                    direction: None,
                });
            }
        }

        // Bias: per state, the per-run mean normalised error e/√P_ii is N(0, ·) across runs.
        for (i, state) in state_names.iter().enumerate().take(self.row_width() - 1) {
            if let Some(mut t) = self.t_test(1 + i, &format!("bias_{state}"), 0.0, alpha) {
                t.direction = None;
                out.push(t);
            }
        }

        // The verdict: both calibrated tests at α/2 (Bonferroni) ⇒ false-alarm rate ≤ α. A
        // filter without an error transition (a marginal of a larger state, say) has no
        // calibrated NEES test; with N ≥ 20 runs the model-free run-average t-test, valid for
        // any filter, stands in for it.
        let nees = nees.or_else(|| {
            (self.used >= 20)
                .then(|| out.iter().find(|t| t.test == "nees_run_average_t").cloned())
                .flatten()
        });
        if let (Some(a), Some(b)) = (&nees, &nis) {
            let (pa, pb) = (a.p_value.unwrap_or(0.0), b.p_value.unwrap_or(0.0));
            let pass = pa > alpha / 2.0 && pb > alpha / 2.0;
            // The failing test's side of its band's centre (its expected value) says which way.
            let side = |t: &TestResult| {
                let centre = (t.lower.unwrap_or(0.0) + t.upper.unwrap_or(0.0)) / 2.0;
                if t.statistic > centre {
                    Direction::Optimistic
                } else {
                    Direction::Pessimistic
                }
            };
            let p = pa.min(pb);
            let direction = (!pass).then(|| if pa <= pb { side(a) } else { side(b) });
            out.push(TestResult {
                test: VERDICT.into(),
                statistic: p,
                lower: Some(alpha / 2.0),
                upper: None,
                dof: None,
                p_value: Some((2.0 * pa.min(pb)).min(1.0)),
                pass,
                direction,
            });
        }
        out
    }
}

/// One cell and filter's consistency evaluations — the whole cell, then each subset of its
/// first N runs — folded run by run: a [`CellSums`] per evaluation and the per-run rows of
/// the second pass in a [`Spill`] shared by all (a subset's counted runs are the first rows),
/// so memory does not grow with the runs.
pub struct ConsistencyFold {
    /// Per evaluation: it counts the runs with index below this bound.
    evaluations: Vec<(usize, CellSums)>,
    rows: Spill,
    row: Vec<f64>,
    next_run: usize,
}

impl ConsistencyFold {
    /// Evaluations of the runs below each bound of `run_bounds` (`usize::MAX`: all), for `n`
    /// states of which `bias_states` are bias-tested; scratch space (if any) goes into `dir`.
    pub fn new(dir: &Path, n: usize, bias_states: usize, run_bounds: &[usize]) -> Self {
        Self::with_capacity(dir, n, bias_states, run_bounds, SPILL_ROWS)
    }

    /// As [`ConsistencyFold::new`], keeping at most `cap_rows` rows in memory (tests use a
    /// small one).
    pub fn with_capacity(
        dir: &Path,
        n: usize,
        bias_states: usize,
        run_bounds: &[usize],
        cap_rows: usize,
    ) -> Self {
        let sums = CellSums::new(n, bias_states);
        let width = sums.row_width();
        ConsistencyFold {
            evaluations: run_bounds.iter().map(|&b| (b, sums.clone())).collect(),
            rows: Spill::with_capacity(dir, width, cap_rows),
            row: vec![0.0; width],
            next_run: 0,
        }
    }

    /// Adds run `run`'s sums; runs come in increasing order.
    pub fn push(&mut self, run: usize, r: &RunConsistency) -> Result<(), OutputError> {
        debug_assert!(run >= self.next_run, "runs are folded in order");
        self.next_run = run + 1;
        for (bound, sums) in &mut self.evaluations {
            if run < *bound {
                sums.push(r);
            }
        }
        if CellSums::per_run_row(r, &mut self.row) {
            self.rows.push(&self.row)?;
        }
        Ok(())
    }

    /// The evaluations' sums, in the order of the bounds, after the second pass (which
    /// leaves none behind).
    pub fn finish(&mut self) -> Result<Vec<CellSums>, OutputError> {
        let evaluations = &mut self.evaluations;
        let mut at = 0usize;
        self.rows.for_each_row(|row| {
            for (_, sums) in evaluations.iter_mut() {
                if at < sums.used {
                    sums.push_deviations(row);
                }
            }
            at += 1;
            Ok(())
        })?;
        Ok(std::mem::take(&mut self.evaluations)
            .into_iter()
            .map(|(_, s)| s)
            .collect())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: f64, b: f64) -> bool {
        (a - b).abs() < 5e-5
    }

    #[test]
    fn bands_match_the_reference_values() {
        // Published χ² quantiles, to their 4 decimals.
        let b = average_chi2_band(6.0, 50.0, 0.05).unwrap();
        assert!(close(b.lo, 5.0782) && close(b.hi, 6.9975), "{b:?}");
        let b = average_chi2_band(6.0, 200.0, 0.003).unwrap();
        assert!(close(b.lo, 5.2990) && close(b.hi, 6.7530), "{b:?}");
        let b = average_chi2_band(3.0, 100.0, 0.01).unwrap();
        assert!(close(b.lo, 2.4066) && close(b.hi, 3.6684), "{b:?}");
        let mut cache = BandCache::new(0.05);
        assert_eq!(cache.band(300, 50), average_chi2_band(6.0, 50.0, 0.05));
    }

    #[test]
    fn p_values_by_hand() {
        // χ²(2) has cdf 1 − e^{−x/2}: at x = 2 ln 2 the cdf is 1/2, so p = 1.
        assert!((chi2_two_sided_p(2.0 * 2f64.ln(), 2.0).unwrap() - 1.0).abs() < 1e-12);
        // cdf(x) = 0.025 ⇒ p = 0.05.
        let x = -2.0 * (1.0f64 - 0.025).ln();
        assert!((chi2_two_sided_p(x, 2.0).unwrap() - 0.05).abs() < 1e-12);
        assert!((normal_two_sided_p(1.959963984540054) - 0.05).abs() < 1e-9);
        assert!((normal_quantile(0.975) - 1.959963984540054).abs() < 1e-9);
    }

    #[test]
    fn huge_dof_bands_are_accurate() {
        // For large ν the χ² is nearly normal: the band half-width ≈ z·√(2/ν)·d.
        let r = scaled_chi2_test("x", 6.0, 6.0, 1.2e6, 0.05).unwrap();
        let half = 1.959963984540054 * (2.0f64 / 1.2e6).sqrt() * 6.0;
        assert!(((r.upper.unwrap() - r.lower.unwrap()) / 2.0 - half).abs() < 1e-4 * half);
        assert!(r.pass);
        let r = scaled_chi2_test("x", 6.5, 6.0, 1.2e6, 0.05).unwrap();
        assert_eq!(r.direction, Some(Direction::Optimistic));
    }

    #[test]
    fn test_names_cover_every_test_a_cell_produces() {
        let states = ["a", "b"];
        let run = |i: f64| RunConsistency {
            first_step: Some(1),
            nees_sum: 20.0 + i,
            nees_n: 10,
            rho_sum: Some(1.0),
            nis_sum: 10.0 + i,
            nis_dof: 10,
            nis_n: 10,
            nme_sum: vec![0.1 * i, -0.2 * i],
            lag_prod: vec![0.1 * i, -0.1],
            lag_pairs: vec![9, 8],
            w_sq: 10.0,
            initial_nees: Some(2.0 + i),
        };
        let runs: Vec<_> = (0..25).map(|i| run(i as f64 / 10.0)).collect();
        let names = test_names(&states);
        let tests = cell_tests(&runs, 2, &states, 0.05, (Some(0.9), Some(0.95)));
        assert!(tests.len() >= 10, "{tests:?}");
        for t in tests {
            assert!(
                names.contains(&t.test),
                "{} missing from test_names",
                t.test
            );
        }
    }

    #[test]
    fn t_test_by_hand() {
        // mean 1, sd 1, n = 4 ⇒ t = 2 with 3 dof.
        let v = [0.0, 1.0, 2.0, 1.0];
        let sd = (2.0f64 / 3.0).sqrt();
        let r = t_test("t", &v, 0.0, 0.05, true).unwrap();
        assert!((r.statistic - 1.0 / (sd / 2.0)).abs() < 1e-12);
        assert!((r.upper.unwrap() - 3.182446305284263).abs() < 1e-6);
    }
}
