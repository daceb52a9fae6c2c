//! Extended Kalman filter, as in `simulation_quadrotor.m` (seed 000, lines 105–149).
//!
//! Predict: x̂⁻ = f(x̂, u_k), P⁻ = F P Fᵀ + Q with F = ∂f/∂x at the previous estimate.
//! Update:  ν = z − h(x̂⁻, u_k) (angle components wrapped by the model), S = H P⁻ Hᵀ + R,
//! K = P⁻ Hᵀ S⁻¹, x̂ = x̂⁻ + K ν, and P = (I − K H) P⁻ (the seeds' form, computed as
//! P⁻ − K (H P⁻)) or the Joseph form (I − K H) P⁻ (I − K H)ᵀ + K R Kᵀ. F P Fᵀ + Q and
//! P⁻ − K (H P⁻) are formed on their lower triangle and mirrored, and the Joseph product's
//! upper triangle is replaced by the mirror of its lower one, so P is exactly symmetric after
//! every step (the products' two triangles would differ in their last bits, and the
//! difference would grow over a run).
//!
//! Requirements on the model: f, h and both Jacobians ([`Model`]).
//!
//! Components that did not report at a step are removed exactly: their rows of H and ν are
//! zeroed and their block of R replaced by the identity, which makes S block-diagonal and the
//! corresponding columns of K zero, so the update equals one over the reporting rows alone.
//!
//! # Reference
//! Welch & Bishop, *An Introduction to the Kalman Filter*, TR 95-041 (2002) — the seeds' source.

use super::{Filter, FilterError, Innovation};
use crate::linalg::{
    Matrix, SmallCholesky, Vector, mirror_lower, select_i_kh, select_rows, sparse_sandwich,
    subtract_product,
};
use crate::model::{Measurement, Model};

/// How the covariance is updated after a measurement.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CovarianceUpdate {
    /// P = (I − K H) P⁻, as the seeds do (computed as P⁻ − K (H P⁻)).
    Standard,
    /// Joseph form; symmetric and PSD by construction, valid for any gain.
    Joseph,
}

/// EKF configuration: the Q and R it *assumes* (which need not be the truth's).
#[derive(Clone, Debug, PartialEq)]
pub struct Ekf<const NX: usize, const NZ: usize> {
    /// Assumed process-noise covariance Q.
    pub q: Matrix<NX, NX>,
    /// Assumed measurement-noise covariance R.
    pub r: Matrix<NZ, NZ>,
    /// Covariance update form.
    pub update_form: CovarianceUpdate,
}

/// The EKF's belief: mean and covariance, plus the last step's F and what forms its I − KH
/// (kept so the error transition A_k can be formed on demand without costing every step a
/// product; a step without an update has I − KH = I, which is not written out).
#[derive(Clone, Debug, PartialEq)]
pub struct Gaussian<const NX: usize> {
    /// x̂
    pub x: Vector<NX>,
    /// P
    pub p: Matrix<NX, NX>,
    f: Matrix<NX, NX>,
    /// I − KH ([`Gain::Formed`]), or K in the first NZ columns ([`Gain::Selected`]).
    i_kh: Matrix<NX, NX>,
    gain: Gain<NX>,
}

/// How a belief holds the last step's I − K H.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Gain<const NX: usize> {
    /// A prediction alone: I − K H = I.
    None,
    /// `i_kh` is I − K H.
    Formed,
    /// `i_kh`'s first NZ columns are K and `sel[..NZ]` is H's row selection. I − K H is
    /// formed only when the error transition is asked for (the consistency tests, exports):
    /// most studies never need it, and forming it costs a dense NX×NX product per step.
    Selected { sel: [usize; NX] },
}

impl<const NX: usize> Gaussian<NX> {
    /// A belief with mean `x` and covariance `p`'s lower triangle, mirrored.
    pub fn new(x: Vector<NX>, mut p: Matrix<NX, NX>) -> Self {
        // Every step keeps P exactly symmetric, and the declared-structure path reads P's
        // columns for its rows (as the NEES factor reads the lower triangle), so a P whose
        // triangles differ in their last bits would otherwise make it part from the dense path.
        mirror_lower(&mut p);
        Gaussian {
            x,
            p,
            f: Matrix::<NX, NX>::identity(),
            i_kh: Matrix::<NX, NX>::identity(),
            gain: Gain::None,
        }
    }
}

/// A NaN or ±∞ anywhere in x̂ or on P's diagonal makes the sum non-finite; an off-diagonal
/// one reaches the diagonal at the next product. One sum per step instead of 42 tests.
#[inline]
fn check_finite<const NX: usize>(b: &Gaussian<NX>) -> Result<(), FilterError> {
    if !b.x.sum().is_finite() {
        return Err(FilterError::NonFinite {
            what: "state estimate",
        });
    }
    if !b.p.trace().is_finite() {
        return Err(FilterError::NonFinite {
            what: "state covariance",
        });
    }
    Ok(())
}

/// What a measurement update computes from P⁻ alone (with H and R): S, its factor, the gain K
/// and what the covariance update reads. For a linear model it does not depend on the
/// estimate, so a group of runs with one P can share it ([`Ekf::gain`]).
#[derive(Clone, Debug)]
pub struct UpdateGain<const NX: usize, const NZ: usize> {
    /// K = P⁻ Hᵀ S⁻¹.
    pub k: Matrix<NX, NZ>,
    /// The factor of S.
    pub chol: SmallCholesky<NZ>,
    /// S = H P⁻ Hᵀ + R (masked rows and columns the identity).
    pub s: Matrix<NZ, NZ>,
    hp: Matrix<NZ, NX>,
    selection: Option<[usize; NZ]>,
    /// H and the masked R when the dense path is taken.
    dense: Option<(Matrix<NZ, NX>, Matrix<NZ, NZ>)>,
}

impl<const NX: usize, const NZ: usize> UpdateGain<NX, NZ> {
    /// Zeroes the components of ν that did not report, as the update does before forming
    /// K ν (the dense path masks ν with H and R; the selection path has every component).
    #[inline]
    pub fn mask_residual(&self, available: crate::model::Availability, nu: &mut Vector<NZ>) {
        if self.dense.is_some() && available != crate::model::Availability::all(NZ) {
            for i in 0..NZ {
                if !available.has(i) {
                    nu[i] = 0.0;
                }
            }
        }
    }
}

impl<const NX: usize, const NZ: usize> Ekf<NX, NZ> {
    /// S, its factor and K at the belief's P⁻ for a measurement over `available` (H at the
    /// belief's estimate), masking ν's missing components as it goes; the error when S is
    /// not positive definite.
    #[inline]
    pub fn gain<const NU: usize, M: Model<NX, NU, NZ>>(
        &self,
        model: &M,
        b: &Gaussian<NX>,
        u: &Vector<NU>,
        available: crate::model::Availability,
        nu: &mut Vector<NZ>,
    ) -> Result<UpdateGain<NX, NZ>, FilterError> {
        // A selection H with every component reporting: H P⁻ is rows of P⁻ and (I − K H) P⁻
        // is formed over its non-zero entries, the dense results at a fraction of the cost.
        // Missing components (masked rows) take the dense path.
        let selection = model
            .measurement_selection()
            .filter(|_| available == crate::model::Availability::all(NZ));
        // `dense` holds H and the masked R when the dense path is taken.
        let (hp, s, dense) = match &selection {
            Some(sel) => {
                let hp = select_rows(sel, &b.p);
                let s = Matrix::<NZ, NZ>::from_fn(|i, j| hp[(i, sel[j])]) + self.r;
                (hp, s, None)
            }
            None => {
                let mut h = model.measurement_jacobian(&b.x, u);
                let r = super::mask_rows(&self.r, available, &mut h, nu);
                let hp = h * b.p;
                (hp, hp * h.transpose() + r, Some((h, r)))
            }
        };
        let chol = SmallCholesky::new(&s).ok_or(FilterError::NotPositiveDefinite {
            which: "innovation covariance S",
        })?;
        // Kᵀ = S⁻¹ H P⁻ because S and P⁻ are symmetric.
        let k = chol.solve(&hp).transpose();
        Ok(UpdateGain {
            k,
            chol,
            s,
            hp,
            selection,
            dense,
        })
    }

    /// The covariance half of an update with `gain` (formed at this belief's P⁻): P and what
    /// the error transition reads. The estimate is left alone.
    #[inline]
    pub fn update_covariance(&self, b: &mut Gaussian<NX>, gain: &UpdateGain<NX, NZ>) {
        let k = &gain.k;
        match (&gain.selection, &gain.dense) {
            // K fits in `i_kh` when NZ ≤ NX; Joseph's form reads I − K H at once.
            (Some(sel), _) if NZ <= NX && self.update_form == CovarianceUpdate::Standard => {
                for l in 0..NZ {
                    b.i_kh.column_mut(l).copy_from(&k.column(l));
                }
                let mut padded = [0; NX];
                padded[..NZ].copy_from_slice(sel);
                b.gain = Gain::Selected { sel: padded };
            }
            (Some(sel), _) => {
                select_i_kh(k, sel, &mut b.i_kh);
                b.gain = Gain::Formed;
            }
            (None, Some((h, _))) => {
                b.i_kh = Matrix::<NX, NX>::identity() - k * h;
                b.gain = Gain::Formed;
            }
            (None, None) => unreachable!("the dense path keeps its H"),
        }
        match self.update_form {
            // (I − K H) P⁻ as P⁻ − K (H P⁻): H P⁻ is at hand (the selected rows, or the dense
            // product), so the update is one NX×NZ by NZ×NX product instead of an NX×NX one,
            // and the selection and dense paths give the same bits.
            CovarianceUpdate::Standard => subtract_product(&mut b.p, k, &gain.hp),
            CovarianceUpdate::Joseph => {
                let r = gain.dense.as_ref().map_or(self.r, |(_, r)| *r);
                b.p = b.i_kh * b.p * b.i_kh.transpose() + k * r * k.transpose();
                mirror_lower(&mut b.p);
            }
        }
    }
}

impl<const NX: usize, const NU: usize, const NZ: usize, M: Model<NX, NU, NZ>> Filter<NX, NU, NZ, M>
    for Ekf<NX, NZ>
{
    type Belief = Gaussian<NX>;

    fn init(
        &self,
        _model: &M,
        x0_hat: &Vector<NX>,
        p0: &Matrix<NX, NX>,
        _z0: &Measurement<NZ>,
    ) -> Gaussian<NX> {
        Gaussian::new(*x0_hat, *p0)
    }

    #[inline]
    fn predict(&self, model: &M, b: &mut Gaussian<NX>, u: &Vector<NU>) -> Result<(), FilterError> {
        b.f = model.transition_jacobian(&b.x, u);
        b.x = model.propagate(&b.x, u);
        match model.transition_pattern() {
            Some(pattern) => sparse_sandwich(&b.f, pattern, &mut b.p, &self.q),
            // The declared pattern's result, bit for bit: the same lower triangle, mirrored.
            None => {
                b.p = b.f * b.p * b.f.transpose() + self.q;
                mirror_lower(&mut b.p);
            }
        }
        b.gain = Gain::None;
        check_finite(b)
    }

    #[inline]
    fn update(
        &self,
        model: &M,
        b: &mut Gaussian<NX>,
        u: &Vector<NU>,
        z: &Measurement<NZ>,
    ) -> Result<Option<Innovation<NZ>>, FilterError> {
        if z.available.count() == 0 {
            return Ok(None);
        }
        let mut nu = model.residual(&z.z, &model.measure(&b.x, u));
        let gain = self.gain(model, b, u, z.available, &mut nu)?;
        let whitened = gain.chol.solve_lower(&nu);
        b.x += gain.k * nu;
        self.update_covariance(b, &gain);
        check_finite(b)?;
        Ok(Some(
            Innovation::new(nu, whitened, z.available).with_covariance(gain.s),
        ))
    }

    fn mean(&self, b: &Gaussian<NX>) -> Vector<NX> {
        b.x
    }

    fn covariance(&self, b: &Gaussian<NX>) -> Option<Matrix<NX, NX>> {
        Some(b.p)
    }

    fn covariance_ref<'b>(&self, b: &'b Gaussian<NX>) -> Option<&'b Matrix<NX, NX>> {
        Some(&b.p)
    }

    fn error_transition(&self, b: &Gaussian<NX>) -> Option<Matrix<NX, NX>> {
        Some(match b.gain {
            Gain::None => b.f,
            Gain::Formed => b.i_kh * b.f,
            Gain::Selected { sel } => {
                // The I − K H the update would have written: the same function on the same K.
                let k = Matrix::<NX, NZ>::from_fn(|i, l| b.i_kh[(i, l)]);
                let sel: [usize; NZ] = std::array::from_fn(|l| sel[l]);
                let mut i_kh = Matrix::<NX, NX>::identity();
                select_i_kh(&k, &sel, &mut i_kh);
                i_kh * b.f
            }
        })
    }

    fn repair_covariance(&self, b: &mut Gaussian<NX>) -> bool {
        super::repair_spd(&mut b.p).is_some()
    }

    fn as_kalman(&self) -> Option<&Ekf<NX, NZ>> {
        Some(self)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::linalg::symmetrize;
    use crate::model::Availability;
    use crate::systems::planar::model::{PlanarP1, PlanarParams};

    fn setup() -> (PlanarP1, Ekf<6, 3>, Gaussian<6>) {
        let model = PlanarP1::new(PlanarParams::default());
        let ekf = Ekf {
            q: Matrix::<6, 6>::identity() * 0.003f64.powi(2),
            r: Matrix::<3, 3>::identity() * 0.01f64.powi(2),
            update_form: CovarianceUpdate::Standard,
        };
        let b = Gaussian::new(
            Vector::<6>::new(0.0, 3.0, 10.0, 0.0, -1.5, 0.1),
            Matrix::<6, 6>::identity(),
        );
        (model, ekf, b)
    }

    #[test]
    fn joseph_equals_standard_at_the_optimal_gain() {
        let (model, ekf, b0) = setup();
        let u = Vector::<2>::new(4.05, 4.0);
        let z = Measurement {
            z: Vector::<3>::new(10.02, -1.49, 0.11),
            available: Availability::all(3),
        };
        let mut a = b0.clone();
        let mut b = b0;
        let joseph = Ekf {
            update_form: CovarianceUpdate::Joseph,
            ..ekf.clone()
        };
        Filter::<6, 2, 3, _>::predict(&ekf, &model, &mut a, &u).unwrap();
        Filter::<6, 2, 3, _>::predict(&joseph, &model, &mut b, &u).unwrap();
        Filter::<6, 2, 3, _>::update(&ekf, &model, &mut a, &u, &z).unwrap();
        Filter::<6, 2, 3, _>::update(&joseph, &model, &mut b, &u, &z).unwrap();
        assert!((a.x - b.x).amax() < 1e-15);
        assert!((a.p - b.p).amax() < 1e-12);
        assert!(SmallCholesky::new(&symmetrize(&b.p)).is_some());
    }

    #[test]
    fn masked_update_equals_update_on_the_reporting_rows() {
        // Only θ̇ reports: the result must equal a scalar KF update with H = e_6ᵀ.
        let (model, ekf, mut b) = setup();
        let z = Measurement {
            z: Vector::<3>::new(99.0, 99.0, 0.25),
            available: Availability(0b100),
        };
        let p = b.p;
        let x = b.x;
        let u = Vector::<2>::zeros();
        let inn = Filter::<6, 2, 3, _>::update(&ekf, &model, &mut b, &u, &z)
            .unwrap()
            .unwrap();
        let s = p[(5, 5)] + 1e-4;
        let k = p.column(5) / s;
        let nu = 0.25 - x[5];
        assert!((b.x - (x + k * nu)).amax() < 1e-14);
        assert!((inn.nis - nu * nu / s).abs() < 1e-12);
        assert_eq!(inn.dof, 1);
    }

    #[test]
    fn repair_makes_an_indefinite_covariance_factorable() {
        let (_, ekf, mut b) = setup();
        b.p[(0, 1)] = 1.0 + 1e-15;
        b.p[(1, 0)] = 1.0;
        assert!(SmallCholesky::new(&b.p).is_none());
        assert!(Filter::<6, 2, 3, PlanarP1>::repair_covariance(&ekf, &mut b));
        assert!(SmallCholesky::new(&b.p).is_some());
    }
}
