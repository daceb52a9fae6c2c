//! Fixed-size linear algebra for the per-step hot loop (nalgebra `SMatrix`), and the one place
//! that converts to faer for larger, dynamically sized problems.
//!
//! DESIGN §8: filter algebra is small (n ≤ 9) and fixed-size, where nalgebra's stack-allocated
//! matrices beat faer by about 2× per step; faer serves stacked whole-trajectory problems.

use nalgebra::{SMatrix, SVector};

/// A state, measurement or input vector of compile-time length `N`.
pub type Vector<const N: usize> = SVector<f64, N>;
/// A compile-time `R × C` matrix.
pub type Matrix<const R: usize, const C: usize> = SMatrix<f64, R, C>;

/// `(A + Aᵀ)/2`: removes the asymmetry that round-off leaves in `(I − KH)P`.
pub fn symmetrize<const N: usize>(a: &Matrix<N, N>) -> Matrix<N, N> {
    (a + a.transpose()) * 0.5
}

/// A Cholesky factor L (lower triangular, A = L Lᵀ) of a small fixed-size SPD matrix.
///
/// Written out for compile-time sizes so the compiler unrolls it: on the 3×3 innovation
/// covariance of the planar EKF it is several times faster than nalgebra's generic
/// decomposition, which matters in a step that runs 10⁸ times per study.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SmallCholesky<const N: usize> {
    l: Matrix<N, N>,
}

impl<const N: usize> SmallCholesky<N> {
    /// Factors `a` (only its lower triangle is read); `None` unless numerically SPD.
    #[inline]
    pub fn new(a: &Matrix<N, N>) -> Option<Self> {
        let mut l = Matrix::<N, N>::zeros();
        for j in 0..N {
            let mut d = a[(j, j)];
            for k in 0..j {
                d -= l[(j, k)] * l[(j, k)];
            }
            // Rejects NaN too: a NaN pivot is neither positive nor comparable.
            if d.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater) {
                return None;
            }
            let djj = d.sqrt();
            l[(j, j)] = djj;
            for i in j + 1..N {
                let mut v = a[(i, j)];
                for k in 0..j {
                    v -= l[(i, k)] * l[(j, k)];
                }
                l[(i, j)] = v / djj;
            }
        }
        Some(SmallCholesky { l })
    }

    /// L⁻¹ v by forward substitution.
    #[inline]
    pub fn solve_lower(&self, v: &Vector<N>) -> Vector<N> {
        let mut w = *v;
        for i in 0..N {
            for k in 0..i {
                w[i] -= self.l[(i, k)] * w[k];
            }
            w[i] /= self.l[(i, i)];
        }
        w
    }

    /// vᵀ A⁻¹ v = ‖L⁻¹ v‖².
    #[inline]
    pub fn inverse_quadratic_form(&self, v: &Vector<N>) -> f64 {
        self.solve_lower(v).norm_squared()
    }

    /// A⁻¹ B for a right-hand side with `C` columns (forward then back substitution).
    #[inline]
    pub fn solve<const C: usize>(&self, b: &Matrix<N, C>) -> Matrix<N, C> {
        let mut x = *b;
        for c in 0..C {
            for i in 0..N {
                let mut v = x[(i, c)];
                for k in 0..i {
                    v -= self.l[(i, k)] * x[(k, c)];
                }
                x[(i, c)] = v / self.l[(i, i)];
            }
            for i in (0..N).rev() {
                let mut v = x[(i, c)];
                for k in i + 1..N {
                    v -= self.l[(k, i)] * x[(k, c)];
                }
                x[(i, c)] = v / self.l[(i, i)];
            }
        }
        x
    }

    /// The factor L.
    pub fn l(&self) -> &Matrix<N, N> {
        &self.l
    }
}

/// Diagonal matrix from standard deviations: `diag(σ²)`.
pub fn diag_from_std<const N: usize>(std: &Vector<N>) -> Matrix<N, N> {
    Matrix::<N, N>::from_diagonal(&std.component_mul(std))
}

/// Converts a fixed-size matrix into a faer matrix (for the larger, dynamic problems).
pub fn to_faer<const R: usize, const C: usize>(a: &Matrix<R, C>) -> faer::Mat<f64> {
    faer::Mat::from_fn(R, C, |i, j| a[(i, j)])
}

/// Converts a faer matrix of the right shape back into a fixed-size matrix.
///
/// # Panics
/// When the shapes differ; callers build the faer matrix from the same dimensions.
pub fn from_faer<const R: usize, const C: usize>(a: faer::MatRef<'_, f64>) -> Matrix<R, C> {
    assert_eq!(
        (a.nrows(), a.ncols()),
        (R, C),
        "faer/nalgebra shape mismatch"
    );
    Matrix::<R, C>::from_fn(|i, j| a[(i, j)])
}

/// Numerical rank of a matrix by a rank-revealing decomposition (faer's SVD): the number of
/// singular values above `rel_tol · σ_max`.
pub fn numerical_rank(a: faer::MatRef<'_, f64>, rel_tol: f64) -> usize {
    let Ok(s) = a.singular_values() else {
        return 0;
    };
    let max = s.iter().cloned().fold(0.0_f64, f64::max);
    s.iter().filter(|&&v| v > rel_tol * max).count()
}

/// The matrix exponential e^A by scaling and squaring with a Taylor approximant.
///
/// A is scaled by 2^−s until ‖A‖₁/2^s ≤ 1/2; there the degree-18 Taylor remainder is below
/// 0.5¹⁹/19! ≈ 2·10⁻²³, far under f64 round-off, and s squarings undo the scaling. Used for
/// the small, fixed-size discretisation problems (zero-order hold, Van Loan), once per model.
pub fn expm<const N: usize>(a: &Matrix<N, N>) -> Matrix<N, N> {
    let norm = (0..N)
        .map(|j| a.column(j).iter().map(|v| v.abs()).sum::<f64>())
        .fold(0.0_f64, f64::max);
    let mut s = 0u32;
    while norm / 2f64.powi(s as i32) > 0.5 && s < 64 {
        s += 1;
    }
    let scaled = a / 2f64.powi(s as i32);
    let mut term = Matrix::<N, N>::identity();
    let mut sum = Matrix::<N, N>::identity();
    for k in 1..=18 {
        term = term * scaled / k as f64;
        sum += term;
    }
    for _ in 0..s {
        sum = sum * sum;
    }
    sum
}

/// A lower-triangular L with L Lᵀ = A Aᵀ and a non-negative diagonal, from the QR
/// factorisation of Aᵀ (A = Rᵀ Qᵀ, so A Aᵀ = Rᵀ R): the square-root filter's way of combining
/// stacked factors without ever forming the product A Aᵀ. `a` has at least as many columns as
/// rows.
pub fn triangularize(a: &nalgebra::DMatrix<f64>) -> nalgebra::DMatrix<f64> {
    let r = a.transpose().qr().r();
    let n = a.nrows();
    let mut l = r.transpose().view((0, 0), (n, n)).into_owned();
    // Householder QR leaves arbitrary signs on the diagonal; flipping a column of L is an
    // orthogonal change that keeps L Lᵀ and makes L the (unique) Cholesky factor.
    for j in 0..n {
        if l[(j, j)] < 0.0 {
            for i in 0..n {
                l[(i, j)] = -l[(i, j)];
            }
        }
    }
    l
}

/// Eigenvalues (re, im) of a small fixed-size matrix by faer's eigendecomposition, sorted by
/// real then imaginary part; `None` when the decomposition fails to converge.
pub fn eigenvalues<const N: usize>(a: &Matrix<N, N>) -> Option<Vec<(f64, f64)>> {
    let mut ev: Vec<(f64, f64)> = to_faer(a)
        .eigenvalues()
        .ok()?
        .into_iter()
        .map(|c| (c.re, c.im))
        .collect();
    ev.sort_by(|x, y| x.0.total_cmp(&y.0).then(x.1.total_cmp(&y.1)));
    Some(ev)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quadratic_form_matches_explicit_inverse() {
        let a = Matrix::<3, 3>::new(4.0, 1.0, 0.5, 1.0, 3.0, 0.2, 0.5, 0.2, 2.0);
        let v = Vector::<3>::new(0.3, -1.2, 2.0);
        let chol = SmallCholesky::new(&a).expect("SPD");
        let explicit = (v.transpose() * a.try_inverse().unwrap() * v)[(0, 0)];
        assert!((chol.inverse_quadratic_form(&v) - explicit).abs() < 1e-12);
    }

    #[test]
    fn small_cholesky_agrees_with_nalgebra() {
        let a = Matrix::<3, 3>::new(4.0, 1.0, 0.5, 1.0, 3.0, 0.2, 0.5, 0.2, 2.0);
        let b = Matrix::<3, 6>::from_fn(|i, j| (i * 7 + j * 3) as f64 * 0.1 - 0.8);
        let v = Vector::<3>::new(0.3, -1.2, 2.0);
        let ours = SmallCholesky::new(&a).unwrap();
        let theirs = nalgebra::Cholesky::new(a).unwrap();
        assert!((ours.l() - theirs.l()).amax() < 1e-14);
        assert!((ours.solve(&b) - theirs.solve(&b)).amax() < 1e-13);
        let w = theirs.l().solve_lower_triangular(&v).unwrap();
        assert!((ours.inverse_quadratic_form(&v) - w.norm_squared()).abs() < 1e-13);
        assert!(SmallCholesky::new(&Matrix::<2, 2>::new(1.0, 2.0, 2.0, 1.0)).is_none());
        assert!(SmallCholesky::new(&Matrix::<1, 1>::new(f64::NAN)).is_none());
    }

    #[test]
    fn faer_round_trip_and_rank() {
        let a = Matrix::<3, 3>::new(1.0, 2.0, 3.0, 2.0, 4.0, 6.0, 0.0, 1.0, 1.0);
        let f = to_faer(&a);
        assert_eq!(from_faer::<3, 3>(f.as_ref()), a);
        assert_eq!(numerical_rank(f.as_ref(), 1e-12), 2);
    }

    #[test]
    fn expm_matches_closed_forms() {
        // Rotation generator: e^{[[0, −w], [w, 0]]} = [[cos w, −sin w], [sin w, cos w]]; a large
        // w exercises the squaring.
        for w in [0.3, 2.0, 25.0] {
            let e = expm(&Matrix::<2, 2>::new(0.0, -w, w, 0.0));
            let c = Matrix::<2, 2>::new(w.cos(), -w.sin(), w.sin(), w.cos());
            assert!((e - c).amax() < 1e-12, "w = {w}: {e}");
        }
        // Nilpotent: e^N = I + N + N²/2 exactly for a strictly upper-triangular 3×3 N.
        let n = Matrix::<3, 3>::new(0.0, 2.0, -1.0, 0.0, 0.0, 3.0, 0.0, 0.0, 0.0);
        let exact = Matrix::<3, 3>::identity() + n + n * n / 2.0;
        assert!((expm(&n) - exact).amax() < 1e-14);
        // Diagonal: e^{diag(d)} = diag(e^d).
        let d = Matrix::<2, 2>::new(-3.0, 0.0, 0.0, 1.5);
        let e = expm(&d);
        assert!((e[(0, 0)] - (-3.0f64).exp()).abs() < 1e-15);
        assert!((e[(1, 1)] - 1.5f64.exp()).abs() < 1e-13);
    }

    #[test]
    fn triangularize_gives_the_cholesky_factor_of_a_at() {
        let a = nalgebra::DMatrix::<f64>::from_fn(3, 5, |i, j| {
            ((i * i * 3 + j * j + 1) as f64).sqrt().sin()
        });
        let l = triangularize(&a);
        let aat = &a * a.transpose();
        assert!((&l * l.transpose() - &aat).amax() < 1e-13);
        let chol = nalgebra::Cholesky::new(aat).unwrap();
        assert!((l - chol.l()).amax() < 1e-12);
    }

    #[test]
    fn eigenvalues_of_a_rotation_are_cos_plus_minus_i_sin() {
        let w = 0.7f64;
        let ev = eigenvalues(&Matrix::<2, 2>::new(w.cos(), -w.sin(), w.sin(), w.cos())).unwrap();
        assert!((ev[0].0 - w.cos()).abs() < 1e-14 && (ev[0].1 + w.sin()).abs() < 1e-14);
        assert!((ev[1].0 - w.cos()).abs() < 1e-14 && (ev[1].1 - w.sin()).abs() < 1e-14);
    }
}
