//! Statistical facts about the planar study, with fixed seeds and stated tolerances.

use crate::common::{repo, spec_in_tempdir};
use kfmc::experiment::{self, Overrides};
use kfmc::output::table::read;
use kfmc::runner::NullObserver;
use kfmc::study::{ExecOptions, run};

/// Table 1 of seed 001 (horizontal scenario, one MATLAB run with rng(47)):
/// EKF and running-mean RMSE per state.
const TABLE1_EKF: [f64; 6] = [0.0417, 0.0222, 0.0084, 0.0659, 0.0084, 0.0083];
const TABLE1_RM: [f64; 6] = [0.6632, 0.1866, 0.5453, 0.1902, 0.0100, 0.0095];
const STATES: [&str; 6] = ["x", "xdot", "y", "ydot", "theta", "thetadot"];

fn mean_rmse(dir: &std::path::Path, filter: &str, scenario: &str) -> Vec<f64> {
    let df = read(&dir.join("summary.parquet")).unwrap();
    let f = df.column("filter").unwrap().str().unwrap().clone();
    let s = df.column("scenario").unwrap().str().unwrap().clone();
    let st = df.column("state").unwrap().str().unwrap().clone();
    let m = df.column("rmse_mean").unwrap().f64().unwrap().clone();
    STATES
        .iter()
        .map(|state| {
            (0..df.height())
                .find(|&i| {
                    f.get(i) == Some(filter)
                        && s.get(i) == Some(scenario)
                        && st.get(i) == Some(state)
                })
                .and_then(|i| m.get(i))
                .expect("row")
        })
        .collect()
}

#[test]
fn monte_carlo_means_match_the_orders_of_magnitude_of_table_1() {
    let tmp = tempfile::tempdir().unwrap();
    let mut plan = experiment::load(&repo().join("experiments/planar_seed_study.toml")).unwrap();
    plan.apply(&Overrides {
        runs: Some(200),
        output: Some(tmp.path().to_path_buf()),
        trace_runs: Some(0),
        ..Default::default()
    })
    .unwrap();
    plan.retain_scenarios(|s| s == "horizontal");
    run(
        &plan,
        &ExecOptions {
            threads: 0,
            ..Default::default()
        },
        &NullObserver,
    )
    .unwrap();
    let ekf = mean_rmse(tmp.path(), "ekf", "horizontal");
    let rm = mean_rmse(tmp.path(), "running_mean", "horizontal");
    for i in 0..6 {
        // Same order of magnitude: within a factor of 10 either way.
        for (got, want, who) in [
            (ekf[i], TABLE1_EKF[i], "ekf"),
            (rm[i], TABLE1_RM[i], "running_mean"),
        ] {
            let r = (got / want).log10().abs();
            assert!(
                r < 1.0,
                "{who} rmse_{}: {got:.4} vs Table 1 {want}",
                STATES[i]
            );
        }
        // The seeds' conclusion: the EKF beats the running mean on every state.
        assert!(
            ekf[i] < rm[i],
            "rmse_{}: ekf {} ≥ running mean {}",
            STATES[i],
            ekf[i],
            rm[i]
        );
    }
    // Directly measured states: the EKF's RMSE lies below the sensor's σ = 0.01.
    for i in [2, 4, 5] {
        assert!(ekf[i] < 0.01, "rmse_{}", STATES[i]);
    }
}

#[test]
fn a_correctly_tuned_ekf_is_consistent_on_average() {
    // Matched noise and a sampled initial error: the time-and-run average NEES must lie
    // within a loose band around n = 6 (the full χ² verdict is a separate feature).
    let tmp = tempfile::tempdir().unwrap();
    let text = format!(
        r#"
master_seed = 5
runs = 100
output = "{}"
[model]
kind = "planar_quadrotor"
[[scenarios]]
name = "basic"
duration_s = 3.0
[[filters]]
label = "ekf"
kind = "ekf"
[noise]
scales = [1.0]
filter_noise = "matched"
[initial_estimate]
mode = "sampled"
p0_std = 0.01
"#,
        tmp.path().display()
    );
    let (_d, spec) = spec_in_tempdir(&text);
    let plan = experiment::load(&spec).unwrap();
    run(
        &plan,
        &ExecOptions {
            threads: 0,
            ..Default::default()
        },
        &NullObserver,
    )
    .unwrap();
    let df = read(&tmp.path().join("runs.parquet")).unwrap();
    let nees: Vec<f64> = df
        .column("nees_mean")
        .unwrap()
        .f64()
        .unwrap()
        .iter()
        .flatten()
        .collect();
    let nis: Vec<f64> = df
        .column("nis_mean")
        .unwrap()
        .f64()
        .unwrap()
        .iter()
        .flatten()
        .collect();
    assert_eq!(nees.len(), 100);
    let m = nees.iter().sum::<f64>() / 100.0;
    let p = nis.iter().sum::<f64>() / 100.0;
    // 100 runs × 300 steps: the standard error of the mean NEES is far below 0.3 even with
    // strong time correlation; a tuned EKF on this mildly nonlinear model sits near 6 and 3.
    assert!((m - 6.0).abs() < 0.6, "mean NEES {m}");
    assert!((p - 3.0).abs() < 0.2, "mean NIS {p}");
}

#[test]
fn numerical_trouble_is_recorded_per_run_and_never_aborts_the_batch() {
    // A custom scenario whose thrusts sum to +∞ makes the truth, the measurements and every
    // filter non-finite at step 1. Its runs must be recorded as numerical failures with their
    // step while the other scenario's runs in the same batch are unaffected.
    let tmp = tempfile::tempdir().unwrap();
    let text = crate::common::small_spec(tmp.path(), 3, "[1.0, 2.0]", crate::common::EKF_AND_MEAN).replace(
        "[[scenarios]]\nname = \"roll\"\nduration_s = 2.0\n",
        "[[scenarios]]\nname = \"blowup\"\nx0 = [0, 0, 1, 0, 0, 0]\nduration_s = 2.0\nstages = [{ from_step = 0, thrust_n = [1e308, 1e308] }]\n",
    );
    let (_d, spec) = spec_in_tempdir(&text);
    let plan = experiment::load(&spec).unwrap();
    run(
        &plan,
        &ExecOptions {
            threads: 2,
            ..Default::default()
        },
        &NullObserver,
    )
    .unwrap();
    let df = read(&tmp.path().join("runs.parquet")).unwrap();
    let status = df.column("status").unwrap().str().unwrap().clone();
    let scenario = df.column("scenario").unwrap().str().unwrap().clone();
    let step = df.column("status_step").unwrap().i64().unwrap().clone();
    let detail = df.column("status_detail").unwrap().str().unwrap().clone();
    let rmse = df.column("rmse_x").unwrap().f64().unwrap().clone();
    assert_eq!(df.height(), 2 * 2 * 3 * 2);
    for i in 0..df.height() {
        if scenario.get(i) == Some("blowup") {
            assert_eq!(status.get(i), Some("numerical_failure"));
            assert_eq!(step.get(i), Some(1));
            assert!(
                detail.get(i).unwrap().contains("non-finite"),
                "{:?}",
                detail.get(i)
            );
            assert_eq!(rmse.get(i), None);
        } else {
            assert_ne!(status.get(i), Some("numerical_failure"));
            assert!(rmse.get(i).is_some_and(f64::is_finite));
        }
    }
    let summary = read(&tmp.path().join("summary.parquet")).unwrap();
    let failed: i64 = summary
        .column("runs_failed")
        .unwrap()
        .i64()
        .unwrap()
        .iter()
        .flatten()
        .sum();
    // blowup: 2 scales × 2 filters × 6 states rows, each counting 3 failed runs.
    assert_eq!(failed, 2 * 2 * 6 * 3);
    // The steps table keeps step 0 (before the failure) and drops the failed runs after it.
    let steps = read(&tmp.path().join("steps.parquet")).unwrap();
    let sc = steps.column("scenario").unwrap().str().unwrap().clone();
    let st = steps.column("step").unwrap().i64().unwrap().clone();
    let n = steps.column("runs").unwrap().i64().unwrap().clone();
    for i in 0..steps.height() {
        if sc.get(i) == Some("blowup") {
            assert_eq!(n.get(i), Some(if st.get(i) == Some(0) { 3 } else { 0 }));
        }
    }
}
