//! The one-log NIS verdict measured on innovations of known correlation: AR(1) series
//! w_k = ρ w_{k−1} + √(1 − ρ²) ε_k (unit variance, so a matched S gives NIS = w²), judged by
//! exactly the code `kfmc ulog nis` judges an axis with ([`crate::metrics::batch_means`]).
//!
//! Per (ρ, length) and replication: the plan (τ̂, batch length; incomplete when the batches
//! are too short), then the t-test of the batch means of w² (S matched: a rejection is a false
//! alarm), of 2w² (S halved: over-confident) and of w²/2 (S doubled: over-conservative). Each
//! scale has its own plan, since τ̂ is estimated at the scale a consistent filter would have.
//! `examples/ulog_calibration.rs` prints the full table the docs show; a test runs a reduced
//! one.

use rand::{RngExt, SeedableRng};

use crate::metrics::batch_means;
use crate::power::clopper_pearson;

/// One (ρ, length) cell of the calibration table.
#[derive(Clone, Debug, PartialEq)]
pub struct Cell {
    /// Lag-1 correlation of the innovations.
    pub rho: f64,
    /// Samples in the series.
    pub length: usize,
    /// Replications.
    pub replications: u64,
    /// Replications judged (not incomplete).
    pub judged: u64,
    /// Judged replications that failed with S matched (false alarms).
    pub false_alarms: u64,
    /// Replications judged with S halved.
    pub judged_halved: u64,
    /// Of those, the ones that failed.
    pub caught_halved: u64,
    /// Replications judged with S doubled.
    pub judged_doubled: u64,
    /// Of those, the ones that failed.
    pub caught_doubled: u64,
}

impl Cell {
    /// False alarms over every replication (an incomplete verdict is not a failure) with its
    /// Clopper–Pearson 95 % interval.
    pub fn false_alarm_rate(&self) -> (f64, (f64, f64)) {
        rate(self.false_alarms, self.replications)
    }
    /// False alarms among the judged replications, with its interval.
    pub fn false_alarm_rate_judged(&self) -> (f64, (f64, f64)) {
        rate(self.false_alarms, self.judged)
    }
    /// Power against S halved among the replications judged with S halved.
    pub fn power_halved(&self) -> (f64, (f64, f64)) {
        rate(self.caught_halved, self.judged_halved)
    }
    /// Power against S doubled among the replications judged with S doubled.
    pub fn power_doubled(&self) -> (f64, (f64, f64)) {
        rate(self.caught_doubled, self.judged_doubled)
    }
}

fn rate(k: u64, n: u64) -> (f64, (f64, f64)) {
    if n == 0 {
        return (f64::NAN, (0.0, 1.0));
    }
    (k as f64 / n as f64, clopper_pearson(k, n))
}

/// A unit-variance AR(1) series of `n` samples with lag-1 correlation `rho`, started in its
/// stationary distribution.
pub fn ar1(rho: f64, n: usize, rng: &mut impl rand::Rng) -> Vec<f64> {
    let normal = rand_distr::StandardNormal;
    let s = (1.0 - rho * rho).max(0.0).sqrt();
    let mut out = Vec::with_capacity(n);
    let mut x: f64 = rng.sample(normal);
    for _ in 0..n {
        out.push(x);
        x = rho * x + s * rng.sample::<f64, _>(normal);
    }
    out
}

/// The cell (ρ, `length`) over `replications`, seeded by `seed`, at level `alpha`.
pub fn cell(rho: f64, length: usize, replications: u64, seed: u64, alpha: f64) -> Cell {
    let mut c = Cell {
        rho,
        length,
        replications,
        judged: 0,
        false_alarms: 0,
        judged_halved: 0,
        caught_halved: 0,
        judged_doubled: 0,
        caught_doubled: 0,
    };
    let key = crate::hash::fnv1a64(format!("{seed}/{rho}/{length}").as_bytes());
    let mut rng = rand_pcg::Pcg64::seed_from_u64(key);
    for _ in 0..replications {
        let w = ar1(rho, length, &mut rng);
        // Some(failed) when the series is judged with the logged S = S_true / scale.
        let verdict = |scale: f64| {
            let w: Vec<f64> = w.iter().map(|w| w * scale.sqrt()).collect();
            let y: Vec<f64> = w.iter().map(|w| w * w).collect();
            let plan = batch_means::plan(&[&y], &[&w]);
            let (None, Some(m)) = (&plan.incomplete, plan.batch_length) else {
                return None;
            };
            let means = batch_means::batch_means(&[&y], m);
            Some(batch_means::t_test(&means, 1.0, alpha).is_none_or(|t| t.p_value <= alpha))
        };
        let tally = |scale: f64, judged: &mut u64, failed: &mut u64| {
            if let Some(f) = verdict(scale) {
                *judged += 1;
                *failed += u64::from(f);
            }
        };
        tally(1.0, &mut c.judged, &mut c.false_alarms);
        tally(2.0, &mut c.judged_halved, &mut c.caught_halved);
        tally(0.5, &mut c.judged_doubled, &mut c.caught_doubled);
    }
    c
}

/// The table's text: one line per cell.
pub fn render(cells: &[Cell], alpha: f64) -> String {
    let pct = |(r, (lo, hi)): (f64, (f64, f64))| {
        if r.is_nan() {
            "—".to_string()
        } else {
            format!("{:.1} % [{:.1}, {:.1}]", 100.0 * r, 100.0 * lo, 100.0 * hi)
        }
    };
    let share = |k: u64, n: u64| 100.0 * k as f64 / n.max(1) as f64;
    let mut s = String::from(
        "| ρ | samples | judged | false alarms (all) | false alarms (judged) | S halved: judged, power | S doubled: judged, power |\n|---|---|---|---|---|---|---|\n",
    );
    for c in cells {
        s.push_str(&format!(
            "| {} | {} | {:.1} % | {} | {} | {:.1} %, {} | {:.1} %, {} |\n",
            c.rho,
            c.length,
            share(c.judged, c.replications),
            pct(c.false_alarm_rate()),
            pct(c.false_alarm_rate_judged()),
            share(c.judged_halved, c.replications),
            pct(c.power_halved()),
            share(c.judged_doubled, c.replications),
            pct(c.power_doubled()),
        ));
    }
    s.push_str(&format!(
        "\nα = {alpha}; rates with their Clopper–Pearson 95 % intervals; \"all\" counts an incomplete verdict as no alarm.\n"
    ));
    s
}
