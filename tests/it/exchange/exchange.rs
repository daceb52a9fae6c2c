//! The estimates exchange: `kfmc simulate` → an estimator outside kfmc → `kfmc score` /
//! `kfmc check --estimates`.
//!
//! * kfmc's own KF exported with `--export-estimates` and scored as an external filter gives
//!   the run's tables byte for byte (runs, steps, summary, divergence); the consistency table
//!   agrees to 1e-12 relative, because the exchange carries P's lower triangle only and the
//!   seeds' P = (I − KH)P⁻ is not exactly symmetric (ρ's recursion sees the difference).
//!   The UKF and CKF (kfmc's sigma-point filters, with S and their statistical-linearisation
//!   A_k) round-trip the same way on L1, and so do the q_scale/r_scale variants of one label,
//!   exported with a variant column per keyed axis and scored as that label's external
//!   variants (the columns are absent for a label with one variant).
//! * Bad files are refused naming the file, the column and the first offending key; trouble in
//!   a row becomes that run's status and the batch completes.
//! * FilterPy's KalmanFilter (examples/python/filterpy_estimates.py) equals kfmc's KF, and a
//!   negative control proves the gate rejects it mistuned (Q × 4). The Python packages are
//!   installed by `.ci/run`, which sets KFMC_REQUIRE_INTEROP=1; elsewhere the test skips.

use std::fs;
use std::path::{Path, PathBuf};

use crate::common::{kfmc, ok, read, repo, stamp_of, write_with};
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

pub(crate) struct Study {
    _tmp: tempfile::TempDir,
    pub(crate) dir: PathBuf,
    ext_spec: PathBuf,
    /// The stamp of the run's estimates.parquet (its `kfmc.*` metadata).
    stamp: Vec<(String, String)>,
    /// Whether the `kf` entry has several q_scale/r_scale variants (in both specs).
    variants: bool,
}

impl Study {
    /// Writes `df` carrying the run's stamp, as a writer outside kfmc would.
    pub(crate) fn write(&self, df: &DataFrame, path: &Path) {
        write_with(df, path, &self.stamp);
    }
}

/// Runs kfmc's KF with its estimates exported, keeps the KF's rows as an external filter's
/// file, and simulates the spec in which `kf` is external.
pub(crate) fn study() -> Study {
    study_of("ekf")
}

/// [`study`] with the `kf` entry of another kind.
fn study_of(kind: &str) -> Study {
    study_runs(kind, 12)
}

/// [`study_of`] with `runs` runs per cell.
fn study_runs(kind: &str, runs: usize) -> Study {
    study_variants(kind, runs, "")
}

/// [`study_runs`] with `variants` (`q_scale = [...]`, `r_scale = [...]` lines) in the `kf`
/// entry of both specs: the run's and the external one's.
fn study_variants(kind: &str, runs: usize, variants: &str) -> Study {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().to_path_buf();
    let run_spec = dir.join("run.toml");
    let ext_spec = dir.join("ext.toml");
    let spec = RUN_SPEC
        .replace("runs = 12", &format!("runs = {runs}"))
        .replace("kind = \"KIND\"\n", &format!("kind = \"KIND\"\n{variants}"));
    fs::write(&run_spec, spec.replace("KIND", kind)).unwrap();
    fs::write(&ext_spec, spec.replace("KIND", "external")).unwrap();
    ok(kfmc()
        .args(["run", "-q", "--export-estimates", "--out"])
        .arg(dir.join("run"))
        .arg(&run_spec));
    let all = read(&dir.join("run/estimates.parquet"));
    let names: Vec<&str> = all.get_column_names().iter().map(|n| n.as_str()).collect();
    let at = names.iter().position(|n| *n == "filter").unwrap() + 1;
    // The variant columns follow `filter`, one for each axis the `kf` variants are keyed on;
    // a label with one variant (`sqrt`, and `kf` without variants) names none.
    let keyed: Vec<&str> = ["q_scale", "r_scale"]
        .into_iter()
        .filter(|c| variants.contains(c))
        .collect();
    assert_eq!(names[at..at + keyed.len()], keyed[..], "{names:?}");
    for c in ["q_scale", "r_scale"] {
        assert_eq!(names.contains(&c), keyed.contains(&c), "{c} in {names:?}");
    }
    for c in &keyed {
        let filter = all.column("filter").unwrap().str().unwrap();
        let v = all.column(c).unwrap().f64().unwrap();
        for (f, v) in filter.iter().zip(v.iter()) {
            assert_eq!(f == Some("kf"), v.is_some(), "{c} of {f:?}: {v:?}");
        }
    }
    let kf = all
        .filter(&all.column("filter").unwrap().str().unwrap().equal("kf"))
        .unwrap();
    let stamp = stamp_of(&dir.join("run/estimates.parquet"));
    write_with(&kf, &dir.join("kf.parquet"), &stamp);
    ok(kfmc()
        .args(["simulate", "-q", "--out"])
        .arg(dir.join("sim"))
        .arg(&ext_spec));
    Study {
        _tmp: tmp,
        dir,
        ext_spec,
        stamp,
        variants: !variants.is_empty(),
    }
}

fn write(df: &DataFrame, path: &Path) {
    let mut df = df.clone();
    ParquetWriter::new(fs::File::create(path).unwrap())
        .finish(&mut df)
        .unwrap();
}

pub(crate) fn score(s: &Study, files: &[&Path], out: &str) -> std::process::Output {
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
        // An external filter with variants is keyed by the run's multipliers: every column
        // is the run's.
        if s.variants {
            assert!(
                a.equals_missing(&b),
                "{t}.parquet differs between run and score"
            );
            continue;
        }
        // One without carries no multipliers: its q_scale and r_scale are null, kfmc's
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
    let keys: &[&str] = if s.variants {
        &["scenario", "noise_scale", "filter", "q_scale", "r_scale"]
    } else {
        &["scenario", "noise_scale", "filter"]
    };
    for c in keys.iter().chain(&["test", "pass", "direction"]) {
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
fn exported_variants_of_one_label_scored_as_external_variants_give_the_run_tables() {
    // One label with several tunings exports its variants in `q_scale`/`r_scale` columns,
    // which the same label declared external with the same variants reads back: on Q alone,
    // on both axes, and on R with a Q multiplier other than 1 (which the rows then name too,
    // as the external entry lists it).
    for (variants, schema) in [
        ("q_scale = [0.5, 1, 2]\n", &["q_scale = 0.5, 1, 2"][..]),
        (
            "q_scale = [0.5, 2]\nr_scale = [1, 4]\n",
            &["q_scale = 0.5, 2", "r_scale = 1, 4"],
        ),
        (
            "q_scale = 2\nr_scale = [0.5, 2]\n",
            &["q_scale = 2", "r_scale = 0.5, 2"],
        ),
    ] {
        let s = study_variants("ekf", 6, variants);
        scored_equals_run(&s);
        // `kfmc schema estimates` of the run's spec lists the variant columns its export has,
        // with the values they name.
        let o = ok(kfmc()
            .args(["schema", "estimates"])
            .arg(s.dir.join("run.toml")));
        let text = String::from_utf8_lossy(&o.stdout);
        let lines: Vec<&str> = text
            .lines()
            .filter(|l| l.starts_with("q_scale ") || l.starts_with("r_scale "))
            .collect();
        assert_eq!(lines.len(), schema.len(), "{text}");
        for (line, want) in lines.iter().zip(schema) {
            assert!(line.contains(&format!("`kf` {want}")), "{line}");
        }
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
    // The error transition's dimension: every A_<qi>_<qj> of the study's quantities, no other.
    cases.push((
        "a_short",
        good.drop("A_ydot_z").unwrap(),
        "missing column `A_ydot_z`",
    ));
    let mut a_wide = good.clone();
    a_wide
        .with_column(Column::new("A_x_w".into(), vec![0.0; good.height()]))
        .unwrap();
    cases.push(("a_wide", a_wide, "unexpected column `A_x_w`"));
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
    cases.push((
        "float_run",
        float_run,
        "column `run` holds float64 values; it must be an integer column",
    ));
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
    // Run 3: a NaN estimate at step 5 (a filter that blew up says so in its estimate).
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
    let mut df = good.clone();
    df.with_column(Column::new("est_x".into(), est_x)).unwrap();
    let path = s.dir.join("trouble.parquet");
    s.write(&df, &path);
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
    assert_ne!(status(4).0, "numerical_failure");
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

/// `kfmc run --export-estimates` of the run spec at another master seed, its `kf` rows with
/// their stamp.
fn exported_at_seed(s: &Study, seed: &str) -> (DataFrame, Vec<(String, String)>) {
    let out = s.dir.join(format!("run_seed{seed}"));
    ok(kfmc()
        .args(["run", "-q", "--export-estimates", "--seed", seed, "--out"])
        .arg(&out)
        .arg(s.dir.join("run.toml")));
    let all = read(&out.join("estimates.parquet"));
    let kf = all
        .filter(&all.column("filter").unwrap().str().unwrap().equal("kf"))
        .unwrap();
    (kf, stamp_of(&out.join("estimates.parquet")))
}

fn value<'a>(stamp: &'a [(String, String)], key: &str) -> &'a str {
    &stamp.iter().find(|(k, _)| k == key).unwrap().1
}

#[test]
fn estimates_of_another_simulation_are_refused_naming_it_and_the_stamp_ignores_comments_and_filters()
 {
    let s = study();
    // kfmc's own export carries the stamp, and the simulation's manifest states it.
    let keys: Vec<&str> = s.stamp.iter().map(|(k, _)| k.as_str()).collect();
    assert_eq!(keys, ["kfmc.master_seed", "kfmc.world_stamp"]);
    assert_eq!(value(&s.stamp, "kfmc.master_seed"), "7");
    let world = value(&s.stamp, "kfmc.world_stamp").to_string();
    assert_eq!(world.len(), 16);
    let manifest = fs::read_to_string(s.dir.join("sim/manifest.toml")).unwrap();
    assert!(
        manifest.contains(&format!("world_stamp = \"{world}\"")),
        "{manifest}"
    );
    // The run spec's export is accepted by the external spec, which differs in its filters.
    let o = score(&s, &[&s.dir.join("kf.parquet")], "score");
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert!(!err.contains("warning"), "{err}");
    // So by that spec with comments, another layout and another filter list.
    let text = fs::read_to_string(&s.ext_spec).unwrap();
    let edited = format!(
        "# simulated for the FilterPy comparison\n{}",
        text.replace("master_seed = 7", "master_seed   =   7   # the seed")
            .replace(
                "[[filters]]\nlabel = \"sqrt\"\nkind = \"sqrt\"",
                "[[filters]]\nkind = \"ukf\"\nlabel = \"u\""
            )
            .replace("runs = 12", "runs = 12\ntrace_runs = 2")
    );
    assert_ne!(edited, text);
    let edited_spec = s.dir.join("edited.toml");
    fs::write(&edited_spec, edited).unwrap();
    ok(kfmc()
        .args(["simulate", "-q", "--out"])
        .arg(s.dir.join("sim_edited"))
        .arg(&edited_spec));
    ok(kfmc()
        .args(["score", "-q"])
        .arg(s.dir.join("sim_edited"))
        .arg("--estimates")
        .arg(s.dir.join("kf.parquet")));

    // Estimates made on master seed 8, scored against the seed-7 simulation: refused, naming
    // the simulation the file belongs to, before anything is written.
    let (kf8, stamp8) = exported_at_seed(&s, "8");
    assert_eq!(value(&stamp8, "kfmc.master_seed"), "8");
    let world8 = value(&stamp8, "kfmc.world_stamp").to_string();
    assert_ne!(world8, world);
    let path = s.dir.join("kf8.parquet");
    write_with(&kf8, &path, &stamp8);
    let o = score(&s, &[&path], "score8");
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    for expect in [
        "made on another simulation".to_string(),
        format!("kfmc.world_stamp = {world8}, kfmc.master_seed = 8"),
        format!("this study simulates world {world} with master seed 7"),
        path.to_string_lossy().to_string(),
    ] {
        assert!(err.contains(&expect), "expected `{expect}` in {err}");
    }
    assert!(!s.dir.join("score8").exists());
}

/// The external spec with a `[check]` assertion any of the filters meets.
fn check_spec_rmse(s: &Study) -> PathBuf {
    let path = s.dir.join("check.toml");
    let text = fs::read_to_string(&s.ext_spec).unwrap()
        + "[check]\n[[check.assert]]\nkind = \"rmse_below\"\nfilter = \"kf\"\nstate = \"x\"\nmax = 1000.0\n";
    fs::write(&path, text).unwrap();
    path
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

fn check(spec: &Path, out: &Path, files: &[&Path], extra: &[&str]) -> std::process::Output {
    kfmc()
        .args(["check", "-q", "--out"])
        .arg(out)
        .arg(spec)
        .args(extra)
        .arg("--estimates")
        .args(files)
        .output()
        .unwrap()
}

#[test]
fn unstamped_estimates_warn_in_score_and_are_refused_by_check() {
    let s = study();
    // Without file metadata, estimates of another simulation (master seed 8) cannot be told
    // from data: score judges them with a warning, check refuses them.
    let (kf8, _) = exported_at_seed(&s, "8");
    let path = s.dir.join("unstamped.parquet");
    write(&kf8, &path);
    let o = score(&s, &[&path], "score");
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert!(
        err.contains(&format!(
            "warning: {} carries no world stamp",
            path.display()
        )),
        "{err}"
    );
    let world = value(&s.stamp, "kfmc.world_stamp");
    assert!(
        err.contains(&format!("kfmc.world_stamp = {world}, kfmc.master_seed = 7")),
        "the warning says how to stamp: {err}"
    );

    let spec = check_spec_rmse(&s);
    let o = check(&spec, &s.dir.join("chk"), &[&path], &[]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains("carries no world stamp"), "{err}");
    assert!(err.contains("--allow-unstamped"), "{err}");
    assert!(!s.dir.join("chk").exists());

    let o = check(
        &spec,
        &s.dir.join("chk_allowed"),
        &[&path],
        &["--allow-unstamped"],
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(0), "{err}");
    assert!(err.contains("warning:"), "{err}");

    // The stamped file of this simulation passes without a word.
    let o = check(
        &spec,
        &s.dir.join("chk_stamped"),
        &[&s.dir.join("kf.parquet")],
        &[],
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(0), "{err}");
    assert!(!err.contains("warning"), "{err}");
}

#[test]
fn partial_runs_and_non_finite_values_are_refused_naming_run_and_step() {
    let s = study();
    let good = read(&s.dir.join("kf.parquet"));
    let h = good.height();
    let (run, step) = (
        good.column("run").unwrap().i64().unwrap().clone(),
        good.column("step").unwrap().i64().unwrap().clone(),
    );
    let scen = good.column("scenario").unwrap().str().unwrap().clone();
    let noise = good.column("noise_scale").unwrap().f64().unwrap().clone();
    let at = |i: usize, r: i64, k: Option<i64>| {
        scen.get(i) == Some("hover")
            && noise.get(i) == Some(1.0)
            && run.get(i) == Some(r)
            && k.is_none_or(|k| step.get(i) == Some(k))
    };
    let nu = good
        .get_column_names()
        .into_iter()
        .find(|c| c.starts_with("nu_"))
        .unwrap()
        .to_string();
    let with_value = |col: &str, v: Option<f64>| {
        let c = good.column(col).unwrap().f64().unwrap();
        let vals: Vec<Option<f64>> = (0..h)
            .map(|i| if at(i, 3, Some(5)) { v } else { c.get(i) })
            .collect();
        let mut df = good.clone();
        df.with_column(Column::new(col.into(), vals)).unwrap();
        df
    };
    let keep = |f: &dyn Fn(usize) -> bool| {
        let m: BooleanChunked = (0..h).map(f).collect();
        good.filter(&m).unwrap()
    };
    let mut shifted = good.clone();
    let steps: Vec<i64> = (0..h)
        .map(|i| step.get(i).unwrap() + at(i, 2, None) as i64)
        .collect();
    shifted
        .with_column(Column::new("step".into(), steps))
        .unwrap();
    let key = |r: i64, k: i64| {
        format!("scenario = \"hover\", noise_scale = 1, run = {r}, step = {k}, filter = \"kf\"")
    };
    let cases: Vec<(&str, DataFrame, String)> = vec![
        (
            "no_step_0",
            keep(&|i| step.get(i) != Some(0)),
            "filter `kf`, scenario = \"hover\", noise_scale = 1, run = 0: no row for step 0 (50 of its 51 steps".into(),
        ),
        (
            "partial_run",
            keep(&|i| !(at(i, 4, None) && step.get(i).unwrap() >= 7)),
            "run = 4: no row for step 7 (7 of its 51 steps 0..=50 are given)".into(),
        ),
        (
            "shifted",
            shifted,
            format!("column `step`: outside 0..=50 at {}", key(2, 51)),
        ),
        (
            "nan_nu",
            with_value(&nu, Some(f64::NAN)),
            format!("column `{nu}`: NaN at {}", key(3, 5)),
        ),
        (
            "inf_a",
            with_value("A_x_x", Some(f64::INFINITY)),
            format!("column `A_x_x`: inf at {}", key(3, 5)),
        ),
        (
            "partial_a",
            with_value("A_x_x", None),
            format!("column `A_x_x`: null at {}", key(3, 5)),
        ),
    ];
    for (name, df, expect) in cases {
        let path = s.dir.join(format!("{name}.parquet"));
        s.write(&df, &path);
        let o = score(&s, &[&path], &format!("score_{name}"));
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(1), "{name}: {err}");
        assert!(err.contains(&*path.to_string_lossy()), "{name}: {err}");
        assert!(
            err.contains(&expect),
            "{name}: expected `{expect}` in {err}"
        );
        assert!(
            !s.dir.join(format!("score_{name}")).exists(),
            "{name}: refused after scoring had begun"
        );
    }
}

/// The stamp `kfmc schema estimates` states for `spec`'s world, as a writer outside kfmc
/// reads it (none for a spec it refuses).
fn stamp_for(spec: &Path) -> Option<Vec<(String, String)>> {
    let o = kfmc()
        .args(["schema", "estimates"])
        .arg(spec)
        .output()
        .unwrap();
    if !o.status.success() {
        return None;
    }
    let text = String::from_utf8_lossy(&o.stdout).into_owned();
    let line = text
        .lines()
        .find(|l| l.contains("kfmc.world_stamp = "))
        .unwrap_or_else(|| panic!("no stamp in {text}"));
    let value = |key: &str| {
        let rest = &line[line.find(key).unwrap() + key.len()..];
        rest.split(|c: char| c == ',' || c.is_whitespace())
            .next()
            .unwrap()
            .to_string()
    };
    Some(vec![
        ("kfmc.master_seed".into(), value("kfmc.master_seed = ")),
        ("kfmc.world_stamp".into(), value("kfmc.world_stamp = ")),
    ])
}

/// `kfmc check` of `spec` on estimates `file`: (exit code, report, stderr, JUnit XML). The
/// file is stamped for `spec`'s world first: a check spec keeps noise scale 1 alone, another
/// world than the simulation's two scales, and these tests are about the rows, not the stamp.
fn check_with(
    s: &Study,
    spec: &Path,
    file: &Path,
    out: &str,
) -> (Option<i32>, String, String, String) {
    if let Some(stamp) = stamp_for(spec) {
        write_with(&read(file), file, &stamp);
    }
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
    s.write(
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
fn a_csv_both_covariance_forms_and_a_file_for_the_folder_get_messages_that_say_so() {
    let s = study();
    let csv = s.dir.join("estimates.csv");
    fs::write(
        &csv,
        "scenario,noise_scale,run,step,filter\nhover,1,0,0,kf\n",
    )
    .unwrap();
    let o = score(&s, &[&csv], "score_csv");
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(
        err.contains("estimates must be Parquet (got a CSV?)"),
        "{err}"
    );

    let good = read(&s.dir.join("kf.parquet"));
    let mut both = good.clone();
    for i in 0..6 {
        for j in 0..=i {
            both.with_column(Column::new(
                format!("L_{i}_{j}").into(),
                vec![1.0; good.height()],
            ))
            .unwrap();
        }
    }
    let path = s.dir.join("both.parquet");
    s.write(&both, &path);
    let o = score(&s, &[&path], "score_both");
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(
        err.contains("both `P_x_x` and `L_0_0`: give the covariance one way"),
        "{err}"
    );

    let o = kfmc()
        .arg("score")
        .arg(s.dir.join("kf.parquet"))
        .arg("--estimates")
        .arg(s.dir.join("kf.parquet"))
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(
        err.contains("is a file; kfmc score takes the folder `kfmc simulate` wrote"),
        "{err}"
    );
}

/// `kfmc score` scores against a whole, unaltered `kfmc simulate` folder and nothing else:
/// a `kfmc run` folder, one part of a sharded simulation and a folder whose recorded spec no
/// longer hashes to its manifest's are refused, each saying which.
#[test]
fn score_takes_only_a_whole_unaltered_simulation_folder() {
    let s = study();
    let refused = |sim: &Path, out: &str, why: &str| {
        let o = kfmc()
            .args(["score", "-q"])
            .arg(sim)
            .arg("--out")
            .arg(s.dir.join(out))
            .arg("--estimates")
            .arg(s.dir.join("kf.parquet"))
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(1), "{out}: {err}");
        assert!(err.contains(why), "{out}: {err}");
        assert!(!s.dir.join(out).exists(), "{out} was written");
    };
    refused(
        &s.dir.join("run"),
        "of_run",
        "was not written by `kfmc simulate`",
    );

    ok(kfmc()
        .args(["simulate", "-q", "--shard", "1/2", "--out"])
        .arg(s.dir.join("sharded"))
        .arg(&s.ext_spec));
    let part = s.dir.join("sharded/parts/part-00001-of-00002");
    assert!(part.join("manifest.toml").exists());
    refused(&part, "of_part", "is one part of a sharded simulation");

    let altered = s.dir.join("altered");
    fs::create_dir(&altered).unwrap();
    for entry in fs::read_dir(s.dir.join("sim")).unwrap() {
        let entry = entry.unwrap();
        fs::copy(entry.path(), altered.join(entry.file_name())).unwrap();
    }
    let manifest = fs::read_to_string(altered.join("manifest.toml")).unwrap();
    assert!(manifest.contains("duration_s = "));
    fs::write(
        altered.join("manifest.toml"),
        manifest.replacen("duration_s = ", "duration_s =  ", 1),
    )
    .unwrap();
    refused(&altered, "of_altered", "holds an altered simulation");
}

#[test]
fn measurements_have_no_step_0_measurement_and_schema_says_so() {
    let s = study();
    let m = read(&s.dir.join("sim/measurements.parquet"));
    let step = m.column("step").unwrap().i64().unwrap().clone();
    let z: Vec<String> = m
        .get_column_names()
        .into_iter()
        .filter(|c| c.starts_with("z_"))
        .map(|c| c.to_string())
        .collect();
    assert_eq!(z.len(), 3);
    let (first, later) = (
        m.filter(&step.equal(0)).unwrap(),
        m.filter(&step.gt(0)).unwrap(),
    );
    // 2 scenarios × 2 scales × 12 runs start at step 0.
    assert_eq!(first.height(), 48);
    for c in &z {
        assert_eq!(first.column(c).unwrap().null_count(), 48, "{c} at step 0");
        // The positions sensor reports at every later step.
        assert_eq!(later.column(c).unwrap().null_count(), 0, "{c} after step 0");
    }
    let out = ok(kfmc().args(["schema", "measurements"]).arg(&s.ext_spec));
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(text.contains("null at step 0"), "{text}");
    let out = ok(kfmc().args(["schema", "estimates"]).arg(&s.ext_spec));
    let text = String::from_utf8_lossy(&out.stdout);
    let line = |name: &str| {
        text.lines()
            .find(|l| l.split_whitespace().next() == Some(name))
            .unwrap_or_else(|| panic!("no {name} in {text}"))
            .to_string()
    };
    assert!(!line("noise_scale").contains("nullable"), "{text}");
    assert!(line("est_x").contains("nullable"), "{text}");
    let world = value(&s.stamp, "kfmc.world_stamp");
    assert!(
        text.contains(&format!("kfmc.world_stamp = {world}, kfmc.master_seed = 7")),
        "{text}"
    );
}

#[test]
fn the_pyarrow_stamping_example_stamps_a_file_that_check_then_accepts() {
    if !python_has("pyarrow, tomllib") {
        assert!(
            std::env::var("KFMC_REQUIRE_INTEROP").is_err(),
            "KFMC_REQUIRE_INTEROP is set but pyarrow (or Python ≥ 3.11) is missing"
        );
        eprintln!("skipped: pip install pyarrow (Python ≥ 3.11) to run it");
        return;
    }
    let s = study();
    let path = s.dir.join("plain.parquet");
    write(&read(&s.dir.join("kf.parquet")), &path);
    assert!(stamp_of(&path).is_empty());
    ok(std::process::Command::new("python3")
        .arg(repo().join("examples/python/stamp_estimates.py"))
        .arg(s.dir.join("sim"))
        .arg(&path));
    assert_eq!(stamp_of(&path), s.stamp);
    let spec = check_spec_rmse(&s);
    let o = check(&spec, &s.dir.join("chk"), &[&path], &[]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(0), "{err}");
    assert!(!err.contains("warning"), "{err}");
}

#[test]
fn check_never_passes_a_cell_whose_runs_are_missing() {
    // Only runs 0 and 1 of (hover, noise 1): the verdict would be computed on 2 of 12 runs.
    // Either the estimates are refused before scoring (exit 1, naming the run) or the case is
    // incomplete (exit 4, naming the cell and the count); never a pass.
    let s = study();
    let good = read(&s.dir.join("kf.parquet"));
    let path = s.dir.join("two_runs.parquet");
    s.write(&edited(&good, |run, _| run < 2, None), &path);
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
        s.write(
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
