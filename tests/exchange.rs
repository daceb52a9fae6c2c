//! The estimates exchange: `kfmc simulate` → an estimator outside kfmc → `kfmc score` /
//! `kfmc check --estimates`.
//!
//! * kfmc's own KF exported with `--export-estimates` and scored as an external filter gives
//!   the run's tables byte for byte (runs, steps, summary, divergence); the consistency table
//!   agrees to 1e-12 relative, because the exchange carries P's lower triangle only and the
//!   seeds' P = (I − KH)P⁻ is not exactly symmetric (ρ's recursion sees the difference).
//!   The UKF and CKF (kfmc's sigma-point filters, with S and their statistical-linearisation
//!   A_k) round-trip the same way on L1.
//! * Bad files are refused naming the file, the column and the first offending key; trouble in
//!   a row becomes that run's status and the batch completes.
//! * FilterPy's KalmanFilter (examples/python/filterpy_estimates.py) equals kfmc's KF, and a
//!   negative control proves the gate rejects it mistuned (Q × 4). The Python packages are
//!   installed by `.ci/run`, which sets KFMC_REQUIRE_INTEROP=1; elsewhere the test skips.

mod common;

use std::fs;
use std::path::{Path, PathBuf};

use common::{kfmc, read, repo};
use polars::prelude::*;

const RUN_SPEC: &str = r#"
name = "exchange"
master_seed = 7
runs = 12
[model]
kind = "linear_quadrotor"
sensor = "positions"
[[scenarios]]
name = "hover"
x0 = [1.0, 0.0, 1.0, 0.0, 1.0, 0.0]
duration_s = 5.0
[[scenarios]]
name = "drift"
x0 = [0.0, 0.5, 0.0, -0.5, 2.0, 0.0]
duration_s = 3.0
[noise]
scales = [1.0, 3.0]
[[filters]]
label = "kf"
kind = "KIND"
[[filters]]
label = "sqrt"
kind = "sqrt"
[initial_estimate]
mode = "sampled"
p0_std = 1.0
[consistency]
alpha = 0.05
[divergence]
rmse_thresholds = [0.5, 0.5, 0.5, 0.5, 0.5, 0.5]
"#;

struct Study {
    _tmp: tempfile::TempDir,
    dir: PathBuf,
    ext_spec: PathBuf,
}

fn ok(cmd: &mut std::process::Command) -> std::process::Output {
    let o = cmd.output().unwrap();
    assert!(
        o.status.success(),
        "{:?} failed: {}",
        cmd,
        String::from_utf8_lossy(&o.stderr)
    );
    o
}

/// Runs kfmc's KF with its estimates exported, keeps the KF's rows as an external filter's
/// file, and simulates the spec in which `kf` is external.
fn study() -> Study {
    study_of("ekf")
}

/// [`study`] with the `kf` entry of another kind.
fn study_of(kind: &str) -> Study {
    study_runs(kind, 12)
}

/// [`study_of`] with `runs` runs per cell.
fn study_runs(kind: &str, runs: usize) -> Study {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().to_path_buf();
    let run_spec = dir.join("run.toml");
    let ext_spec = dir.join("ext.toml");
    let spec = RUN_SPEC.replace("runs = 12", &format!("runs = {runs}"));
    fs::write(&run_spec, spec.replace("KIND", kind)).unwrap();
    fs::write(&ext_spec, spec.replace("KIND", "external")).unwrap();
    ok(kfmc()
        .args(["run", "-q", "--export-estimates", "--out"])
        .arg(dir.join("run"))
        .arg(&run_spec));
    let all = read(&dir.join("run/estimates.parquet"));
    let kf = all
        .filter(&all.column("filter").unwrap().str().unwrap().equal("kf"))
        .unwrap();
    write(&kf, &dir.join("kf.parquet"));
    ok(kfmc()
        .args(["simulate", "-q", "--out"])
        .arg(dir.join("sim"))
        .arg(&ext_spec));
    Study {
        _tmp: tmp,
        dir,
        ext_spec,
    }
}

fn write(df: &DataFrame, path: &Path) {
    let mut df = df.clone();
    ParquetWriter::new(fs::File::create(path).unwrap())
        .finish(&mut df)
        .unwrap();
}

fn score(s: &Study, files: &[&Path], out: &str) -> std::process::Output {
    let mut c = kfmc();
    c.args(["score", "-q"])
        .arg(s.dir.join("sim"))
        .arg("--out")
        .arg(s.dir.join(out))
        .arg("--estimates")
        .args(files);
    c.output().unwrap()
}

/// Scores the exported `kf` rows and checks that the tables equal the run's.
fn scored_equals_run(s: &Study) {
    let o = score(s, &[&s.dir.join("kf.parquet")], "score");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    for t in ["runs", "steps", "summary", "divergence", "divergence_runs"] {
        let (a, b) = (
            read(&s.dir.join(format!("run/{t}.parquet"))),
            read(&s.dir.join(format!("score/{t}.parquet"))),
        );
        // An external filter carries no multipliers: its q_scale and r_scale are null, kfmc's
        // own filter's are 1; every other column is the run's.
        let filter = b.column("filter").unwrap().str().unwrap().clone();
        for c in ["q_scale", "r_scale"] {
            let v = b.column(c).unwrap().f64().unwrap().clone();
            for (f, v) in filter.iter().zip(v.iter()) {
                match f {
                    Some("kf") => assert_eq!(v, None, "{t}.{c} of the external kf"),
                    _ => assert_eq!(v, Some(1.0), "{t}.{c} of {f:?}"),
                }
            }
        }
        let (a, b) = (
            a.drop_many(["q_scale", "r_scale"]),
            b.drop_many(["q_scale", "r_scale"]),
        );
        assert!(
            a.equals_missing(&b),
            "{t}.parquet differs between run and score"
        );
    }
    let (a, b) = (
        read(&s.dir.join("run/consistency.parquet")),
        read(&s.dir.join("score/consistency.parquet")),
    );
    assert_eq!(a.shape(), b.shape());
    let mut worst = 0.0f64;
    for c in ["statistic", "lower", "upper", "dof", "p_value"] {
        let (x, y) = (
            a.column(c).unwrap().f64().unwrap(),
            b.column(c).unwrap().f64().unwrap(),
        );
        for (p, q) in x.iter().zip(y.iter()) {
            match (p, q) {
                (Some(p), Some(q)) => worst = worst.max((p - q).abs() / p.abs().max(1e-300)),
                (None, None) => {}
                other => panic!("{c}: {other:?}"),
            }
        }
    }
    assert!(worst < 1e-12, "consistency differs by {worst:e} (relative)");
    for c in ["test", "pass", "direction"] {
        assert!(
            a.column(c).unwrap().equals_missing(b.column(c).unwrap()),
            "{c} differs"
        );
    }
}

#[test]
fn exported_kf_scored_as_external_gives_the_run_tables() {
    let s = study();
    scored_equals_run(&s);
    let truth = read(&s.dir.join("sim/truth.parquet"));
    assert_eq!(truth.height(), 12 * 2 * (51 + 31));

    // Scoring does not depend on the thread count either.
    for threads in ["1", "2"] {
        let mut c = kfmc();
        c.args(["score", "-q", "--threads", threads])
            .arg(s.dir.join("sim"))
            .arg("--out")
            .arg(s.dir.join(format!("score_t{threads}")))
            .arg("--estimates")
            .arg(s.dir.join("kf.parquet"));
        ok(&mut c);
    }
    for t in ["runs", "steps", "summary", "consistency", "divergence_runs"] {
        let a = fs::read(s.dir.join(format!("score_t1/{t}.parquet"))).unwrap();
        let b = fs::read(s.dir.join(format!("score_t2/{t}.parquet"))).unwrap();
        assert!(
            a == b,
            "{t}.parquet of score differs between 1 and 2 threads"
        );
    }

    // A sharded simulation merges into the single process's tables, byte for byte, and
    // scores like it (4 cells in 3 parts).
    let sharded = s.dir.join("sharded");
    for i in 0..3 {
        ok(kfmc()
            .args(["simulate", "-q", "--shard", &format!("{i}/3"), "--out"])
            .arg(&sharded)
            .arg(&s.ext_spec));
    }
    ok(kfmc().arg("merge").arg(&sharded));
    for t in ["truth", "measurements", "initial"] {
        let a = fs::read(s.dir.join(format!("sim/{t}.parquet"))).unwrap();
        let b = fs::read(sharded.join(format!("{t}.parquet"))).unwrap();
        assert!(a == b, "{t}.parquet of the merged shards differs");
    }
}

#[test]
fn exported_sigma_point_filters_scored_as_external_give_the_run_tables() {
    // The exchange carries the UKF's and CKF's S and statistical-linearisation A_k, so their
    // NIS, whiteness and calibrated NEES verdict survive the round trip.
    for kind in ["ukf", "ckf"] {
        scored_equals_run(&study_of(kind));
    }
}

#[test]
fn bad_files_are_refused_naming_file_column_and_key() {
    let s = study();
    let good = read(&s.dir.join("kf.parquet"));
    let mut cases: Vec<(&str, DataFrame, &str)> = Vec::new();
    cases.push((
        "duplicate",
        good.vstack(&good.slice(0, 1)).unwrap(),
        "duplicate row scenario = \"hover\", noise_scale = 1, run = 0, step = 0, filter = \"kf\"",
    ));
    cases.push((
        "missing_column",
        good.drop("P_y_x").unwrap(),
        "missing column `P_y_x`",
    ));
    let mut extra = good.clone();
    extra
        .with_column(Column::new("bonus".into(), vec![1.0; good.height()]))
        .unwrap();
    cases.push(("extra_column", extra, "unexpected column `bonus`"));
    let mut undeclared = good.clone();
    undeclared
        .with_column(Column::new("filter".into(), vec!["mine"; good.height()]))
        .unwrap();
    cases.push((
        "undeclared",
        undeclared,
        "`mine` is not a filter of the spec; declare it with [[filters]] label = \"mine\", kind = \"external\"",
    ));
    let mut sqrt = good.clone();
    sqrt.with_column(Column::new("filter".into(), vec!["sqrt"; good.height()]))
        .unwrap();
    cases.push(("kfmc_label", sqrt, "`sqrt` is one of kfmc's filters"));
    let mut far = good.clone();
    let steps: Vec<i64> = (0..good.height() as i64).map(|i| i + 1000).collect();
    far.with_column(Column::new("step".into(), steps)).unwrap();
    cases.push((
        "step_range",
        far,
        "column `step`: outside 0..=50 at scenario = \"hover\", noise_scale = 1, run = 0, step = 1000",
    ));
    let mut scale = good.clone();
    scale
        .with_column(Column::new("noise_scale".into(), vec![2.0; good.height()]))
        .unwrap();
    cases.push((
        "noise_scale",
        scale,
        "column `noise_scale`: not a noise scale of this study",
    ));
    let mut float_run = good.clone();
    let runs: Vec<f64> = good
        .column("run")
        .unwrap()
        .i64()
        .unwrap()
        .into_no_null_iter()
        .map(|r| r as f64)
        .collect();
    float_run
        .with_column(Column::new("run".into(), runs))
        .unwrap();
    cases.push(("float_run", float_run, "column `run` must be an integer"));
    for (name, df, expect) in cases {
        let path = s.dir.join(format!("{name}.parquet"));
        write(&df, &path);
        let o = score(&s, &[&path], &format!("score_{name}"));
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(1), "{name}: {err}");
        assert!(
            err.contains(&*path.to_string_lossy()),
            "{name}: no file in {err}"
        );
        assert!(err.contains(expect), "{name}: expected `{expect}` in {err}");
        assert!(
            !s.dir.join(format!("score_{name}")).exists(),
            "{name}: a refused score wrote a folder"
        );
    }
    // Estimates of a spec without the external filter: no rows for it at all.
    let o = score(&s, &[], "score_none");
    assert_eq!(o.status.code(), Some(2), "clap requires --estimates");
}

#[test]
fn row_trouble_becomes_the_runs_status_and_the_batch_completes() {
    let s = study();
    let good = read(&s.dir.join("kf.parquet"));
    let (run, step) = (
        good.column("run").unwrap().i64().unwrap().clone(),
        good.column("step").unwrap().i64().unwrap().clone(),
    );
    let scen = good.column("scenario").unwrap().str().unwrap().clone();
    let noise = good.column("noise_scale").unwrap().f64().unwrap().clone();
    let first_cell = |i: usize| scen.get(i) == Some("hover") && noise.get(i) == Some(1.0);
    // Run 3: a NaN estimate at step 5. Run 4: rows from step 7 on missing.
    let est_x: Vec<Option<f64>> = (0..good.height())
        .map(|i| {
            let v = good.column("est_x").unwrap().f64().unwrap().get(i);
            if first_cell(i) && run.get(i) == Some(3) && step.get(i) == Some(5) {
                Some(f64::NAN)
            } else {
                v
            }
        })
        .collect();
    let keep: BooleanChunked = (0..good.height())
        .map(|i| !(first_cell(i) && run.get(i) == Some(4) && step.get(i).unwrap() >= 7))
        .collect();
    let mut df = good.clone();
    df.with_column(Column::new("est_x".into(), est_x)).unwrap();
    let df = df.filter(&keep).unwrap();
    let path = s.dir.join("trouble.parquet");
    write(&df, &path);
    let o = score(&s, &[&path], "score");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let runs = read(&s.dir.join("score/runs.parquet"));
    let status = |r: i64| {
        let m = runs.column("filter").unwrap().str().unwrap().equal("kf")
            & runs
                .column("scenario")
                .unwrap()
                .str()
                .unwrap()
                .equal("hover")
            & runs
                .column("noise_scale")
                .unwrap()
                .f64()
                .unwrap()
                .equal(1.0)
            & runs.column("run").unwrap().i64().unwrap().equal(r);
        let row = runs.filter(&m).unwrap();
        (
            row.column("status")
                .unwrap()
                .str()
                .unwrap()
                .get(0)
                .unwrap()
                .to_string(),
            row.column("status_step").unwrap().i64().unwrap().get(0),
            row.column("status_detail")
                .unwrap()
                .str()
                .unwrap()
                .get(0)
                .unwrap()
                .to_string(),
        )
    };
    assert_eq!(
        status(3),
        (
            "numerical_failure".into(),
            Some(5),
            "estimates: est_x is null or non-finite".into()
        )
    );
    assert_eq!(
        status(4),
        (
            "numerical_failure".into(),
            Some(7),
            "estimates: no row for step 7".into()
        )
    );
    assert_ne!(status(5).0, "numerical_failure");
    // Every run of every filter has its row.
    assert_eq!(runs.height(), 2 * 2 * 2 * 12);
}

#[test]
fn kfmc_run_refuses_a_spec_with_an_external_filter() {
    let s = study();
    let o = kfmc()
        .args(["run", "-q", "--out"])
        .arg(s.dir.join("nope"))
        .arg(&s.ext_spec)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains("`kf` is an external filter"), "{err}");
    assert!(err.contains("kfmc simulate"), "{err}");
}

fn python_has(modules: &str) -> bool {
    std::process::Command::new("python3")
        .args(["-c", &format!("import {modules}")])
        .output()
        .is_ok_and(|o| o.status.success())
}

#[test]
fn filterpy_kf_equals_kfmc_kf_and_the_negative_control_catches_q_times_4() {
    if !python_has("filterpy, pyarrow, numpy") {
        assert!(
            std::env::var("KFMC_REQUIRE_INTEROP").is_err(),
            "KFMC_REQUIRE_INTEROP is set but filterpy, pyarrow or numpy is missing"
        );
        eprintln!("skipped: pip install filterpy pyarrow numpy to run it");
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let spec = repo().join("experiments/external_filterpy_l1.toml");
    let script = repo().join("examples/python/filterpy_estimates.py");
    ok(kfmc()
        .args(["simulate", "-q", "--runs", "30", "--out"])
        .arg(dir.join("sim"))
        .arg(&spec));
    let py = |out: &str, label: &str, q: &str| {
        ok(std::process::Command::new("python3")
            .arg(&script)
            .arg("l1")
            .arg(dir.join("sim"))
            .arg(dir.join(out))
            .args(["--label", label, "--q-scale", q]));
    };
    py("kf.parquet", "filterpy_kf", "1");
    py("q4.parquet", "filterpy_kf_q4", "4");
    py("q1.parquet", "filterpy_kf_q4", "1");
    let junit = dir.join("junit.xml");
    let check = |files: &[&str], out: &str| {
        let mut c = kfmc();
        c.args(["check", "-q", "--runs", "30", "--out"])
            .arg(dir.join(out))
            .arg("--junit")
            .arg(&junit)
            .arg(&spec)
            .arg("--estimates")
            .args(files.iter().map(|f| dir.join(f)));
        c.output().unwrap()
    };
    let o = check(&["kf.parquet", "q4.parquet"], "chk");
    let report = String::from_utf8_lossy(&o.stdout);
    assert_eq!(
        o.status.code(),
        Some(0),
        "{report}{}",
        String::from_utf8_lossy(&o.stderr)
    );
    let xml = fs::read_to_string(&junit).unwrap();
    assert!(
        xml.contains("name=\"negative_control:consistent[hover noise=1 filterpy_kf_q4]\""),
        "{xml}"
    );
    // FilterPy's KF and kfmc's agree run by run, and so do their verdicts.
    let runs = read(&dir.join("chk/runs.parquet"));
    let of = |label: &str, c: &str| -> Vec<f64> {
        let m = runs.column("filter").unwrap().str().unwrap().equal(label);
        let r = runs.filter(&m).unwrap();
        r.column(c)
            .unwrap()
            .f64()
            .unwrap()
            .into_no_null_iter()
            .collect()
    };
    for c in ["rmse_x", "rmse_xdot", "rmse_zdot", "nees_mean", "nis_mean"] {
        let (a, b) = (of("kf", c), of("filterpy_kf", c));
        assert_eq!(a.len(), 30);
        for (x, y) in a.iter().zip(&b) {
            assert!((x - y).abs() <= 1e-9 * x.abs(), "{c}: {x} vs {y}");
        }
    }
    let cons = read(&dir.join("chk/consistency.parquet"));
    let verdict = |label: &str| {
        let m = cons.column("filter").unwrap().str().unwrap().equal(label)
            & cons.column("test").unwrap().str().unwrap().equal("verdict");
        let r = cons.filter(&m).unwrap();
        (
            r.column("pass").unwrap().bool().unwrap().get(0),
            r.column("statistic")
                .unwrap()
                .f64()
                .unwrap()
                .get(0)
                .unwrap(),
        )
    };
    let (kf, fp) = (verdict("kf"), verdict("filterpy_kf"));
    assert_eq!(kf.0, fp.0);
    assert!((kf.1 - fp.1).abs() <= 1e-9 * kf.1.abs(), "{kf:?} vs {fp:?}");
    assert_eq!(verdict("filterpy_kf_q4").0, Some(false));

    // A gate that lets the mistuned filter through is caught by the control: exit 3.
    let o = check(&["kf.parquet", "q1.parquet"], "chk_q1");
    assert_eq!(
        o.status.code(),
        Some(3),
        "{}",
        String::from_utf8_lossy(&o.stdout)
    );
    assert!(String::from_utf8_lossy(&o.stdout).contains("expected to fail, and it passed"));

    // Estimates of another simulation (here: another master seed) are refused by metadata.
    let o = kfmc()
        .args(["check", "-q", "--runs", "30", "--seed", "1", "--out"])
        .arg(dir.join("chk_seed"))
        .arg(&spec)
        .arg("--estimates")
        .arg(dir.join("kf.parquet"))
        .arg(dir.join("q4.parquet"))
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains("kfmc.master_seed = 2016"), "{err}");
}

#[test]
fn filterpy_ekf_on_p1_equals_kfmc_ekf() {
    if !python_has("filterpy, pyarrow, numpy") {
        assert!(
            std::env::var("KFMC_REQUIRE_INTEROP").is_err(),
            "KFMC_REQUIRE_INTEROP is set but filterpy, pyarrow or numpy is missing"
        );
        eprintln!("skipped: pip install filterpy pyarrow numpy to run it");
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let spec = repo().join("experiments/external_filterpy_p1.toml");
    ok(kfmc()
        .args(["simulate", "-q", "--runs", "6", "--out"])
        .arg(dir.join("sim"))
        .arg(&spec));
    ok(std::process::Command::new("python3")
        .arg(repo().join("examples/python/filterpy_estimates.py"))
        .arg("p1")
        .arg(dir.join("sim"))
        .arg(dir.join("ekf.parquet"))
        .args(["--label", "filterpy_ekf"]));
    ok(kfmc()
        .args(["score", "-q"])
        .arg(dir.join("sim"))
        .arg("--estimates")
        .arg(dir.join("ekf.parquet")));
    let runs = read(&dir.join("sim/score/runs.parquet"));
    let of = |label: &str, c: &str| -> Vec<f64> {
        let m = runs.column("filter").unwrap().str().unwrap().equal(label);
        let r = runs.filter(&m).unwrap();
        r.column(c)
            .unwrap()
            .f64()
            .unwrap()
            .into_no_null_iter()
            .collect()
    };
    // FilterPy updates in Joseph form, kfmc (as the seeds) in the standard form, and numpy's
    // sin/cos are not Rust's: they agree at round-off, amplified over 1,000 steps.
    for c in ["rmse_x", "rmse_ydot", "rmse_theta", "nees_mean", "nis_mean"] {
        let (a, b) = (of("ekf", c), of("filterpy_ekf", c));
        assert_eq!(a.len(), 4 * 6, "{c}");
        for (x, y) in a.iter().zip(&b) {
            assert!((x - y).abs() <= 1e-9 * x.abs(), "{c}: {x} vs {y}");
        }
    }
}

/// The external spec at noise scale 1 alone (at 3 the nominal KF is rightly optimistic),
/// with a `consistent` assertion on `kf` (and `extra` in `[check]`).
fn check_spec(s: &Study, extra: &str) -> PathBuf {
    let text = fs::read_to_string(&s.ext_spec)
        .unwrap()
        .replace("scales = [1.0, 3.0]", "scales = [1.0]")
        + &format!("[check]\n{extra}\n[[check.assert]]\nkind = \"consistent\"\nfilter = \"kf\"\n");
    let path = s.dir.join(format!("check_{}.toml", extra.len()));
    fs::write(&path, text).unwrap();
    path
}

/// `kfmc check` of `spec` on estimates `file`: (exit code, report, stderr, JUnit XML).
fn check_with(
    s: &Study,
    spec: &Path,
    file: &Path,
    out: &str,
) -> (Option<i32>, String, String, String) {
    let junit = s.dir.join(format!("{out}.xml"));
    let o = kfmc()
        .args(["check", "-q", "--out"])
        .arg(s.dir.join(out))
        .arg("--junit")
        .arg(&junit)
        .arg(spec)
        .arg("--estimates")
        .arg(file)
        .output()
        .unwrap();
    (
        o.status.code(),
        String::from_utf8_lossy(&o.stdout).into_owned(),
        String::from_utf8_lossy(&o.stderr).into_owned(),
        fs::read_to_string(&junit).unwrap_or_default(),
    )
}

/// The rows of the `kf` estimates at noise scale 1, with `keep` and with column `c` replaced
/// at `(run, step)` of the first cell (hover, noise 1).
fn edited(
    good: &DataFrame,
    keep: impl Fn(i64, i64) -> bool,
    edit: Option<(&str, i64, i64, f64)>,
) -> DataFrame {
    let col_i = |c: &str| good.column(c).unwrap().i64().unwrap().clone();
    let (run, step) = (col_i("run"), col_i("step"));
    let scen = good.column("scenario").unwrap().str().unwrap().clone();
    let noise = good.column("noise_scale").unwrap().f64().unwrap().clone();
    let first = |i: usize| scen.get(i) == Some("hover") && noise.get(i) == Some(1.0);
    let at = |i: usize| (run.get(i).unwrap(), step.get(i).unwrap());
    let mut df = good.clone();
    if let Some((c, r, k, v)) = edit {
        let col: Vec<Option<f64>> = (0..good.height())
            .map(|i| {
                if first(i) && at(i) == (r, k) {
                    Some(v)
                } else {
                    good.column(c).unwrap().f64().unwrap().get(i)
                }
            })
            .collect();
        df.with_column(Column::new(c.into(), col)).unwrap();
    }
    let mask: BooleanChunked = (0..good.height())
        .map(|i| noise.get(i) == Some(1.0) && (!first(i) || keep(at(i).0, at(i).1)))
        .collect();
    df.filter(&mask).unwrap()
}

#[test]
fn check_is_incomplete_when_runs_fail_numerically_beyond_max_failed_runs() {
    // Run 3 of (hover, noise 1) hands kfmc a covariance that is not positive definite at step
    // 5: a valid file, and a numerical failure of that run. 1 of 12 runs is more than the
    // default max_failed_runs = 0 allows, and within 0.1.
    let s = study();
    let good = read(&s.dir.join("kf.parquet"));
    let path = s.dir.join("not_pd.parquet");
    write(
        &edited(&good, |_, _| true, Some(("P_x_x", 3, 5, -1.0))),
        &path,
    );

    let (code, report, err, xml) = check_with(&s, &check_spec(&s, ""), &path, "strict");
    assert_eq!(code, Some(4), "{report}{err}");
    assert!(
        report.contains(": 2 cases, 1 passed, 0 failed, 1 incomplete"),
        "{report}"
    );
    assert!(
        report.contains("INCOMPLETE  consistent[hover noise=1 kf]"),
        "{report}"
    );
    // The JUnit failure is the incomplete one, naming the cell and the count.
    assert!(
        xml.contains("name=\"consistent[hover noise=1 kf]\"")
            && xml.contains("<failure type=\"incomplete\" message=\"incomplete: 1 of the 12 runs of hover noise=1 kf failed numerically, more than check.max_failed_runs = 0 allows; first: run 3"),
        "{xml}"
    );
    // An external filter's case is named by its label: it carries no q/r multipliers.
    assert!(!xml.contains("kf q="), "{xml}");

    let (code, report, err, _) = check_with(
        &s,
        &check_spec(&s, "max_failed_runs = 0.1"),
        &path,
        "lenient",
    );
    assert!(matches!(code, Some(0 | 3)), "{report}{err}");
    assert!(!report.contains("INCOMPLETE"), "{report}");
    assert!(
        report.contains("  consistent[hover noise=1 kf]"),
        "{report}"
    );

    // The key is a fraction, refused outside [0, 1] with its key path.
    for bad in [
        "max_failed_runs = 1.5",
        "max_failed_runs = -0.1",
        "max_failed_runs = nan",
    ] {
        let (code, _, err, _) = check_with(&s, &check_spec(&s, bad), &path, "bad");
        assert_eq!(code, Some(2), "{bad}: {err}");
        assert!(err.contains("check.max_failed_runs"), "{bad}: {err}");
    }
}

#[test]
fn check_never_passes_a_cell_whose_runs_are_missing() {
    // Only runs 0 and 1 of (hover, noise 1): the verdict would be computed on 2 of 12 runs.
    // Either the estimates are refused before scoring (exit 1, naming the run) or the case is
    // incomplete (exit 4, naming the cell and the count); never a pass.
    let s = study();
    let good = read(&s.dir.join("kf.parquet"));
    let path = s.dir.join("two_runs.parquet");
    write(&edited(&good, |run, _| run < 2, None), &path);
    let (code, report, err, xml) = check_with(&s, &check_spec(&s, ""), &path, "missing");
    match code {
        Some(4) => {
            assert!(
                report.contains("INCOMPLETE  consistent[hover noise=1 kf]"),
                "{report}"
            );
            assert!(
                xml.contains("<failure type=\"incomplete\" message=\"incomplete: 10 of the 12 runs of hover noise=1 kf"),
                "{xml}"
            );
        }
        Some(1) => assert!(err.contains("run 2"), "{err}"),
        other => panic!("exit {other:?}: {report}{err}"),
    }
}

#[test]
fn check_is_incomplete_when_the_calibrated_test_cannot_be_computed() {
    // One non-finite A_x_x of one row: that run has no error transition, so the calibrated
    // NEES test of the cell cannot be computed. With 12 runs the cell's verdict used to
    // vanish (3 cases instead of 4, all passed); with 20 the model-free test used to stand in
    // for the calibrated one the filter selects. Either the file is refused before scoring
    // (exit 1, naming the column) or the case is incomplete (exit 4); never a pass.
    for runs in [12, 20] {
        let s = study_runs("ekf", runs);
        let good = read(&s.dir.join("kf.parquet"));
        let path = s.dir.join("nan_a.parquet");
        write(
            &edited(&good, |_, _| true, Some(("A_x_x", 3, 5, f64::NAN))),
            &path,
        );
        let (code, report, err, xml) = check_with(&s, &check_spec(&s, ""), &path, "nan_a");
        match code {
            Some(4) => {
                // Every declared cell has its case; the others are judged either way.
                assert!(
                    report.contains(": 2 cases, 1 passed, 0 failed, 1 incomplete"),
                    "N={runs}: {report}"
                );
                assert!(
                    report.contains("INCOMPLETE  consistent[hover noise=1 kf]"),
                    "N={runs}: {report}"
                );
                assert!(
                    xml.contains(
                        "the calibrated NEES test needs every run&apos;s error transition"
                    ),
                    "N={runs}: {xml}"
                );
            }
            Some(1) => assert!(err.contains("A_x_x"), "N={runs}: {err}"),
            other => panic!("N={runs}: exit {other:?}: {report}{err}"),
        }
    }
}
