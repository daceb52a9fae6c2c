//! The model role: the **only** place f(x, u), h(x, u) and their Jacobians live.
//!
//! The truth simulator ([`crate::sim`]) calls [`Model::propagate`] and [`Model::measure`] and
//! adds seeded noise; filters call the very same functions without noise. A mismatched-model
//! study gives the filter a different *parameterisation* of a model, never a second copy.
//!
//! Dimensions are compile-time constants (`NX` states, `NU` inputs, `NZ` measurement
//! components) so the per-step algebra is stack-allocated and monomorphised.

pub mod exposed;

use crate::linalg::{Matrix, Vector};

/// Which measurement components report at a step, as a bit mask (bit `i` ⇔ component `i`).
///
/// Multi-rate systems (seed 004: GPS at 10 Hz, barometer at 50 Hz) report a subset per step;
/// filters process exactly the available rows.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Availability(pub u32);

impl Availability {
    /// Every one of `n` components reports.
    pub fn all(n: usize) -> Self {
        Availability(if n >= 32 { u32::MAX } else { (1u32 << n) - 1 })
    }
    /// Whether component `i` reports.
    pub fn has(self, i: usize) -> bool {
        self.0 & (1 << i) != 0
    }
    /// Number of reporting components (the NIS degrees of freedom at this step).
    pub fn count(self) -> usize {
        self.0.count_ones() as usize
    }
}

/// Wraps an angle difference into [−π, π) exactly as MATLAB's `mod(a + pi, 2*pi) - pi`.
pub fn wrap_angle(a: f64) -> f64 {
    wrap_symmetric(a, std::f64::consts::PI)
}

/// Wraps `a` into [−half, half) as `mod(a + half, 2·half) − half` with MATLAB's `mod` (the
/// sign of the divisor): the one implementation behind radians and degrees.
#[inline]
pub fn wrap_symmetric(a: f64, half: f64) -> f64 {
    let shifted = a + half;
    // In [0, 2·half) the remainder is `shifted` itself, exactly: skipping the `fmod` call
    // (most differences are small) keeps the bits.
    if (0.0..2.0 * half).contains(&shifted) {
        shifted - half
    } else {
        shifted.rem_euclid(2.0 * half) - half
    }
}

/// A measurement at one step: the value and which components it contains.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Measurement<const NZ: usize> {
    /// z_k; components that did not report hold 0 and must be ignored.
    pub z: Vector<NZ>,
    /// The components that reported.
    pub available: Availability,
}

/// The matrices of a linear model, x_k = F x_{k−1} + G u_k and z_k = H x_k: the very values
/// its [`Model::propagate`] and [`Model::measure`] multiply with.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LinearMatrices<const NX: usize, const NU: usize, const NZ: usize> {
    /// F.
    pub f: Matrix<NX, NX>,
    /// G.
    pub g: Matrix<NX, NU>,
    /// H.
    pub h: Matrix<NZ, NX>,
}

/// A discrete-time nonlinear state-space model with additive Gaussian noise:
///
/// x_k = f(x_{k−1}, u_k) + w_k,  z_k = h(x_k, u_k) + v_k.
///
/// Note the index of the input: the seeds' code integrates from k−1 to k with the control of
/// the *new* step k, and so does every model here.
pub trait Model<const NX: usize, const NU: usize, const NZ: usize>: Send + Sync {
    /// Sample time Δt in seconds.
    fn dt_s(&self) -> f64;
    /// f(x_{k−1}, u_k): the noise-free transition.
    fn propagate(&self, x: &Vector<NX>, u: &Vector<NU>) -> Vector<NX>;
    /// F_k = ∂f/∂x at (x_{k−1}, u_k).
    fn transition_jacobian(&self, x: &Vector<NX>, u: &Vector<NU>) -> Matrix<NX, NX>;
    /// h(x_k, u_k): the noise-free measurement.
    fn measure(&self, x: &Vector<NX>, u: &Vector<NU>) -> Vector<NZ>;
    /// H_k = ∂h/∂x at (x_k, u_k).
    fn measurement_jacobian(&self, x: &Vector<NX>, u: &Vector<NU>) -> Matrix<NZ, NX>;
    /// Where F = [`Model::transition_jacobian`] may be non-zero, when the model knows it: the
    /// (row, column) positions, the columns of each row in ascending order, valid at every
    /// (x, u). F = I + A·Δt with a sparse A is the common case. The EKF then forms F P Fᵀ over
    /// these entries only ([`crate::linalg::sparse_sandwich`]: the same sums in the same order
    /// as the dense product, so the same result). `None` (the default): F is treated as dense.
    /// An entry outside the pattern must be zero; tests check the declarations at sampled
    /// points.
    fn transition_pattern(&self) -> Option<&[(usize, usize)]> {
        None
    }
    /// When H = [`Model::measurement_jacobian`] is a selection of states at every (x, u) —
    /// H\[i, s\[i\]\] = 1 and every other entry 0 — the selection `s`. The EKF then reads H P⁻ as
    /// rows of P⁻ and forms (I − K H) P⁻ over its non-zero entries (the dense result, see
    /// [`crate::linalg::select_i_kh`]). `None` (the default): H is treated as dense.
    fn measurement_selection(&self) -> Option<[usize; NZ]> {
        None
    }
    /// The residual z − ẑ, with the [`Model::angle_measurements`] wrapped to [−π, π).
    fn residual(&self, z: &Vector<NZ>, z_pred: &Vector<NZ>) -> Vector<NZ> {
        let mut r = z - z_pred;
        for &i in self.angle_measurements() {
            r[i] = wrap_angle(r[i]);
        }
        r
    }
    /// The difference a − b of two states, with the [`Model::angle_states`] wrapped to
    /// [−π, π). Sigma-point filters form their deviations with it.
    fn state_residual(&self, a: &Vector<NX>, b: &Vector<NX>) -> Vector<NX> {
        let mut d = a - b;
        for &i in self.angle_states() {
            d[i] = wrap_angle(d[i]);
        }
        d
    }
    /// Indices of the state components that are angles in radians (none by default).
    ///
    /// A sigma-point filter averages them on the circle and wraps their deviations, so a
    /// cloud of points that straddles ±π (or an angle the model keeps on any branch) has the
    /// right mean. The filters never wrap the estimate itself: a model whose angle is
    /// continuous (the planar θ) keeps its branch.
    fn angle_states(&self) -> &[usize] {
        &[]
    }
    /// Indices of the measurement components that are angles in radians (none by default):
    /// the default [`Model::residual`] wraps them and sigma-point filters average them on the
    /// circle. A model that overrides `residual` should list its wrapped components here.
    fn angle_measurements(&self) -> &[usize] {
        &[]
    }
    /// Which measurement components report at `step` (all of them unless the model is
    /// multi-rate).
    fn availability(&self, _step: usize) -> Availability {
        Availability::all(NZ)
    }
    /// The model's own discrete process-noise covariance Q, when it has one (a linear model
    /// discretised from a continuous noise intensity, whose Q is full, not diagonal). The truth
    /// then samples w_k = L ξ_k with Q = L Lᵀ, and filters assume Q unless told otherwise.
    /// `None` (the default) keeps the spec's per-state standard deviations.
    fn process_noise_covariance(&self) -> Option<Matrix<NX, NX>> {
        None
    }
    /// F, G and H when the model is linear (f(x, u) = F x + G u, h(x, u) = H x), so that a
    /// filter written elsewhere can use the model's own matrices at full precision. `None`
    /// (the default): the model is not known to be linear.
    fn linear(&self) -> Option<LinearMatrices<NX, NU, NZ>> {
        None
    }
    /// Whether h(x, u) depends on u (an accelerometer measures the input's effect). `true`
    /// (the default) makes callers outside kfmc pass u to h; a model whose h reads only x
    /// says `false`.
    fn measurement_uses_input(&self) -> bool {
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The remainder taken every time, as before the fast path.
    fn by_remainder(a: f64, half: f64) -> f64 {
        (a + half).rem_euclid(2.0 * half) - half
    }

    #[test]
    fn wrapping_without_the_remainder_keeps_its_bits() {
        let pi = std::f64::consts::PI;
        for half in [pi, 180.0] {
            let mut values = vec![
                0.0,
                -0.0,
                half,
                -half,
                half - f64::EPSILON,
                -half + f64::EPSILON,
                f64::MIN_POSITIVE,
                -f64::MIN_POSITIVE,
                1e300,
                -1e300,
            ];
            // A sweep across several periods, dense near the interval's ends.
            values.extend((-4000..=4000).map(|i| i as f64 * half / 997.0));
            values.extend((0..200).map(|i| half * (1.0 - (i as f64) * 1e-16)));
            values.extend((0..200).map(|i| -half * (1.0 - (i as f64) * 1e-16)));
            for a in values {
                assert_eq!(
                    wrap_symmetric(a, half).to_bits(),
                    by_remainder(a, half).to_bits(),
                    "a = {a:e}, half = {half}"
                );
            }
            assert!(wrap_symmetric(f64::NAN, half).is_nan());
        }
    }
}
