//! Unit tests of `src/metrics/consistency.rs`, kept apart so that the module reads as its role.

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

/// ln Σ_{k<m} (x/2)^k / k!: with e^{−x/2} the χ²(2m) survival function, in log space
/// (ln k! summed from ln j, not from a gamma function).
fn ln_poisson_head(x: f64, m: usize) -> f64 {
    let h = x / 2.0;
    let mut ln_fact = 0.0;
    let terms: Vec<f64> = (0..m)
        .map(|k| {
            if k > 0 {
                ln_fact += (k as f64).ln();
            }
            k as f64 * h.ln() - ln_fact
        })
        .collect();
    let top = terms.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
    top + terms.iter().map(|t| (t - top).exp()).sum::<f64>().ln()
}

fn rel(a: f64, b: f64) -> f64 {
    ((a - b) / b).abs()
}

#[test]
fn far_tail_p_values_keep_their_digits() {
    // χ² with even dof 2m: P(X > x) = e^{−x/2} Σ_{k<m} (x/2)^k / k! exactly. These tails
    // are far below 1e-16, where 1 − cdf is 0.
    for (x, dof) in [(200.0, 6.0), (1000.0, 20.0), (1200.0, 400.0)] {
        let exact = (2.0 * (-x / 2.0 + ln_poisson_head(x, (dof / 2.0) as usize)).exp()).min(1.0);
        assert!(exact > 0.0 && exact < 1e-20, "{x}, {dof}: {exact}");
        let p = chi2_two_sided_p(x, dof).unwrap();
        assert!(rel(p, exact) < 1e-8, "χ²({dof}) at {x}: {p} vs {exact}");
    }
    // Hard numbers from mpmath 1.3 at 50 digits: 2·gammainc(k/2, x/2, ∞, regularized),
    // erfc(z/√2) and betainc(ν/2, 1/2, 0, ν/(ν + t²), regularized).
    let p = chi2_two_sided_p(400.0, 3.0).unwrap();
    assert!(rel(p, 4.427773186202235e-86) < 1e-10, "{p}");
    let p = chi2_two_sided_p(2400.0, 1201.0).unwrap();
    assert!(rel(p, 5.05404850716276e-82) < 1e-9, "{p}");
    // The dof of a large study's NEES test (N·K·n of about a million).
    let p = chi2_two_sided_p(209_500.0, 2.0e5).unwrap();
    assert!(rel(p, 1.6889899959214821e-49) < 1e-9, "{p}");
    let p = chi2_two_sided_p(1_223_000.0, 1.2e6).unwrap();
    assert!(rel(p, 2.9402450564040366e-49) < 1e-9, "{p}");
    let p = normal_two_sided_p(20.0);
    assert!(rel(p, 5.5072482372124675e-89) < 1e-8, "{p}");
    let p = normal_two_sided_p(-37.0);
    assert!(rel(p, 1.1451142445049154e-299) < 1e-8, "{p}");
    let p = t_two_sided_p(30.0, 49.0).unwrap();
    assert!(rel(p, 3.407670106498325e-33) < 1e-10, "{p}");
    let p = t_two_sided_p(-1000.0, 9.0).unwrap();
    assert!(rel(p, 5.091606607896935e-24) < 1e-10, "{p}");
    // Closed forms: with 1 dof p = (2/π)·atan(1/t), with 2 dof p = 1 − t/√(t² + 2).
    let p = t_two_sided_p(1e20, 1.0).unwrap();
    assert!(rel(p, 2.0 / std::f64::consts::PI * 1e-20) < 1e-12, "{p}");
    let t = 1e6f64;
    let r = (t * t + 2.0).sqrt();
    let p = t_two_sided_p(t, 2.0).unwrap();
    assert!(rel(p, 2.0 / (r * (r + t))) < 1e-10, "{p}");
    // Larger statistics, smaller p-values: the order survives far into the tail.
    let ps: Vec<f64> = [300.0, 400.0, 600.0, 900.0]
        .map(|x| chi2_two_sided_p(x, 6.0).unwrap())
        .to_vec();
    assert!(ps.windows(2).all(|w| w[0] > w[1] && w[1] > 0.0), "{ps:?}");
}

#[test]
fn a_statistic_that_is_not_a_number_has_no_p_value() {
    assert_eq!(chi2_two_sided_p(f64::NAN, 6.0), None);
    assert_eq!(t_two_sided_p(f64::NAN, 6.0), None);
    for mean in [f64::NAN, f64::INFINITY] {
        let r = scaled_chi2_test("nees_time_average", mean, 6.0, 300.0, 0.05).unwrap();
        assert!(r.statistic.is_nan() && r.p_value.is_none(), "{r:?}");
        assert!(!r.pass && !r.computed() && r.direction.is_none(), "{r:?}");
        assert!(r.lower.is_some() && r.upper.is_some());
    }
}

#[test]
fn a_t_test_without_spread_is_a_rejection_or_not_computed_never_a_pass() {
    // Every run's NEES exactly 0 where 6 is expected: no spread, mean far from μ.
    let r = t_test("nees_run_average_t", &[0.0; 30], 6.0, 0.05, true).unwrap();
    assert_eq!(r.statistic, f64::NEG_INFINITY, "{r:?}");
    assert_eq!(r.p_value, Some(0.0));
    assert!(!r.pass && r.computed());
    assert_eq!(r.direction, Some(Direction::Pessimistic));
    // An estimate off by 1e20 in every run: run-to-run differences below one ulp.
    let v: Vec<f64> = (0..30).map(|i| 1e20 + (i % 2) as f64 * 16384.0).collect();
    let r = t_test("bias_x", &v, 0.0, 0.05, true).unwrap();
    assert_eq!(r.statistic, f64::INFINITY, "{r:?}");
    assert!(!r.pass && r.computed() && r.p_value == Some(0.0), "{r:?}");
    // No spread and the mean is μ: 0/0, not computed.
    let r = t_test("bias_x", &[0.0; 30], 0.0, 0.05, true).unwrap();
    assert!(r.statistic.is_nan() && r.p_value.is_none(), "{r:?}");
    assert!(!r.pass && !r.computed());
    // A value or a square that overflowed: no mean or no spread to test.
    let mut v: Vec<f64> = (0..30).map(|i| 6.0 + (i as f64 * 0.7).sin()).collect();
    v[4] = 1e160;
    let r = t_test("nees_run_average_t", &v, 6.0, 0.05, true).unwrap();
    assert!(!r.pass && !r.computed(), "{r:?}");
    for bad in [f64::INFINITY, f64::NAN] {
        v[4] = bad;
        let r = t_test("nees_run_average_t", &v, 6.0, 0.05, true).unwrap();
        assert!(!r.pass && !r.computed(), "{bad}: {r:?}");
    }
    // A real spread is tested as before.
    v[4] = 6.0;
    let r = t_test("nees_run_average_t", &v, 6.0, 0.05, true).unwrap();
    assert!(r.computed() && r.statistic.is_finite(), "{r:?}");
}

#[test]
fn whiteness_from_sums_that_are_not_finite_or_zero_is_not_computed() {
    for (prod, w_sq) in [
        ([0.5, f64::NAN], 40.0),
        ([0.5, 0.1], f64::INFINITY),
        ([f64::INFINITY, 0.1], 40.0),
        ([0.0, 0.0], 0.0),
    ] {
        let r = whiteness_test(&prod, &[38, 36], w_sq, 40, 0.05).unwrap();
        assert!(!r.pass && !r.computed(), "{prod:?}, {w_sq}: {r:?}");
    }
    assert!(whiteness_test(&[0.5, 0.1], &[38, 36], 40.0, 40, 0.05).is_some_and(|r| r.computed()));
}

#[test]
fn a_cell_whose_nees_is_exactly_zero_is_rejected_by_the_model_free_verdict() {
    // 25 runs without an error transition (the model-free verdict), every NEES 0: the
    // filter's estimate is the truth at every step, where n = 2 is expected.
    let runs: Vec<RunConsistency> = runs_25()
        .into_iter()
        .map(|r| RunConsistency {
            nees_sum: 0.0,
            rho_sum: None,
            nme_sum: vec![0.0, 0.0],
            ..r
        })
        .collect();
    let tests = cell_tests(&runs, 2, &["a", "b"], 0.05, (None, None));
    let t = find(&tests, "nees_run_average_t");
    assert!(!t.pass && t.computed() && t.p_value == Some(0.0), "{t:?}");
    let v = find(&tests, VERDICT);
    assert!(!v.pass && v.computed(), "{v:?}");
    assert_eq!(v.direction, Some(Direction::Pessimistic));
    // Every normalised error exactly 0 and μ = 0: the bias tests cannot be computed.
    let b = find(&tests, "bias_a");
    assert!(!b.pass && !b.computed(), "{b:?}");
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
        w_n: 10,
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

/// 25 runs of a two-state filter with an error transition on every run.
fn runs_25() -> Vec<RunConsistency> {
    (0..25)
        .map(|i| {
            let i = i as f64 / 10.0;
            RunConsistency {
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
                w_n: 10,
                initial_nees: None,
            }
        })
        .collect()
}

fn verdict(runs: &[RunConsistency]) -> Option<TestResult> {
    cell_tests(runs, 2, &["a", "b"], 0.05, (None, None))
        .into_iter()
        .find(|t| t.test == VERDICT)
}

#[test]
fn a_run_without_its_error_transition_leaves_no_verdict_rather_than_another_test() {
    let mut runs = runs_25();
    assert!(verdict(&runs).is_some(), "the calibrated verdict");
    // One run of a filter that exposes the transition lacks it: the calibrated NEES test
    // cannot be computed, and the model-free test (N ≥ 20) must not stand in for it.
    runs[7].rho_sum = None;
    assert_eq!(verdict(&runs), None);
    let tests = cell_tests(&runs, 2, &["a", "b"], 0.05, (None, None));
    assert!(tests.iter().all(|t| t.test != "nees_time_average"));
    assert!(tests.iter().any(|t| t.test == "nees_run_average_t"));
    // A filter that exposes no transition on any run selects the model-free test.
    for r in &mut runs {
        r.rho_sum = None;
    }
    let v = verdict(&runs).expect("the model-free verdict at N = 25");
    let t = cell_tests(&runs, 2, &["a", "b"], 0.05, (None, None))
        .into_iter()
        .find(|t| t.test == "nees_run_average_t")
        .unwrap();
    // The verdict's Bonferroni p-value is at most twice the stand-in test's.
    assert!(v.statistic <= (2.0 * t.p_value.unwrap()).min(1.0));
}

#[test]
fn a_nan_p_value_leaves_no_verdict() {
    let mut runs = runs_25();
    runs[3].nis_sum = f64::NAN;
    let tests = cell_tests(&runs, 2, &["a", "b"], 0.05, (None, None));
    let nis = tests.iter().find(|t| t.test == "nis_time_average").unwrap();
    assert!(nis.statistic.is_nan());
    assert_eq!(verdict(&runs), None, "{tests:?}");
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

/// A cell of 30 runs with two lags, fixed values standing in for white innovations.
fn white_cell() -> Vec<RunConsistency> {
    (0..30)
        .map(|i| {
            let x = i as f64;
            RunConsistency {
                first_step: Some(1),
                nees_sum: 40.0 + (x * 0.9).sin(),
                nees_n: 20,
                rho_sum: Some(1.0),
                nis_sum: 40.0 + (x * 0.7).sin(),
                nis_dof: 40,
                nis_n: 20,
                nme_sum: vec![0.1 * (x * 0.3).sin(), -0.1 * (x * 0.5).cos()],
                lag_prod: vec![3.0 * (x * 1.3).sin(), 2.0 * (x * 0.4).cos()],
                lag_pairs: vec![38, 36],
                w_sq: 40.0 + (x * 0.7).sin(),
                w_n: 40,
                initial_nees: None,
            }
        })
        .collect()
}

fn find(tests: &[TestResult], name: &str) -> TestResult {
    tests.iter().find(|t| t.test == name).cloned().unwrap()
}

#[test]
fn whiteness_band_does_not_change_when_the_innovations_are_scaled() {
    // The same innovations multiplied by c: every product and square scales by c², as it
    // does when the truth's noise is c² times what the filter assumes (gain unchanged).
    let base = white_cell();
    let scaled = |c: f64| -> Vec<RunConsistency> {
        base.iter()
            .map(|r| RunConsistency {
                nis_sum: r.nis_sum * c * c,
                lag_prod: r.lag_prod.iter().map(|p| p * c * c).collect(),
                w_sq: r.w_sq * c * c,
                ..r.clone()
            })
            .collect()
    };
    let white = |runs: &[RunConsistency]| {
        find(
            &cell_tests(runs, 2, &["a", "b"], 0.05, (None, None)),
            "innovation_whiteness",
        )
    };
    let w1 = white(&base);
    // By hand: ρ̂_l = (Σ prod_l / Σ pairs_l) / (Σ ‖w‖² / Σ p), the lag with the larger
    // |ρ̂_l|·√pairs_l reported, band ±z_{1−α/4}/√pairs_l (Bonferroni over 2 lags).
    let w_sq: f64 = base.iter().map(|r| r.w_sq).sum();
    let var = w_sq / (30.0 * 40.0);
    let (rho, half) = (0..2)
        .map(|l| {
            let prod: f64 = base.iter().map(|r| r.lag_prod[l]).sum();
            let m = 30.0 * base[0].lag_pairs[l] as f64;
            (prod / m / var, normal_quantile(1.0 - 0.05 / 4.0) / m.sqrt())
        })
        .max_by(|a, b| (a.0.abs() / a.1).total_cmp(&(b.0.abs() / b.1)))
        .unwrap();
    assert!(
        (w1.statistic - rho).abs() <= 1e-12 * rho.abs(),
        "{w1:?} vs {rho}"
    );
    assert!(
        (w1.upper.unwrap() - half).abs() <= 1e-12 * half,
        "{w1:?} vs {half}"
    );
    assert_eq!(w1.lower, w1.upper.map(|h| -h));
    for c in [0.5, 10.0, 1e-3, 3.7] {
        let w = white(&scaled(c));
        assert_eq!((w.lower, w.upper), (w1.lower, w1.upper), "band at c = {c}");
        assert!(
            (w.statistic - w1.statistic).abs() <= 1e-12 * w1.statistic.abs(),
            "statistic at c = {c}: {} vs {}",
            w.statistic,
            w1.statistic
        );
        assert_eq!(w.pass, w1.pass, "c = {c}");
        let (p, p1) = (w.p_value.unwrap(), w1.p_value.unwrap());
        assert!((p - p1).abs() <= 1e-9 * p1.max(1e-300), "p at c = {c}");
    }
}

#[test]
fn verdict_row_holds_the_bonferroni_p_value_against_alpha() {
    let alpha = 0.05;
    let mut cell = white_cell();
    for (i, r) in cell.iter_mut().enumerate() {
        // NEES a little high in some runs, so the two p-values differ.
        r.nees_sum += 2.0 * (i % 3) as f64;
    }
    let tests = cell_tests(&cell, 2, &["a", "b"], alpha, (None, None));
    let (a, b, v) = (
        find(&tests, "nees_time_average"),
        find(&tests, "nis_time_average"),
        find(&tests, VERDICT),
    );
    let (pa, pb) = (a.p_value.unwrap(), b.p_value.unwrap());
    let p = (2.0 * pa.min(pb)).min(1.0);
    assert_eq!(v.statistic, p);
    assert_eq!(v.p_value, Some(p));
    assert_eq!((v.lower, v.upper, v.dof), (Some(alpha), None, None));
    assert_eq!(v.pass, p > alpha);
    assert_eq!(v.pass, pa > alpha / 2.0 && pb > alpha / 2.0);
    // Two p-values that straddle α/2 and 1.
    assert_eq!(bonferroni_p(0.02, 0.9), 0.04);
    assert_eq!(bonferroni_p(0.7, 0.6), 1.0);
}

#[test]
fn verdict_bands_are_the_component_bands_at_half_alpha() {
    let alpha = 0.05;
    for (mean, d, nu) in [(6.2, 6.0, 3000.0), (2.9, 3.0, 40.0), (1.0, 1.0, 1.2e6)] {
        let at_alpha = scaled_chi2_test("nees_time_average", mean, d, nu, alpha).unwrap();
        let at_half = scaled_chi2_test("nees_time_average", mean, d, nu, alpha / 2.0).unwrap();
        for name in ["nees_time_average", "nis_time_average"] {
            let b =
                verdict_band(name, at_alpha.lower, at_alpha.upper, at_alpha.dof, alpha).unwrap();
            let (lo, hi) = (at_half.lower.unwrap(), at_half.upper.unwrap());
            assert!((b.lo - lo).abs() <= 1e-12 * lo, "{b:?} vs {lo}");
            assert!((b.hi - hi).abs() <= 1e-12 * hi, "{b:?} vs {hi}");
        }
    }
    let v = [5.0, 6.5, 7.0, 5.5, 6.0, 8.0];
    let at_alpha = t_test("nees_run_average_t", &v, 6.0, alpha, true).unwrap();
    let at_half = t_test("nees_run_average_t", &v, 6.0, alpha / 2.0, true).unwrap();
    let b = verdict_band(
        "nees_run_average_t",
        at_alpha.lower,
        at_alpha.upper,
        at_alpha.dof,
        alpha,
    )
    .unwrap();
    assert_eq!((Some(b.lo), Some(b.hi)), (at_half.lower, at_half.upper));
    assert_eq!(
        verdict_band(
            "innovation_whiteness",
            Some(-1.0),
            Some(1.0),
            Some(3.0),
            alpha
        ),
        None
    );
}
