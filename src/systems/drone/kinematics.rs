//! ZYX Euler kinematics of seed 004 §3.1: R(φ, θ, ψ) body → NED, the rate transform T, and
//! the Jacobians ∂(R a)/∂Θ and ∂(T ω)/∂Θ (the seed's `dR_dangles` and `dT_dangles`).

use crate::linalg::{Matrix, Vector};

/// Euler angles [φ, θ, ψ] in radians.
pub type Euler = Vector<3>;

fn rx(phi: f64) -> (Matrix<3, 3>, Matrix<3, 3>) {
    let (s, c) = phi.sin_cos();
    (
        Matrix::<3, 3>::new(1.0, 0.0, 0.0, 0.0, c, -s, 0.0, s, c),
        Matrix::<3, 3>::new(0.0, 0.0, 0.0, 0.0, -s, -c, 0.0, c, -s),
    )
}

fn ry(theta: f64) -> (Matrix<3, 3>, Matrix<3, 3>) {
    let (s, c) = theta.sin_cos();
    (
        Matrix::<3, 3>::new(c, 0.0, s, 0.0, 1.0, 0.0, -s, 0.0, c),
        Matrix::<3, 3>::new(-s, 0.0, c, 0.0, 0.0, 0.0, -c, 0.0, -s),
    )
}

fn rz(psi: f64) -> (Matrix<3, 3>, Matrix<3, 3>) {
    let (s, c) = psi.sin_cos();
    (
        Matrix::<3, 3>::new(c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0),
        Matrix::<3, 3>::new(-s, -c, 0.0, c, -s, 0.0, 0.0, 0.0, 0.0),
    )
}

/// R(φ, θ, ψ) = R_z(ψ) R_y(θ) R_x(φ), body → NED (the matrix printed in seed §3.1.2).
pub fn rotation(e: &Euler) -> Matrix<3, 3> {
    rz(e[2]).0 * ry(e[1]).0 * rx(e[0]).0
}

/// ∂(R(Θ) a)/∂[φ, θ, ψ] for a fixed body vector a: column j is (∂R/∂Θ_j) a.
pub fn d_rotation_times(e: &Euler, a: &Vector<3>) -> Matrix<3, 3> {
    let (x, dx) = rx(e[0]);
    let (y, dy) = ry(e[1]);
    let (z, dz) = rz(e[2]);
    let mut m = Matrix::<3, 3>::zeros();
    m.set_column(0, &(z * y * dx * a));
    m.set_column(1, &(z * dy * x * a));
    m.set_column(2, &(dz * y * x * a));
    m
}

/// T(Θ): body rates → Euler-angle rates (seed §3.1.3). Singular at θ = ±90°.
pub fn rate_transform(e: &Euler) -> Matrix<3, 3> {
    let (sp, cp) = e[0].sin_cos();
    let (st, ct) = e[1].sin_cos();
    let tt = st / ct;
    Matrix::<3, 3>::new(1.0, sp * tt, cp * tt, 0.0, cp, -sp, 0.0, sp / ct, cp / ct)
}

/// T(Θ)⁻¹: Euler-angle rates → body rates, ω = T⁻¹ Θ̇ (defined at every attitude).
pub fn inverse_rate_transform(e: &Euler) -> Matrix<3, 3> {
    crate::linalg::so3::euler_rates_to_body(e)
}

/// ∂(T(Θ) ω)/∂[φ, θ, ψ] for fixed body rates ω (ψ does not enter T).
pub fn d_rate_transform_times(e: &Euler, w: &Vector<3>) -> Matrix<3, 3> {
    let (sp, cp) = e[0].sin_cos();
    let (st, ct) = e[1].sin_cos();
    let tt = st / ct;
    let (w2, w3) = (w[1], w[2]);
    let a = sp * w2 + cp * w3;
    let b = cp * w2 - sp * w3;
    Matrix::<3, 3>::new(
        b * tt,
        a / (ct * ct),
        0.0,
        -a,
        0.0,
        0.0,
        b / ct,
        a * st / (ct * ct),
        0.0,
    )
}

/// Euler angles of a rotation matrix (ZYX; θ clamped to [−90°, 90°]).
pub fn euler_of(r: &Matrix<3, 3>) -> Euler {
    Euler::new(
        r[(2, 1)].atan2(r[(2, 2)]),
        (-r[(2, 0)]).clamp(-1.0, 1.0).asin(),
        r[(1, 0)].atan2(r[(0, 0)]),
    )
}

pub(crate) use crate::linalg::so3::skew;

/// exp(\[φ\]×): the rotation by the vector φ (Rodrigues).
pub fn exp_so3(phi: &Vector<3>) -> Matrix<3, 3> {
    let angle = phi.norm();
    let k = skew(phi);
    if angle < 1e-8 {
        return Matrix::<3, 3>::identity() + k + k * k * 0.5;
    }
    Matrix::<3, 3>::identity()
        + k * (angle.sin() / angle)
        + k * k * ((1.0 - angle.cos()) / (angle * angle))
}

/// E(Θ) with δΘ = E δφ for a small rotation δφ applied on the NED side (R ← exp(\[δφ\]×) R):
/// the Euler-angle change of a navigation-frame rotation error.
pub fn euler_of_nav_rotation(e: &Euler) -> Matrix<3, 3> {
    // δφ_nav = R δφ_body, and δφ_body = T⁻¹ δΘ, so δΘ = T Rᵀ δφ_nav.
    rate_transform(e) * rotation(e).transpose()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn numeric(f: impl Fn(&Euler) -> Vector<3>, e: &Euler) -> Matrix<3, 3> {
        let h = 1e-6;
        let mut m = Matrix::<3, 3>::zeros();
        for j in 0..3 {
            let mut a = *e;
            let mut b = *e;
            a[j] += h;
            b[j] -= h;
            m.set_column(j, &((f(&a) - f(&b)) / (2.0 * h)));
        }
        m
    }

    #[test]
    fn rotation_is_the_printed_matrix_and_orthonormal() {
        let e = Euler::new(0.3, -0.4, 1.1);
        let r = rotation(&e);
        let (sp, cp) = e[0].sin_cos();
        let (st, ct) = e[1].sin_cos();
        let (ss, cs) = e[2].sin_cos();
        let printed = Matrix::<3, 3>::new(
            ct * cs,
            cs * st * sp - ss * cp,
            cs * st * cp + ss * sp,
            ct * ss,
            ss * st * sp + cs * cp,
            ss * st * cp - cs * sp,
            -st,
            ct * sp,
            ct * cp,
        );
        assert!((r - printed).amax() < 1e-15);
        assert!((r * r.transpose() - Matrix::<3, 3>::identity()).amax() < 1e-15);
        assert!((euler_of(&r) - e).amax() < 1e-12);
    }

    #[test]
    fn jacobians_match_central_differences() {
        let e = Euler::new(0.2, 0.35, -0.7);
        let a = Vector::<3>::new(1.0, -0.5, 9.0);
        let w = Vector::<3>::new(0.1, -0.3, 0.25);
        let dr = numeric(|x| rotation(x) * a, &e);
        assert!((d_rotation_times(&e, &a) - dr).amax() < 1e-8);
        let dt = numeric(|x| rate_transform(x) * w, &e);
        assert!((d_rate_transform_times(&e, &w) - dt).amax() < 1e-8);
        assert!(
            (rate_transform(&e) * inverse_rate_transform(&e) - Matrix::<3, 3>::identity()).amax()
                < 1e-14
        );
    }

    #[test]
    fn a_small_nav_rotation_changes_the_euler_angles_by_e() {
        let e = Euler::new(0.2, 0.35, -0.7);
        let d = Vector::<3>::new(1e-6, -2e-6, 1.5e-6);
        let moved = euler_of(&(exp_so3(&d) * rotation(&e)));
        let predicted = euler_of_nav_rotation(&e) * d;
        assert!(((moved - e) - predicted).amax() < 1e-11);
    }
}
