//! No test passes on data it cannot judge, through `kfmc check`:
//!
//! * kfmc's KF with no noise and the prior at the truth (every NEES exactly 0 where 6 is
//!   expected) is rejected by `nees_run_average_t`, and its bias tests (every normalised
//!   error 0, μ = 0: 0/0) are incomplete;
//! * an outside filter biased by 1e20 on x (run-to-run differences below one ulp) fails
//!   `unbiased` and the model-free NEES test;
//! * a run at 1e160 (its squared error overflows) is a numerical failure, so the case is
//!   incomplete unless `check.max_failed_runs` allows it;
//! * runs the estimates leave out are missing: incomplete whatever `max_failed_runs` says,
//!   and `kfmc score` warns; only runs marked in the `failed` column count as failures;
//! * estimates without innovations are "not judged: no innovations", never left out.

use std::fs;
use std::path::{Path, PathBuf};

use crate::common::{kfmc, ok, read, stamp_of, write_with};
use polars::prelude::*;

const SPEC: &str = r#"
name = "unjudged"
master_seed = 5
runs = 30
[model]
kind = "linear_quadrotor"
sensor = "positions"
[[scenarios]]
name = "hover"
x0 = [1.0, 0.0, 1.0, 0.0, 1.0, 0.0]
duration_s = 2.0
[[filters]]
label = "mine"
kind = "KIND"
[initial_estimate]
mode = "sampled"
p0_std = 1.0
[consistency]
alpha = 0.05
"#;

/// Checks of the filter `mine` as an outside filter, on kfmc's own KF's exported estimates.
const ASSERTS: &str = r#"
[[check.assert]]
kind = "consistent"
filter = "mine"
[[check.assert]]
kind = "unbiased"
filter = "mine"
[[check.assert]]
kind = "test_passes"
filter = "mine"
test = "nees_run_average_t"
"#;

struct Exported {
    _tmp: tempfile::TempDir,
    dir: PathBuf,
    /// kfmc's KF's estimates, labelled `mine`.
    good: DataFrame,
    stamp: Vec<(String, String)>,
}

/// kfmc's KF on the spec's runs, its estimates exported (the label is `mine` already).
fn exported() -> Exported {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().to_path_buf();
    let spec = dir.join("own.toml");
    fs::write(&spec, SPEC.replace("KIND", "ekf")).unwrap();
    ok(kfmc()
        .args(["run", "-q", "--export-estimates", "--out"])
        .arg(dir.join("own"))
        .arg(&spec));
    let path = dir.join("own/estimates.parquet");
    Exported {
        good: read(&path),
        stamp: stamp_of(&path),
        _tmp: tmp,
        dir,
    }
}

/// `kfmc check` of the outside filter `mine` on `df` (written with the world's stamp), with
/// `extra` in `[check]`: (exit code, report, stderr, the output folder).
fn check(e: &Exported, name: &str, df: &DataFrame, extra: &str) -> (i32, String, String, PathBuf) {
    let file = e.dir.join(format!("{name}.parquet"));
    write_with(df, &file, &e.stamp);
    let spec = e.dir.join(format!("{name}.toml"));
    fs::write(
        &spec,
        SPEC.replace("KIND", "external") + "[check]\n" + extra + "\n" + ASSERTS,
    )
    .unwrap();
    let out = e.dir.join(name);
    let o = kfmc()
        .args(["check", "-q", "--out"])
        .arg(&out)
        .arg(&spec)
        .arg("--estimates")
        .arg(&file)
        .output()
        .unwrap();
    (
        o.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&o.stdout).into_owned(),
        String::from_utf8_lossy(&o.stderr).into_owned(),
        out,
    )
}

/// `df` with column `c` replaced by `f(run, step, value)`.
fn edit(df: &DataFrame, c: &str, f: impl Fn(i64, i64, f64) -> f64) -> DataFrame {
    let ints = |n: &str| df.column(n).unwrap().i64().unwrap().clone();
    let (run, step) = (ints("run"), ints("step"));
    let old = df.column(c).unwrap().f64().unwrap().clone();
    let new: Vec<Option<f64>> = (0..df.height())
        .map(|i| {
            old.get(i)
                .map(|v| f(run.get(i).unwrap(), step.get(i).unwrap(), v))
        })
        .collect();
    let mut out = df.clone();
    out.with_column(Column::new(c.into(), new)).unwrap();
    out
}

/// The (status, status_step, status_detail) of run `r` of `mine` in `runs.parquet`.
fn status(folder: &Path, r: i64) -> (String, Option<i64>, String) {
    let runs = read(&folder.join("runs.parquet"));
    let m = runs.column("filter").unwrap().str().unwrap().equal("mine")
        & runs.column("run").unwrap().i64().unwrap().equal(r);
    let row = runs.filter(&m).unwrap();
    let s = |c: &str| {
        row.column(c)
            .unwrap()
            .str()
            .unwrap()
            .get(0)
            .unwrap()
            .to_string()
    };
    (
        s("status"),
        row.column("status_step").unwrap().i64().unwrap().get(0),
        s("status_detail"),
    )
}

/// The report's line of the case whose name contains `case`.
fn line<'a>(report: &'a str, case: &str) -> &'a str {
    report
        .lines()
        .find(|l| l.starts_with("  ") && l.contains(case))
        .unwrap_or_else(|| panic!("no case {case} in {report}"))
}

#[test]
fn a_kf_without_noise_from_the_true_prior_is_rejected_or_incomplete_never_passed() {
    let tmp = tempfile::tempdir().unwrap();
    let spec = tmp.path().join("zero.toml");
    let text = SPEC
        .replace("KIND", "ekf")
        .replace("mode = \"sampled\"", "mode = \"truth\"")
        + "[noise]\nscales = [0.0]\n"
        + ASSERTS;
    fs::write(&spec, text).unwrap();
    let o = kfmc()
        .args(["check", "-q", "--out"])
        .arg(tmp.path().join("out"))
        .arg(&spec)
        .output()
        .unwrap();
    let report = String::from_utf8_lossy(&o.stdout);
    assert_eq!(o.status.code(), Some(3), "{report}");
    // Every NEES is exactly 0 where 6 is expected: no spread, far from μ, a rejection.
    let t = line(&report, "test_passes[hover noise=0 mine");
    assert!(
        t.starts_with("  FAIL")
            && t.contains("nees_run_average_t = -inf")
            && t.contains("pessimistic"),
        "{t}"
    );
    // Every normalised error is exactly 0 and μ = 0: 0/0, not a pass.
    let b = line(&report, "unbiased[hover noise=0 mine q=1 r=1 bias_x]");
    assert!(
        b.contains("INCOMPLETE") && b.contains("could not be computed"),
        "{b}"
    );
    assert!(!report.contains("PASS"), "{report}");
}

#[test]
fn an_outside_filter_biased_by_1e20_fails_unbiased_and_the_model_free_test() {
    let e = exported();
    let biased = edit(&e.good, "est_x", |_, _, v| v + 1e20);
    let (code, report, err, _) = check(&e, "bias", &biased, "");
    assert_eq!(code, 3, "{report}{err}");
    let b = line(&report, "unbiased[hover noise=1 mine bias_x]");
    assert!(
        b.starts_with("  FAIL") && b.contains("bias_x = -inf"),
        "{b}"
    );
    let t = line(
        &report,
        "test_passes[hover noise=1 mine nees_run_average_t]",
    );
    assert!(t.starts_with("  FAIL") && t.contains("= inf"), "{t}");
    // The unbiased states still pass: the rejection is the biased one's alone.
    assert!(
        line(&report, "unbiased[hover noise=1 mine bias_y]").starts_with("  PASS"),
        "{report}"
    );
}

#[test]
fn a_run_whose_squared_error_overflows_is_a_numerical_failure() {
    let e = exported();
    let huge = edit(&e.good, "est_x", |r, _, v| if r == 3 { 1e160 } else { v });
    let (code, report, err, out) = check(&e, "huge", &huge, "");
    assert_eq!(code, 4, "{report}{err}");
    let (s, step, detail) = status(&out, 3);
    assert_eq!(
        (s.as_str(), step),
        ("numerical_failure", Some(0)),
        "{detail}"
    );
    assert!(detail.contains("squares to a non-finite value"), "{detail}");
    assert!(
        line(&report, "consistent[hover noise=1 mine]")
            .contains("1 of the 30 runs of hover noise=1 mine failed numerically"),
        "{report}"
    );
    // Within the tolerance the cases are judged on the other 29 runs.
    let (code, report, err, _) = check(&e, "huge_ok", &huge, "max_failed_runs = 0.05");
    assert!(matches!(code, 0 | 3), "{report}{err}");
    assert!(!report.contains("INCOMPLETE"), "{report}");
}

#[test]
fn missing_runs_are_incomplete_whatever_max_failed_runs_allows_and_score_warns() {
    let e = exported();
    let run = e.good.column("run").unwrap().i64().unwrap().clone();
    let keep: BooleanChunked = run.iter().map(|r| !matches!(r, Some(4 | 9))).collect();
    let left_out = e.good.filter(&keep).unwrap();
    let (code, report, err, out) = check(&e, "missing", &left_out, "max_failed_runs = 0.5");
    assert_eq!(code, 4, "{report}{err}");
    let c = line(&report, "consistent[hover noise=1 mine]");
    assert!(
        c.contains("2 of the 30 runs of hover noise=1 mine the spec declares are missing")
            && c.contains("first: run 4"),
        "{c}"
    );
    assert!(err.contains("leave 2 of its 30 runs out"), "{err}");
    assert_eq!(status(&out, 9).0, "missing");
    // Neither completed nor failed in the summary.
    let summary = read(&out.join("summary.parquet"));
    let mine = summary
        .filter(
            &summary
                .column("filter")
                .unwrap()
                .str()
                .unwrap()
                .equal("mine"),
        )
        .unwrap();
    let ints = |c: &str| -> Vec<i64> {
        mine.column(c)
            .unwrap()
            .i64()
            .unwrap()
            .iter()
            .flatten()
            .collect()
    };
    assert!(ints("runs").iter().all(|&n| n == 28), "{mine}");
    assert!(ints("runs_failed").iter().all(|&n| n == 0), "{mine}");
    // `kfmc score` scores the rest and says which runs are missing.
    let sim_spec = e.dir.join("missing.toml");
    ok(kfmc()
        .args(["simulate", "-q", "--out"])
        .arg(e.dir.join("sim"))
        .arg(&sim_spec));
    let o = kfmc()
        .args(["score", "-q", "--out"])
        .arg(e.dir.join("scored"))
        .arg(e.dir.join("sim"))
        .arg("--estimates")
        .arg(e.dir.join("missing.parquet"))
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert!(
        err.contains("warning: the estimates of `mine` leave 2 of its 30 runs out; first: scenario hover, noise scale 1, run 4"),
        "{err}"
    );
}

#[test]
fn only_runs_marked_failed_count_against_max_failed_runs() {
    let e = exported();
    let ints = |c: &str| e.good.column(c).unwrap().i64().unwrap().clone();
    let (run, step) = (ints("run"), ints("step"));
    let failed: BooleanChunked = run
        .iter()
        .zip(step.iter())
        .map(|(r, k)| r == Some(5) && k >= Some(7))
        .collect();
    let mut marked = e.good.clone();
    marked
        .with_column(Column::new("failed".into(), failed.into_series()))
        .unwrap();
    let (code, report, err, out) = check(&e, "marked", &marked, "");
    assert_eq!(code, 4, "{report}{err}");
    assert_eq!(
        status(&out, 5),
        (
            "numerical_failure".into(),
            Some(7),
            "estimates: the filter failed at step 7 (`failed` = true)".into()
        )
    );
    assert!(
        line(&report, "consistent[hover noise=1 mine]").contains("failed numerically"),
        "{report}"
    );
    let (code, report, err, _) = check(&e, "marked_ok", &marked, "max_failed_runs = 0.05");
    assert!(matches!(code, 0 | 3), "{report}{err}");
    // A `failed` column of another type is refused, naming it.
    let mut bad = e.good.clone();
    bad.with_column(Column::new("failed".into(), vec![0.0f64; e.good.height()]))
        .unwrap();
    let (code, _, err, _) = check(&e, "bad_failed", &bad, "");
    assert_eq!(code, 1, "{err}");
    assert!(
        err.contains("column `failed` holds float64 values; it must be a bool column"),
        "{err}"
    );
}

#[test]
fn estimates_without_innovations_are_not_judged_rather_than_left_out() {
    let e = exported();
    let keep: Vec<PlSmallStr> = e
        .good
        .get_column_names()
        .into_iter()
        .filter(|c| !c.starts_with("nu_") && !c.starts_with("S_"))
        .cloned()
        .collect();
    let no_innovations = e.good.select(keep).unwrap();
    let (code, report, err, _) = check(&e, "no_nu", &no_innovations, "");
    assert_eq!(code, 4, "{report}{err}");
    let c = line(&report, "consistent[hover noise=1 mine]");
    assert!(
        c.contains("INCOMPLETE") && c.contains("not judged: no innovations"),
        "{c}"
    );
}
