//! Batch least squares for the initial state (seed 002 §4.2, which derived it and could not
//! make it work): x̂_0 from *all* measurements z_1..z_K of a run.
//!
//! Stacking x_k = F^k x_0 + m_k + Σ_{j≤k} F^{k−j} w_j (m_k the noise-free response to the
//! inputs from x = 0) gives one linear model for the whole run,
//!
//!   z̄ − H̄m̄ = H̄ x_0 + ε,  H̄ = [H F; H F²; …; H F^K],  ε ~ N(0, Σ),
//!   Σ_{kl} = H F^{k−l} P_l Hᵀ + δ_{kl} R  (k ≥ l),  P_l = F P_{l−1} Fᵀ + Q,  P_0 = 0,
//!
//! whose generalised least-squares solution x̂_0 = (H̄ᵀΣ⁻¹H̄)⁻¹ H̄ᵀΣ⁻¹(z̄ − H̄m̄) is the
//! minimum-variance unbiased estimate, with error covariance P̂_0 = (H̄ᵀΣ⁻¹H̄)⁻¹. The process
//! noise makes Σ dense, which is the point of doing it in faer: Σ = L Lᵀ (Cholesky), the
//! whitened H̃ = L⁻¹H̄ = Q R (Householder QR, never the normal equations), P̂_0 = R⁻¹R⁻ᵀ.
//!
//! The seed's eq. 12 minimises J(x_0, w) over the initial state *and* the process noise
//! jointly; eliminating w from that quadratic gives exactly this estimate (the unit tests
//! check the two against each other). Σ, the factors and the operator
//! M = P̂_0 H̄ᵀΣ⁻¹ depend only on the model, the noise levels and the sensor schedule, so they
//! are computed once per scenario; each run then costs one M·(z̄ − H̄m̄) product.
//!
//! z_0 is not used: the seeds record it noise-free, which would pin x_0's measured part
//! exactly.
//!
//! # Reference
//! Crassidis & Junkins, *Optimal Estimation of Dynamic Systems* (2nd ed., 2012), §1.2.2
//! (weighted least squares) and §4.1 (batch estimation with process noise).

use faer::Side;

use crate::linalg::{Matrix, Vector, numerical_rank};
use crate::model::{Availability, Measurement, Model};

/// Why a batch least-squares initial estimate cannot be formed.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum BatchLsError {
    /// The stacked measurements do not determine x_0 (an unobservable direction).
    #[error(
        "the measurements do not determine x0: the stacked model has rank {rank} of {states} (the sensor set is not observable)"
    )]
    NotObservable {
        /// Numerical rank of H̄.
        rank: usize,
        /// Number of states.
        states: usize,
    },
    /// Σ is not positive definite (a zero measurement noise, for example).
    #[error("the stacked measurement-error covariance is not positive definite (is R > 0?)")]
    NotPositiveDefinite,
    /// The run has no measurement after z_0.
    #[error("the run has no measurements after z_0")]
    NoMeasurements,
}

/// The precomputed estimator of x_0 for one scenario (its inputs and sensor schedule).
#[derive(Clone, Debug, PartialEq)]
pub struct BatchInitial<const NX: usize> {
    /// Column r of M = P̂_0 H̄ᵀΣ⁻¹: the weight of stacked measurement row r in x̂_0.
    weights: Vec<Vector<NX>>,
    /// Stacked row r is component `rows[r].1` of z at step `rows[r].0`.
    rows: Vec<(usize, usize)>,
    /// (H̄m̄)_r, the input response to remove from each row.
    input_response: Vec<f64>,
    /// P̂_0 = (H̄ᵀΣ⁻¹H̄)⁻¹ for the Q and R given to [`BatchInitial::new`].
    pub covariance: Matrix<NX, NX>,
}

impl<const NX: usize> BatchInitial<NX> {
    /// The estimator for `model` (linear: F and H are its Jacobians at x = 0, u = 0) over
    /// steps 1..=K of `controls` (u_0..u_K), with process-noise covariance `q` and measurement
    /// covariance `r`.
    pub fn new<const NU: usize, const NZ: usize, M: Model<NX, NU, NZ>>(
        model: &M,
        controls: &[Vector<NU>],
        q: &Matrix<NX, NX>,
        r: &Matrix<NZ, NZ>,
    ) -> Result<Self, BatchLsError> {
        let steps = controls.len().saturating_sub(1);
        let (x0, u0) = (Vector::<NX>::zeros(), Vector::<NU>::zeros());
        let f = model.transition_jacobian(&x0, &u0);
        let h = model.measurement_jacobian(&x0, &u0);

        // Powers H F^d (d = 0..K), P_l Hᵀ (l = 1..K) and the input response m_k.
        let mut h_pow = Vec::with_capacity(steps + 1);
        let mut hf = h;
        for _ in 0..=steps {
            h_pow.push(hf);
            hf *= f;
        }
        let mut p_ht = vec![Matrix::<NX, NZ>::zeros(); steps + 1];
        let mut p = Matrix::<NX, NX>::zeros();
        let mut m = Vec::with_capacity(steps + 1);
        let mut mk = Vector::<NX>::zeros();
        m.push(mk);
        for k in 1..=steps {
            p = f * p * f.transpose() + q;
            p_ht[k] = p * h.transpose();
            mk = model.propagate(&mk, &controls[k]);
            m.push(mk);
        }

        let mut rows = Vec::new();
        for k in 1..=steps {
            let available: Availability = model.availability(k);
            rows.extend((0..NZ).filter(|&i| available.has(i)).map(|i| (k, i)));
        }
        let n = rows.len();
        if n == 0 {
            return Err(BatchLsError::NoMeasurements);
        }
        // H̄ row (k, i) = (H F^k)_i; Σ entry ((k, i), (l, j)) for k ≥ l from the block above.
        let hbar = faer::Mat::<f64>::from_fn(n, NX, |a, c| {
            let (k, i) = rows[a];
            h_pow[k][(i, c)]
        });
        let sigma = faer::Mat::<f64>::from_fn(n, n, |a, b| {
            let ((k, i), (l, j)) = if a >= b {
                (rows[a], rows[b])
            } else {
                (rows[b], rows[a])
            };
            let mut v = h_pow[k - l].row(i).dot(&p_ht[l].column(j).transpose());
            if k == l {
                v += r[(i, j)];
            }
            v
        });
        let llt = sigma
            .llt(Side::Lower)
            .map_err(|_| BatchLsError::NotPositiveDefinite)?;
        let l = llt.L();
        let mut whitened = hbar.clone();
        l.solve_lower_triangular_in_place(whitened.as_mut());
        let qr = whitened.qr();
        let r_fac = qr.thin_R();
        // An unpivoted QR's diagonal flags a deficiency but does not count it; the SVD does.
        let diag: Vec<f64> = (0..NX.min(n)).map(|i| r_fac[(i, i)].abs()).collect();
        let biggest = diag.iter().cloned().fold(0.0, f64::max);
        if n < NX
            || diag.iter().any(|&d| d.is_nan() || d <= 1e-10 * biggest)
            || !biggest.is_finite()
        {
            let rank = numerical_rank(whitened.as_ref(), 1e-10);
            return Err(BatchLsError::NotObservable { rank, states: NX });
        }
        let rank = NX;
        let r_up = Matrix::<NX, NX>::from_fn(|i, j| if j >= i { r_fac[(i, j)] } else { 0.0 });
        let r_inv = r_up
            .solve_upper_triangular(&Matrix::<NX, NX>::identity())
            .ok_or(BatchLsError::NotObservable { rank, states: NX })?;
        let cov = r_inv * r_inv.transpose();
        let covariance = (cov + cov.transpose()) * 0.5;
        // Mᵀ = Σ⁻¹ H̄ P̂_0 = L⁻ᵀ (H̃ P̂_0).
        let mut mt = faer::Mat::<f64>::from_fn(n, NX, |a, c| {
            (0..NX).map(|t| whitened[(a, t)] * covariance[(t, c)]).sum()
        });
        l.transpose().solve_upper_triangular_in_place(mt.as_mut());
        let weights = (0..n)
            .map(|a| Vector::<NX>::from_fn(|c, _| mt[(a, c)]))
            .collect();
        let input_response = rows.iter().map(|&(k, i)| (h * m[k])[i]).collect();
        Ok(BatchInitial {
            weights,
            rows,
            input_response,
            covariance,
        })
    }

    /// x̂_0 from a run's measurements z_0..z_K (z_0 is not used).
    pub fn estimate<const NZ: usize>(&self, measurements: &[Measurement<NZ>]) -> Vector<NX> {
        let mut x = Vector::<NX>::zeros();
        for ((w, &(k, i)), hm) in self
            .weights
            .iter()
            .zip(&self.rows)
            .zip(&self.input_response)
        {
            x += w * (measurements[k].z[i] - hm);
        }
        x
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::linalg::SmallCholesky;
    use crate::scenario::Scenario;
    use crate::sim::{NoiseDraws, TruthNoise, simulate};
    use crate::systems::linear_quadrotor::model::{Linear, Linear2, Linear3, LinearSensor};

    fn scenario(steps: usize, with_input: bool) -> Scenario<6, 4> {
        Scenario {
            name: "t".into(),
            x0: Vector::<6>::new(1.0, -0.2, 1.0, 0.1, 1.0, 0.3),
            controls: (0..=steps)
                .map(|k| {
                    if with_input {
                        Vector::<4>::new((k as f64 * 0.1).sin(), 0.2, -0.1, 0.05 * k as f64)
                    } else {
                        Vector::<4>::zeros()
                    }
                })
                .collect(),
        }
    }

    fn run<const NZ: usize>(
        model: &Linear<NZ>,
        sc: &Scenario<6, 4>,
        scale: f64,
        seed: u64,
    ) -> crate::sim::Trajectory<6, NZ> {
        let noise = TruthNoise {
            process_std: Vector::<6>::zeros(),
            measurement_std: Vector::<NZ>::from_fn(|i, _| model.r()[(i, i)].sqrt()),
        };
        let draws = NoiseDraws::<6, NZ>::draw(seed, sc.steps());
        simulate(model, sc, &noise, scale, None, &draws)
    }

    #[test]
    fn noise_free_measurements_give_x0_exactly_even_with_inputs() {
        let model = Linear3::new(LinearSensor::Positions, 0.1).unwrap();
        let sc = scenario(60, true);
        let tr = run(&model, &sc, 0.0, 3);
        let b = BatchInitial::new(&model, &sc.controls, &model.discrete().q, &model.r()).unwrap();
        assert!((b.estimate(&tr.measurements) - sc.x0).amax() < 1e-9);
        assert!(SmallCholesky::new(&b.covariance).is_some());
    }

    #[test]
    fn without_process_noise_it_is_weighted_least_squares_by_normal_equations() {
        // Second algorithm: Σ_k (H F^k)ᵀ R⁻¹ (H F^k) and its right-hand side, in nalgebra.
        let model = Linear3::new(LinearSensor::Positions, 0.1).unwrap();
        let sc = scenario(80, true);
        let tr = run(&model, &sc, 1.0, 11);
        let q0 = Matrix::<6, 6>::zeros();
        let b = BatchInitial::new(&model, &sc.controls, &q0, &model.r()).unwrap();
        let d = model.discrete();
        let r_inv = model.r().try_inverse().unwrap();
        let (mut info, mut rhs) = (Matrix::<6, 6>::zeros(), Vector::<6>::zeros());
        let (mut fk, mut m) = (Matrix::<6, 6>::identity(), Vector::<6>::zeros());
        for k in 1..=sc.steps() {
            fk = d.f * fk;
            m = d.f * m + d.g * sc.controls[k];
            let hk = model.h() * fk;
            info += hk.transpose() * r_inv * hk;
            rhs += hk.transpose() * r_inv * (tr.measurements[k].z - model.h() * m);
        }
        let cov = info.try_inverse().unwrap();
        let x = cov * rhs;
        let est = b.estimate(&tr.measurements);
        assert!((est - x).amax() < 1e-9 * x.amax(), "{est} vs {x}");
        assert!((b.covariance - cov).amax() < 1e-9 * cov.amax());
    }

    #[test]
    fn it_equals_the_seeds_joint_estimate_of_x0_and_the_process_noise() {
        // Seed eq. 12: minimise ‖z − H x‖²_R⁻¹ + Σ‖w_k‖²_Q⁻¹ over (x_0, w_1..w_K) jointly —
        // one whitened least-squares problem in 6 + 6K unknowns, solved by nalgebra's SVD.
        let model = Linear3::new(LinearSensor::Positions, 0.1).unwrap();
        let k_steps = 8;
        let sc = scenario(k_steps, true);
        let noise = TruthNoise {
            process_std: Vector::<6>::zeros(),
            measurement_std: Vector::<3>::from_fn(|i, _| model.r()[(i, i)].sqrt()),
        };
        let draws = NoiseDraws::<6, 3>::draw(5, k_steps);
        let tr = simulate(&model, &sc, &noise, 1.0, None, &draws);
        let d = model.discrete();
        // Inflate Q so the process noise matters over 8 steps.
        let q = d.q * 50.0;
        let b = BatchInitial::new(&model, &sc.controls, &q, &model.r()).unwrap();

        let nu = 6 + 6 * k_steps;
        let rows = 3 * k_steps + 6 * k_steps;
        let mut a = nalgebra::DMatrix::<f64>::zeros(rows, nu);
        let mut y = nalgebra::DVector::<f64>::zeros(rows);
        let r_isqrt = model
            .r()
            .map(|v| if v > 0.0 { 1.0 / v.sqrt() } else { 0.0 });
        let lq = SmallCholesky::new(&q).unwrap();
        let lq_inv = lq.l().try_inverse().unwrap();
        let mut m = Vector::<6>::zeros();
        // x_k = Φ_k θ + m_k with Φ_k = [F^k, F^{k−1}, …, I, 0, …].
        let mut phi = nalgebra::DMatrix::<f64>::zeros(6, nu);
        phi.view_mut((0, 0), (6, 6))
            .copy_from(&Matrix::<6, 6>::identity());
        for k in 1..=k_steps {
            let next = nalgebra::DMatrix::from_fn(6, 6, |i, j| d.f[(i, j)]) * &phi;
            phi = next;
            for i in 0..6 {
                phi[(i, 6 * k + i)] += 1.0;
            }
            m = d.f * m + d.g * sc.controls[k];
            let hphi = nalgebra::DMatrix::from_fn(3, 6, |i, j| model.h()[(i, j)]) * &phi;
            let resid = tr.measurements[k].z - model.h() * m;
            for i in 0..3 {
                let row = 3 * (k - 1) + i;
                for c in 0..nu {
                    a[(row, c)] = hphi[(i, c)] * r_isqrt[(i, i)];
                }
                y[row] = resid[i] * r_isqrt[(i, i)];
            }
            let base = 3 * k_steps + 6 * (k - 1);
            for i in 0..6 {
                for j in 0..6 {
                    a[(base + i, 6 * k + j)] = lq_inv[(i, j)];
                }
            }
        }
        let svd = a.clone().svd(true, true);
        let theta = svd.solve(&y, 1e-14).unwrap();
        let joint_x0 = Vector::<6>::from_fn(|i, _| theta[i]);
        let est = b.estimate(&tr.measurements);
        assert!((est - joint_x0).amax() < 1e-9, "{est} vs {joint_x0}");
        // The x_0 block of the joint covariance (AᵀA)⁻¹ is P̂_0.
        let cov = (a.transpose() * &a).try_inverse().unwrap();
        let cov_x0 = Matrix::<6, 6>::from_fn(|i, j| cov[(i, j)]);
        assert!((cov_x0 - b.covariance).amax() < 1e-8 * b.covariance.amax());
    }

    #[test]
    fn unobservable_sensor_sets_are_refused_with_their_rank() {
        let sc = scenario(50, false);
        let vel = Linear3::new(LinearSensor::Velocities, 0.1).unwrap();
        let e = BatchInitial::new(&vel, &sc.controls, &vel.discrete().q, &vel.r()).unwrap_err();
        assert_eq!(e, BatchLsError::NotObservable { rank: 3, states: 6 });
        let xy = Linear2::new(LinearSensor::Xy, 0.1).unwrap();
        let e = BatchInitial::new(&xy, &sc.controls, &xy.discrete().q, &xy.r()).unwrap_err();
        assert_eq!(e, BatchLsError::NotObservable { rank: 4, states: 6 });
    }
}
