//! Fixed-size linear algebra for the per-step hot loop (nalgebra `SMatrix`), and the one place
//! that converts to faer for larger, dynamically sized problems.
//!
//! DESIGN §8: filter algebra is small (n ≤ 9) and fixed-size, where nalgebra's stack-allocated
//! matrices beat faer by about 2× per step; faer serves stacked whole-trajectory problems.

use nalgebra::{Cholesky, Const, SMatrix, SVector};

/// A state, measurement or input vector of compile-time length `N`.
pub type Vector<const N: usize> = SVector<f64, N>;
/// A compile-time `R × C` matrix.
pub type Matrix<const R: usize, const C: usize> = SMatrix<f64, R, C>;

/// `(A + Aᵀ)/2`: removes the asymmetry that round-off leaves in `(I − KH)P`.
pub fn symmetrize<const N: usize>(a: &Matrix<N, N>) -> Matrix<N, N> {
    (a + a.transpose()) * 0.5
}

/// Cholesky factor of a symmetric matrix, or `None` when it is not numerically positive definite.
pub fn cholesky<const N: usize>(a: &Matrix<N, N>) -> Option<Cholesky<f64, Const<N>>> {
    Cholesky::new(*a)
}

/// The quadratic form `vᵀ A⁻¹ v` through a Cholesky factor of `A` (never an explicit inverse).
pub fn inverse_quadratic_form<const N: usize>(
    chol: &Cholesky<f64, Const<N>>,
    v: &Vector<N>,
) -> f64 {
    // ‖L⁻¹v‖² = vᵀ(LLᵀ)⁻¹v; one triangular solve instead of two.
    let w = chol
        .l_dirty()
        .solve_lower_triangular(v)
        .expect("a Cholesky factor has a non-zero diagonal");
    w.norm_squared()
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
    assert_eq!((a.nrows(), a.ncols()), (R, C), "faer/nalgebra shape mismatch");
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quadratic_form_matches_explicit_inverse() {
        let a = Matrix::<3, 3>::new(4.0, 1.0, 0.5, 1.0, 3.0, 0.2, 0.5, 0.2, 2.0);
        let v = Vector::<3>::new(0.3, -1.2, 2.0);
        let chol = cholesky(&a).expect("SPD");
        let explicit = (v.transpose() * a.try_inverse().unwrap() * v)[(0, 0)];
        assert!((inverse_quadratic_form(&chol, &v) - explicit).abs() < 1e-12);
    }

    #[test]
    fn cholesky_rejects_indefinite() {
        let a = Matrix::<2, 2>::new(1.0, 2.0, 2.0, 1.0);
        assert!(cholesky(&a).is_none());
    }

    #[test]
    fn faer_round_trip_and_rank() {
        let a = Matrix::<3, 3>::new(1.0, 2.0, 3.0, 2.0, 4.0, 6.0, 0.0, 1.0, 1.0);
        let f = to_faer(&a);
        assert_eq!(from_faer::<3, 3>(f.as_ref()), a);
        assert_eq!(numerical_rank(f.as_ref(), 1e-12), 2);
    }
}
