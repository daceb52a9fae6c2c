//! Tests of the tests: the band, verdict, whiteness and bias code fed with samples drawn from
//! the exact null distributions must reject at the stated rate (binomial tolerance, fixed
//! seed); and the verdict on a correctly tuned planar EKF keeps its false-alarm rate over 200
//! independent master seeds.

use kfmc::experiment;
use kfmc::metrics::RunConsistency;
use kfmc::metrics::consistency::{VERDICT, average_chi2_band, cell_tests};
use kfmc::step_loop::Unit;
use rand::SeedableRng;
use rand_distr::{ChiSquared, Distribution, StandardNormal};
use rand_pcg::Pcg64;
use std::path::Path;

const ALPHA: f64 = 0.05;

/// |rate − p| ≤ 3 binomial standard deviations over `trials`.
fn within_binomial(rate: f64, p: f64, trials: usize) -> bool {
    (rate - p).abs() <= 3.0 * (p * (1.0 - p) / trials as f64).sqrt()
}

/// One simulated cell of N runs × K steps under the null: NEES ~ χ²(n), NIS ~ χ²(p), white
/// N(0, 1) whitened innovations, zero-mean normalised errors, no time correlation (ρ = 1).
fn null_cell(
    rng: &mut Pcg64,
    runs: usize,
    steps: usize,
    n: usize,
    p: usize,
    lags: usize,
) -> Vec<RunConsistency> {
    let nees = ChiSquared::new(n as f64).unwrap();
    (0..runs)
        .map(|_| {
            let mut r = RunConsistency {
                first_step: Some(1),
                rho_sum: Some(0.0),
                nme_sum: vec![0.0; n],
                lag_prod: vec![0.0; lags],
                lag_pairs: vec![0; lags],
                ..Default::default()
            };
            let mut history: Vec<Vec<f64>> = Vec::new();
            for _ in 0..steps {
                r.nees_sum += nees.sample(rng);
                r.nees_n += 1;
                for v in r.nme_sum.iter_mut() {
                    let z: f64 = StandardNormal.sample(rng);
                    *v += z;
                }
                let w: Vec<f64> = (0..p).map(|_| StandardNormal.sample(rng)).collect();
                let nis: f64 = w.iter().map(|x| x * x).sum();
                r.nis_sum += nis;
                r.nis_dof += p as u64;
                r.nis_n += 1;
                r.w_sq += nis;
                r.w_n += p as u64;
                for l in 0..lags.min(history.len()) {
                    let old = &history[history.len() - 1 - l];
                    r.lag_prod[l] += old.iter().zip(&w).map(|(a, b)| a * b).sum::<f64>();
                    r.lag_pairs[l] += p as u64;
                }
                history.push(w);
            }
            r
        })
        .collect()
}

#[test]
fn per_step_band_accepts_exact_chi2_averages_at_1_minus_alpha() {
    let mut rng = Pcg64::seed_from_u64(1);
    let (n, runs, trials) = (6.0, 50.0, 4000);
    let band = average_chi2_band(n, runs, ALPHA).unwrap();
    let chi = ChiSquared::new(n).unwrap();
    let inside = (0..trials)
        .filter(|_| {
            let avg = (0..runs as usize)
                .map(|_| chi.sample(&mut rng))
                .sum::<f64>()
                / runs;
            band.contains(avg)
        })
        .count();
    let rate = 1.0 - inside as f64 / trials as f64;
    assert!(within_binomial(rate, ALPHA, trials), "band rejects {rate}");
}

#[test]
fn verdict_whiteness_and_bias_reject_at_their_stated_rates_under_the_null() {
    let mut rng = Pcg64::seed_from_u64(2);
    let trials = 600;
    let states = ["a", "b", "c", "d", "e", "f"];
    let (mut verdict, mut nees, mut nis, mut white, mut bias) = (0, 0, 0, 0, 0);
    for _ in 0..trials {
        let cell = null_cell(&mut rng, 20, 30, 6, 3, 3);
        let tests = cell_tests(&cell, 6, &states, ALPHA, (None, None));
        let fails = |name: &str| tests.iter().any(|t| t.test == name && !t.pass);
        verdict += fails(VERDICT) as usize;
        nees += fails("nees_time_average") as usize;
        nis += fails("nis_time_average") as usize;
        white += fails("innovation_whiteness") as usize;
        bias += fails("bias_a") as usize;
    }
    let r = |c: usize| c as f64 / trials as f64;
    // The NEES and NIS draws are independent here, so the Bonferroni verdict rejects at
    // exactly 1 − (1 − α/2)².
    assert!(
        within_binomial(r(verdict), 1.0 - (1.0 - ALPHA / 2.0).powi(2), trials),
        "verdict {}",
        r(verdict)
    );
    assert!(within_binomial(r(nees), ALPHA, trials), "nees {}", r(nees));
    assert!(within_binomial(r(nis), ALPHA, trials), "nis {}", r(nis));
    assert!(within_binomial(r(bias), ALPHA, trials), "bias {}", r(bias));
    // Bonferroni over 3 lags: at most α, and not far below it for nearly independent lags.
    assert!(
        r(white) <= ALPHA + 3.0 * (ALPHA * (1.0 - ALPHA) / trials as f64).sqrt() && r(white) > 0.01,
        "white {}",
        r(white)
    );
}

#[test]
fn whiteness_false_alarm_rate_is_at_most_alpha_whatever_the_innovations_scale() {
    // White innovations whose covariance is c² times the filter's S (gain still optimal, so
    // the whitened innovations are N(0, c²) and still white): the whiteness test must keep
    // its false-alarm rate ≤ α at every c, within 3 binomial standard deviations over 600
    // exact null cells (20 runs × 30 steps × 3 components, 3 lags). The NIS test is the
    // one that must see c.
    let trials = 600;
    let tol = 3.0 * (ALPHA * (1.0 - ALPHA) / trials as f64).sqrt();
    for c in [0.5, 1.0, 10.0] {
        let mut rng = Pcg64::seed_from_u64(4);
        let (mut white, mut nis) = (0, 0);
        for _ in 0..trials {
            let mut cell = null_cell(&mut rng, 20, 30, 6, 3, 3);
            for r in &mut cell {
                let c2 = c * c;
                r.nis_sum *= c2;
                r.w_sq *= c2;
                r.lag_prod.iter_mut().for_each(|p| *p *= c2);
            }
            let tests = cell_tests(&cell, 6, &["a"], ALPHA, (None, None));
            let fails = |name: &str| tests.iter().any(|t| t.test == name && !t.pass);
            white += fails("innovation_whiteness") as usize;
            nis += fails("nis_time_average") as usize;
        }
        let rate = white as f64 / trials as f64;
        assert!(
            rate <= ALPHA + tol,
            "c = {c}: whiteness false-alarm rate {rate}"
        );
        // Bonferroni over 3 nearly independent lags rejects at nearly α, not at 0.
        assert!(rate > 0.01, "c = {c}: whiteness rejects at {rate}");
        let nis_rate = nis as f64 / trials as f64;
        if c == 1.0 {
            assert!(within_binomial(nis_rate, ALPHA, trials), "NIS {nis_rate}");
        } else {
            assert_eq!(nis, trials, "c = {c}: the NIS test sees the scale");
        }
    }
}

#[test]
fn verdict_detects_a_wrong_covariance_scale() {
    // NEES drawn as 1.1·χ²(n): a filter whose P is 10 % too small must be called optimistic.
    let mut rng = Pcg64::seed_from_u64(3);
    let mut cell = null_cell(&mut rng, 50, 100, 6, 3, 0);
    for r in &mut cell {
        r.nees_sum *= 1.1;
    }
    let tests = cell_tests(
        &cell,
        6,
        &["a", "b", "c", "d", "e", "f"],
        ALPHA,
        (None, None),
    );
    let v = tests.iter().find(|t| t.test == VERDICT).unwrap();
    assert!(!v.pass);
    assert_eq!(v.direction.map(|d| d.label()), Some("optimistic"));
}

#[test]
fn tuned_planar_ekf_false_alarm_rate_over_200_master_seeds() {
    // 200 independent master seeds × 50 runs × 200 steps of a correctly tuned EKF (matched
    // noise, sampled initial error). The verdict's stated rate is ≤ α (Bonferroni over the
    // NEES and NIS tests), ≈ α when they are nearly independent; the measured rate must lie
    // within the binomial tolerance of α = 0.05.
    let seeds = 200;
    let rejections: usize = (1..=seeds as u64)
        .map(|seed| {
            let text = format!(
                "master_seed = {seed}\nruns = 50\n[model]\nkind = \"planar_quadrotor\"\n[[scenarios]]\nname = \"roll\"\nduration_s = 2.0\n[[filters]]\nlabel = \"ekf\"\nkind = \"ekf\"\n[noise]\nfilter_noise = \"matched\"\n[initial_estimate]\nmode = \"sampled\"\np0_std = 0.01\n[consistency]\nalpha = 0.05\n"
            );
            let plan = experiment::parse(&text, Path::new("fa.toml")).unwrap();
            let trial = plan.trial();
            let cons: Vec<RunConsistency> = (0..plan.runs)
                .filter_map(|run| trial.run(&Unit { scenario: 0, scale: 0, run }).filters[0].consistency.clone())
                .collect();
            let states = trial.layout().quantity_names();
            let tests = cell_tests(&cons, 6, &states, ALPHA, (None, None));
            !tests.iter().find(|t| t.test == VERDICT).unwrap().pass as usize
        })
        .sum();
    let rate = rejections as f64 / seeds as f64;
    assert!(
        within_binomial(rate, ALPHA, seeds),
        "false-alarm rate {rate} over {seeds} seeds"
    );
}
