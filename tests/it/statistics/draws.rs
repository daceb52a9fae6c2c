//! `[noise] draws`: common random numbers (the default) against robustness.m's fresh noise at
//! every multiplier, and `divergence.never_crossed`.
//!
//! * Common: a run has one seed at every multiplier; fresh: every (run, multiplier) its own.
//! * Fresh draws make a run's first crossing the first of many independent chances, so on the
//!   basic scenario the EKF's x crosses earlier and its crossings spread less than with common
//!   numbers (30 runs, multipliers 0.2..30, master seed 47).
//! * `never_crossed = "largest_scale"` records the largest multiplier, flagged, as
//!   robustness.m's max_tested does.

use std::path::Path;

use crate::common::{kfmc, read, spec_in_tempdir};
use polars::prelude::*;

fn spec(draws: &str, never: &str) -> String {
    format!(
        r#"
name = "draws"
master_seed = 47
runs = 30
[model]
kind = "planar_quadrotor"
sensor = "p1"
process_noise_std = 0.003
measurement_noise_std = 0.01
[[scenarios]]
name = "basic"
[[filters]]
label = "ekf"
kind = "ekf"
q_std = 0.003
r_std = 0.01
[noise]
scales = {{ start = 0.2, stop = 30.0, step = 0.2 }}
draws = "{draws}"
[initial_estimate]
mode = "truth"
[divergence]
rmse_thresholds = [5.0, 1.0, 0.2, 0.2, 0.2, 0.1]
never_crossed = "{never}"
"#
    )
}

fn study(draws: &str, never: &str) -> (tempfile::TempDir, std::path::PathBuf) {
    let (dir, path) = spec_in_tempdir(&spec(draws, never));
    let out = dir.path().join("out");
    let o = kfmc()
        .args(["run", "-q", "--out"])
        .arg(&out)
        .arg(&path)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    (dir, out)
}

fn seeds_of_run_0(out: &Path) -> Vec<u64> {
    let runs = read(&out.join("runs.parquet"));
    let m = runs.column("run").unwrap().i64().unwrap().equal(0);
    let r = runs.filter(&m).unwrap();
    r.column("seed")
        .unwrap()
        .u64()
        .unwrap()
        .into_no_null_iter()
        .collect()
}

fn x_crossings(out: &Path) -> (Vec<Option<f64>>, Vec<bool>) {
    let d = read(&out.join("divergence_runs.parquet"));
    let m = d.column("state").unwrap().str().unwrap().equal("x");
    let x = d.filter(&m).unwrap();
    (
        x.column("divergence_scale")
            .unwrap()
            .f64()
            .unwrap()
            .iter()
            .collect(),
        x.column("never_crossed")
            .unwrap()
            .bool()
            .unwrap()
            .iter()
            .map(|b| b.expect("never_crossed is never null"))
            .collect(),
    )
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

#[test]
fn fresh_draws_give_every_multiplier_its_own_noise_and_earlier_crossings() {
    let (_a, common) = study("common", "null");
    let (_b, fresh) = study("fresh", "null");
    let c = seeds_of_run_0(&common);
    let f = seeds_of_run_0(&fresh);
    assert_eq!(c.len(), 150);
    assert!(c.iter().all(|s| *s == c[0]), "common: one seed per run");
    let mut distinct = f.clone();
    distinct.sort_unstable();
    distinct.dedup();
    assert_eq!(
        distinct.len(),
        f.len(),
        "fresh: a seed per (run, multiplier)"
    );

    // Runs that never cross are censored beyond 30: +∞ for the median.
    let never = |v: Vec<Option<f64>>| v.into_iter().map(|x| x.unwrap_or(f64::INFINITY)).collect();
    let (cx, cn) = x_crossings(&common);
    let (fx, fnv) = x_crossings(&fresh);
    let (mc, mf) = (median(never(cx.clone())), median(never(fx.clone())));
    assert!(mf < mc, "fresh median {mf} should come before common {mc}");
    // The flag says which runs are censored.
    assert!(cx.iter().zip(&cn).all(|(x, n)| x.is_none() == *n));
    assert!(fx.iter().zip(&fnv).all(|(x, n)| x.is_none() == *n));
}

#[test]
fn never_crossed_can_record_the_largest_multiplier() {
    let (_a, out) = study("common", "largest_scale");
    let d = read(&out.join("divergence_runs.parquet"));
    let never = d.column("never_crossed").unwrap().bool().unwrap();
    let scale = d.column("divergence_scale").unwrap().f64().unwrap();
    let mut flagged = 0;
    for i in 0..d.height() {
        if never.get(i) == Some(true) {
            flagged += 1;
            assert_eq!(scale.get(i), Some(30.0), "row {i}");
        } else {
            assert!(scale.get(i).is_some_and(|s| s <= 30.0));
        }
    }
    // θ̇ (threshold 0.1 rad/s, measured) never crosses in this grid for any run.
    assert!(flagged >= 30, "{flagged} never-crossed rows");
}
