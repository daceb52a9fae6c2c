//! `kfmc power`: rejection rates over independent replications.
//!
//! * The table is a function of the spec, R and the base seed: byte-identical on 1 and 2
//!   threads.
//! * Replication r is exactly the study `kfmc run --seed replication_seed(base, r)` runs: with
//!   R = 1 every statistic equals that run's consistency table.
//! * On L1 (30 runs × 50 steps, R = 30, base seed 5) Q × 2 is rejected by the verdict in 28 of
//!   30 replications, and the false alarms at the true Q stay within the binomial range of α.

mod common;

use std::path::Path;

use common::{kfmc, spec_in_tempdir};
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

fn read(path: &Path) -> DataFrame {
    ParquetReader::new(std::fs::File::open(path).unwrap())
        .finish()
        .unwrap()
}

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
