//! A whole study: plan → units → executor → in-order folding into the tables → manifest.
//!
//! The files, by role, each importing only those listed before it: [`options`] (what an
//! execution may vary without changing its results), `rows` (the key columns of a cell's
//! rows), [`mod@resources`] (what a plan will take, checked before it runs, and the result sizes
//! that set the executor's window), `resume` (the checkpoint), `fold` (units into the
//! tables, cell by cell), `divergence` (the divergence trackers and tables), `manifest`, and
//! this file, which runs the executor over a folder.

mod divergence;
mod fold;
mod manifest;
pub mod options;
pub mod resources;
mod resume;
mod rows;

pub(crate) use divergence::{DivergenceFeed, divergence_tables};
pub(crate) use manifest::manifest_for;
pub use manifest::study_kind;
pub use options::{Checkpoints, ExecOptions, ExistingCheckpoint, MAX_SHARDS, Shard, StudyReport};
pub(crate) use resources::trajectory_bytes;
pub use resources::{Resources, check_limits, check_replications, resources};

use std::time::{Instant, SystemTime, UNIX_EPOCH};

use crate::error::{KfmcError, OutputError};
use crate::experiment::Plan;
use crate::metrics::blocks::QuantityBlock;
use crate::metrics::consistency::BandCache;
use crate::output::folder::StudyFolder;
use crate::output::{TableWriter, Value, schema};
use crate::runner::{Executor, RunObserver, execute_groups, window_for};
use crate::trial::{Trial, Unit, UnitResult};

use fold::{Aggregator, EstimatesTable, SequentialState};
use resources::window_unit_bytes;
use resume::{Checkpointer, checkpoint_identity, existing_checkpoint};

/// Runs the study described by `plan`, writing its tables and manifest into `plan.output`.
pub fn run(
    plan: &Plan,
    opts: &ExecOptions,
    observer: &dyn RunObserver,
) -> Result<StudyReport, KfmcError> {
    run_locked(plan, opts, observer).map(|(report, _)| report)
}

/// [`run`], returning the folder still locked, so that a caller that reads the committed
/// tables back (`kfmc check`) reads this study's, not a later writer's.
pub fn run_locked(
    plan: &Plan,
    opts: &ExecOptions,
    observer: &dyn RunObserver,
) -> Result<(StudyReport, StudyFolder), KfmcError> {
    if plan.system.recorded() && plan.truth.is_none() {
        return Err(KfmcError::Spec(crate::error::SpecErrors(vec![
            crate::error::SpecError {
                file: plan.spec_path.clone(),
                key_path: "model.kind".into(),
                message: format!(
                    "`{}` cannot simulate: its truth is recorded. Judge its runs with `kfmc score --truth TRUTH --estimates EST --spec SPEC` (or `kfmc check SPEC --truth TRUTH --estimates EST`)",
                    plan.kind
                ),
            },
        ])));
    }
    if let Some(f) = plan.filters.iter().find(|f| f.external)
        && plan.estimates.is_none()
    {
        return Err(KfmcError::Spec(crate::error::SpecErrors(vec![
            crate::error::SpecError {
                file: plan.spec_path.clone(),
                key_path: "filters".into(),
                message: format!(
                    "`{}` is an external filter: its estimates come from a file. Run `kfmc simulate`, estimate from its tables, then `kfmc score DIR --estimates FILE` (or `kfmc check SPEC --estimates FILE`)",
                    f.label
                ),
            },
        ])));
    }
    let started = Instant::now();
    let started_unix_s = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_secs());
    let part_dir = opts.shard.map(|s| s.folder(&plan.output));
    let dir = part_dir.as_ref().unwrap_or(&plan.output);
    if opts.shard.is_some() {
        crate::output::folder::refuse_link(&plan.output.join("parts"))?;
    }
    let folder = StudyFolder::open_with(dir, study_kind(plan), opts.force, &inputs(plan))?;
    let n_cells = plan.scenarios.len() * plan.noise_scales.len();
    let session = Session {
        dir,
        folder: &folder,
        n_cells,
        cells: opts.shard.map_or(0..n_cells, |s| s.cells(n_cells)),
        started,
        started_unix_s,
    };
    let result = run_in(plan, opts, observer, session);
    if result.is_err()
        && opts.checkpoints.is_some()
        && matches!(crate::output::checkpoint::Index::read(dir), Ok(None))
    {
        // Journals that no index vouches for cannot be resumed: they only take disk (which
        // may be what ran out).
        let _ = crate::output::checkpoint::remove(dir);
    }
    result.map(|report| (report, folder))
}

/// The files a study of `plan` reads: its spec file and the estimates files attached to it.
/// None of them may lie inside the folder the study writes.
pub(crate) fn inputs(plan: &Plan) -> Vec<std::path::PathBuf> {
    let mut files: Vec<std::path::PathBuf> = plan
        .estimates
        .iter()
        .flat_map(|set| set.sources())
        .flat_map(|(_, files)| files)
        .collect();
    if plan.spec_path.is_file() {
        files.push(plan.spec_path.clone());
    }
    files
}

/// What [`run_locked`] settles before a study runs: the folder it holds, the cells this
/// process runs there (every cell, or a shard's), and when it started.
struct Session<'a> {
    /// The folder written: the study's, or its part's.
    dir: &'a std::path::Path,
    folder: &'a StudyFolder,
    /// The study's cells, of which this process runs `cells`.
    n_cells: usize,
    cells: std::ops::Range<usize>,
    started: Instant,
    /// The start as the manifest records it.
    started_unix_s: u64,
}

/// [`run`] once the folder is held.
fn run_in(
    plan: &Plan,
    opts: &ExecOptions,
    observer: &dyn RunObserver,
    session: Session<'_>,
) -> Result<StudyReport, KfmcError> {
    let Session {
        dir,
        folder,
        n_cells,
        cells,
        started,
        started_unix_s,
    } = session;
    let trial = plan.trial();
    let resume = existing_checkpoint(plan, opts, dir, n_cells, &cells)?;
    let cells_resumed = resume.as_ref().map_or(0, |i| i.cells_done as usize);
    let identity = checkpoint_identity(plan, n_cells, &cells);
    let opener = TableOpener {
        plan,
        dir,
        journaling: opts.checkpoints.is_some(),
        identity: &identity,
        resume: resume.as_ref(),
    };
    let checkpoint = opts.checkpoints.as_ref().map(|c| Checkpointer {
        dir: dir.to_path_buf(),
        every: c.every,
        last: Instant::now(),
        index: resume.clone().unwrap_or_else(|| identity.clone()),
        boundary: None,
        first_cell: cells.start,
    });
    let mut agg = open_aggregator(plan, trial.as_ref(), &opener, checkpoint)?;
    let todo = cells.start + cells_resumed..cells.end;
    execute(plan, trial.as_ref(), &mut agg, opts, observer, todo.clone())
        .map_err(|e| interrupted(e, &mut agg, dir, cells.len()))?;
    let finished = finish_tables(plan, opts, dir, agg)?;
    let wall_s = started.elapsed().as_secs_f64();
    let manifest = manifest_for(plan, opts, started_unix_s, wall_s, cells.clone());
    let tables = folder.commit(finished, manifest)?;
    // Committed: the tables are complete, and a checkpoint of them would only mislead.
    crate::output::checkpoint::remove(dir)?;
    Ok(StudyReport {
        output: dir.to_path_buf(),
        tables,
        wall_s,
        runs: (todo.len() * plan.runs) as u64,
        cells_resumed: cells_resumed as u64,
    })
}

/// Opens a study's tables: journaled when the study is resumable, and on a resume first
/// refilled from the checkpoint's journal.
struct TableOpener<'a> {
    plan: &'a Plan,
    dir: &'a std::path::Path,
    journaling: bool,
    /// The study's identity, which every journal begins with and a resumed one must name.
    identity: &'a crate::output::checkpoint::Index,
    resume: Option<&'a crate::output::checkpoint::Index>,
}

impl TableOpener<'_> {
    /// Opens table `name`; on a resume each row replayed from its journal is also shown to
    /// `on_row`.
    fn open(
        &self,
        name: &str,
        columns: Vec<crate::output::schema::ColumnDef>,
        on_row: &mut dyn FnMut(&[Value<'_>]) -> Result<(), OutputError>,
    ) -> Result<TableWriter, OutputError> {
        let (plan, dir) = (self.plan, self.dir);
        let metadata = plan.table_metadata(name);
        if !self.journaling {
            return TableWriter::create_with_metadata(dir, name, columns, &metadata);
        }
        let journal = crate::output::checkpoint::journal_path(dir, name);
        let from = match self.resume {
            None => None,
            Some(index) => Some(
                index
                    .tables
                    .iter()
                    .find(|t| t.name == name)
                    .map(|t| (t.bytes, t.rows, index.cells_done))
                    .ok_or_else(|| OutputError::Mismatch {
                        path: journal.clone(),
                        why: format!(
                            "is missing: the checkpoint has no journal of table `{name}`; start over with `kfmc run SPEC --restart`"
                        ),
                    })?,
            ),
        };
        TableWriter::journaled(
            dir,
            name,
            columns,
            &metadata,
            &journal,
            self.identity,
            from,
            on_row,
        )
    }

    /// Opens a table whose replayed rows need no other use.
    fn open_plain(
        &self,
        name: &str,
        columns: Vec<crate::output::schema::ColumnDef>,
    ) -> Result<TableWriter, OutputError> {
        self.open(name, columns, &mut |_| Ok(()))
    }
}

/// The fold over a study's tables. The divergence trackers look across cells: a resume
/// rebuilds them from the replayed runs and summary rows, as `kfmc merge` does from the
/// parts' tables.
fn open_aggregator<'a>(
    plan: &'a Plan,
    trial: &'a dyn Trial,
    opener: &TableOpener<'_>,
    checkpoint: Option<Checkpointer>,
) -> Result<Aggregator<'a>, OutputError> {
    let dir = opener.dir;
    let layout = plan.layout();
    let states = layout.quantity_names();
    let mut feed = DivergenceFeed::new(plan, dir);
    let damaged = |why: &str| OutputError::Mismatch {
        path: crate::output::checkpoint::dir(dir),
        why: format!(
            "is a damaged checkpoint: a row {why}; start over with `kfmc run SPEC --restart`"
        ),
    };
    let runs = opener.open("runs", feed.runs_columns().to_vec(), &mut |row| {
        feed.run_row(row, &damaged)
    })?;
    let summary = opener.open("summary", feed.summary_columns().to_vec(), &mut |row| {
        feed.summary_row(row, &damaged)
    })?;
    let divergence = feed.into_trackers();
    // The blocks the runs keep NEES for (none when they do not fit the runs' masks).
    let blocks =
        if plan.consistency.is_some() && !crate::system::settings::block_masks(layout).is_empty() {
            crate::trial::layout_blocks(layout)
        } else {
            Vec::new()
        };
    let block_names: Vec<String> = blocks.iter().map(QuantityBlock::column_name).collect();
    let block_names: Vec<&str> = block_names.iter().map(String::as_str).collect();
    let optional = |wanted: bool, name: &str, columns: Vec<crate::output::schema::ColumnDef>| {
        wanted.then(|| opener.open_plain(name, columns)).transpose()
    };
    Ok(Aggregator {
        plan,
        trial,
        runs,
        steps: opener.open_plain(
            "steps",
            schema::steps(&states, plan.consistency.as_ref().map(|_| &block_names[..])),
        )?,
        summary,
        run_steps: optional(plan.per_step_runs, "run_steps", schema::run_steps())?,
        traces: optional(
            plan.trace_runs > 0,
            "traces",
            schema::traces(
                &states,
                &layout.input_names(),
                &layout.measurement_names(),
                &layout.world_state_names(),
            ),
        )?,
        consistency: optional(
            plan.consistency.is_some(),
            "consistency",
            schema::consistency(Some(&block_names)),
        )?,
        sensors: optional(
            !trial.world_metrics().is_empty(),
            "sensors",
            schema::sensors(),
        )?,
        estimates: match plan.export_estimates {
            true => Some(open_estimates(plan, &states, opener)?),
            false => None,
        },
        bands: BandCache::new(plan.alpha),
        blocks,
        divergence,
        states,
        cell: None,
        scratch: dir.to_path_buf(),
        checkpoint,
        sequential: match &plan.sequential {
            Some(gate) => Some(SequentialState {
                gate,
                gating: plan
                    .filters
                    .iter()
                    .map(|f| plan.has_covariance(f))
                    .collect(),
                table: opener.open_plain("sequential", schema::sequential())?,
            }),
            None => None,
        },
    })
}

/// `estimates.parquet` of `--export-estimates`: the exchange format, with a variant column
/// for each axis on which a label's rows must name their variant ([`Plan::export_variant_keys`];
/// null in the rows of a filter that does not key that axis).
fn open_estimates(
    plan: &Plan,
    states: &[&str],
    opener: &TableOpener<'_>,
) -> Result<EstimatesTable, OutputError> {
    let layout = plan.layout();
    let keys = plan.export_variant_keys();
    let axes = [0, 1].map(|axis| keys.iter().any(|k| k[axis].is_some()));
    let columns = schema::with_variant_columns(
        crate::score::estimate_columns_in(
            states,
            &layout.measurement_names(),
            &layout.rotations(),
            plan.export_precision,
        ),
        axes,
    );
    Ok(EstimatesTable {
        table: opener.open_plain("estimates", columns)?,
        variant_keys: keys
            .iter()
            .map(|k| {
                (0..2)
                    .filter(|&axis| axes[axis])
                    .map(|axis| Value::F64(k[axis]))
                    .collect()
            })
            .collect(),
    })
}

/// Runs the units of `cells` on the executor and folds their results in order.
fn execute(
    plan: &Plan,
    trial: &dyn Trial,
    agg: &mut Aggregator<'_>,
    opts: &ExecOptions,
    observer: &dyn RunObserver,
    cells: std::ops::Range<usize>,
) -> Result<(), KfmcError> {
    // Unit i ↔ (scenario, scale, run) in scenario-major order, so cells complete in order.
    let (n_scales, n_runs) = (plan.noise_scales.len(), plan.runs);
    let unit_of = |i: usize| Unit {
        scenario: i / (n_scales * n_runs),
        scale: i / n_runs % n_scales,
        run: i % n_runs,
    };
    let first_unit = cells.start * n_runs;
    // Results that keep trajectories or per-step errors are large: the window holds fewer.
    let window = window_for(window_unit_bytes(plan), opts.threads);
    if let Some(gate) = &plan.sequential {
        let executor = Executor::new(
            opts.threads,
            window,
            observer,
            (cells.len() * n_runs) as u64,
        )?;
        let result = execute_looks(gate, &executor, trial, agg, cells, &unit_of);
        executor.finish();
        return result;
    }
    execute_groups::<_, KfmcError>(
        cells.len() * n_runs,
        opts.threads,
        window,
        (n_runs, trial.lanes()),
        |g| run_group(trial, g, first_unit, &unit_of),
        observer,
        |r| agg.fold(r).map_err(KfmcError::from),
    )
}

/// Runs the units `first + g` as one group on `trial` ([`Trial::run_group`]).
pub(crate) fn run_group(
    trial: &dyn Trial,
    g: std::ops::Range<usize>,
    first: usize,
    unit_of: &(dyn Fn(usize) -> Unit + Sync),
) -> Vec<UnitResult> {
    if g.len() == 1 {
        return vec![trial.run(&unit_of(first + g.start))];
    }
    let units: Vec<Unit> = g.map(|i| unit_of(first + i)).collect();
    trial.run_group(&units)
}

/// [`execute`] under a sequential gate: each cell's runs in batches up to the gate's looks,
/// each look judged once its runs are folded, and the cell finished at the look that
/// settles it. The runs made are the first runs of each cell, seeded by their index as in
/// the fixed study, and cells stay in order, so the tables are those of a study that
/// declared each cell's stopping look as its runs.
fn execute_looks(
    gate: &crate::sequential::Gate,
    executor: &Executor<'_>,
    trial: &dyn Trial,
    agg: &mut Aggregator<'_>,
    cells: std::ops::Range<usize>,
    unit_of: &(dyn Fn(usize) -> Unit + Sync),
) -> Result<(), KfmcError> {
    let n_runs = *gate.looks.last().expect("a gate has looks");
    for cell in cells {
        let first_unit = cell * n_runs;
        let mut done = 0;
        for (k, &look) in gate.looks.iter().enumerate() {
            executor.run_groups::<_, KfmcError>(
                first_unit + done..first_unit + look,
                n_runs,
                trial.lanes(),
                |g| run_group(trial, g, 0, unit_of),
                |r| agg.fold(r).map_err(KfmcError::from),
            )?;
            done = look;
            if agg.look(k)? {
                break;
            }
        }
        executor.skip((n_runs - done) as u64);
        agg.finish_cell()?;
        agg.cell_boundary(cell + 1)?;
    }
    Ok(())
}

/// An interrupted study keeps every cell that completed (the next `--resume` starts after
/// it); any other error passes through.
fn interrupted(
    e: KfmcError,
    agg: &mut Aggregator<'_>,
    dir: &std::path::Path,
    cells: usize,
) -> KfmcError {
    if !matches!(e, KfmcError::Output(OutputError::Interrupted)) {
        return e;
    }
    match agg.write_checkpoint() {
        Ok(Some(done)) => KfmcError::Output(OutputError::InterruptedCheckpointed {
            dir: crate::output::checkpoint::dir(dir),
            cells_done: done,
            cells: cells as u64,
        }),
        Ok(None) => e,
        Err(w) => KfmcError::Output(w),
    }
}

/// The tables of a folded study, finished in the order the folder commits them; the
/// divergence tables look across every noise scale of a scenario, so a part (which has only
/// some) leaves them to `kfmc merge`.
fn finish_tables(
    plan: &Plan,
    opts: &ExecOptions,
    dir: &std::path::Path,
    mut agg: Aggregator<'_>,
) -> Result<Vec<crate::output::table::FinishedTable>, OutputError> {
    let mut written: Vec<TableWriter> = Vec::new();
    if let (Some(thr), None) = (&plan.rmse_thresholds, opts.shard) {
        let (d, dr) = divergence_tables(plan, dir, &mut agg.divergence, &agg.states, thr)?;
        written.extend([d, dr]);
    }
    let Aggregator {
        runs,
        steps,
        run_steps,
        summary,
        traces,
        estimates,
        consistency,
        sensors,
        sequential: agg_sequential,
        ..
    } = agg;
    written.extend([runs, steps, summary]);
    written.extend(run_steps);
    written.extend(sensors);
    written.extend(consistency);
    written.extend(agg_sequential.map(|q| q.table));
    written.extend(traces);
    written.extend(estimates.map(|e| e.table));
    written.into_iter().map(TableWriter::finish).collect()
}
