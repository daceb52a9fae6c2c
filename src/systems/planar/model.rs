//! P1/P2 — the planar quadrotor of seeds 000, 001 and 003.
//!
//! State `[x, ẋ, y, ẏ, θ, θ̇]`, input `[u1, u2]` (rotor thrusts, N):
//!
//! m ẍ = −(u1+u2) sin θ,  m ÿ = (u1+u2) cos θ − m g,  I θ̈ = r (u1 − u2),
//!
//! integrated by one explicit Euler step per sample exactly as `simulation_quadrotor.m` does:
//! positions advance with the *previous* velocities, velocities with the accelerations at the
//! previous θ and the control of the new step.
//!
//! Two sensor sets:
//! * [`PlanarSensor::P1`] — `[y, θ, θ̇]` (seeds 000/001, linear `C`); the θ residual is wrapped
//!   to [−π, π) as line 138 of `simulation_quadrotor.m` does;
//! * [`PlanarSensor::Imu`] — `[y, θ̇, ẍ, ÿ]` (seed 003): an altimeter, a gyro and the model's
//!   accelerations, nonlinear in θ and in the input.

use crate::linalg::{Matrix, Vector};
use crate::model::Model;

/// Physical parameters of the planar quadrotor (SI units).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PlanarParams {
    /// Mass m (kg).
    pub mass_kg: f64,
    /// Distance r from the centre to each rotor (m).
    pub arm_m: f64,
    /// Moment of inertia I (kg·m²).
    pub inertia_kg_m2: f64,
    /// Gravitational acceleration g (m/s²).
    pub gravity_m_s2: f64,
    /// Sample time Δt (s).
    pub dt_s: f64,
}

impl Default for PlanarParams {
    /// The seeds' values: m = 0.5, r = 0.15, I = 0.005, g = 9.81, Δt = 0.01.
    fn default() -> Self {
        PlanarParams {
            mass_kg: 0.5,
            arm_m: 0.15,
            inertia_kg_m2: 0.005,
            gravity_m_s2: 9.81,
            dt_s: 0.01,
        }
    }
}

/// Which sensor set the planar model carries.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PlanarSensor {
    /// `[y, θ, θ̇]` — seeds 000/001.
    P1,
    /// `[y, θ̇, ẍ, ÿ]` — seed 003's altimeter + IMU.
    Imu,
}

/// Measurement names of P1.
pub const P1_MEASUREMENTS: [&str; 3] = ["y", "theta", "thetadot"];
/// Measurement names of P2 (the IMU set).
pub const IMU_MEASUREMENTS: [&str; 4] = ["y", "thetadot", "xddot", "yddot"];

/// State names of the planar model, shared by both sensor sets.
pub const PLANAR_STATES: [&str; 6] = ["x", "xdot", "y", "ydot", "theta", "thetadot"];

/// The planar quadrotor with a sensor set of `NZ` components (3 for P1, 4 for the IMU set).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Planar<const NZ: usize> {
    /// Physical parameters.
    pub params: PlanarParams,
}

/// P1: the planar quadrotor measuring `[y, θ, θ̇]`.
pub type PlanarP1 = Planar<3>;
/// P2: the planar quadrotor measuring `[y, θ̇, ẍ, ÿ]`.
pub type PlanarImu = Planar<4>;

impl<const NZ: usize> Planar<NZ> {
    /// A planar model with the given parameters.
    pub fn new(params: PlanarParams) -> Self {
        Planar { params }
    }

    /// Accelerations `(ẍ, ÿ, θ̈)` at attitude θ under input u.
    #[inline]
    pub fn accelerations(&self, theta: f64, u: &Vector<2>) -> (f64, f64, f64) {
        let p = &self.params;
        let thrust = u[0] + u[1];
        let (s, c) = theta.sin_cos();
        (
            -s * thrust / p.mass_kg,
            c * thrust / p.mass_kg - p.gravity_m_s2,
            // Written as the seed writes it, r/I·u1 − r/I·u2, so the rounding matches too.
            p.arm_m / p.inertia_kg_m2 * u[0] - p.arm_m / p.inertia_kg_m2 * u[1],
        )
    }

    fn propagate_impl(&self, x: &Vector<6>, u: &Vector<2>) -> Vector<6> {
        let dt = self.params.dt_s;
        let (xdd, ydd, thdd) = self.accelerations(x[4], u);
        // x_t = x_{t−1} + Δx with Δx as on lines 64–71 of simulation_quadrotor.m.
        Vector::<6>::new(
            x[0] + x[1] * dt,
            x[1] + xdd * dt,
            x[2] + x[3] * dt,
            x[3] + ydd * dt,
            x[4] + x[5] * dt,
            x[5] + thdd * dt,
        )
    }

    fn transition_jacobian_impl(&self, x: &Vector<6>, u: &Vector<2>) -> Matrix<6, 6> {
        let p = &self.params;
        let dt = p.dt_s;
        let thrust = u[0] + u[1];
        let (s, c) = x[4].sin_cos();
        // F = I + A·Δt with A as in eq. (15) of seed 000 (lines 125–130 of the code).
        let mut f = Matrix::<6, 6>::identity();
        f[(0, 1)] = dt;
        f[(1, 4)] = -c * thrust / p.mass_kg * dt;
        f[(2, 3)] = dt;
        f[(3, 4)] = -s * thrust / p.mass_kg * dt;
        f[(4, 5)] = dt;
        f
    }
}

/// θ, the attitude: an angle state of both sensor sets.
const ANGLE_STATES: [usize; 1] = [4];
/// Where F = I + A·Δt may be non-zero (eq. 15 of seed 000): the diagonal and five entries of A.
const TRANSITION_PATTERN: [(usize, usize); 11] = [
    (0, 0),
    (0, 1),
    (1, 1),
    (1, 4),
    (2, 2),
    (2, 3),
    (3, 3),
    (3, 4),
    (4, 4),
    (4, 5),
    (5, 5),
];
/// P1's θ measurement: its residual is wrapped (line 138 of `simulation_quadrotor.m`).
const P1_ANGLE_MEASUREMENTS: [usize; 1] = [1];

impl Model<6, 2, 3> for PlanarP1 {
    fn dt_s(&self) -> f64 {
        self.params.dt_s
    }
    fn propagate(&self, x: &Vector<6>, u: &Vector<2>) -> Vector<6> {
        self.propagate_impl(x, u)
    }
    fn transition_jacobian(&self, x: &Vector<6>, u: &Vector<2>) -> Matrix<6, 6> {
        self.transition_jacobian_impl(x, u)
    }
    fn measure(&self, x: &Vector<6>, _u: &Vector<2>) -> Vector<3> {
        Vector::<3>::new(x[2], x[4], x[5])
    }
    fn measurement_jacobian(&self, _x: &Vector<6>, _u: &Vector<2>) -> Matrix<3, 6> {
        let mut h = Matrix::<3, 6>::zeros();
        h[(0, 2)] = 1.0;
        h[(1, 4)] = 1.0;
        h[(2, 5)] = 1.0;
        h
    }
    fn transition_pattern(&self) -> Option<&[(usize, usize)]> {
        Some(&TRANSITION_PATTERN)
    }
    fn measurement_selection(&self) -> Option<[usize; 3]> {
        Some([2, 4, 5])
    }
    fn angle_states(&self) -> &[usize] {
        &ANGLE_STATES
    }
    fn angle_measurements(&self) -> &[usize] {
        &P1_ANGLE_MEASUREMENTS
    }
    fn measurement_uses_input(&self) -> bool {
        false
    }
}

impl Model<6, 2, 4> for PlanarImu {
    fn dt_s(&self) -> f64 {
        self.params.dt_s
    }
    fn propagate(&self, x: &Vector<6>, u: &Vector<2>) -> Vector<6> {
        self.propagate_impl(x, u)
    }
    fn transition_jacobian(&self, x: &Vector<6>, u: &Vector<2>) -> Matrix<6, 6> {
        self.transition_jacobian_impl(x, u)
    }
    fn measure(&self, x: &Vector<6>, u: &Vector<2>) -> Vector<4> {
        let (xdd, ydd, _) = self.accelerations(x[4], u);
        Vector::<4>::new(x[2], x[5], xdd, ydd)
    }
    fn measurement_jacobian(&self, x: &Vector<6>, u: &Vector<2>) -> Matrix<4, 6> {
        let p = &self.params;
        let thrust = u[0] + u[1];
        let (s, c) = x[4].sin_cos();
        // Seed 003's C matrix: rows 3–4 are ∂(ẍ, ÿ)/∂θ.
        let mut h = Matrix::<4, 6>::zeros();
        h[(0, 2)] = 1.0;
        h[(1, 5)] = 1.0;
        h[(2, 4)] = -c * thrust / p.mass_kg;
        h[(3, 4)] = -s * thrust / p.mass_kg;
        h
    }
    fn transition_pattern(&self) -> Option<&[(usize, usize)]> {
        Some(&TRANSITION_PATTERN)
    }
    // ẍ and ÿ are accelerations, not angles: only the state θ is.
    fn angle_states(&self) -> &[usize] {
        &ANGLE_STATES
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn numeric_jacobian<const NZ: usize>(
        f: impl Fn(&Vector<6>) -> Vector<NZ>,
        x: &Vector<6>,
    ) -> Matrix<NZ, 6> {
        let mut j = Matrix::<NZ, 6>::zeros();
        for i in 0..6 {
            let h = 1e-6;
            let mut xp = *x;
            let mut xm = *x;
            xp[i] += h;
            xm[i] -= h;
            j.set_column(i, &((f(&xp) - f(&xm)) / (2.0 * h)));
        }
        j
    }

    #[test]
    fn jacobians_match_central_differences() {
        let x = Vector::<6>::new(0.3, -1.0, 12.0, 2.0, 0.7, -0.4);
        let u = Vector::<2>::new(4.05, 3.9);
        let p1 = PlanarP1::new(PlanarParams::default());
        let imu = PlanarImu::new(PlanarParams::default());
        let fd = numeric_jacobian(|x| p1.propagate(x, &u), &x);
        assert!((fd - p1.transition_jacobian(&x, &u)).amax() < 1e-7);
        let hd = numeric_jacobian(|x| imu.measure(x, &u), &x);
        assert!((hd - imu.measurement_jacobian(&x, &u)).amax() < 1e-6);
        let hd = numeric_jacobian(|x| p1.measure(x, &u), &x);
        assert!((hd - p1.measurement_jacobian(&x, &u)).amax() < 1e-9);
    }

    #[test]
    fn one_euler_step_by_hand() {
        // Fall scenario, first step: x0 = [0, −1, 15, −3, −(π/2 − atan 3), 0], u = 2.7·(1 ± …).
        let m = PlanarP1::new(PlanarParams::default());
        let th = -(std::f64::consts::FRAC_PI_2 - 3f64.atan());
        let x0 = Vector::<6>::new(0.0, -1.0, 15.0, -3.0, th, 0.0);
        let u = Vector::<2>::new(2.7, 2.7);
        let x1 = m.propagate(&x0, &u);
        // sin θ = −1/√10, cos θ = 3/√10; thrust/m = 10.8.
        let s10 = 10f64.sqrt();
        let expected = [
            -0.01,
            -1.0 + 10.8 / s10 * 0.01,
            15.0 - 0.03,
            -3.0 + (10.8 * 3.0 / s10 - 9.81) * 0.01,
            th,
            0.0,
        ];
        for i in 0..6 {
            assert!((x1[i] - expected[i]).abs() < 1e-14, "state {i}");
        }
    }

    #[test]
    fn wrap_matches_matlab_mod() {
        use crate::model::wrap_angle;
        let pi = std::f64::consts::PI;
        assert!((wrap_angle(0.1) - 0.1).abs() < 1e-15);
        assert!((wrap_angle(2.0 * pi + 0.1) - 0.1).abs() < 1e-12);
        assert!((wrap_angle(-2.0 * pi - 0.1) + 0.1).abs() < 1e-12);
        assert_eq!(wrap_angle(pi), -pi); // the interval is half-open, [−π, π)
        assert!((wrap_angle(-3.5) - (-3.5 + 2.0 * pi)).abs() < 1e-12);
    }
}
