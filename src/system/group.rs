//! Runs of one cell in a group, where a built-in filter shares work across them.
//!
//! A Kalman filter on a linear model has a covariance recursion (P, S, K) that does not depend
//! on the run: not on the estimate, not on the measurements' values, only on P_0 and on which
//! components report at each step. When every run of a group starts from the same P_0 and
//! sees the same sensor schedule, [`run_group_shared`] computes that recursion once for the
//! group and runs only the estimate recursion per run, through the same step loop with the
//! same operations in the same order on each run's estimate (the gain's functions are the
//! scalar update's own, [`Ekf::gain`] and [`Ekf::update_covariance`]), so every value is the
//! scalar path's, bit for bit. A group that does not qualify (a nonlinear model, different P_0 or
//! schedules, a covariance the step loop would have to repair) runs one run at a time.

use crate::filter::ekf::{Ekf, Gaussian, UpdateGain};
use crate::filter::{Filter, FilterError, Innovation};
use crate::linalg::{Matrix, SmallCholesky, Vector};
use crate::model::{Measurement, Model};
use crate::step_loop::{FilterOutput, Identity, Prior, RunContext, run_filter};

/// Runs `ekf` on a group of runs of one cell (`priors[i]` with `ctxs[i]`) with its covariance
/// recursion computed once for the group, one output per run, each equal to the scalar
/// path's ([`run_filter`] on the run alone); `None` when the group does not qualify (see the
/// module's documentation), and the caller runs the runs one by one.
pub fn run_group_shared<const NX: usize, const NU: usize, const NZ: usize, M>(
    ekf: &Ekf<NX, NZ>,
    model: &M,
    priors: &[Prior<'_, NX>],
    ctxs: &[RunContext<'_, NX, NU, NZ>],
) -> Option<Vec<FilterOutput>>
where
    M: Model<NX, NU, NZ>,
{
    let track = Track::build(ekf, model, priors, ctxs)?;
    let shared = Shared { ekf, track: &track };
    Some(
        priors
            .iter()
            .zip(ctxs)
            .map(|(p, c)| run_filter(model, &shared, &Identity, p, c))
            .collect(),
    )
}

/// Where in a step the shared recursion failed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Phase {
    /// The prediction's P is not finite.
    Predict,
    /// S is not positive definite (before the estimate is updated).
    Gain,
    /// The updated P is not finite (after the estimate is updated).
    AfterUpdate,
}

/// One step of the shared recursion: the belief after it (its estimate unused) and the
/// update's gain when a component reported.
struct TrackStep<const NX: usize, const NZ: usize> {
    belief: Gaussian<NX>,
    gain: Option<UpdateGain<NX, NZ>>,
}

/// The covariance recursion of a group: `steps[k]` for every step reached, and the step,
/// phase and error at which it failed (every run of the group fails there, unless its own
/// estimate failed first, as on the scalar path).
struct Track<const NX: usize, const NZ: usize> {
    steps: Vec<TrackStep<NX, NZ>>,
    end: Option<(usize, Phase, FilterError)>,
}

/// Whether two matrices hold the same bits.
fn same_bits<const R: usize, const C: usize>(a: &Matrix<R, C>, b: &Matrix<R, C>) -> bool {
    a.iter()
        .zip(b.iter())
        .all(|(x, y)| x.to_bits() == y.to_bits())
}

impl<const NX: usize, const NZ: usize> Track<NX, NZ> {
    /// The recursion shared by every run of a group, or `None` when the group does not
    /// qualify: a model not declared linear, fewer than two runs, priors whose P_0 differ,
    /// runs of different lengths or sensor schedules, or a P the step loop could not factor
    /// (it would repair it, and the repair belongs to the scalar path).
    fn build<const NU: usize, M: Model<NX, NU, NZ>>(
        ekf: &Ekf<NX, NZ>,
        model: &M,
        priors: &[Prior<'_, NX>],
        ctxs: &[RunContext<'_, NX, NU, NZ>],
    ) -> Option<Self> {
        let lin = model.linear()?;
        let (first, ctx0) = (priors.first()?, ctxs.first()?);
        if priors.len() < 2 || priors.len() != ctxs.len() {
            return None;
        }
        let samples = ctx0.truth.len();
        let same_schedule = |c: &RunContext<'_, NX, NU, NZ>| {
            c.truth.len() == samples
                && c.measurements.len() == ctx0.measurements.len()
                && c.inputs.len() == ctx0.inputs.len()
                && c.measurements
                    .iter()
                    .zip(ctx0.measurements)
                    .all(|(a, b)| a.available == b.available)
        };
        if !priors.iter().all(|p| same_bits(p.p0, first.p0)) || !ctxs.iter().all(same_schedule) {
            return None;
        }
        // The estimate enters P only through the Jacobians, which a linear model declares
        // constant: hold it to that at the recursion's own estimate.
        let mut b = Gaussian::new(Vector::<NX>::zeros(), *first.p0);
        if let Some(u) = ctx0.inputs.get(1) {
            let f_ok = same_bits(&model.transition_jacobian(&b.x, u), &lin.f);
            let h_ok = same_bits(&model.measurement_jacobian(&b.x, u), &lin.h);
            if !(f_ok && h_ok) {
                return None;
            }
        }
        SmallCholesky::new(&b.p)?;
        let mut steps = Vec::with_capacity(samples);
        steps.push(TrackStep {
            belief: b.clone(),
            gain: None,
        });
        let mut end = None;
        for k in 1..samples {
            let u = &ctx0.inputs[k];
            if let Err(e) = Filter::<NX, NU, NZ, M>::predict(ekf, model, &mut b, u) {
                // The recursion's own estimate stays finite; if it did not, the error is
                // not the covariance's.
                if !b.x.sum().is_finite() {
                    return None;
                }
                end = Some((k, Phase::Predict, e));
                break;
            }
            let available = ctx0.measurements[k].available;
            let gain = if available.count() > 0 {
                let mut nu = Vector::<NZ>::zeros();
                match ekf.gain(model, &b, u, available, &mut nu) {
                    Ok(g) => {
                        ekf.update_covariance(&mut b, &g);
                        Some(g)
                    }
                    Err(e) => {
                        end = Some((k, Phase::Gain, e));
                        break;
                    }
                }
            } else {
                None
            };
            let updated = gain.is_some();
            steps.push(TrackStep {
                belief: b.clone(),
                gain,
            });
            if updated && !b.p.trace().is_finite() {
                let e = FilterError::NonFinite {
                    what: "state covariance",
                };
                end = Some((k, Phase::AfterUpdate, e));
                break;
            }
            SmallCholesky::new(&b.p)?;
        }
        Some(Track { steps, end })
    }

    /// The error of the shared recursion at step `k` in `phase`, if it failed there.
    fn failure(&self, k: usize, phase: Phase) -> Option<FilterError> {
        match &self.end {
            Some((at, p, e)) if *at == k && *p == phase => Some(e.clone()),
            _ => None,
        }
    }
}

/// The filter one run of a group runs: its own estimate, the group's covariance.
struct Shared<'t, const NX: usize, const NZ: usize> {
    ekf: &'t Ekf<NX, NZ>,
    track: &'t Track<NX, NZ>,
}

/// A run's belief on the shared recursion: its estimate, the step, and the step's record.
#[derive(Clone)]
struct SharedBelief<'t, const NX: usize, const NZ: usize> {
    x: Vector<NX>,
    k: usize,
    step: &'t TrackStep<NX, NZ>,
}

/// The estimate's half of the EKF's finiteness check.
#[inline]
fn estimate_finite<const NX: usize>(x: &Vector<NX>) -> Result<(), FilterError> {
    if x.sum().is_finite() {
        Ok(())
    } else {
        Err(FilterError::NonFinite {
            what: "state estimate",
        })
    }
}

impl<'t, const NX: usize, const NU: usize, const NZ: usize, M> Filter<NX, NU, NZ, M>
    for Shared<'t, NX, NZ>
where
    M: Model<NX, NU, NZ>,
{
    type Belief = SharedBelief<'t, NX, NZ>;

    fn init(
        &self,
        _model: &M,
        x0_hat: &Vector<NX>,
        _p0: &Matrix<NX, NX>,
        _z0: &Measurement<NZ>,
    ) -> Self::Belief {
        SharedBelief {
            x: *x0_hat,
            k: 0,
            step: &self.track.steps[0],
        }
    }

    #[inline]
    fn predict(&self, model: &M, b: &mut Self::Belief, u: &Vector<NU>) -> Result<(), FilterError> {
        b.x = model.propagate(&b.x, u);
        b.k += 1;
        estimate_finite(&b.x)?;
        match self.track.failure(b.k, Phase::Predict) {
            Some(e) => Err(e),
            None => Ok(()),
        }
    }

    #[inline]
    fn update(
        &self,
        model: &M,
        b: &mut Self::Belief,
        u: &Vector<NU>,
        z: &Measurement<NZ>,
    ) -> Result<Option<Innovation<NZ>>, FilterError> {
        if z.available.count() == 0 {
            b.step = &self.track.steps[b.k];
            return Ok(None);
        }
        let mut nu = model.residual(&z.z, &model.measure(&b.x, u));
        if let Some(e) = self.track.failure(b.k, Phase::Gain) {
            return Err(e);
        }
        let step = &self.track.steps[b.k];
        let gain = step
            .gain
            .as_ref()
            .expect("a step with a report has its gain");
        gain.mask_residual(z.available, &mut nu);
        let whitened = gain.chol.solve_lower(&nu);
        b.x += gain.k * nu;
        estimate_finite(&b.x)?;
        if let Some(e) = self.track.failure(b.k, Phase::AfterUpdate) {
            return Err(e);
        }
        b.step = step;
        Ok(Some(
            Innovation::new(nu, whitened, z.available).with_covariance(gain.s),
        ))
    }

    fn mean(&self, b: &Self::Belief) -> Vector<NX> {
        b.x
    }

    fn covariance(&self, b: &Self::Belief) -> Option<Matrix<NX, NX>> {
        Some(b.step.belief.p)
    }

    fn covariance_ref<'b>(&self, b: &'b Self::Belief) -> Option<&'b Matrix<NX, NX>> {
        Some(&b.step.belief.p)
    }

    fn error_transition(&self, b: &Self::Belief) -> Option<Matrix<NX, NX>> {
        Filter::<NX, NU, NZ, M>::error_transition(self.ekf, &b.step.belief)
    }
}
