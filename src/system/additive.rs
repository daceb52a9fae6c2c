//! Systems whose world is the filter's model plus additive Gaussian noise.
//!
//! x_k = f(x_{k−1}, u_k) + w_k, z_k = h(x_k, u_k) + v_k, the evaluated quantities are the
//! states, and the filters' inputs are the scenario's controls. P1, P2, L1, the generic
//! linear-Gaussian system and most users' first systems are of this kind; they describe the
//! model, the scenarios and which filter kinds they offer, and [`AdditivePlan`] does the rest
//! (it is the [`SystemPlan`] and builds the [`Trial`]).
//!
//! Filter kinds are values of [`FilterKind`]: [`common_kinds`] work on any [`Model`]
//! (EKF, information, square-root, open loop, UKF, CKF), [`linear_kinds`] add the fixed-gain ones that
//! need a linear model (steady state, pole placement). A system adds its own (the planar
//! running mean) and a user adds theirs, through the same trait.
//! The kind API is in [`super::filter_kind`] and the built-ins in [`super::kinds`]; both are
//! re-exported here, where a system reaches for them.

use std::any::Any;
use std::fmt::Debug;
use std::sync::{Arc, OnceLock};

pub use super::filter_kind::{
    AssumedNoise, AssumedStd, FilterContext, FilterEntry, FilterKind, FilterKinds, FnKind,
    RunFilter, check_scenarios,
};
pub use super::kinds::{common_kinds, linear_kinds};
use super::settings::{FilterNoiseMode, InitialMode, RunSettings};
use super::trial::Trial;
use super::{FilterInfo, Layout, ScenarioInfo, SystemPlan};
use crate::filter::BatchInitial;
use crate::linalg::{Matrix, Vector, diag_from_std};
use crate::metrics::RunConsistency;
use crate::model::Model;
use crate::scenario::Scenario;
use crate::sim::{NoiseDraws, TruthNoise, simulate};
use crate::step_loop::{
    ConsistencyOptions, Prior, RunContext, RunTrace, Unit, UnitResult, lower_triangle,
};

/// A configured additive system: the model, its scenarios, the truth's noise and the
/// validated filter entries. It is the [`SystemPlan`]; [`SystemPlan::trial`] binds it to a
/// plan's runs.
pub struct AdditivePlan<const NX: usize, const NU: usize, const NZ: usize, M> {
    /// The model (the world's and the filters').
    pub model: M,
    /// Names and Δt.
    pub layout: Layout,
    /// The expanded scenarios (x0 and u_0..u_K).
    pub scenarios: Vec<Scenario<NX, NU>>,
    /// The scenarios as the generic code sees them (same order).
    pub scenario_info: Vec<ScenarioInfo>,
    /// The truth's noise at scale 1 (per-state std; a model with a full Q samples that).
    pub truth_noise: TruthNoise<NX, NZ>,
    /// P_0 = diag(p0_std²).
    pub p0_std: Vector<NX>,
    /// Per scenario: the batch least-squares initialiser (`initial_estimate.mode = "batch_ls"`).
    pub batch: Option<Vec<BatchInitial<NX>>>,
    /// The filter entries, in spec order.
    pub entries: Vec<Arc<dyn FilterEntry<NX, NU, NZ, M>>>,
    /// Their infos (same order).
    pub filter_info: Vec<FilterInfo>,
    /// The system's own sections of `kfmc describe` (e.g. the ranks of other sensor sets).
    pub analysis_sections: Vec<crate::analysis::Section>,
}

impl<const NX: usize, const NU: usize, const NZ: usize, M: Debug> Debug
    for AdditivePlan<NX, NU, NZ, M>
{
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("AdditivePlan")
            .field("model", &self.model)
            .field("layout", &self.layout)
            .field("scenarios", &self.scenario_info)
            .field("filters", &self.entries)
            .finish_non_exhaustive()
    }
}

impl<const NX: usize, const NU: usize, const NZ: usize, M> AdditivePlan<NX, NU, NZ, M>
where
    M: Model<NX, NU, NZ> + Debug + 'static,
{
    /// A plan from its parts; the filter infos are taken from the entries.
    pub fn new(
        model: M,
        layout: Layout,
        scenarios: Vec<Scenario<NX, NU>>,
        truth_noise: TruthNoise<NX, NZ>,
        p0_std: Vector<NX>,
        entries: Vec<Arc<dyn FilterEntry<NX, NU, NZ, M>>>,
    ) -> Self {
        AdditivePlan {
            scenario_info: scenarios
                .iter()
                .map(|s| ScenarioInfo {
                    name: s.name.clone(),
                    steps: s.steps(),
                })
                .collect(),
            filter_info: entries.iter().map(|e| e.info()).collect(),
            model,
            layout,
            scenarios,
            truth_noise,
            p0_std,
            batch: None,
            entries,
            analysis_sections: Vec::new(),
        }
    }
}

impl<const NX: usize, const NU: usize, const NZ: usize, M> SystemPlan
    for AdditivePlan<NX, NU, NZ, M>
where
    M: Model<NX, NU, NZ> + Debug + 'static,
{
    fn layout(&self) -> &Layout {
        &self.layout
    }
    fn scenarios(&self) -> &[ScenarioInfo] {
        &self.scenario_info
    }
    fn filters(&self) -> &[FilterInfo] {
        &self.filter_info
    }
    fn trial<'a>(&'a self, settings: &'a RunSettings) -> Box<dyn Trial + 'a> {
        Box::new(AdditiveTrial::new(self, settings))
    }
    fn as_any(&self) -> &dyn Any {
        self
    }
    fn describe(&self, settings: &RunSettings) -> Option<crate::analysis::Description> {
        let trial = AdditiveTrial::new(self, settings);
        let mut d = super::describe::describe_model(
            settings,
            &self.layout,
            &self.model,
            &self.scenarios,
            &self.truth_noise,
            |scenario| trial.clean_consistency(scenario),
        );
        d.sections.extend(self.analysis_sections.iter().cloned());
        Some(d)
    }
    fn filter_model(&self) -> Option<super::filter_model::FilterModel<'_>> {
        Some(super::filter_model::FilterModel::of_additive(
            &self.model,
            NU,
            &self.truth_noise,
            &self.p0_std,
            &self.scenarios,
        ))
    }
}

/// The trial of an [`AdditivePlan`] for one study's settings.
struct AdditiveTrial<'a, const NX: usize, const NU: usize, const NZ: usize, M> {
    sys: &'a AdditivePlan<NX, NU, NZ, M>,
    settings: &'a RunSettings,
    p0: Matrix<NX, NX>,
    p0_factor: Option<Matrix<NX, NX>>,
    /// The model's full discrete Q, which filters assume (times q_scale) when it exists.
    model_q: Option<Matrix<NX, NX>>,
    names: Vec<&'a str>,
    /// The angle quantities (index, in degrees), whose errors are wrapped.
    angles: Vec<(usize, bool)>,
    /// The rotations among the quantities, scored by their rotation error.
    rotations: Vec<crate::linalg::so3::EulerRotation>,
    /// What the consistency tests need of every run (the same for all of them).
    consistency: Option<ConsistencyOptions>,
    /// Per (filter variant, noise scale): the prepared filter, built on first use.
    prepared: Vec<OnceLock<Box<dyn RunFilter<NX, NU, NZ, M>>>>,
}

impl<'a, const NX: usize, const NU: usize, const NZ: usize, M> AdditiveTrial<'a, NX, NU, NZ, M>
where
    M: Model<NX, NU, NZ>,
{
    fn new(sys: &'a AdditivePlan<NX, NU, NZ, M>, settings: &'a RunSettings) -> Self {
        AdditiveTrial {
            p0: diag_from_std(&sys.p0_std),
            p0_factor: (settings.initial == InitialMode::Sampled)
                .then(|| Matrix::<NX, NX>::from_diagonal(&sys.p0_std)),
            model_q: sys.model.process_noise_covariance(),
            names: sys.layout.quantity_names(),
            angles: sys.layout.angles(),
            rotations: sys.layout.rotations(),
            consistency: settings.consistency_options(&sys.layout),
            prepared: (0..settings.filters.len() * settings.noise_scales.len())
                .map(|_| OnceLock::new())
                .collect(),
            sys,
            settings,
        }
    }

    /// The filter's Q and R for a variant at a truth-noise scale.
    fn assumed(&self, variant: usize, filter_scale: f64) -> AssumedNoise<NX, NZ> {
        let f = &self.settings.filters[variant];
        AssumedNoise::for_cell(
            self.sys.entries[f.entry].assumed_std(),
            self.model_q.as_ref(),
            filter_scale,
            f.q_scale,
            f.r_scale,
        )
    }

    /// P_0 for a run of system scenario `si`; with the batch initialiser also x̂_0, set in
    /// `trajectory` from the run's own measurements (its covariance scaled as the filters'
    /// noise is).
    fn initial_estimate(
        &self,
        si: usize,
        trajectory: &mut crate::sim::Trajectory<NX, NZ>,
        filter_scale: f64,
    ) -> Matrix<NX, NX> {
        match &self.sys.batch {
            Some(batch) => {
                let b = &batch[si];
                trajectory.x0_hat = b.estimate(&trajectory.measurements);
                b.covariance * (filter_scale * filter_scale)
            }
            None => self.p0,
        }
    }

    /// The consistency sums of every filter variant on the clean (noise-free) run of study
    /// scenario `scenario`, with the filters' Q and R at noise scale 1: what `kfmc describe`
    /// calibrates the tests with. `None` for a variant without a covariance or an external one.
    fn clean_consistency(&self, scenario: usize) -> Vec<Option<RunConsistency>> {
        let (settings, sys) = (self.settings, self.sys);
        let si = settings.scenarios[scenario].index;
        let sc = &sys.scenarios[si];
        let draws = NoiseDraws::<NX, NZ>::draw(0, sc.steps());
        let mut trajectory = simulate(&sys.model, sc, &sys.truth_noise, 0.0, None, &draws);
        let p0 = self.initial_estimate(si, &mut trajectory, 1.0);
        let prior = Prior {
            x0_hat: &trajectory.x0_hat,
            p0: &p0,
        };
        let ctx = RunContext {
            truth: &trajectory.truth,
            inputs: &sc.controls,
            measurements: &trajectory.measurements,
            angles: &self.angles,
            rotations: &self.rotations,
            thresholds: None,
            quantity_names: &self.names,
            trace: false,
            export: false,
            consistency: Some(
                settings
                    .consistency_options(&sys.layout)
                    .unwrap_or_else(|| settings.consistency_options_with_lags(&sys.layout, 0)),
            ),
            unit: Unit {
                scenario,
                scale: 0,
                run: 0,
            },
        };
        settings
            .filters
            .iter()
            .enumerate()
            .map(|(fi, f)| {
                if f.external {
                    return None;
                }
                let filter = sys.entries[f.entry].prepare(&sys.model, &self.assumed(fi, 1.0));
                filter.run(&sys.model, &prior, &ctx).run.consistency
            })
            .collect()
    }
}

impl<const NX: usize, const NU: usize, const NZ: usize, M> Trial
    for AdditiveTrial<'_, NX, NU, NZ, M>
where
    M: Model<NX, NU, NZ>,
{
    fn run(&self, unit: &Unit) -> UnitResult {
        let settings = self.settings;
        let sys = self.sys;
        let si = settings.scenarios[unit.scenario].index;
        let scenario = &sys.scenarios[si];
        let noise_scale = settings.noise_scales[unit.scale];
        let seed = settings.run_seed(&scenario.name, unit.scale, unit.run);
        let draws = NoiseDraws::<NX, NZ>::draw(seed, scenario.steps());
        let mut trajectory = simulate(
            &sys.model,
            scenario,
            &sys.truth_noise,
            noise_scale,
            self.p0_factor.as_ref(),
            &draws,
        );
        let traced = unit.run < settings.trace_runs;
        let filter_scale = match settings.filter_noise {
            FilterNoiseMode::Nominal => 1.0,
            FilterNoiseMode::Matched => noise_scale,
        };
        let p0 = self.initial_estimate(si, &mut trajectory, filter_scale);
        let prior = Prior {
            x0_hat: &trajectory.x0_hat,
            p0: &p0,
        };
        let ctx = RunContext {
            truth: &trajectory.truth,
            inputs: &scenario.controls,
            measurements: &trajectory.measurements,
            angles: &self.angles,
            rotations: &self.rotations,
            thresholds: settings.rmse_thresholds.as_deref(),
            quantity_names: &self.names,
            trace: traced,
            export: settings.export_estimates,
            consistency: self.consistency,
            unit: *unit,
        };
        let keep = traced || settings.export_estimates;
        let mut trace = keep.then(|| {
            let mut t = RunTrace::of_world(
                &scenario.controls,
                &trajectory.truth,
                &trajectory.measurements,
                Vec::new(),
            );
            t.initial = Some((trajectory.x0_hat.as_slice().to_vec(), lower_triangle(&p0)));
            t
        });
        let mut filters = Vec::with_capacity(settings.filters.len());
        for (fi, f) in settings.filters.iter().enumerate() {
            let mut out = if f.external {
                crate::score::replay(
                    settings.estimates.as_deref(),
                    fi,
                    &f.label,
                    &sys.model,
                    &ctx,
                )
            } else {
                let slot = &self.prepared[fi * settings.noise_scales.len() + unit.scale];
                let filter = slot.get_or_init(|| {
                    sys.entries[f.entry].prepare(&sys.model, &self.assumed(fi, filter_scale))
                });
                filter.run(&sys.model, &prior, &ctx)
            };
            if let Some(t) = trace.as_mut() {
                t.push_filter(&mut out, NX);
            }
            filters.push(out.run);
        }
        UnitResult {
            unit: *unit,
            seed,
            filters,
            trace,
            world_metrics: Vec::new(),
        }
    }

    fn steps(&self, scenario: usize) -> usize {
        self.sys.scenarios[self.settings.scenarios[scenario].index].steps()
    }

    fn layout(&self) -> &Layout {
        &self.sys.layout
    }
}
