//! Determinism and seeding: identical tables for any thread count; adding a
//! filter, a noise scale or a scenario leaves existing runs' numbers unchanged; all filters of
//! a run see the same truth and measurements; common random numbers across noise scales.

use std::path::Path;

use crate::common::{EKF_AND_MEAN, small_spec, spec_in_tempdir};
use kfmc::experiment;
use kfmc::output::table::read;
use kfmc::runner::NullObserver;
use kfmc::study::{ExecOptions, run};
use polars::prelude::*;

fn run_spec(text: &str, threads: usize) -> (tempfile::TempDir, std::path::PathBuf) {
    let (dir, spec) = spec_in_tempdir(text);
    let plan = experiment::load(&spec).expect("valid spec");
    run(
        &plan,
        &ExecOptions {
            threads,
            ..Default::default()
        },
        &NullObserver,
    )
    .expect("study runs");
    let out = plan.output.clone();
    (dir, out)
}

fn bytes(dir: &Path, table: &str) -> Vec<u8> {
    std::fs::read(dir.join(format!("{table}.parquet"))).expect("table exists")
}

/// Rows of `table` matching `filter`/`scenario`/`noise_scale`, as comparable text
/// (f64 values by their bit patterns).
fn rows(dir: &Path, table: &str, filter: &str, scenario: &str, scale: f64) -> Vec<String> {
    let df = read(&dir.join(format!("{table}.parquet"))).unwrap();
    let f = df.column("filter").unwrap().str().unwrap().clone();
    let s = df.column("scenario").unwrap().str().unwrap().clone();
    let n = df.column("noise_scale").unwrap().f64().unwrap().clone();
    (0..df.height())
        .filter(|&i| {
            f.get(i) == Some(filter) && s.get(i) == Some(scenario) && n.get(i) == Some(scale)
        })
        .map(|i| {
            df.columns()
                .iter()
                .filter(|c| c.name().as_str() != "filter")
                .map(|c| match c.dtype() {
                    DataType::Float64 => format!("{:?}", c.f64().unwrap().get(i).map(f64::to_bits)),
                    _ => format!("{:?}", c.get(i).unwrap()),
                })
                .collect::<Vec<_>>()
                .join("|")
        })
        .collect()
}

#[test]
fn tables_are_bit_identical_for_one_and_two_threads() {
    let tmp = tempfile::tempdir().unwrap();
    let spec = |out: &str| {
        small_spec(&tmp.path().join(out), 24, "[0.5, 1.0, 3.0]", EKF_AND_MEAN)
            .replace("runs = 24", "runs = 24\ntrace_runs = 2")
    };
    let (_a, one) = run_spec(&spec("t1"), 1);
    let (_b, two) = run_spec(&spec("t2"), 2);
    for table in [
        "runs",
        "steps",
        "summary",
        "divergence",
        "divergence_runs",
        "traces",
    ] {
        assert_eq!(
            bytes(&one, table),
            bytes(&two, table),
            "{table}.parquet differs"
        );
    }
}

#[test]
fn adding_a_filter_a_scale_or_a_scenario_leaves_existing_runs_unchanged() {
    let tmp = tempfile::tempdir().unwrap();
    let ekf_only = "[[filters]]\nlabel = \"ekf\"\nkind = \"ekf\"\n";
    let base = small_spec(&tmp.path().join("base"), 8, "[1.0]", ekf_only);
    let more = small_spec(
        &tmp.path().join("more"),
        8,
        "[0.5, 1.0, 2.0]",
        &format!(
            "{EKF_AND_MEAN}[[filters]]\nlabel = \"ekf_joseph\"\nkind = \"ekf\"\ncovariance_update = \"joseph\"\n"
        ),
    );
    // Scenario order swapped and one removed: streams depend on the name, not the position.
    let roll_only = small_spec(&tmp.path().join("roll"), 8, "[1.0]", ekf_only)
        .replace("[[scenarios]]\nname = \"basic\"\nduration_s = 2.0\n", "");
    let (_a, base) = run_spec(&base, 2);
    let (_b, more) = run_spec(&more, 2);
    let (_c, roll) = run_spec(&roll_only, 2);
    for table in ["runs", "steps", "summary"] {
        for scenario in ["basic", "roll"] {
            let a = rows(&base, table, "ekf", scenario, 1.0);
            assert!(!a.is_empty());
            assert_eq!(
                a,
                rows(&more, table, "ekf", scenario, 1.0),
                "{table} {scenario}"
            );
        }
        assert_eq!(
            rows(&base, table, "ekf", "roll", 1.0),
            rows(&roll, table, "ekf", "roll", 1.0),
            "{table}: removing a scenario changed another's runs"
        );
    }
}

#[test]
fn every_filter_of_a_run_sees_the_same_truth_and_measurements() {
    let tmp = tempfile::tempdir().unwrap();
    let spec = small_spec(&tmp.path().join("o"), 3, "[1.0, 4.0]", EKF_AND_MEAN)
        .replace("runs = 3", "runs = 3\ntrace_runs = 3");
    let (_d, out) = run_spec(&spec, 2);
    let df = read(&out.join("traces.parquet")).unwrap();
    let filter = df.column("filter").unwrap().str().unwrap().clone();
    let key = |i: usize| {
        ["scenario", "noise_scale", "run", "step"]
            .map(|c| format!("{:?}", df.column(c).unwrap().get(i).unwrap()))
            .join("|")
    };
    let cols: Vec<&str> = df
        .get_column_names()
        .into_iter()
        .map(|c| c.as_str())
        .filter(|c| c.starts_with("truth_") || c.starts_with("z_") || c.starts_with("u_"))
        .collect();
    assert_eq!(cols.len(), 6 + 3 + 2);
    let mut ekf = std::collections::HashMap::new();
    for i in 0..df.height() {
        let vals: Vec<Option<f64>> = cols
            .iter()
            .map(|c| df.column(c).unwrap().f64().unwrap().get(i))
            .collect();
        if filter.get(i) == Some("ekf") {
            ekf.insert(key(i), vals);
        }
    }
    let mut compared = 0;
    for i in 0..df.height() {
        if filter.get(i) == Some("running_mean") {
            let vals: Vec<Option<f64>> = cols
                .iter()
                .map(|c| df.column(c).unwrap().f64().unwrap().get(i))
                .collect();
            assert_eq!(ekf[&key(i)], vals);
            compared += 1;
        }
    }
    assert_eq!(compared, 2 * 2 * 3 * 201);
}

#[test]
fn runs_share_their_seed_across_noise_scales() {
    let tmp = tempfile::tempdir().unwrap();
    let (_d, out) = run_spec(
        &small_spec(&tmp.path().join("o"), 4, "[1.0, 2.0]", EKF_AND_MEAN),
        2,
    );
    let df = read(&out.join("runs.parquet")).unwrap();
    let seeds = df.column("seed").unwrap().u64().unwrap().clone();
    let scale = df.column("noise_scale").unwrap().f64().unwrap().clone();
    let run = df.column("run").unwrap().i64().unwrap().clone();
    let scen = df.column("scenario").unwrap().str().unwrap().clone();
    for i in 0..df.height() {
        for j in 0..df.height() {
            if run.get(i) == run.get(j) && scen.get(i) == scen.get(j) {
                assert_eq!(
                    seeds.get(i),
                    seeds.get(j),
                    "scales {:?} {:?}",
                    scale.get(i),
                    scale.get(j)
                );
            } else if scen.get(i) == scen.get(j) {
                assert_ne!(seeds.get(i), seeds.get(j));
            }
        }
    }
}
