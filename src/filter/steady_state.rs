//! Steady-state Kalman filter: one fixed gain K∞ from the discrete algebraic Riccati equation
//!
//! P = F (P − P Hᵀ (H P Hᵀ + R)⁻¹ H P) Fᵀ + Q   (P = P∞⁻, the predicted covariance),
//!
//! solved by iterating the Riccati recursion from P = Q until it stops changing (it converges
//! for a detectable (F, H) and stabilisable (F, Q^{1/2}); the seed's position sensor is both,
//! its velocity and xy sensors leave an integrator unobserved and have no steady state).
//! Then S∞ = H P Hᵀ + R, K∞ = P Hᵀ S∞⁻¹, P∞ = (I − K∞ H) P.
//!
//! The filter is x̂⁻ = f(x̂, u), x̂ = x̂⁻ + K∞ ν, and reports the fixed P∞ (after an update) or
//! P∞⁻ (after a prediction alone) as its covariance. F and H are taken at x̂ = 0, u = 0, which
//! is exact for a linear model (plan validation allows this filter for linear models only).
//! A component that did not report has its column of K∞ zeroed.
//!
//! # Reference
//! Anderson & Moore, *Optimal Filtering* (1979), §4.4 — the seed's reference \[1\].

use super::{Filter, FilterError, Innovation, mask_rows};
use crate::linalg::{Matrix, SmallCholesky, Vector};
use crate::model::{Measurement, Model};

/// The DARE solution and the fixed gain.
#[derive(Clone, Debug, PartialEq)]
pub struct Dare<const NX: usize, const NZ: usize> {
    /// P∞⁻, the stabilising solution of the DARE (predicted covariance).
    pub p_prior: Matrix<NX, NX>,
    /// P∞ = (I − K∞ H) P∞⁻ (updated covariance).
    pub p_post: Matrix<NX, NX>,
    /// K∞.
    pub gain: Matrix<NX, NZ>,
    /// S∞ = H P∞⁻ Hᵀ + R.
    pub s: Matrix<NZ, NZ>,
    /// F used.
    pub f: Matrix<NX, NX>,
    /// H used.
    pub h: Matrix<NZ, NX>,
    /// Riccati iterations until convergence.
    pub iterations: usize,
}

/// Solves the DARE for (F, H, Q, R) by the Riccati recursion.
pub fn solve_dare<const NX: usize, const NZ: usize>(
    f: &Matrix<NX, NX>,
    h: &Matrix<NZ, NX>,
    q: &Matrix<NX, NX>,
    r: &Matrix<NZ, NZ>,
) -> Result<Dare<NX, NZ>, FilterError> {
    let not_pd = FilterError::NotPositiveDefinite {
        which: "innovation covariance S",
    };
    let mut p = *q;
    for it in 1..=200_000 {
        let s = h * p * h.transpose() + r;
        let c = SmallCholesky::new(&s).ok_or(not_pd.clone())?;
        let hp = h * p;
        let post = p - hp.transpose() * c.solve(&hp);
        let next = f * post * f.transpose() + q;
        let next = (next + next.transpose()) * 0.5;
        let change = (next - p).amax();
        let scale = next.amax().max(f64::MIN_POSITIVE);
        if !change.is_finite() || scale > 1e12 {
            return Err(FilterError::NoSteadyState);
        }
        p = next;
        // Converged when a further step changes P by round-off only.
        if change <= 1e-15 * scale {
            let s = h * p * h.transpose() + r;
            let c = SmallCholesky::new(&s).ok_or(not_pd)?;
            let gain = c.solve(&(h * p)).transpose();
            let p_post = (Matrix::<NX, NX>::identity() - gain * h) * p;
            return Ok(Dare {
                p_prior: p,
                p_post: (p_post + p_post.transpose()) * 0.5,
                gain,
                s,
                f: *f,
                h: *h,
                iterations: it,
            });
        }
    }
    Err(FilterError::NoSteadyState)
}

/// Steady-state KF configuration: the DARE solution for the assumed Q and R, or why there is
/// none (every run of the filter then fails at step 1 with that reason).
#[derive(Clone, Debug, PartialEq)]
pub struct SteadyState<const NX: usize, const NZ: usize> {
    /// The solution.
    pub dare: Result<Dare<NX, NZ>, FilterError>,
}

impl<const NX: usize, const NZ: usize> SteadyState<NX, NZ> {
    /// Solves the DARE for `model` linearised at x = 0, u = 0 with assumed `q` and `r`.
    pub fn new<const NU: usize, M: Model<NX, NU, NZ>>(
        model: &M,
        q: &Matrix<NX, NX>,
        r: &Matrix<NZ, NZ>,
    ) -> Self {
        let (x, u) = (Vector::<NX>::zeros(), Vector::<NU>::zeros());
        let f = model.transition_jacobian(&x, &u);
        let h = model.measurement_jacobian(&x, &u);
        SteadyState {
            dare: solve_dare(&f, &h, q, r),
        }
    }
}

/// The steady-state filter's belief.
#[derive(Clone, Debug, PartialEq)]
pub struct FixedGainBelief<const NX: usize> {
    /// x̂
    pub x: Vector<NX>,
    /// The covariance reported: P_0, then P∞⁻ or P∞.
    pub p: Matrix<NX, NX>,
    updated: bool,
}

impl<const NX: usize, const NU: usize, const NZ: usize, M: Model<NX, NU, NZ>> Filter<NX, NU, NZ, M>
    for SteadyState<NX, NZ>
{
    type Belief = FixedGainBelief<NX>;

    fn init(
        &self,
        _model: &M,
        x0_hat: &Vector<NX>,
        p0: &Matrix<NX, NX>,
        _z0: &Measurement<NZ>,
    ) -> FixedGainBelief<NX> {
        FixedGainBelief {
            x: *x0_hat,
            p: *p0,
            updated: false,
        }
    }

    fn predict(
        &self,
        model: &M,
        b: &mut FixedGainBelief<NX>,
        u: &Vector<NU>,
    ) -> Result<(), FilterError> {
        let d = self.dare.as_ref().map_err(Clone::clone)?;
        b.x = model.propagate(&b.x, u);
        b.p = d.p_prior;
        b.updated = false;
        Ok(())
    }

    fn update(
        &self,
        model: &M,
        b: &mut FixedGainBelief<NX>,
        u: &Vector<NU>,
        z: &Measurement<NZ>,
    ) -> Result<Option<Innovation<NZ>>, FilterError> {
        let d = self.dare.as_ref().map_err(Clone::clone)?;
        if z.available.count() == 0 {
            return Ok(None);
        }
        let mut h = d.h;
        let mut nu = model.residual(&z.z, &model.measure(&b.x, u));
        let s = mask_rows(&d.s, z.available, &mut h, &mut nu);
        let mut gain = d.gain;
        for i in 0..NZ {
            if !z.available.has(i) {
                gain.column_mut(i).fill(0.0);
            }
        }
        let c = SmallCholesky::new(&s).ok_or(FilterError::NotPositiveDefinite {
            which: "innovation covariance S",
        })?;
        let whitened = c.solve_lower(&nu);
        b.x += gain * nu;
        b.p = d.p_post;
        b.updated = true;
        if !b.x.sum().is_finite() {
            return Err(FilterError::NonFinite {
                what: "state estimate",
            });
        }
        Ok(Some(
            Innovation::new(nu, whitened, z.available).with_covariance(s),
        ))
    }

    fn mean(&self, b: &FixedGainBelief<NX>) -> Vector<NX> {
        b.x
    }

    fn covariance(&self, b: &FixedGainBelief<NX>) -> Option<Matrix<NX, NX>> {
        Some(b.p)
    }

    fn covariance_ref<'b>(&self, b: &'b FixedGainBelief<NX>) -> Option<&'b Matrix<NX, NX>> {
        Some(&b.p)
    }

    fn error_transition(&self, b: &FixedGainBelief<NX>) -> Option<Matrix<NX, NX>> {
        let d = self.dare.as_ref().ok()?;
        Some(if b.updated {
            (Matrix::<NX, NX>::identity() - d.gain * d.h) * d.f
        } else {
            d.f
        })
    }
}
