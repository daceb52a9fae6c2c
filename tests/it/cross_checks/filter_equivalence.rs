//! Linear-Gaussian filters are one estimator in different algebra: on the same L1 runs the
//! covariance-form KF (the EKF on a linear model), the information filter, the square-root
//! filter and the sigma-point filters (UKF, CKF: exact for a linear model) must agree on x̂_k and P_k to round-off. A new linear-Gaussian filter joins the
//! comparison by adding one line to [`FILTERS`].
//!
//! The steady-state KF is checked against the seed's printed closed-loop poles λ_K and against
//! the limit of the time-varying gain.

use kfmc::filter::steady_state::solve_dare;
use kfmc::filter::{
    CovarianceUpdate, Ekf, Filter, Information, SigmaPointKalman, SigmaPoints, SquareRoot,
    SteadyState,
};
use kfmc::linalg::{Matrix, Vector, eigenvalues};
use kfmc::model::{Availability, Measurement, Model};
use kfmc::scenario::Scenario;
use kfmc::sim::{NoiseDraws, Trajectory, simulate};
use kfmc::systems::linear_quadrotor::model::{Linear, LinearSensor};

/// x̂_k, P_k and the error transition A_k = (I − K_k H_k) F_k after every step k = 0..=K
/// (A_0 = I). A_k feeds the calibrated NEES test, so every form must expose the same one.
type History = Vec<(Vector<6>, Matrix<6, 6>, Matrix<6, 6>)>;

fn history<const NZ: usize, F: Filter<6, 4, NZ, Linear<NZ>>>(
    model: &Linear<NZ>,
    filter: &F,
    traj: &Trajectory<6, NZ>,
) -> History {
    let u = Vector::<4>::zeros();
    let mut b = filter.init(
        model,
        &traj.x0_hat,
        &Matrix::identity(),
        &traj.measurements[0],
    );
    let mut out = vec![(
        filter.mean(&b),
        filter.covariance(&b).unwrap(),
        Matrix::identity(),
    )];
    for z in &traj.measurements[1..] {
        filter.predict(model, &mut b, &u).expect("predict");
        filter.update(model, &mut b, &u, z).expect("update");
        out.push((
            filter.mean(&b),
            filter.covariance(&b).unwrap(),
            filter
                .error_transition(&b)
                .expect("a linear-Gaussian filter has A_k"),
        ));
    }
    out
}

type Run3 = fn(&Linear<3>, Matrix<6, 6>, Matrix<3, 3>, &Trajectory<6, 3>) -> History;

/// The filters compared with the reference (the first line). One line per filter.
const FILTERS: &[(&str, Run3)] = &[
    ("kf", |m, q, r, t| {
        history(
            m,
            &Ekf {
                q,
                r,
                update_form: CovarianceUpdate::Standard,
            },
            t,
        )
    }),
    ("kf_joseph", |m, q, r, t| {
        history(
            m,
            &Ekf {
                q,
                r,
                update_form: CovarianceUpdate::Joseph,
            },
            t,
        )
    }),
    ("information", |m, q, r, t| {
        history(m, &Information::new(q, r), t)
    }),
    ("sqrt", |m, q, r, t| history(m, &SquareRoot::new(q, r), t)),
    ("ukf", |m, q, r, t| {
        history(
            m,
            &SigmaPointKalman::new(q, r, SigmaPoints::DEFAULT_UNSCENTED).unwrap(),
            t,
        )
    }),
    ("ckf", |m, q, r, t| {
        history(
            m,
            &SigmaPointKalman::new(q, r, SigmaPoints::Cubature).unwrap(),
            t,
        )
    }),
];

/// One seeded L1 run with the seed's x̂_0 = [1,0,1,0,1,0], P_0 = I, the truth drawn from
/// N(x̂_0, I), 40 s, and measurement gaps: every 7th step reports nothing (predict only) and
/// every 5th reports only its first component.
fn l1_run(model: &Linear<3>, seed: u64) -> Trajectory<6, 3> {
    let x_hat0 = Vector::<6>::new(1.0, 0.0, 1.0, 0.0, 1.0, 0.0);
    let steps = 400;
    let draws = NoiseDraws::<6, 3>::draw(seed, steps);
    let sc = Scenario::unforced("hover", x_hat0 + draws.initial, steps);
    let noise = model.truth_noise();
    let mut t = simulate(model, &sc, &noise, 1.0, None, &draws);
    t.x0_hat = x_hat0;
    for (k, m) in t.measurements.iter_mut().enumerate() {
        if k % 7 == 0 {
            *m = Measurement {
                z: Vector::zeros(),
                available: Availability(0),
            };
        } else if k % 5 == 0 {
            m.available = Availability(0b001);
            m.z[1] = 0.0;
            m.z[2] = 0.0;
        }
    }
    t
}

#[test]
fn every_linear_gaussian_filter_agrees_to_1e_9() {
    for sensor in [LinearSensor::Positions, LinearSensor::Velocities] {
        let model = Linear::<3>::new(sensor, 0.1).unwrap();
        let q = model.process_noise_covariance().unwrap();
        let r = model.r();
        let mut worst = vec![0.0f64; FILTERS.len()];
        for seed in 0..5 {
            let t = l1_run(&model, seed);
            let reference = (FILTERS[0].1)(&model, q, r, &t);
            assert_eq!(reference.len(), 401);
            for (i, (name, run)) in FILTERS.iter().enumerate() {
                let h = run(&model, q, r, &t);
                for (k, ((x, p, a), (xr, pr, ar))) in h.iter().zip(&reference).enumerate() {
                    let e = (x - xr).amax().max((p - pr).amax()).max((a - ar).amax());
                    assert!(e <= 1e-9, "{name} ({sensor:?}) differs at k = {k} by {e:e}");
                    worst[i] = worst[i].max(e);
                }
            }
        }
        for ((name, _), w) in FILTERS.iter().zip(&worst) {
            println!("{sensor:?} {name}: max |Δx̂|, |ΔP| over 5 runs × 401 steps = {w:.2e}");
        }
    }
}

#[test]
fn the_comparison_can_fail() {
    // A filter with a slightly different R must not pass the 1e-9 test.
    let model = Linear::<3>::new(LinearSensor::Positions, 0.1).unwrap();
    let q = model.process_noise_covariance().unwrap();
    let t = l1_run(&model, 1);
    let a = (FILTERS[0].1)(&model, q, model.r(), &t);
    let b = (FILTERS[0].1)(&model, q, model.r() * (1.0 + 1e-6), &t);
    let e = a
        .iter()
        .zip(&b)
        .map(|(x, y)| (x.0 - y.0).amax())
        .fold(0.0, f64::max);
    assert!(e > 1e-9);
}

#[test]
fn steady_state_poles_match_the_seeds_lambda_k() {
    let model = Linear::<3>::new(LinearSensor::Positions, 0.1).unwrap();
    let q = model.process_noise_covariance().unwrap();
    let d = solve_dare(&model.discrete().f, model.h(), &q, &model.r()).unwrap();
    let a = (Matrix::<6, 6>::identity() - d.gain * model.h()) * model.discrete().f;
    let ev = eigenvalues(&a).unwrap();
    // Seed 002 §5.4: λ_K = 0.9090 ± 0.0831i, 0.9200 ± 0.0739i, 0.9533 ± 0.0445i.
    let seed = [
        (0.9090, -0.0831),
        (0.9090, 0.0831),
        (0.9200, -0.0739),
        (0.9200, 0.0739),
        (0.9533, -0.0445),
        (0.9533, 0.0445),
    ];
    println!(
        "eig((I − K∞H)F) = {ev:?} after {} Riccati iterations",
        d.iterations
    );
    for ((re, im), (sr, si)) in ev.iter().zip(seed) {
        assert!(
            (re - sr).abs() <= 5e-5 && (im - si).abs() <= 5e-5,
            "{re} {im:+}i vs the seed's {sr} {si:+}i"
        );
    }
    // The fixed point: one more Riccati step leaves P∞⁻ unchanged.
    let s = model.h() * d.p_prior * model.h().transpose() + model.r();
    let k = d.p_prior * model.h().transpose() * s.try_inverse().unwrap();
    let f = model.discrete().f;
    let next = f * (d.p_prior - k * model.h() * d.p_prior) * f.transpose() + q;
    assert!((next - d.p_prior).amax() < 1e-14);
}

#[test]
fn time_varying_gain_converges_to_the_dare_gain() {
    let model = Linear::<3>::new(LinearSensor::Positions, 0.1).unwrap();
    let q = model.process_noise_covariance().unwrap();
    let r = model.r();
    let ss = SteadyState::new(&model, &q, &r);
    let d = ss.dare.as_ref().unwrap();
    let (f, h) = (model.discrete().f, *model.h());
    let mut p = Matrix::<6, 6>::identity();
    let mut gap = Vec::new();
    for _ in 0..400 {
        p = f * p * f.transpose() + q;
        let s = h * p * h.transpose() + r;
        let k = p * h.transpose() * s.try_inverse().unwrap();
        p = (Matrix::<6, 6>::identity() - k * h) * p;
        gap.push((k - d.gain).amax());
    }
    println!(
        "|K_k − K∞| at k = 10, 100, 400: {:.1e} {:.1e} {:.1e}",
        gap[9], gap[99], gap[399]
    );
    assert!(gap[9] > 1e-3, "the gain starts away from K∞");
    assert!(gap[399] < 1e-12);
}

#[test]
fn undetectable_sensors_have_no_steady_state() {
    let model = Linear::<3>::new(LinearSensor::Velocities, 0.1).unwrap();
    let q = model.process_noise_covariance().unwrap();
    assert!(SteadyState::new(&model, &q, &model.r()).dare.is_err());
    let model = Linear::<2>::new(LinearSensor::Xy, 0.1).unwrap();
    let q = model.process_noise_covariance().unwrap();
    assert!(SteadyState::new(&model, &q, &model.r()).dare.is_err());
}
