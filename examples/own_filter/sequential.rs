//! A user's filter for kfmc's built-in planar quadrotor (`kind = "user_filter"`, sensor P1):
//! an EKF that processes the measurement components one scalar at a time.
//!
//! With a diagonal R the components are independent, so each can be a scalar update:
//! s = h P hᵀ + r, k = P hᵀ / s, no matrix inverse at all. Each component re-linearises at the
//! estimate the previous ones produced; for P1's linear sensor that is exactly the batch
//! update. The scalar innovations divided by √s are the whitened innovation L⁻¹ν of the batch
//! S = L Lᵀ (sequential processing is a Cholesky factorisation of S), so NIS and the
//! whiteness test see the same numbers as for a batch filter.

use kfmc::prelude::*;

use super::user_ekf::Belief;

/// The sequential EKF: its assumed Q and the diagonal of its assumed R.
#[derive(Clone, Debug, PartialEq)]
pub struct SequentialEkf<const NX: usize, const NZ: usize> {
    /// Assumed process-noise covariance.
    pub q: Matrix<NX, NX>,
    /// Assumed measurement-noise variance per component.
    pub r: Vector<NZ>,
}

impl<const NX: usize, const NU: usize, const NZ: usize, M> Filter<NX, NU, NZ, M>
    for SequentialEkf<NX, NZ>
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
        // The reported innovation is the one against the prediction, before any component.
        let mut residual = model.residual(&z.z, &model.measure(&b.x, u));
        let mut whitened = Vector::<NZ>::zeros();
        for i in 0..NZ {
            if !z.available.has(i) {
                residual[i] = 0.0;
                continue;
            }
            let h = model.measurement_jacobian(&b.x, u).row(i).into_owned();
            let nu = model.residual(&z.z, &model.measure(&b.x, u))[i];
            let ph = b.p * h.transpose();
            let s = (h * ph)[(0, 0)] + self.r[i];
            // A NaN s must fail here too, hence not `s <= 0.0`.
            if !kfmc::prelude::positive(s) {
                return Err(FilterError::NotPositiveDefinite {
                    which: "innovation variance s",
                });
            }
            let k = ph / s;
            b.x += k * nu;
            let i_kh = Matrix::<NX, NX>::identity() - k * h;
            // Joseph form: a scalar update per component compounds round-off; this form keeps
            // P symmetric and positive semi-definite anyway.
            b.p = i_kh * b.p * i_kh.transpose() + k * k.transpose() * self.r[i];
            b.a = i_kh * b.a;
            whitened[i] = nu / s.sqrt();
        }
        b.check_finite()?;
        Ok(Some(Innovation::new(residual, whitened, z.available)))
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

/// `kind = "user_filter"`.
pub fn sequential_kind<const NX: usize, const NU: usize, const NZ: usize, M>()
-> impl FilterKind<NX, NU, NZ, M>
where
    M: Model<NX, NU, NZ> + 'static,
{
    FnKind::new(
        "user_filter",
        "the example's sequential-update EKF (one scalar update per component, no inverse); q_std, r_std",
        // kfmc builds R as diag(r_std²)·r_scale, so its diagonal is all of it.
        |_: &M, n: &AssumedNoise<NX, NZ>| SequentialEkf {
            q: n.q,
            r: n.r.diagonal(),
        },
    )
}
