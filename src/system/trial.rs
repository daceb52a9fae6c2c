//! One Monte Carlo run as the executor sees it: the object-safe [`Trial`] a
//! [`super::SystemPlan`] builds. Dynamic dispatch happens once per run, never per step.
//!
//! The two kits' trials (additive and world) run a unit the same way: derive the run's seed
//! and cell, simulate, run every filter variant on the one simulation (paired comparison),
//! replay the external ones, and assemble the trace. That is `UnitRunner::run`, written
//! once; a kit says only what differs through `TrialKit`: how a run is simulated, how a
//! variant's filter is built and run, and on which model external rows are replayed.

use std::sync::OnceLock;

use super::settings::{FilterNoiseMode, FilterPlan, RunSettings};
use super::{Layout, ScenarioInfo};
use crate::linalg::Vector;
use crate::model::{Measurement, Model};
use crate::step_loop::{
    ConsistencyOptions, FilterOutput, Prior, RunContext, RunTrace, Unit, UnitResult, lower_triangle,
};

/// A study that can execute units: what a [`crate::system::SystemPlan`] builds.
pub trait Trial: Sync {
    /// Runs one unit.
    fn run(&self, unit: &Unit) -> UnitResult;
    /// Runs a group of consecutive units of one cell (same scenario and noise scale, runs in
    /// order), one result per unit in the same order; each must equal [`Trial::run`]'s, bit
    /// for bit. The default runs them one by one, so a trial that shares nothing across runs
    /// needs nothing here.
    fn run_group(&self, units: &[Unit]) -> Vec<UnitResult> {
        units.iter().map(|u| self.run(u)).collect()
    }
    /// Up to how many units the executor hands [`Trial::run_group`] at once: 1 (the
    /// default) for a trial that runs units one by one.
    fn lanes(&self) -> usize {
        1
    }
    /// Number of transitions K of a plan scenario.
    fn steps(&self, scenario: usize) -> usize;
    /// Column names.
    fn layout(&self) -> &Layout;
    /// Names of the per-run numbers a world reports about its own sensors
    /// ([`UnitResult::world_metrics`]), summarised per cell in the `sensors` table; none by
    /// default.
    fn world_metrics(&self) -> &[String] {
        &[]
    }
}

/// The cell of a unit as its simulation and filters see it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) struct Cell {
    /// Index of the system's scenario (not the plan's).
    pub scenario: usize,
    /// The truth-noise multiplier.
    pub noise_scale: f64,
    /// The multiplier of the filters' assumed standard deviations: 1 (`nominal`) or the
    /// truth's (`matched`).
    pub filter_scale: f64,
}

/// One simulated run as its filters and its trace read it.
pub(super) struct Simulated<'r, const NQ: usize, const NU: usize, const NZ: usize> {
    /// The true evaluated quantities q_0..q_K.
    pub truth: &'r [Vector<NQ>],
    /// The filters' inputs u_0..u_K.
    pub inputs: &'r [Vector<NU>],
    /// z_0..z_K with their availability.
    pub measurements: &'r [Measurement<NZ>],
    /// The world's own states, row-major per step (empty when it has none).
    pub world: &'r [f64],
    /// The prior every filter of the run starts from, when the kit forms one for all of them
    /// (it is traced to `initial.parquet`).
    pub prior: Option<Prior<'r, NQ>>,
}

/// What a kit's trial does for [`UnitRunner::run`]: everything that differs between kits.
pub(super) trait TrialKit<const NQ: usize, const NU: usize, const NZ: usize> {
    /// A variant's filter, prepared once per cell.
    type Filter: ?Sized;
    /// What one simulation produces and the filters run on.
    type Run;
    /// The model external filters' rows are replayed on.
    type ReplayModel: Model<NQ, NU, NZ>;

    /// Simulates run `unit` (of `cell`) with this seed.
    fn simulate(&self, cell: &Cell, unit: &Unit, seed: u64) -> Self::Run;
    /// The run as the filters and the trace read it.
    fn view<'r>(&'r self, run: &'r Self::Run) -> Simulated<'r, NQ, NU, NZ>;
    /// Builds a variant's filter for a cell.
    fn prepare(&self, variant: &FilterPlan, cell: &Cell) -> Box<Self::Filter>;
    /// Runs a prepared filter on a run.
    fn run_filter(
        &self,
        filter: &Self::Filter,
        run: &Self::Run,
        ctx: &RunContext<'_, NQ, NU, NZ>,
    ) -> FilterOutput;
    /// Runs a prepared filter on a group of runs of one cell, one output per run in order;
    /// each must equal [`TrialKit::run_filter`]'s. The default runs them one by one.
    fn run_filter_group(
        &self,
        filter: &Self::Filter,
        runs: &[&Self::Run],
        ctxs: &[RunContext<'_, NQ, NU, NZ>],
    ) -> Vec<FilterOutput> {
        runs.iter()
            .zip(ctxs)
            .map(|(run, ctx)| self.run_filter(filter, run, ctx))
            .collect()
    }
    /// The model of [`TrialKit::ReplayModel`].
    fn replay_model(&self) -> &Self::ReplayModel;
    /// The world's per-run metrics of a run ([`UnitResult::world_metrics`]).
    fn world_metrics(&self, run: Self::Run) -> Vec<f64>;
}

/// What every kit's trial keeps of a study for its units: the settings, the quantities'
/// names, angles and rotations, the consistency options, and the prepared filter of each
/// cell (variant × noise scale), built on first use.
pub(super) struct UnitRunner<'a, F: ?Sized> {
    pub(super) settings: &'a RunSettings,
    layout: &'a Layout,
    scenarios: &'a [ScenarioInfo],
    names: Vec<&'a str>,
    /// The angle quantities (index, in degrees), whose errors are wrapped.
    angles: Vec<(usize, bool)>,
    /// The rotations among the quantities, scored by their rotation error.
    rotations: Vec<crate::linalg::so3::EulerRotation>,
    /// What the consistency tests need of every run (the same for all of them).
    consistency: Option<ConsistencyOptions>,
    prepared: Vec<OnceLock<Box<F>>>,
}

impl<'a, F: ?Sized> UnitRunner<'a, F> {
    /// The runner of a system's `layout` and `scenarios` for a study's settings.
    pub(super) fn new(
        layout: &'a Layout,
        scenarios: &'a [ScenarioInfo],
        settings: &'a RunSettings,
    ) -> Self {
        UnitRunner {
            names: layout.quantity_names(),
            angles: layout.angles(),
            rotations: layout.rotations(),
            consistency: settings.consistency_options(layout),
            prepared: (0..settings.filters.len() * settings.noise_scales.len())
                .map(|_| OnceLock::new())
                .collect(),
            settings,
            layout,
            scenarios,
        }
    }

    /// The layout ([`Trial::layout`]).
    pub(super) fn layout(&self) -> &'a Layout {
        self.layout
    }

    /// K of plan scenario `scenario` ([`Trial::steps`]).
    pub(super) fn steps(&self, scenario: usize) -> usize {
        self.scenarios[self.settings.scenarios[scenario].index].steps
    }

    /// The context of a unit's filter runs on a simulated run, as a study runs them.
    pub(super) fn context<'r, const NQ: usize, const NU: usize, const NZ: usize>(
        &'r self,
        unit: &Unit,
        sim: &Simulated<'r, NQ, NU, NZ>,
    ) -> RunContext<'r, NQ, NU, NZ> {
        let settings = self.settings;
        RunContext {
            truth: sim.truth,
            inputs: sim.inputs,
            measurements: sim.measurements,
            angles: &self.angles,
            rotations: &self.rotations,
            thresholds: settings.rmse_thresholds.as_deref(),
            quantity_names: &self.names,
            trace: unit.run < settings.trace_runs,
            export: settings.export_estimates,
            consistency: self.consistency,
            unit: *unit,
        }
    }

    /// The cell of a unit and the unit's seed.
    fn cell_and_seed(&self, unit: &Unit) -> (Cell, u64) {
        let settings = self.settings;
        let si = settings.scenarios[unit.scenario].index;
        let noise_scale = settings.noise_scales[unit.scale];
        let cell = Cell {
            scenario: si,
            noise_scale,
            filter_scale: match settings.filter_noise {
                FilterNoiseMode::Nominal => 1.0,
                FilterNoiseMode::Matched => noise_scale,
            },
        };
        let seed = settings.run_seed(&self.scenarios[si].name, unit.scale, unit.run);
        (cell, seed)
    }

    /// The world's part of a traced or exported run's trace (`None` for other runs).
    fn world_trace<const NQ: usize, const NU: usize, const NZ: usize>(
        sim: &Simulated<'_, NQ, NU, NZ>,
        ctx: &RunContext<'_, NQ, NU, NZ>,
    ) -> Option<RunTrace> {
        (ctx.trace || ctx.export).then(|| {
            let mut t =
                RunTrace::of_world(sim.inputs, sim.truth, sim.measurements, sim.world.to_vec());
            t.initial = sim
                .prior
                .map(|p| (p.x0_hat.as_slice().to_vec(), lower_triangle(p.p0)));
            t
        })
    }

    /// Runs a group of consecutive units of one cell ([`Trial::run_group`]): simulates each
    /// once, then runs every filter variant on the whole group in plan order (a prepared
    /// filter may share work across its runs, [`TrialKit::run_filter_group`]), and assembles
    /// each unit's result exactly as [`UnitRunner::run`] does.
    pub(super) fn run_group<K, const NQ: usize, const NU: usize, const NZ: usize>(
        &self,
        kit: &K,
        units: &[Unit],
    ) -> Vec<UnitResult>
    where
        K: TrialKit<NQ, NU, NZ, Filter = F>,
    {
        if units.len() < 2 {
            return units.iter().map(|u| self.run(kit, u)).collect();
        }
        let settings = self.settings;
        let (cell, _) = self.cell_and_seed(&units[0]);
        let seeds: Vec<u64> = units.iter().map(|u| self.cell_and_seed(u).1).collect();
        let runs: Vec<K::Run> = units
            .iter()
            .zip(&seeds)
            .map(|(u, &seed)| kit.simulate(&cell, u, seed))
            .collect();
        let per_unit: Vec<(Option<RunTrace>, Vec<crate::metrics::FilterRun>)> = {
            let sims: Vec<_> = runs.iter().map(|r| kit.view(r)).collect();
            let ctxs: Vec<_> = units
                .iter()
                .zip(&sims)
                .map(|(u, sim)| self.context(u, sim))
                .collect();
            let mut traces: Vec<Option<RunTrace>> = sims
                .iter()
                .zip(&ctxs)
                .map(|(sim, ctx)| Self::world_trace(sim, ctx))
                .collect();
            let mut filters: Vec<Vec<_>> = units
                .iter()
                .map(|_| Vec::with_capacity(settings.filters.len()))
                .collect();
            let run_refs: Vec<&K::Run> = runs.iter().collect();
            for (fi, f) in settings.filters.iter().enumerate() {
                let outs: Vec<FilterOutput> = if f.external {
                    ctxs.iter()
                        .map(|ctx| {
                            crate::score::replay(
                                settings.estimates.as_deref(),
                                fi,
                                &f.label,
                                kit.replay_model(),
                                ctx,
                            )
                        })
                        .collect()
                } else {
                    let slot = &self.prepared[fi * settings.noise_scales.len() + units[0].scale];
                    let filter = slot.get_or_init(|| kit.prepare(f, &cell));
                    kit.run_filter_group(filter, &run_refs, &ctxs)
                };
                for ((mut out, trace), runs) in outs.into_iter().zip(&mut traces).zip(&mut filters)
                {
                    if let Some(t) = trace.as_mut() {
                        t.push_filter(&mut out, NQ);
                    }
                    runs.push(out.run);
                }
            }
            traces.into_iter().zip(filters).collect()
        };
        runs.into_iter()
            .zip(per_unit)
            .zip(units.iter().zip(seeds))
            .map(|((run, (trace, filters)), (unit, seed))| UnitResult {
                unit: *unit,
                seed,
                filters,
                trace,
                world_metrics: kit.world_metrics(run),
            })
            .collect()
    }

    /// Runs one unit ([`Trial::run`]): simulates it once through `kit`, runs every filter
    /// variant of the plan on it in plan order (external ones replayed from their rows), and
    /// keeps the trace of a traced or exported run.
    pub(super) fn run<K, const NQ: usize, const NU: usize, const NZ: usize>(
        &self,
        kit: &K,
        unit: &Unit,
    ) -> UnitResult
    where
        K: TrialKit<NQ, NU, NZ, Filter = F>,
    {
        let settings = self.settings;
        let (cell, seed) = self.cell_and_seed(unit);
        let run = kit.simulate(&cell, unit, seed);
        let sim = kit.view(&run);
        let ctx = self.context(unit, &sim);
        let mut trace = Self::world_trace(&sim, &ctx);
        let mut filters = Vec::with_capacity(settings.filters.len());
        for (fi, f) in settings.filters.iter().enumerate() {
            let mut out = if f.external {
                crate::score::replay(
                    settings.estimates.as_deref(),
                    fi,
                    &f.label,
                    kit.replay_model(),
                    &ctx,
                )
            } else {
                let slot = &self.prepared[fi * settings.noise_scales.len() + unit.scale];
                let filter = slot.get_or_init(|| kit.prepare(f, &cell));
                kit.run_filter(filter, &run, &ctx)
            };
            if let Some(t) = trace.as_mut() {
                t.push_filter(&mut out, NQ);
            }
            filters.push(out.run);
        }
        UnitResult {
            unit: *unit,
            seed,
            filters,
            trace,
            world_metrics: kit.world_metrics(run),
        }
    }
}
