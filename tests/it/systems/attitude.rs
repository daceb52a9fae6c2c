//! Attitude errors on SO(3): the drone's attitude scored as a rotation error
//! against three Euler-angle differences next to the singularity at pitch 90°, and the
//! estimates exchange carrying a rotation as a quaternion or as Euler angles.

use std::fs;
use std::path::Path;

use kfmc::experiment;
use kfmc::output::table::read;
use kfmc::power::clopper_pearson;
use kfmc::runner::NullObserver;
use kfmc::study::{ExecOptions, run};
use polars::prelude::*;

use crate::common::{f64s_or_nan, kfmc, ok, stamp_of, write_with};

/// The drone nose-up at pitch 89.9° with a roll swing about its upward body axis: the full
/// world of `drone_principled` (specific force, biases, drifts, latency, delay), 10 s.
const GIMBAL: &str = r#"
runs = 30
[model]
kind = "drone"
imu_output = "specific_force"
attitude_error = "ERROR"
[[scenarios]]
name = "nose_up"
base = "sinusoidal"
duration_s = 10.0
attitude_offset_deg = [0.0, 89.9, 0.0]
attitude_deg = [30.0, 0.0, 0.0]
attitude_period_s = [8.0, 1.0, 1.0]
[[filters]]
label = "error_state"
kind = "error_state"
[initial_estimate]
mode = "sampled"
[consistency]
alpha = 0.05
"#;

fn study(spec: &str) -> tempfile::TempDir {
    let tmp = tempfile::tempdir().unwrap();
    let mut plan = experiment::parse_with(spec, Path::new("drone.toml"), &kfmc::systems::builtin())
        .unwrap_or_else(|e| panic!("{e:?}"));
    plan.output = tmp.path().to_path_buf();
    run(
        &plan,
        &ExecOptions {
            threads: 2,
            ..Default::default()
        },
        &NullObserver,
    )
    .unwrap();
    tmp
}

/// One study's verdict on the error-state filter: whether the t-test of the runs' average
/// NEES against 9 accepts (runs are independent, so it is calibrated), the time-averaged
/// ANEES, and the fraction of steps whose ANEES lies in its two-sided 95 % band.
struct Verdict {
    accepted: bool,
    anees: f64,
    in_band: f64,
}

fn verdict(dir: &Path) -> Verdict {
    let cons = read(&dir.join("consistency.parquet")).unwrap();
    let t = cons.column("test").unwrap().str().unwrap().clone();
    let p = cons.column("pass").unwrap().bool().unwrap().clone();
    let row = (0..cons.height())
        .find(|&i| t.get(i) == Some("nees_run_average_t"))
        .expect("nees_run_average_t row");
    let steps = read(&dir.join("steps.parquet")).unwrap();
    let step = steps.column("step").unwrap().i64().unwrap().clone();
    let inside = steps
        .column("anees_inside")
        .unwrap()
        .bool()
        .unwrap()
        .clone();
    let anees = steps.column("anees").unwrap().f64().unwrap().clone();
    let (mut n, mut k, mut sum) = (0usize, 0usize, 0.0);
    for i in 0..steps.height() {
        if step.get(i).unwrap() >= 1 {
            n += 1;
            k += inside.get(i).unwrap_or(false) as usize;
            sum += anees.get(i).unwrap_or(f64::NAN);
        }
    }
    Verdict {
        accepted: p.get(row).unwrap_or(false),
        anees: sum / n as f64,
        in_band: k as f64 / n as f64,
    }
}

#[test]
fn near_pitch_90_euler_nees_explodes_and_the_rotation_nees_stays_in_band() {
    // The same error-state filter on the same runs, scored two ways, over independent
    // replications (master seeds 9001..=9012, 30 runs each). A replication "stays in band"
    // when the calibrated t-test of the runs' average NEES accepts at α = 0.05: a consistent
    // filter does so with probability 0.95 per replication.
    //
    // Tolerances: with the rotation error, at least 10 of 12 replications must accept (a
    // consistent filter fails this with probability 1 − P(Bin(12, 0.95) ≥ 10) ≈ 0.02); with
    // Euler-angle errors at most 1 of 12 may accept, and its time-averaged ANEES must exceed
    // 3 × 9 in every replication.
    let seeds: Vec<u64> = (9001..=9012).collect();
    let (mut rot_ok, mut euler_ok) = (0u64, 0u64);
    let mut euler_min_anees = f64::INFINITY;
    for &seed in &seeds {
        let mut v = Vec::new();
        for error in ["rotation", "euler"] {
            let spec = format!("master_seed = {seed}\n{}", GIMBAL.replace("ERROR", error));
            let dir = study(&spec);
            v.push(verdict(dir.path()));
        }
        eprintln!(
            "seed {seed}: rotation ANEES {:.2} ({:.1} % of steps in band, {}), Euler ANEES {:.3e} ({:.1} % in band, {})",
            v[0].anees,
            100.0 * v[0].in_band,
            if v[0].accepted {
                "accepted"
            } else {
                "rejected"
            },
            v[1].anees,
            100.0 * v[1].in_band,
            if v[1].accepted {
                "accepted"
            } else {
                "rejected"
            },
        );
        rot_ok += v[0].accepted as u64;
        euler_ok += v[1].accepted as u64;
        euler_min_anees = euler_min_anees.min(v[1].anees);
    }
    let n = seeds.len() as u64;
    let (rl, rh) = clopper_pearson(rot_ok, n);
    let (el, eh) = clopper_pearson(euler_ok, n);
    eprintln!(
        "accepted: rotation {rot_ok}/{n} [{rl:.3}, {rh:.3}], Euler {euler_ok}/{n} [{el:.3}, {eh:.3}] (Clopper–Pearson 95 %); smallest Euler ANEES {euler_min_anees:.3e}"
    );
    assert!(rot_ok >= 10, "rotation error accepted in {rot_ok}/{n}");
    assert!(
        euler_ok <= 1,
        "Euler-angle error accepted in {euler_ok}/{n}"
    );
    assert!(
        euler_min_anees > 27.0,
        "Euler-angle ANEES {euler_min_anees} in some replication"
    );
}

#[test]
fn right_and_left_rotation_errors_give_the_same_nees() {
    // P_left = R̂ P_right R̂ᵀ and e_left = R̂ e_right: the NEES is the same number, and the
    // rotation's RMSE over its three components (|e| is invariant) is too.
    let tables: Vec<DataFrame> = ["rotation", "rotation_left"]
        .iter()
        .map(|error| {
            let spec = format!(
                "master_seed = 5\n{}",
                GIMBAL
                    .replace("ERROR", error)
                    .replace("runs = 30", "runs = 4")
                    .replace("duration_s = 10.0", "duration_s = 2.0")
            );
            let dir = study(&spec);
            read(&dir.path().join("runs.parquet")).unwrap()
        })
        .collect();
    let col = |df: &DataFrame, c: &str| -> Vec<f64> {
        df.column(c)
            .unwrap()
            .f64()
            .unwrap()
            .iter()
            .map(|v| v.unwrap())
            .collect()
    };
    let (r, l) = (col(&tables[0], "nees_mean"), col(&tables[1], "nees_mean"));
    for (a, b) in r.iter().zip(&l) {
        assert!((a - b).abs() <= 1e-9 * a.abs(), "NEES {a} right, {b} left");
    }
    let norm = |df: &DataFrame| -> Vec<f64> {
        let (x, y, z) = (
            col(df, "rmse_roll"),
            col(df, "rmse_pitch"),
            col(df, "rmse_yaw"),
        );
        (0..x.len())
            .map(|i| x[i] * x[i] + y[i] * y[i] + z[i] * z[i])
            .collect()
    };
    for (a, b) in norm(&tables[0]).iter().zip(&norm(&tables[1])) {
        assert!((a - b).abs() <= 1e-9 * a.abs(), "|e|² {a} right, {b} left");
    }
    // The position and velocity columns do not depend on the attitude convention.
    assert_eq!(col(&tables[0], "rmse_px"), col(&tables[1], "rmse_px"));
}

const EXCHANGE: &str = r#"
name = "drone_exchange"
master_seed = 12
runs = 3
[model]
kind = "drone"
imu_output = "specific_force"
ERRORLINE
[[scenarios]]
name = "maneuver"
duration_s = 2.0
[[filters]]
label = "ekf9"
kind = "KIND"
[initial_estimate]
mode = "sampled"
[consistency]
alpha = 0.05
"#;

#[test]
fn the_exchange_carries_a_rotation_as_a_quaternion_or_as_euler_angles() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let spec = |error: &str, kind: &str| EXCHANGE.replace("ERRORLINE", error).replace("KIND", kind);
    // The rotation study (the default convention) and the same world scored with Euler
    // angles, each with its estimates exported.
    fs::write(dir.join("run.toml"), spec("", "ekf9")).unwrap();
    fs::write(
        dir.join("euler.toml"),
        spec("attitude_error = \"euler\"", "ekf9"),
    )
    .unwrap();
    fs::write(dir.join("ext.toml"), spec("", "external")).unwrap();
    for (s, out) in [("run.toml", "run"), ("euler.toml", "euler")] {
        ok(kfmc()
            .args(["run", "-q", "--export-estimates", "--out"])
            .arg(dir.join(out))
            .arg(dir.join(s)));
    }
    ok(kfmc()
        .args(["simulate", "-q", "--out"])
        .arg(dir.join("sim"))
        .arg(dir.join("ext.toml")));

    // kfmc writes the rotation as a quaternion, and `kfmc schema` says so.
    let quat = read(&dir.join("run/estimates.parquet")).unwrap();
    let names: Vec<String> = quat
        .get_column_names()
        .iter()
        .map(|s| s.to_string())
        .collect();
    for c in [
        "quat_roll_pitch_yaw_w",
        "quat_roll_pitch_yaw_z",
        "P_roll_roll",
    ] {
        assert!(names.contains(&c.to_string()), "{c} in {names:?}");
    }
    assert!(!names.contains(&"est_roll".to_string()));
    let o = kfmc()
        .args(["schema", "estimates"])
        .arg(dir.join("run.toml"))
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(text.contains("quat_roll_pitch_yaw_w"), "{text}");
    assert!(text.contains("log(R̂ᵀR)"), "{text}");
    // The unit quaternion (w ≥ 0) of every row.
    let w = f64s_or_nan(&quat, "quat_roll_pitch_yaw_w");
    let x = f64s_or_nan(&quat, "quat_roll_pitch_yaw_x");
    let y = f64s_or_nan(&quat, "quat_roll_pitch_yaw_y");
    let z = f64s_or_nan(&quat, "quat_roll_pitch_yaw_z");
    for i in 0..w.len() {
        let n = w[i] * w[i] + x[i] * x[i] + y[i] * y[i] + z[i] * z[i];
        assert!(
            (n - 1.0).abs() < 1e-12 && w[i] >= 0.0,
            "row {i}: |q|² = {n}"
        );
    }

    // The drone's sequential updates report no joint S, so the optional innovation columns
    // (null S where ν reported) are left out of the files scored here.
    let without_innovations = |df: &DataFrame| {
        let keep: Vec<String> = df
            .get_column_names()
            .iter()
            .map(|s| s.to_string())
            .filter(|c| !c.starts_with("nu_") && !c.starts_with("S_"))
            .collect();
        df.select(keep).unwrap()
    };
    // Scored back, the quaternion file gives the rotation study's numbers (the quaternion's
    // Euler angles agree with the trace's to rounding).
    let stamp = stamp_of(&dir.join("run/estimates.parquet"));
    let quat = without_innovations(&quat);
    write_with(&quat, &dir.join("quat.parquet"), &stamp);
    // An Euler-angle file, as files were before rotations: the Euler study's estimates and
    // Euler-angle covariance, carrying this world's stamp as an outside writer would.
    let euler = without_innovations(&read(&dir.join("euler/estimates.parquet")).unwrap());
    assert!(
        euler
            .get_column_names()
            .iter()
            .any(|c| c.as_str() == "est_roll")
    );
    write_with(&euler, &dir.join("euler.parquet"), &stamp);
    let run = read(&dir.join("run/runs.parquet")).unwrap();
    for (file, tol) in [("quat.parquet", 1e-9), ("euler.parquet", 0.0)] {
        let out = dir.join(format!("score_{file}"));
        ok(kfmc()
            .args(["score", "-q"])
            .arg(dir.join("sim"))
            .arg("--out")
            .arg(&out)
            .arg("--estimates")
            .arg(dir.join(file)));
        let scored = read(&out.join("runs.parquet")).unwrap();
        for c in [
            "nees_mean",
            "rmse_px",
            "rmse_vz",
            "rmse_roll",
            "rmse_pitch",
            "rmse_yaw",
        ] {
            let (a, b) = (f64s_or_nan(&run, c), f64s_or_nan(&scored, c));
            assert_eq!(a.len(), b.len());
            for (p, q) in a.iter().zip(&b) {
                assert!(
                    (p - q).abs() <= tol * p.abs(),
                    "{file}: {c} {p} in the run, {q} scored"
                );
            }
        }
    }

    // A zero quaternion fails its run, naming the quaternion's columns; the batch completes.
    let mut zero = quat.clone();
    let (run_col, step_col) = (
        zero.column("run").unwrap().i64().unwrap().clone(),
        zero.column("step").unwrap().i64().unwrap().clone(),
    );
    let at = (0..zero.height())
        .find(|&i| run_col.get(i) == Some(1) && step_col.get(i) == Some(5))
        .unwrap();
    for c in ["w", "x", "y", "z"] {
        let name = format!("quat_roll_pitch_yaw_{c}");
        let mut v = f64s_or_nan(&zero, &name);
        v[at] = 0.0;
        zero.with_column(Column::new(name.into(), v)).unwrap();
    }
    write_with(&zero, &dir.join("zero.parquet"), &stamp);
    ok(kfmc()
        .args(["score", "-q"])
        .arg(dir.join("sim"))
        .arg("--out")
        .arg(dir.join("zero"))
        .arg("--estimates")
        .arg(dir.join("zero.parquet")));
    let runs = read(&dir.join("zero/runs.parquet")).unwrap();
    let detail = runs.column("status_detail").unwrap().str().unwrap().clone();
    let step = runs.column("status_step").unwrap().i64().unwrap().clone();
    let run_of = runs.column("run").unwrap().i64().unwrap().clone();
    for i in 0..runs.height() {
        if run_of.get(i) == Some(1) {
            assert_eq!(step.get(i), Some(5));
            let d = detail.get(i).unwrap_or("");
            assert!(d.contains("quaternion quat_roll_pitch_yaw_w"), "{d}");
        } else {
            assert_eq!(step.get(i), None, "run {:?}", run_of.get(i));
        }
    }

    // Both forms at once is refused, naming the columns.
    let mut both = quat.clone();
    both.with_column(Column::new("est_roll".into(), vec![0.0; quat.height()]))
        .unwrap();
    write_with(&both, &dir.join("both.parquet"), &stamp);
    let o = kfmc()
        .args(["score", "-q"])
        .arg(dir.join("sim"))
        .arg("--out")
        .arg(dir.join("both"))
        .arg("--estimates")
        .arg(dir.join("both.parquet"))
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success());
    assert!(
        err.contains("est_roll") && err.contains("quat_roll_pitch_yaw_w"),
        "{err}"
    );
}
