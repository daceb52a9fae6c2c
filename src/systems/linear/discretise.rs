//! Zero-order hold and Van Loan: the one discretisation of ẋ = A x + B u + Γ ω, ω ~ N(0, Q̃),
//! that every continuous linear system uses (L1's [`ContinuousLinear::discretise`] calls it
//! too, so a TOML system given L1's matrices gets L1's F, G and Q bit for bit).
//!
//! [`ContinuousLinear::discretise`]: crate::systems::linear_quadrotor::model::ContinuousLinear::discretise

use crate::linalg::{Matrix, expm};

/// x_k = F x_{k−1} + G u_k + w_k, w_k ~ N(0, Q), from a continuous model.
#[derive(Clone, Debug, PartialEq)]
pub struct ZohVanLoan<const NX: usize, const NU: usize> {
    /// F = e^{AΔt}.
    pub f: Matrix<NX, NX>,
    /// G = ∫₀^Δt e^{As} ds B.
    pub g: Matrix<NX, NU>,
    /// Q = ∫₀^Δt e^{As} W e^{Aᵀs} ds (symmetric).
    pub q: Matrix<NX, NX>,
}

/// F and G by zero-order hold (one exponential of [[A, B], [0, 0]]Δt) and Q by Van Loan's
/// method, for the continuous noise intensity in state space W = Γ Q̃ Γᵀ.
///
/// `NA` must be NX + NU and `NV` must be 2·NX (checked at compile time): stable Rust cannot
/// write `{NX + NU}` in a generic signature, so callers name the sizes of the two augmented
/// matrices, e.g. `zoh_van_loan::<6, 4, 10, 12>` for L1.
pub fn zoh_van_loan<const NX: usize, const NU: usize, const NA: usize, const NV: usize>(
    a: &Matrix<NX, NX>,
    b: &Matrix<NX, NU>,
    w: &Matrix<NX, NX>,
    dt_s: f64,
) -> ZohVanLoan<NX, NU> {
    const {
        assert!(
            NA == NX + NU && NV == 2 * NX,
            "zoh_van_loan needs NA = NX + NU and NV = 2·NX"
        )
    };
    // Zero-order hold: e^{[[A, B], [0, 0]]Δt} = [[F, G], [0, I]].
    let mut m = Matrix::<NA, NA>::zeros();
    m.fixed_view_mut::<NX, NX>(0, 0).copy_from(&(a * dt_s));
    m.fixed_view_mut::<NX, NU>(0, NX).copy_from(&(b * dt_s));
    let e = expm(&m);
    let f: Matrix<NX, NX> = e.fixed_view::<NX, NX>(0, 0).into_owned();
    let g: Matrix<NX, NU> = e.fixed_view::<NX, NU>(0, NX).into_owned();
    // Van Loan (1978): e^{[[−A, W], [0, Aᵀ]]Δt} = [[·, F⁻¹Q], [0, Fᵀ]], so Q = F·(F⁻¹Q).
    let mut v = Matrix::<NV, NV>::zeros();
    v.fixed_view_mut::<NX, NX>(0, 0).copy_from(&(-a * dt_s));
    v.fixed_view_mut::<NX, NX>(0, NX).copy_from(&(w * dt_s));
    v.fixed_view_mut::<NX, NX>(NX, NX)
        .copy_from(&(a.transpose() * dt_s));
    let ev = expm(&v);
    let f_vl: Matrix<NX, NX> = ev.fixed_view::<NX, NX>(NX, NX).transpose();
    let q = f_vl * ev.fixed_view::<NX, NX>(0, NX);
    // Q is symmetric in exact arithmetic; remove the round-off asymmetry once, here.
    let q = (q + q.transpose()) * 0.5;
    ZohVanLoan { f, g, q }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn constant_velocity_has_the_textbook_closed_forms() {
        // ẋ = v, v̇ = u + ω: F = [[1, Δt], [0, 1]], G = [Δt²/2, Δt], and for white acceleration
        // of intensity q: Q = q [[Δt³/3, Δt²/2], [Δt²/2, Δt]].
        let a = Matrix::<2, 2>::new(0.0, 1.0, 0.0, 0.0);
        let b = Matrix::<2, 1>::new(0.0, 1.0);
        let w = Matrix::<2, 2>::new(0.0, 0.0, 0.0, 0.3);
        let dt: f64 = 0.25;
        let d = zoh_van_loan::<2, 1, 3, 4>(&a, &b, &w, dt);
        let f = Matrix::<2, 2>::new(1.0, dt, 0.0, 1.0);
        let g = Matrix::<2, 1>::new(dt * dt / 2.0, dt);
        let q = Matrix::<2, 2>::new(dt.powi(3) / 3.0, dt * dt / 2.0, dt * dt / 2.0, dt) * 0.3;
        assert!((d.f - f).amax() < 1e-15);
        assert!((d.g - g).amax() < 1e-15);
        assert!((d.q - q).amax() < 1e-15);
    }

    #[test]
    fn zero_input_columns_leave_f_and_q_unchanged() {
        // The TOML system pads B with zero columns up to its fixed input size; that must not
        // move F or Q by a single bit.
        let a = Matrix::<2, 2>::new(-0.3, 1.0, -0.2, -0.1);
        let w = Matrix::<2, 2>::new(0.1, 0.02, 0.02, 0.3);
        let b1 = Matrix::<2, 1>::new(0.5, -1.0);
        let mut b4 = Matrix::<2, 4>::zeros();
        b4.set_column(0, &b1.column(0));
        let one = zoh_van_loan::<2, 1, 3, 4>(&a, &b1, &w, 0.1);
        let four = zoh_van_loan::<2, 4, 6, 4>(&a, &b4, &w, 0.1);
        assert_eq!(one.f, four.f);
        assert_eq!(one.q, four.q);
        assert_eq!(one.g.column(0), four.g.column(0));
        assert!(four.g.columns(1, 3).iter().all(|&v| v == 0.0));
    }
}
