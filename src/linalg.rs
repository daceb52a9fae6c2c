//! Fixed-size linear algebra for the per-step hot loop (nalgebra `SMatrix`), and the one place
//! that converts to faer for larger, dynamically sized problems.
//!
//! Filter algebra is small (n ≤ 9) and fixed-size, where nalgebra's stack-allocated
//! matrices beat faer per step (the docs' performance page); faer serves stacked whole-trajectory problems.

use nalgebra::{SMatrix, SVector};

pub mod so3;

/// A state, measurement or input vector of compile-time length `N`.
pub type Vector<const N: usize> = SVector<f64, N>;
/// A compile-time `R × C` matrix.
pub type Matrix<const R: usize, const C: usize> = SMatrix<f64, R, C>;

/// `(A + Aᵀ)/2`: removes the asymmetry that round-off leaves in `(I − KH)P`.
pub fn symmetrize<const N: usize>(a: &Matrix<N, N>) -> Matrix<N, N> {
    (a + a.transpose()) * 0.5
}

/// A Cholesky factorisation A = L Lᵀ of a small fixed-size SPD matrix, held as A = L̃ D L̃ᵀ
/// (L̃ unit lower triangular, D diagonal, L = L̃ D^½).
///
/// Written out for compile-time sizes so the compiler unrolls it: on the 3×3 innovation
/// covariance of the planar EKF it is several times faster than nalgebra's generic
/// decomposition, which matters in a step that runs 10⁸ times per study.
///
/// Why L̃ D L̃ᵀ rather than L itself: the factorisation is a chain, each pivot waiting for the
/// previous one, and a Cholesky pivot costs a square root *and* a division on that chain.
/// Without the root a pivot waits for one division, and the 6×6 NEES factor is a hot spot of
/// an EKF study's step loop. The quadratic form, the solves and the PD test need no root at all; L⁻¹ v takes
/// one per component, off the chain. The factor keeps 1/dᵢ, so a substitution multiplies
/// where it would divide: an N×C solve costs N divisions (at the factoring), not N·C.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SmallCholesky<const N: usize> {
    /// L̃ below the diagonal (its unit diagonal is implied); on and above it, wᵢₖ = L̃ᵢₖ dₖ at
    /// (k, i): the pivots' unscaled numerators (kept so that a pivot's update waits for one
    /// multiply, not two), and on the diagonal wₖₖ = dₖ, the pivots themselves.
    unit: Matrix<N, N>,
    inv_d: Vector<N>,
}

impl<const N: usize> SmallCholesky<N> {
    /// Factors `a` (only its lower triangle is read); `None` unless numerically SPD.
    #[inline]
    pub fn new(a: &Matrix<N, N>) -> Option<Self> {
        let mut c = SmallCholesky::unfactored();
        c.factor(a).then_some(c)
    }

    /// Factors `a` into `self` in place (the same factor as [`SmallCholesky::new`]); returns
    /// whether `a` is numerically SPD (every pivot dⱼ > 0). The step loop keeps one factor
    /// and refactors it every step, so the factor's bytes are not moved out of an `Option`
    /// each time. After `false`, `self` holds a partial factor and must be refactored before
    /// use.
    #[inline]
    pub fn factor(&mut self, a: &Matrix<N, N>) -> bool {
        let u = &mut self.unit;
        // Loops of constant length with the triangle's tests inside: they unroll fully into
        // straight-line code (with `0..j` bounds the compiler kept the loops, and a 6×6
        // factor cost about 700 instructions).
        for j in 0..N {
            let mut d = a[(j, j)];
            for k in 0..N {
                if k < j {
                    d -= u[(k, j)] * u[(j, k)];
                }
            }
            // Rejects NaN too: a NaN pivot is neither positive nor comparable.
            if d.partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater) {
                return false;
            }
            let inv = 1.0 / d;
            u[(j, j)] = d;
            self.inv_d[j] = inv;
            for i in 0..N {
                if i > j {
                    let mut w = a[(i, j)];
                    for k in 0..N {
                        if k < j {
                            w -= u[(k, i)] * u[(j, k)];
                        }
                    }
                    u[(j, i)] = w;
                    u[(i, j)] = w * inv;
                }
            }
        }
        true
    }

    /// A factor to refactor with [`SmallCholesky::factor`] (not a valid factor).
    pub fn unfactored() -> Self {
        SmallCholesky {
            unit: Matrix::<N, N>::zeros(),
            inv_d: Vector::<N>::zeros(),
        }
    }

    /// L̃⁻¹ v by forward substitution with the unit factor.
    #[inline(always)]
    fn solve_unit_lower(&self, v: &Vector<N>) -> Vector<N> {
        let mut w = *v;
        for i in 0..N {
            for k in 0..N {
                if k < i {
                    w[i] -= self.unit[(i, k)] * w[k];
                }
            }
        }
        w
    }

    /// L⁻¹ v = D^-½ L̃⁻¹ v, whose squared norm is vᵀ A⁻¹ v: the whitened innovation.
    #[inline]
    pub fn solve_lower(&self, v: &Vector<N>) -> Vector<N> {
        let mut w = self.solve_unit_lower(v);
        for i in 0..N {
            w[i] *= self.inv_d[i].sqrt();
        }
        w
    }

    /// vᵀ A⁻¹ v = Σ (L̃⁻¹ v)ᵢ² / dᵢ.
    #[inline]
    pub fn inverse_quadratic_form(&self, v: &Vector<N>) -> f64 {
        let w = self.solve_unit_lower(v);
        let mut sum = 0.0;
        for i in 0..N {
            sum += w[i] * w[i] * self.inv_d[i];
        }
        sum
    }

    /// A⁻¹ B for a right-hand side with `C` columns: L̃⁻ᵀ D⁻¹ L̃⁻¹ B.
    #[inline]
    pub fn solve<const C: usize>(&self, b: &Matrix<N, C>) -> Matrix<N, C> {
        let mut x = *b;
        for c in 0..C {
            for i in 0..N {
                let mut v = x[(i, c)];
                for k in 0..i {
                    v -= self.unit[(i, k)] * x[(k, c)];
                }
                x[(i, c)] = v;
            }
            for i in 0..N {
                x[(i, c)] *= self.inv_d[i];
            }
            for i in (0..N).rev() {
                let mut v = x[(i, c)];
                for k in i + 1..N {
                    v -= self.unit[(k, i)] * x[(k, c)];
                }
                x[(i, c)] = v;
            }
        }
        x
    }

    /// The Cholesky factor L = L̃ D^½ (lower triangular, positive diagonal).
    pub fn l(&self) -> Matrix<N, N> {
        let sqrt_d = Vector::<N>::from_fn(|j, _| self.unit[(j, j)].sqrt());
        Matrix::<N, N>::from_fn(|i, j| match i.cmp(&j) {
            std::cmp::Ordering::Less => 0.0,
            std::cmp::Ordering::Equal => sqrt_d[j],
            std::cmp::Ordering::Greater => self.unit[(i, j)] * sqrt_d[j],
        })
    }
}

/// P ← F P Fᵀ + Q for an F whose only entries that may be non-zero are at `pattern` (row,
/// column), with the columns of each row in ascending order
/// ([`crate::model::Model::transition_pattern`]).
///
/// Every element of the lower triangle is the dense product's sum in the dense product's
/// order (nalgebra's fixed-size product accumulates over the inner index in ascending order),
/// with the zero terms left out, and the upper triangle is its mirror
/// ([`mirror_lower`]): the result is the dense product made exactly symmetric, as the EKF's
/// dense path forms it, and a sparse F costs its non-zeros, not N³. P is overwritten in place
/// (no 8·N² byte copies of the result). P must be exactly symmetric, as the EKF keeps it:
/// F P is formed as (P Fᵀ)ᵀ, which has the same bits only then.
// Always inlined: a model's pattern is a constant, so inlined into the filter's predict the
// loops over it unroll into straight-line code on registers. They are indexed loops over
// columns on purpose: with `pattern.iter().filter(..)`, or with F P formed row by row (rows
// are strided in column-major storage), LLVM kept them as loops over the pattern, with P and
// F P in memory, and the step ran measurably slower (bench_step shows the difference).
#[inline(always)]
#[allow(
    clippy::needless_range_loop,
    reason = "the indexed loops over the pattern are the ones LLVM unrolls (measured)"
)]
pub fn sparse_sandwich<const N: usize>(
    f: &Matrix<N, N>,
    pattern: &[(usize, usize)],
    p: &mut Matrix<N, N>,
    q: &Matrix<N, N>,
) {
    if unit_diagonal_first(f, pattern) {
        // F = I + E with every row's diagonal first: each sum starts with 0 + 1·x = 0 + x,
        // so P + 0 stands for the diagonal's terms and only E's entries are multiplied.
        // Column i of P Fᵀ is row i of F P: P's column j is its row j, P being symmetric.
        let mut pft = p.map(|x| 0.0 + x);
        for t in 0..pattern.len() {
            let (i, j) = pattern[t];
            if i != j {
                let v = f[(i, j)];
                let (src, mut dst) = (p.column(j), pft.column_mut(i));
                for c in 0..N {
                    dst[c] += v * src[c];
                }
            }
        }
        let fp = pft.transpose();
        // Only the lower triangle of (F P) Fᵀ is summed: rows r ≥ k of each column k.
        let mut out = fp.map(|x| 0.0 + x);
        for t in 0..pattern.len() {
            let (k, j) = pattern[t];
            if k != j {
                let v = f[(k, j)];
                let (src, mut dst) = (fp.column(j), out.column_mut(k));
                for r in 0..N {
                    if r >= k {
                        dst[r] += v * src[r];
                    }
                }
            }
        }
        *p = out + q;
        mirror_lower(p);
        return;
    }
    // A unit entry adds its term without the multiply: 1·x is x, so the sums keep their
    // bits. One bounds check per entry, not per element.
    let mut pft = Matrix::<N, N>::zeros();
    for t in 0..pattern.len() {
        let (i, j) = pattern[t];
        assert!(
            i < N && j < N,
            "transition pattern entry ({i}, {j}) outside {N}×{N}"
        );
        let v = f[(i, j)];
        let (src, mut dst) = (p.column(j), pft.column_mut(i));
        if v == 1.0 {
            for c in 0..N {
                dst[c] += src[c];
            }
        } else {
            for c in 0..N {
                dst[c] += v * src[c];
            }
        }
    }
    let fp = pft.transpose();
    p.fill(0.0);
    for t in 0..pattern.len() {
        let (k, j) = pattern[t];
        let v = f[(k, j)];
        let (src, mut dst) = (fp.column(j), p.column_mut(k));
        if v == 1.0 {
            for r in 0..N {
                if r >= k {
                    dst[r] += src[r];
                }
            }
        } else {
            for r in 0..N {
                if r >= k {
                    dst[r] += v * src[r];
                }
            }
        }
    }
    *p += q;
    mirror_lower(p);
}

/// Copies the lower triangle onto the upper one. A covariance update whose lower triangle is
/// summed and mirrored is exactly symmetric (a dense product's two triangles differ in their
/// last bits, and the difference grows over a run), and costs about half the multiplies.
#[inline(always)]
pub fn mirror_lower<const N: usize>(p: &mut Matrix<N, N>) {
    // Loops of constant length unroll fully, and the triangle's test folds away.
    for c in 0..N {
        for r in 0..N {
            if r < c {
                p[(r, c)] = p[(c, r)];
            }
        }
    }
}

/// Whether every row of F has its diagonal as the first entry of `pattern` and equal to 1:
/// F = I + E with E to the right of the diagonal in each row's order (F = I + A·Δt of a
/// chain of integrators), where the dense product's sums begin with the identity's term.
#[allow(
    clippy::needless_range_loop,
    reason = "indexed as in sparse_sandwich, into which it is inlined"
)]
fn unit_diagonal_first<const N: usize>(f: &Matrix<N, N>, pattern: &[(usize, usize)]) -> bool {
    let mut rows = 0;
    let mut row = usize::MAX;
    for t in 0..pattern.len() {
        let (i, j) = pattern[t];
        if i != row {
            if j != i || i >= N || f[(i, i)] != 1.0 {
                return false;
            }
            rows += 1;
            row = i;
        }
    }
    rows == N
}

/// The positions of a constant matrix's non-zero entries, row by row in ascending column
/// order: the [`crate::model::Model::transition_pattern`] of a model with a constant F.
pub fn nonzero_pattern<const N: usize>(f: &Matrix<N, N>) -> Vec<(usize, usize)> {
    (0..N)
        .flat_map(|i| (0..N).map(move |j| (i, j)))
        .filter(|&(i, j)| f[(i, j)] != 0.0)
        .collect()
}

/// The selection s with H\[i, s\[i\]\] = 1 and every other entry 0, when a constant H is one: the
/// [`crate::model::Model::measurement_selection`] of a model with a constant H.
pub fn row_selection<const NZ: usize, const NX: usize>(h: &Matrix<NZ, NX>) -> Option<[usize; NZ]> {
    let mut sel = [0; NZ];
    for (i, s) in sel.iter_mut().enumerate() {
        let ones: Vec<usize> = (0..NX).filter(|&j| h[(i, j)] != 0.0).collect();
        match ones.as_slice() {
            [j] if h[(i, *j)] == 1.0 => *s = *j,
            _ => return None,
        }
    }
    Some(sel)
}

/// H P for H the row selection `sel` (H\[l, sel\[l\]\] = 1, every other entry 0): the rows of P.
#[inline]
pub fn select_rows<const NX: usize, const NZ: usize>(
    sel: &[usize; NZ],
    p: &Matrix<NX, NX>,
) -> Matrix<NZ, NX> {
    Matrix::<NZ, NX>::from_fn(|l, c| p[(sel[l], c)])
}

/// I − K H for H the row selection `sel`, written into `out` (the dense result: each entry is
/// 1 or 0 minus the same sum of entries of K, in the same order). In place, because the EKF
/// keeps it in its belief and a returned 8·NX² byte matrix is copied there every update.
#[inline(always)]
pub fn select_i_kh<const NX: usize, const NZ: usize>(
    k: &Matrix<NX, NZ>,
    sel: &[usize; NZ],
    out: &mut Matrix<NX, NX>,
) {
    out.fill_with_identity();
    if (1..NZ).all(|l| !sel[..l].contains(&sel[l])) {
        // Each selected column holds one column of K: δ − K, the bits of δ − (0 + K).
        for (l, &j) in sel.iter().enumerate() {
            for i in 0..NX {
                out[(i, j)] = if i == j { 1.0 } else { 0.0 } - k[(i, l)];
            }
        }
        return;
    }
    for (l, &j) in sel.iter().enumerate() {
        // A state selected twice: its column sums both columns of K, in order.
        if sel[..l].contains(&j) {
            continue;
        }
        for i in 0..NX {
            let mut kh = 0.0;
            for (m, &jm) in sel.iter().enumerate().skip(l) {
                if jm == j {
                    kh += k[(i, m)];
                }
            }
            out[(i, j)] = if i == j { 1.0 } else { 0.0 } - kh;
        }
    }
}

/// P ← P − A B for A of NX×NZ and B of NZ×NX whose result is symmetric: the Kalman update
/// P⁻ − K (H P⁻) in place. The lower triangle is formed and mirrored ([`mirror_lower`]), so
/// P stays exactly symmetric. Always inlined: nalgebra's product of these shapes is called
/// out of line, and its NX×NX result is written and read back only to be subtracted.
#[inline(always)]
pub fn subtract_product<const NX: usize, const NZ: usize>(
    p: &mut Matrix<NX, NX>,
    a: &Matrix<NX, NZ>,
    b: &Matrix<NZ, NX>,
) {
    // Column by column over the storage's column arrays, rows c.. of column c; every entry
    // sums 0 + a_i0 b_0c + a_i1 b_1c + … in that order.
    let (a_cols, b_cols, p_cols) = (&a.data.0, &b.data.0, &mut p.data.0);
    // Loops of constant length unroll fully, and the triangle's test folds away.
    for c in 0..NX {
        for i in 0..NX {
            if i >= c {
                let mut ab = 0.0;
                for l in 0..NZ {
                    ab += a_cols[l][i] * b_cols[c][l];
                }
                p_cols[c][i] -= ab;
            }
        }
    }
    mirror_lower(p);
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

/// A pre-array `[[A₁₁, A₁₂], [A₂₁, A₂₂]]` of `R1 + R2` rows and `C1 + C2 ≥ R1 + R2` columns,
/// kept as four fixed-size blocks (any of which may have zero rows or columns).
///
/// Stable Rust cannot name `Matrix<{R1 + R2}, {C1 + C2}>` in generic code, so the array is never
/// assembled: each Householder reflection spans a whole row across both column blocks and is
/// applied to both row blocks. The square-root filter's two pre-arrays fit this shape directly:
/// the time update's `[F S, L_Q]` has no second row block, and the measurement update's
/// `[[L_R, H S⁻], [0, S⁻]]` is the 2 × 2 block layout itself, whose post-array blocks
/// `[[L_S, 0], [K̄, S]]` are then read off in place.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PreArray<const R1: usize, const R2: usize, const C1: usize, const C2: usize> {
    /// Top-left block, `R1 × C1`.
    pub a11: Matrix<R1, C1>,
    /// Top-right block, `R1 × C2`.
    pub a12: Matrix<R1, C2>,
    /// Bottom-left block, `R2 × C1`.
    pub a21: Matrix<R2, C1>,
    /// Bottom-right block, `R2 × C2`.
    pub a22: Matrix<R2, C2>,
}

impl<const R1: usize, const R2: usize, const C1: usize, const C2: usize> PreArray<R1, R2, C1, C2> {
    /// Replaces the array A by its post-array `[L, 0] = A Θ` (Θ orthogonal): L is the
    /// `(R1 + R2)`-square lower-triangular matrix in the leading columns, with L Lᵀ = A Aᵀ and a
    /// non-negative diagonal, so where A has full row rank L is the Cholesky factor of A Aᵀ,
    /// obtained without forming A Aᵀ. All columns after the first `R1 + R2` become zero.
    ///
    /// Row-wise Householder (an LQ factorisation of A, i.e. QR of Aᵀ) on the stack; no
    /// allocation. Entries must be small enough for their squares to be finite (|a| ≲ 10¹⁵⁰):
    /// unlike LAPACK the row norms are not rescaled, which covariance factors never need.
    pub fn triangularize(&mut self) {
        const {
            assert!(
                R1 + R2 <= C1 + C2,
                "a pre-array needs at least as many columns as rows"
            )
        };
        for k in 0..R1 + R2 {
            let reflector = if k < R1 {
                Reflector::of_row(&self.a11, &self.a12, k, k)
            } else {
                Reflector::of_row(&self.a21, &self.a22, k - R1, k)
            };
            let Some(h) = reflector else { continue };
            // Only rows below the pivot change (see `Reflector::apply`): once the pivot has
            // left the top block that block is done, and the last pivot has no rows below.
            if k + 1 < R1 {
                h.apply(&mut self.a11, &mut self.a12);
            }
            if k + 1 < R1 + R2 {
                h.apply(&mut self.a21, &mut self.a22);
            }
            // The pivot row's image is known exactly; writing it makes the zeros exact.
            if k < R1 {
                h.write_image(&mut self.a11, &mut self.a12, k);
            } else {
                h.write_image(&mut self.a21, &mut self.a22, k - R1);
            }
        }
    }
}

/// The Householder reflection I − τ v vᵀ acting on the combined columns `k..C1 + C2` of rows
/// split across a left (`C1`) and a right (`C2`) block. v = (v₁ at column k, then the pivot
/// row's own entries right of it); those entries are stored split like the rows, zero up to
/// and including column k.
struct Reflector<const C1: usize, const C2: usize> {
    xl: [f64; C1],
    xr: [f64; C2],
    v1: f64,
    tau: f64,
    k: usize,
    mu: f64,
}

impl<const C1: usize, const C2: usize> Reflector<C1, C2> {
    /// The reflection that maps row `i` of `[left, right]` (from column k on) to μ e_k with
    /// μ = its norm ≥ 0. `None` when the row already has that form (nothing right of the pivot
    /// and a non-negative pivot), including a zero row.
    #[inline(always)]
    fn of_row<const RR: usize>(
        left: &Matrix<RR, C1>,
        right: &Matrix<RR, C2>,
        i: usize,
        k: usize,
    ) -> Option<Self> {
        let (mut xl, mut xr) = ([0.0; C1], [0.0; C2]);
        // σ = Σ x_j² over j > k, from the entries themselves rather than as ‖x‖² − x₁², which
        // would cancel away exactly the small part that matters when x₁ dominates.
        let mut sigma = 0.0;
        for j in (k + 1).min(C1)..C1 {
            xl[j] = left[(i, j)];
            sigma += xl[j] * xl[j];
        }
        for j in (k + 1).saturating_sub(C1)..C2 {
            xr[j] = right[(i, j)];
            sigma += xr[j] * xr[j];
        }
        let x1 = if k < C1 {
            left[(i, k)]
        } else {
            right[(i, k - C1)]
        };
        if sigma == 0.0 && x1 >= 0.0 {
            return None;
        }
        let mu = (x1 * x1 + sigma).sqrt();
        // v₁ = x₁ − μ makes the image +μ e_k (a non-negative diagonal with no sign fix-up
        // afterwards); for x₁ > 0 it is rewritten as −σ/(x₁ + μ) to avoid the cancellation
        // (Parlett 1971; Golub & Van Loan, Algorithm 5.1.1).
        let v1 = if x1 > 0.0 {
            -sigma / (x1 + mu)
        } else {
            x1 - mu
        };
        Some(Reflector {
            xl,
            xr,
            v1,
            tau: 2.0 / (v1 * v1 + sigma),
            k,
            mu,
        })
    }

    /// [left, right] ← [left, right] (I − τ v vᵀ), over every row of the blocks.
    ///
    /// Column by column, which is contiguous in nalgebra's column-major storage and
    /// vectorises. The rows above the pivot are included because that keeps the column loops
    /// at the fixed length `RR`, and it leaves them exactly unchanged: they are zero from
    /// column k on and v is zero before it, so their product with v is an exact 0. The pivot
    /// column comes last so that the bulk of the products does not wait for the square root
    /// and divisions behind v₁ and τ.
    #[inline(always)]
    fn apply<const RR: usize>(&self, left: &mut Matrix<RR, C1>, right: &mut Matrix<RR, C2>) {
        if RR == 0 {
            return;
        }
        let (jl, jr) = ((self.k + 1).min(C1), (self.k + 1).saturating_sub(C1));
        let mut y = [0.0; RR];
        let left_cols = left.as_slice().chunks_exact(RR).zip(&self.xl).skip(jl);
        let right_cols = right.as_slice().chunks_exact(RR).zip(&self.xr).skip(jr);
        for (col, &x) in left_cols.chain(right_cols) {
            for (y, a) in y.iter_mut().zip(col) {
                *y += a * x;
            }
        }
        let pivot = if self.k < C1 {
            &mut left.as_mut_slice()[self.k * RR..][..RR]
        } else {
            &mut right.as_mut_slice()[(self.k - C1) * RR..][..RR]
        };
        for (y, a) in y.iter_mut().zip(pivot) {
            *y = (*y + *a * self.v1) * self.tau;
            *a -= *y * self.v1;
        }
        let left_cols = left
            .as_mut_slice()
            .chunks_exact_mut(RR)
            .zip(&self.xl)
            .skip(jl);
        let right_cols = right
            .as_mut_slice()
            .chunks_exact_mut(RR)
            .zip(&self.xr)
            .skip(jr);
        for (col, &x) in left_cols.chain(right_cols) {
            for (a, y) in col.iter_mut().zip(&y) {
                *a -= y * x;
            }
        }
    }

    /// Writes the pivot row's image μ e_k into row `i`.
    #[inline(always)]
    fn write_image<const RR: usize>(
        &self,
        left: &mut Matrix<RR, C1>,
        right: &mut Matrix<RR, C2>,
        i: usize,
    ) {
        for j in self.k..C1 {
            left[(i, j)] = 0.0;
        }
        for j in self.k.saturating_sub(C1)..C2 {
            right[(i, j)] = 0.0;
        }
        if self.k < C1 {
            left[(i, self.k)] = self.mu;
        } else {
            right[(i, self.k - C1)] = self.mu;
        }
    }
}

/// The lower-triangular L (`R × R`, non-negative diagonal) with L Lᵀ = A Aᵀ for the wide array
/// A = `[left, right]` (`C1 + C2 ≥ R`): the Cholesky factor of `left leftᵀ + right rightᵀ`
/// where that is nonsingular, without forming it. The square-root filter's time update is
/// `triangularize(&(F S), &L_Q)`. See [`PreArray::triangularize`].
pub fn triangularize<const R: usize, const C1: usize, const C2: usize>(
    left: &Matrix<R, C1>,
    right: &Matrix<R, C2>,
) -> Matrix<R, R> {
    let mut pre = PreArray {
        a11: *left,
        a12: *right,
        a21: Matrix::<0, C1>::zeros(),
        a22: Matrix::<0, C2>::zeros(),
    };
    pre.triangularize();
    Matrix::<R, R>::from_fn(|i, j| {
        if j < C1 {
            pre.a11[(i, j)]
        } else {
            pre.a12[(i, j - C1)]
        }
    })
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
    fn the_ldl_factor_is_the_cholesky_factor_on_random_spd_matrices() {
        // 500 SPD matrices B Bᵀ + εI with condition numbers up to about 10⁸, against
        // nalgebra's textbook Cholesky (an independent implementation): the same L, solves,
        // whitened vector and quadratic form, each to a tolerance scaled by the conditioning.
        use rand::{RngExt, SeedableRng};
        let mut rng = rand_pcg::Pcg64::seed_from_u64(7);
        for case in 0..500 {
            let b = Matrix::<6, 6>::from_fn(|_, _| rng.random_range(-1.0..1.0));
            let eps = 10f64.powi(-(case % 9));
            let a = b * b.transpose() + Matrix::<6, 6>::identity() * eps;
            let v = Vector::<6>::from_fn(|_, _| rng.random_range(-1.0..1.0));
            let rhs = Matrix::<6, 2>::from_fn(|_, _| rng.random_range(-1.0..1.0));
            let ours = SmallCholesky::new(&a).expect("SPD");
            let theirs = nalgebra::Cholesky::new(a).expect("SPD");
            let cond = 1.0 + 40.0 / eps;
            assert!((ours.l() - theirs.l()).amax() <= 1e-14 * cond.sqrt() * a.amax().sqrt());
            let l = ours.l();
            assert!((l * l.transpose() - a).amax() <= 1e-14 * a.amax());
            let w = theirs.l().solve_lower_triangular(&v).unwrap();
            assert!((ours.solve_lower(&v) - w).amax() <= 1e-13 * cond * w.amax().max(1.0));
            let q = ours.inverse_quadratic_form(&v);
            assert!((q - w.norm_squared()).abs() <= 1e-13 * cond * q);
            assert!((q - ours.solve_lower(&v).norm_squared()).abs() <= 1e-14 * q);
            let x = ours.solve(&rhs);
            assert!((a * x - rhs).amax() <= 1e-13 * cond.sqrt() * x.amax().max(1.0));
        }
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

    /// A deterministic pseudo-random entry in [−1, 1) (SplitMix64 of the position), plus 3 on
    /// the combined array's diagonal so that the arrays stay well conditioned: the comparison
    /// with the Cholesky factor of A Aᵀ should measure our error, not that route's.
    fn entry(seed: usize, i: usize, j: usize) -> f64 {
        let mut z = (seed as u64) << 40 ^ (i as u64) << 20 ^ j as u64;
        z = z.wrapping_add(0x9e37_79b9_7f4a_7c15);
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^= z >> 31;
        let u = (z >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0;
        if i == j { u + 3.0 } else { u }
    }

    /// The pre-array assembled densely, for the reference computations only.
    fn dense<const R1: usize, const R2: usize, const C1: usize, const C2: usize>(
        p: &PreArray<R1, R2, C1, C2>,
    ) -> nalgebra::DMatrix<f64> {
        nalgebra::DMatrix::from_fn(R1 + R2, C1 + C2, |i, j| match (i < R1, j < C1) {
            (true, true) => p.a11[(i, j)],
            (true, false) => p.a12[(i, j - C1)],
            (false, true) => p.a21[(i - R1, j)],
            (false, false) => p.a22[(i - R1, j - C1)],
        })
    }

    fn pre_array<const R1: usize, const R2: usize, const C1: usize, const C2: usize>(
        seed: usize,
    ) -> PreArray<R1, R2, C1, C2> {
        PreArray {
            a11: Matrix::from_fn(|i, j| entry(seed, i, j)),
            a12: Matrix::from_fn(|i, j| entry(seed, i, j + C1)),
            a21: Matrix::from_fn(|i, j| entry(seed, i + R1, j)),
            a22: Matrix::from_fn(|i, j| entry(seed, i + R1, j + C1)),
        }
    }

    /// Triangularises `pre` and checks the post-array against the definition: [L, 0] with L
    /// lower triangular, diag(L) ≥ 0 and L Lᵀ = A Aᵀ; where A Aᵀ is nonsingular, also that L is
    /// nalgebra's Cholesky factor of A Aᵀ. Returns L.
    fn check<const R1: usize, const R2: usize, const C1: usize, const C2: usize>(
        mut pre: PreArray<R1, R2, C1, C2>,
        full_rank: bool,
    ) -> nalgebra::DMatrix<f64> {
        let a = dense(&pre);
        pre.triangularize();
        let post = dense(&pre);
        let n = R1 + R2;
        let l = post.columns(0, n).into_owned();
        for i in 0..n {
            assert!(l[(i, i)] >= 0.0, "diagonal {i}: {}", l[(i, i)]);
            for j in i + 1..post.ncols() {
                assert_eq!(post[(i, j)], 0.0, "post-array ({i}, {j}) not zero");
            }
        }
        let aat = &a * a.transpose();
        // Backward stability: every entry is within a few ulps of the array's scale.
        let tol = 1e-14 * a.amax().powi(2).max(1.0);
        assert!((&l * l.transpose() - &aat).amax() < tol, "L Lᵀ ≠ A Aᵀ");
        if full_rank {
            let chol = nalgebra::Cholesky::new(aat).expect("A Aᵀ SPD");
            assert!(
                (&l - chol.l()).amax() < 1e-12,
                "L ≠ chol(A Aᵀ):\n{l}\n{}",
                chol.l()
            );
        }
        l
    }

    #[test]
    fn triangularize_gives_the_cholesky_factor_of_a_at() {
        // The filter's two shapes (predict NX × 2NX, update (NZ+NX)-square), then rectangular
        // blocks: a pivot column that leaves the left block early (C1 < R), a left block wider
        // than the rows, an empty left block, more rows below than above.
        for seed in 0..4 {
            check(pre_array::<6, 0, 6, 6>(seed), true);
            check(pre_array::<3, 6, 3, 6>(seed), true);
            check(pre_array::<2, 6, 2, 6>(seed), true);
            check(pre_array::<4, 0, 1, 5>(seed), true);
            check(pre_array::<3, 0, 7, 2>(seed), true);
            check(pre_array::<3, 0, 0, 4>(seed), true);
            check(pre_array::<2, 3, 4, 2>(seed), true);
            check(pre_array::<1, 4, 2, 5>(seed), true);
            check(pre_array::<0, 3, 2, 1>(seed), true);
        }
        // The two-block function is the R2 = 0 case, with L read off across both blocks.
        let left = Matrix::<4, 1>::from_fn(|i, j| entry(9, i, j));
        let right = Matrix::<4, 5>::from_fn(|i, j| entry(9, i, j + 1));
        let l = triangularize(&left, &right);
        let aat = left * left.transpose() + right * right.transpose();
        assert!((l - SmallCholesky::new(&aat).unwrap().l()).amax() < 1e-12);
    }

    #[test]
    fn triangularize_handles_rank_deficient_arrays() {
        // Zero columns: rank 2 in 4 rows; L L^T still reproduces A Aᵀ, with zero pivots.
        let mut pre = pre_array::<4, 0, 2, 3>(1);
        pre.a12.fill(0.0);
        let l = check(pre, false);
        assert_eq!((l[(2, 2)], l[(3, 3)]), (0.0, 0.0));
        // A zero block, as in an update whose H S⁻ is zero: the blocks decouple.
        let mut pre = pre_array::<2, 3, 2, 3>(2);
        pre.a12.fill(0.0);
        pre.a21.fill(0.0);
        let (top, bottom) = (pre.a11, pre.a22);
        pre.triangularize();
        assert!((pre.a11 - triangularize(&top, &Matrix::<2, 0>::zeros())).amax() < 1e-15);
        assert!((pre.a22 - triangularize(&bottom, &Matrix::<3, 0>::zeros())).amax() < 1e-15);
        assert_eq!(pre.a21, Matrix::<3, 2>::zeros());
        // A zero row gives a zero row of L, and the all-zero array gives L = 0.
        let mut pre = pre_array::<3, 0, 3, 3>(3);
        pre.a11.row_mut(1).fill(0.0);
        pre.a12.row_mut(1).fill(0.0);
        let l = check(pre, false);
        assert!(l.row(1).iter().all(|&v| v == 0.0));
        assert!(l[(2, 2)] > 0.0);
        let zero = triangularize(&Matrix::<3, 3>::zeros(), &Matrix::<3, 2>::zeros());
        assert_eq!(zero, Matrix::<3, 3>::zeros());
        // Two equal rows: rank 1, the second pivot is zero up to round-off.
        let row = Matrix::<1, 4>::from_fn(|_, j| entry(4, 0, j));
        let a = Matrix::<2, 4>::from_fn(|_, j| row[(0, j)]);
        let l = triangularize(&a, &Matrix::<2, 0>::zeros());
        assert!(l[(1, 1)] >= 0.0 && l[(1, 1)] < 1e-15);
        assert!((l * l.transpose() - a * a.transpose()).amax() < 1e-14);
    }

    #[test]
    fn triangularize_diagonal_is_non_negative() {
        // −I and diagonals of mixed sign: the reflection must map each row onto +‖row‖ e_k,
        // including rows with nothing right of a negative pivot (a pure sign flip).
        let minus_i = triangularize(&(-Matrix::<3, 3>::identity()), &Matrix::<3, 1>::zeros());
        assert_eq!(minus_i, Matrix::<3, 3>::identity());
        let d = Matrix::<3, 3>::from_diagonal(&Vector::<3>::new(-2.0, 3.0, -0.5));
        let l = triangularize(&Matrix::<3, 0>::zeros(), &d);
        assert_eq!(
            l,
            Matrix::<3, 3>::from_diagonal(&Vector::<3>::new(2.0, 3.0, 0.5))
        );
        // Negative pivots with mass to their right, for every seed's signs.
        for seed in 0..8 {
            let mut pre = pre_array::<5, 0, 5, 5>(seed);
            pre.a11 = -pre.a11.abs();
            check(pre, true);
        }
    }

    #[test]
    fn triangularize_keeps_accuracy_where_forming_a_at_loses_it() {
        // A very precise sensor: P⁻ = I₂, H = [1, 0], R = ε². The update pre-array
        // [[ε, 1, 0], [0, 1, 0], [0, 0, 1]] has A Aᵀ = [[1 + ε², 1, 0], [1, 1, 0], [0, 0, 1]],
        // whose exact factor has the posterior standard deviation ε/√(1 + ε²) as its (1, 1)
        // pivot. Forming A Aᵀ rounds 1 + ε² with an absolute error up to 2⁻⁵³ ≈ 1.1·10⁻¹⁶, i.e.
        // an error of order 10⁻¹⁶/ε in that pivot: the product squares the condition number.
        // Householder works on A itself and is backward stable, so the error stays at a few
        // ulps of ‖A‖ = 1 whatever ε is.
        for eps in [1e-4, 1e-6, 1e-7, 1e-9] {
            let pre = PreArray {
                a11: Matrix::<1, 1>::new(eps),
                a12: Matrix::<1, 2>::new(1.0, 0.0),
                a21: Matrix::<2, 1>::zeros(),
                a22: Matrix::<2, 2>::identity(),
            };
            let exact_sd = eps / (1.0 + eps * eps).sqrt();
            let mut qr = pre;
            qr.triangularize();
            let qr_err = (qr.a22[(0, 0)] - exact_sd).abs();
            let a = dense(&pre);
            let naive =
                SmallCholesky::new(&Matrix::<3, 3>::from_fn(|i, j| a.row(i).dot(&a.row(j))));
            let naive_err = naive.map_or(f64::INFINITY, |c| (c.l()[(1, 1)] - exact_sd).abs());
            println!("ε = {eps:e}: |error| QR {qr_err:.1e}, naive {naive_err:.1e}");
            // A few ulps of ‖A‖: 4·2⁻⁵³ ≈ 4.4·10⁻¹⁶.
            assert!(qr_err <= 4.5e-16, "ε = {eps}: QR error {qr_err:e}");
            assert!((qr.a21[(0, 0)] - 1.0 / (1.0 + eps * eps).sqrt()).abs() <= 4.5e-16);
            if eps <= 1e-6 {
                // Forming A Aᵀ costs at least three orders of magnitude here (at ε = 10⁻⁹,
                // 1 + ε² rounds to 1: A Aᵀ is singular and the factorisation fails).
                assert!(
                    naive_err > 1e3 * qr_err.max(f64::EPSILON * eps),
                    "ε = {eps}"
                );
            }
        }
    }

    #[test]
    fn eigenvalues_of_a_rotation_are_cos_plus_minus_i_sin() {
        let w = 0.7f64;
        let ev = eigenvalues(&Matrix::<2, 2>::new(w.cos(), -w.sin(), w.sin(), w.cos())).unwrap();
        assert!((ev[0].0 - w.cos()).abs() < 1e-14 && (ev[0].1 + w.sin()).abs() < 1e-14);
        assert!((ev[1].0 - w.cos()).abs() < 1e-14 && (ev[1].1 - w.sin()).abs() < 1e-14);
    }
}
