//! The drone system of seed 004: its world against hand calculations and the
//! seed's sensor tables, the principled EKF's consistency on a white-noise world, and
//! determinism.

use std::path::Path;

use kfmc::experiment;
use kfmc::output::table::read;
use kfmc::runner::NullObserver;
use kfmc::study::{ExecOptions, run};
use kfmc::system::world::World;
use kfmc::systems::drone::world::{DroneParams, DroneScenario, DroneWorld, ImuOutput, Route};
use kfmc::systems::drone::z;
use statrs::distribution::{ChiSquared, ContinuousCDF};

fn study(spec: &str, threads: usize) -> tempfile::TempDir {
    let tmp = tempfile::tempdir().unwrap();
    let mut plan = experiment::parse_with(spec, Path::new("drone.toml"), &kfmc::systems::builtin())
        .unwrap_or_else(|e| panic!("{e:?}"));
    plan.output = tmp.path().to_path_buf();
    run(
        &plan,
        &ExecOptions {
            threads,
            ..Default::default()
        },
        &NullObserver,
    )
    .unwrap();
    tmp
}

/// `(scenario, key) → value` of a table, for a key column and a value column.
fn lookup(dir: &Path, table: &str, key: &str, value: &str) -> Vec<(String, String, f64)> {
    let df = read(&dir.join(format!("{table}.parquet"))).unwrap();
    let s = df.column("scenario").unwrap().str().unwrap().clone();
    let k = df.column(key).unwrap().str().unwrap().clone();
    let v = df.column(value).unwrap().f64().unwrap().clone();
    (0..df.height())
        .map(|i| {
            (
                s.get(i).unwrap().to_string(),
                k.get(i).unwrap().to_string(),
                v.get(i).unwrap_or(f64::NAN),
            )
        })
        .collect()
}

fn find(rows: &[(String, String, f64)], s: &str, k: &str) -> f64 {
    rows.iter()
        .find(|r| r.0 == s && r.1 == k)
        .unwrap_or_else(|| panic!("no row {s}/{k}"))
        .2
}

fn world(params: DroneParams, route: &str) -> DroneWorld {
    DroneWorld {
        params,
        scenarios: vec![DroneScenario {
            name: route.into(),
            route: Route::builtin(route).unwrap(),
            steps: 2000,
            seed_table: 1,
        }],
    }
}

#[test]
fn sensor_white_noise_is_recovered_within_its_chi_square_interval() {
    // White noise only: each native GPS/barometer error is N(0, σ²), so Σe²/σ² ~ χ²(n).
    let params = DroneParams {
        accel_bias_std: [0.0; 3],
        accel_bias_rw: [0.0; 3],
        gyro_bias_std: [0.0; 3],
        gyro_bias_rw: [0.0; 3],
        gps_drift_std: [0.0; 3],
        gps_velocity_latency_s: 0.0,
        baro_drift_rw: 0.0,
        baro_delay_s: 0.0,
        ..DroneParams::default()
    };
    let w = world(params.clone(), "sinusoidal");
    let route = Route::builtin("sinusoidal").unwrap();
    let mut sums = [0.0f64; 7];
    let mut count = [0usize; 7];
    for run in 0..20u64 {
        let real = w.simulate(0, 1.0, 1000 + run);
        for (k, m) in real.measurements.iter().enumerate() {
            let st = route.at(k as f64 * params.dt_s);
            for (j, (i, truth)) in [
                (z::GPS_P, st.p[0]),
                (z::GPS_P + 2, st.p[2]),
                (z::GPS_V, st.v[0]),
                (z::GPS_V + 2, st.v[2]),
                (z::BARO, -st.p[2]),
            ]
            .into_iter()
            .enumerate()
            {
                if m.available.has(i) {
                    sums[j] += (m.z[i] - truth).powi(2);
                    count[j] += 1;
                }
            }
        }
    }
    let sigma = [1.09, 3.19, 0.147, 0.183, 1.06];
    for j in 0..5 {
        let n = count[j] as f64;
        let chi = ChiSquared::new(n).unwrap();
        let (lo, hi) = (chi.inverse_cdf(0.0005), chi.inverse_cdf(0.9995));
        let stat = sums[j] / (sigma[j] * sigma[j]);
        assert!(
            (lo..=hi).contains(&stat),
            "sensor {j}: Σe²/σ² = {stat:.0} outside [{lo:.0}, {hi:.0}] (n = {n})"
        );
    }
    // 20 runs × 201 GPS epochs, 20 × 1001 barometer epochs.
    assert_eq!(count[0], 20 * 201);
    assert_eq!(count[4], 20 * 1001);
}

#[test]
fn with_zero_body_rates_the_attitude_stays_level_and_the_imu_sees_gravity() {
    // Route R1 has ω = 0: the true attitude is (0, 0, 0) throughout, and the noise-free
    // specific force is a − g in the body frame = the NED frame.
    let params = DroneParams {
        imu_output: ImuOutput::SpecificForce,
        ..DroneParams::default()
    };
    let w = world(params, "linear");
    let real = w.simulate(0, 0.0, 7);
    for (k, q) in real.truth.iter().enumerate() {
        assert_eq!((q[6], q[7], q[8]), (0.0, 0.0, 0.0), "step {k}");
    }
    for u in &real.inputs[1..] {
        assert!((u[0] - 1.0).abs() < 1e-12 && (u[1] - 0.15).abs() < 1e-12);
        assert!((u[2] - (0.02 - 9.81)).abs() < 1e-12);
        assert_eq!((u[3], u[4], u[5]), (0.0, 0.0, 0.0));
    }
    // At noise scale 0 the strapdown pseudo-measurement follows the truth to its Euler
    // discretisation: for constant a the step p += vΔt + ½aΔt² is exact.
    let last = real.measurements.last().unwrap();
    let q = real.truth.last().unwrap();
    for i in 0..3 {
        assert!((last.z[z::IMU_P + i] - q[i]).abs() < 1e-9);
    }
}

#[test]
fn the_velocity_latency_and_the_barometer_delay_read_the_past() {
    // Noise scale 0 isolates the timing: GPS velocity at t is v(t − 0.2), the barometer
    // −z(t − 1), and the drone hovered before t = 0.
    let w = world(DroneParams::default(), "linear");
    let real = w.simulate(0, 0.0, 3);
    let m = &real.measurements;
    // t = 1.0 s: v(0.8) = a·0.8 = 0.8 m/s in x.
    assert!((m[100].z[z::GPS_V] - 0.8).abs() < 1e-12);
    // t = 0.1 s: v(−0.1) = 0.
    assert_eq!(m[10].z[z::GPS_V], 0.0);
    // t = 3.0 s: altitude −z(2) = 100 − ½·0.02·4.
    assert!((m[300].z[z::BARO] - (100.0 - 0.04)).abs() < 1e-12);
    assert!(m[300].available.has(z::BARO) && !m[301].available.has(z::BARO));
    assert!(m[300].available.has(z::GPS_P) && !m[305].available.has(z::GPS_P));
}

const SENSOR_SPEC: &str = r#"
master_seed = 4
runs = 40
[model]
kind = "drone"
[[scenarios]]
name = "linear"
[[scenarios]]
name = "sinusoidal"
[[scenarios]]
name = "ramp"
[[filters]]
label = "paper_grid"
kind = "paper"
protocol = "grid"
[[filters]]
label = "paper_native"
kind = "paper"
protocol = "native"
[initial_estimate]
mode = "sampled"
"#;

#[test]
fn the_sensor_table_reproduces_the_seeds_sensor_rmse() {
    let dir = study(SENSOR_SPEC, 2);
    let rows = lookup(dir.path(), "sensors", "metric", "mean");
    // The seed's Tables 1–3 (one run each); the calibration targets their grid values.
    // Tolerances: the grid RMSE of 2001 correlated samples varies by a few percent per run,
    // and the mean of 40 runs is compared with one seed run.
    let seed = [
        ("linear", [0.914, 0.921, 2.643, 0.242, 0.123, 0.150, 0.959]),
        (
            "sinusoidal",
            [0.915, 0.921, 2.643, 0.152, 0.213, 0.150, 1.419],
        ),
        ("ramp", [0.914, 0.921, 2.643, 0.227, 0.149, 0.150, 2.311]),
    ];
    let names = [
        "gps_px_grid",
        "gps_py_grid",
        "gps_pz_grid",
        "gps_vx_grid",
        "gps_vy_grid",
        "gps_vz_grid",
        "baro_pz_grid",
    ];
    for (route, values) in seed {
        for (name, v) in names.iter().zip(values) {
            let got = find(&rows, route, name);
            eprintln!("{route:10} {name:14} seed {v:.3}  kfmc {got:.3}");
            assert!(
                (got / v - 1.0).abs() < 0.12,
                "{route} {name}: {got} vs seed {v}"
            );
        }
        for (name, v) in [("accel_x", 0.721), ("gyro_x", 0.071)] {
            let got = find(&rows, route, name);
            assert!(
                (got / v - 1.0).abs() < 0.02,
                "{route} {name}: {got} vs seed {v}"
            );
        }
    }
    // The grid interpolates between independent fixes: its RMSE is √(2/3) of the native
    // white noise (hand calculation: the mean of (1−s)² + s² over s ∈ [0, 1)).
    let native = find(&rows, "linear", "gps_pz_native");
    let grid = find(&rows, "linear", "gps_pz_grid");
    let expected = (3.19f64.powi(2) + 0.4f64.powi(2)).sqrt();
    assert!((native / expected - 1.0).abs() < 0.05, "{native}");
    assert!(
        (grid / native - (2.0f64 / 3.0).sqrt()).abs() < 0.04,
        "{grid} / {native}"
    );

    // `kfmc summary` shows the table beside the filters' RMSE.
    let text = kfmc::cli::summary::render(dir.path(), None).unwrap();
    let line = text
        .lines()
        .find(|l| l.starts_with("ramp") && l.contains("baro_pz_grid"))
        .unwrap_or_else(|| panic!("no sensors line in:\n{text}"));
    assert!(line.contains(&format!("{:.4}", find(&rows, "ramp", "baro_pz_grid"))));

    // Every paper-filter run completes, with a covariance that stayed positive definite.
    let runs = read(&dir.path().join("runs.parquet")).unwrap();
    let status = runs.column("status").unwrap().str().unwrap().clone();
    assert!((0..runs.height()).all(|i| status.get(i) == Some("ok")));
}

const CONSISTENCY_SPEC: &str = r#"
runs = 30
[model]
kind = "drone"
imu_output = "specific_force"
accel_bias_std = 0.0
accel_bias_rw = 0.0
gyro_bias_std = 0.0
gyro_bias_rw = 0.0
gps_drift_std = 0.0
gps_velocity_latency_s = 0.0
baro_drift_rw = 0.0
baro_delay_s = 0.0
[[scenarios]]
name = "sinusoidal"
duration_s = 8.0
[[scenarios]]
name = "maneuver"
duration_s = 8.0
[[filters]]
label = "ekf9"
kind = "ekf9"
[[filters]]
label = "error_state"
kind = "error_state"
[initial_estimate]
mode = "sampled"
[consistency]
alpha = 0.05
"#;

#[test]
fn ekf9_is_consistent_on_the_white_noise_world() {
    // Over 4 master seeds × 2 routes: the calibrated NEES verdict accepts ekf9, and its
    // average NEES lies within 10 % of the 9 degrees of freedom; the error-state filter, whose
    // bias and drift states are known to be zero here, is held to the same average.
    let mut passes = 0;
    let mut cells = 0;
    for seed in 1..=4u64 {
        let spec = format!("master_seed = {seed}\n{CONSISTENCY_SPEC}");
        let dir = study(&spec, 2);
        let cons = read(&dir.path().join("consistency.parquet")).unwrap();
        let f = cons.column("filter").unwrap().str().unwrap().clone();
        let t = cons.column("test").unwrap().str().unwrap().clone();
        let p = cons.column("pass").unwrap().bool().unwrap().clone();
        for i in 0..cons.height() {
            if f.get(i) == Some("ekf9") && t.get(i) == Some("nees_time_average") {
                cells += 1;
                passes += p.get(i).unwrap() as usize;
            }
        }
        let runs = read(&dir.path().join("runs.parquet")).unwrap();
        let rf = runs.column("filter").unwrap().str().unwrap().clone();
        let nees = runs.column("nees_mean").unwrap().f64().unwrap().clone();
        for label in ["ekf9", "error_state"] {
            let v: Vec<f64> = (0..runs.height())
                .filter(|&i| rf.get(i) == Some(label))
                .filter_map(|i| nees.get(i))
                .collect();
            let mean = v.iter().sum::<f64>() / v.len() as f64;
            eprintln!("seed {seed} {label}: mean NEES {mean:.3} (9 dof)");
            assert!((mean / 9.0 - 1.0).abs() < 0.10, "{label}: {mean}");
        }
    }
    assert_eq!(cells, 8);
    // At α = 0.05 per cell, 8 independent cells pass all but at most one with probability
    // 0.94; a filter off by 10 % fails nearly all.
    assert!(passes >= 7, "{passes}/8 cells accepted");
}

#[test]
fn same_spec_and_seed_give_bit_identical_tables_on_any_thread_count() {
    let spec = SENSOR_SPEC.replace("runs = 40", "runs = 6");
    let a = study(&spec, 1);
    let b = study(&spec, 2);
    for table in ["runs", "summary", "sensors", "steps"] {
        let x = read(&a.path().join(format!("{table}.parquet"))).unwrap();
        let y = read(&b.path().join(format!("{table}.parquet"))).unwrap();
        assert!(x.equals_missing(&y), "{table} differs");
    }
}

#[test]
fn velocity_clones_and_delay_compensation_restore_consistency_under_latency() {
    // White noise plus the 0.2 s GPS velocity latency and the 1 s barometer delay: ekf9,
    // which takes both as current, is overconfident by far; with cloning and compensation
    // its mean NEES returns to within 12 % of the 9 degrees of freedom (measured 9.6 here;
    // the barometer compensation is first order, so a little above 9).
    let spec = r#"
master_seed = 3
runs = 30
[model]
kind = "drone"
imu_output = "specific_force"
accel_bias_std = 0.0
accel_bias_rw = 0.0
gyro_bias_std = 0.0
gyro_bias_rw = 0.0
gps_drift_std = 0.0
baro_drift_rw = 0.0
[[scenarios]]
name = "sinusoidal"
duration_s = 10.0
[[scenarios]]
name = "ramp"
duration_s = 10.0
[[filters]]
label = "ekf9"
kind = "ekf9"
[[filters]]
label = "ekf9_latency"
kind = "ekf9"
latency = true
[initial_estimate]
mode = "sampled"
"#;
    let dir = study(spec, 2);
    let runs = read(&dir.path().join("runs.parquet")).unwrap();
    let s = runs.column("scenario").unwrap().str().unwrap().clone();
    let f = runs.column("filter").unwrap().str().unwrap().clone();
    let nees = runs.column("nees_mean").unwrap().f64().unwrap().clone();
    for route in ["sinusoidal", "ramp"] {
        let mean = |label: &str| {
            let v: Vec<f64> = (0..runs.height())
                .filter(|&i| s.get(i) == Some(route) && f.get(i) == Some(label))
                .filter_map(|i| nees.get(i))
                .collect();
            v.iter().sum::<f64>() / v.len() as f64
        };
        let (naive, cloned) = (mean("ekf9"), mean("ekf9_latency"));
        eprintln!("{route}: ekf9 {naive:.2}, ekf9_latency {cloned:.2} (9 dof)");
        assert!((cloned / 9.0 - 1.0).abs() < 0.12, "{route}: {cloned}");
        assert!(naive > 18.0, "{route}: {naive}");
    }
}

#[test]
fn the_error_state_filter_is_consistent_on_the_full_world() {
    // The full world of drone_principled (biases, GPS drift and velocity latency, barometer
    // drift and delay), whose noise models the error-state filter carries: over 40 runs the
    // per-step ANEES lies inside its two-sided 95 % χ² band (9·40 dof) on at least 85 % of
    // the 2000 steps, and the t-test of the runs' average NEES against 9 (runs are
    // independent, so it is calibrated whatever the correlation over steps) accepts. A
    // consistent filter has each step inside with probability 0.95; the steps are correlated
    // (the GPS drift is nearly constant over a 20 s run), so one study's fraction varies, and
    // 85 % leaves room for that. The fixed filter has 98.9 % here. A filter that treats the
    // latent GPS velocity as a measurement of the current velocity is overconfident in
    // velocity by about a third: 42.7 % of steps inside with this seed, t = 3.8.
    let spec = r#"
master_seed = 36
runs = 40
[model]
kind = "drone"
imu_output = "specific_force"
[[scenarios]]
name = "sinusoidal"
[[filters]]
label = "error_state"
kind = "error_state"
[initial_estimate]
mode = "sampled"
[consistency]
alpha = 0.05
"#;
    let dir = study(spec, 2);
    let steps = read(&dir.path().join("steps.parquet")).unwrap();
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
            k += inside.get(i).unwrap() as usize;
            sum += anees.get(i).unwrap();
        }
    }
    let frac = k as f64 / n as f64;
    eprintln!(
        "error_state: {k}/{n} steps inside the band ({:.1} %), time-averaged ANEES {:.2}",
        100.0 * frac,
        sum / n as f64
    );
    assert_eq!(n, 2000);
    assert!(frac >= 0.85, "{:.1} % of steps in band", 100.0 * frac);
    let cons = read(&dir.path().join("consistency.parquet")).unwrap();
    let t = cons.column("test").unwrap().str().unwrap().clone();
    let p = cons.column("pass").unwrap().bool().unwrap().clone();
    let row = (0..cons.height())
        .find(|&i| t.get(i) == Some("nees_run_average_t"))
        .expect("nees_run_average_t row");
    assert!(p.get(row).unwrap(), "the runs' average NEES is rejected");
}
