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
use std::sync::Arc;

pub(crate) use super::filter_kind::{
    AssumedNoise, FilterContext, FilterEntry, FilterKind, FilterKinds, FilterSetup, RunFilter,
    check_scenarios,
};
pub(crate) use super::kinds::{common_kinds, linear_kinds};
use super::settings::{FilterPlan, InitialMode, RunSettings};
use super::trial::{Cell, Simulated, Trial, TrialKit, UnitRunner};
use super::{FilterInfo, Layout, ScenarioInfo, SystemPlan};
use crate::filter::BatchInitial;
use crate::linalg::{Matrix, Vector, diag_from_std};
use crate::metrics::RunConsistency;
use crate::model::Model;
use crate::scenario::Scenario;
use crate::sim::{NoiseDraws, Trajectory, TruthNoise, simulate};
use crate::step_loop::{FilterOutput, Prior, RunContext, Unit, UnitResult};

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
    runner: UnitRunner<'a, dyn RunFilter<NX, NU, NZ, M>>,
    p0: Matrix<NX, NX>,
    p0_factor: Option<Matrix<NX, NX>>,
    /// The model's full discrete Q, which filters assume (times q_scale) when it exists.
    model_q: Option<Matrix<NX, NX>>,
}

/// One simulated run of an additive system: the trajectory (with x̂_0) and P_0.
struct AdditiveRun<const NX: usize, const NZ: usize> {
    scenario: usize,
    trajectory: Trajectory<NX, NZ>,
    p0: Matrix<NX, NX>,
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
            runner: UnitRunner::new(&sys.layout, &sys.scenario_info, settings),
            sys,
            settings,
        }
    }

    /// The filter's Q and R for a variant at a truth-noise scale.
    fn assumed(&self, variant: &FilterPlan, filter_scale: f64) -> AssumedNoise<NX, NZ> {
        AssumedNoise::for_cell(
            self.sys.entries[variant.entry].assumed_std(),
            self.model_q.as_ref(),
            filter_scale,
            variant.q_scale,
            variant.r_scale,
        )
    }

    /// P_0 for a run of system scenario `si`; with the batch initialiser also x̂_0, set in
    /// `trajectory` from the run's own measurements (its covariance scaled as the filters'
    /// noise is).
    fn initial_estimate(
        &self,
        si: usize,
        trajectory: &mut Trajectory<NX, NZ>,
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
        let run = AdditiveRun {
            scenario: si,
            trajectory,
            p0,
        };
        let unit = Unit {
            scenario,
            scale: 0,
            run: 0,
        };
        let ctx = RunContext {
            thresholds: None,
            trace: false,
            export: false,
            consistency: Some(
                settings
                    .consistency_options(&sys.layout)
                    .unwrap_or_else(|| settings.consistency_options_with_lags(&sys.layout, 0)),
            ),
            ..self.runner.context(&unit, &self.view(&run))
        };
        settings
            .filters
            .iter()
            .map(|f| {
                if f.external {
                    return None;
                }
                let filter = sys.entries[f.entry].prepare(&sys.model, &self.assumed(f, 1.0));
                self.run_filter(filter.as_ref(), &run, &ctx).run.consistency
            })
            .collect()
    }
}

impl<const NX: usize, const NU: usize, const NZ: usize, M> TrialKit<NX, NU, NZ>
    for AdditiveTrial<'_, NX, NU, NZ, M>
where
    M: Model<NX, NU, NZ>,
{
    type Filter = dyn RunFilter<NX, NU, NZ, M>;
    type Run = AdditiveRun<NX, NZ>;
    type ReplayModel = M;

    fn simulate(&self, cell: &Cell, _: &Unit, seed: u64) -> AdditiveRun<NX, NZ> {
        let scenario = &self.sys.scenarios[cell.scenario];
        let draws = NoiseDraws::<NX, NZ>::draw(seed, scenario.steps());
        let mut trajectory = simulate(
            &self.sys.model,
            scenario,
            &self.sys.truth_noise,
            cell.noise_scale,
            self.p0_factor.as_ref(),
            &draws,
        );
        let p0 = self.initial_estimate(cell.scenario, &mut trajectory, cell.filter_scale);
        AdditiveRun {
            scenario: cell.scenario,
            trajectory,
            p0,
        }
    }

    fn view<'r>(&'r self, run: &'r AdditiveRun<NX, NZ>) -> Simulated<'r, NX, NU, NZ> {
        Simulated {
            truth: &run.trajectory.truth,
            inputs: &self.sys.scenarios[run.scenario].controls,
            measurements: &run.trajectory.measurements,
            world: &[],
            prior: Some(Prior {
                x0_hat: &run.trajectory.x0_hat,
                p0: &run.p0,
            }),
        }
    }

    fn prepare(&self, variant: &FilterPlan, cell: &Cell) -> Box<dyn RunFilter<NX, NU, NZ, M>> {
        self.sys.entries[variant.entry]
            .prepare(&self.sys.model, &self.assumed(variant, cell.filter_scale))
    }

    fn run_filter(
        &self,
        filter: &dyn RunFilter<NX, NU, NZ, M>,
        run: &AdditiveRun<NX, NZ>,
        ctx: &RunContext<'_, NX, NU, NZ>,
    ) -> FilterOutput {
        let prior = Prior {
            x0_hat: &run.trajectory.x0_hat,
            p0: &run.p0,
        };
        filter.run(&self.sys.model, &prior, ctx)
    }

    fn run_filter_group(
        &self,
        filter: &dyn RunFilter<NX, NU, NZ, M>,
        runs: &[&AdditiveRun<NX, NZ>],
        ctxs: &[RunContext<'_, NX, NU, NZ>],
    ) -> Vec<FilterOutput> {
        let priors: Vec<Prior<'_, NX>> = runs
            .iter()
            .map(|run| Prior {
                x0_hat: &run.trajectory.x0_hat,
                p0: &run.p0,
            })
            .collect();
        filter.run_group(&self.sys.model, &priors, ctxs)
    }

    fn replay_model(&self) -> &M {
        &self.sys.model
    }

    fn world_metrics(&self, _run: AdditiveRun<NX, NZ>) -> Vec<f64> {
        Vec::new()
    }
}

impl<const NX: usize, const NU: usize, const NZ: usize, M> Trial
    for AdditiveTrial<'_, NX, NU, NZ, M>
where
    M: Model<NX, NU, NZ>,
{
    fn run(&self, unit: &Unit) -> UnitResult {
        self.runner.run(self, unit)
    }

    fn run_group(&self, units: &[Unit]) -> Vec<UnitResult> {
        self.runner.run_group(self, units)
    }

    fn lanes(&self) -> usize {
        self.settings.lanes.width()
    }

    fn steps(&self, scenario: usize) -> usize {
        self.runner.steps(scenario)
    }

    fn layout(&self) -> &Layout {
        self.runner.layout()
    }
}
