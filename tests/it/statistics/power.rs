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
