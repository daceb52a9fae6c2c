//! L1: the linear 3-axis quadrotor of seed 002 (Vogel & Harris, ASEN 5044, 2016).
//!
//! State `[x, ẋ, y, ẏ, z, ż]`, four rotor thrusts `[T1, T2, T3, T4]`:
//!
//! ẋ = A x + B u + Γ ω,  ω ~ N(0, Q̃)  (seed eqs. 2–3), discretised at Δt = 0.1 s **here**, from
//! the continuous matrices: F = e^{AΔt} and G = ∫₀^Δt e^{As} ds B by zero-order hold (one
//! exponential of the augmented matrix [[A, B], [0, 0]]Δt), and Q = ∫₀^Δt e^{As} Γ Q̃ Γᵀ e^{Aᵀs} ds
//! by Van Loan's method. The seed's printed eq. 7 is only a 4-decimal check (its Q is even
//! indefinite as printed), never a source.
//!
//! Readings of seed 002's typos:
//! * Γ is printed 7×3; the intended matrix is 6×3 with the noise entering ẋ, ẏ, ż;
//! * Q̃ is printed non-symmetric (entries (1,3) = 0.005, (3,1) = 0.002); both are taken as 0.002,
//!   the reading that reproduces the seed's Q (its Q(ẋ, ż) = 0.0002 = 0.002·Δt).
//!
//! Sensor sets (seed eqs. 4–5): `positions` H = C (x, y, z), `velocities` H = C1 (ẋ, ẏ, ż),
//! `xy` H = C2 (x, y); R = diag(0.0933, 0.0885, 0.2450) (the first two for `xy`).
//!
//! The input: the seed's open-loop manoeuvre (section 3.5) is described only in words and its
//! feedback law G(u − T x) uses a matrix printed with few digits, so the truth here runs with
//! u = 0: it is driven by process noise alone, which is what the seed's NEES/NIS tests
//! exercise. F and G are still exact, so a control profile can be added later.

use crate::linalg::{Matrix, Vector};
use crate::model::{LinearMatrices, Model};
use crate::systems::linear::discretise::zoh_van_loan;

/// State names (`rmse_<state>` columns).
pub const LINEAR_STATES: [&str; 6] = ["x", "xdot", "y", "ydot", "z", "zdot"];

/// The seed's sample time Δt = 0.1 s.
pub const LINEAR_DT_S: f64 = 0.1;

/// The seed's measurement-noise variances R = diag(0.0933, 0.0885, 0.2450) (eq. 7).
pub const LINEAR_R_DIAG: [f64; 3] = [0.0933, 0.0885, 0.2450];

/// The continuous-time model ẋ = A x + B u + Γ ω, ω ~ N(0, Q̃).
#[derive(Clone, Debug, PartialEq)]
pub struct ContinuousLinear {
    /// A (6×6).
    pub a: Matrix<6, 6>,
    /// B (6×4).
    pub b: Matrix<6, 4>,
    /// Γ (6×3).
    pub gamma: Matrix<6, 3>,
    /// Q̃ (3×3), the noise intensity in (m/s²)²·s.
    pub q_tilde: Matrix<3, 3>,
}

impl ContinuousLinear {
    /// Seed 002, eqs. 2–3, with the readings in the module docs.
    pub fn seed() -> Self {
        #[rustfmt::skip]
        let a = Matrix::<6, 6>::from_row_slice(&[
            0.0, 1.0, 0.0, 0.0, 0.0, 0.0,
            0.0, -0.0104, 0.0, 0.0, 0.0, 0.0,
            0.0, 0.0, 0.0, 1.0, 0.0, 0.0,
            0.0, 0.0, 0.0, -0.0104, 0.0, 0.0,
            0.0, 0.0, 0.0, 0.0, 0.0, 1.0,
            0.0, 0.0, 0.0, 0.0, 0.0, -0.0208,
        ]);
        #[rustfmt::skip]
        let b = Matrix::<6, 4>::from_row_slice(&[
            0.0, 0.0, 0.0, 0.0,
            -0.04167, 0.0, 0.04167, 0.0,
            0.0, 0.0, 0.0, 0.0,
            0.0, -0.04167, 0.0, 0.04167,
            0.0, 0.0, 0.0, 0.0,
            0.4, 0.4, 0.4, 0.4,
        ]);
        let mut gamma = Matrix::<6, 3>::zeros();
        gamma[(1, 0)] = 1.0;
        gamma[(3, 1)] = 1.0;
        gamma[(5, 2)] = 1.0;
        #[rustfmt::skip]
        let q_tilde = Matrix::<3, 3>::from_row_slice(&[
            0.02, 0.005, 0.002,
            0.005, 0.02, 0.002,
            0.002, 0.002, 0.005,
        ]);
        ContinuousLinear {
            a,
            b,
            gamma,
            q_tilde,
        }
    }

    /// F, G and Q at sample time `dt_s` (zero-order hold and Van Loan, by the same function
    /// as every continuous `kind = "linear"` system).
    pub fn discretise(&self, dt_s: f64) -> Discrete {
        let w = self.gamma * self.q_tilde * self.gamma.transpose();
        let d = zoh_van_loan::<6, 4, 10, 12>(&self.a, &self.b, &w, dt_s);
        Discrete {
            f: d.f,
            g: d.g,
            q: d.q,
        }
    }
}

/// The discrete model x_k = F x_{k−1} + G u_k + w_k, w_k ~ N(0, Q).
#[derive(Clone, Debug, PartialEq)]
pub struct Discrete {
    /// F = e^{AΔt}.
    pub f: Matrix<6, 6>,
    /// G = ∫₀^Δt e^{As} ds B.
    pub g: Matrix<6, 4>,
    /// Q (full, symmetric positive definite).
    pub q: Matrix<6, 6>,
}

/// Which sensor set of the seed a [`Linear`] model measures.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LinearSensor {
    /// C: `[x, y, z]`.
    Positions,
    /// C1: `[ẋ, ẏ, ż]`.
    Velocities,
    /// C2: `[x, y]`.
    Xy,
}

impl LinearSensor {
    /// The name `model.sensor` gives it.
    pub fn name(self) -> &'static str {
        match self {
            LinearSensor::Positions => "positions",
            LinearSensor::Velocities => "velocities",
            LinearSensor::Xy => "xy",
        }
    }

    /// The measured state indices.
    pub fn rows(self) -> &'static [usize] {
        match self {
            LinearSensor::Positions => &[0, 2, 4],
            LinearSensor::Velocities => &[1, 3, 5],
            LinearSensor::Xy => &[0, 2],
        }
    }
    /// Number of measurement components.
    pub fn nz(self) -> usize {
        self.rows().len()
    }
}

/// The L1 model with `NZ` measured components (3 for positions/velocities, 2 for xy).
#[derive(Clone, Debug, PartialEq)]
pub struct Linear<const NZ: usize> {
    dt_s: f64,
    disc: Discrete,
    h: Matrix<NZ, 6>,
    sensor: LinearSensor,
    /// F's non-zero entries (F is constant), for [`Model::transition_pattern`].
    pattern: Vec<(usize, usize)>,
}

/// L1 measuring positions or velocities.
pub type Linear3 = Linear<3>;
/// L1 measuring x and y.
pub type Linear2 = Linear<2>;

/// A sensor set whose size does not match the model's measurement dimension.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[error("sensor set {sensor:?} measures {got} components, the model type has {expected}")]
pub struct SensorSizeError {
    /// The sensor set.
    pub sensor: LinearSensor,
    /// Its component count.
    pub got: usize,
    /// The model type's NZ.
    pub expected: usize,
}

impl<const NZ: usize> Linear<NZ> {
    /// The seed's model with sensor set `sensor`, discretised at `dt_s`.
    pub fn new(sensor: LinearSensor, dt_s: f64) -> Result<Self, SensorSizeError> {
        if sensor.nz() != NZ {
            return Err(SensorSizeError {
                sensor,
                got: sensor.nz(),
                expected: NZ,
            });
        }
        let mut h = Matrix::<NZ, 6>::zeros();
        for (i, &j) in sensor.rows().iter().enumerate() {
            h[(i, j)] = 1.0;
        }
        let disc = ContinuousLinear::seed().discretise(dt_s);
        Ok(Linear {
            dt_s,
            pattern: crate::linalg::nonzero_pattern(&disc.f),
            disc,
            h,
            sensor,
        })
    }

    /// The measured components' names.
    pub fn measurement_names(&self) -> Vec<&'static str> {
        let m = ["x", "y", "z"];
        let v = ["xdot", "ydot", "zdot"];
        match self.sensor {
            LinearSensor::Positions => m.to_vec(),
            LinearSensor::Velocities => v.to_vec(),
            LinearSensor::Xy => m[..2].to_vec(),
        }
    }

    /// F, G and Q.
    pub fn discrete(&self) -> &Discrete {
        &self.disc
    }

    /// H.
    pub fn h(&self) -> &Matrix<NZ, 6> {
        &self.h
    }

    /// The sensor set.
    pub fn sensor(&self) -> LinearSensor {
        self.sensor
    }

    /// R = diag of the seed's variances for the measured components.
    pub fn r(&self) -> Matrix<NZ, NZ> {
        Matrix::<NZ, NZ>::from_fn(|i, j| if i == j { LINEAR_R_DIAG[i] } else { 0.0 })
    }

    /// The truth's noise for [`crate::sim::simulate`]: measurement std √diag R; the process
    /// noise is the model's full Q ([`Model::process_noise_covariance`]), so no per-state std.
    pub fn truth_noise(&self) -> crate::sim::TruthNoise<6, NZ> {
        let r = self.r();
        crate::sim::TruthNoise {
            process_std: Vector::<6>::zeros(),
            measurement_std: Vector::<NZ>::from_fn(|i, _| r[(i, i)].sqrt()),
        }
    }

    /// Rank of the observability matrix [H; HF; …; HF⁵] (seed eq. 9), by faer's SVD.
    pub fn observability_rank(&self) -> usize {
        crate::analysis::unobservable_modes(&self.disc.f, &self.h).0
    }
}

impl<const NZ: usize> Model<6, 4, NZ> for Linear<NZ> {
    fn dt_s(&self) -> f64 {
        self.dt_s
    }

    #[inline]
    fn propagate(&self, x: &Vector<6>, u: &Vector<4>) -> Vector<6> {
        self.disc.f * x + self.disc.g * u
    }

    #[inline]
    fn transition_jacobian(&self, _x: &Vector<6>, _u: &Vector<4>) -> Matrix<6, 6> {
        self.disc.f
    }

    #[inline]
    fn measure(&self, x: &Vector<6>, _u: &Vector<4>) -> Vector<NZ> {
        self.h * x
    }

    #[inline]
    fn measurement_jacobian(&self, _x: &Vector<6>, _u: &Vector<4>) -> Matrix<NZ, 6> {
        self.h
    }

    fn transition_pattern(&self) -> Option<&[(usize, usize)]> {
        Some(&self.pattern)
    }

    fn measurement_selection(&self) -> Option<[usize; NZ]> {
        let mut sel = [0; NZ];
        sel.copy_from_slice(self.sensor.rows());
        Some(sel)
    }

    fn process_noise_covariance(&self) -> Option<Matrix<6, 6>> {
        Some(self.disc.q)
    }

    fn linear(&self) -> Option<LinearMatrices<6, 4, NZ>> {
        Some(LinearMatrices {
            f: self.disc.f,
            g: self.disc.g,
            h: self.h,
        })
    }

    fn measurement_uses_input(&self) -> bool {
        false
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Seed 002, eq. 7, as printed (4 decimals).
    #[rustfmt::skip]
    const F7: [f64; 36] = [
        1.0000, 0.0999, 0.0, 0.0, 0.0, 0.0,
        0.0, 0.9990, 0.0, 0.0, 0.0, 0.0,
        0.0, 0.0, 1.0000, 0.0999, 0.0, 0.0,
        0.0, 0.0, 0.0, 0.9990, 0.0, 0.0,
        0.0, 0.0, 0.0, 0.0, 1.0000, 0.0999,
        0.0, 0.0, 0.0, 0.0, 0.0, 0.9979,
    ];
    #[rustfmt::skip]
    const G7: [f64; 24] = [
        -0.0002, 0.0, 0.0002, 0.0,
        -0.0042, 0.0, 0.0042, 0.0,
        0.0, -0.0002, 0.0, 0.0002,
        0.0, -0.0042, 0.0, 0.0042,
        0.0020, 0.0020, 0.0020, 0.0020,
        0.0400, 0.0400, 0.0400, 0.0400,
    ];
    #[rustfmt::skip]
    const Q7: [f64; 36] = [
        0.0000, 0.0001, 0.0000, 0.0000, 0.0000, 0.0000,
        0.0001, 0.0020, 0.0000, 0.0005, 0.0000, 0.0002,
        0.0000, 0.0000, 0.0000, 0.0001, 0.0000, 0.0000,
        0.0000, 0.0005, 0.0001, 0.0020, 0.0000, 0.0002,
        0.0000, 0.0000, 0.0000, 0.0000, 0.0000, 0.0000,
        0.0000, 0.0002, 0.0000, 0.0002, 0.0000, 0.0005,
    ];

    /// Largest |ours − printed| over the entries; every printed entry is a 4-decimal rounding,
    /// so agreement means ≤ 5·10⁻⁵ (plus a hair for values that sit on a rounding edge).
    fn worst<const R: usize, const C: usize>(ours: &Matrix<R, C>, printed: &[f64]) -> f64 {
        let p = Matrix::<R, C>::from_row_slice(printed);
        (ours - p).amax()
    }

    #[test]
    fn discretisation_matches_the_seeds_eq_7_to_four_decimals() {
        let d = ContinuousLinear::seed().discretise(LINEAR_DT_S);
        println!(
            "eq. 7 max deviation: F {:.1e}, G {:.1e}, Q {:.1e}",
            worst(&d.f, &F7),
            worst(&d.g, &G7),
            worst(&d.q, &Q7)
        );
        assert!(worst(&d.f, &F7) <= 5e-5, "F: {}", worst(&d.f, &F7));
        assert!(worst(&d.g, &G7) <= 5e-5, "G: {}", worst(&d.g, &G7));
        assert!(worst(&d.q, &Q7) <= 5e-5, "Q: {}", worst(&d.q, &Q7));
        // Closed forms on the x axis: F(0,1) = (1 − e^{−aΔt})/a, F(1,1) = e^{−aΔt}.
        let a = 0.0104f64;
        assert!((d.f[(0, 1)] - (1.0 - (-a * 0.1).exp()) / a).abs() < 1e-12);
        assert!((d.f[(1, 1)] - (-a * 0.1f64).exp()).abs() < 1e-14);
        // Q(ẋ, ẋ) = q̃ (1 − e^{−2aΔt})/(2a) for the first-order velocity.
        let qxx = 0.02 * (1.0 - (-2.0 * a * 0.1f64).exp()) / (2.0 * a);
        assert!((d.q[(1, 1)] - qxx).abs() < 1e-14);
        // Unlike the printed one, the computed Q is positive definite.
        assert!(crate::linalg::SmallCholesky::new(&d.q).is_some());
    }

    #[test]
    fn the_other_reading_of_q_tilde_would_not_reproduce_the_seed() {
        // With Q̃(x, z) = 0.005 the entry Q(ẋ, ż) would print 0.0005, not the seed's 0.0002.
        let mut c = ContinuousLinear::seed();
        c.q_tilde[(0, 2)] = 0.005;
        c.q_tilde[(2, 0)] = 0.005;
        let d = c.discretise(LINEAR_DT_S);
        assert!((d.q[(1, 5)] - 0.0005).abs() < 5e-5);
    }

    #[test]
    fn observability_ranks_are_6_3_4() {
        assert_eq!(
            Linear3::new(LinearSensor::Positions, 0.1)
                .unwrap()
                .observability_rank(),
            6
        );
        assert_eq!(
            Linear3::new(LinearSensor::Velocities, 0.1)
                .unwrap()
                .observability_rank(),
            3
        );
        assert_eq!(
            Linear2::new(LinearSensor::Xy, 0.1)
                .unwrap()
                .observability_rank(),
            4
        );
        assert!(Linear2::new(LinearSensor::Positions, 0.1).is_err());
    }
}
