//! Speed of the P1 EKF step and of a whole Monte Carlo run, as ratios against a minimal
//! hand-written fixed-size EKF step measured in the same process (the machines are shared
//! and noisy, so absolute times mean little; ratios are what to compare).
//!
//! ```text
//! cargo run --release --example bench_step
//! ```
//!
//! Method: the same 1,000-step trajectory is filtered repeatedly; the baseline and kfmc are
//! interleaved in rounds and the median round is reported.

use std::hint::black_box;
use std::path::Path;
use std::time::Instant;

use kfmc::experiment;
use kfmc::filter::{CovarianceUpdate, Ekf, Filter};
use kfmc::linalg::{Matrix, Vector};
use kfmc::model::Measurement;
use kfmc::model::planar::{PlanarP1, PlanarParams};
use kfmc::scenario::planar::builtin;
use kfmc::sim::{NoiseDraws, TruthNoise, seed::run_seed, simulate};
use kfmc::trial::{Unit, build};

/// The baseline: the seed's EKF step written out by hand for exactly this model, with
/// nalgebra fixed-size matrices, an explicit 3×3 inverse and nothing else.
#[inline(never)]
fn hand_step(
    x: &mut Vector<6>,
    p: &mut Matrix<6, 6>,
    u: &Vector<2>,
    z: &Vector<3>,
    q: &Matrix<6, 6>,
    r: &Matrix<3, 3>,
) {
    let (m, arm, inertia, g, dt) = (0.5, 0.15, 0.005, 9.81, 0.01);
    let thrust = u[0] + u[1];
    let (s, c) = x[4].sin_cos();
    let mut f = Matrix::<6, 6>::identity();
    f[(0, 1)] = dt;
    f[(1, 4)] = -c * thrust / m * dt;
    f[(2, 3)] = dt;
    f[(3, 4)] = -s * thrust / m * dt;
    f[(4, 5)] = dt;
    *x = Vector::<6>::new(
        x[0] + x[1] * dt,
        x[1] - s * thrust / m * dt,
        x[2] + x[3] * dt,
        x[3] + (c * thrust / m - g) * dt,
        x[4] + x[5] * dt,
        x[5] + arm / inertia * (u[0] - u[1]) * dt,
    );
    let pp = f * *p * f.transpose() + q;
    let mut h = Matrix::<3, 6>::zeros();
    h[(0, 2)] = 1.0;
    h[(1, 4)] = 1.0;
    h[(2, 5)] = 1.0;
    let mut nu = z - Vector::<3>::new(x[2], x[4], x[5]);
    nu[1] = (nu[1] + std::f64::consts::PI).rem_euclid(2.0 * std::f64::consts::PI)
        - std::f64::consts::PI;
    let s_mat = h * pp * h.transpose() + r;
    let k = pp * h.transpose() * s_mat.try_inverse().expect("S invertible");
    *x += k * nu;
    *p = (Matrix::<6, 6>::identity() - k * h) * pp;
}

/// One bare hand-written EKF pass over a trajectory; returns the final x̂ for black-boxing.
fn hand_pass(
    x0: &Vector<6>,
    controls: &[Vector<2>],
    zs: &[Measurement<3>],
    q: &Matrix<6, 6>,
    r: &Matrix<3, 3>,
) -> Vector<6> {
    let mut x = *x0;
    let mut p = Matrix::<6, 6>::identity();
    for k in 1..controls.len() {
        hand_step(&mut x, &mut p, &controls[k], &zs[k].z, q, r);
    }
    x
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn main() {
    let model = PlanarP1::new(PlanarParams::default());
    let sc = builtin("roll").unwrap().expand(0.01);
    let noise = TruthNoise {
        process_std: Vector::<6>::repeat(0.003),
        measurement_std: Vector::<3>::repeat(0.01),
    };
    let draws = NoiseDraws::<6, 3>::draw(run_seed(1, "roll", 0), sc.steps());
    let traj = simulate(&model, &sc, &noise, 1.0, None, &draws);
    let q = Matrix::<6, 6>::identity() * 0.003f64.powi(2);
    let r = Matrix::<3, 3>::identity() * 0.01f64.powi(2);
    let ekf = Ekf {
        q,
        r,
        update_form: CovarianceUpdate::Standard,
    };
    let steps = sc.steps();
    let reps = 200;

    let mut base = Vec::new();
    let mut kf = Vec::new();
    let mut checksum = 0.0;
    for _round in 0..15 {
        let t = Instant::now();
        for _ in 0..reps {
            let x = hand_pass(&traj.x0_hat, &sc.controls, &traj.measurements, &q, &r);
            checksum += black_box(x[0]);
        }
        base.push(t.elapsed().as_secs_f64() / (reps * steps) as f64);

        let t = Instant::now();
        for _ in 0..reps {
            let mut b = Filter::<6, 2, 3, PlanarP1>::init(
                &ekf,
                &model,
                &traj.x0_hat,
                &Matrix::<6, 6>::identity(),
                &traj.measurements[0],
            );
            for k in 1..=steps {
                let u = &sc.controls[k];
                let z: &Measurement<3> = &traj.measurements[k];
                ekf.predict(&model, &mut b, u).unwrap();
                black_box(ekf.update(&model, &mut b, u, z).unwrap());
            }
            checksum -= black_box(b.x[0]);
        }
        kf.push(t.elapsed().as_secs_f64() / (reps * steps) as f64);
    }
    let (b, k) = (median(base), median(kf));
    println!("P1 EKF step (predict + update), median of 15 rounds × {reps} runs × {steps} steps:");
    println!(
        "  hand-written fixed-size baseline  {:8.1} ns/step",
        b * 1e9
    );
    println!(
        "  kfmc Ekf via the Filter trait      {:8.1} ns/step   ratio {:.2}×",
        k * 1e9,
        k / b
    );
    println!(
        "  (checksum {:.3e}: both compute the same estimates)",
        checksum
    );

    // Whole Monte Carlo run: simulate + EKF + running mean + per-step metrics, one thread.
    let spec = Path::new(env!("CARGO_MANIFEST_DIR")).join("experiments/planar_robustness.toml");
    let plan = experiment::load(&spec).expect("bundled spec");
    let trial = build(&plan);
    let mut per_run = Vec::new();
    let mut base_run = Vec::new();
    for round in 0..9 {
        let t = Instant::now();
        for run in 0..50 {
            black_box(trial.run(&Unit {
                scenario: 2,
                scale: 4,
                run: round * 50 + run,
            }));
        }
        per_run.push(t.elapsed().as_secs_f64() / 50.0);
        let t = Instant::now();
        for _ in 0..50 {
            black_box(hand_pass(
                &traj.x0_hat,
                &sc.controls,
                &traj.measurements,
                &q,
                &r,
            ));
        }
        base_run.push(t.elapsed().as_secs_f64() / 50.0);
    }
    let (pr, br) = (median(per_run), median(base_run));
    println!(
        "Whole Monte Carlo run (1,001 samples: truth + measurements, EKF, running mean, errors, NEES/NIS), one thread:"
    );
    println!(
        "  kfmc run                 {:8.1} µs   = {:.2}× one bare hand-written EKF pass over the same steps",
        pr * 1e6,
        pr / br
    );
    println!("  bare EKF pass (baseline) {:8.1} µs", br * 1e6);
}
