//! Square-root covariance filter: propagates a lower-triangular S with P = S Sᵀ and never forms
//! P to re-factorise it.
//!
//! Both steps triangularise a stacked pre-array by Householder reflections on fixed-size
//! blocks ([`crate::linalg::triangularize`], [`crate::linalg::PreArray`]), on the stack:
//! * predict: [F S, L_Q] → [S⁻, 0], since F S Sᵀ Fᵀ + L_Q L_Qᵀ = F P Fᵀ + Q;
//! * update:  [[L_R, H S⁻], [0, S⁻]] → [[L_S, 0], [K̄, S]], where L_S L_Sᵀ = S (the innovation
//!   covariance), K = K̄ L_S⁻¹ and S Sᵀ = (I − K H) P⁻; then x̂ = x̂⁻ + K̄ (L_S⁻¹ ν).
//!
//! L_S⁻¹ν is the whitened innovation itself, so the NIS costs one triangular solve. Components
//! that did not report are masked as in the EKF (zero rows of H and ν, identity block in R),
//! which makes their columns of K̄ zero.
//!
//! # Reference
//! Kaminski, Bryson & Schmidt, "Discrete square root filtering: a survey of current
//! techniques", IEEE TAC 16(6), 1971; Verhaegen & Van Dooren (1986), the seed's reference \[8\].

use super::{Filter, FilterError, Innovation, check_finite, mask_rows};
use crate::linalg::{Matrix, PreArray, SmallCholesky, Vector, triangularize};
use crate::model::{Availability, Measurement, Model};

/// Square-root filter configuration: the assumed Q and R (both positive definite), kept as
/// their Cholesky factors so no step re-factors a constant matrix.
#[derive(Clone, Debug, PartialEq)]
pub struct SquareRoot<const NX: usize, const NZ: usize> {
    r: Matrix<NZ, NZ>,
    l_q: Result<Matrix<NX, NX>, FilterError>,
    l_r: Result<Matrix<NZ, NZ>, FilterError>,
}

impl<const NX: usize, const NZ: usize> SquareRoot<NX, NZ> {
    /// The filter assuming process noise `q` and measurement noise `r`. A matrix that is not
    /// positive definite makes every run fail at its first step with that reason.
    pub fn new(q: Matrix<NX, NX>, r: Matrix<NZ, NZ>) -> Self {
        SquareRoot {
            r,
            l_q: factor(&q, "process noise Q"),
            l_r: factor(&r, "measurement noise R"),
        }
    }
}

/// The square-root filter's belief.
#[derive(Clone, Debug, PartialEq)]
pub struct SqrtBelief<const NX: usize, const NZ: usize> {
    /// x̂
    pub x: Vector<NX>,
    /// S, lower triangular, P = S Sᵀ.
    pub s: Matrix<NX, NX>,
    f: Matrix<NX, NX>,
    /// After an update: K̄, L_S and H, from which I − K H is formed only when the consistency
    /// tests ask for the error transition (most studies never do).
    gain: Option<(Matrix<NX, NZ>, Matrix<NZ, NZ>, Matrix<NZ, NX>)>,
}

fn factor<const N: usize>(
    a: &Matrix<N, N>,
    which: &'static str,
) -> Result<Matrix<N, N>, FilterError> {
    SmallCholesky::new(a)
        .map(|c| c.l())
        .ok_or(FilterError::NotPositiveDefinite { which })
}

impl<const NX: usize, const NU: usize, const NZ: usize, M: Model<NX, NU, NZ>> Filter<NX, NU, NZ, M>
    for SquareRoot<NX, NZ>
{
    type Belief = SqrtBelief<NX, NZ>;

    fn init(
        &self,
        _model: &M,
        x0_hat: &Vector<NX>,
        p0: &Matrix<NX, NX>,
        _z0: &Measurement<NZ>,
    ) -> SqrtBelief<NX, NZ> {
        // The one Cholesky factorisation of a covariance: P_0 is given, not propagated.
        let s = factor(p0, "initial covariance P0")
            .unwrap_or_else(|_| Matrix::<NX, NX>::from_element(f64::NAN));
        SqrtBelief {
            x: *x0_hat,
            s,
            f: Matrix::<NX, NX>::identity(),
            gain: None,
        }
    }

    fn predict(
        &self,
        model: &M,
        b: &mut SqrtBelief<NX, NZ>,
        u: &Vector<NU>,
    ) -> Result<(), FilterError> {
        let f = model.transition_jacobian(&b.x, u);
        let l_q = self.l_q.as_ref().map_err(Clone::clone)?;
        b.s = triangularize(&(f * b.s), l_q);
        b.x = model.propagate(&b.x, u);
        b.f = f;
        b.gain = None;
        check_finite(&b.x, &b.s)
    }

    fn update(
        &self,
        model: &M,
        b: &mut SqrtBelief<NX, NZ>,
        u: &Vector<NU>,
        z: &Measurement<NZ>,
    ) -> Result<Option<Innovation<NZ>>, FilterError> {
        if z.available.count() == 0 {
            return Ok(None);
        }
        let mut h = model.measurement_jacobian(&b.x, u);
        let mut nu = model.residual(&z.z, &model.measure(&b.x, u));
        let r = mask_rows(&self.r, z.available, &mut h, &mut nu);
        let l_r = if z.available == Availability::all(NZ) {
            self.l_r.clone()?
        } else {
            factor(&r, "measurement noise R")?
        };
        let mut pre = PreArray {
            a11: l_r,
            a12: h * b.s,
            a21: Matrix::<NX, NZ>::zeros(),
            a22: b.s,
        };
        pre.triangularize();
        let (l_s, k_bar) = (pre.a11, pre.a21);
        // L_S's diagonal is non-negative, so with no zero pivot L_S is S's Cholesky factor; a
        // zero pivot means S is singular.
        if (0..NZ).any(|i| l_s[(i, i)].partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater)) {
            return Err(FilterError::NotPositiveDefinite {
                which: "innovation covariance S",
            });
        }
        let whitened = l_s
            .solve_lower_triangular(&nu)
            .ok_or(FilterError::NotPositiveDefinite {
                which: "innovation covariance S",
            })?;
        b.x += k_bar * whitened;
        b.s = pre.a22;
        b.gain = Some((k_bar, l_s, h));
        check_finite(&b.x, &b.s)?;
        Ok(Some(
            Innovation::new(nu, whitened, z.available).with_covariance(l_s * l_s.transpose()),
        ))
    }

    fn mean(&self, b: &SqrtBelief<NX, NZ>) -> Vector<NX> {
        b.x
    }

    fn covariance(&self, b: &SqrtBelief<NX, NZ>) -> Option<Matrix<NX, NX>> {
        Some(b.s * b.s.transpose())
    }

    fn error_transition(&self, b: &SqrtBelief<NX, NZ>) -> Option<Matrix<NX, NX>> {
        let Some((k_bar, l_s, h)) = &b.gain else {
            return Some(b.f);
        };
        // K = K̄ L_S⁻¹, i.e. Kᵀ = L_S⁻ᵀ K̄ᵀ.
        let kt = l_s.transpose().solve_upper_triangular(&k_bar.transpose())?;
        Some((Matrix::<NX, NX>::identity() - kt.transpose() * h) * b.f)
    }
}
