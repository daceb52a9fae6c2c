//! `[consistency] per_step_runs = true`: every run's NEES and NIS at every step in
//! `run_steps.parquet`, agreeing with the per-run means of runs.parquet and the per-step
//! averages of steps.parquet, which are computed apart from it.

use crate::common::{f64s, i64s, read, repo, run_cli as run, spec_in_tempdir, strs};
use std::collections::HashMap;

fn close(a: f64, b: f64) -> bool {
    (a - b).abs() <= 1e-12 * a.abs().max(b.abs()).max(1e-300)
}

#[test]
fn every_runs_nees_per_step_agrees_with_the_runs_and_steps_tables() {
    let base = std::fs::read_to_string(repo().join("experiments/ci_consistency.toml")).unwrap();
    let text = base
        .replace("runs = 100", "runs = 12")
        .replace(
            "whiteness_lags = 5",
            "whiteness_lags = 5\nper_step_runs = true",
        )
        .replace(
            "[noise]",
            "[[filters]]\nlabel = \"ukf\"\nkind = \"ukf\"\n\n[noise]",
        );
    let (_d, spec) = spec_in_tempdir(&text);
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("o");
    let (code, _, err) = run(&[
        "run",
        spec.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--quiet",
    ]);
    assert_eq!(code, 0, "{err}");

    let per_step = read(&out.join("run_steps.parquet"));
    let steps = read(&out.join("steps.parquet"));
    let runs = read(&out.join("runs.parquet"));
    // Two scenarios × two filters × 12 runs × every sample of the run.
    let samples = steps.height() / 4;
    assert_eq!(per_step.height(), 4 * 12 * samples);

    let (scenario, filter, run_col, step) = (
        strs(&per_step, "scenario"),
        strs(&per_step, "filter"),
        i64s(&per_step, "run"),
        i64s(&per_step, "step"),
    );
    let (nees, nis, dof) = (
        f64s(&per_step, "nees"),
        f64s(&per_step, "nis"),
        i64s(&per_step, "nis_dof"),
    );
    // Step 0 is the prior: no measurement, no NIS.
    for i in 0..per_step.height() {
        if step[i] == 0 {
            assert_eq!((nis[i], dof[i]), (None, 0));
        } else {
            assert!(
                nees[i].is_some() && nis[i].is_some() && dof[i] == 3,
                "row {i}"
            );
        }
    }

    // Per run: the mean over steps 1..K is runs.parquet's nees_mean (and nis_mean).
    let mut per_run: HashMap<(String, String, i64), (f64, f64, f64)> = HashMap::new();
    for i in 0..per_step.height() {
        let e = per_run
            .entry((scenario[i].clone(), filter[i].clone(), run_col[i]))
            .or_default();
        if step[i] > 0 {
            e.0 += nees[i].unwrap();
            e.1 += nis[i].unwrap();
            e.2 += 1.0;
        }
    }
    let (r_s, r_f, r_r, r_nees, r_nis) = (
        strs(&runs, "scenario"),
        strs(&runs, "filter"),
        i64s(&runs, "run"),
        f64s(&runs, "nees_mean"),
        f64s(&runs, "nis_mean"),
    );
    assert_eq!(per_run.len(), runs.height());
    for i in 0..runs.height() {
        let (sn, si, n) = per_run[&(r_s[i].clone(), r_f[i].clone(), r_r[i])];
        assert!(close(sn / n, r_nees[i].unwrap()), "nees of run row {i}");
        assert!(close(si / n, r_nis[i].unwrap()), "nis of run row {i}");
    }

    // Per step: the mean over runs is steps.parquet's ANEES.
    let mut per_k: HashMap<(String, String, i64), (f64, f64)> = HashMap::new();
    for i in 0..per_step.height() {
        let e = per_k
            .entry((scenario[i].clone(), filter[i].clone(), step[i]))
            .or_default();
        e.0 += nees[i].unwrap();
        e.1 += 1.0;
    }
    let (s_s, s_f, s_k, s_anees) = (
        strs(&steps, "scenario"),
        strs(&steps, "filter"),
        i64s(&steps, "step"),
        f64s(&steps, "anees"),
    );
    for i in 0..steps.height() {
        let (sum, n) = per_k[&(s_s[i].clone(), s_f[i].clone(), s_k[i])];
        assert!(
            close(sum / n, s_anees[i].unwrap()),
            "anees of steps row {i}"
        );
    }

    // Opt-in: without the key there is no such table.
    let plain = tmp.path().join("plain");
    let (_d2, spec2) = spec_in_tempdir(&base.replace("runs = 100", "runs = 3"));
    let (code, _, err) = run(&[
        "run",
        spec2.to_str().unwrap(),
        "--out",
        plain.to_str().unwrap(),
        "--quiet",
    ]);
    assert_eq!(code, 0, "{err}");
    assert!(!plain.join("run_steps.parquet").exists());
}
