//! `kfmc power`: rejection rates over independent replications.
//!
//! * The table is a function of the spec, R and the base seed: byte-identical on 1 and 2
//!   threads.
//! * Replication r is exactly the study `kfmc run --seed replication_seed(base, r)` runs: with
//!   R = 1 every statistic equals that run's consistency table.
//! * On L1 (30 runs × 50 steps, R = 30, base seed 5) Q × 2 is rejected by the verdict in 28 of
//!   30 replications, and the false alarms at the true Q stay within the binomial range of α.

use std::path::Path;

use crate::common::{kfmc, read, spec_in_tempdir};
use polars::prelude::*;

const SPEC: &str = r#"
name = "power_test"
master_seed = 5
runs = 30
[model]
kind = "linear_quadrotor"
sensor = "positions"
[[scenarios]]
name = "hover"
x0 = [1.0, 0.0, 1.0, 0.0, 1.0, 0.0]
duration_s = 5.0
[[filters]]
label = "kf"
kind = "ekf"
q_scale = [1.0, 2.0]
[initial_estimate]
mode = "sampled"
p0_std = 1.0
[consistency]
alpha = 0.05
"#;

fn power(spec: &Path, out: &Path, r: &str, threads: &str) {
    let o = kfmc()
        .args(["power", "-q", "-R", r, "--threads", threads, "--out"])
        .arg(out)
        .arg(spec)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
}

#[test]
fn power_is_deterministic_and_detects_q_times_2() {
    let (dir, spec) = spec_in_tempdir(SPEC);
    let (a, b) = (dir.path().join("a"), dir.path().join("b"));
    power(&spec, &a, "30", "1");
    power(&spec, &b, "30", "2");
    assert!(
        std::fs::read(a.join("power.parquet")).unwrap()
            == std::fs::read(b.join("power.parquet")).unwrap(),
        "power.parquet depends on the thread count"
    );
    let df = read(&a.join("power.parquet"));
    let row = |q: f64, test: &str| {
        let m = df.column("q_scale").unwrap().f64().unwrap().equal(q)
            & df.column("test").unwrap().str().unwrap().equal(test);
        let r = df.filter(&m).unwrap();
        assert_eq!(r.height(), 1);
        let i = |c: &str| r.column(c).unwrap().i64().unwrap().get(0).unwrap();
        (i("replications"), i("rejections"))
    };
    // Q × 2 on 30 runs of 50 steps: the verdict's power is about 0.9 (28 of 30 here); fewer
    // than 25 would put the Clopper–Pearson interval's top below 0.93.
    let (n, detected) = row(2.0, "verdict");
    assert_eq!(n, 30);
    assert!(detected >= 25, "Q × 2 rejected in only {detected} of 30");
    let (n, false_alarms) = row(1.0, "verdict");
    assert_eq!(n, 30);
    // P(X ≥ 7) < 0.001 for X ~ Bin(30, 0.05): a correct filter rejected this often would be a
    // broken test.
    assert!(false_alarms <= 6, "{false_alarms} false alarms in 30");
}

#[test]
fn a_replication_is_the_run_of_its_seed() {
    let (dir, spec) = spec_in_tempdir(SPEC);
    let out = dir.path().join("p");
    power(&spec, &out, "1", "0");
    let seed = kfmc::power::replication_seed(5, 0);
    let run = dir.path().join("run");
    let o = kfmc()
        .args(["run", "-q", "--seed", &seed.to_string(), "--out"])
        .arg(&run)
        .arg(&spec)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let p = read(&out.join("power.parquet"));
    let c = read(&run.join("consistency.parquet"));
    assert_eq!(p.height(), c.height());
    let (pm, cs) = (
        p.column("statistic_mean").unwrap().f64().unwrap(),
        c.column("statistic").unwrap().f64().unwrap(),
    );
    let (rej, pass) = (
        p.column("rejections").unwrap().i64().unwrap(),
        c.column("pass").unwrap().bool().unwrap(),
    );
    for i in 0..p.height() {
        assert_eq!(pm.get(i), cs.get(i), "row {i}");
        assert_eq!(rej.get(i) == Some(1), pass.get(i) == Some(false), "row {i}");
    }
}

/// `kfmc check` judges `rejection_rate` assertions on `kfmc power`'s table: the verdict's
/// power against Q × 2 (28 of 30 replications above) passes `min = 0.8`; its false-alarm rate
/// at the true Q passes `max = 0.2`; a negative control asking for power ≥ 0.5 at the true Q
/// must fail, and does; without replications the spec is refused at `check.replications`.
#[test]
fn check_asserts_on_rejection_rates() {
    let gate = |asserts: &str, replications: Option<usize>| {
        let text = format!(
            "{SPEC}\n[check]\n{}{asserts}",
            replications.map_or(String::new(), |r| format!("replications = {r}\n"))
        );
        let (dir, spec) = spec_in_tempdir(&text);
        let junit = dir.path().join("junit.xml");
        let o = kfmc()
            .args(["check", "-q", "--out"])
            .arg(dir.path().join("out"))
            .arg("--junit")
            .arg(&junit)
            .arg(&spec)
            .output()
            .unwrap();
        let xml = std::fs::read_to_string(&junit).unwrap_or_default();
        (o, xml, dir)
    };
    let passing = r#"
[[check.assert]]
kind = "rejection_rate"
filter = "kf"
q_scale = 2.0
min = 0.8
[[check.assert]]
kind = "rejection_rate"
q_scale = 1.0
max = 0.2
[[check.assert]]
kind = "rejection_rate"
q_scale = 1.0
min = 0.5
expect = "fail"
"#;
    let (o, xml, dir) = gate(passing, Some(30));
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert_eq!(
        o.status.code(),
        Some(0),
        "{stdout}{}",
        String::from_utf8_lossy(&o.stderr)
    );
    assert!(stdout.contains("of 30 replications"), "{stdout}");
    assert!(xml.contains("negative_control:rejection_rate["), "{xml}");
    assert!(dir.path().join("out/power/power.parquet").exists());

    // The same power demanded at the true Q is a failing gate (exit 3).
    let failing = "[[check.assert]]\nkind = \"rejection_rate\"\nq_scale = 1.0\nmin = 0.5\n";
    let (o, xml, _d) = gate(failing, Some(30));
    assert_eq!(
        o.status.code(),
        Some(3),
        "{}",
        String::from_utf8_lossy(&o.stdout)
    );
    assert!(xml.contains("<failure"), "{xml}");

    let (o, _, _d) = gate(failing, None);
    assert_eq!(o.status.code(), Some(2));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("check.replications"), "{err}");

    // A rate outside [0, 1] and a min on another kind are named by key.
    let bad = "[[check.assert]]\nkind = \"rejection_rate\"\nmax = 1.5\n[[check.assert]]\nkind = \"consistent\"\nmin = 0.1\n";
    let (o, _, _d) = gate(bad, Some(3));
    assert_eq!(o.status.code(), Some(2));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("check.assert[0].max"), "{err}");
    assert!(err.contains("check.assert[1].min"), "{err}");
}

fn power_with(spec: &Path, out: &Path, args: &[&str]) {
    let o = kfmc()
        .args(["power", "-q", "--out"])
        .arg(out)
        .args(args)
        .arg(spec)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
}

/// A verdict row of power.parquet: (q_scale, sequential) → (replications, rejections,
/// runs_used_mean).
type VerdictRow = ((f64, bool), (i64, i64, f64));

fn verdicts(path: &Path) -> Vec<VerdictRow> {
    let df = read(path);
    let m = df.column("test").unwrap().str().unwrap().equal("verdict")
        & df.column("runs").unwrap().i64().unwrap().equal(30);
    let r = df.filter(&m).unwrap();
    let q = r.column("q_scale").unwrap().f64().unwrap().clone();
    let s = r.column("sequential").unwrap().bool().unwrap().clone();
    let n = r.column("replications").unwrap().i64().unwrap().clone();
    let k = r.column("rejections").unwrap().i64().unwrap().clone();
    let u = r.column("runs_used_mean").unwrap().f64().unwrap().clone();
    (0..r.height())
        .map(|i| {
            (
                (q.get(i).unwrap(), s.get(i).unwrap()),
                (n.get(i).unwrap(), k.get(i).unwrap(), u.get(i).unwrap()),
            )
        })
        .collect()
}

/// `kfmc power --sequential`: a gate of one look is the fixed-N verdict, replication by
/// replication (the same rejections); with ten looks the table is byte-identical on 1 and 2
/// threads, Q × 2 is still caught and the gate stops early on it, and the false alarms at the
/// true Q stay within the binomial range of α.
#[test]
fn a_sequential_gate_of_one_look_is_the_fixed_verdict_and_ten_looks_stop_early() {
    let (dir, spec) = spec_in_tempdir(SPEC);
    let one = dir.path().join("one");
    power_with(&spec, &one, &["-R", "30", "--sequential", "--looks", "1"]);
    let rows = verdicts(&one.join("power.parquet"));
    for q in [1.0, 2.0] {
        let get = |s: bool| rows.iter().find(|(k, _)| *k == (q, s)).unwrap().1;
        let (fixed, seq) = (get(false), get(true));
        assert_eq!(
            (fixed.0, fixed.1),
            (seq.0, seq.1),
            "Q × {q}: {fixed:?} vs {seq:?}"
        );
        assert_eq!(seq.2, 30.0);
    }

    let (a, b) = (dir.path().join("a"), dir.path().join("b"));
    let ten = ["-R", "30", "--sequential", "--looks", "10"];
    power_with(&spec, &a, &[&ten[..], &["--threads", "1"]].concat());
    power_with(&spec, &b, &[&ten[..], &["--threads", "2"]].concat());
    assert!(
        std::fs::read(a.join("power.parquet")).unwrap()
            == std::fs::read(b.join("power.parquet")).unwrap(),
        "the sequential power table depends on the thread count"
    );
    let rows = verdicts(&a.join("power.parquet"));
    let get = |q: f64| rows.iter().find(|(k, _)| *k == (q, true)).unwrap().1;
    let (n, detected, runs_used) = get(2.0);
    assert_eq!(n, 30);
    // The fixed verdict catches Q × 2 in about 28 of 30 (test above); O'Brien–Fleming
    // spending loses little power, and stops on average well before the 30th run.
    assert!(detected >= 24, "Q × 2 caught in only {detected} of 30");
    assert!(runs_used < 25.0, "Q × 2: {runs_used} runs used on average");
    let (n, false_alarms, runs_used) = get(1.0);
    assert_eq!(n, 30);
    assert!(false_alarms <= 6, "{false_alarms} false alarms in 30");
    // A correct filter rarely stops early without futility bounds.
    assert!(runs_used > 25.0, "{runs_used}");
}

#[test]
fn bad_sequential_settings_are_usage_errors() {
    let (dir, spec) = spec_in_tempdir(SPEC);
    for args in [
        &["--looks", "10,20"][..],
        &["--looks", "20,10,30"],
        &["--looks", "0"],
        &["--looks", "1,30"],
        &["--futility", "1.5"],
    ] {
        let o = kfmc()
            .args(["power", "-q", "-R", "2", "--sequential", "--out"])
            .arg(dir.path().join("x"))
            .args(args)
            .arg(&spec)
            .output()
            .unwrap();
        assert_eq!(
            o.status.code(),
            Some(2),
            "{args:?}: {}",
            String::from_utf8_lossy(&o.stderr)
        );
    }
    // The gate's settings need --sequential (clap refuses them alone).
    let o = kfmc()
        .args(["power", "-q", "-R", "2", "--looks", "5"])
        .arg(&spec)
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(2));
}

/// `kfmc power --target-power P --against q_scale=X`: the power curve's point at N runs is the
/// power study of an N-run spec (the same first N runs of every replication), and the answer
/// printed is the first run count whose rate reaches P.
#[test]
fn target_power_reads_a_curve_of_prefix_studies() {
    let (dir, spec) = spec_in_tempdir(SPEC);
    let out = dir.path().join("curve");
    let o = kfmc()
        .args(["power", "-q", "-R", "30", "--target-power", "0.8"])
        .args(["--against", "q_scale=2", "--out"])
        .arg(&out)
        .arg(&spec)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let text = String::from_utf8_lossy(&o.stdout).to_string();

    let curve = read(&out.join("power.parquet"));
    let verdict_at = |df: &DataFrame, q: f64, n: i64| {
        let m = df.column("test").unwrap().str().unwrap().equal("verdict")
            & df.column("q_scale").unwrap().f64().unwrap().equal(q)
            & df.column("runs").unwrap().i64().unwrap().equal(n);
        let r = df.filter(&m).unwrap();
        assert_eq!(r.height(), 1, "q {q}, N {n}");
        (
            r.column("rejections")
                .unwrap()
                .i64()
                .unwrap()
                .get(0)
                .unwrap(),
            r.column("statistic_mean").unwrap().f64().unwrap().get(0),
        )
    };
    // The 12-run point equals a 12-run study's power, bit for bit.
    let short = dir.path().join("spec12.toml");
    std::fs::write(&short, SPEC.replace("runs = 30", "runs = 12")).unwrap();
    let out12 = dir.path().join("p12");
    power(&short, &out12, "30", "0");
    let direct = read(&out12.join("power.parquet"));
    for q in [1.0, 2.0] {
        assert_eq!(
            verdict_at(&curve, q, 12),
            verdict_at(&direct, q, 12),
            "Q × {q}"
        );
    }
    // The printed answer is the first point of the curve at or above 0.8.
    let first = (3..=30)
        .step_by(3)
        .find(|&n| verdict_at(&curve, 2.0, n).0 as f64 / 30.0 >= 0.8)
        .expect("Q × 2 reaches power 0.8 by 30 runs");
    assert!(
        text.contains(&format!("smallest N with power ≥ 0.8: {first} ")),
        "{text}"
    );
}

/// A power request that cannot be answered is refused before any replication runs (exit 2,
/// nothing written): no replications, a target outside (0, 1), an `--against` that is not
/// KEY=VALUE, and a variant the spec's filters do not have (which used to surface only after
/// every replication had run).
#[test]
fn unanswerable_power_requests_are_refused_before_running() {
    let (dir, spec) = spec_in_tempdir(SPEC);
    let cases: [(&[&str], &str); 4] = [
        (&["-R", "0"], "replications: must be at least 1"),
        (
            &["-R", "5", "--target-power", "1.2", "--against", "q_scale=2"],
            "--target-power",
        ),
        (
            &["-R", "5", "--target-power", "0.8", "--against", "q=2"],
            "unknown key `q`",
        ),
        (
            &["-R", "5", "--target-power", "0.8", "--against", "q_scale=3"],
            "no filter variant has q_scale=3",
        ),
    ];
    for (i, (args, message)) in cases.into_iter().enumerate() {
        let out = dir.path().join(format!("p{i}"));
        let o = kfmc()
            .args(["power", "-q", "--out"])
            .arg(&out)
            .args(args)
            .arg(&spec)
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(2), "{args:?}: {err}");
        assert!(err.contains(message), "{args:?}: {err}");
        assert!(!out.exists(), "{args:?} wrote {}", out.display());
    }
}
