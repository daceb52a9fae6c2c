//! Square-root covariance filter: propagates a lower-triangular S with P = S Sᵀ and never forms
//! P to re-factorise it.
//!
//! Both steps triangularise a stacked pre-array by QR ([`crate::linalg::triangularize`]):
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
//! techniques", IEEE TAC 16(6), 1971; Verhaegen & Van Dooren (1986), the seed's [8].

use nalgebra::DMatrix;

use super::{Filter, FilterError, Innovation, check_finite, mask_rows};
use crate::linalg::{Matrix, SmallCholesky, Vector, triangularize};
use crate::model::{Measurement, Model};

/// Square-root filter configuration: the assumed Q and R (both positive definite).
#[derive(Clone, Debug, PartialEq)]
pub struct SquareRoot<const NX: usize, const NZ: usize> {
    /// Assumed process-noise covariance Q.
    pub q: Matrix<NX, NX>,
    /// Assumed measurement-noise covariance R.
    pub r: Matrix<NZ, NZ>,
}

/// The square-root filter's belief.
#[derive(Clone, Debug, PartialEq)]
pub struct SqrtBelief<const NX: usize> {
    /// x̂
    pub x: Vector<NX>,
    /// S, lower triangular, P = S Sᵀ.
    pub s: Matrix<NX, NX>,
    f: Matrix<NX, NX>,
    i_kh: Matrix<NX, NX>,
}

fn factor<const N: usize>(
    a: &Matrix<N, N>,
    which: &'static str,
) -> Result<Matrix<N, N>, FilterError> {
    SmallCholesky::new(a)
        .map(|c| *c.l())
        .ok_or(FilterError::NotPositiveDefinite { which })
}

impl<const NX: usize, const NU: usize, const NZ: usize, M: Model<NX, NU, NZ>> Filter<NX, NU, NZ, M>
    for SquareRoot<NX, NZ>
{
    type Belief = SqrtBelief<NX>;

    fn init(
        &self,
        _model: &M,
        x0_hat: &Vector<NX>,
        p0: &Matrix<NX, NX>,
        _z0: &Measurement<NZ>,
    ) -> SqrtBelief<NX> {
        // The one Cholesky factorisation of a covariance: P_0 is given, not propagated.
        let s = factor(p0, "initial covariance P0")
            .unwrap_or_else(|_| Matrix::<NX, NX>::from_element(f64::NAN));
        SqrtBelief {
            x: *x0_hat,
            s,
            f: Matrix::<NX, NX>::identity(),
            i_kh: Matrix::<NX, NX>::identity(),
        }
    }

    fn predict(
        &self,
        model: &M,
        b: &mut SqrtBelief<NX>,
        u: &Vector<NU>,
    ) -> Result<(), FilterError> {
        let f = model.transition_jacobian(&b.x, u);
        let l_q = factor(&self.q, "process noise Q")?;
        let fs = f * b.s;
        let pre = DMatrix::<f64>::from_fn(NX, 2 * NX, |i, j| {
            if j < NX { fs[(i, j)] } else { l_q[(i, j - NX)] }
        });
        let post = triangularize(&pre);
        b.s = Matrix::<NX, NX>::from_fn(|i, j| post[(i, j)]);
        b.x = model.propagate(&b.x, u);
        b.f = f;
        b.i_kh = Matrix::<NX, NX>::identity();
        check_finite(&b.x, &b.s)
    }

    fn update(
        &self,
        model: &M,
        b: &mut SqrtBelief<NX>,
        u: &Vector<NU>,
        z: &Measurement<NZ>,
    ) -> Result<Option<Innovation<NZ>>, FilterError> {
        if z.available.count() == 0 {
            return Ok(None);
        }
        let mut h = model.measurement_jacobian(&b.x, u);
        let mut nu = model.residual(&z.z, &model.measure(&b.x, u));
        let r = mask_rows(&self.r, z.available, &mut h, &mut nu);
        let l_r = factor(&r, "measurement noise R")?;
        let hs = h * b.s;
        let n = NZ + NX;
        let mut pre = DMatrix::<f64>::zeros(n, n);
        for i in 0..NZ {
            for j in 0..NZ {
                pre[(i, j)] = l_r[(i, j)];
            }
            for j in 0..NX {
                pre[(i, NZ + j)] = hs[(i, j)];
            }
        }
        for i in 0..NX {
            for j in 0..NX {
                pre[(NZ + i, NZ + j)] = b.s[(i, j)];
            }
        }
        let post = triangularize(&pre);
        let l_s = Matrix::<NZ, NZ>::from_fn(|i, j| post[(i, j)]);
        let k_bar = Matrix::<NX, NZ>::from_fn(|i, j| post[(NZ + i, j)]);
        // L_S has a positive diagonal, so it is S's Cholesky factor; a zero pivot means S is
        // singular.
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
        b.s = Matrix::<NX, NX>::from_fn(|i, j| post[(NZ + i, NZ + j)]);
        // K = K̄ L_S⁻¹, i.e. Kᵀ = L_S⁻ᵀ K̄ᵀ; only the error transition needs it.
        if let Some(kt) = l_s.transpose().solve_upper_triangular(&k_bar.transpose()) {
            b.i_kh = Matrix::<NX, NX>::identity() - kt.transpose() * h;
        }
        check_finite(&b.x, &b.s)?;
        Ok(Some(Innovation::new(nu, whitened, z.available)))
    }

    fn mean(&self, b: &SqrtBelief<NX>) -> Vector<NX> {
        b.x
    }

    fn covariance(&self, b: &SqrtBelief<NX>) -> Option<Matrix<NX, NX>> {
        Some(b.s * b.s.transpose())
    }

    fn error_transition(&self, b: &SqrtBelief<NX>) -> Option<Matrix<NX, NX>> {
        Some(b.i_kh * b.f)
    }
}
