//! The running-mean baseline of `simulation_quadrotor.m` (seed 000, lines 152–175).
//!
//! At step k the last `window` measurements (indices max(0, k−window+1)..=k, fewer at the
//! start, including the noise-free z_0) are averaged; the smoothed y, θ, θ̇ are substituted
//! into the estimate, and x, ẋ, ẏ are propagated with the smoothed θ:
//!
//! x_k = x_{k−1} + ẋ_{k−1}Δt,  ẋ_k = ẋ_{k−1} − (u1+u2)/m · sin θ̄_k Δt,
//! ẏ_k = ẏ_{k−1} + ((u1+u2)/m · cos θ̄_k − g) Δt.
//!
//! The seed names its window "10" but averages `max(1, t−10):t`, i.e. 11 samples; the spec key
//! `window` counts samples, so the seed's filter is `window = 11`.
//!
//! Requirements on the model: the P1 planar quadrotor (it reads y, θ, θ̇ directly from the
//! measurement). It carries no covariance, so its NEES/NIS are reported as null.

use super::model::PlanarP1;
use crate::filter::{Filter, FilterError, Innovation};
use crate::linalg::{Matrix, Vector};
use crate::model::{Measurement, Model};

/// Running-mean baseline configuration.
#[derive(Clone, Debug, PartialEq)]
pub struct RunningMean {
    /// Number of samples averaged (11 in the seeds).
    pub window: usize,
}

/// The running mean's belief: the estimate and the measurement window.
#[derive(Clone, Debug, PartialEq)]
pub struct WindowBelief {
    x: Vector<6>,
    /// The last `window` measurements in a ring; `len` of them are valid.
    ring: Vec<Vector<3>>,
    next: usize,
    len: usize,
}

impl WindowBelief {
    fn push(&mut self, z: Vector<3>) {
        let cap = self.ring.len();
        self.ring[self.next] = z;
        self.next += 1;
        if self.next == cap {
            self.next = 0;
        }
        self.len = (self.len + 1).min(cap);
    }

    /// Mean of the window, summed oldest first as MATLAB's `mean` over the rows does.
    fn mean(&self) -> Vector<3> {
        // The oldest sample first, as before: the ring split at `start` into its two runs
        // (no integer division per sample; the sum's order, and so its bits, is unchanged).
        let cap = self.ring.len();
        let start = if self.next >= self.len {
            self.next - self.len
        } else {
            self.next + cap - self.len
        };
        let (tail, head) = if start + self.len <= cap {
            (&self.ring[start..start + self.len], &self.ring[..0])
        } else {
            (&self.ring[start..], &self.ring[..start + self.len - cap])
        };
        let mut sum = Vector::<3>::zeros();
        for z in tail.iter().chain(head) {
            sum += z;
        }
        sum / self.len as f64
    }
}

impl Filter<6, 2, 3, PlanarP1> for RunningMean {
    type Belief = WindowBelief;

    fn init(
        &self,
        _model: &PlanarP1,
        x0_hat: &Vector<6>,
        _p0: &Matrix<6, 6>,
        z0: &Measurement<3>,
    ) -> WindowBelief {
        let mut b = WindowBelief {
            x: *x0_hat,
            ring: vec![Vector::<3>::zeros(); self.window.max(1)],
            next: 0,
            len: 0,
        };
        b.push(z0.z);
        b
    }

    fn predict(
        &self,
        _model: &PlanarP1,
        _b: &mut WindowBelief,
        _u: &Vector<2>,
    ) -> Result<(), FilterError> {
        // Everything happens at the update: the propagation uses the *current* smoothed θ.
        Ok(())
    }

    fn update(
        &self,
        model: &PlanarP1,
        b: &mut WindowBelief,
        u: &Vector<2>,
        z: &Measurement<3>,
    ) -> Result<Option<Innovation<3>>, FilterError> {
        b.push(z.z);
        let smooth = b.mean();
        let dt = model.dt_s();
        let prev = b.x;
        let (xdd, ydd, _) = model.accelerations(smooth[1], u);
        b.x = Vector::<6>::new(
            prev[0] + prev[1] * dt,
            prev[1] + xdd * dt,
            smooth[0],
            prev[3] + ydd * dt,
            smooth[1],
            smooth[2],
        );
        if !b.x.iter().all(|v| v.is_finite()) {
            return Err(FilterError::NonFinite {
                what: "state estimate",
            });
        }
        Ok(None)
    }

    fn mean(&self, b: &WindowBelief) -> Vector<6> {
        b.x
    }

    fn covariance(&self, _b: &WindowBelief) -> Option<Matrix<6, 6>> {
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::Availability;
    use crate::systems::planar::model::PlanarParams;

    #[test]
    fn window_averages_the_last_samples_including_z0() {
        let model = PlanarP1::new(PlanarParams::default());
        let f = RunningMean { window: 3 };
        let meas = |v: f64| Measurement {
            z: Vector::<3>::new(v, 0.0, 0.0),
            available: Availability::all(3),
        };
        let mut b = f.init(
            &model,
            &Vector::<6>::zeros(),
            &Matrix::<6, 6>::identity(),
            &meas(1.0),
        );
        let u = Vector::<2>::new(2.4525, 2.4525); // hover: thrust = m g
        f.update(&model, &mut b, &u, &meas(2.0)).unwrap();
        assert_eq!(f.mean(&b)[2], 1.5);
        f.update(&model, &mut b, &u, &meas(3.0)).unwrap();
        assert_eq!(f.mean(&b)[2], 2.0);
        f.update(&model, &mut b, &u, &meas(7.0)).unwrap();
        assert_eq!(f.mean(&b)[2], 4.0); // (2 + 3 + 7) / 3: z0 has left the window
        assert!(f.mean(&b)[3].abs() < 1e-15); // hover thrust: no vertical acceleration
    }
}
