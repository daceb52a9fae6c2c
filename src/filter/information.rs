//! Information filter: propagates the information matrix Y = P⁻¹ and vector y = P⁻¹x̂.
//!
//! Predict (needs F invertible, true for any F = e^{AΔt}; Q positive definite):
//! M = F⁻ᵀ Y F⁻¹ (the information of F x̂ before the noise), then by the matrix inversion lemma
//! Y⁻ = (M⁻¹ + Q)⁻¹ = M − M (M + Q⁻¹)⁻¹ M, and y⁻ = Y⁻ f(x̂, u).
//! Update: Y = Y⁻ + Hᵀ R⁻¹ H, y = y⁻ + Hᵀ R⁻¹ (ν + H x̂⁻), which for a linear h = Hx is the
//! textbook y⁻ + Hᵀ R⁻¹ z and for a nonlinear h the extended information filter.
//!
//! The update is where the form pays off: adding information is a sum, and a sensor that did
//! not report adds nothing (its rows are masked as in the EKF). The common view
//! ([`Filter::mean`], [`Filter::covariance`]) solves with a Cholesky factor of Y. The innovation
//! statistics (NIS, whitened ν) need S = H P⁻ Hᵀ + R, which is formed from Y⁻ for the metrics
//! only; the recursion never uses it.
//!
//! # Reference
//! Maybeck, *Stochastic Models, Estimation and Control*, Vol. 1, §5.7; Crassidis & Junkins,
//! *Optimal Estimation of Dynamic Systems*, §3.3.

use super::{Filter, FilterError, Innovation, check_finite, mask_rows};
use crate::linalg::{Matrix, SmallCholesky, Vector, symmetrize};
use crate::model::{Availability, Measurement, Model};

/// Information-filter configuration: the assumed Q and R, with the inverses the recursion
/// uses computed once rather than every step.
#[derive(Clone, Debug, PartialEq)]
pub struct Information<const NX: usize, const NZ: usize> {
    r: Matrix<NZ, NZ>,
    q_inv: Result<Matrix<NX, NX>, FilterError>,
    r_inv: Result<Matrix<NZ, NZ>, FilterError>,
}

impl<const NX: usize, const NZ: usize> Information<NX, NZ> {
    /// The filter assuming process noise `q` and measurement noise `r` (both must be positive
    /// definite; otherwise every run fails at its first step with that reason).
    pub fn new(q: Matrix<NX, NX>, r: Matrix<NZ, NZ>) -> Self {
        Information {
            r,
            q_inv: inverse_spd(&q, "process noise Q"),
            r_inv: inverse_spd(&r, "measurement noise R"),
        }
    }
}

/// The information filter's belief.
#[derive(Clone, Debug, PartialEq)]
pub struct InformationBelief<const NX: usize> {
    /// y = P⁻¹ x̂.
    pub y: Vector<NX>,
    /// Y = P⁻¹.
    pub info: Matrix<NX, NX>,
    /// x̂⁻ of the last prediction (the linearisation point of the update).
    x_prior: Vector<NX>,
    f: Matrix<NX, NX>,
    /// After an update, Hᵀ R⁻¹ H: the error transition's K H = P Hᵀ R⁻¹ H is formed from it
    /// only when the consistency tests ask.
    ht_rinv_h: Option<Matrix<NX, NX>>,
}

fn chol_y<const NX: usize>(y: &Matrix<NX, NX>) -> Result<SmallCholesky<NX>, FilterError> {
    SmallCholesky::new(y).ok_or(FilterError::NotPositiveDefinite {
        which: "information matrix Y",
    })
}

fn inverse_spd<const N: usize>(
    a: &Matrix<N, N>,
    which: &'static str,
) -> Result<Matrix<N, N>, FilterError> {
    let c = SmallCholesky::new(a).ok_or(FilterError::NotPositiveDefinite { which })?;
    Ok(c.solve(&Matrix::<N, N>::identity()))
}

impl<const NX: usize, const NU: usize, const NZ: usize, M: Model<NX, NU, NZ>> Filter<NX, NU, NZ, M>
    for Information<NX, NZ>
{
    type Belief = InformationBelief<NX>;

    fn init(
        &self,
        _model: &M,
        x0_hat: &Vector<NX>,
        p0: &Matrix<NX, NX>,
        _z0: &Measurement<NZ>,
    ) -> InformationBelief<NX> {
        // A P_0 that is not SPD yields a NaN Y, which the first step reports as non-finite.
        let info = inverse_spd(p0, "initial covariance P0")
            .unwrap_or_else(|_| Matrix::<NX, NX>::from_element(f64::NAN));
        InformationBelief {
            y: info * x0_hat,
            info,
            x_prior: *x0_hat,
            f: Matrix::<NX, NX>::identity(),
            ht_rinv_h: None,
        }
    }

    fn predict(
        &self,
        model: &M,
        b: &mut InformationBelief<NX>,
        u: &Vector<NU>,
    ) -> Result<(), FilterError> {
        check_finite(&b.y, &b.info)?;
        let x = chol_y(&b.info)?.solve(&b.y);

        let f = model.transition_jacobian(&x, u);
        let f_inv = f.try_inverse().ok_or(FilterError::Singular {
            which: "transition matrix F",
        })?;
        let m = symmetrize(&(f_inv.transpose() * b.info * f_inv));
        let q_inv = self.q_inv.as_ref().map_err(Clone::clone)?;
        let c = SmallCholesky::new(&(m + q_inv)).ok_or(FilterError::NotPositiveDefinite {
            which: "M + Q⁻¹",
        })?;
        b.info = symmetrize(&(m - m * c.solve(&m)));
        b.x_prior = model.propagate(&x, u);
        b.y = b.info * b.x_prior;
        b.f = f;
        b.ht_rinv_h = None;
        check_finite(&b.y, &b.info)
    }

    fn update(
        &self,
        model: &M,
        b: &mut InformationBelief<NX>,
        u: &Vector<NU>,
        z: &Measurement<NZ>,
    ) -> Result<Option<Innovation<NZ>>, FilterError> {
        if z.available.count() == 0 {
            return Ok(None);
        }
        let x = b.x_prior;
        let mut h = model.measurement_jacobian(&x, u);
        let mut nu = model.residual(&z.z, &model.measure(&x, u));
        let r = mask_rows(&self.r, z.available, &mut h, &mut nu);
        let r_inv = if z.available == Availability::all(NZ) {
            self.r_inv.clone()?
        } else {
            inverse_spd(&r, "measurement noise R")?
        };
        // Innovation statistics for the metrics: S = H P⁻ Hᵀ + R.
        let p_prior = chol_y(&b.info)?.solve(&Matrix::<NX, NX>::identity());
        let s = h * p_prior * h.transpose() + r;
        let s_chol = SmallCholesky::new(&s).ok_or(FilterError::NotPositiveDefinite {
            which: "innovation covariance S",
        })?;
        let whitened = s_chol.solve_lower(&nu);
        let ht_rinv = h.transpose() * r_inv;
        let ht_rinv_h = ht_rinv * h;
        b.info = symmetrize(&(b.info + ht_rinv_h));
        b.y += ht_rinv * (nu + h * x);
        b.ht_rinv_h = Some(ht_rinv_h);
        check_finite(&b.y, &b.info)?;
        Ok(Some(
            Innovation::new(nu, whitened, z.available).with_covariance(s),
        ))
    }

    fn mean(&self, b: &InformationBelief<NX>) -> Vector<NX> {
        match SmallCholesky::new(&b.info) {
            Some(c) => c.solve(&b.y),
            None => Vector::<NX>::from_element(f64::NAN),
        }
    }

    fn covariance(&self, b: &InformationBelief<NX>) -> Option<Matrix<NX, NX>> {
        Some(match SmallCholesky::new(&b.info) {
            Some(c) => symmetrize(&c.solve(&Matrix::<NX, NX>::identity())),
            None => Matrix::<NX, NX>::from_element(f64::NAN),
        })
    }

    fn error_transition(&self, b: &InformationBelief<NX>) -> Option<Matrix<NX, NX>> {
        let Some(ht_rinv_h) = &b.ht_rinv_h else {
            return Some(b.f);
        };
        // K H = P Hᵀ R⁻¹ H with P = Y⁻¹ (the gain this update applied).
        let kh = SmallCholesky::new(&b.info)?.solve(ht_rinv_h);
        Some((Matrix::<NX, NX>::identity() - kh) * b.f)
    }
}
