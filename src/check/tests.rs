//! Unit tests of the judging: the paired test, the run pairs and the declared-runs rule.

use super::judge::settle;
use super::paired::{StateRuns, rmse_pairs};
use super::tables::{RunCounts, runs_problem};
use super::*;
use crate::experiment::plan::{Assertion, Selection};
use crate::metrics::consistency::VERDICT;

#[test]
fn the_paired_excess_test_matches_a_hand_calculation() {
    // d = (0, 1, 2): mean 1, s = 1, t = 1/(1/√3) = √3. With 2 degrees of freedom the
    // t distribution's tail has the closed form ½(1 − t/√(t² + 2)).
    let t = paired_excess_test(&[(1.0, 1.0), (2.0, 1.0), (3.0, 1.0)], 0.0).unwrap();
    let root3 = 3f64.sqrt();
    assert!((t.t - root3).abs() < 1e-12, "{t:?}");
    let closed = 0.5 * (1.0 - root3 / (3.0f64 + 2.0).sqrt());
    assert!(
        (t.p_value - closed).abs() < 1e-9,
        "{} vs {closed}",
        t.p_value
    );
    assert_eq!((t.runs, t.mean, t.reference_mean), (3, 2.0, 1.0));
    // The margin scales the reference: 2 = (1 + 1) × 1 makes the mean difference 0 − 1.
    let m = paired_excess_test(&[(1.0, 1.0), (2.0, 1.0), (3.0, 1.0)], 1.0).unwrap();
    assert!(
        (m.t - 0.0).abs() < 1e-12 && (m.p_value - 0.5).abs() < 1e-12,
        "{m:?}"
    );
    // Equal runs: no spread, not worse.
    let same = paired_excess_test(&[(0.5, 0.5), (0.7, 0.7)], 0.0).unwrap();
    assert_eq!(same.p_value, 1.0);
    assert!(paired_excess_test(&[(1.0, 1.0)], 0.0).is_none());
}

#[test]
fn the_paired_excess_test_rejects_at_rate_alpha_on_its_boundary_and_catches_an_excess() {
    // Runs share a difficulty c_i (lognormal, spread 30 %); the filter's RMSE is
    // (1 + margin)·c_i·(1 + δ) + noise and the reference's c_i + noise. On the boundary
    // (δ = 0) the rejection rate must be α within 3 binomial standard deviations; 5 % worse
    // than the margin allows, with 30 runs, it must be caught in most replications.
    use rand::{RngExt, SeedableRng};
    let normal = |rng: &mut rand_pcg::Pcg64| {
        let (u, v): (f64, f64) = (rng.random(), rng.random());
        (-2.0 * (1.0 - u).ln()).sqrt() * (std::f64::consts::TAU * v).cos()
    };
    let (alpha, margin, n, reps) = (0.05, 0.1, 30, 4000);
    let mut rng = rand_pcg::Pcg64::seed_from_u64(36);
    let mut rate = |delta: f64| {
        let mut rejected = 0;
        for _ in 0..reps {
            let pairs: Vec<(f64, f64)> = (0..n)
                .map(|_| {
                    let c = (0.3 * normal(&mut rng)).exp();
                    let a = (1.0 + margin) * c * (1.0 + delta) + 0.02 * normal(&mut rng);
                    let b = c + 0.02 * normal(&mut rng);
                    (a, b)
                })
                .collect();
            let t = paired_excess_test(&pairs, margin).unwrap();
            rejected += usize::from(t.p_value <= alpha);
        }
        rejected as f64 / reps as f64
    };
    let null = rate(0.0);
    let sd = (alpha * (1.0 - alpha) / reps as f64).sqrt();
    assert!((null - alpha).abs() <= 3.0 * sd, "false-alarm rate {null}");
    let power = rate(0.05);
    assert!(power > 0.8, "power {power}");
    // Better than the reference by the margin: never failed.
    assert!(rate(-0.2) < 0.001);
}

#[test]
fn rmse_pairs_refuse_a_non_finite_rmse_of_a_run_that_did_not_fail() {
    let runs = |values: Vec<Option<f64>>, left_out: Vec<bool>| StateRuns {
        values: vec![values],
        left_out,
    };
    let theirs = runs(vec![Some(1.0), Some(1.0), Some(2.0)], vec![false; 3]);
    // A failed run (null RMSE) is left out; the others pair.
    let mine = runs(vec![Some(1.5), None, Some(2.5)], vec![false, true, false]);
    assert_eq!(
        rmse_pairs(&mine, &theirs, 0, "x", ("a", "b")),
        Ok(vec![(1.5, 1.0), (2.5, 2.0)])
    );
    // An infinite or NaN RMSE, or a null one of a run that did not fail, is no pair to
    // drop: the case cannot be judged.
    for bad in [Some(f64::INFINITY), Some(f64::NAN), None] {
        let mine = runs(vec![Some(1.5), bad, Some(2.5)], vec![false; 3]);
        let why = rmse_pairs(&mine, &theirs, 0, "x", ("a", "b")).unwrap_err();
        assert!(why.starts_with("run 1 is not a failure"), "{why}");
    }
}

fn counts(present: u64, failed: u64) -> RunCounts {
    RunCounts {
        present: vec![present],
        failed: vec![failed],
        first_failure: (failed > 0).then(|| (4, "non-finite estimate".into())),
        first_missing: None,
    }
}

#[test]
fn a_case_is_judged_only_on_the_declared_runs() {
    let cell = "basic noise=1 ekf q=1 r=1";
    assert_eq!(
        runs_problem(Some(&counts(10, 0)), 0, 10, 10, 0.0, cell),
        None
    );
    // Missing runs: named with their count, whatever the tolerance for failures.
    let why = runs_problem(Some(&counts(2, 0)), 0, 10, 10, 1.0, cell).unwrap();
    assert_eq!(
        why,
        "8 of the 10 runs of basic noise=1 ekf q=1 r=1 the spec declares are missing"
    );
    assert!(runs_problem(None, 0, 10, 10, 1.0, cell).is_some());
    // Failures: beyond the fraction of the declared runs, not within it (1/10 ≤ 0.1).
    let why = runs_problem(Some(&counts(10, 1)), 0, 10, 10, 0.0, cell).unwrap();
    assert!(
        why.starts_with("1 of the 10 runs of basic noise=1 ekf q=1 r=1 failed numerically")
            && why.ends_with("first: run 4: non-finite estimate"),
        "{why}"
    );
    assert_eq!(
        runs_problem(Some(&counts(10, 1)), 0, 10, 10, 0.1, cell),
        None
    );
    assert!(runs_problem(Some(&counts(10, 2)), 0, 10, 10, 0.1, cell).is_some());
    // A subset of more runs than the study ran (a --runs override) is not judged on fewer.
    let why = runs_problem(Some(&counts(10, 0)), 0, 50, 10, 0.0, cell).unwrap();
    assert!(why.starts_with("the study ran 10 runs per cell"), "{why}");
}

#[test]
fn incomplete_cases_are_counted_apart_and_never_pass() {
    let cases = vec![
        CaseResult::judged("consistent", "a".into(), true, String::new()),
        CaseResult::judged("consistent", "b".into(), false, String::new()),
        CaseResult::incomplete("consistent", "c".into(), "2 of 10 runs".into()),
    ];
    assert_eq!(tally(&cases), (1, 1));
    let text = render("kfmc", "x", &cases);
    assert!(
        text.starts_with("kfmc check x: 3 cases, 1 passed, 1 failed, 1 incomplete\n"),
        "{text}"
    );
    assert!(
        text.contains("INCOMPLETE  c  incomplete: 2 of 10 runs"),
        "{text}"
    );
    let xml = junit("kfmc", "x", &cases, 0.0);
    assert!(xml.contains("tests=\"3\" failures=\"2\""), "{xml}");
    assert!(
        xml.contains("<failure type=\"incomplete\" message=\"incomplete: 2 of 10 runs\">"),
        "{xml}"
    );
    // A negative control that could not be judged stays incomplete.
    let a = Assertion::TestPasses {
        kind: "consistent".into(),
        tests: vec![VERDICT.into()],
        select: Selection::default(),
        expect_fail: true,
    };
    let mut out = vec![CaseResult::incomplete(
        "consistent",
        "c".into(),
        "why".into(),
    )];
    settle(&a, "consistent", &mut out, 0);
    assert!(out[0].incomplete && !out[0].pass, "{:?}", out[0]);
}
