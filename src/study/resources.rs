//! What a plan will take before it runs (memory, disk, scratch, filter steps), and the
//! result sizes that set the executor's window.

use crate::error::SpecErrors;
use crate::experiment::Plan;
use crate::system::limits;

/// About the bytes a run's result holds when it keeps its trajectories for every filter of
/// `plan` (the longest scenario's truth, z, u and world states, and per filter the estimate,
/// P's lower triangle, ν, S and A per step), for [`crate::runner::window_for`].
/// Bytes of one run's per-step values kept for the credibility measures (signed errors and
/// block NEES of every filter; [`crate::metrics::StepValues::enable_credibility`]); 0 without
/// `[consistency]`.
pub(super) fn credibility_bytes(plan: &Plan) -> u64 {
    if plan.consistency.is_none() {
        return 0;
    }
    let l = plan.layout();
    let per_step = (l.quantities.len() + crate::trial::layout_blocks(l).len()) as u64;
    let samples = plan
        .scenarios
        .iter()
        .map(|s| s.steps as u64 + 1)
        .max()
        .unwrap_or(1);
    samples * 8 * per_step * plan.filters.len() as u64
}

/// Bytes of one unit's result that set the executor's window ([`crate::runner::window_for`]):
/// an exported run's whole trajectory, and with the consistency tests each filter's signed
/// errors and block NEES per step. The executor and the estimate both read it, so the window
/// the estimate assumes is the one the study runs with.
pub(crate) fn window_unit_bytes(plan: &Plan) -> u64 {
    if plan.export_estimates {
        trajectory_bytes(plan)
    } else {
        0
    }
    .saturating_add(credibility_bytes(plan))
}

pub(crate) fn trajectory_bytes(plan: &Plan) -> u64 {
    let l = plan.layout();
    let (nq, nz) = (l.quantities.len() as u64, l.measurements.len() as u64);
    let world = nq + nz + l.inputs.len() as u64 + l.world_state_names().len() as u64;
    let filter = nq + nq * (nq + 1) / 2 + nz + nz * (nz + 1) / 2 + nq * nq;
    let samples = plan
        .scenarios
        .iter()
        .map(|s| s.steps as u64 + 1)
        .max()
        .unwrap_or(1);
    samples * 8 * (world + plan.filters.len() as u64 * filter)
}

/// World metrics assumed per run by the estimate (systems declare a handful at most); their
/// spill is a small part of the total either way.
const WORLD_METRICS_ESTIMATE: u128 = 16;

/// What a plan will take, estimated in exact (128-bit) arithmetic before it runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Resources {
    /// Simulated runs (cells × runs per cell).
    pub runs: u128,
    /// Filter steps in total.
    pub filter_steps: u128,
    /// Peak memory of the executor and the per-cell folding, bytes (an upper estimate).
    pub memory_bytes: u128,
    /// Uncompressed size of the tables, bytes (an upper estimate of the disk they take).
    pub disk_bytes: u128,
    /// Largest scratch file space alive at once, bytes: one cell's per-run values beyond what
    /// is kept in memory (see [`crate::metrics::spill`]), freed when the cell is summarised, and the
    /// divergence trackers' per-run crossings, freed when the tables are written.
    pub scratch_bytes: u128,
}

fn human_bytes(b: u128) -> String {
    let units = ["B", "KiB", "MiB", "GiB", "TiB", "PiB", "EiB"];
    let mut v = b as f64;
    let mut i = 0;
    while v >= 1024.0 && i + 1 < units.len() {
        v /= 1024.0;
        i += 1;
    }
    format!("{v:.1} {}", units[i])
}

impl Resources {
    /// One line for `validate`.
    pub fn describe(&self) -> String {
        format!(
            "estimated peak memory {}, tables up to {} uncompressed (and as much again for the checkpoint of `kfmc run` while it runs), scratch up to {}, {} filter steps",
            human_bytes(self.memory_bytes),
            human_bytes(self.disk_bytes),
            human_bytes(self.scratch_bytes),
            self.filter_steps
        )
    }
}

/// The resources `plan` will take (see [`Resources`]).
pub fn resources(plan: &Plan) -> Resources {
    let l = plan.layout();
    let (nq, nz, nu) = (
        l.quantities.len() as u128,
        l.measurements.len() as u128,
        l.inputs.len() as u128 + l.world_states.len() as u128,
    );
    let nf = plan.filters.len() as u128;
    let scales = plan.noise_scales.len() as u128;
    let runs = plan.runs as u128;
    let samples: Vec<u128> = plan.scenarios.iter().map(|s| s.steps as u128 + 1).collect();
    let max_k = samples.iter().copied().max().unwrap_or(1);
    let sum_k: u128 = samples.iter().sum();
    let cells = plan.scenarios.len() as u128 * scales;
    // Per unit in flight: every filter's per-step values (squared errors, NEES, NIS) plus
    // the simulated run, and what sets the window (an exported trajectory, the credibility
    // values); up to three windows are alive at once (being run, queued, being folded), each
    // of the size the executor will choose for this plan on this machine.
    let unit = nf * max_k * (8 * nq + 17) + max_k * 8 * (2 * nq + nz + nu);
    let traced = (plan.trace_runs > 0) as u128 * nf * max_k * 8 * (nq * (nq + 3) / 2);
    let window_unit = window_unit_bytes(plan);
    let window = crate::runner::window_for(window_unit, 0) as u128;
    let executor = 3 * window * (unit + traced + window_unit as u128);
    // Per cell being folded: per-step sums and the |e| sketches per filter; the per-run
    // RMSE and world metrics in spills (at most SPILL_ROWS rows in memory each, the rest
    // in scratch files) and the selection's counts and candidates while summarising.
    let spill_rows = crate::metrics::spill::SPILL_ROWS as u128;
    let spilled_cols = nf * nq + WORLD_METRICS_ESTIMATE;
    let select =
        nq.max(WORLD_METRICS_ESTIMATE) * 6 * (8 << crate::metrics::spill::DIGIT_BITS as u128)
            + 6 * nq.max(WORLD_METRICS_ESTIMATE) * 8 * crate::metrics::spill::COLLECT_CAP as u128;
    // The |e| values kept for exact quantiles: 8 bytes per (run, grid point, quantity,
    // filter), up to the budget.
    let grid = crate::metrics::abs_err_grid_points(max_k as usize) as u128;
    let exact_values = (runs * nf * grid * nq * 8)
        .min(crate::metrics::ABS_ERR_EXACT_BYTES as u128 + nf * grid * nq * 8 * 32);
    let cell = nf * max_k * (8 * nq + 48)
        + nf * max_k.div_ceil(5) * nq * 320
        + exact_values
        + spill_rows.min(runs) * 8 * spilled_cols
        + select;
    // Only when asked for, and bounded like the spills: per filter, the consistency tests'
    // per-run rows (NEES average and a normalised error per state; the sums of each
    // evaluation are a few hundred bytes); per (scenario, filter), a divergence tracker's
    // crossings in memory, the previous scale's being read while the current is written.
    let consistency_cols = 1 + nq;
    let consistency = plan.consistency.as_ref().map_or(0, |c| {
        nf * (spill_rows.min(runs) * 8 * consistency_cols
            + (1 + c.subsets.len() as u128) * (256 + 16 * c.whiteness_lags as u128 + 16 * nq))
    });
    let trackers = plan
        .rmse_thresholds
        .as_ref()
        .map_or(0, |_| plan.scenarios.len() as u128 * nf);
    let tracker_rows = crate::metrics::divergence::TRACKER_ROWS as u128;
    let io_buffer = crate::metrics::spill::IO_BUFFER as u128;
    // …and, while the divergence tables are written, one state's values for the quantiles.
    let divergence = trackers * 2 * (tracker_rows.min(runs) * 8 * nq + io_buffer)
        + (trackers > 0) as u128 * spill_rows.min(runs) * 8;
    let row = |cols: u128| cols * 8 + 32;
    // The tables' row buffers: one row group each (runs, steps, summary, traces).
    let writers = crate::output::FLUSH_ROWS as u128
        * (row(nq + 12)
            + row(3 * nq + 16)
            + row(12)
            + (plan.trace_runs > 0) as u128 * row(nq * (nq + 5) / 2 + nz + nu + 8)
            + plan.per_step_runs as u128 * row(11));
    // The scratch files alive at once: one cell's spills beyond their buffers, and every
    // tracker's crossings (current and previous scale) until the tables are written.
    let scratch = runs.saturating_sub(spill_rows)
        * 8
        * (spilled_cols + plan.consistency.is_some() as u128 * nf * consistency_cols)
        + trackers * 2 * runs.saturating_sub(tracker_rows) * 8 * nq;
    let disk = cells * nf * runs * row(nq + 12)
        + cells * nf * max_k * row(3 * nq + 16)
        + cells * nf * 64 * row(12)
        + (plan.trace_runs as u128) * scales * nf * sum_k * row(nq * (nq + 5) / 2 + nz + nu + 8)
        + plan.per_step_runs as u128 * scales * runs * nf * sum_k * row(11);
    Resources {
        runs: cells * runs,
        filter_steps: sum_k.saturating_sub(plan.scenarios.len() as u128) * scales * runs * nf,
        // The checkpoint's write buffers: one per journaled table, at most seven.
        memory_bytes: (64 << 20)
            + 7 * crate::output::checkpoint::JOURNAL_BUFFER_BYTES as u128
            + executor
            + writers
            + cell
            + consistency
            + divergence,
        disk_bytes: disk,
        scratch_bytes: scratch,
    }
}

/// Refuses a plan beyond the documented [`limits`], with the estimate in the message;
/// `allow_large` lifts the resource caps.
pub fn check_limits(plan: &Plan, allow_large: bool) -> Result<(), SpecErrors> {
    let r = resources(plan);
    let mut errs = Vec::new();
    if (plan.runs as u64) > limits::MAX_RUNS {
        errs.push(plan.err(
            "runs",
            format!("{} runs per cell; at most {}", plan.runs, limits::MAX_RUNS),
        ));
    }
    if !allow_large {
        let over = [
            (r.memory_bytes > limits::MAX_MEMORY_BYTES).then(|| {
                format!(
                    "needs about {} of memory (limit {})",
                    human_bytes(r.memory_bytes),
                    human_bytes(limits::MAX_MEMORY_BYTES)
                )
            }),
            (r.disk_bytes + r.scratch_bytes > limits::MAX_DISK_BYTES).then(|| {
                format!(
                    "writes up to {} of tables and {} of scratch files (limit {} together)",
                    human_bytes(r.disk_bytes),
                    human_bytes(r.scratch_bytes),
                    human_bytes(limits::MAX_DISK_BYTES)
                )
            }),
            (r.filter_steps > limits::MAX_FILTER_STEPS).then(|| {
                format!(
                    "{} filter steps (limit {})",
                    r.filter_steps,
                    limits::MAX_FILTER_STEPS
                )
            }),
        ];
        for msg in over.into_iter().flatten() {
            errs.push(plan.err(
                "(plan)",
                format!(
                    "this plan ({} runs) {msg}; reduce runs, scenarios, noise scales, trace_runs or filters, or pass --allow-large",
                    r.runs
                ),
            ));
        }
    }
    if errs.is_empty() {
        Ok(())
    } else {
        Err(SpecErrors(errs))
    }
}

/// Whether `replications` whole studies of `plan` (`kfmc power`, `kfmc check
/// --replications`) stay within the filter-step limit together: the limit bounds a
/// command's work, not one replication's.
pub fn check_replications(
    plan: &Plan,
    replications: usize,
    allow_large: bool,
) -> Result<(), SpecErrors> {
    let steps = resources(plan)
        .filter_steps
        .saturating_mul(replications as u128);
    if allow_large || steps <= limits::MAX_FILTER_STEPS {
        return Ok(());
    }
    Err(SpecErrors(vec![plan.err(
        "--replications",
        format!(
            "{replications} replications of this plan take {steps} filter steps (limit {}); use fewer replications or runs, or pass --allow-large",
            limits::MAX_FILTER_STEPS
        ),
    )]))
}
