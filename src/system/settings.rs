//! What a system's trial needs of a study: [`RunSettings`].
//!
//! The experiment layer validates a spec into a `Plan`, which holds these settings beside what
//! only the commands need (the output folder, the assertions, the spec text). A system sees
//! only the settings, so the plugin API does not depend on how a spec is read.

use std::sync::Arc;

use crate::metrics::blocks::BlockMasks;
use crate::score::EstimateSet;
use crate::step_loop::ConsistencyOptions;

use super::Layout;

/// A validated scenario.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ScenarioPlan {
    /// Name (the `scenario` column; it also selects the run seeds).
    pub name: String,
    /// Transitions K.
    pub steps: usize,
    /// Index into the system's scenarios ([`super::SystemPlan::scenarios`]).
    pub index: usize,
}

/// A validated filter variant: one (entry, q_scale, r_scale) of the spec's filters.
#[derive(Clone, Debug, PartialEq)]
pub struct FilterPlan {
    /// Label (the `filter` column).
    pub label: String,
    /// The kind tag.
    pub kind: String,
    /// Index into the system's filter entries ([`super::SystemPlan::filters`]); unused for an
    /// external filter.
    pub entry: usize,
    /// Whether the filter is outside kfmc (`kind = "external"`): its estimates come from a
    /// file (`kfmc score`, `kfmc check --estimates`), not from a system's filter kind.
    pub external: bool,
    /// Multiplier of the assumed Q (the `q_scale` column).
    pub q_scale: f64,
    /// Multiplier of the assumed R (the `r_scale` column).
    pub r_scale: f64,
    /// Which multipliers the spec entry lists (`q_scale`, `r_scale`). An external filter
    /// that lists either has variants: the tables key them by their multipliers as kfmc's
    /// own (1 on an axis it does not list), and its estimates carry a column for each axis
    /// it lists, naming each row's variant.
    pub declared: DeclaredScales,
}

/// Which of `q_scale` and `r_scale` a `[[filters]]` entry lists.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct DeclaredScales {
    /// The entry lists `q_scale`.
    pub q_scale: bool,
    /// The entry lists `r_scale`.
    pub r_scale: bool,
}

impl DeclaredScales {
    /// Whether the entry lists either.
    pub fn any(self) -> bool {
        self.q_scale || self.r_scale
    }
}

impl FilterPlan {
    /// The variant's (q_scale, r_scale) as the tables key it: `None` for an external filter
    /// that declares no variants (its tuning is its own, and the tables' scales are null).
    pub fn multipliers(&self) -> Option<(f64, f64)> {
        (!self.external || self.declared.any()).then_some((self.q_scale, self.r_scale))
    }
}

/// The validated `[consistency]` section.
#[derive(Clone, Debug, PartialEq)]
pub struct ConsistencyPlan {
    /// Significance level of every test.
    pub alpha: f64,
    /// Whiteness lags 1..=L.
    pub whiteness_lags: usize,
    /// Steps 1..=B whose innovations are left out of the whiteness sums
    /// (`consistency.whiteness_burn_in`): the transient of a prior that does not scale with
    /// the noise is correlated in time even when the gain is right.
    pub whiteness_burn_in: usize,
    /// Extra (runs, α) evaluations of the same tests on the first `runs` runs of each cell.
    pub subsets: Vec<(usize, f64)>,
}

impl ConsistencyPlan {
    /// The whiteness lags of a spec that does not set `consistency.whiteness_lags`.
    pub const DEFAULT_WHITENESS_LAGS: usize = 5;

    /// The tests at level `alpha` with the default lags and no subsets: what a spec without
    /// `[consistency]` gets when a command needs the tests (`check`'s consistency
    /// assertions, `power`).
    pub fn at_level(alpha: f64) -> Self {
        Self {
            alpha,
            whiteness_lags: Self::DEFAULT_WHITENESS_LAGS,
            whiteness_burn_in: 0,
            subsets: Vec::new(),
        }
    }
}

/// What the filters assume when the truth noise is scaled.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FilterNoiseMode {
    /// Filters keep their Q/R (the seeds' robustness study).
    Nominal,
    /// Filters' assumed std scale with the truth's.
    Matched,
}

/// How x̂_0 is formed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum InitialMode {
    /// x̂_0 = x_0 (the seeds).
    Truth,
    /// x̂_0 ~ N(x_0, P_0), drawn once per run and shared by all filters.
    Sampled,
    /// x̂_0 and P_0 from the run's own measurements by the system's initialiser (batch least
    /// squares on linear models with an observable sensor set).
    BatchLs,
}

/// How a run's random numbers relate across the noise multipliers (`[noise] draws`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Draws {
    /// A run sees the same standard normals at every multiplier (common random numbers):
    /// smooth, paired curves, and a run's divergence point is where its own errors, scaled,
    /// cross the threshold.
    Common,
    /// Every (run, multiplier) has its own streams, as `robustness.m` draws fresh noise at
    /// each multiplier: a run's first crossing is the first of many independent chances.
    Fresh,
}

/// What a trial needs of a study: the cells (scenarios × noise multipliers), the filter
/// variants, the seeds and what each run records. [`super::SystemPlan::trial`] and
/// [`super::SystemPlan::describe`] take it; a system's scenarios and filter entries are
/// indexed by [`ScenarioPlan::index`] and [`FilterPlan::entry`].
#[derive(Clone, Debug)]
pub struct RunSettings {
    /// Scenarios.
    pub scenarios: Vec<ScenarioPlan>,
    /// Filter variants.
    pub filters: Vec<FilterPlan>,
    /// Truth-noise multipliers, ascending.
    pub noise_scales: Vec<f64>,
    /// Filter noise mode.
    pub filter_noise: FilterNoiseMode,
    /// Initial-estimate mode.
    pub initial: InitialMode,
    /// Runs per cell.
    pub runs: usize,
    /// Master seed.
    pub master_seed: u64,
    /// How the runs' random numbers relate across noise multipliers (`noise.draws`).
    pub draws: Draws,
    /// Traced runs per (scenario, noise scale).
    pub trace_runs: usize,
    /// RMSE divergence thresholds per evaluated quantity.
    pub rmse_thresholds: Option<Vec<f64>>,
    /// Consistency tests, when the spec asks for them.
    pub consistency: Option<ConsistencyPlan>,
    /// Whether to write every run's estimates in the exchange format (`estimates.parquet`,
    /// `kfmc run --export-estimates`).
    pub export_estimates: bool,
    /// The precision of the exported covariance, innovation, S and A columns
    /// (`--export-estimates-precision`; the estimates themselves stay float64).
    pub export_precision: crate::score::EstimatePrecision,
    /// The estimates of the external filters, once read (`kfmc score`, `kfmc check
    /// --estimates`).
    pub estimates: Option<Arc<EstimateSet>>,
    /// The truth of a system that cannot simulate ([`super::SystemPlan::recorded`]), read from
    /// a user's table (`kfmc score --truth`); its runs stand in for simulated ones.
    pub truth: Option<Arc<crate::exchange::recorded::RecordedTable>>,
    /// Whether runs of a cell are handed to the trial in groups (`--lanes`, `KFMC_LANES`):
    /// never a result, only the path that computes it.
    pub lanes: crate::runner::lanes::LanesMode,
}

impl RunSettings {
    /// The seed of run `run` of scenario `scenario` at noise multiplier index `scale`: every
    /// random stream of that run derives from it.
    pub fn run_seed(&self, scenario: &str, scale: usize, run: usize) -> u64 {
        let common = crate::sim::seed::run_seed(self.master_seed, scenario, run as u64);
        match self.draws {
            Draws::Common => common,
            Draws::Fresh => crate::sim::seed::mix64(
                common ^ crate::sim::seed::mix64(0x6672_6573_6800_0000 ^ scale as u64),
            ),
        }
    }

    /// What the consistency tests need computed during a run (`None` without a
    /// `[consistency]` section).
    pub fn consistency_options(&self, layout: &Layout) -> Option<ConsistencyOptions> {
        self.consistency
            .as_ref()
            .map(|c| self.consistency_options_with_lags(layout, c.whiteness_lags))
    }

    /// [`RunSettings::consistency_options`] with `lags` whiteness lags, whether or not the
    /// spec asks for the tests (`kfmc describe` calibrates them on a clean run either way).
    pub fn consistency_options_with_lags(
        &self,
        layout: &Layout,
        lags: usize,
    ) -> ConsistencyOptions {
        ConsistencyOptions {
            lags,
            whiteness_burn_in: self.consistency.as_ref().map_or(0, |c| c.whiteness_burn_in),
            burn_in: self.initial != InitialMode::Sampled,
            initial_nees: self.initial == InitialMode::BatchLs,
            blocks: block_masks(layout),
        }
    }
}

/// The block masks of a layout's quantities ([`crate::metrics::blocks::group`]).
pub fn block_masks(layout: &Layout) -> BlockMasks {
    BlockMasks::new(&layout_blocks(layout), layout.quantities.len())
}

/// The blocks of a layout's quantities ([`crate::metrics::blocks::group`]).
pub fn layout_blocks(layout: &Layout) -> Vec<crate::metrics::blocks::QuantityBlock> {
    // A rotation's three quantities form an attitude block as three angles do.
    crate::metrics::blocks::group(
        layout
            .quantities
            .iter()
            .map(|q| (q.unit.as_str(), q.angle || q.rotation.is_some())),
    )
}
