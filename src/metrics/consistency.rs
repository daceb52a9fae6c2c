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
//!     (Bonferroni), so its false-alarm rate is at most α: its row holds the combined p-value
//!     min(1, 2·min(p_NEES, p_NIS)) as `statistic` and `p_value`, and α as `lower` (it passes
//!     when the p-value exceeds α). [`verdict_band`] gives the α/2 bands it judges by. The
//!     book (`docs/src/statistics/consistency.md`) reports the rate measured by
//!     `examples/calibration.rs`.
//! * **Whiteness**, scale-free: see [`whiteness_test`].
//!
//! # Reference
//! Bar-Shalom, Li & Kirubarajan, *Estimation with Applications to Tracking and Navigation*
//! (2001), §5.4 (NEES/NIS tests, whiteness test).

use std::collections::HashMap;
use std::path::Path;

use statrs::distribution::{ChiSquared, ContinuousCDF, Normal, StudentsT};

use super::RunConsistency;
use super::spill::{SPILL_ROWS, Spill};
use crate::error::OutputError;

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

/// Two-sided p-value of `x` under χ²(`dof`); `None` for a NaN `x` (a statistic that could
/// not be computed has no p-value). Each tail is computed as itself (the upper one by the
/// survival function, never as 1 − cdf), so p-values far below 1e-16 keep their value and
/// their order down to the smallest positive double.
pub fn chi2_two_sided_p(x: f64, dof: f64) -> Option<f64> {
    if x.is_nan() {
        return None;
    }
    let chi = ChiSquared::new(dof).ok()?;
    let c = chi.cdf(x);
    // 1 − cdf is exact to 2⁻⁵³ in absolute terms: above `COMPLEMENT_FLOOR` that is within
    // 1e-10 of the tail and the complement is kept, so every p-value it gave to ten digits
    // stays bit for bit what it was; below, only the survival function has the digits.
    let tail = if 1.0 - c > COMPLEMENT_FLOOR {
        c.min(1.0 - c)
    } else {
        chi.sf(x)
    };
    Some((2.0 * tail).min(1.0))
}

/// The upper tail below which [`chi2_two_sided_p`] takes the survival function rather than
/// 1 − cdf (whose rounding, 2⁻⁵³, is 1e-10 of a tail of about 1.1e-6).
const COMPLEMENT_FLOOR: f64 = 1.2e-6;

/// Two-sided p-value of a standard normal statistic (NaN for a NaN `z`), from erfc: to about
/// 1e-9 in relative terms far into the tail.
pub fn normal_two_sided_p(z: f64) -> f64 {
    let n = Normal::new(0.0, 1.0).expect("the standard normal is valid");
    2.0 * n.sf(z.abs())
}

/// The standard normal quantile z_q.
pub fn normal_quantile(q: f64) -> f64 {
    Normal::new(0.0, 1.0)
        .expect("the standard normal is valid")
        .inverse_cdf(q)
}

/// Two-sided p-value of a Student-t statistic with `dof` degrees of freedom (`None` for a NaN
/// `t`; 0 for an infinite one). The tail is the regularised incomplete beta function of
/// ν/(ν + t²) itself, so a far-tail p-value is not lost to 1 − cdf.
pub fn t_two_sided_p(t: f64, dof: f64) -> Option<f64> {
    if t.is_nan() {
        return None;
    }
    if t.is_infinite() {
        return Some(0.0);
    }
    let d = StudentsT::new(0.0, 1.0, dof).ok()?;
    Some((2.0 * d.sf(t.abs())).min(1.0))
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

impl TestResult {
    /// A test whose statistic could not be computed from the data (a NaN or infinite sum, a
    /// spread of zero that leaves the statistic 0/0): statistic NaN (null in the table), no
    /// p-value, and never a pass. The band and dof are those the statistic would have been
    /// judged against.
    pub fn not_computed(
        test: &str,
        lower: Option<f64>,
        upper: Option<f64>,
        dof: Option<f64>,
    ) -> Self {
        TestResult {
            test: test.to_string(),
            statistic: f64::NAN,
            lower,
            upper,
            dof,
            p_value: None,
            pass: false,
            direction: None,
        }
    }

    /// Whether the test was computed: a statistic that is not NaN and a finite p-value (the
    /// descriptive fractions, which have no p-value, by their statistic alone). An infinite
    /// statistic with p = 0 is computed: a rejection ([`t_statistic`]).
    pub fn computed(&self) -> bool {
        !self.statistic.is_nan()
            && (self.p_value.is_some_and(f64::is_finite)
                || (self.p_value.is_none() && self.test.ends_with("_steps_inside")))
    }
}

/// The χ²-average test: `mean` is an average whose scaled value `mean·ν/d` ~ χ²(ν).
/// `d` is the expected value of one term (n for NEES, p for NIS). A `mean` that is NaN or
/// infinite (a sum that overflowed) has no p-value: the test is
/// [not computed](TestResult::not_computed).
pub fn scaled_chi2_test(test: &str, mean: f64, d: f64, nu: f64, alpha: f64) -> Option<TestResult> {
    let chi = ChiSquared::new(nu).ok()?;
    let lo = d * chi.inverse_cdf(alpha / 2.0) / nu;
    let hi = d * chi.inverse_cdf(1.0 - alpha / 2.0) / nu;
    if !mean.is_finite() {
        return Some(TestResult::not_computed(test, Some(lo), Some(hi), Some(nu)));
    }
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

/// Spreads at or below this many ulp of the mean's magnitude are rounding, not data: a
/// sum of N values carries a rounding of a few ulp per term, so a standard error that small
/// says the values are equal as far as doubles can tell.
pub const ROUNDING_ULPS: f64 = 4.0;

/// The one-sample t statistic (mean − μ)/se, or what stands in for it when se cannot carry
/// it:
///
/// * `None` (not computed) when the mean or se is NaN or infinite (a value or a square
///   that overflowed), or when the spread is at the level of rounding
///   (se ≤ [`ROUNDING_ULPS`] ulp of |mean|) and the mean is μ to the same rounding: 0/0;
/// * ±∞ (a rejection, p = 0) when the spread is at the level of rounding but the mean is
///   not μ: values that agree to the last digits away from μ are no sample of a
///   distribution centred on it (every NEES exactly 0 where n is expected; an estimate off
///   by 1e20 in every run, whose run-to-run differences are below one ulp).
pub fn t_statistic(mean: f64, se: f64, mu: f64) -> Option<f64> {
    if !mean.is_finite() || !se.is_finite() {
        return None;
    }
    let ulp = f64::EPSILON;
    if se > ROUNDING_ULPS * ulp * mean.abs() {
        return Some((mean - mu) / se);
    }
    let d = mean - mu;
    (d.abs() > ROUNDING_ULPS * ulp * mean.abs().max(mu.abs())).then(|| d.signum() * f64::INFINITY)
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
    let crit = t_quantile(1.0 - alpha / 2.0, nf - 1.0)?;
    let Some(t) = t_statistic(mean, (var / nf).sqrt(), mu) else {
        return Some(TestResult::not_computed(
            test,
            Some(-crit),
            Some(crit),
            Some(nf - 1.0),
        ));
    };
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

/// The innovation-whiteness test (`innovation_whiteness`) from the sums of whitened
/// innovations w_k = L_k⁻¹ν_k (S_k = L_k L_kᵀ, the filter's innovation covariance):
/// `lag_prod[l−1]` = Σ w_kᵀw_{k+l} over `lag_pairs[l−1]` = m_l pairs of components that both
/// reported, `w_sq` = Σ ‖w_k‖² over `components` = M reported components.
///
/// Per lag l = 1..L the statistic is the normalised autocorrelation
///
/// ```text
/// ρ̂_l = (Σ w_kᵀw_{k+l} / m_l) / (Σ ‖w_k‖² / M)
/// ```
///
/// the lag-l sample autocovariance divided by the sample variance of the same components,
/// as Bar-Shalom, Li & Kirubarajan (2001, §5.4) normalise the innovations' sample
/// autocorrelation. For white innovations √m_l·ρ̂_l is asymptotically N(0, 1), so the band is
/// ±z/√m_l with z = z_{1−α/(2L)}: it depends on the number of pairs only.
///
/// **Scale-free.** A filter whose S is off by a common factor c² (true innovation covariance
/// c²·S, gain still optimal) gives w_k with N(0, c²) components: numerator and denominator
/// both scale by c², so ρ̂_l and its band do not change. Only correlation in time moves the
/// statistic; the scale is the NIS test's business. (A normaliser by the nominal variance 1
/// instead of the sample's own would call a 10× noise error "correlated".)
///
/// **Lags combined** by Bonferroni: the test passes when every lag's |ρ̂_l| ≤ z/√m_l, so its
/// false-alarm rate is at most α. The row reports the lag with the largest |ρ̂_l|·√m_l, its
/// band, `dof` = L and p = min(1, L·p_l). `None` without lags, pairs or components;
/// [not computed](TestResult::not_computed) when the sums are not finite (an innovation
/// that overflowed) or the innovations are all exactly zero (no variance to normalise by).
pub fn whiteness_test(
    lag_prod: &[f64],
    lag_pairs: &[u64],
    w_sq: f64,
    components: u64,
    alpha: f64,
) -> Option<TestResult> {
    let lags = lag_prod.len();
    if lags == 0 || components == 0 || lag_pairs.iter().all(|&m| m == 0) {
        return None;
    }
    const TEST: &str = "innovation_whiteness";
    let finite = w_sq.is_finite() && lag_prod.iter().all(|p| p.is_finite());
    if !finite || w_sq <= 0.0 {
        return Some(TestResult::not_computed(
            TEST,
            None,
            None,
            Some(lags as f64),
        ));
    }
    let variance = w_sq / components as f64;
    let crit = normal_quantile(1.0 - alpha / (2.0 * lags as f64));
    let mut worst: Option<(f64, f64, f64)> = None; // (|z|, ρ̂, band half-width)
    for (&prod, &pairs) in lag_prod.iter().zip(lag_pairs) {
        if pairs == 0 {
            continue;
        }
        let m = pairs as f64;
        let rho = prod / m / variance;
        let z = rho * m.sqrt();
        if worst.is_none_or(|(wz, _, _)| z.abs() > wz) {
            worst = Some((z.abs(), rho, crit / m.sqrt()));
        }
    }
    let (z, rho, half) = worst?;
    Some(TestResult {
        test: TEST.into(),
        statistic: rho,
        lower: Some(-half),
        upper: Some(half),
        dof: Some(lags as f64),
        p_value: Some((normal_two_sided_p(z) * lags as f64).min(1.0)),
        pass: z <= crit,
        direction: None,
    })
}

/// The verdict's p-value from the NEES and NIS tests' two-sided p-values (Bonferroni):
/// min(1, 2·min(p_NEES, p_NIS)). It exceeds α exactly when both exceed α/2.
pub fn bonferroni_p(p_nees: f64, p_nis: f64) -> f64 {
    (2.0 * p_nees.min(p_nis)).min(1.0)
}

/// The band the verdict judges a component test's statistic against: the band at α/2 where
/// the row (`test`, `lower`, `upper`, `dof`) holds it at the study's α. The verdict's
/// components are `nees_time_average` (or `nees_run_average_t` standing in for it) and
/// `nis_time_average`; `None` for other tests or a row without its band or dof.
///
/// A χ² band [d·χ²⁻¹(α/2, ν)/ν, d·χ²⁻¹(1−α/2, ν)/ν] becomes [d·χ²⁻¹(α/4, ν)/ν,
/// d·χ²⁻¹(1−α/4, ν)/ν] (each end rescaled by the ratio of quantiles, so d need not be known);
/// a t band becomes ±t_{1−α/4}(dof).
pub fn verdict_band(
    test: &str,
    lower: Option<f64>,
    upper: Option<f64>,
    dof: Option<f64>,
    alpha: f64,
) -> Option<Band> {
    let dof = dof?;
    match test {
        "nees_time_average" | "nis_time_average" => {
            let chi = ChiSquared::new(dof).ok()?;
            let q = |p: f64| chi.inverse_cdf(p);
            Some(Band {
                lo: lower? * q(alpha / 4.0) / q(alpha / 2.0),
                hi: upper? * q(1.0 - alpha / 4.0) / q(1.0 - alpha / 2.0),
            })
        }
        "nees_run_average_t" => {
            let crit = t_quantile(1.0 - alpha / 4.0, dof)?;
            Some(Band {
                lo: -crit,
                hi: crit,
            })
        }
        _ => None,
    }
}

/// The name of the combined test row.
pub const VERDICT: &str = "verdict";

/// The name of the row holding a sequential gate's decision on the verdict (`kfmc check`
/// with `check.sequential`), after the verdict row of the same cell.
pub const SEQUENTIAL: &str = "sequential";

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
    out.push(SEQUENTIAL.into());
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
    /// Counted runs that exposed an error transition: the calibrated NEES test is the one a
    /// filter selects when any run has one, so a mixture means it could not be computed.
    rho_runs: usize,
    nis_n: u64,
    nis_dof: u64,
    nis_sum: f64,
    /// Σ initial NEES, `None` once a run has none.
    initial: Option<f64>,
    w_sq: f64,
    /// Components in `w_sq`.
    w_n: u64,
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
            rho_runs: 0,
            nis_n: 0,
            nis_dof: 0,
            nis_sum: -0.0,
            initial: Some(-0.0),
            w_sq: -0.0,
            w_n: 0,
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
        self.rho_runs += usize::from(r.rho_sum.is_some());
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
        self.w_n += r.w_n;
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

        out.extend(whiteness_test(
            self.lag_prod.as_deref().unwrap_or(&[]),
            &self.lag_pairs,
            self.w_sq,
            self.w_n,
            alpha,
        ));

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
        // any filter, stands in for it. A filter whose runs expose the transition selects the
        // calibrated test: when some of its runs lack it, the calibrated test cannot be
        // computed and nothing stands in, so no verdict is written rather than one from
        // another test.
        let nees = nees.or_else(|| {
            (self.used >= 20 && self.rho_runs == 0)
                .then(|| out.iter().find(|t| t.test == "nees_run_average_t").cloned())
                .flatten()
        });
        // A test that was not computed (a NaN statistic, a missing or NaN p-value) is a
        // verdict that could not be computed: none is written (NaN compares false, and
        // `f64::min` would drop it silently).
        if let (Some(a), Some(b)) = (&nees, &nis)
            && a.computed()
            && b.computed()
        {
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
            let direction = (!pass).then(|| if pa <= pb { side(a) } else { side(b) });
            // Bonferroni: the combined p-value is 2·min(p_NEES, p_NIS) (capped at 1), and the
            // verdict passes when it exceeds α, i.e. when both tests pass at α/2. `statistic`
            // and `p_value` both hold it, `lower` holds α, so the row reads like any other.
            let p = bonferroni_p(pa, pb);
            out.push(TestResult {
                test: VERDICT.into(),
                statistic: p,
                lower: Some(alpha),
                upper: None,
                dof: None,
                p_value: Some(p),
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

    /// The first evaluation's sums over the runs pushed so far, after their second pass,
    /// while the fold goes on: a sequential gate's look at a cell's first runs. Equal bit for
    /// bit to what [`ConsistencyFold::finish`] gives a fold of those runs alone.
    pub fn current(&mut self) -> Result<CellSums, OutputError> {
        let (_, first) = self
            .evaluations
            .first()
            .expect("a fold has at least one evaluation");
        let mut sums = first.clone();
        let mut at = 0usize;
        self.rows.for_each_row(|row| {
            if at < sums.used {
                sums.push_deviations(row);
            }
            at += 1;
            Ok(())
        })?;
        Ok(sums)
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
mod tests;
