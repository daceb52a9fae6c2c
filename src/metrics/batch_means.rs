//! The mean of one correlated series tested by non-overlapping batch means: the calibrated
//! verdict on one real log's NIS (`kfmc ulog nis`).
//!
//! A real filter's innovations are correlated in time, so the time average of N samples of
//! NIS varies far more than 2/N, and a χ²(N) band would reject a consistent filter. The
//! series (cut into *stretches*, runs of samples with nothing excluded between them) is
//! split into B ≥ [`BATCHES`] batches of m consecutive samples, never across a stretch's end.
//! When m is many times the series' integrated autocorrelation time τ, the batch means are
//! nearly independent and nearly normal, so
//!
//! ```text
//! t = (ȳ − μ₀) / (s_b / √B)  ~  t(B − 1)
//! ```
//!
//! where ȳ is the mean of the batch means and s_b their standard deviation: the t reference
//! carries the uncertainty of the variance estimate, which a χ² band with an effective dof
//! would ignore. The verdict is judged only when m ≥ [`TAU_MULTIPLE`]·τ̂, so the minimum
//! length of a judged series is B·[`TAU_MULTIPLE`]·τ̂ samples, i.e. B·[`TAU_MULTIPLE`]
//! effective samples; shorter series are **incomplete**, never a pass.
//!
//! τ̂ is the larger of two estimates, so that it errs long: Sokal's automatic-window estimate
//! from the NIS series' own autocorrelation (window M, the first with M ≥ 5·τ̂(M)), and the τ
//! of the NIS of an AR(1) innovation, (1 + r²)/(1 − r²), at an upper bound of the whitened
//! innovation's lag-1 correlation r. Both are pooled over stretches.
//!
//! r is estimated **at the scale the null hypothesis claims**, E(w²) = 1: r̃ = 1 − ½·mean(Δw²).
//! The sample lag-1 autocorrelation, 1 − ½·mean(Δw²)/mean((w − w̄)²), divides by the sample
//! variance, which is the quantity under test: a series whose NIS happens to average low
//! looks less correlated, so near the minimum length the judged series would be mostly those
//! with a low mean (60–90 % of them fail a consistent filter). The squared increments carry the
//! series' fast part, nearly independent of its level, so selecting on r̃ leaves the mean NIS
//! of a consistent filter's judged series unbiased. Under an alternative the scale is wrong
//! on purpose: S too small shrinks τ̂ (any failure is then a true one), S too large inflates it
//! by S/S_true, so an over-conservative filter needs that much more flight to be judged.
//!
//! The false-alarm rate and power of this verdict on AR(1) innovations of known ρ are measured
//! by [`crate::ulog::calibration`] (the docs' table).

/// Batches a judged series is split into, at least.
pub const BATCHES: usize = 10;

/// A batch must be at least this many integrated autocorrelation times long.
pub const TAU_MULTIPLE: f64 = 10.0;

/// Sokal's window constant: the window M is the first with M ≥ this × τ̂(M).
const SOKAL_C: f64 = 5.0;

/// The series' integrated autocorrelation time estimate, pooled over `stretches`
/// (autocovariances from pairs inside one stretch), by Sokal's automatic window. Lags stop at
/// `max_lag`: a τ̂ beyond `max_lag / 5` is returned as `max_lag / 5`, since a caller only
/// needs to know it is that long.
pub fn integrated_time(stretches: &[&[f64]], max_lag: usize) -> f64 {
    let n: usize = stretches.iter().map(|s| s.len()).sum();
    if n < 2 {
        return 1.0;
    }
    let mean = stretches.iter().flat_map(|s| s.iter()).sum::<f64>() / n as f64;
    let c0 = stretches
        .iter()
        .flat_map(|s| s.iter())
        .map(|y| (y - mean).powi(2))
        .sum::<f64>()
        / n as f64;
    if c0.is_nan() || c0 <= 0.0 {
        return 1.0;
    }
    let mut tau = 1.0;
    for lag in 1..=max_lag.max(1) {
        let (mut sum, mut pairs) = (0.0, 0usize);
        for s in stretches {
            if s.len() > lag {
                for i in 0..s.len() - lag {
                    sum += (s[i] - mean) * (s[i + lag] - mean);
                }
                pairs += s.len() - lag;
            }
        }
        if pairs == 0 {
            break;
        }
        tau += 2.0 * sum / pairs as f64 / c0;
        if lag as f64 >= SOKAL_C * tau {
            return tau.max(1.0);
        }
    }
    tau.max(max_lag as f64 / SOKAL_C).max(1.0)
}

/// The NIS's integrated autocorrelation time if the whitened innovations `w` followed an
/// AR(1), (1 + r²)/(1 − r²) (the autocorrelation of w² at lag k is r^{2k} for Gaussian w), at
/// an upper bound r = r̃ + 2·sd(r̃) of r̃ = 1 − ½·mean(Δw²), the lag-1 correlation at the
/// null hypothesis' scale E(w²) = 1 (increments paired inside stretches; see the module
/// documentation for why not the sample autocorrelation).
pub fn ar1_time(stretches: &[&[f64]]) -> f64 {
    let d: Vec<f64> = stretches
        .iter()
        .flat_map(|s| s.windows(2).map(|p| (p[1] - p[0]).powi(2)))
        .collect();
    let n = d.len();
    if n < 2 {
        return 1.0;
    }
    let mean = d.iter().sum::<f64>() / n as f64;
    let var = d.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1) as f64;
    if !mean.is_finite() || !var.is_finite() {
        return 1.0;
    }
    // Successive increments of an AR(1) correlate by −(1 − r)/2, so their squares by at most
    // 1/4 (Gaussian), and the variance of mean(Δw²) is at most 1 + 2·(1/4) = 1.5 times the
    // independent one; the sample variance of Δw² keeps heavy tails in the bound.
    let sd = (1.5 * var / n as f64).sqrt() / 2.0;
    let r = (1.0 - mean / 2.0).max(0.0);
    let up = (r + 2.0 * sd).clamp(0.0, 0.999_999);
    (1.0 + up * up) / (1.0 - up * up)
}

/// The batch length for `lengths` (the stretches' sample counts): the longest m that still
/// gives at least [`BATCHES`] whole batches inside the stretches, `None` when even m = 1
/// does not.
pub fn batch_length(lengths: &[usize]) -> Option<usize> {
    let count = |m: usize| lengths.iter().map(|l| l / m).sum::<usize>();
    let total: usize = lengths.iter().sum();
    if count(1) < BATCHES {
        return None;
    }
    let (mut lo, mut hi) = (1usize, total / BATCHES + 1);
    // Largest m with count(m) ≥ BATCHES (count falls as m grows).
    while lo < hi {
        let mid = (lo + hi).div_ceil(2);
        if count(mid) >= BATCHES {
            lo = mid;
        } else {
            hi = mid - 1;
        }
    }
    Some(lo)
}

/// The means of consecutive batches of `m` samples inside each stretch (a stretch's last
/// samples that do not fill a batch are left out).
pub fn batch_means(stretches: &[&[f64]], m: usize) -> Vec<f64> {
    let mut out = Vec::new();
    if m == 0 {
        return out;
    }
    for s in stretches {
        for chunk in s.chunks_exact(m) {
            out.push(chunk.iter().sum::<f64>() / m as f64);
        }
    }
    out
}

/// The t-test of batch means against μ₀.
#[derive(Clone, Debug, PartialEq)]
pub struct MeanTest {
    /// Mean of the batch means (the mean of the samples used).
    pub mean: f64,
    /// Acceptance band of the mean at the test's level: μ₀ ∓ t·s_b/√B.
    pub lower: f64,
    /// Its upper end.
    pub upper: f64,
    /// Degrees of freedom of the t reference, B − 1.
    pub dof: f64,
    /// Two-sided p-value.
    pub p_value: f64,
    /// Batches.
    pub batches: usize,
}

/// The two-sided t-test of `means` (≥ 2, with spread) against `mu0` at level `alpha`.
pub fn t_test(means: &[f64], mu0: f64, alpha: f64) -> Option<MeanTest> {
    let b = means.len();
    if b < 2 {
        return None;
    }
    let mean = means.iter().sum::<f64>() / b as f64;
    let var = means.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (b - 1) as f64;
    let se = (var / b as f64).sqrt();
    if se.is_nan() || se <= 0.0 || !mean.is_finite() {
        return None;
    }
    let dof = (b - 1) as f64;
    let crit = super::consistency::t_quantile(1.0 - alpha / 2.0, dof)?;
    Some(MeanTest {
        mean,
        lower: mu0 - crit * se,
        upper: mu0 + crit * se,
        dof,
        p_value: super::consistency::t_two_sided_p((mean - mu0) / se, dof)?,
        batches: b,
    })
}

/// How a series' batch plan came out.
#[derive(Clone, Debug, PartialEq)]
pub struct Plan {
    /// τ̂, the integrated autocorrelation time used (samples).
    pub tau: f64,
    /// Samples per batch, when the series gives [`BATCHES`] batches at all.
    pub batch_length: Option<usize>,
    /// Samples in the stretches.
    pub samples: usize,
    /// Why the series cannot be judged, when it cannot.
    pub incomplete: Option<String>,
}

impl Plan {
    /// Effective samples, N/τ̂.
    pub fn effective_samples(&self) -> f64 {
        self.samples as f64 / self.tau
    }
}

/// The batch plan of a series of NIS values `y` and its whitened innovations `w` (same
/// stretches, w scaled so that a consistent filter has E(w²) = 1; empty when only the NIS is
/// known): τ̂, the batch length, and whether the batches are long enough
/// (m ≥ [`TAU_MULTIPLE`]·τ̂).
pub fn plan(y: &[&[f64]], w: &[&[f64]]) -> Plan {
    let lengths: Vec<usize> = y.iter().map(|s| s.len()).collect();
    let samples: usize = lengths.iter().sum();
    let m = batch_length(&lengths);
    // A τ̂ longer than m/TAU_MULTIPLE makes the series incomplete whatever its value, so the
    // window need not reach past it.
    let cap = m.map_or(1, |m| {
        ((m as f64 / TAU_MULTIPLE) * SOKAL_C).ceil() as usize + 1
    });
    let tau = integrated_time(y, cap).max(if w.is_empty() { 1.0 } else { ar1_time(w) });
    let incomplete = match m {
        None => Some(format!(
            "{samples} samples in {} stretch{} cannot make {BATCHES} batches",
            lengths.len(),
            if lengths.len() == 1 { "" } else { "es" }
        )),
        Some(m) if (m as f64) < TAU_MULTIPLE * tau => Some(format!(
            "{samples} samples are {:.1} effective samples (τ̂ = {tau:.1} samples); a verdict needs {BATCHES} batches of ≥ {TAU_MULTIPLE}·τ̂ each, i.e. {} effective samples",
            samples as f64 / tau,
            (BATCHES as f64 * TAU_MULTIPLE) as usize
        )),
        Some(_) => None,
    };
    Plan {
        tau,
        batch_length: m,
        samples,
        incomplete,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_batch_length_is_the_longest_that_gives_ten_batches_inside_stretches() {
        assert_eq!(batch_length(&[100]), Some(10));
        assert_eq!(batch_length(&[105]), Some(10));
        // 3 stretches of 35: m = 10 gives 3 + 3 + 3 = 9 batches, m = 8 gives 4 × 3 = 12.
        assert_eq!(batch_length(&[35, 35, 35]), Some(8));
        assert_eq!(batch_length(&[9]), None);
        assert_eq!(batch_means(&[&[1.0, 2.0, 3.0, 4.0, 5.0]], 2), [1.5, 3.5]);
    }

    #[test]
    fn white_series_have_a_time_near_one_and_ar1_its_known_time() {
        use rand::{RngExt, SeedableRng};
        let mut rng = rand_pcg::Pcg64::seed_from_u64(7);
        let normal = rand_distr::StandardNormal;
        let n = 100_000;
        let white: Vec<f64> = (0..n).map(|_| rng.sample::<f64, _>(normal)).collect();
        let y: Vec<f64> = white.iter().map(|w| w * w).collect();
        assert!((integrated_time(&[&y], 1000) - 1.0).abs() < 0.1);
        assert!((ar1_time(&[&white]) - 1.0).abs() < 0.05);
        // AR(1) with ρ = 0.9: the NIS's τ is (1 + ρ²)/(1 − ρ²) = 9.53.
        let rho: f64 = 0.9;
        let mut w = vec![0.0; n];
        w[0] = rng.sample::<f64, _>(normal);
        for k in 1..n {
            w[k] = rho * w[k - 1] + (1.0 - rho * rho).sqrt() * rng.sample::<f64, _>(normal);
        }
        let y: Vec<f64> = w.iter().map(|w| w * w).collect();
        let tau = integrated_time(&[&y], 1000);
        assert!((tau - 9.53).abs() < 1.5, "{tau}");
        let ar = ar1_time(&[&w]);
        assert!(ar > 9.53 && ar < 11.0, "{ar}");
    }
}
