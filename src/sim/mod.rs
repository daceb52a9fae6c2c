//! The sim role: truth and measurements from the model and seeded noise.
//!
//! The noise is drawn as standard normals first ([`NoiseDraws`]) and only then scaled by the
//! truth's standard deviations and the noise multiplier. That split gives common random
//! numbers across multipliers, and lets a test replay the normals of an independent reference
//! implementation.

pub mod seed;

use rand::Rng;
use rand_distr::{Distribution, StandardNormal};

use crate::linalg::{Matrix, SmallCholesky, Vector};
use crate::model::{Measurement, Model};
use crate::scenario::Scenario;
use seed::{StreamKind, stream};

/// The standard normals of one run.
#[derive(Clone, Debug, PartialEq)]
pub struct NoiseDraws<const NX: usize, const NZ: usize> {
    /// ξ_k for the process noise, k = 0..=K (ξ_0 unused and zero).
    pub process: Vec<Vector<NX>>,
    /// η_k for the measurement noise, k = 0..=K (η_0 zero: the seeds' z_0 is noise-free).
    pub measurement: Vec<Vector<NZ>>,
    /// ζ for a sampled initial estimate x̂_0 = x_0 + L_0 ζ with P_0 = L_0 L_0ᵀ.
    pub initial: Vector<NX>,
}

fn normals<const N: usize>(rng: &mut impl Rng) -> Vector<N> {
    Vector::<N>::from_fn(|_, _| StandardNormal.sample(rng))
}

impl<const NX: usize, const NZ: usize> NoiseDraws<NX, NZ> {
    /// Draws the normals of the run with seed `run_seed` for K = `steps` transitions.
    pub fn draw(run_seed: u64, steps: usize) -> Self {
        let mut p = stream(run_seed, StreamKind::ProcessNoise);
        let mut m = stream(run_seed, StreamKind::MeasurementNoise);
        let mut i = stream(run_seed, StreamKind::InitialEstimate);
        let mut process = Vec::with_capacity(steps + 1);
        let mut measurement = Vec::with_capacity(steps + 1);
        process.push(Vector::<NX>::zeros());
        measurement.push(Vector::<NZ>::zeros());
        for _ in 0..steps {
            process.push(normals(&mut p));
            measurement.push(normals(&mut m));
        }
        NoiseDraws {
            process,
            measurement,
            initial: normals(&mut i),
        }
    }
}

/// The truth's noise levels at noise multiplier 1.
#[derive(Clone, Debug, PartialEq)]
pub struct TruthNoise<const NX: usize, const NZ: usize> {
    /// Standard deviation of each process-noise component.
    pub process_std: Vector<NX>,
    /// Standard deviation of each measurement-noise component.
    pub measurement_std: Vector<NZ>,
}

/// One simulated run: truth, measurements and the initial estimate every filter starts from.
#[derive(Clone, Debug, PartialEq)]
pub struct Trajectory<const NX: usize, const NZ: usize> {
    /// x_0..x_K.
    pub truth: Vec<Vector<NX>>,
    /// z_0..z_K.
    pub measurements: Vec<Measurement<NZ>>,
    /// x̂_0: the truth (the seeds) or a draw from N(x_0, P_0).
    pub x0_hat: Vector<NX>,
}

/// A factor L with L Lᵀ = Q, for drawing w = L ξ ~ N(0, Q): Q's Cholesky factor when Q is
/// positive definite, else, for a singular but positive semi-definite Q (a noise that drives
/// fewer directions than there are states), V·diag(√λ) from its symmetric eigenvalues.
/// `None` when Q is not a finite, symmetric, positive semi-definite matrix: no Gaussian has
/// it as covariance, and systems refuse such a model while validating
/// ([`crate::system::additive::FilterKinds::configure_entries`]).
pub fn process_factor<const NX: usize>(q: &Matrix<NX, NX>) -> Option<Matrix<NX, NX>> {
    // A Cholesky factorisation reads one triangle only: symmetry is checked first. The
    // tolerance leaves room for the round-off of a discretised Q.
    let scale = q.amax();
    if !q.iter().all(|v| v.is_finite()) || (q - q.transpose()).amax() > 1e-9 * scale {
        return None;
    }
    if let Some(c) = SmallCholesky::new(q) {
        return Some(c.l());
    }
    let eig =
        nalgebra::DMatrix::from_fn(NX, NX, |i, j| 0.5 * (q[(i, j)] + q[(j, i)])).symmetric_eigen();
    // Round-off leaves the zero eigenvalues of a singular Q a few ulps either side of 0.
    let floor = -1e-12 * scale;
    if eig.eigenvalues.iter().any(|&l| l < floor) {
        return None;
    }
    Some(Matrix::<NX, NX>::from_fn(|i, j| {
        eig.eigenvectors[(i, j)] * eig.eigenvalues[j].max(0.0).sqrt()
    }))
}

/// Simulates one run of `scenario` with the truth noise scaled by `noise_scale`.
///
/// `p0_factor` is a lower-triangular L_0 with P_0 = L_0 L_0ᵀ when the initial estimate is
/// sampled, or `None` to start at the truth.
pub fn simulate<const NX: usize, const NU: usize, const NZ: usize, M: Model<NX, NU, NZ>>(
    model: &M,
    scenario: &Scenario<NX, NU>,
    noise: &TruthNoise<NX, NZ>,
    noise_scale: f64,
    p0_factor: Option<&Matrix<NX, NX>>,
    draws: &NoiseDraws<NX, NZ>,
) -> Trajectory<NX, NZ> {
    let steps = scenario.steps();
    let w_std = noise.process_std * noise_scale;
    let v_std = noise.measurement_std * noise_scale;
    let mut truth = Vec::with_capacity(steps + 1);
    let mut measurements = Vec::with_capacity(steps + 1);
    let x0 = scenario.x0;
    truth.push(x0);
    measurements.push(Measurement {
        z: model.measure(&x0, &scenario.controls[0]),
        available: model.availability(0),
    });
    // A full model Q is sampled through a factor of it (its Cholesky factor when it is
    // positive definite); the planar models have none and keep the per-state std path.
    // A model whose Q has no factor was refused while validating; were one to get here, its
    // truth must not silently take the per-state std instead of Q.
    let w_factor = model.process_noise_covariance().map(|q| {
        process_factor(&q).expect("a model's Q is checked positive semi-definite when validated")
            * noise_scale
    });
    let mut x = x0;
    for k in 1..=steps {
        let u = &scenario.controls[k];
        let w = match &w_factor {
            Some(l) => l * draws.process[k],
            None => w_std.component_mul(&draws.process[k]),
        };
        x = model.propagate(&x, u) + w;
        let available = model.availability(k);
        let mut z = model.measure(&x, u) + v_std.component_mul(&draws.measurement[k]);
        for i in 0..NZ {
            if !available.has(i) {
                z[i] = 0.0;
            }
        }
        truth.push(x);
        measurements.push(Measurement { z, available });
    }
    let x0_hat = match p0_factor {
        Some(l) => x0 + l * draws.initial,
        None => x0,
    };
    Trajectory {
        truth,
        measurements,
        x0_hat,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::systems::planar::model::{PlanarP1, PlanarParams};
    use crate::systems::planar::scenario::builtin;

    #[test]
    fn common_random_numbers_across_noise_scales() {
        let model = PlanarP1::new(PlanarParams::default());
        let sc = builtin("basic").unwrap().expand(0.01);
        let noise = TruthNoise {
            process_std: Vector::<6>::repeat(0.003),
            measurement_std: Vector::<3>::repeat(0.01),
        };
        let draws = NoiseDraws::<6, 3>::draw(seed::run_seed(1, "basic", 0), sc.steps());
        let a = simulate(&model, &sc, &noise, 1.0, None, &draws);
        let b = simulate(&model, &sc, &noise, 2.0, None, &draws);
        // z_1 − h(x_1) doubles exactly when the scale doubles.
        let u = &sc.controls[1];
        let ra = a.measurements[1].z - model.measure(&a.truth[1], u);
        let rb = b.measurements[1].z - model.measure(&b.truth[1], u);
        assert!((rb - ra * 2.0).amax() < 1e-15);
        assert_eq!(a.truth.len(), 1001);
        assert_eq!(a.measurements[0].z, model.measure(&sc.x0, &sc.controls[0]));
    }

    /// x_k = x_{k−1} + w_k with a full Q: the increments are the truth's process noise.
    struct RandomWalk(Matrix<2, 2>);

    impl Model<2, 1, 1> for RandomWalk {
        fn dt_s(&self) -> f64 {
            0.1
        }
        fn propagate(&self, x: &Vector<2>, _: &Vector<1>) -> Vector<2> {
            *x
        }
        fn transition_jacobian(&self, _: &Vector<2>, _: &Vector<1>) -> Matrix<2, 2> {
            Matrix::<2, 2>::identity()
        }
        fn measure(&self, x: &Vector<2>, _: &Vector<1>) -> Vector<1> {
            Vector::<1>::new(x[0])
        }
        fn measurement_jacobian(&self, _: &Vector<2>, _: &Vector<1>) -> Matrix<1, 2> {
            Matrix::<1, 2>::new(1.0, 0.0)
        }
        fn process_noise_covariance(&self) -> Option<Matrix<2, 2>> {
            Some(self.0)
        }
    }

    /// The truth's process-noise increments have the model's full Q as covariance, for a
    /// positive definite Q and for a singular one (rank 1: one noise drives both states, as
    /// a white-acceleration model's does), at noise scale 2 (covariance 4 Q). Seeded: 40,000
    /// increments; each sample covariance entry must lie within 5 standard errors of 4 Q,
    /// SE(Ĉ_ij) = √((C_ii C_jj + C_ij²)/N) (Gaussian increments). The per-state-std fallback
    /// this replaces gives Ĉ_01 ≈ 0 where 4 Q_01 = 8 for the singular Q: 80 SE off.
    #[test]
    fn a_full_q_is_the_covariance_of_the_truth_noise_even_when_singular() {
        let n = 40_000usize;
        for q in [
            Matrix::<2, 2>::new(1.0, 2.0, 2.0, 4.0),
            Matrix::<2, 2>::new(1.0, 0.6, 0.6, 2.0),
        ] {
            let model = RandomWalk(q);
            let sc = Scenario::<2, 1>::unforced("walk", Vector::<2>::zeros(), n);
            let noise = TruthNoise {
                process_std: Vector::<2>::zeros(),
                measurement_std: Vector::<1>::repeat(1.0),
            };
            let draws = NoiseDraws::<2, 1>::draw(seed::run_seed(3, "walk", 0), n);
            let tr = simulate(&model, &sc, &noise, 2.0, None, &draws);
            let want = q * 4.0;
            let mut c = Matrix::<2, 2>::zeros();
            for k in 1..=n {
                let w = tr.truth[k] - tr.truth[k - 1];
                c += w * w.transpose();
            }
            c /= n as f64;
            for (i, j) in [(0, 0), (0, 1), (1, 1)] {
                let se = ((want[(i, i)] * want[(j, j)] + want[(i, j)].powi(2)) / n as f64).sqrt();
                assert!(
                    (c[(i, j)] - want[(i, j)]).abs() < 5.0 * se,
                    "Q = {q:?}: Ĉ[{i},{j}] = {} vs 4Q = {} (SE {se})",
                    c[(i, j)],
                    want[(i, j)]
                );
            }
        }
    }

    /// A factor reproduces Q (L Lᵀ = Q) for definite and singular Q; an indefinite, a
    /// non-symmetric or a non-finite Q has none.
    #[test]
    fn process_factor_reproduces_q_or_refuses() {
        for q in [
            Matrix::<3, 3>::new(4.0, 2.0, 0.0, 2.0, 1.0, 0.0, 0.0, 0.0, 0.0),
            Matrix::<3, 3>::new(2.0, 0.5, 0.1, 0.5, 1.0, 0.2, 0.1, 0.2, 3.0),
            Matrix::<3, 3>::zeros(),
        ] {
            let l = process_factor(&q).unwrap();
            assert!((l * l.transpose() - q).amax() < 1e-12, "{q:?}");
        }
        for q in [
            Matrix::<3, 3>::new(1.0, 2.0, 0.0, 2.0, 1.0, 0.0, 0.0, 0.0, 1.0),
            Matrix::<3, 3>::new(1.0, 0.5, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0),
            Matrix::<3, 3>::new(f64::NAN, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0),
        ] {
            assert!(process_factor(&q).is_none(), "{q:?}");
        }
    }

    #[test]
    fn clean_basic_trajectory_by_hand() {
        // Noise scale 0: the seeds' `state.clean`. With u1 ≠ u2 only through the ripple,
        // θ̇_k = Σ_{j=1..k} (r/I)(u1_j − u2_j)Δt; check it and y at k = 100 by direct sums.
        let p = PlanarParams::default();
        let model = PlanarP1::new(p);
        let sc = builtin("basic").unwrap().expand(0.01);
        let noise = TruthNoise {
            process_std: Vector::<6>::repeat(0.003),
            measurement_std: Vector::<3>::repeat(0.01),
        };
        let draws = NoiseDraws::<6, 3>::draw(7, sc.steps());
        let tr = simulate(&model, &sc, &noise, 0.0, None, &draws);
        let (mut th, mut thd, mut y, mut yd) = (0.0f64, 0.0f64, 1.0f64, 0.0f64);
        for k in 1..=100 {
            let t = k as f64 * 0.01;
            let u1 = 3.0 * (1.0 + 0.001 * (2.0 * t).cos());
            let u2 = 3.0 * (1.0 + 0.001 * (2.0 * t).sin());
            let ydd = (u1 + u2) * th.cos() / 0.5 - 9.81;
            let thdd = 0.15 / 0.005 * (u1 - u2);
            y += yd * 0.01;
            th += thd * 0.01;
            yd += ydd * 0.01;
            thd += thdd * 0.01;
        }
        assert!((tr.truth[100][2] - y).abs() < 1e-12);
        assert!((tr.truth[100][3] - yd).abs() < 1e-12);
        assert!((tr.truth[100][4] - th).abs() < 1e-14);
        assert!((tr.truth[100][5] - thd).abs() < 1e-14);
        // Hand value: ẏ ≈ (12·1.00… − 9.81)·1 s ≈ 2.19 m/s after 1 s of 6 N on 0.5 kg.
        assert!((yd - 2.19).abs() < 0.02);
    }
}
