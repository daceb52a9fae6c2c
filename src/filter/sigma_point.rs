//! Sigma-point Kalman filters: the unscented Kalman filter (UKF) and the third-degree
//! cubature Kalman filter (CKF). One code serves both; they differ only in their points and
//! weights ([`SigmaPoints`]).
//!
//! With P = L Lᵀ (Cholesky), spread c and pair weight w = 1/(2c²), the points are
//! χ_{j±} = x̂ ± c L e_j (j = 1..n) and, for the UKF only, a centre point χ_0 = x̂:
//!
//! | | c² | w_{m,0} | w_{c,0} |
//! |---|---|---|---|
//! | UKF (Van der Merwe) | n + λ, λ = α²(n + κ) − n | λ/(n + λ) | λ/(n + λ) + 1 − α² + β |
//! | CKF (Arasaratnam & Haykin) | n | no centre point | no centre point |
//!
//! Predict (additive noise): y_i = f(χ_i, u_k), x̂⁻ = Σ w_{m,i} y_i, P⁻ = Σ w_{c,i} d_i d_iᵀ + Q
//! with d_i = y_i ⊖ x̂⁻. Update: the points are drawn again from (x̂⁻, P⁻) (so they carry Q),
//! ζ_i = h(χ_i, u_k), ẑ = Σ w_{m,i} ζ_i, S = Σ w_{c,i} e_i e_iᵀ + R with e_i = ζ_i ⊖ ẑ,
//! P_xz = Σ w_{c,i} (χ_i − x̂⁻) e_iᵀ, K = P_xz S⁻¹, x̂ = x̂⁻ + K ν with ν = z ⊖ ẑ, and
//! P = P⁻ − K S Kᵀ.
//!
//! **Angles.** ⊖ is [`Model::state_residual`] / [`Model::residual`], which wrap the model's
//! [`Model::angle_states`] / [`Model::angle_measurements`] to [−π, π); the weighted mean of
//! an angle component is the circular mean a + atan2(Σ w_i sin(y_i − a), Σ w_i cos(y_i − a)),
//! anchored at the first point's value a, so the mean stays on the branch the model keeps its
//! angle on (the planar θ is continuous) whichever branch each point lands on.
//!
//! **Multi-rate.** Components that did not report are removed as in the EKF: their rows of
//! ν and of the cross-covariance and their rows and columns of the points' spread are zeroed
//! and their block of R replaced by the identity, so their columns of K are zero and the
//! update equals one over the reporting components alone.
//!
//! **Error transition** (the statistical linearisation, for the calibrated NEES test and the
//! burn-in rule): F̃ = P_{x_k x_{k−1}} P_{k−1}⁻¹ and H̃ = P_xzᵀ (P⁻)⁻¹, A_k = (I − K H̃) F̃.
//! Because χ_{j±} − x̂ = ±c L e_j, F̃ = D L⁻¹ / (2c) where column j of D is d_{j+} − d_{j−}: a
//! central difference of f along the Cholesky directions, exact (= F) for a linear model.
//! Only D and L are kept per step; the solve is made when a consistency test asks.
//!
//! **Positive definiteness.** P⁻ and P must be factored to draw points. A factorisation that
//! fails is repaired as every filter repairs ([`super::repair_spd`]) and counted
//! ([`Filter::internal_repairs`]); with non-negative weights (the defaults) P⁻ ⪰ Q, so a
//! repair needs a singular Q or a covariance rounded into indefiniteness.
//!
//! Requirements on the model: f and h only (no Jacobians), and the angle components.
//!
//! # Reference
//! Julier & Uhlmann, "Unscented filtering and nonlinear estimation", Proc. IEEE 92(3), 2004;
//! Wan & van der Merwe, "The unscented Kalman filter for nonlinear estimation", AS-SPCC 2000;
//! Arasaratnam & Haykin, "Cubature Kalman filters", IEEE TAC 54(6), 2009.

use super::{Filter, FilterError, Innovation, check_finite, mask_rows, repair_spd};
use crate::linalg::{Matrix, SmallCholesky, Vector, symmetrize};
use crate::model::{Availability, Measurement, Model};

/// Which points and weights a sigma-point filter uses.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum SigmaPoints {
    /// Van der Merwe's scaled unscented points: 2n + 1 points, spread √(α²(n + κ)).
    Unscented {
        /// α ∈ (0, 1]: the spread of the points around the mean.
        alpha: f64,
        /// β ≥ 0: prior knowledge of the distribution in the centre covariance weight (2 is
        /// optimal for a Gaussian).
        beta: f64,
        /// κ: secondary scaling; n + κ must be positive.
        kappa: f64,
    },
    /// The third-degree spherical-radial cubature rule: 2n points x̂ ± √n L e_j, weight 1/(2n).
    Cubature,
}

/// Why a set of unscented parameters is unusable.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum SigmaPointError {
    /// α outside (0, 1].
    #[error("{0} is not in (0, 1]")]
    Alpha(f64),
    /// β negative or not finite.
    #[error("{0} is not a non-negative number")]
    Beta(f64),
    /// κ not finite.
    #[error("{0} is not a finite number")]
    Kappa(f64),
    /// n + κ ≤ 0, so n + λ = α²(n + κ) ≤ 0 and the points have no real spread.
    #[error(
        "n + κ = {n} + ({kappa}) is not positive: the points' spread is √(α²(n + κ)) with n = {n} states"
    )]
    Spread {
        /// The state dimension.
        n: usize,
        /// The κ given.
        kappa: f64,
    },
    /// α so small that α²(n + κ) underflows to zero.
    #[error("{0} is so small that α²(n + κ) underflows to 0: the points would not spread")]
    AlphaUnderflow(f64),
}

impl SigmaPointError {
    /// The spec key the error is about (`alpha`, `beta` or `kappa`).
    pub fn key(&self) -> &'static str {
        match self {
            SigmaPointError::Alpha(_) | SigmaPointError::AlphaUnderflow(_) => "alpha",
            SigmaPointError::Beta(_) => "beta",
            SigmaPointError::Kappa(_) | SigmaPointError::Spread { .. } => "kappa",
        }
    }
}

/// The points' spread and weights for a state of dimension n.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Weights {
    /// c: the points are x̂ ± c L e_j.
    pub spread: f64,
    /// w = 1/(2c²): the mean and covariance weight of every ± point.
    pub pair: f64,
    /// (w_{m,0}, w_{c,0}) of the centre point x̂, when there is one (the UKF).
    pub centre: Option<(f64, f64)>,
}

impl SigmaPoints {
    /// The default unscented parameters: α = 1, β = 2, κ = 0.
    ///
    /// α = 1, κ = 0 put the points at ±√n σ with pair weights 1/(2n) and a zero centre mean
    /// weight, and β = 2 gives the centre a covariance weight of 2: every weight is
    /// non-negative, so P⁻ = Σ w_c d dᵀ + Q ⪰ Q is positive definite by construction. The
    /// textbook α = 10⁻³ puts the points at ±0.0024σ (n = 6), which samples f only where the
    /// EKF's Jacobian does, with a centre weight of −10⁶ whose cancellation costs six digits
    /// and can make P⁻ indefinite; κ = 3 − n = −3 (Julier's fourth-moment match) gives a
    /// centre mean weight of −1 (its covariance weight is 1 with β = 2). The price of the wide spread, measured on the
    /// planar IMU set (`docs/src/systems/sigma-point.md`): at high noise S comes out too large, and
    /// α = 0.1 stays consistent longer until its −99 centre weight forces repairs.
    pub const DEFAULT_UNSCENTED: SigmaPoints = SigmaPoints::Unscented {
        alpha: 1.0,
        beta: 2.0,
        kappa: 0.0,
    };

    /// The spread and weights for `n` states, or why the parameters are unusable.
    pub fn weights(self, n: usize) -> Result<Weights, SigmaPointError> {
        match self {
            SigmaPoints::Cubature => Ok(Weights {
                spread: (n as f64).sqrt(),
                pair: 0.5 / n as f64,
                centre: None,
            }),
            SigmaPoints::Unscented { alpha, beta, kappa } => {
                if !(alpha > 0.0 && alpha <= 1.0) {
                    return Err(SigmaPointError::Alpha(alpha));
                }
                if !(beta.is_finite() && beta >= 0.0) {
                    return Err(SigmaPointError::Beta(beta));
                }
                if !kappa.is_finite() {
                    return Err(SigmaPointError::Kappa(kappa));
                }
                let nf = n as f64;
                let n_lambda = alpha * alpha * (nf + kappa);
                if nf + kappa <= 0.0 {
                    return Err(SigmaPointError::Spread { n, kappa });
                }
                if n_lambda <= 0.0 {
                    return Err(SigmaPointError::AlphaUnderflow(alpha));
                }
                let lambda = n_lambda - nf;
                Ok(Weights {
                    spread: n_lambda.sqrt(),
                    pair: 0.5 / n_lambda,
                    centre: Some((
                        lambda / n_lambda,
                        lambda / n_lambda + 1.0 - alpha * alpha + beta,
                    )),
                })
            }
        }
    }
}

/// A sigma-point Kalman filter (`kind = "ukf"` or `"ckf"`): the Q and R it assumes and its
/// points.
#[derive(Clone, Debug, PartialEq)]
pub struct SigmaPointKalman<const NX: usize, const NZ: usize> {
    /// Assumed process-noise covariance Q (additive).
    pub q: Matrix<NX, NX>,
    /// Assumed measurement-noise covariance R (additive).
    pub r: Matrix<NZ, NZ>,
    points: SigmaPoints,
    weights: Weights,
}

impl<const NX: usize, const NZ: usize> SigmaPointKalman<NX, NZ> {
    /// The filter assuming noise `q`, `r` with the given points.
    pub fn new(
        q: Matrix<NX, NX>,
        r: Matrix<NZ, NZ>,
        points: SigmaPoints,
    ) -> Result<Self, SigmaPointError> {
        Ok(SigmaPointKalman {
            q,
            r,
            weights: points.weights(NX)?,
            points,
        })
    }

    /// The points it uses.
    pub fn points(&self) -> SigmaPoints {
        self.points
    }

    /// Their spread and weights.
    pub fn weights(&self) -> Weights {
        self.weights
    }
}

/// The belief of a sigma-point filter: mean, covariance and what the error transition needs.
#[derive(Clone, Debug, PartialEq)]
pub struct SigmaBelief<const NX: usize, const NZ: usize> {
    /// x̂
    pub x: Vector<NX>,
    /// P
    pub p: Matrix<NX, NX>,
    /// F̃ L_{k−1} (half the central difference of f along the points, over c) and L_{k−1}.
    f_l: Matrix<NX, NX>,
    l_prev: Matrix<NX, NX>,
    /// After an update: K, H̃ L⁻ and L⁻.
    gain: Option<(Matrix<NX, NZ>, Matrix<NZ, NX>, Matrix<NX, NX>)>,
    repairs: u32,
}

impl<const NX: usize, const NZ: usize> SigmaBelief<NX, NZ> {
    /// A belief with mean `x` and covariance `p`.
    pub fn new(x: Vector<NX>, p: Matrix<NX, NX>) -> Self {
        SigmaBelief {
            x,
            p,
            f_l: Matrix::<NX, NX>::identity(),
            l_prev: Matrix::<NX, NX>::identity(),
            gain: None,
            repairs: 0,
        }
    }
}

/// The image of the points under a function g: the weighted mean and the deviations from it.
#[derive(Clone, Debug, PartialEq)]
pub struct Cloud<const M: usize, const NX: usize> {
    /// ḡ = Σ w_{m,i} g(χ_i), circular in the angle components.
    pub mean: Vector<M>,
    /// Column j: g(x̂ + c L e_j) ⊖ ḡ.
    pub plus: Matrix<M, NX>,
    /// Column j: g(x̂ − c L e_j) ⊖ ḡ.
    pub minus: Matrix<M, NX>,
    /// g(x̂) ⊖ ḡ (zero without a centre point).
    pub centre: Vector<M>,
}

impl<const M: usize, const NX: usize> Cloud<M, NX> {
    /// Σ w_{c,i} d_i d_iᵀ.
    #[inline]
    pub fn covariance(&self, w: &Weights) -> Matrix<M, M> {
        let mut c =
            (self.plus * self.plus.transpose() + self.minus * self.minus.transpose()) * w.pair;
        if let Some((_, wc0)) = w.centre {
            c += self.centre * self.centre.transpose() * wc0;
        }
        c
    }

    /// (D/(2c)) with column j of D = d_{j+} − d_{j−}: the regression of g on the state times
    /// L (G̃ L, with G̃ = P_{g x} P⁻¹).
    #[inline]
    pub fn regression_times_l(&self, w: &Weights) -> Matrix<M, NX> {
        (self.plus - self.minus) * (0.5 / w.spread)
    }
}

/// Pushes the points of (x, L) through `g`: the unscented transform's mean and deviations.
/// `angles` are the components of g's output averaged on the circle; `diff` forms the
/// deviations (wrapping those components).
#[inline]
pub fn sigma_cloud<const NX: usize, const M: usize>(
    w: &Weights,
    x: &Vector<NX>,
    l: &Matrix<NX, NX>,
    g: impl Fn(&Vector<NX>) -> Vector<M>,
    angles: &[usize],
    diff: impl Fn(&Vector<M>, &Vector<M>) -> Vector<M>,
) -> Cloud<M, NX> {
    let mut plus = Matrix::<M, NX>::zeros();
    let mut minus = Matrix::<M, NX>::zeros();
    for j in 0..NX {
        let d = l.column(j) * w.spread;
        plus.set_column(j, &g(&(x + d)));
        minus.set_column(j, &g(&(x - d)));
    }
    let y0 = w.centre.map(|_| g(x));
    let mut mean = (plus + minus).column_sum() * w.pair;
    if let (Some(y0), Some((wm0, _))) = (&y0, w.centre) {
        mean += y0 * wm0;
    }
    for &i in angles {
        // Anchored at one point, so the mean keeps that point's branch; the centre point's
        // own term is sin 0 = 0, cos 0 = 1.
        let (anchor, mut s, mut c) = match (&y0, w.centre) {
            (Some(y0), Some((wm0, _))) => (y0[i], 0.0, wm0),
            _ => (plus[(i, 0)], 0.0, 0.0),
        };
        for j in 0..NX {
            let (sp, cp) = (plus[(i, j)] - anchor).sin_cos();
            let (sm, cm) = (minus[(i, j)] - anchor).sin_cos();
            s += w.pair * (sp + sm);
            c += w.pair * (cp + cm);
        }
        mean[i] = anchor + s.atan2(c);
    }
    for j in 0..NX {
        let p = diff(&plus.column(j).into_owned(), &mean);
        plus.set_column(j, &p);
        let m = diff(&minus.column(j).into_owned(), &mean);
        minus.set_column(j, &m);
    }
    let centre = y0.map_or_else(Vector::<M>::zeros, |y| diff(&y, &mean));
    Cloud {
        mean,
        plus,
        minus,
        centre,
    }
}

/// M L⁻¹ for a lower-triangular L: undoes the factor in [`Cloud::regression_times_l`].
fn times_l_inverse<const R: usize, const NX: usize>(
    m: &Matrix<R, NX>,
    l: &Matrix<NX, NX>,
) -> Option<Matrix<R, NX>> {
    Some(
        l.transpose()
            .solve_upper_triangular(&m.transpose())?
            .transpose(),
    )
}

/// The Cholesky factor of `p`, repairing (and counting) a failed factorisation.
fn factor<const NX: usize>(
    p: &mut Matrix<NX, NX>,
    repairs: &mut u32,
    which: &'static str,
) -> Result<Matrix<NX, NX>, FilterError> {
    if let Some(c) = SmallCholesky::new(p) {
        return Ok(c.l());
    }
    let c = repair_spd(p).ok_or(FilterError::NotPositiveDefinite { which })?;
    *repairs += 1;
    Ok(c.l())
}

impl<const NX: usize, const NU: usize, const NZ: usize, M: Model<NX, NU, NZ>> Filter<NX, NU, NZ, M>
    for SigmaPointKalman<NX, NZ>
{
    type Belief = SigmaBelief<NX, NZ>;

    fn init(
        &self,
        _model: &M,
        x0_hat: &Vector<NX>,
        p0: &Matrix<NX, NX>,
        _z0: &Measurement<NZ>,
    ) -> SigmaBelief<NX, NZ> {
        SigmaBelief::new(*x0_hat, *p0)
    }

    #[inline]
    fn predict(
        &self,
        model: &M,
        b: &mut SigmaBelief<NX, NZ>,
        u: &Vector<NU>,
    ) -> Result<(), FilterError> {
        let w = &self.weights;
        let l = factor(&mut b.p, &mut b.repairs, "state covariance P")?;
        let cloud = sigma_cloud(
            w,
            &b.x,
            &l,
            |s| model.propagate(s, u),
            model.angle_states(),
            |a, c| model.state_residual(a, c),
        );
        b.p = cloud.covariance(w) + self.q;
        b.f_l = cloud.regression_times_l(w);
        b.l_prev = l;
        b.gain = None;
        b.x = cloud.mean;
        check_finite(&b.x, &b.p)
    }

    #[inline]
    fn update(
        &self,
        model: &M,
        b: &mut SigmaBelief<NX, NZ>,
        u: &Vector<NU>,
        z: &Measurement<NZ>,
    ) -> Result<Option<Innovation<NZ>>, FilterError> {
        if z.available.count() == 0 {
            return Ok(None);
        }
        let w = &self.weights;
        let l = factor(&mut b.p, &mut b.repairs, "predicted covariance P⁻")?;
        let cloud = sigma_cloud(
            w,
            &b.x,
            &l,
            |s| model.measure(s, u),
            model.angle_measurements(),
            |a, c| model.residual(a, c),
        );
        let mut h_l = cloud.regression_times_l(w);
        let mut pzz = cloud.covariance(w);
        let mut nu = model.residual(&z.z, &cloud.mean);
        // Zero rows of H̃ L⁻ zero the same rows of P_xzᵀ; the spread loses the same rows and
        // columns, as H P Hᵀ would.
        let r = mask_rows(&self.r, z.available, &mut h_l, &mut nu);
        if z.available != Availability::all(NZ) {
            for i in (0..NZ).filter(|&i| !z.available.has(i)) {
                pzz.row_mut(i).fill(0.0);
                pzz.column_mut(i).fill(0.0);
            }
        }
        // P_xzᵀ = Σ w_c e_i (χ_i − x̂⁻)ᵀ = (H̃ L⁻) L⁻ᵀ, since χ_{j±} − x̂⁻ = ±c L⁻ e_j.
        let pxz_t = h_l * l.transpose();
        let s = pzz + r;
        let chol = SmallCholesky::new(&s).ok_or(FilterError::NotPositiveDefinite {
            which: "innovation covariance S",
        })?;
        let k = chol.solve(&pxz_t).transpose();
        let whitened = chol.solve_lower(&nu);
        b.x += k * nu;
        // K S Kᵀ = K P_xzᵀ.
        b.p = symmetrize(&(b.p - k * pxz_t));
        b.gain = Some((k, h_l, l));
        check_finite(&b.x, &b.p)?;
        Ok(Some(
            Innovation::new(nu, whitened, z.available).with_covariance(s),
        ))
    }

    fn mean(&self, b: &SigmaBelief<NX, NZ>) -> Vector<NX> {
        b.x
    }

    fn covariance(&self, b: &SigmaBelief<NX, NZ>) -> Option<Matrix<NX, NX>> {
        Some(b.p)
    }

    fn covariance_ref<'b>(&self, b: &'b SigmaBelief<NX, NZ>) -> Option<&'b Matrix<NX, NX>> {
        Some(&b.p)
    }

    fn error_transition(&self, b: &SigmaBelief<NX, NZ>) -> Option<Matrix<NX, NX>> {
        let f = times_l_inverse(&b.f_l, &b.l_prev)?;
        let Some((k, h_l, l)) = &b.gain else {
            return Some(f);
        };
        let h = times_l_inverse(h_l, l)?;
        Some((Matrix::<NX, NX>::identity() - k * h) * f)
    }

    fn repair_covariance(&self, b: &mut SigmaBelief<NX, NZ>) -> bool {
        repair_spd(&mut b.p).is_some()
    }

    fn internal_repairs(&self, b: &SigmaBelief<NX, NZ>) -> u32 {
        b.repairs
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::wrap_angle;
    use crate::systems::planar::model::{PlanarP1, PlanarParams};

    const UKF_TEXTBOOK: SigmaPoints = SigmaPoints::Unscented {
        alpha: 1e-3,
        beta: 2.0,
        kappa: 0.0,
    };

    fn plain<const M: usize>(a: &Vector<M>, b: &Vector<M>) -> Vector<M> {
        a - b
    }

    #[test]
    fn weights_sum_to_one_and_match_the_formulas() {
        for pts in [
            SigmaPoints::DEFAULT_UNSCENTED,
            UKF_TEXTBOOK,
            SigmaPoints::Unscented {
                alpha: 0.5,
                beta: 0.0,
                kappa: -3.0,
            },
            SigmaPoints::Cubature,
        ] {
            let w = pts.weights(6).unwrap();
            let (wm0, _) = w.centre.unwrap_or((0.0, 0.0));
            assert!((wm0 + 12.0 * w.pair - 1.0).abs() < 1e-9, "{pts:?}");
            assert!((w.pair * 2.0 * w.spread * w.spread - 1.0).abs() < 1e-15);
        }
        // α = 1, κ = 0: points at ±√6 σ, centre mean weight 0, covariance weight β = 2.
        let w = SigmaPoints::DEFAULT_UNSCENTED.weights(6).unwrap();
        assert_eq!(w.centre, Some((0.0, 2.0)));
        assert_eq!(w.spread, 6f64.sqrt());
        // The textbook α = 10⁻³ has a centre weight of about −10⁶ (n = 6).
        let (wm0, _) = UKF_TEXTBOOK.weights(6).unwrap().centre.unwrap();
        assert!((wm0 + 999_999.0).abs() < 1.0, "{wm0}");
    }

    #[test]
    fn unusable_parameters_are_refused() {
        let ukf = |alpha, beta, kappa| SigmaPoints::Unscented { alpha, beta, kappa }.weights(6);
        assert_eq!(ukf(0.0, 2.0, 0.0), Err(SigmaPointError::Alpha(0.0)));
        assert!(matches!(
            ukf(f64::NAN, 2.0, 0.0),
            Err(SigmaPointError::Alpha(_))
        ));
        assert_eq!(ukf(1.5, 2.0, 0.0), Err(SigmaPointError::Alpha(1.5)));
        assert_eq!(ukf(1.0, -1.0, 0.0), Err(SigmaPointError::Beta(-1.0)));
        assert_eq!(
            ukf(1.0, 2.0, f64::INFINITY),
            Err(SigmaPointError::Kappa(f64::INFINITY))
        );
        assert_eq!(
            ukf(1.0, 2.0, -6.0),
            Err(SigmaPointError::Spread { n: 6, kappa: -6.0 })
        );
        assert_eq!(ukf(1.0, 2.0, -6.0).unwrap_err().key(), "kappa");
        // A denormal α squares to 0: the fault is α's, whatever κ is.
        assert_eq!(
            ukf(5e-324, 2.0, 0.0),
            Err(SigmaPointError::AlphaUnderflow(5e-324))
        );
        assert_eq!(ukf(5e-324, 2.0, 0.0).unwrap_err().key(), "alpha");
        assert!(ukf(1.0, 2.0, -5.9).is_ok());
    }

    #[test]
    fn linear_maps_are_reproduced_exactly() {
        // y = A x + b: mean A x̂ + b and covariance A P Aᵀ for every rule.
        let a = Matrix::<2, 3>::new(1.0, -2.0, 0.5, 0.3, 0.0, 4.0);
        let bvec = Vector::<2>::new(0.7, -1.1);
        let x = Vector::<3>::new(0.2, -0.4, 1.5);
        let p = Matrix::<3, 3>::new(2.0, 0.3, -0.1, 0.3, 1.0, 0.2, -0.1, 0.2, 0.5);
        let l = SmallCholesky::new(&p).unwrap().l();
        for (pts, tol) in [
            (SigmaPoints::DEFAULT_UNSCENTED, 1e-13),
            (SigmaPoints::Cubature, 1e-13),
            // The −10⁶ centre weight cancels six digits.
            (UKF_TEXTBOOK, 1e-8),
        ] {
            let w = pts.weights(3).unwrap();
            let c = sigma_cloud(&w, &x, &l, |s| a * s + bvec, &[], plain);
            assert!((c.mean - (a * x + bvec)).amax() < tol, "{pts:?}");
            assert!(
                (c.covariance(&w) - a * p * a.transpose()).amax() < tol,
                "{pts:?}"
            );
            // The regression of y on x is A itself.
            let g = times_l_inverse(&c.regression_times_l(&w), &l).unwrap();
            assert!((g - a).amax() < 1e-6_f64.max(tol), "{pts:?}");
        }
    }

    #[test]
    fn the_square_of_a_gaussian_has_the_moments_each_rule_promises() {
        // x ~ N(μ, σ²), y = x²: E y = μ² + σ², Var y = 4μ²σ² + 2σ⁴. Both rules get the mean;
        // the unscented points with κ = 3 − n, β = 0 also match the fourth moment, while the
        // third-degree cubature rule misses the 2σ⁴ term.
        let (mu, sigma) = (1.3, 0.4);
        let x = Vector::<1>::new(mu);
        let l = Matrix::<1, 1>::new(sigma);
        let sq = |s: &Vector<1>| Vector::<1>::new(s[0] * s[0]);
        let (s2, m2) = (sigma * sigma, mu * mu);
        let ukf = SigmaPoints::Unscented {
            alpha: 1.0,
            beta: 0.0,
            kappa: 2.0,
        }
        .weights(1)
        .unwrap();
        let c = sigma_cloud(&ukf, &x, &l, sq, &[], plain);
        assert!((c.mean[0] - (m2 + s2)).abs() < 1e-14);
        assert!((c.covariance(&ukf)[(0, 0)] - (4.0 * m2 * s2 + 2.0 * s2 * s2)).abs() < 1e-14);
        let ckf = SigmaPoints::Cubature.weights(1).unwrap();
        let c = sigma_cloud(&ckf, &x, &l, sq, &[], plain);
        assert!((c.mean[0] - (m2 + s2)).abs() < 1e-14);
        assert!((c.covariance(&ckf)[(0, 0)] - 4.0 * m2 * s2).abs() < 1e-14);
    }

    #[test]
    fn an_angle_cloud_straddling_pi_has_its_circular_mean() {
        // θ ~ N(π − 0.01, 0.2²) pushed through a map that reports θ on [−π, π): half the
        // points land near −π. The circular mean is the centre (mod 2π) and the spread is
        // σ²; an arithmetic mean would land near 0.
        let theta = std::f64::consts::PI - 0.01;
        let x = Vector::<1>::new(theta);
        let l = Matrix::<1, 1>::new(0.2);
        let wrapped = |s: &Vector<1>| Vector::<1>::new(wrap_angle(s[0]));
        let wdiff = |a: &Vector<1>, b: &Vector<1>| Vector::<1>::new(wrap_angle(a[0] - b[0]));
        for pts in [SigmaPoints::DEFAULT_UNSCENTED, SigmaPoints::Cubature] {
            let w = pts.weights(1).unwrap();
            let c = sigma_cloud(&w, &x, &l, wrapped, &[0], wdiff);
            assert!(
                wrap_angle(c.mean[0] - theta).abs() < 1e-12,
                "{pts:?}: {}",
                c.mean[0]
            );
            assert!((c.covariance(&w)[(0, 0)] - 0.04).abs() < 1e-12, "{pts:?}");
            let arithmetic = sigma_cloud(&w, &x, &l, wrapped, &[], plain);
            assert!(
                wrap_angle(arithmetic.mean[0] - theta).abs() > 1.0,
                "{pts:?}"
            );
        }
    }

    fn setup(points: SigmaPoints) -> (PlanarP1, SigmaPointKalman<6, 3>, SigmaBelief<6, 3>) {
        let model = PlanarP1::new(PlanarParams::default());
        let f = SigmaPointKalman::new(
            Matrix::<6, 6>::identity() * 0.003f64.powi(2),
            Matrix::<3, 3>::identity() * 0.01f64.powi(2),
            points,
        )
        .unwrap();
        let b = SigmaBelief::new(
            Vector::<6>::new(0.0, 3.0, 10.0, 0.0, -1.5, 0.1),
            Matrix::<6, 6>::identity(),
        );
        (model, f, b)
    }

    #[test]
    fn masked_update_equals_update_on_the_reporting_rows() {
        // P1's h is linear, so with only θ̇ reporting the update is a scalar KF update with
        // H = e_6ᵀ, for both rules.
        for pts in [SigmaPoints::DEFAULT_UNSCENTED, SigmaPoints::Cubature] {
            let (model, f, mut b) = setup(pts);
            let z = Measurement {
                z: Vector::<3>::new(99.0, 99.0, 0.25),
                available: Availability(0b100),
            };
            let (p, x) = (b.p, b.x);
            let u = Vector::<2>::zeros();
            let inn = Filter::<6, 2, 3, _>::update(&f, &model, &mut b, &u, &z)
                .unwrap()
                .unwrap();
            let s = p[(5, 5)] + 1e-4;
            let k = p.column(5) / s;
            let nu = 0.25 - x[5];
            assert!((b.x - (x + k * nu)).amax() < 1e-14, "{pts:?}");
            assert!(
                (b.p - (p - k * k.transpose() * s)).amax() < 1e-14,
                "{pts:?}"
            );
            assert!((inn.nis - nu * nu / s).abs() < 1e-12);
            assert_eq!(inn.dof, 1);
            assert_eq!(inn.residual[0], 0.0);
        }
    }

    #[test]
    fn the_statistical_linearisation_tends_to_the_jacobian() {
        // For a small prior spread F̃ → ∂f/∂x and A → (I − K H) F.
        let (model, f, mut b) = setup(SigmaPoints::DEFAULT_UNSCENTED);
        b.p = Matrix::<6, 6>::identity() * 1e-10;
        let u = Vector::<2>::new(4.05, 4.0);
        let x = b.x;
        Filter::<6, 2, 3, _>::predict(&f, &model, &mut b, &u).unwrap();
        let a = Filter::<6, 2, 3, PlanarP1>::error_transition(&f, &b).unwrap();
        let jac = model.transition_jacobian(&x, &u);
        assert!((a - jac).amax() < 1e-6, "{}", (a - jac).amax());
        // f is nonlinear in θ: with σ_θ = 1 rad the regression is not the Jacobian.
        let (model, f, mut b) = setup(SigmaPoints::DEFAULT_UNSCENTED);
        Filter::<6, 2, 3, _>::predict(&f, &model, &mut b, &u).unwrap();
        let a = Filter::<6, 2, 3, PlanarP1>::error_transition(&f, &b).unwrap();
        assert!((a - jac).amax() > 1e-3);
        // After an update A = (I − K H) F̃ with the linear H of P1.
        let z = Measurement {
            z: Vector::<3>::new(10.0, -1.5, 0.1),
            available: Availability::all(3),
        };
        let f_tilde = a;
        let p_prior = b.p;
        Filter::<6, 2, 3, _>::update(&f, &model, &mut b, &u, &z).unwrap();
        let h = model.measurement_jacobian(&b.x, &u);
        let s = h * p_prior * h.transpose() + f.r;
        let k = p_prior * h.transpose() * s.try_inverse().unwrap();
        let expected = (Matrix::<6, 6>::identity() - k * h) * f_tilde;
        let a = Filter::<6, 2, 3, PlanarP1>::error_transition(&f, &b).unwrap();
        assert!((a - expected).amax() < 1e-9, "{}", (a - expected).amax());
    }

    #[test]
    fn a_covariance_that_cannot_be_factored_is_repaired_and_counted() {
        let (model, f, mut b) = setup(SigmaPoints::Cubature);
        b.p[(0, 1)] = 1.0 + 1e-15;
        b.p[(1, 0)] = 1.0;
        assert!(SmallCholesky::new(&b.p).is_none());
        let u = Vector::<2>::new(4.0, 4.0);
        Filter::<6, 2, 3, _>::predict(&f, &model, &mut b, &u).unwrap();
        assert_eq!(Filter::<6, 2, 3, PlanarP1>::internal_repairs(&f, &b), 1);
        // A NaN covariance cannot be repaired: the step fails with its reason.
        b.p[(2, 2)] = f64::NAN;
        let e = Filter::<6, 2, 3, _>::predict(&f, &model, &mut b, &u).unwrap_err();
        assert_eq!(
            e,
            FilterError::NotPositiveDefinite {
                which: "state covariance P"
            }
        );
    }
}
