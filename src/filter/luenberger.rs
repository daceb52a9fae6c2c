//! Luenberger observer: the Kalman filter's predict/update structure with a fixed gain K chosen
//! by pole placement instead of from noise statistics (seed 002, §5.4).
//!
//! x̂⁻_k = f(x̂_{k−1}, u_k),  x̂_k = x̂⁻_k + K (z_k − h(x̂⁻_k, u_k)),
//!
//! so for a linear model the estimation error obeys e_k = (I − K H) F e_{k−1} and "placing the
//! poles" means choosing K with eig((I − K H) F) = the requested set, MATLAB's
//! `place(F', (H*F)', p)'`.
//!
//! # Why this placement method
//!
//! With several outputs the gain is not unique: every choice of closed-loop eigenvectors from
//! the admissible subspaces gives one. The choice matters, because the eigenvalues of the
//! closed loop are only as accurate, and the transient ‖e_k‖ ≤ κ(X) ρᵏ ‖e_0‖ only as short, as
//! the eigenvector matrix X is well conditioned. Kautsky, Nichols & Van Dooren ("Robust pole
//! assignment in linear state feedback", Int. J. Control 41(5), 1985) choose the eigenvectors to
//! keep X well conditioned; their method 0 is what MATLAB's `place` and SciPy's `place_poles`
//! implement. Single-input formulas (Ackermann on a reduction to one output) instead fix the
//! eigenvectors arbitrarily and lose digits through the companion form.
//!
//! The computation is on the dual state-feedback problem A − B G with A = Fᵀ, B = (HF)ᵀ, K = Gᵀ:
//! * B = U Σ Vᵀ; for each pole λ the eigenvectors it may have are the null space S_λ of
//!   U₁ᵀ (A − λ I) (U₁ spans range(B)^⊥), of dimension rank(B) when (A, B) is controllable;
//! * sweeps of coordinate ascent on |det X| with unit columns (the KNV-0 step; Tits & Yang,
//!   IEEE TAC 41(10), 1996, show it is exactly that ascent): a real pole's vector becomes the
//!   projection onto S_λ of the direction orthogonal to all other columns. A conjugate pair
//!   (x, x̄) is updated together: with Q the real 2-D complement of the other columns and
//!   x = S_λ c, |det Qᵀ[x x̄]| = 2 |cᴴ Ĥ c| for a Hermitian Ĥ, so its top eigenvector is the exact
//!   maximiser — the pair stays conjugate and the gain real;
//! * the sweeps start from a fixed generic combination of each basis rather than a basis
//!   column: structured systems (L1's three decoupled axes) otherwise start on a saddle where
//!   the ascent stalls for tens of sweeps;
//! * G = V Σ⁻¹ U₀ᵀ (A − X Λ X⁻¹) with X, Λ in real 2×2-block form; it is the minimum-norm gain
//!   when HF is rank deficient.
//!
//! Observability is checked on (F, HF), the pair the update form actually sees (it equals that
//! of (F, H) when F is invertible), by an orthogonal block-Krylov (staircase) recursion rather
//! than the rank of the power matrix [HF; HF²; …], which loses digits as powers grow.
//!
//! The observer carries no covariance: [`Filter::covariance`] is `None` and NEES/NIS are
//! reported as null, like the running mean.

use faer::c64;
use nalgebra::{DMatrix, DVector};

use super::{Filter, FilterError, Innovation};
use crate::linalg::{Matrix, Vector};
use crate::model::{Measurement, Model};

/// Relative tolerance of every numerical rank decision (rank of HF, controllable subspace).
const RANK_TOL: f64 = 1e-10;
/// Poles closer than this (relative to max(1, |λ|)) count as one point: the multiplicity check
/// and conjugate matching. √ε: a Jordan block perturbed by ε splits its eigenvalue by √ε, so
/// closer poles are numerically a multiple pole.
const SAME_POLE_TOL: f64 = 1e-8;
/// Sweeps stop when one raises |det X| by less than this fraction…
const SWEEP_RTOL: f64 = 1e-6;
/// …or after this many (a few suffice; the determinant then creeps along flat ridges).
const MAX_SWEEPS: usize = 50;
/// Above this condition number of X the placed eigenvalues would carry no useful accuracy.
const MAX_CONDITION: f64 = 1e12;

/// Why a gain could not be placed.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum PlacementError {
    /// The pole list does not have one pole per state.
    #[error("{got} poles requested for a state of dimension {expected}")]
    WrongPoleCount {
        /// NX.
        expected: usize,
        /// The list's length.
        got: usize,
    },
    /// A complex pole without its conjugate: the gain would have to be complex.
    #[error("the pole list is not closed under complex conjugation: {re} {im:+}i has no conjugate")]
    NotConjugateClosed {
        /// Real part of the unmatched pole.
        re: f64,
        /// Imaginary part of the unmatched pole.
        im: f64,
    },
    /// Some error modes cannot be moved by any gain.
    #[error(
        "(F, H) is not observable through the observer update (pair (F, HF)): \
         observability rank {rank} < {n}"
    )]
    NotObservable {
        /// Dimension of the observable subspace of (F, HF).
        rank: usize,
        /// NX.
        n: usize,
    },
    /// One point can be an eigenvalue with at most rank(HF) independent eigenvectors.
    #[error(
        "pole {re} {im:+}i is requested {multiplicity} times, but at most rank(HF) = {max} \
         (the number of independent outputs) poles can be placed at one point"
    )]
    MultiplicityTooLarge {
        /// Real part of the pole.
        re: f64,
        /// Imaginary part of the pole.
        im: f64,
        /// How many times it was requested (poles within 1e-8 relative count as one point).
        multiplicity: usize,
        /// rank(HF).
        max: usize,
    },
    /// NaN or ±∞ in F, H or the poles.
    #[error("non-finite {what}")]
    NonFinite {
        /// "F", "H" or "pole".
        what: &'static str,
    },
    /// The eigenvector matrix stayed (numerically) singular.
    #[error("no well-conditioned set of closed-loop eigenvectors (condition number {condition:e})")]
    IllConditioned {
        /// κ₂(X) reached.
        condition: f64,
    },
    /// A decomposition failed to converge.
    #[error("{what} did not converge")]
    NoConvergence {
        /// Which decomposition.
        what: &'static str,
    },
}

/// A placed observer gain and how robust the placement is.
#[derive(Clone, Debug, PartialEq)]
pub struct ObserverPlacement<const NX: usize, const NZ: usize> {
    /// K, with eig((I − K H) F) = the requested poles.
    pub gain: Matrix<NX, NZ>,
    /// κ₂(X) of the closed-loop eigenvector matrix (unit columns). It bounds the eigenvalues'
    /// sensitivity (Bauer–Fike) and the transient: ‖e_k‖ ≤ κ₂(X) ρᵏ ‖e_0‖, ρ = max |λ|.
    pub eigenvector_condition: f64,
    /// KNV sweeps made.
    pub sweeps: usize,
}

/// The observer gain K with eig((I − K H) F) = `poles` (given as (re, im)), by robust
/// eigenstructure assignment (see the module docs).
///
/// # Errors
/// [`PlacementError`]: not NX poles; a complex pole without its conjugate; (F, HF) not
/// observable; a pole requested more than rank(HF) times; NaN or ±∞ in F, H or the poles; an
/// eigenvector matrix that stays singular (κ₂ > 1e12); a decomposition that fails.
pub fn place_observer_poles<const NX: usize, const NZ: usize>(
    f: &Matrix<NX, NX>,
    h: &Matrix<NZ, NX>,
    poles: &[(f64, f64)],
) -> Result<Matrix<NX, NZ>, PlacementError> {
    place_observer(f, h, poles).map(|p| p.gain)
}

/// [`place_observer_poles`] with the eigenvector conditioning and sweep count.
pub fn place_observer<const NX: usize, const NZ: usize>(
    f: &Matrix<NX, NX>,
    h: &Matrix<NZ, NX>,
    poles: &[(f64, f64)],
) -> Result<ObserverPlacement<NX, NZ>, PlacementError> {
    let fd = DMatrix::from_fn(NX, NX, |i, j| f[(i, j)]);
    let hd = DMatrix::from_fn(NZ, NX, |i, j| h[(i, j)]);
    let p = place_dyn(&fd, &hd, poles)?;
    Ok(ObserverPlacement {
        gain: Matrix::<NX, NZ>::from_fn(|i, j| p.gain[(i, j)]),
        eigenvector_condition: p.condition,
        sweeps: p.sweeps,
    })
}

/// How to read the seed's printed pole list λ = a·[−0.707 ± 0.707i, 1, −0.3536 ± 0.3536i, 0.5].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum SeedPoleReading {
    /// Literally: the real poles are +a and +0.5a.
    #[default]
    Printed,
    /// The leading minus applies to the whole list: the real poles are −a and −0.5a (the
    /// complex ones are unchanged).
    Negated,
}

/// Seed 002 §5.4's observer poles for scale `a` (the seed uses 0.9, 0.5 and 0.2).
pub fn seed_poles(a: f64, reading: SeedPoleReading) -> [(f64, f64); 6] {
    let s = match reading {
        SeedPoleReading::Printed => 1.0,
        SeedPoleReading::Negated => -1.0,
    };
    [
        (-0.707 * a, 0.707 * a),
        (-0.707 * a, -0.707 * a),
        (s * a, 0.0),
        (-0.3536 * a, 0.3536 * a),
        (-0.3536 * a, -0.3536 * a),
        (s * 0.5 * a, 0.0),
    ]
}

/// A real pole or a conjugate pair re ± i·im (im > 0): one or two columns of X.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Block {
    Real(f64),
    Pair(f64, f64),
}

impl Block {
    fn lambda(self) -> c64 {
        match self {
            Block::Real(re) => c64::new(re, 0.0),
            Block::Pair(re, im) => c64::new(re, im),
        }
    }
}

fn close(a: c64, b: c64) -> bool {
    (a - b).norm() <= SAME_POLE_TOL * a.norm().max(1.0)
}

/// Groups the poles into real poles and conjugate pairs.
fn blocks(poles: &[(f64, f64)]) -> Result<Vec<Block>, PlacementError> {
    let mut used = vec![false; poles.len()];
    let mut out = Vec::with_capacity(poles.len());
    for i in 0..poles.len() {
        if used[i] {
            continue;
        }
        used[i] = true;
        let (re, im) = poles[i];
        if im == 0.0 {
            out.push(Block::Real(re));
            continue;
        }
        let target = c64::new(re, -im);
        let partner = (i + 1..poles.len())
            .find(|&j| !used[j] && close(target, c64::new(poles[j].0, poles[j].1)));
        match partner {
            Some(j) => {
                used[j] = true;
                out.push(Block::Pair(re, im.abs()));
            }
            None => return Err(PlacementError::NotConjugateClosed { re, im }),
        }
    }
    Ok(out)
}

/// A full real SVD A = U diag(σ) Vᵀ, σ non-increasing.
struct RealSvd {
    u: DMatrix<f64>,
    s: Vec<f64>,
    v: DMatrix<f64>,
}

/// Full SVD of a real matrix (faer).
fn svd_real(a: &DMatrix<f64>) -> Result<RealSvd, PlacementError> {
    let svd = faer::Mat::<f64>::from_fn(a.nrows(), a.ncols(), |i, j| a[(i, j)])
        .svd()
        .map_err(|_| PlacementError::NoConvergence { what: "real SVD" })?;
    let (u, v, s) = (svd.U(), svd.V(), svd.S().column_vector());
    Ok(RealSvd {
        u: DMatrix::from_fn(u.nrows(), u.ncols(), |i, j| u[(i, j)]),
        s: (0..s.nrows()).map(|i| s[i]).collect(),
        v: DMatrix::from_fn(v.nrows(), v.ncols(), |i, j| v[(i, j)]),
    })
}

/// Full SVD of a complex matrix (faer): σ (non-increasing) and V.
fn svd_complex(a: &DMatrix<c64>) -> Result<(Vec<f64>, DMatrix<c64>), PlacementError> {
    let svd = faer::Mat::<c64>::from_fn(a.nrows(), a.ncols(), |i, j| a[(i, j)])
        .svd()
        .map_err(|_| PlacementError::NoConvergence {
            what: "complex SVD",
        })?;
    let (v, s) = (svd.V(), svd.S().column_vector());
    Ok((
        (0..s.nrows()).map(|i| s[i].re).collect(),
        DMatrix::from_fn(v.nrows(), v.ncols(), |i, j| v[(i, j)]),
    ))
}

/// Dimension of the controllable subspace of (A, B), B's range given by the orthonormal `q0`:
/// an orthogonal block-Krylov recursion (each new block is A times the last one, orthogonalised
/// twice against the basis, kept where its singular values exceed RANK_TOL·‖A‖).
fn controllable_dimension(a: &DMatrix<f64>, q0: DMatrix<f64>) -> Result<usize, PlacementError> {
    let n = a.nrows();
    let scale = a.norm().max(f64::MIN_POSITIVE);
    let mut basis = q0.clone();
    let mut fresh = q0;
    while basis.ncols() < n && fresh.ncols() > 0 {
        let mut w = a * &fresh;
        for _ in 0..2 {
            let proj = basis.transpose() * &w;
            w -= &basis * proj;
        }
        let RealSvd { u, s, .. } = svd_real(&w)?;
        let k = s
            .iter()
            .filter(|&&v| v > RANK_TOL * scale)
            .count()
            .min(n - basis.ncols());
        fresh = u.columns(0, k).into_owned();
        let c = basis.ncols();
        let mut grown = DMatrix::<f64>::zeros(n, c + k);
        grown.columns_mut(0, c).copy_from(&basis);
        grown.columns_mut(c, k).copy_from(&fresh);
        basis = grown;
    }
    Ok(basis.ncols())
}

/// The real form of X (a real pole's column; Re x, Im x for a pair), without block `skip`.
fn real_form(blocks: &[Block], xs: &[DVector<c64>], skip: Option<usize>) -> DMatrix<f64> {
    let n = xs.first().map_or(0, |x| x.len());
    let mut cols: Vec<DVector<f64>> = Vec::with_capacity(n);
    for (j, (b, x)) in blocks.iter().zip(xs).enumerate() {
        if Some(j) == skip {
            continue;
        }
        cols.push(x.map(|v| v.re));
        if let Block::Pair(..) = b {
            cols.push(x.map(|v| v.im));
        }
    }
    DMatrix::from_fn(n, cols.len(), |i, j| cols[j][i])
}

/// The placement in dynamic sizes: gain (n × m), κ₂(X) and sweeps.
#[derive(Debug)]
struct DynPlacement {
    gain: DMatrix<f64>,
    condition: f64,
    sweeps: usize,
}

fn place_dyn(
    f: &DMatrix<f64>,
    h: &DMatrix<f64>,
    poles: &[(f64, f64)],
) -> Result<DynPlacement, PlacementError> {
    let (n, m) = (f.nrows(), h.nrows());
    if poles.len() != n {
        return Err(PlacementError::WrongPoleCount {
            expected: n,
            got: poles.len(),
        });
    }
    for (what, ok) in [
        ("F", f.iter().all(|v| v.is_finite())),
        ("H", h.iter().all(|v| v.is_finite())),
        (
            "pole",
            poles.iter().all(|p| p.0.is_finite() && p.1.is_finite()),
        ),
    ] {
        if !ok {
            return Err(PlacementError::NonFinite { what });
        }
    }
    let blocks = blocks(poles)?;
    if n == 0 {
        return Ok(DynPlacement {
            gain: DMatrix::zeros(0, m),
            condition: 1.0,
            sweeps: 0,
        });
    }

    // The dual state-feedback problem A − B G, G = Kᵀ.
    let a = f.transpose();
    let b = (h * f).transpose();
    let RealSvd {
        u: ub,
        s: sb,
        v: vb,
    } = if m == 0 {
        RealSvd {
            u: DMatrix::identity(n, n),
            s: Vec::new(),
            v: DMatrix::zeros(0, 0),
        }
    } else {
        svd_real(&b)?
    };
    let smax = sb.first().copied().unwrap_or(0.0);
    let r = sb.iter().filter(|&&s| s > RANK_TOL * smax).count();
    let rank = controllable_dimension(&a, ub.columns(0, r).into_owned())?;
    if rank < n {
        return Err(PlacementError::NotObservable { rank, n });
    }
    for &(re, im) in poles {
        let p = c64::new(re, im);
        let multiplicity = poles
            .iter()
            .filter(|q| close(p, c64::new(q.0, q.1)))
            .count();
        if multiplicity > r {
            return Err(PlacementError::MultiplicityTooLarge {
                re,
                im,
                multiplicity,
                max: r,
            });
        }
    }

    // Admissible eigenvector subspaces S_λ = null(U₁ᵀ (A − λ I)), orthonormal n × r.
    let u1 = ub.columns(r, n - r).into_owned();
    let mut subspaces: Vec<DMatrix<c64>> = Vec::with_capacity(blocks.len());
    for &blk in &blocks {
        let s = if r == n {
            DMatrix::<c64>::identity(n, n)
        } else {
            match blk {
                Block::Real(l) => {
                    let mut al = a.clone();
                    for i in 0..n {
                        al[(i, i)] -= l;
                    }
                    let v = svd_real(&(u1.transpose() * al))?.v;
                    v.columns(n - r, r).map(|x| c64::new(x, 0.0))
                }
                Block::Pair(..) => {
                    let mut al = a.map(|x| c64::new(x, 0.0));
                    for i in 0..n {
                        al[(i, i)] -= blk.lambda();
                    }
                    let u1c = u1.map(|x| c64::new(x, 0.0));
                    let (_, v) = svd_complex(&(u1c.transpose() * al))?;
                    v.columns(n - r, r).into_owned()
                }
            }
        };
        subspaces.push(s);
    }

    // Start from a fixed generic combination (golden-ratio sequence) of each basis.
    const PHI: f64 = 0.618_033_988_749_894_9;
    let mut xs: Vec<DVector<c64>> = subspaces
        .iter()
        .enumerate()
        .map(|(j, s)| {
            let c = DVector::<f64>::from_fn(r, |i, _| ((j * r + i + 1) as f64 * PHI).fract() - 0.5);
            let c = c.normalize();
            s * c.map(|v| c64::new(v, 0.0))
        })
        .collect();

    let abs_det = |xs: &[DVector<c64>]| real_form(&blocks, xs, None).determinant().abs();
    let mut det = abs_det(&xs);
    let mut sweeps = 0;
    while sweeps < MAX_SWEEPS {
        sweeps += 1;
        for (j, &blk) in blocks.iter().enumerate() {
            let width = if let Block::Pair(..) = blk { 2 } else { 1 };
            // Q: a real orthonormal basis of the complement of the other columns' span.
            let y = real_form(&blocks, &xs, Some(j));
            let q = if y.ncols() == 0 {
                DMatrix::<f64>::identity(n, width)
            } else {
                svd_real(&y)?.u.columns(n - width, width).into_owned()
            };
            let s = &subspaces[j];
            let qc = q.map(|v| c64::new(v, 0.0));
            match blk {
                Block::Real(_) => {
                    // max |qᵀ x| over unit x ∈ S: x ∝ S Sᴴ q.
                    let c = s.adjoint() * qc.column(0);
                    let norm = c.norm();
                    if norm > 0.0 {
                        xs[j] = s * (c / c64::new(norm, 0.0));
                    }
                }
                Block::Pair(..) => {
                    // |det Qᵀ[x x̄]| = 2|Im(w₁ w̄₂)| = 2|cᴴ Ĥ c|, w = Qᵀ S c.
                    let w = qc.transpose() * s;
                    let (m1, m2) = (w.row(0), w.row(1));
                    let two_i = c64::new(0.0, 2.0);
                    let hh = DMatrix::<c64>::from_fn(r, r, |k, l| {
                        (m2[k].conj() * m1[l] - m1[k].conj() * m2[l]) / two_i
                    });
                    // Hermitian r × r through its real symmetric 2r × 2r embedding.
                    let emb = DMatrix::<f64>::from_fn(2 * r, 2 * r, |i, k| {
                        let e = hh[(i % r, k % r)];
                        match (i < r, k < r) {
                            (true, true) | (false, false) => e.re,
                            (true, false) => -e.im,
                            (false, true) => e.im,
                        }
                    });
                    let eig = nalgebra::SymmetricEigen::new(emb);
                    let best = (0..2 * r)
                        .max_by(|&p, &q| {
                            eig.eigenvalues[p]
                                .abs()
                                .total_cmp(&eig.eigenvalues[q].abs())
                        })
                        .unwrap_or(0);
                    if eig.eigenvalues[best].abs() > 0.0 {
                        let v = eig.eigenvectors.column(best);
                        let c = DVector::<c64>::from_fn(r, |i, _| c64::new(v[i], v[i + r]));
                        let x = s * &c;
                        let norm = x.norm();
                        xs[j] = x / c64::new(norm, 0.0);
                    }
                }
            }
        }
        let next = abs_det(&xs);
        let done = next - det <= SWEEP_RTOL * next;
        det = next;
        if done {
            break;
        }
    }

    // κ₂ of the complex eigenvector matrix [.., x, x̄, ..] (unit columns).
    let mut xc = DMatrix::<c64>::zeros(n, n);
    let mut col = 0;
    for (b, x) in blocks.iter().zip(&xs) {
        xc.set_column(col, x);
        col += 1;
        if let Block::Pair(..) = b {
            xc.set_column(col, &x.map(|v| v.conj()));
            col += 1;
        }
    }
    let (sx, _) = svd_complex(&xc)?;
    let condition = sx[0] / sx[n - 1];
    if condition.is_nan() || condition > MAX_CONDITION {
        return Err(PlacementError::IllConditioned { condition });
    }

    // A_cl = X Λ X⁻¹ in real block form, then G = V Σ⁻¹ U₀ᵀ (A − A_cl).
    let xr = real_form(&blocks, &xs, None);
    let mut lam = DMatrix::<f64>::zeros(n, n);
    let mut c = 0;
    for b in &blocks {
        match *b {
            Block::Real(l) => {
                lam[(c, c)] = l;
                c += 1;
            }
            Block::Pair(re, im) => {
                lam[(c, c)] = re;
                lam[(c, c + 1)] = im;
                lam[(c + 1, c)] = -im;
                lam[(c + 1, c + 1)] = re;
                c += 2;
            }
        }
    }
    let a_cl_t = xr.transpose().lu().solve(&(&xr * lam).transpose()).ok_or(
        PlacementError::IllConditioned {
            condition: f64::INFINITY,
        },
    )?;
    let rhs = ub.columns(0, r).transpose() * (&a - a_cl_t.transpose());
    let g = DMatrix::from_fn(m, n, |i, j| {
        (0..r)
            .map(|k| vb[(i, k)] * rhs[(k, j)] / sb[k])
            .sum::<f64>()
    });
    Ok(DynPlacement {
        gain: g.transpose(),
        condition,
        sweeps,
    })
}

/// Luenberger observer configuration: the fixed gain K.
#[derive(Clone, Debug, PartialEq)]
pub struct Luenberger<const NX: usize, const NZ: usize> {
    /// K (NX × NZ).
    pub gain: Matrix<NX, NZ>,
}

impl<const NX: usize, const NZ: usize> Luenberger<NX, NZ> {
    /// The observer with gain `gain`.
    pub fn new(gain: Matrix<NX, NZ>) -> Self {
        Luenberger { gain }
    }

    /// The observer whose error dynamics (I − K H) F, with F and H of `model` linearised at
    /// x = 0, u = 0 (exact for a linear model), have eigenvalues `poles`.
    pub fn from_poles<const NU: usize, M: Model<NX, NU, NZ>>(
        model: &M,
        poles: &[(f64, f64)],
    ) -> Result<Self, PlacementError> {
        let (x, u) = (Vector::<NX>::zeros(), Vector::<NU>::zeros());
        let f = model.transition_jacobian(&x, &u);
        let h = model.measurement_jacobian(&x, &u);
        place_observer_poles(&f, &h, poles).map(Self::new)
    }
}

fn finite<const NX: usize>(x: &Vector<NX>) -> Result<(), FilterError> {
    if x.iter().all(|v| v.is_finite()) {
        Ok(())
    } else {
        Err(FilterError::NonFinite {
            what: "state estimate",
        })
    }
}

/// The belief is the estimate x̂ alone. There is no `error_transition`: its only consumers (the
/// calibrated NEES test and the burn-in rule) need a covariance, which the observer lacks.
impl<const NX: usize, const NU: usize, const NZ: usize, M: Model<NX, NU, NZ>> Filter<NX, NU, NZ, M>
    for Luenberger<NX, NZ>
{
    type Belief = Vector<NX>;

    fn init(
        &self,
        _model: &M,
        x0_hat: &Vector<NX>,
        _p0: &Matrix<NX, NX>,
        _z0: &Measurement<NZ>,
    ) -> Vector<NX> {
        *x0_hat
    }

    fn predict(&self, model: &M, x: &mut Vector<NX>, u: &Vector<NU>) -> Result<(), FilterError> {
        *x = model.propagate(x, u);
        finite(x)
    }

    /// x̂ += K ν with the gain column of every component that did not report zeroed (done by
    /// zeroing its residual, which also keeps a NaN placeholder out). No innovation covariance,
    /// hence no NIS: returns `Ok(None)`.
    fn update(
        &self,
        model: &M,
        x: &mut Vector<NX>,
        u: &Vector<NU>,
        z: &Measurement<NZ>,
    ) -> Result<Option<Innovation<NZ>>, FilterError> {
        if z.available.count() == 0 {
            return Ok(None);
        }
        let mut nu = model.residual(&z.z, &model.measure(x, u));
        for i in 0..NZ {
            if !z.available.has(i) {
                nu[i] = 0.0;
            }
        }
        *x += self.gain * nu;
        finite(x)?;
        Ok(None)
    }

    fn mean(&self, x: &Vector<NX>) -> Vector<NX> {
        *x
    }

    fn covariance(&self, _x: &Vector<NX>) -> Option<Matrix<NX, NX>> {
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::Availability;
    use crate::systems::linear_quadrotor::model::{Linear, LinearSensor};
    use rand::{RngExt, SeedableRng};
    use rand_distr::{Distribution, StandardNormal};
    use rand_pcg::Pcg64;

    /// Eigenvalues of a dynamic real matrix (faer).
    fn eig(a: &DMatrix<f64>) -> Vec<c64> {
        faer::Mat::<f64>::from_fn(a.nrows(), a.ncols(), |i, j| a[(i, j)])
            .eigenvalues()
            .expect("eigenvalues")
    }

    /// max over the requested poles of the distance to the computed eigenvalue matched to it
    /// (greedy nearest unused; the poles here are separated far beyond the errors).
    fn max_pole_error(computed: &[c64], requested: &[(f64, f64)]) -> f64 {
        assert_eq!(computed.len(), requested.len());
        let mut used = vec![false; computed.len()];
        let mut worst = 0.0f64;
        for &(re, im) in requested {
            let p = c64::new(re, im);
            let (k, d) = computed
                .iter()
                .enumerate()
                .filter(|(k, _)| !used[*k])
                .map(|(k, c)| (k, (c - p).norm()))
                .min_by(|a, b| a.1.total_cmp(&b.1))
                .unwrap();
            used[k] = true;
            worst = worst.max(d);
        }
        worst
    }

    fn closed_loop(f: &DMatrix<f64>, h: &DMatrix<f64>, k: &DMatrix<f64>) -> DMatrix<f64> {
        (DMatrix::identity(f.nrows(), f.nrows()) - k * h) * f
    }

    fn normal(rng: &mut Pcg64) -> f64 {
        StandardNormal.sample(rng)
    }

    /// Random observable MIMO systems, n = 4..9, m = 1..3, fixed seed. Each pole list holds an
    /// exact eigenvalue of F (F is block triangular with a known diagonal entry μ) and, when
    /// m ≥ 2, a real pole repeated m times (the largest multiplicity allowed).
    #[test]
    fn random_mimo_systems_get_their_poles() {
        let mut rng = Pcg64::seed_from_u64(0x9e37_79b9);
        let mut worst = 0.0f64;
        let mut worst_kappa = 0.0f64;
        let mut relaxed = 0;
        let mut worst_mimo = 0.0f64;
        for n in 4..=9 {
            for m in 1..=3 {
                for _ in 0..4 {
                    let mut f =
                        DMatrix::<f64>::from_fn(n, n, |_, _| normal(&mut rng)) / (n as f64).sqrt();
                    let mu = rng.random::<f64>() * 1.6 - 0.8;
                    for j in 0..n - 1 {
                        f[(n - 1, j)] = 0.0;
                    }
                    f[(n - 1, n - 1)] = mu;
                    let h = DMatrix::<f64>::from_fn(m, n, |_, _| normal(&mut rng));
                    assert!(eig(&f).iter().any(|e| *e == c64::new(mu, 0.0)));
                    let mut poles = vec![(mu, 0.0)];
                    if m >= 2 {
                        let rep = rng.random::<f64>() * 1.6 - 0.8;
                        poles.extend(std::iter::repeat_n((rep, 0.0), m));
                    }
                    while poles.len() < n {
                        let rho = 0.1 + 0.8 * rng.random::<f64>();
                        if n - poles.len() >= 2 && rng.random::<f64>() < 0.5 {
                            let th = 0.1 + 3.0 * rng.random::<f64>();
                            poles.push((rho * th.cos(), rho * th.sin()));
                            poles.push((rho * th.cos(), -rho * th.sin()));
                        } else {
                            poles.push((rho * (2.0 * rng.random::<f64>() - 1.0), 0.0));
                        }
                    }
                    let p = place_dyn(&f, &h, &poles).expect("placement");
                    let err = max_pole_error(&eig(&closed_loop(&f, &h, &p.gain)), &poles);
                    // Eigenvalues with eigenvector condition κ cannot even be *computed* to
                    // better than ~κ ε ‖A‖ (Bauer–Fike); only single-output systems, whose gain
                    // is unique, reach a κ where that exceeds 1e-8.
                    let floor = 1e3 * f64::EPSILON * p.condition * f.norm();
                    if floor > 1e-8 {
                        assert_eq!(m, 1, "κ = {:e} with {m} outputs", p.condition);
                        relaxed += 1;
                    }
                    assert!(
                        err <= floor.max(1e-8),
                        "n = {n}, m = {m}: error {err:e}, κ = {:e}",
                        p.condition
                    );
                    worst = worst.max(err);
                    if m > 1 {
                        worst_mimo = worst_mimo.max(err);
                    }
                    worst_kappa = worst_kappa.max(p.condition);
                }
            }
        }
        println!(
            "72 random systems: max pole error {worst:.1e} ({worst_mimo:.1e} with m ≥ 2), \
             max κ(X) {worst_kappa:.1e}, \
             {relaxed} single-output case(s) judged against κ ε ‖F‖"
        );
    }

    #[test]
    fn a_single_output_gain_is_the_unique_one() {
        // n = 2, m = 1: K is unique; check against the closed form for F = [[1, 1], [0, 1]],
        // H = [1, 0], poles 0 and 0.5 (not repeated: multiplicity 2 > rank(HF) = 1).
        let f = Matrix::<2, 2>::new(1.0, 1.0, 0.0, 1.0);
        let h = Matrix::<1, 2>::new(1.0, 0.0);
        let k = place_observer_poles(&f, &h, &[(0.0, 0.0), (0.5, 0.0)]).unwrap();
        // (I − KH)F = [[1 − k1, 1 − k1], [−k2, 1 − k2]]: trace 2 − k1 − k2 = 0.5,
        // det (1 − k1)(1 − k2) + k2(1 − k1) = 1 − k1 = 0 ⇒ k1 = 1, k2 = 0.5.
        assert!(
            (k[(0, 0)] - 1.0).abs() < 1e-12 && (k[(1, 0)] - 0.5).abs() < 1e-12,
            "{k}"
        );
    }

    #[test]
    fn the_error_cases_are_reported() {
        let l1 = Linear::<3>::new(LinearSensor::Positions, 0.1).unwrap();
        let (f, h) = (l1.discrete().f, *l1.h());
        let good = seed_poles(0.5, SeedPoleReading::Printed);
        assert!(place_observer_poles(&f, &h, &good).is_ok());

        assert_eq!(
            place_observer_poles(&f, &h, &good[..5]),
            Err(PlacementError::WrongPoleCount {
                expected: 6,
                got: 5
            })
        );
        let mut lonely = good;
        lonely[1] = (-0.3, 0.2);
        assert!(matches!(
            place_observer_poles(&f, &h, &lonely),
            Err(PlacementError::NotConjugateClosed { .. })
        ));
        let mut nan = good;
        nan[2].0 = f64::NAN;
        assert_eq!(
            place_observer_poles(&f, &h, &nan),
            Err(PlacementError::NonFinite { what: "pole" })
        );
        let mut f_inf = f;
        f_inf[(1, 1)] = f64::INFINITY;
        assert_eq!(
            place_observer_poles(&f_inf, &h, &good),
            Err(PlacementError::NonFinite { what: "F" })
        );
        let mut h_nan = h;
        h_nan[(0, 0)] = f64::NAN;
        assert_eq!(
            place_observer_poles(&f, &h_nan, &good),
            Err(PlacementError::NonFinite { what: "H" })
        );

        // Three copies are allowed with three outputs, four are not.
        let three = [
            (0.3, 0.0),
            (0.3, 0.0),
            (0.3, 0.0),
            (0.5, 0.0),
            (0.1, 0.2),
            (0.1, -0.2),
        ];
        assert!(place_observer_poles(&f, &h, &three).is_ok());
        let four = [
            (0.3, 0.0),
            (0.3, 0.0),
            (0.3, 0.0),
            (0.3, 0.0),
            (0.1, 0.2),
            (0.1, -0.2),
        ];
        assert_eq!(
            place_observer_poles(&f, &h, &four),
            Err(PlacementError::MultiplicityTooLarge {
                re: 0.3,
                im: 0.0,
                multiplicity: 4,
                max: 3
            })
        );
        // Poles within 1e-8 of each other are one point.
        let mut near = four;
        near[3].0 += 1e-12;
        assert!(matches!(
            place_observer_poles(&f, &h, &near),
            Err(PlacementError::MultiplicityTooLarge {
                multiplicity: 4,
                ..
            })
        ));

        // Velocities leave the three positions unobservable; x, y leave z, ż.
        let vel = Linear::<3>::new(LinearSensor::Velocities, 0.1).unwrap();
        assert_eq!(
            place_observer_poles(&vel.discrete().f, vel.h(), &good),
            Err(PlacementError::NotObservable { rank: 3, n: 6 })
        );
        let xy = Linear::<2>::new(LinearSensor::Xy, 0.1).unwrap();
        assert_eq!(
            place_observer_poles(&xy.discrete().f, xy.h(), &good),
            Err(PlacementError::NotObservable { rank: 4, n: 6 })
        );
        // A singular F: (I − KH)F keeps the zero mode whatever K is (here ẋ no longer moves
        // anything, so (F, HF) loses exactly that direction).
        let mut f0 = f;
        f0.column_mut(1).fill(0.0);
        assert_eq!(
            place_observer_poles(&f0, &h, &good),
            Err(PlacementError::NotObservable { rank: 5, n: 6 })
        );
        let e = PlacementError::NotObservable { rank: 3, n: 6 };
        assert!(e.to_string().contains("rank 3 < 6"), "{e}");
    }

    #[test]
    fn seed_poles_follow_the_two_readings() {
        let p = seed_poles(0.5, SeedPoleReading::Printed);
        let n = seed_poles(0.5, SeedPoleReading::Negated);
        assert_eq!(SeedPoleReading::default(), SeedPoleReading::Printed);
        assert_eq!((p[2], p[5]), ((0.5, 0.0), (0.25, 0.0)));
        assert_eq!((n[2], n[5]), ((-0.5, 0.0), (-0.25, 0.0)));
        for i in [0, 1, 3, 4] {
            assert_eq!(p[i], n[i]);
        }
        assert_eq!(p[0], (-0.3535, 0.3535));
        assert_eq!(p[4], (-0.1768, -0.1768));
    }

    #[test]
    fn the_update_ignores_components_that_did_not_report() {
        let l1 = Linear::<3>::new(LinearSensor::Positions, 0.1).unwrap();
        let obs = Luenberger::from_poles(&l1, &seed_poles(0.5, SeedPoleReading::Printed)).unwrap();
        let u = Vector::<4>::zeros();
        let x0 = Vector::<6>::new(1.0, 0.2, -1.0, 0.0, 2.0, 0.1);
        let mut full = obs.init(
            &l1,
            &x0,
            &Matrix::identity(),
            &Measurement {
                z: Vector::zeros(),
                available: Availability::all(3),
            },
        );
        let mut part = full;
        obs.predict(&l1, &mut full, &u).unwrap();
        obs.predict(&l1, &mut part, &u).unwrap();
        let prior = full;
        let z = Vector::<3>::new(1.5, -0.5, 2.5);
        assert_eq!(
            obs.update(
                &l1,
                &mut full,
                &u,
                &Measurement {
                    z,
                    available: Availability::all(3)
                }
            ),
            Ok(None)
        );
        assert!((full - (prior + obs.gain * (z - l1.h() * prior))).amax() < 1e-15);
        // Component 1 missing, with a NaN placeholder: only columns 0 and 2 of K act.
        let zp = Vector::<3>::new(1.5, f64::NAN, 2.5);
        obs.update(
            &l1,
            &mut part,
            &u,
            &Measurement {
                z: zp,
                available: Availability(0b101),
            },
        )
        .unwrap();
        let mut k = obs.gain;
        k.column_mut(1).fill(0.0);
        let nu = Vector::<3>::new(z[0] - prior[0], 0.0, z[2] - prior[4]);
        assert!((part - (prior + k * nu)).amax() < 1e-15);
        assert_eq!(Filter::<6, 4, 3, Linear<3>>::covariance(&obs, &part), None);
        // Nothing reported: the prediction stands.
        let mut none = prior;
        obs.update(
            &l1,
            &mut none,
            &u,
            &Measurement {
                z: zp,
                available: Availability(0),
            },
        )
        .unwrap();
        assert_eq!(none, prior);
        // A non-finite estimate is an error.
        let mut bad = prior;
        bad[3] = f64::INFINITY;
        assert_eq!(
            obs.predict(&l1, &mut bad, &u),
            Err(FilterError::NonFinite {
                what: "state estimate"
            })
        );
    }
}
