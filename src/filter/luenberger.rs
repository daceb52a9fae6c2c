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
//! The algorithm is in the submodule `placement`; this module is the observer.
//!
//! The observer carries no covariance: [`Filter::covariance`] is `None` and NEES/NIS are
//! reported as null, like the running mean.

mod placement;

use super::{Filter, FilterError, Innovation};
use crate::linalg::{Matrix, Vector};
use crate::model::{Measurement, Model};

pub use placement::{ObserverPlacement, PlacementError, place_observer, place_observer_poles};

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
