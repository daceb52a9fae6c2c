//! Systems whose world is not the filters' model.
//!
//! The world of one run — truth dynamics plus sensors, each with its own rate, noise and error
//! states (bias, drift, delay) — produces a [`Realisation`]: the true evaluated quantities,
//! the measurement stream with its availability, and the inputs the filters receive (for an
//! INS, the measured IMU samples). Each filter carries its own model and state, larger,
//! smaller or differently parameterised than the world's, forms its own prior from the
//! realisation, and is scored on the same quantities through an
//! [`Evaluate`](crate::step_loop::Evaluate) map.
//!
//! A system implements [`World`] and one [`WorldFilterEntry`] per filter kind, and
//! [`WorldPlan`] is its [`SystemPlan`]: seeds, filter variants, caching per cell and traces
//! are done here once for every such system.

use std::any::Any;
use std::fmt::Debug;
use std::sync::Arc;

use super::settings::{FilterPlan, RunSettings};
use super::trial::{Cell, Simulated, Trial, TrialKit, UnitRunner};
use super::{FilterInfo, Layout, ScenarioInfo, SystemPlan};
use crate::linalg::Vector;
use crate::model::Measurement;
use crate::step_loop::{FilterOutput, RunContext, Unit, UnitResult};

/// One simulated run of a world.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Realisation<const NQ: usize, const NU: usize, const NZ: usize> {
    /// The true evaluated quantities q_0..q_K.
    pub truth: Vec<Vector<NQ>>,
    /// The inputs the filters receive, u_0..u_K.
    pub inputs: Vec<Vector<NU>>,
    /// z_0..z_K with the components that reported.
    pub measurements: Vec<Measurement<NZ>>,
    /// The world's own states beyond the quantities (biases, drifts), one value per
    /// [`Layout::world_states`] name per step, row-major; empty when the world has none.
    pub world: Vec<f64>,
    /// Standard normals drawn once per run for the filters' priors (shared by every filter
    /// of the run, so their initial errors are paired); as many as the world declares.
    pub prior_draws: Vec<f64>,
    /// The index of the system's scenario this is a run of, for filters whose settings
    /// depend on the scenario (a paper's filter tuned per route).
    pub scenario: usize,
    /// The world's own per-run numbers about its sensors (each raw sensor's RMSE against the
    /// truth, …), one per [`WorldPlan::world_metrics`] name; they fill the `sensors` table.
    pub metrics: Vec<f64>,
}

/// The truth and sensors of a system.
pub trait World<const NQ: usize, const NU: usize, const NZ: usize>: Send + Sync {
    /// Simulates one run of scenario `scenario` (an index into the system's scenarios) with
    /// every truth-noise level times `noise_scale`. All randomness must come from `seed`
    /// (e.g. through [`crate::sim::seed::stream`]), so runs are reproducible on any thread
    /// and shard.
    fn simulate(&self, scenario: usize, noise_scale: f64, seed: u64) -> Realisation<NQ, NU, NZ>;
}

/// What a filter variant of a cell is told about its noise settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NoiseSettings {
    /// The truth-noise multiplier of the cell.
    pub noise_scale: f64,
    /// The multiplier of the filter's assumed standard deviations: 1 (`nominal`) or the
    /// truth's multiplier (`matched`).
    pub filter_scale: f64,
    /// The variant's Q multiplier.
    pub q_scale: f64,
    /// The variant's R multiplier.
    pub r_scale: f64,
}

/// A filter ready to run on realisations of a world: one virtual call per run, then the
/// monomorphised step loop ([`crate::step_loop::run_filter`] with the filter's own prior and
/// evaluation).
pub trait WorldFilter<const NQ: usize, const NU: usize, const NZ: usize>: Send + Sync {
    /// Runs the filter on one realisation.
    fn run(
        &self,
        realisation: &Realisation<NQ, NU, NZ>,
        ctx: &RunContext<'_, NQ, NU, NZ>,
    ) -> FilterOutput;
}

/// A validated filter entry of a world system.
pub trait WorldFilterEntry<const NQ: usize, const NU: usize, const NZ: usize>:
    Send + Sync + Debug
{
    /// What the generic code needs to know of it.
    fn info(&self) -> FilterInfo;
    /// Builds the filter of one cell (variant × truth-noise scale); cached per cell.
    fn prepare(&self, noise: &NoiseSettings) -> Box<dyn WorldFilter<NQ, NU, NZ>>;
}

/// A configured world system: the [`SystemPlan`] of any [`World`].
pub struct WorldPlan<const NQ: usize, const NU: usize, const NZ: usize> {
    /// The world.
    pub world: Arc<dyn World<NQ, NU, NZ>>,
    /// Names and Δt.
    pub layout: Layout,
    /// The scenarios (names and lengths; the world knows the rest).
    pub scenario_info: Vec<ScenarioInfo>,
    /// The filter entries, in spec order.
    pub entries: Vec<Arc<dyn WorldFilterEntry<NQ, NU, NZ>>>,
    /// Their infos.
    pub filter_info: Vec<FilterInfo>,
    /// Names of the world's per-run metrics ([`Realisation::metrics`]); empty for none.
    pub world_metrics: Vec<String>,
    /// Whether the world's truth is recorded, never simulated ([`SystemPlan::recorded`]).
    pub recorded: bool,
}

impl<const NQ: usize, const NU: usize, const NZ: usize> WorldPlan<NQ, NU, NZ> {
    /// A plan from its parts.
    pub fn new(
        world: Arc<dyn World<NQ, NU, NZ>>,
        layout: Layout,
        scenario_info: Vec<ScenarioInfo>,
        entries: Vec<Arc<dyn WorldFilterEntry<NQ, NU, NZ>>>,
    ) -> Self {
        WorldPlan {
            filter_info: entries.iter().map(|e| e.info()).collect(),
            world,
            layout,
            scenario_info,
            entries,
            world_metrics: Vec::new(),
            recorded: false,
        }
    }

    /// The plan of a world whose truth is recorded ([`SystemPlan::recorded`]): its
    /// [`World::simulate`] is never called with a truth table attached, and the commands that
    /// simulate refuse it.
    pub fn with_recorded_truth(mut self) -> Self {
        self.recorded = true;
        self
    }

    /// The plan with per-run world metrics named `names` (the `sensors` table).
    pub fn with_world_metrics(mut self, names: Vec<String>) -> Self {
        self.world_metrics = names;
        self
    }
}

impl<const NQ: usize, const NU: usize, const NZ: usize> Debug for WorldPlan<NQ, NU, NZ> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("WorldPlan")
            .field("layout", &self.layout)
            .field("scenarios", &self.scenario_info)
            .field("filters", &self.entries)
            .finish_non_exhaustive()
    }
}

impl<const NQ: usize, const NU: usize, const NZ: usize> SystemPlan for WorldPlan<NQ, NU, NZ> {
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
        Box::new(WorldTrial {
            runner: UnitRunner::new(&self.layout, &self.scenario_info, settings),
            unmodelled: crate::score::Unmodelled {
                dt_s: self.layout.dt_s,
            },
            sys: self,
        })
    }
    fn as_any(&self) -> &dyn Any {
        self
    }
    fn recorded(&self) -> bool {
        self.recorded
    }
}

/// The trial of a [`WorldPlan`] for one study's settings.
struct WorldTrial<'a, const NQ: usize, const NU: usize, const NZ: usize> {
    sys: &'a WorldPlan<NQ, NU, NZ>,
    runner: UnitRunner<'a, dyn WorldFilter<NQ, NU, NZ>>,
    /// The model external filters are replayed on.
    unmodelled: crate::score::Unmodelled,
}

impl<const NQ: usize, const NU: usize, const NZ: usize> TrialKit<NQ, NU, NZ>
    for WorldTrial<'_, NQ, NU, NZ>
{
    type Filter = dyn WorldFilter<NQ, NU, NZ>;
    type Run = Realisation<NQ, NU, NZ>;
    type ReplayModel = crate::score::Unmodelled;

    fn simulate(&self, cell: &Cell, unit: &Unit, seed: u64) -> Realisation<NQ, NU, NZ> {
        match &self.runner.settings.truth {
            Some(truth) => recorded_run(
                truth,
                unit,
                self.runner.settings.noise_scales.len(),
                self.runner.steps(unit.scenario),
                cell.scenario,
            ),
            None => self
                .sys
                .world
                .simulate(cell.scenario, cell.noise_scale, seed),
        }
    }

    fn view<'r>(&'r self, real: &'r Realisation<NQ, NU, NZ>) -> Simulated<'r, NQ, NU, NZ> {
        Simulated {
            truth: &real.truth,
            inputs: &real.inputs,
            measurements: &real.measurements,
            world: &real.world,
            prior: None,
        }
    }

    fn prepare(&self, variant: &FilterPlan, cell: &Cell) -> Box<dyn WorldFilter<NQ, NU, NZ>> {
        self.sys.entries[variant.entry].prepare(&NoiseSettings {
            noise_scale: cell.noise_scale,
            filter_scale: cell.filter_scale,
            q_scale: variant.q_scale,
            r_scale: variant.r_scale,
        })
    }

    fn run_filter(
        &self,
        filter: &dyn WorldFilter<NQ, NU, NZ>,
        real: &Realisation<NQ, NU, NZ>,
        ctx: &RunContext<'_, NQ, NU, NZ>,
    ) -> FilterOutput {
        filter.run(real, ctx)
    }

    fn replay_model(&self) -> &crate::score::Unmodelled {
        &self.unmodelled
    }

    fn world_metrics(&self, real: Realisation<NQ, NU, NZ>) -> Vec<f64> {
        real.metrics
    }
}

impl<const NQ: usize, const NU: usize, const NZ: usize> Trial for WorldTrial<'_, NQ, NU, NZ> {
    fn run(&self, unit: &Unit) -> UnitResult {
        self.runner.run(self, unit)
    }

    fn steps(&self, scenario: usize) -> usize {
        self.runner.steps(scenario)
    }

    fn layout(&self) -> &Layout {
        self.runner.layout()
    }

    fn world_metrics(&self) -> &[String] {
        &self.sys.world_metrics
    }
}

/// Run `unit` of a recorded truth (K transitions) as a realisation: its quantities, no
/// inputs and no measurements (a recorded world's filters are outside ones, replayed from
/// their rows). A run the table leaves out is all NaN: its estimates leave it out too (the
/// reading refuses estimates of a run without truth), so it is scored as missing.
fn recorded_run<const NQ: usize, const NU: usize, const NZ: usize>(
    truth: &crate::exchange::recorded::RecordedTable,
    unit: &Unit,
    n_scales: usize,
    steps: usize,
    scenario: usize,
) -> Realisation<NQ, NU, NZ> {
    let cell = unit.scenario * n_scales + unit.scale;
    let quantities = match truth.run(cell, unit.run) {
        Some(run) => (0..=steps)
            .map(|k| Vector::<NQ>::from_column_slice(&run.values[k * run.width..][..NQ]))
            .collect(),
        None => vec![Vector::<NQ>::from_element(f64::NAN); steps + 1],
    };
    Realisation {
        truth: quantities,
        inputs: vec![Vector::<NU>::zeros(); steps + 1],
        measurements: vec![
            Measurement {
                z: Vector::<NZ>::zeros(),
                available: crate::model::Availability(0),
            };
            steps + 1
        ],
        world: Vec::new(),
        prior_draws: Vec::new(),
        scenario,
        metrics: Vec::new(),
    }
}

/// A filter of its own model on a world: the model, the filter, the evaluation that maps its
/// state onto the quantities, and the prior it forms from each realisation. It is the
/// [`WorldFilter`] most entries prepare.
pub struct ModelFilter<const NX: usize, M, F, E, P> {
    /// The filter's model.
    pub model: M,
    /// The filter.
    pub filter: F,
    /// Its state → the evaluated quantities.
    pub eval: E,
    /// x̂_0 and P_0 from a realisation (e.g. the first GPS fix, or the truth plus
    /// [`Realisation::prior_draws`]).
    pub prior: P,
}

impl<const NX: usize, const NQ: usize, const NU: usize, const NZ: usize, M, F, E, P>
    WorldFilter<NQ, NU, NZ> for ModelFilter<NX, M, F, E, P>
where
    M: crate::model::Model<NX, NU, NZ>,
    F: crate::filter::Filter<NX, NU, NZ, M> + Send,
    E: crate::step_loop::Evaluate<NX, NQ> + Send,
    P: Fn(&Realisation<NQ, NU, NZ>) -> (Vector<NX>, crate::linalg::Matrix<NX, NX>) + Send + Sync,
{
    fn run(
        &self,
        realisation: &Realisation<NQ, NU, NZ>,
        ctx: &RunContext<'_, NQ, NU, NZ>,
    ) -> FilterOutput {
        let (x0_hat, p0) = (self.prior)(realisation);
        crate::step_loop::run_filter(
            &self.model,
            &self.filter,
            &self.eval,
            &crate::step_loop::Prior {
                x0_hat: &x0_hat,
                p0: &p0,
            },
            ctx,
        )
    }
}
