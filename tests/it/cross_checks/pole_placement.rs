//! The pole-placement observer of seed 002 §5.4 on L1 with the position sensor: the placed
//! gains give exactly the requested error dynamics, the observer's error decays at the rate of
//! the slowest placed pole, and with noise it does what its error covariance says — which is
//! never better than the steady-state Kalman filter's.

use kfmc::filter::luenberger::place_observer;
use kfmc::filter::steady_state::solve_dare;
use kfmc::filter::{Filter, Luenberger, SeedPoleReading, seed_poles};
use kfmc::linalg::{Matrix, Vector, eigenvalues};
use kfmc::model::{Measurement, Model};
use kfmc::scenario::Scenario;
use kfmc::sim::{NoiseDraws, Trajectory, TruthNoise, simulate};
use kfmc::systems::linear_quadrotor::model::{Linear, LinearSensor};

const SCALES: [f64; 3] = [0.9, 0.5, 0.2];
const READINGS: [SeedPoleReading; 2] = [SeedPoleReading::Printed, SeedPoleReading::Negated];

fn l1() -> Linear<3> {
    Linear::<3>::new(LinearSensor::Positions, 0.1).unwrap()
}

/// max over the requested poles of |λ − λ̂| with each computed eigenvalue used once (nearest
/// first). Sorting both lists by (re, im) would do for separated poles but can pair a
/// conjugate pair crosswise when round-off makes their real parts differ in the last bit.
fn max_pole_error(computed: &[(f64, f64)], requested: &[(f64, f64)]) -> f64 {
    assert_eq!(computed.len(), requested.len());
    let mut used = vec![false; computed.len()];
    let mut worst = 0.0f64;
    for &(re, im) in requested {
        let (k, d) = computed
            .iter()
            .enumerate()
            .filter(|(k, _)| !used[*k])
            .map(|(k, c)| (k, (c.0 - re).hypot(c.1 - im)))
            .min_by(|a, b| a.1.total_cmp(&b.1))
            .unwrap();
        used[k] = true;
        worst = worst.max(d);
    }
    worst
}

fn error_dynamics(model: &Linear<3>, k: &Matrix<6, 3>) -> Matrix<6, 6> {
    (Matrix::<6, 6>::identity() - k * model.h()) * model.discrete().f
}

fn spectral_radius(poles: &[(f64, f64)]) -> f64 {
    poles.iter().map(|p| p.0.hypot(p.1)).fold(0.0, f64::max)
}

#[test]
fn seed_poles_are_placed_to_1e_8() {
    let model = l1();
    let (f, h) = (model.discrete().f, *model.h());
    for reading in READINGS {
        for a in SCALES {
            let poles = seed_poles(a, reading);
            let p = place_observer(&f, &h, &poles).unwrap();
            let ev = eigenvalues(&error_dynamics(&model, &p.gain)).unwrap();
            let err = max_pole_error(&ev, &poles);
            println!(
                "{reading:?} a = {a}: max |λ − λ̂| = {err:.1e}, κ₂(X) = {:.2}, sweeps = {}, \
                 ‖K‖_F = {:.3}",
                p.eigenvector_condition,
                p.sweeps,
                p.gain.norm()
            );
            assert!(err <= 1e-8, "{reading:?} a = {a}: {err:e}");
            assert!(p.eigenvector_condition < 1e3);
            // The convenience constructor gives the same gain.
            let obs = Luenberger::from_poles(&model, &poles).unwrap();
            assert_eq!(obs.gain, p.gain);
        }
    }
}

#[test]
fn poles_on_eigenvalues_of_f_and_repeated_poles() {
    let model = l1();
    let f = model.discrete().f;
    // F is block upper triangular: 1 (three times) and F₂₂, F₄₄, F₆₆ are exact eigenvalues.
    let cases: [[(f64, f64); 6]; 3] = [
        [
            (1.0, 0.0),
            (f[(1, 1)], 0.0),
            (0.5, 0.0),
            (0.2, 0.0),
            (-0.3, 0.2),
            (-0.3, -0.2),
        ],
        // The open-loop spectrum itself, with 1 three times (K = 0 would do).
        [
            (1.0, 0.0),
            (1.0, 0.0),
            (1.0, 0.0),
            (f[(1, 1)], 0.0),
            (f[(3, 3)], 0.0),
            (f[(5, 5)], 0.0),
        ],
        // A repeated real pole and a repeated conjugate pair (multiplicity ≤ rank(HF) = 3).
        [
            (0.4, 0.0),
            (0.4, 0.0),
            (0.1, 0.3),
            (0.1, -0.3),
            (0.1, 0.3),
            (0.1, -0.3),
        ],
    ];
    for poles in cases {
        let p = place_observer(&f, model.h(), &poles).unwrap();
        let ev = eigenvalues(&error_dynamics(&model, &p.gain)).unwrap();
        let err = max_pole_error(&ev, &poles);
        println!(
            "{poles:?}: error {err:.1e}, κ₂(X) = {:.2}",
            p.eigenvector_condition
        );
        assert!(err <= 1e-8, "{poles:?}: {err:e}");
    }
}

/// A noise-free L1 run: truth from x̂_0 + N(0, I), u = 0, 400 steps, every measurement.
fn noise_free_run(model: &Linear<3>, seed: u64) -> Trajectory<6, 3> {
    let x_hat0 = Vector::<6>::new(1.0, 0.0, 1.0, 0.0, 1.0, 0.0);
    let steps = 400;
    let draws = NoiseDraws::<6, 3>::draw(seed, steps);
    let sc = Scenario::unforced("hover", x_hat0 + draws.initial, steps);
    let noise = TruthNoise {
        process_std: Vector::<6>::zeros(),
        measurement_std: Vector::<3>::zeros(),
    };
    let mut t = simulate(model, &sc, &noise, 0.0, None, &draws);
    t.x0_hat = x_hat0;
    t
}

/// x̂ through the `Filter` view the metrics use.
fn mean(obs: &Luenberger<6, 3>, b: &Vector<6>) -> Vector<6> {
    Filter::<6, 4, 3, Linear<3>>::mean(obs, b)
}

/// e_k = x_k − x̂_k of the observer over a trajectory, through the `Filter` trait.
fn errors(model: &Linear<3>, obs: &Luenberger<6, 3>, t: &Trajectory<6, 3>) -> Vec<Vector<6>> {
    let u = Vector::<4>::zeros();
    let mut b = obs.init(model, &t.x0_hat, &Matrix::identity(), &t.measurements[0]);
    let mut out = vec![t.truth[0] - mean(obs, &b)];
    for (x, z) in t.truth.iter().zip(&t.measurements).skip(1) {
        obs.predict(model, &mut b, &u).unwrap();
        assert_eq!(obs.update(model, &mut b, &u, z).unwrap(), None);
        assert_eq!(Filter::<6, 4, 3, Linear<3>>::covariance(obs, &b), None);
        out.push(x - mean(obs, &b));
    }
    out
}

/// Without noise e_k = A^k e_0, A = (I − KH)F = X Λ X⁻¹, so
/// |wᵀ e_0| ρᵏ ≤ ‖e_k‖ ≤ κ₂(X) ρᵏ ‖e_0‖ with ρ the slowest pole and w the unit left
/// eigenvector of the slowest (real) pole: the error decays at exactly that pole's rate, not
/// merely "somehow".
#[test]
fn the_error_decays_at_the_rate_of_the_slowest_pole() {
    let model = l1();
    for reading in READINGS {
        for a in SCALES {
            let poles = seed_poles(a, reading);
            let p = place_observer(&model.discrete().f, model.h(), &poles).unwrap();
            let obs = Luenberger::new(p.gain);
            let rho = spectral_radius(&poles);
            // The slowest pole is the real one at ±a (|−0.707a ± 0.707ai| = 0.99985a < a).
            let slow = poles[2].0;
            assert_eq!(rho, slow.abs());
            let ac = error_dynamics(&model, &p.gain);
            let svd = (ac - Matrix::<6, 6>::identity() * slow)
                .transpose()
                .svd(false, true);
            let (imin, _) = svd.singular_values.argmin();
            let w: Vector<6> = svd.v_t.unwrap().row(imin).transpose();
            assert!((ac.transpose() * w - w * slow).amax() < 1e-12);
            for seed in 0..5 {
                let t = noise_free_run(&model, seed);
                let e = errors(&model, &obs, &t);
                let (e0, w0) = (e[0].norm(), w.dot(&e[0]).abs());
                assert!(w0 > 1e-3, "the slowest mode is excited");
                let mut last_checked = 0;
                for (k, ek) in e.iter().enumerate() {
                    let rk = rho.powi(k as i32);
                    let upper = p.eigenvector_condition * rk * e0;
                    assert!(
                        ek.norm() <= upper * (1.0 + 1e-9) + 1e-11,
                        "{reading:?} a = {a}, seed {seed}, k = {k}: ‖e‖ = {:e} > {upper:e}",
                        ek.norm()
                    );
                    if w0 * rk > 1e-9 {
                        assert!(
                            ek.norm() >= w0 * rk * (1.0 - 1e-6) - 1e-11,
                            "{reading:?} a = {a}, seed {seed}, k = {k}: decays too fast"
                        );
                        last_checked = k;
                    }
                }
                if seed == 0 {
                    println!(
                        "{reading:?} a = {a}: ‖e_0‖ = {e0:.2}, |wᵀe_0| = {w0:.2}, ρ = {rho}, \
                         ‖e_20‖ = {:.2e}, bounds checked to k = {last_checked}",
                        e[20].norm()
                    );
                }
            }
        }
    }
}

/// Steady-state error covariance of a fixed-gain observer under the true Q and R:
/// P = A P Aᵀ + (I − KH) Q (I − KH)ᵀ + K R Kᵀ, by doubling.
fn observer_covariance(model: &Linear<3>, k: &Matrix<6, 3>) -> Matrix<6, 6> {
    let ikh = Matrix::<6, 6>::identity() - k * model.h();
    let q = model.process_noise_covariance().unwrap();
    let mut a = ikh * model.discrete().f;
    let mut p = ikh * q * ikh.transpose() + k * model.r() * k.transpose();
    for _ in 0..40 {
        p += a * p * a.transpose();
        a = a * a;
    }
    (p + p.transpose()) * 0.5
}

/// With the truth noise on, the observer's squared error matches its Lyapunov covariance
/// (Monte Carlo), and that covariance is never below the steady-state KF's P∞ (Kalman
/// optimality among gains of the form x̂⁻ + K ν), which is the seed's observation that the
/// placed poles give poorer estimates than the KF.
#[test]
fn with_noise_the_observer_is_never_better_than_the_kalman_filter() {
    let model = l1();
    let q = model.process_noise_covariance().unwrap();
    let kf = solve_dare(&model.discrete().f, model.h(), &q, &model.r()).unwrap();
    let rms = |p: &Matrix<6, 6>, idx: [usize; 3]| {
        (idx.iter().map(|&i| p[(i, i)]).sum::<f64>() / 3.0).sqrt()
    };
    println!(
        "steady-state KF: RMS position {:.3} m, velocity {:.3} m/s, ‖K∞‖_F = {:.3}",
        rms(&kf.p_post, [0, 2, 4]),
        rms(&kf.p_post, [1, 3, 5]),
        kf.gain.norm()
    );
    let noise = model.truth_noise();
    for reading in READINGS {
        for a in SCALES {
            let obs = Luenberger::from_poles(&model, &seed_poles(a, reading)).unwrap();
            let p = observer_covariance(&model, &obs.gain);
            let gap = nalgebra::SymmetricEigen::new(p - kf.p_post)
                .eigenvalues
                .min();
            assert!(
                gap >= -1e-12,
                "{reading:?} a = {a}: P − P∞ has eigenvalue {gap:e}"
            );
            // Monte Carlo: mean ‖e_k‖² over 200 runs, k = 100..=400 (past the transient).
            let (mut sum, mut count) = (0.0, 0usize);
            for seed in 0..200 {
                let x0 = Vector::<6>::new(1.0, 0.0, 1.0, 0.0, 1.0, 0.0);
                let draws = NoiseDraws::<6, 3>::draw(1000 + seed, 400);
                let sc = Scenario {
                    name: "hover".into(),
                    x0,
                    controls: vec![Vector::<4>::zeros(); 401],
                };
                let mut t = simulate(&model, &sc, &noise, 1.0, None, &draws);
                t.x0_hat = x0;
                for ek in &errors(&model, &obs, &t)[100..] {
                    sum += ek.norm_squared();
                    count += 1;
                }
            }
            let mc = sum / count as f64;
            let rel = mc / p.trace() - 1.0;
            println!(
                "{reading:?} a = {a}: RMS position {:.3} m, velocity {:.3} m/s; \
                 tr P = {:.3} (KF {:.4}), Monte Carlo mean ‖e‖² = {mc:.3} ({:+.1}%), \
                 min eig(P − P∞) = {gap:.1e}",
                rms(&p, [0, 2, 4]),
                rms(&p, [1, 3, 5]),
                p.trace(),
                kf.p_post.trace(),
                100.0 * rel
            );
            assert!(
                rel.abs() < 0.05,
                "{reading:?} a = {a}: {:+.1}%",
                100.0 * rel
            );
        }
    }
}

#[test]
fn missing_measurements_leave_the_prediction_alone() {
    let model = l1();
    let obs = Luenberger::from_poles(&model, &seed_poles(0.5, SeedPoleReading::Printed)).unwrap();
    let t = noise_free_run(&model, 3);
    let u = Vector::<4>::zeros();
    let mut b = obs.init(&model, &t.x0_hat, &Matrix::identity(), &t.measurements[0]);
    obs.predict(&model, &mut b, &u).unwrap();
    let prior = b;
    let empty = Measurement {
        z: Vector::<3>::repeat(f64::NAN),
        available: kfmc::model::Availability(0),
    };
    assert_eq!(obs.update(&model, &mut b, &u, &empty), Ok(None));
    assert_eq!(b, prior);
}
