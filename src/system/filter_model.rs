//! The filter-side model of a configured system: what a filter written outside kfmc needs to
//! use the world's own model instead of rebuilding it — f, h and their Jacobians as code
//! ([`DynModel`], the functions the truth simulator and kfmc's filters call), F, G, H for a
//! linear model, the truth's Q and R, the prior's P_0, and the step convention
//! ([`StepConvention`]): which input drives a step, what row 0 is, what wraps.
//!
//! [`SystemPlan::filter_model`](super::SystemPlan::filter_model) returns it; systems built on
//! one [`Model`] with additive noise (P1, P2, L1, `kind = "linear"`) have one, a world that is
//! not one model (the drone) has none. The Python package's `Simulation.f/h/jacobians` and
//! `kfmc describe`'s `[filter_model]` are made from it.

use super::Layout;
use crate::linalg::{Vector, diag_from_std};
use crate::model::Model;
use crate::model::exposed::{DynMatrix, DynModel, FilterModelRecord, ModelView, ScenarioStart};
use crate::output::manifest::StepConvention;
use crate::scenario::Scenario;
use crate::sim::TruthNoise;

/// [`StepConvention::transition`]: kfmc's step loop ([`crate::trial::run_filter`]) and truth
/// simulator ([`crate::sim::simulate`]) both take the input of the new step.
pub const TRANSITION: &str = "x_k = f(x_{k-1}, u_k) + w_k: the input on row k (u_k) drives the step from k-1 to k, so u_0 drives nothing; a filter predicts step k with u_k, then updates with z_k";

/// [`StepConvention::measurement`].
pub const MEASUREMENT: &str = "z_k = h(x_k, u_k) + v_k on row k, for k = 1..K; step 0 has no measurement (z is null on row 0 of measurements.parquet), and a component that did not report is null";

/// [`StepConvention::row_0`].
pub const ROW_0: &str = "step 0 is the start: row 0 of truth.parquet is x_0, the run's prior (x̂_0, P_0) is its row of initial.parquet, and an estimates file's step-0 row is that prior, without an innovation";

/// The model kfmc's filters use, and the noise and prior of the world they run in.
pub struct FilterModel<'a> {
    /// f, h and their Jacobians, through slices.
    pub model: Box<dyn DynModel + 'a>,
    /// Q: the truth's process-noise covariance at noise scale 1 (the model's full Q, or the
    /// diagonal of the per-state standard deviations squared). Noise scale s draws s² Q.
    pub process_noise: DynMatrix,
    /// R: the truth's measurement-noise covariance at noise scale 1 (s² R at scale s).
    pub measurement_noise: DynMatrix,
    /// P_0 = diag(p0_std²): the prior's covariance in the `truth` and `sampled` modes.
    pub initial_covariance: DynMatrix,
    /// Each scenario's true initial state x_0.
    pub initial_states: Vec<ScenarioStart>,
}

impl std::fmt::Debug for FilterModel<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FilterModel")
            .field("states", &self.model.states())
            .field("inputs", &self.model.inputs())
            .field("measurements", &self.model.measurements())
            .field("process_noise", &self.process_noise)
            .field("measurement_noise", &self.measurement_noise)
            .field("initial_covariance", &self.initial_covariance)
            .finish_non_exhaustive()
    }
}

impl<'a> FilterModel<'a> {
    /// The filter-side model of a world that is `model` plus additive noise: the parts of an
    /// [`super::additive::AdditivePlan`]. `inputs`: how many of the model's `NU` inputs the
    /// spec names (the rest are padding, zero).
    pub fn of_additive<const NX: usize, const NU: usize, const NZ: usize, M>(
        model: &'a M,
        inputs: usize,
        truth_noise: &TruthNoise<NX, NZ>,
        p0_std: &Vector<NX>,
        scenarios: &[Scenario<NX, NU>],
    ) -> Self
    where
        M: Model<NX, NU, NZ> + 'a,
    {
        // The same Q the truth samples (crate::sim::simulate): the model's own full Q when
        // it has one, else the per-state standard deviations.
        let q = model
            .process_noise_covariance()
            .unwrap_or_else(|| diag_from_std(&truth_noise.process_std));
        FilterModel {
            model: Box::new(ModelView::<M, NX, NU, NZ>::with_inputs(model, inputs)),
            process_noise: DynMatrix::of(&q),
            measurement_noise: DynMatrix::of(&diag_from_std(&truth_noise.measurement_std)),
            initial_covariance: DynMatrix::of(&diag_from_std(p0_std)),
            initial_states: scenarios
                .iter()
                .map(|s| ScenarioStart {
                    scenario: s.name.clone(),
                    x0: s.x0.as_slice().to_vec(),
                })
                .collect(),
        }
    }

    /// The record `kfmc describe` writes, with the names of `layout`.
    pub fn record(&self, layout: &Layout) -> FilterModelRecord {
        let linear = self.model.linear();
        FilterModelRecord {
            form: if linear.is_some() {
                "linear"
            } else {
                "nonlinear"
            }
            .into(),
            dt_s: self.model.dt_s(),
            states: layout
                .quantity_names()
                .iter()
                .map(|s| s.to_string())
                .collect(),
            inputs: layout.inputs.clone(),
            measurements: layout.measurements.clone(),
            f: linear.as_ref().map(|l| l.0.to_rows()),
            g: linear.as_ref().map(|l| l.1.to_rows()),
            h: linear.as_ref().map(|l| l.2.to_rows()),
            q: self.process_noise.to_rows(),
            r: self.measurement_noise.to_rows(),
            p0: self.initial_covariance.to_rows(),
            x0: self.initial_states.clone(),
            convention: step_convention(layout, Some(self.model.as_ref())),
        }
    }
}

/// The step convention of a system with this layout and, when it has one, filter-side
/// model: the sentences of kfmc's step loop and the system's wrapped quantities.
pub fn step_convention(layout: &Layout, model: Option<&dyn DynModel>) -> StepConvention {
    let names = |idx: &[usize], all: &[String]| -> Vec<String> {
        idx.iter().filter_map(|&i| all.get(i).cloned()).collect()
    };
    let quantities: Vec<String> = layout.quantities.iter().map(|q| q.name.clone()).collect();
    let angle_states = model.map(|m| m.angle_states()).unwrap_or_default();
    StepConvention {
        transition: TRANSITION.into(),
        measurement: MEASUREMENT.into(),
        row_0: ROW_0.into(),
        wrapped_errors: names(&layout.angle_indices(), &quantities),
        continuous_angles: angle_states
            .iter()
            .filter(|&&i| layout.quantities.get(i).is_some_and(|q| !q.angle))
            .filter_map(|&i| quantities.get(i).cloned())
            .collect(),
        wrapped_innovations: model
            .map(|m| names(&m.angle_measurements(), &layout.measurements))
            .unwrap_or_default(),
        rotation_errors: layout
            .rotations()
            .iter()
            .map(|r| {
                let side = layout.quantities[r.first]
                    .rotation
                    .map_or("right", |s| s.name());
                format!(
                    "{} ({side} error)",
                    quantities[r.first..r.first + 3].join(", ")
                )
            })
            .collect(),
    }
}

/// The step convention of a configured system.
pub fn convention_of(system: &dyn super::SystemPlan) -> StepConvention {
    let model = system.filter_model();
    step_convention(system.layout(), model.as_ref().map(|m| m.model.as_ref()))
}
