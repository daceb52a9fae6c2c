//! The user's model: a 2-D constant-velocity target seen by a range-bearing sensor.
//!
//! State `[px, vx, py, vy]` (m, m/s), no input. The acceleration is white noise of spectral
//! density q (m²/s³) on each axis, so the discrete Q is full within an axis:
//! q·[[Δt³/3, Δt²/2], [Δt²/2, Δt]] (Bar-Shalom, Li & Kirubarajan 2001, §6.2.2).
//! The sensor at (sx, sy) reports range r = ‖p − s‖ and bearing β = atan2(py − sy, px − sx).

use std::f64::consts::PI;

use kfmc::prelude::*;

/// State names, in order (the tables' `rmse_<state>` columns).
pub const STATES: [&str; 4] = ["px", "vx", "py", "vy"];
/// Their units.
pub const UNITS: [&str; 4] = ["m", "m/s", "m", "m/s"];
/// Measurement components.
pub const MEASUREMENTS: [&str; 2] = ["range", "bearing"];

/// Wraps an angle to [−π, π).
pub fn wrap(a: f64) -> f64 {
    (a + PI).rem_euclid(2.0 * PI) - PI
}

/// The constant-velocity target and its sensor.
#[derive(Clone, Debug, PartialEq)]
pub struct CvRangeBearing {
    dt_s: f64,
    sensor_xy: [f64; 2],
    f: Matrix<4, 4>,
    q: Matrix<4, 4>,
}

impl CvRangeBearing {
    /// The model at sample time `dt_s` with acceleration spectral density `accel_psd`.
    pub fn new(dt_s: f64, accel_psd: f64, sensor_xy: [f64; 2]) -> Self {
        let mut f = Matrix::<4, 4>::identity();
        f[(0, 1)] = dt_s;
        f[(2, 3)] = dt_s;
        let (t, t2, t3) = (dt_s, dt_s * dt_s / 2.0, dt_s.powi(3) / 3.0);
        let mut q = Matrix::<4, 4>::zeros();
        for a in [0, 2] {
            q[(a, a)] = t3;
            q[(a, a + 1)] = t2;
            q[(a + 1, a)] = t2;
            q[(a + 1, a + 1)] = t;
        }
        CvRangeBearing {
            dt_s,
            sensor_xy,
            f,
            q: q * accel_psd,
        }
    }

    /// The discrete process-noise covariance Q.
    pub fn q(&self) -> Matrix<4, 4> {
        self.q
    }

    fn offset(&self, x: &Vector<4>) -> (f64, f64) {
        (x[0] - self.sensor_xy[0], x[2] - self.sensor_xy[1])
    }
}

impl Model<4, 0, 2> for CvRangeBearing {
    fn dt_s(&self) -> f64 {
        self.dt_s
    }

    fn propagate(&self, x: &Vector<4>, _u: &Vector<0>) -> Vector<4> {
        self.f * x
    }

    fn transition_jacobian(&self, _x: &Vector<4>, _u: &Vector<0>) -> Matrix<4, 4> {
        self.f
    }

    fn measure(&self, x: &Vector<4>, _u: &Vector<0>) -> Vector<2> {
        let (dx, dy) = self.offset(x);
        Vector::<2>::new(dx.hypot(dy), dy.atan2(dx))
    }

    fn measurement_jacobian(&self, x: &Vector<4>, _u: &Vector<0>) -> Matrix<2, 4> {
        let (dx, dy) = self.offset(x);
        let r2 = dx * dx + dy * dy;
        let r = r2.sqrt();
        #[rustfmt::skip]
        let h = Matrix::<2, 4>::new(
            dx / r, 0.0, dy / r, 0.0,
            -dy / r2, 0.0, dx / r2, 0.0,
        );
        h
    }

    fn residual(&self, z: &Vector<2>, z_pred: &Vector<2>) -> Vector<2> {
        // A target crossing the sensor's −x axis jumps from +π to −π; without the wrap the
        // bearing residual would be ≈ 2π there and the update would throw the estimate away.
        Vector::<2>::new(z[0] - z_pred[0], wrap(z[1] - z_pred[1]))
    }

    fn angle_measurements(&self) -> &[usize] {
        // The bearing: kfmc's `ukf` and `ckf` average it on the circle.
        &[1]
    }

    fn process_noise_covariance(&self) -> Option<Matrix<4, 4>> {
        Some(self.q)
    }
}
