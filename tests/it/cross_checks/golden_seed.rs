//! kfmc's planar model, EKF and running mean against an independent implementation of the
//! seed's MATLAB code (`tests/reference/planar_seed_reference.py`, numpy). The reference wrote
//! its standard normals into the CSVs; kfmc replays them and must reproduce the truth, the
//! measurements, the EKF estimate and covariance, the running mean and the RMSE.

use crate::common::{Csv, repo};
use kfmc::filter::{CovarianceUpdate, Ekf};
use kfmc::linalg::{Matrix, Vector, diag_from_std};
use kfmc::model::Model;
use kfmc::sim::{NoiseDraws, TruthNoise, simulate};
use kfmc::step_loop::{FilterOutput, Identity, Prior, RunContext, run_filter};
use kfmc::systems::planar::model::{Planar, PlanarParams};
use kfmc::systems::planar::running_mean::RunningMean;
use kfmc::systems::planar::scenario::builtin;

const STATES: [&str; 6] = ["x", "xdot", "y", "ydot", "theta", "thetadot"];

struct Case {
    file: &'static str,
    scenario: &'static str,
    truth_std: (f64, [f64; 4]),
    filter_std: (f64, [f64; 4]),
}

/// The running mean, for the sensor set that has it (P1).
type Extra<'a, const NZ: usize> =
    Option<&'a dyn Fn(&Planar<NZ>, &Prior<'_, 6>, &RunContext<'_, 6, 2, NZ>) -> FilterOutput>;

/// The diagonal of the traced covariance (its lower triangle, 21 values per step).
fn var_at(cov: &[f64], k: usize, i: usize) -> f64 {
    cov[k * 21 + i * (i + 1) / 2 + i]
}

fn check<const NZ: usize>(case: &Case, running_mean: Extra<'_, NZ>)
where
    Planar<NZ>: Model<6, 2, NZ>,
{
    let csv = Csv::read(&repo().join("tests/golden").join(case.file));
    let model = Planar::<NZ>::new(PlanarParams::default());
    let scenario = builtin(case.scenario).unwrap().expand(0.01);
    let n = csv.rows.len();
    assert_eq!(n, scenario.controls.len());

    // Controls.
    for k in 0..n {
        for (i, u) in ["u1", "u2"].iter().enumerate() {
            let d = (scenario.controls[k][i] - csv.f(k, u)).abs();
            assert!(d < 1e-12, "{}: u at k={k}: {d}", case.file);
        }
    }

    // Replay the reference's standard normals.
    let draws = NoiseDraws::<6, NZ> {
        process: (0..n)
            .map(|k| Vector::<6>::from_fn(|i, _| csv.f(k, &format!("w{i}"))))
            .collect(),
        measurement: (0..n)
            .map(|k| Vector::<NZ>::from_fn(|i, _| csv.f(k, &format!("v{i}"))))
            .collect(),
        initial: Vector::<6>::zeros(),
    };
    let noise = TruthNoise {
        process_std: Vector::<6>::repeat(case.truth_std.0),
        measurement_std: Vector::<NZ>::from_fn(|i, _| case.truth_std.1[i]),
    };
    let traj = simulate(&model, &scenario, &noise, 1.0, None, &draws);
    for k in 0..n {
        for (i, s) in STATES.iter().enumerate() {
            let d = (traj.truth[k][i] - csv.f(k, &format!("truth_{s}"))).abs();
            assert!(d < 1e-10, "{}: truth_{s} at k={k}: {d}", case.file);
        }
        for i in 0..NZ {
            let d = (traj.measurements[k].z[i] - csv.f(k, &format!("z{i}"))).abs();
            assert!(d < 1e-10, "{}: z{i} at k={k}: {d}", case.file);
        }
    }

    let p0 = Matrix::<6, 6>::identity();
    let prior = Prior {
        x0_hat: &traj.x0_hat,
        p0: &p0,
    };
    let ctx = RunContext {
        truth: &traj.truth,
        inputs: &scenario.controls,
        measurements: &traj.measurements,
        angles: &[],
        rotations: &[],
        thresholds: None,
        quantity_names: &STATES,
        trace: true,
        export: false,
        consistency: None,
        unit: kfmc::step_loop::Unit {
            scenario: 0,
            scale: 0,
            run: 0,
        },
    };
    let q = diag_from_std(&Vector::<6>::repeat(case.filter_std.0));
    let r = diag_from_std(&Vector::<NZ>::from_fn(|i, _| case.filter_std.1[i]));
    let ekf = run_filter(
        &model,
        &Ekf {
            q,
            r,
            update_form: CovarianceUpdate::Standard,
        },
        &Identity,
        &prior,
        &ctx,
    );
    let (est, var) = ekf.trace.expect("traced");
    let mut worst = 0.0f64;
    for k in 0..n {
        for (i, s) in STATES.iter().enumerate() {
            let e = csv.f(k, &format!("ekf_{s}"));
            let d = (est[k * 6 + i] - e).abs() / e.abs().max(1.0);
            let dv = (var_at(&var, k, i) - csv.f(k, &format!("ekf_var_{s}"))).abs();
            worst = worst.max(d);
            assert!(d < 1e-9, "{}: ekf_{s} at k={k}: rel {d}", case.file);
            assert!(dv < 1e-12, "{}: ekf_var_{s} at k={k}: {dv}", case.file);
        }
    }
    eprintln!("{}: worst EKF relative difference {worst:.2e}", case.file);

    let golden = Csv::read(&repo().join("tests/golden/planar_golden_rmse.csv"));
    let rmse_row = |filter: &str| {
        golden
            .rows
            .iter()
            .position(|r| r[0] == case.file && r[1] == filter)
            .unwrap_or_else(|| panic!("no golden RMSE for {} {filter}", case.file))
    };
    let row = rmse_row("ekf");
    for (i, s) in STATES.iter().enumerate() {
        let g = golden.f(row, &format!("rmse_{s}"));
        assert!(
            (ekf.run.rmse[i] - g).abs() < 1e-9 * g.max(1e-3),
            "{}: ekf rmse_{s}",
            case.file
        );
    }

    if let Some(run_mean) = running_mean {
        let rm = run_mean(&model, &prior, &ctx);
        let (est, var) = rm.trace.expect("traced");
        assert!(
            var.iter().all(|v| v.is_nan()),
            "the running mean has no covariance"
        );
        assert_eq!(rm.run.nees_mean, None);
        for k in 0..n {
            for (i, s) in STATES.iter().enumerate() {
                let e = csv.f(k, &format!("rm_{s}"));
                let d = (est[k * 6 + i] - e).abs() / e.abs().max(1.0);
                assert!(d < 1e-11, "{}: rm_{s} at k={k}: rel {d}", case.file);
            }
        }
        let row = rmse_row("running_mean");
        for (i, s) in STATES.iter().enumerate() {
            let g = golden.f(row, &format!("rmse_{s}"));
            assert!(
                (rm.run.rmse[i] - g).abs() < 1e-10 * g.max(1e-3),
                "{}: rm rmse_{s}",
                case.file
            );
        }
    }
}

fn run_mean(
    model: &Planar<3>,
    prior: &Prior<'_, 6>,
    ctx: &RunContext<'_, 6, 2, 3>,
) -> FilterOutput {
    run_filter(model, &RunningMean { window: 11 }, &Identity, prior, ctx)
}

const P1: (f64, [f64; 4]) = (0.003, [0.01, 0.01, 0.01, 0.0]);
const P2: (f64, [f64; 4]) = (0.003, [0.01, 0.01, 0.1, 0.1]);

#[test]
fn p1_scenarios_match_the_reference() {
    for (file, scenario) in [
        ("planar_p1_basic.csv", "basic"),
        ("planar_p1_horizontal.csv", "horizontal"),
        ("planar_p1_roll.csv", "roll"),
        ("planar_p1_fall.csv", "fall"),
    ] {
        check::<3>(
            &Case {
                file,
                scenario,
                truth_std: P1,
                filter_std: P1,
            },
            Some(&run_mean),
        );
    }
}

#[test]
fn p1_nominal_filter_under_20x_truth_noise_matches_the_reference() {
    check::<3>(
        &Case {
            file: "planar_p1_roll_x20.csv",
            scenario: "roll",
            truth_std: (0.06, [0.2, 0.2, 0.2, 0.0]),
            filter_std: P1,
        },
        Some(&run_mean),
    );
}

#[test]
fn p2_imu_sensor_matches_the_reference() {
    for (file, scenario) in [
        ("planar_p2_basic.csv", "basic"),
        ("planar_p2_roll.csv", "roll"),
    ] {
        check::<4>(
            &Case {
                file,
                scenario,
                truth_std: P2,
                filter_std: P2,
            },
            None,
        );
    }
}
