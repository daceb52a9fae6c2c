//! The linear-Gaussian model of a `kind = "linear"` spec:
//!
//! x_k = F x_{k−1} + G u_k + w_k, w_k ~ N(0, Q),  z_k = H x_k + v_k, v_k ~ N(0, R),
//!
//! with components that report on a schedule of their own (multi-rate sensor groups).

use std::any::Any;

use crate::linalg::{Matrix, Vector};
use crate::model::{Availability, LinearMatrices, Model};

/// A measurement group that reports every `period` steps (k ≡ 0 mod period, z_0 included).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SensorGroup {
    /// The group's components (bit i ⇔ component i).
    pub components: Availability,
    /// Reporting period in steps (≥ 1).
    pub period: usize,
}

/// A discrete linear-Gaussian model with `NX` states, `NU` inputs and `NZ` measurement
/// components.
#[derive(Clone, Debug, PartialEq)]
pub struct LinearModel<const NX: usize, const NU: usize, const NZ: usize> {
    dt_s: f64,
    f: Matrix<NX, NX>,
    g: Matrix<NX, NU>,
    h: Matrix<NZ, NX>,
    q: Matrix<NX, NX>,
    /// Whether Q is the model's own full covariance ([`Model::process_noise_covariance`]).
    full_q: bool,
    /// Components in no group: they report at every step.
    every_step: Availability,
    groups: Vec<SensorGroup>,
    /// Why the model has no steady state, or `None` when (F, H) is detectable.
    undetectable: Option<String>,
    /// F's non-zero entries, for [`Model::transition_pattern`].
    pattern: Vec<(usize, usize)>,
    /// H as a selection of states, when it is one ([`Model::measurement_selection`]).
    selection: Option<[usize; NZ]>,
}

impl<const NX: usize, const NU: usize, const NZ: usize> LinearModel<NX, NU, NZ> {
    /// The model x_k = F x_{k−1} + G u_k + w_k, z_k = H x_k + v_k at sample time `dt_s`.
    ///
    /// With `full_q`, Q is returned by [`Model::process_noise_covariance`]: the truth samples
    /// it through its Cholesky factor (so it must be positive definite) and filters assume it.
    /// Without, the truth and the filters use per-state standard deviations (exact when Q is
    /// diagonal). `groups` are the multi-rate sensor groups; every other component reports at
    /// every step.
    pub fn new(
        dt_s: f64,
        f: Matrix<NX, NX>,
        g: Matrix<NX, NU>,
        h: Matrix<NZ, NX>,
        q: Matrix<NX, NX>,
        full_q: bool,
        groups: Vec<SensorGroup>,
    ) -> Self {
        let grouped = groups.iter().fold(0, |m, g| m | g.components.0);
        LinearModel {
            dt_s,
            f,
            g,
            h,
            q,
            full_q,
            every_step: Availability(Availability::all(NZ).0 & !grouped),
            groups,
            undetectable: undetectable_reason(&f, &h),
            pattern: crate::linalg::nonzero_pattern(&f),
            selection: crate::linalg::row_selection(&h),
        }
    }

    /// F.
    pub fn f(&self) -> &Matrix<NX, NX> {
        &self.f
    }
    /// G.
    pub fn g(&self) -> &Matrix<NX, NU> {
        &self.g
    }
    /// H.
    pub fn h(&self) -> &Matrix<NZ, NX> {
        &self.h
    }
    /// Q (the full covariance, or the diagonal the per-state standard deviations square to).
    pub fn q(&self) -> &Matrix<NX, NX> {
        &self.q
    }
    /// The multi-rate sensor groups.
    pub fn groups(&self) -> &[SensorGroup] {
        &self.groups
    }
    /// Why (F, H) is not detectable, or `None` when it is.
    pub fn undetectable(&self) -> Option<&str> {
        self.undetectable.as_deref()
    }
}

/// The `detectable` check [`crate::system::additive::linear_kinds`] is given: the steady
/// state (and the pole placement) need every mode that H never sees to decay.
pub fn detectable<const NX: usize, const NU: usize, const NZ: usize>(
    model: &dyn Any,
) -> Option<String> {
    match model.downcast_ref::<LinearModel<NX, NU, NZ>>() {
        Some(m) => m.undetectable.clone(),
        None => Some("steady_state needs a linear model".into()),
    }
}

/// Modes this close to the unit circle count as not decaying: a repeated eigenvalue (the
/// integrators of a constant-velocity model) is computed only to about √ε ≈ 1e-8.
const UNIT_CIRCLE_MARGIN: f64 = 1e-6;

pub(crate) use crate::analysis::unobservable_modes;

/// Why (F, H) is not detectable (an unobservable mode on or outside the unit circle), or
/// `None` when it is.
fn undetectable_reason<const NX: usize, const NZ: usize>(
    f: &Matrix<NX, NX>,
    h: &Matrix<NZ, NX>,
) -> Option<String> {
    let (rank, modes) = unobservable_modes(f, h);
    if rank == NX {
        return None;
    }
    if modes.is_empty() && rank < NX {
        return Some(format!(
            "steady_state needs a detectable (F, H); its unobservable modes could not be computed (observability rank {rank} of {NX})"
        ));
    }
    let bad: Vec<String> = modes
        .iter()
        .filter(|(re, im)| re.hypot(*im) >= 1.0 - UNIT_CIRCLE_MARGIN)
        .map(|&(re, im)| {
            if im.abs() > 1e-12 {
                format!("{re:.4}{im:+.4}i")
            } else {
                format!("{re:.4}")
            }
        })
        .collect();
    (!bad.is_empty()).then(|| {
        format!(
            "steady_state needs a detectable (F, H): the observability rank is {rank} of {NX} and the unobservable mode(s) {} of F do not decay (|λ| ≥ 1), so the Riccati equation has no steady state",
            bad.join(", ")
        )
    })
}

impl<const NX: usize, const NU: usize, const NZ: usize> Model<NX, NU, NZ>
    for LinearModel<NX, NU, NZ>
{
    fn dt_s(&self) -> f64 {
        self.dt_s
    }

    #[inline]
    fn propagate(&self, x: &Vector<NX>, u: &Vector<NU>) -> Vector<NX> {
        self.f * x + self.g * u
    }

    #[inline]
    fn transition_jacobian(&self, _x: &Vector<NX>, _u: &Vector<NU>) -> Matrix<NX, NX> {
        self.f
    }

    #[inline]
    fn measure(&self, x: &Vector<NX>, _u: &Vector<NU>) -> Vector<NZ> {
        self.h * x
    }

    #[inline]
    fn measurement_jacobian(&self, _x: &Vector<NX>, _u: &Vector<NU>) -> Matrix<NZ, NX> {
        self.h
    }

    fn transition_pattern(&self) -> Option<&[(usize, usize)]> {
        Some(&self.pattern)
    }

    fn measurement_selection(&self) -> Option<[usize; NZ]> {
        self.selection
    }

    #[inline]
    fn availability(&self, step: usize) -> Availability {
        let mut mask = self.every_step.0;
        for g in &self.groups {
            if step.is_multiple_of(g.period) {
                mask |= g.components.0;
            }
        }
        Availability(mask)
    }

    fn process_noise_covariance(&self) -> Option<Matrix<NX, NX>> {
        self.full_q.then_some(self.q)
    }

    fn linear(&self) -> Option<LinearMatrices<NX, NU, NZ>> {
        Some(LinearMatrices {
            f: self.f,
            g: self.g,
            h: self.h,
        })
    }

    fn measurement_uses_input(&self) -> bool {
        false
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cv(dt: f64) -> (Matrix<4, 4>, Matrix<2, 4>) {
        #[rustfmt::skip]
        let f = Matrix::<4, 4>::from_row_slice(&[
            1.0, dt, 0.0, 0.0,
            0.0, 1.0, 0.0, 0.0,
            0.0, 0.0, 1.0, dt,
            0.0, 0.0, 0.0, 1.0,
        ]);
        let mut h = Matrix::<2, 4>::zeros();
        h[(0, 0)] = 1.0;
        h[(1, 2)] = 1.0;
        (f, h)
    }

    #[test]
    fn detectability_sees_unobserved_integrators_and_forgives_stable_modes() {
        let (f, h) = cv(0.1);
        assert_eq!(undetectable_reason(&f, &h), None);
        // Velocities only: the positions are unobservable integrators (λ = 1, twice).
        let mut hv = Matrix::<2, 4>::zeros();
        hv[(0, 1)] = 1.0;
        hv[(1, 3)] = 1.0;
        let (rank, modes) = unobservable_modes(&f, &hv);
        assert_eq!(rank, 2);
        assert!(
            modes
                .iter()
                .all(|m| (m.0 - 1.0).abs() < 1e-8 && m.1.abs() < 1e-8)
        );
        let msg = undetectable_reason(&f, &hv).expect("not detectable");
        assert!(
            msg.contains("rank is 2 of 4") && msg.contains("1.0000"),
            "{msg}"
        );
        // x alone: the whole y axis (a Jordan block at 1) is unobserved.
        let hx = Matrix::<1, 4>::new(1.0, 0.0, 0.0, 0.0);
        assert_eq!(unobservable_modes(&f, &hx).0, 2);
        assert!(undetectable_reason(&f, &hx).is_some());
        // An unobserved but decaying mode is detectable.
        let f2 = Matrix::<2, 2>::new(1.0, 0.0, 0.0, 0.5);
        let h2 = Matrix::<1, 2>::new(1.0, 0.0);
        let (rank, modes) = unobservable_modes(&f2, &h2);
        assert_eq!(rank, 1);
        assert!((modes[0].0 - 0.5).abs() < 1e-14);
        assert_eq!(undetectable_reason(&f2, &h2), None);
        // A rotation (|λ| = 1, complex pair) that H never sees.
        let (c, s) = (0.3f64.cos(), 0.3f64.sin());
        #[rustfmt::skip]
        let f3 = Matrix::<3, 3>::from_row_slice(&[
            0.9, 0.0, 0.0,
            0.0, c, -s,
            0.0, s, c,
        ]);
        let h3 = Matrix::<1, 3>::new(1.0, 0.0, 0.0);
        let msg = undetectable_reason(&f3, &h3).expect("not detectable");
        assert!(msg.contains('i'), "{msg}");
    }

    #[test]
    fn sensor_groups_report_on_their_period() {
        let (f, h) = cv(0.1);
        let x_only = SensorGroup {
            components: Availability(0b01),
            period: 5,
        };
        let m = LinearModel::<4, 1, 2>::new(
            0.1,
            f,
            Matrix::<4, 1>::zeros(),
            h,
            Matrix::<4, 4>::identity(),
            true,
            vec![x_only],
        );
        assert_eq!(m.availability(0), Availability(0b11));
        assert_eq!(m.availability(1), Availability(0b10));
        assert_eq!(m.availability(5), Availability(0b11));
        assert_eq!(m.availability(7).count(), 1);
        let every = LinearModel::<4, 1, 2>::new(
            0.1,
            f,
            Matrix::<4, 1>::zeros(),
            h,
            Matrix::<4, 4>::identity(),
            false,
            vec![],
        );
        assert_eq!(every.availability(3), Availability::all(2));
        assert_eq!(every.process_noise_covariance(), None);
        assert_eq!(
            m.process_noise_covariance(),
            Some(Matrix::<4, 4>::identity())
        );
    }
}
