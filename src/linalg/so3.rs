//! Rotations: the exponential and logarithm of SO(3), unit quaternions, ZYX Euler angles,
//! and the chart that scores an attitude estimate by its rotation error.
//!
//! Conventions, the same in every function here:
//! * R maps body to navigation coordinates. ZYX Euler angles Θ = (φ, θ, ψ) (roll, pitch,
//!   yaw) give R(Θ) = R_z(ψ) R_y(θ) R_x(φ).
//! * A quaternion is Hamilton's, scalar first, q = (w, x, y, z), and rotates like R(q).
//! * The **right** error of an estimate R̂ of the truth R is δφ = log(R̂ᵀ R) (body axes: the
//!   truth is the estimate turned by δφ about its own axes, R = R̂ exp(\[δφ\]×)); the **left**
//!   error is log(R R̂ᵀ) = R̂ δφ (navigation axes). Their covariances convert as
//!   P_left = R̂ P_right R̂ᵀ, so both give the same NEES.
//! * The chart Jacobian at an estimate Θ̂ maps a small Euler-angle error to the rotation
//!   error: δφ_right = T(Θ̂)⁻¹ δΘ, δφ_left = R̂ T(Θ̂)⁻¹ δΘ, where T is the body-rate → Euler-rate
//!   matrix. T⁻¹ is defined at every attitude; T itself is singular at θ = ±90°, which is why an
//!   error taken as three Euler-angle differences breaks down there.

use super::{Matrix, Vector};

/// A unit quaternion (w, x, y, z), Hamilton convention, scalar first.
pub type Quaternion = [f64; 4];

/// The skew-symmetric matrix \[v\]× (v × w = \[v\]× w).
pub fn skew(v: &Vector<3>) -> Matrix<3, 3> {
    Matrix::<3, 3>::new(0.0, -v[2], v[1], v[2], 0.0, -v[0], -v[1], v[0], 0.0)
}

/// exp(\[φ\]×): the rotation by |φ| about φ/|φ| (Rodrigues' formula, with its Taylor series
/// near 0 so that tiny rotations keep full relative precision).
pub fn exp(phi: &Vector<3>) -> Matrix<3, 3> {
    let t2 = phi.norm_squared();
    let k = skew(phi);
    let (a, b) = if t2 < 1e-8 {
        (1.0 - t2 / 6.0 * (1.0 - t2 / 20.0), 0.5 * (1.0 - t2 / 12.0))
    } else {
        let t = t2.sqrt();
        (t.sin() / t, (1.0 - t.cos()) / t2)
    };
    Matrix::<3, 3>::identity() + k * a + k * k * b
}

/// The unit quaternion of a rotation matrix (Shepperd's method: the largest of w, x, y, z is
/// formed from the trace or a diagonal entry, so no branch divides by a small number), with
/// w ≥ 0.
pub fn quaternion_of(r: &Matrix<3, 3>) -> Quaternion {
    let tr = r[(0, 0)] + r[(1, 1)] + r[(2, 2)];
    let candidates = [tr, r[(0, 0)], r[(1, 1)], r[(2, 2)]];
    let mut best = 0;
    for i in 1..4 {
        if candidates[i] > candidates[best] {
            best = i;
        }
    }
    let q = match best {
        0 => {
            let s = 2.0 * (1.0 + tr).sqrt();
            [
                0.25 * s,
                (r[(2, 1)] - r[(1, 2)]) / s,
                (r[(0, 2)] - r[(2, 0)]) / s,
                (r[(1, 0)] - r[(0, 1)]) / s,
            ]
        }
        1 => {
            let s = 2.0 * (1.0 + r[(0, 0)] - r[(1, 1)] - r[(2, 2)]).sqrt();
            [
                (r[(2, 1)] - r[(1, 2)]) / s,
                0.25 * s,
                (r[(0, 1)] + r[(1, 0)]) / s,
                (r[(0, 2)] + r[(2, 0)]) / s,
            ]
        }
        2 => {
            let s = 2.0 * (1.0 - r[(0, 0)] + r[(1, 1)] - r[(2, 2)]).sqrt();
            [
                (r[(0, 2)] - r[(2, 0)]) / s,
                (r[(0, 1)] + r[(1, 0)]) / s,
                0.25 * s,
                (r[(1, 2)] + r[(2, 1)]) / s,
            ]
        }
        _ => {
            let s = 2.0 * (1.0 - r[(0, 0)] - r[(1, 1)] + r[(2, 2)]).sqrt();
            [
                (r[(1, 0)] - r[(0, 1)]) / s,
                (r[(0, 2)] + r[(2, 0)]) / s,
                (r[(1, 2)] + r[(2, 1)]) / s,
                0.25 * s,
            ]
        }
    };
    let sign = if q[0] < 0.0 { -1.0 } else { 1.0 };
    let n = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt();
    q.map(|c| sign * c / n)
}

/// The rotation matrix of a quaternion (normalised first; `None` for a zero or non-finite
/// one).
pub fn matrix_of_quaternion(q: &Quaternion) -> Option<Matrix<3, 3>> {
    let n = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt();
    if !(n.is_finite() && n > 0.0) {
        return None;
    }
    let [w, x, y, z] = q.map(|c| c / n);
    Some(Matrix::<3, 3>::new(
        1.0 - 2.0 * (y * y + z * z),
        2.0 * (x * y - w * z),
        2.0 * (x * z + w * y),
        2.0 * (x * y + w * z),
        1.0 - 2.0 * (x * x + z * z),
        2.0 * (y * z - w * x),
        2.0 * (x * z - w * y),
        2.0 * (y * z + w * x),
        1.0 - 2.0 * (x * x + y * y),
    ))
}

/// log(R): the rotation vector φ with exp(\[φ\]×) = R and |φ| ≤ π. Taken through the
/// quaternion (w ≥ 0), |φ| = 2 atan2(|v|, w), which keeps full precision at every angle: near
/// 0, where the matrix formula divides by sin|φ|, and near π, where the axis can no longer be
/// read from the antisymmetric part. At exactly π both ±φ are logarithms; this returns one.
pub fn log(r: &Matrix<3, 3>) -> Vector<3> {
    let [w, x, y, z] = quaternion_of(r);
    let v = Vector::<3>::new(x, y, z);
    let s = v.norm();
    if s < 1e-8 {
        // 2 atan2(s, w)/s = (2/w)(1 − s²/(3w²) + …), w ≈ 1 here.
        return v * (2.0 / w) * (1.0 - s * s / (3.0 * w * w));
    }
    v * (2.0 * s.atan2(w) / s)
}

/// R(Θ) = R_z(ψ) R_y(θ) R_x(φ) for ZYX Euler angles Θ = (φ, θ, ψ) in radians.
pub fn matrix_of_euler(e: &Vector<3>) -> Matrix<3, 3> {
    let (sp, cp) = e[0].sin_cos();
    let (st, ct) = e[1].sin_cos();
    let (ss, cs) = e[2].sin_cos();
    Matrix::<3, 3>::new(
        ct * cs,
        cs * st * sp - ss * cp,
        cs * st * cp + ss * sp,
        ct * ss,
        ss * st * sp + cs * cp,
        ss * st * cp - cs * sp,
        -st,
        ct * sp,
        ct * cp,
    )
}

/// ZYX Euler angles (radians) of a rotation matrix: θ ∈ \[−π/2, π/2\] from atan2 (full
/// precision next to ±90°, where asin loses half the digits), φ and ψ in (−π, π\]. At θ = ±90°
/// only φ ∓ ψ is defined; this sets ψ from the first column as if it were not.
pub fn euler_of_matrix(r: &Matrix<3, 3>) -> Vector<3> {
    Vector::<3>::new(
        r[(2, 1)].atan2(r[(2, 2)]),
        (-r[(2, 0)]).atan2(r[(0, 0)].hypot(r[(1, 0)])),
        r[(1, 0)].atan2(r[(0, 0)]),
    )
}

/// T(Θ)⁻¹: Euler-angle rates → body rates (ω = T⁻¹ Θ̇), defined at every attitude. It is also
/// the right chart Jacobian: a small Euler-angle change δΘ at Θ turns R(Θ) by
/// δφ = T(Θ)⁻¹ δΘ about its body axes.
pub fn euler_rates_to_body(e: &Vector<3>) -> Matrix<3, 3> {
    let (sp, cp) = e[0].sin_cos();
    let (st, ct) = e[1].sin_cos();
    Matrix::<3, 3>::new(1.0, 0.0, -st, 0.0, cp, sp * ct, 0.0, -sp, cp * ct)
}

/// Which side of the estimate a rotation error is taken on.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum ErrorSide {
    /// δφ = log(R̂ᵀ R): body axes of the estimate.
    Right,
    /// δφ = log(R R̂ᵀ) = R̂ · right: navigation axes.
    Left,
}

impl ErrorSide {
    /// `right` or `left`.
    pub fn name(self) -> &'static str {
        match self {
            ErrorSide::Right => "right",
            ErrorSide::Left => "left",
        }
    }
}

/// Three consecutive evaluated quantities that hold a rotation as ZYX Euler angles
/// (roll, pitch, yaw), scored by the rotation error on `side` in their unit (degrees or
/// radians) rather than by three wrapped angle differences.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct EulerRotation {
    /// Index of the roll quantity; pitch and yaw follow it.
    pub first: usize,
    /// Whether the angles (and so the error) are in degrees.
    pub degrees: bool,
    /// The error convention.
    pub side: ErrorSide,
}

impl EulerRotation {
    fn scale(&self) -> f64 {
        if self.degrees {
            180.0 / std::f64::consts::PI
        } else {
            1.0
        }
    }

    /// The Euler angles in radians from a quantity vector.
    pub fn euler(&self, q: &[f64]) -> Vector<3> {
        let s = self.scale();
        Vector::<3>::new(
            q[self.first] / s,
            q[self.first + 1] / s,
            q[self.first + 2] / s,
        )
    }

    /// The rotation a quantity vector holds.
    pub fn matrix(&self, q: &[f64]) -> Matrix<3, 3> {
        matrix_of_euler(&self.euler(q))
    }

    /// The rotation error of `estimate` against `truth` (both quantity vectors), in the
    /// quantities' unit, written over `e[first..first + 3]`.
    pub fn error_into(&self, truth: &[f64], estimate: &[f64], e: &mut [f64]) {
        let (r, rh) = (self.matrix(truth), self.matrix(estimate));
        let phi = match self.side {
            ErrorSide::Right => log(&(rh.transpose() * r)),
            ErrorSide::Left => log(&(r * rh.transpose())),
        };
        let s = self.scale();
        for j in 0..3 {
            e[self.first + j] = phi[j] * s;
        }
    }

    /// The chart Jacobian at `estimate`: ∂δφ/∂Θ, the rotation error per Euler-angle error
    /// (unitless, so the same in degrees and radians).
    pub fn chart_jacobian(&self, estimate: &[f64]) -> Matrix<3, 3> {
        let e = self.euler(estimate);
        let j = euler_rates_to_body(&e);
        match self.side {
            ErrorSide::Right => j,
            ErrorSide::Left => matrix_of_euler(&e) * j,
        }
    }

    /// The tangent-space matrix that takes this rotation's error from the right to its side
    /// (R̂ for left, I for right): P_side = M P_right Mᵀ.
    pub fn from_right(&self, estimate: &[f64]) -> Matrix<3, 3> {
        match self.side {
            ErrorSide::Right => Matrix::<3, 3>::identity(),
            ErrorSide::Left => self.matrix(estimate),
        }
    }
}

/// G P Gᵀ with G the identity except the given 3×3 blocks on the diagonal (each at its
/// rotation's rows): the covariance of quantities after each rotation's error is re-expressed.
pub fn transform_blocks<const N: usize>(
    p: &Matrix<N, N>,
    blocks: &[(usize, Matrix<3, 3>)],
) -> Matrix<N, N> {
    if blocks.is_empty() {
        return *p;
    }
    let mut g = Matrix::<N, N>::identity();
    for (first, m) in blocks {
        g.fixed_view_mut::<3, 3>(*first, *first).copy_from(m);
    }
    g * p * g.transpose()
}

/// G A G⁻¹ for the same G: an error transition re-expressed in the new coordinates (`None`
/// when a block is singular).
pub fn conjugate_blocks<const N: usize>(
    a: &Matrix<N, N>,
    blocks: &[(usize, Matrix<3, 3>)],
) -> Option<Matrix<N, N>> {
    if blocks.is_empty() {
        return Some(*a);
    }
    let mut g = Matrix::<N, N>::identity();
    let mut gi = Matrix::<N, N>::identity();
    for (first, m) in blocks {
        g.fixed_view_mut::<3, 3>(*first, *first).copy_from(m);
        gi.fixed_view_mut::<3, 3>(*first, *first)
            .copy_from(&m.try_inverse()?);
    }
    Some(g * a * gi)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::f64::consts::PI;

    /// The rotation by `angle` about the unit `axis` through the quaternion
    /// (cos ½α, sin ½α a) and its matrix: a route independent of Rodrigues' formula.
    fn by_quaternion(axis: &Vector<3>, angle: f64) -> Matrix<3, 3> {
        let a = axis.normalize();
        let (s, c) = (angle / 2.0).sin_cos();
        matrix_of_quaternion(&[c, s * a[0], s * a[1], s * a[2]]).unwrap()
    }

    fn axes() -> Vec<Vector<3>> {
        vec![
            Vector::<3>::new(1.0, 0.0, 0.0),
            Vector::<3>::new(0.0, 1.0, 0.0),
            Vector::<3>::new(0.0, 0.0, 1.0),
            Vector::<3>::new(1.0, -2.0, 0.5).normalize(),
            Vector::<3>::new(-0.3, 0.1, 0.9).normalize(),
            Vector::<3>::new(1.0, 1.0, 1.0).normalize(),
        ]
    }

    #[test]
    fn exp_is_the_quaternion_rotation() {
        for a in axes() {
            for angle in [0.0, 1e-9, 1e-5, 0.3, 1.0, 2.5, PI - 1e-7, PI] {
                let diff = (exp(&(a * angle)) - by_quaternion(&a, angle)).amax();
                assert!(diff < 1e-14, "axis {a:?}, angle {angle}: {diff}");
            }
        }
    }

    #[test]
    fn log_recovers_axis_and_angle_up_to_pi() {
        for a in axes() {
            for angle in [
                1e-12,
                1e-9,
                1e-6,
                0.1,
                1.0,
                2.0,
                3.0,
                PI - 1e-5,
                PI - 1e-7,
                PI - 3e-8,
            ] {
                let phi = log(&by_quaternion(&a, angle));
                let want = a * angle;
                // Relative to the angle near 0; absolute (about 1e-15 of π) elsewhere.
                let tol = 1e-14 * angle.max(1e-3);
                assert!(
                    (phi - want).amax() < tol.max(4e-15 * angle),
                    "axis {a:?}, angle {angle}: {phi:?} against {want:?}"
                );
            }
            // Past π the shorter way round is the other axis: π + ε about a is π − ε about −a.
            for eps in [1e-7, 3e-8, 1e-3] {
                let phi = log(&by_quaternion(&a, PI + eps));
                assert!(
                    (phi + a * (PI - eps)).amax() < 1e-13,
                    "π + {eps} about {a:?}"
                );
            }
        }
    }

    #[test]
    fn log_at_exactly_pi_is_one_of_the_two_logarithms() {
        for a in axes() {
            let r = by_quaternion(&a, PI);
            let phi = log(&r);
            assert!((phi.norm() - PI).abs() < 1e-14);
            assert!(
                (phi - a * PI).amax() < 1e-13 || (phi + a * PI).amax() < 1e-13,
                "{phi:?} about {a:?}"
            );
            assert!((exp(&phi) - r).amax() < 1e-14);
            // A rotation matrix by π built without a quaternion: 2 a aᵀ − I.
            let direct = a * a.transpose() * 2.0 - Matrix::<3, 3>::identity();
            let phi = log(&direct);
            assert!((phi.norm() - PI).abs() < 1e-14);
            assert!((exp(&phi) - direct).amax() < 1e-14);
        }
    }

    #[test]
    fn round_trips() {
        let mut seed = 0x2545f4914f6cdd1du64;
        let mut uniform = || {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            (seed >> 11) as f64 / (1u64 << 53) as f64
        };
        for _ in 0..2000 {
            let v = Vector::<3>::new(uniform() - 0.5, uniform() - 0.5, uniform() - 0.5);
            let phi = v.normalize() * (PI * uniform());
            let r = exp(&phi);
            assert!((r * r.transpose() - Matrix::<3, 3>::identity()).amax() < 1e-14);
            assert!((log(&r) - phi).amax() < 1e-12, "{phi:?}");
            let q = quaternion_of(&r);
            assert!((matrix_of_quaternion(&q).unwrap() - r).amax() < 1e-14);
            let e = Vector::<3>::new(
                PI * (2.0 * uniform() - 1.0),
                0.5 * PI * (2.0 * uniform() - 1.0),
                PI * (2.0 * uniform() - 1.0),
            );
            let m = matrix_of_euler(&e);
            assert!((euler_of_matrix(&m) - e).amax() < 1e-12, "{e:?}");
        }
        // Next to the singularity the angles are still recovered where they are defined.
        let e = Vector::<3>::new(0.4, (89.9f64).to_radians(), -1.2);
        assert!((euler_of_matrix(&matrix_of_euler(&e)) - e).amax() < 1e-11);
        assert_eq!(matrix_of_quaternion(&[0.0; 4]), None);
    }

    #[test]
    fn euler_matrix_is_the_product_of_axis_rotations() {
        let e = Vector::<3>::new(0.3, -0.4, 1.1);
        let x = by_quaternion(&Vector::<3>::new(1.0, 0.0, 0.0), e[0]);
        let y = by_quaternion(&Vector::<3>::new(0.0, 1.0, 0.0), e[1]);
        let z = by_quaternion(&Vector::<3>::new(0.0, 0.0, 1.0), e[2]);
        assert!((matrix_of_euler(&e) - z * y * x).amax() < 1e-15);
    }

    #[test]
    fn chart_jacobian_matches_finite_differences() {
        let h = 1e-6;
        for pitch in [0.35, -1.2, (89.9f64).to_radians(), (-89.99f64).to_radians()] {
            for side in [ErrorSide::Right, ErrorSide::Left] {
                for degrees in [false, true] {
                    let rot = EulerRotation {
                        first: 1,
                        degrees,
                        side,
                    };
                    let s = if degrees { 180.0 / PI } else { 1.0 };
                    let q = [7.0, 0.2 * s, pitch * s, -0.7 * s];
                    let mut numeric = Matrix::<3, 3>::zeros();
                    for j in 0..3 {
                        let (mut a, mut b) = (q, q);
                        a[1 + j] += h * s;
                        b[1 + j] -= h * s;
                        let (mut ea, mut eb) = ([0.0; 4], [0.0; 4]);
                        // The error of the estimate q against the truths a and b.
                        rot.error_into(&a, &q, &mut ea);
                        rot.error_into(&b, &q, &mut eb);
                        for i in 0..3 {
                            numeric[(i, j)] = (ea[1 + i] - eb[1 + i]) / (2.0 * h * s);
                        }
                    }
                    let diff = (rot.chart_jacobian(&q) - numeric).amax();
                    assert!(
                        diff < 1e-8,
                        "pitch {pitch}, {side:?}, deg {degrees}: {diff}"
                    );
                }
            }
        }
    }

    #[test]
    fn left_error_is_the_estimate_times_the_right_error() {
        let truth = [0.1, 1.3, -2.0];
        let est = [0.15, 1.25, -1.9];
        let (mut r, mut l) = ([0.0; 3], [0.0; 3]);
        let right = EulerRotation {
            first: 0,
            degrees: false,
            side: ErrorSide::Right,
        };
        let left = EulerRotation {
            side: ErrorSide::Left,
            ..right
        };
        right.error_into(&truth, &est, &mut r);
        left.error_into(&truth, &est, &mut l);
        let mapped = left.from_right(&est) * Vector::<3>::from(r);
        assert!((mapped - Vector::<3>::from(l)).amax() < 1e-15);
        // R = R̂ exp(δφ_right): the error reproduces the truth.
        let back = right.matrix(&est) * exp(&Vector::<3>::from(r));
        assert!((back - right.matrix(&truth)).amax() < 1e-15);
    }

    #[test]
    fn block_maps_leave_other_rows_alone() {
        let p = Matrix::<5, 5>::from_fn(|i, j| if i == j { 1.0 + i as f64 } else { 0.1 });
        let m = exp(&Vector::<3>::new(0.2, -0.1, 0.4));
        let t = transform_blocks(&p, &[(1, m)]);
        assert_eq!(t[(0, 0)], p[(0, 0)]);
        assert_eq!(t[(4, 4)], p[(4, 4)]);
        let sub = m * p.fixed_view::<3, 3>(1, 1) * m.transpose();
        assert!((t.fixed_view::<3, 3>(1, 1) - sub).amax() < 1e-15);
        let a = conjugate_blocks(&p, &[(1, m)]).unwrap();
        assert!((a.trace() - p.trace()).abs() < 1e-13);
        assert_eq!(transform_blocks(&p, &[]), p);
    }
}
