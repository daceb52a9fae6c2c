//! Open-loop prediction (seed 002 §4.3): the Kalman filter's time update alone,
//! x̂_k = f(x̂_{k−1}, u_k), P_k = F P_{k−1} Fᵀ + Q, with every measurement ignored.
//!
//! It answers the question the seed's Monte Carlo figures ask by eye: does the propagated
//! covariance describe the spread of the truth around the noise-free prediction? Over runs
//! with a sampled initial estimate, its per-step ANEES must stay inside the χ² band and the
//! sample covariance of x_k − x̂_k must match P_k (tests/it/systems/linear_studies.rs). It has no innovations,
//! so NIS is null.

use super::ekf::Gaussian;
use super::{Ekf, Filter, FilterError, Innovation};
use crate::linalg::{Matrix, Vector};
use crate::model::{Measurement, Model};

/// Predict-only configuration: the assumed Q (R is never used).
#[derive(Clone, Debug, PartialEq)]
pub struct OpenLoop<const NX: usize, const NZ: usize> {
    /// The time update is the EKF's, so the two can never drift apart.
    pub predictor: Ekf<NX, NZ>,
}

impl<const NX: usize, const NU: usize, const NZ: usize, M: Model<NX, NU, NZ>> Filter<NX, NU, NZ, M>
    for OpenLoop<NX, NZ>
{
    type Belief = Gaussian<NX>;

    fn init(
        &self,
        model: &M,
        x0_hat: &Vector<NX>,
        p0: &Matrix<NX, NX>,
        z0: &Measurement<NZ>,
    ) -> Gaussian<NX> {
        Filter::<NX, NU, NZ, M>::init(&self.predictor, model, x0_hat, p0, z0)
    }

    fn predict(&self, model: &M, b: &mut Gaussian<NX>, u: &Vector<NU>) -> Result<(), FilterError> {
        self.predictor.predict(model, b, u)
    }

    fn update(
        &self,
        _model: &M,
        _b: &mut Gaussian<NX>,
        _u: &Vector<NU>,
        _z: &Measurement<NZ>,
    ) -> Result<Option<Innovation<NZ>>, FilterError> {
        Ok(None)
    }

    fn mean(&self, b: &Gaussian<NX>) -> Vector<NX> {
        b.x
    }

    fn covariance(&self, b: &Gaussian<NX>) -> Option<Matrix<NX, NX>> {
        Some(b.p)
    }

    fn covariance_ref<'b>(&self, b: &'b Gaussian<NX>) -> Option<&'b Matrix<NX, NX>> {
        Some(&b.p)
    }

    fn error_transition(&self, b: &Gaussian<NX>) -> Option<Matrix<NX, NX>> {
        Filter::<NX, NU, NZ, M>::error_transition(&self.predictor, b)
    }

    fn repair_covariance(&self, b: &mut Gaussian<NX>) -> bool {
        Filter::<NX, NU, NZ, M>::repair_covariance(&self.predictor, b)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::filter::CovarianceUpdate;
    use crate::model::Availability;
    use crate::systems::linear_quadrotor::model::{Linear3, LinearSensor};

    #[test]
    fn the_covariance_follows_the_lyapunov_recursion_and_measurements_are_ignored() {
        let model = Linear3::new(LinearSensor::Positions, 0.1).unwrap();
        let d = model.discrete().clone();
        let filter = OpenLoop {
            predictor: Ekf {
                q: d.q,
                r: model.r(),
                update_form: CovarianceUpdate::Standard,
            },
        };
        let x0 = Vector::<6>::new(1.0, 0.0, 1.0, 0.0, 1.0, 0.0);
        let z = Measurement {
            z: Vector::<3>::new(5.0, 5.0, 5.0),
            available: Availability::all(3),
        };
        let mut b =
            Filter::<6, 4, 3, _>::init(&filter, &model, &x0, &Matrix::<6, 6>::identity(), &z);
        let (mut x, mut p) = (x0, Matrix::<6, 6>::identity());
        let u = Vector::<4>::new(0.1, 0.0, -0.1, 0.2);
        for _ in 0..400 {
            filter.predict(&model, &mut b, &u).unwrap();
            assert!(filter.update(&model, &mut b, &u, &z).unwrap().is_none());
            x = d.f * x + d.g * u;
            p = d.f * p * d.f.transpose() + d.q;
        }
        assert!((b.x - x).amax() < 1e-12);
        assert!((b.p - p).amax() < 1e-12 * p.amax());
        // Seed §4.3's reading of its Figure 3: position variances grow, ż's settles.
        assert!(p[(0, 0)] > 1.0 && p[(4, 4)] > 1.0);
        assert!(p[(5, 5)] < 1.0);
        assert_eq!(
            Filter::<6, 4, 3, Linear3>::error_transition(&filter, &b),
            Some(d.f)
        );
    }
}
