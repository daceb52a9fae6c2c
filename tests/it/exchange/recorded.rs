//! A user's own runs (`model.kind = "recorded"`): truth and estimates from files.
//!
//! The known answer is kfmc's own study: L1's truth written by `kfmc simulate` and its KF's
//! estimates written by `kfmc run --export-estimates`, re-read as a recorded world, give the
//! study's tables value for value and the same `kfmc check` verdict — a second path to the
//! same numbers. Around it: the truth's content hash (row order and encoding do not change
//! it, one value does), foreign estimates refused, missing runs incomplete (exit 4), and bad
//! columns named.

use std::path::{Path, PathBuf};

use crate::common::{i64s, kfmc, ok, read, write_with};
use kfmc::exchange::recorded::{RecordedKeys, RecordedTable, ValueGroup};
use polars::prelude::*;

const L1: &str = r#"
name = "l1"
master_seed = 7
runs = 10
[model]
kind = "linear_quadrotor"
sensor = "positions"
[[scenarios]]
name = "hover"
x0 = [1.0, 0.0, 1.0, 0.0, 1.0, 0.0]
duration_s = 5.0
[noise]
scales = [1.0, 2.0]
filter_noise = "matched"
[[filters]]
label = "kf"
kind = "ekf"
[initial_estimate]
mode = "sampled"
p0_std = 1.0
[consistency]
alpha = 0.01
[[check.assert]]
kind = "consistent"
filter = "kf"
"#;

const RECORDED: &str = r#"
name = "l1_recorded"
master_seed = 7
runs = 10
[model]
kind = "recorded"
states = ["x", "xdot", "y", "ydot", "z", "zdot"]
state_units = ["m", "m/s", "m", "m/s", "m", "m/s"]
measurements = ["x", "y", "z"]
dt_s = 0.1
steps = 50
[[scenarios]]
name = "hover"
[noise]
scales = [1.0, 2.0]
[[filters]]
label = "kf"
kind = "external"
[initial_estimate]
mode = "sampled"
[consistency]
alpha = 0.01
[[check.assert]]
kind = "consistent"
filter = "kf"
"#;

/// L1's study, its simulation and the recorded spec, in a temporary folder.
struct Setup {
    dir: tempfile::TempDir,
}

impl Setup {
    fn new() -> Self {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("l1.toml"), L1).unwrap();
        std::fs::write(dir.path().join("rec.toml"), RECORDED).unwrap();
        let p = |s: &str| dir.path().join(s);
        ok(kfmc()
            .args(["run", "-q", "--export-estimates", "--out"])
            .arg(p("run"))
            .arg(p("l1.toml")));
        ok(kfmc()
            .args(["simulate", "-q", "--out"])
            .arg(p("sim"))
            .arg(p("l1.toml")));
        std::fs::copy(p("run/estimates.parquet"), p("est.parquet")).unwrap();
        Setup { dir }
    }
    fn p(&self, s: &str) -> PathBuf {
        self.dir.path().join(s)
    }
    fn stamp(&self, truth: &Path, est: &Path) {
        ok(kfmc()
            .arg("stamp")
            .arg("--truth")
            .arg(truth)
            .arg("--spec")
            .arg(self.p("rec.toml"))
            .arg(est));
    }
    /// `kfmc check` of the recorded spec: (exit code, stdout, stderr).
    fn check(&self, truth: &Path, est: &Path, out: &str) -> (i32, String, String) {
        let o = kfmc()
            .args(["check", "-q", "--force"])
            .arg(self.p("rec.toml"))
            .arg("--truth")
            .arg(truth)
            .arg("--estimates")
            .arg(est)
            .arg("--out")
            .arg(self.p(out))
            .output()
            .unwrap();
        (
            o.status.code().unwrap_or(-1),
            String::from_utf8_lossy(&o.stdout).into(),
            String::from_utf8_lossy(&o.stderr).into(),
        )
    }
    fn score(&self, truth: &Path, est: &Path, out: &str) -> std::process::Output {
        kfmc()
            .args(["score", "-q", "--force", "--truth"])
            .arg(truth)
            .arg("--spec")
            .arg(self.p("rec.toml"))
            .arg("--estimates")
            .arg(est)
            .arg("--out")
            .arg(self.p(out))
            .output()
            .unwrap()
    }
}

/// Float columns of two tables, bit for bit, except the variant keys (an external filter
/// without variants has null multipliers where kfmc's own has 1).
fn assert_same_numbers(a: &DataFrame, b: &DataFrame, table: &str) {
    assert_eq!(a.shape(), b.shape(), "{table}");
    for c in a.columns() {
        let name = c.name().as_str();
        if matches!(name, "q_scale" | "r_scale") || !c.dtype().is_float() {
            continue;
        }
        let x = c.cast(&DataType::Float64).unwrap();
        let y = b.column(name).unwrap().cast(&DataType::Float64).unwrap();
        let (x, y) = (x.f64().unwrap(), y.f64().unwrap());
        for i in 0..x.len() {
            let (u, v) = (x.get(i), y.get(i));
            let same = match (u, v) {
                (Some(u), Some(v)) => u.to_bits() == v.to_bits() || (u.is_nan() && v.is_nan()),
                (None, None) => true,
                _ => false,
            };
            assert!(same, "{table}.{name} row {i}: study {u:?}, recorded {v:?}");
        }
    }
}

#[test]
fn a_kfmc_simulation_rejudged_as_recorded_gives_the_study_s_own_numbers() {
    let s = Setup::new();
    let (truth, est) = (s.p("sim/truth.parquet"), s.p("est.parquet"));
    s.stamp(&truth, &est);
    let o = s.score(&truth, &est, "score");
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    for table in ["runs", "steps", "summary", "consistency"] {
        let a = read(&s.p(&format!("run/{table}.parquet")));
        let b = read(&s.p(&format!("score/{table}.parquet")));
        assert_same_numbers(&a, &b, table);
    }
    // The same verdict, through `kfmc check`, with the same Bonferroni p-values.
    let study = kfmc()
        .args(["check", "-q", "--out"])
        .arg(s.p("check0"))
        .arg(s.p("l1.toml"))
        .output()
        .unwrap();
    let (code, out, err) = s.check(&truth, &est, "check1");
    assert_eq!(study.status.code(), Some(0));
    assert_eq!(code, 0, "{out}{err}");
    let p_values = |text: &str| -> Vec<String> {
        text.lines()
            .filter_map(|l| l.split("p-value").nth(1).map(str::to_string))
            .collect()
    };
    let theirs = p_values(&String::from_utf8_lossy(&study.stdout));
    assert_eq!(theirs.len(), 2, "{theirs:?}");
    assert_eq!(theirs, p_values(&out));
}

fn truth_keys() -> RecordedKeys {
    RecordedKeys {
        table: "truth".into(),
        scenarios: vec![("hover".into(), 50)],
        noise_scales: vec![1.0, 2.0],
        runs: 10,
        groups: vec![ValueGroup::truth(&["x", "xdot", "y", "ydot", "z", "zdot"])],
        ignored_prefixes: vec!["world_".into()],
    }
}

#[test]
fn the_content_hash_ignores_row_order_and_encoding_but_not_one_value() {
    let dir = tempfile::tempdir().unwrap();
    // A truth whose values are exact in float32, so a float32 copy holds the same numbers.
    let n = 2 * 10 * 51;
    let keys = truth_keys();
    let mut cols: Vec<Column> = vec![
        Column::new(
            "scenario".into(),
            (0..n).map(|_| "hover").collect::<Vec<_>>(),
        ),
        Column::new(
            "noise_scale".into(),
            (0..n).map(|i| [1.0, 2.0][i / 510]).collect::<Vec<f64>>(),
        ),
        Column::new(
            "run".into(),
            (0..n).map(|i| (i / 51 % 10) as i64).collect::<Vec<_>>(),
        ),
        Column::new(
            "step".into(),
            (0..n).map(|i| (i % 51) as i32).collect::<Vec<_>>(),
        ),
        Column::new(
            "t".into(),
            (0..n).map(|i| (i % 51) as f64 * 0.1).collect::<Vec<_>>(),
        ),
    ];
    for (j, q) in keys.groups[0].names.iter().enumerate() {
        cols.push(Column::new(
            format!("truth_{q}").into(),
            (0..n)
                .map(|i| ((i * 7 + j * 13) % 97) as f64 * 0.125 - 3.0)
                .collect::<Vec<f64>>(),
        ));
    }
    let df = DataFrame::new(n, cols).unwrap();
    let hash = |files: &[PathBuf], frames: &[(String, DataFrame)]| {
        RecordedTable::read(truth_keys(), files, frames)
            .unwrap()
            .content_hash()
    };
    let plain = dir.path().join("plain.parquet");
    write_with(&df, &plain, &[]);
    let base = hash(&[plain], &[]);
    // Rows reversed, float32 values, small row groups, no compression.
    let mut other = df.reverse();
    for q in &keys.groups[0].names {
        let c = other
            .column(&format!("truth_{q}"))
            .unwrap()
            .cast(&DataType::Float32)
            .unwrap();
        other.with_column(c).unwrap();
    }
    let f32_path = dir.path().join("f32.parquet");
    ParquetWriter::new(std::fs::File::create(&f32_path).unwrap())
        .with_compression(ParquetCompression::Uncompressed)
        .with_row_group_size(Some(97))
        .finish(&mut other.clone())
        .unwrap();
    assert_eq!(hash(&[f32_path], &[]), base);
    // The same rows in memory, and split across two tables in another order.
    assert_eq!(hash(&[], &[("<truth>".into(), other.clone())]), base);
    let (a, b) = (other.slice(0, 300), other.slice(300, n));
    assert_eq!(hash(&[], &[("<b>".into(), b), ("<a>".into(), a)]), base);
    // One value changed by one unit in the last place: another hash.
    let mut bumped = df.clone();
    let mut v: Vec<f64> = bumped
        .column("truth_ydot")
        .unwrap()
        .f64()
        .unwrap()
        .into_no_null_iter()
        .collect();
    v[777] = f64::from_bits(v[777].to_bits() + 1);
    bumped
        .with_column(Column::new("truth_ydot".into(), v))
        .unwrap();
    assert_ne!(hash(&[], &[("<bumped>".into(), bumped)]), base);
    // A `world_` column is not part of the truth that is judged.
    let mut with_world = df.clone();
    with_world
        .with_column(Column::new("world_bias".into(), vec![0.5f64; n]))
        .unwrap();
    assert_eq!(hash(&[], &[("<world>".into(), with_world)]), base);
}

#[test]
fn estimates_made_on_another_truth_are_refused() {
    let s = Setup::new();
    let (truth, est) = (s.p("sim/truth.parquet"), s.p("est.parquet"));
    s.stamp(&truth, &est);
    // The same truth with one value changed is another world.
    let mut df = read(&truth);
    let mut v: Vec<f64> = df
        .column("truth_x")
        .unwrap()
        .f64()
        .unwrap()
        .into_no_null_iter()
        .collect();
    v[5] += 1e-9;
    df.with_column(Column::new("truth_x".into(), v)).unwrap();
    let other = s.p("other_truth.parquet");
    write_with(&df, &other, &[]);
    let o = s.score(&other, &est, "foreign");
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(
        err.contains("est.parquet") && err.contains("made on another simulation"),
        "{err}"
    );
    // kfmc's own stamp (of L1's simulated world) is another world too.
    let o = s.score(&truth, &s.p("run/estimates.parquet"), "own_stamp");
    assert_eq!(o.status.code(), Some(1));
    // An unstamped file is scored with a warning, refused by check.
    let plain = s.p("plain.parquet");
    write_with(&read(&est), &plain, &[]);
    let o = s.score(&truth, &plain, "unstamped");
    assert!(o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("carries no world stamp"));
    let (code, _, err) = s.check(&truth, &plain, "unstamped_check");
    assert_eq!(code, 1, "{err}");
}

/// The rows of `df` where `keep(run, step, noise_scale)` holds.
fn rows_where(df: &DataFrame, keep: impl Fn(i64, i64, f64) -> bool) -> DataFrame {
    let (run, step) = (i64s(df, "run"), i64s(df, "step"));
    let noise = crate::common::f64s_or_nan(df, "noise_scale");
    let mask: BooleanChunked = (0..df.height())
        .map(|i| Some(keep(run[i], step[i], noise[i])))
        .collect();
    df.filter(&mask).unwrap()
}

/// `df` without the rows of `run` at noise scale 1.
fn without_run(df: &DataFrame, run: i64) -> DataFrame {
    rows_where(df, |r, _, ns| r != run || ns != 1.0)
}

#[test]
fn missing_runs_make_the_check_incomplete() {
    let s = Setup::new();
    let (truth, est) = (s.p("sim/truth.parquet"), s.p("est.parquet"));
    s.stamp(&truth, &est);
    // A run the estimates leave out: incomplete, exit 4.
    let short_est = s.p("short_est.parquet");
    let meta = crate::common::stamp_of(&est);
    write_with(&without_run(&read(&est), 3), &short_est, &meta);
    let (code, out, err) = s.check(&truth, &short_est, "c1");
    assert_eq!(code, 4, "{out}{err}");
    assert!(
        out.contains("INCOMPLETE") || out.contains("incomplete"),
        "{out}"
    );
    // A run the truth leaves out (and so do its estimates): incomplete too.
    let short_truth = s.p("short_truth.parquet");
    write_with(&without_run(&read(&truth), 3), &short_truth, &[]);
    s.stamp(&short_truth, &short_est);
    let (code, out, err) = s.check(&short_truth, &short_est, "c2");
    assert_eq!(code, 4, "{out}{err}");
    assert!(
        err.contains("the truth leaves 1 of the spec's 20 runs out"),
        "{err}"
    );
    // Estimates of a run the truth leaves out have nothing to be judged against.
    let full = s.p("full_est.parquet");
    std::fs::copy(&est, &full).unwrap();
    s.stamp(&short_truth, &full);
    let (code, _, err) = s.check(&short_truth, &full, "c3");
    assert_eq!(code, 1, "{err}");
    assert!(err.contains("which the truth table leaves out"), "{err}");
    // `kfmc run` on a recorded spec says where to go.
    let o = kfmc()
        .args(["run", "-q"])
        .arg(s.p("rec.toml"))
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_ne!(o.status.code(), Some(0));
    assert!(
        err.contains("cannot simulate") && err.contains("kfmc score --truth"),
        "{err}"
    );
}

#[test]
fn bad_truth_columns_are_named() {
    let s = Setup::new();
    let (truth, est) = (s.p("sim/truth.parquet"), s.p("est.parquet"));
    let df = read(&truth);
    let cases: Vec<(&str, DataFrame, &str)> = vec![
        (
            "no_z",
            df.drop("truth_z").unwrap(),
            "missing column `truth_z`: the spec declares the quantity `z`",
        ),
        (
            "extra",
            {
                let mut d = df.clone();
                d.with_column(Column::new("truth_w".into(), vec![0.0f64; d.height()]))
                    .unwrap();
                d
            },
            "unexpected column `truth_w`: the spec declares no quantity `w`",
        ),
        (
            "text",
            {
                let mut d = df.clone();
                d.with_column(Column::new("truth_y".into(), vec!["1"; d.height()]))
                    .unwrap();
                d
            },
            "column `truth_y` holds",
        ),
        (
            "scenario",
            {
                let mut d = df.clone();
                d.with_column(Column::new("scenario".into(), vec!["climb"; d.height()]))
                    .unwrap();
                d
            },
            "`climb` is not a scenario of the spec",
        ),
        (
            "partial",
            rows_where(&df, |r, k, _| r != 2 || k != 17),
            "run = 2: no row for step 17",
        ),
        (
            "null",
            {
                let mut d = df.clone();
                let v: Vec<Option<f64>> =
                    (0..d.height()).map(|i| (i != 40).then_some(0.0)).collect();
                d.with_column(Column::new("truth_xdot".into(), v)).unwrap();
                d
            },
            "column `truth_xdot`: null",
        ),
    ];
    for (name, bad, message) in cases {
        let path = s.p(&format!("{name}.parquet"));
        write_with(&bad, &path, &[]);
        let o = s.score(&path, &est, name);
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(1), "{name}: {err}");
        assert!(
            err.contains(&format!("{name}.parquet")) && err.contains(message),
            "{name}: {err}"
        );
    }
}
