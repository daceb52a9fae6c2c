//! The user's own EKF (`kind = "user_ekf"`), written against kfmc's `Filter` trait only.
//!
//! It is the textbook EKF in the Joseph form, with S inverted through nalgebra's Cholesky:
//! a different code path from kfmc's `ekf`, the same algebra, so on the same runs the two
//! agree to round-off. That agreement is what `tests/it/systems/own_filter.rs` checks.

use kfmc::prelude::*;

/// Mean, covariance and the last step's error transition.
#[derive(Clone, Debug, PartialEq)]
pub struct Belief<const NX: usize> {
    /// x̂
    pub x: Vector<NX>,
    /// P
    pub p: Matrix<NX, NX>,
    /// A_k = (I − K H) F of the last step. kfmc's calibrated NEES test (the `consistent`
    /// verdict) needs it; without it only the model-free t-test is computed.
    pub a: Matrix<NX, NX>,
}

impl<const NX: usize> Belief<NX> {
    /// A belief with mean `x` and covariance `p`.
    pub fn new(x: Vector<NX>, p: Matrix<NX, NX>) -> Self {
        Belief {
            x,
            p,
            a: Matrix::<NX, NX>::identity(),
        }
    }

    /// The predict step shared by both user filters.
    pub fn predict<const NU: usize, const NZ: usize, M: Model<NX, NU, NZ>>(
        &mut self,
        model: &M,
        q: &Matrix<NX, NX>,
        u: &Vector<NU>,
    ) -> Result<(), FilterError> {
        let f = model.transition_jacobian(&self.x, u);
        self.x = model.propagate(&self.x, u);
        self.p = f * self.p * f.transpose() + q;
        self.a = f;
        self.check_finite()
    }

    /// Turns a NaN or an overflow into a run failure at this step instead of a silent NaN row.
    pub fn check_finite(&self) -> Result<(), FilterError> {
        if !self.x.sum().is_finite() {
            return Err(FilterError::NonFinite {
                what: "state estimate",
            });
        }
        if !self.p.trace().is_finite() {
            return Err(FilterError::NonFinite {
                what: "state covariance",
            });
        }
        Ok(())
    }
}

/// The user's EKF: the Q and R it assumes.
#[derive(Clone, Debug, PartialEq)]
pub struct UserEkf<const NX: usize, const NZ: usize> {
    /// Assumed process-noise covariance.
    pub q: Matrix<NX, NX>,
    /// Assumed measurement-noise covariance.
    pub r: Matrix<NZ, NZ>,
}

impl<const NX: usize, const NU: usize, const NZ: usize, M> Filter<NX, NU, NZ, M> for UserEkf<NX, NZ>
where
    M: Model<NX, NU, NZ>,
{
    type Belief = Belief<NX>;

    fn init(
        &self,
        _model: &M,
        x0_hat: &Vector<NX>,
        p0: &Matrix<NX, NX>,
        _z0: &Measurement<NZ>,
    ) -> Belief<NX> {
        Belief::new(*x0_hat, *p0)
    }

    fn predict(&self, model: &M, b: &mut Belief<NX>, u: &Vector<NU>) -> Result<(), FilterError> {
        b.predict(model, &self.q, u)
    }

    fn update(
        &self,
        model: &M,
        b: &mut Belief<NX>,
        u: &Vector<NU>,
        z: &Measurement<NZ>,
    ) -> Result<Option<Innovation<NZ>>, FilterError> {
        if z.available.count() == 0 {
            return Ok(None);
        }
        let mut h = model.measurement_jacobian(&b.x, u);
        let mut nu = model.residual(&z.z, &model.measure(&b.x, u));
        let mut r = self.r;
        if z.available != Availability::all(NZ) {
            // A missing component must not move the estimate: zero its row of H and ν and
            // give it unit variance, so S stays invertible and K's column for it is zero.
            for i in (0..NZ).filter(|&i| !z.available.has(i)) {
                h.row_mut(i).fill(0.0);
                nu[i] = 0.0;
                r.row_mut(i).fill(0.0);
                r.column_mut(i).fill(0.0);
                r[(i, i)] = 1.0;
            }
        }
        let s = h * b.p * h.transpose() + r;
        let chol = s.cholesky().ok_or(FilterError::NotPositiveDefinite {
            which: "innovation covariance S",
        })?;
        let k = b.p * h.transpose() * chol.inverse();
        b.x += k * nu;
        let i_kh = Matrix::<NX, NX>::identity() - k * h;
        // Joseph form: P stays symmetric and positive semi-definite under round-off.
        b.p = i_kh * b.p * i_kh.transpose() + k * r * k.transpose();
        b.a = i_kh * b.a;
        b.check_finite()?;
        let whitened = chol
            .l()
            .solve_lower_triangular(&nu)
            .ok_or(FilterError::Singular {
                which: "Cholesky factor of S",
            })?;
        Ok(Some(Innovation::new(nu, whitened, z.available)))
    }

    fn mean(&self, b: &Belief<NX>) -> Vector<NX> {
        b.x
    }

    fn covariance(&self, b: &Belief<NX>) -> Option<Matrix<NX, NX>> {
        Some(b.p)
    }

    fn error_transition(&self, b: &Belief<NX>) -> Option<Matrix<NX, NX>> {
        Some(b.a)
    }
}

/// `kind = "user_ekf"`, on any model: its only keys are the assumed noise (`q_std`,
/// `r_std`), so kfmc's [`FnKind`] reads them and the kind is this one function.
pub fn user_ekf_kind<const NX: usize, const NU: usize, const NZ: usize, M>()
-> impl FilterKind<NX, NU, NZ, M>
where
    M: Model<NX, NU, NZ> + 'static,
{
    FnKind::new(
        "user_ekf",
        "the example's own EKF (Joseph form, Cholesky of S); r_std (q_std unless the model has a full Q)",
        |_: &M, n: &AssumedNoise<NX, NZ>| UserEkf { q: n.q, r: n.r },
    )
}
