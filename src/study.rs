//! A whole study: plan → units → executor → in-order folding into the tables → manifest.

use std::path::PathBuf;
use std::time::{Instant, SystemTime, UNIX_EPOCH};

use crate::error::{KfmcError, OutputError};
use crate::experiment::{FilterPlan, Plan};
use crate::metrics::blocks::QuantityBlock;
use crate::metrics::consistency::{BandCache, ConsistencyFold, average_chi2_band};
use crate::metrics::credibility::{CredibilityFold, CredibilityStep, credible_reference};
use crate::metrics::divergence::DivergenceTracker;
use crate::metrics::spill::Spill;
use crate::metrics::{RunStatus, StepAccumulator};
use crate::output::folder::StudyFolder;
use crate::output::manifest::{Manifest, QuantityEntry, StudyKind};
use crate::output::{TableWriter, Value, schema};
use crate::runner::{RunObserver, execute_windowed, window_for};
use crate::trial::{Trial, Unit, UnitResult, build};

/// Options of a study execution that do not change its results.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ExecOptions {
    /// Worker threads; 0 = all cores.
    pub threads: usize,
    /// Write into a non-empty folder that is not a kfmc study.
    pub force: bool,
    /// Run only this part of the plan (`kfmc run --shard i/n`), into its part folder.
    pub shard: Option<Shard>,
    /// Keep a checkpoint so that an interrupted run can be resumed (`kfmc run`); `None`
    /// writes the tables alone.
    pub checkpoints: Option<Checkpoints>,
}

/// How a study keeps its checkpoint ([`crate::output::checkpoint`]).
#[derive(Clone, Debug, PartialEq)]
pub struct Checkpoints {
    /// Least time between two checkpoints: a checkpoint follows a complete cell once this
    /// much has passed since the last one (zero: after every cell). A kill loses at most
    /// this much work plus the cell in progress.
    pub every: std::time::Duration,
    /// What to do with a checkpoint an earlier, interrupted run left in the folder.
    pub existing: ExistingCheckpoint,
}

/// What a study does with a checkpoint it finds.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ExistingCheckpoint {
    /// Refuse to start over a checkpoint of the same study (`kfmc run`): it is work a
    /// `--resume` would keep. A checkpoint of another spec, seed or run count is discarded.
    Refuse,
    /// Continue it (`--resume`); refuse, naming what changed, when it is another study's.
    Resume,
    /// Discard it and start over (`--restart`).
    Discard,
}

/// Most parts a study may be split into (`--shard i/n`, `--shards n`, the scheduler's
/// environment, `kfmc slurm --shards`): far more than any cluster runs at once, and few
/// enough that a typo of a few digits is refused instead of writing millions of parts.
pub const MAX_SHARDS: usize = 100_000;

/// One of `count` disjoint, deterministic parts of a plan: a contiguous range of its cells
/// ((scenario, noise scale) pairs in scenario-major order), so a part's tables are exactly
/// the rows one process writes for those cells, and `kfmc merge` concatenates them.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Shard {
    /// 0-based index.
    pub index: usize,
    /// Number of parts.
    pub count: usize,
}

impl Shard {
    /// The cells `[first, end)` of this part out of `cells`; later parts are empty when there
    /// are more parts than cells.
    pub fn cells(&self, cells: usize) -> std::ops::Range<usize> {
        let at = |i: usize| (i as u128 * cells as u128 / self.count as u128) as usize;
        at(self.index)..at(self.index + 1)
    }

    /// The part's folder inside the study's output folder.
    pub fn folder(&self, output: &std::path::Path) -> PathBuf {
        output
            .join("parts")
            .join(format!("part-{:05}-of-{:05}", self.index, self.count))
    }
}

/// What a finished study wrote.
#[derive(Clone, Debug, PartialEq)]
pub struct StudyReport {
    /// Output folder.
    pub output: PathBuf,
    /// Tables and their row counts.
    pub tables: Vec<(String, u64)>,
    /// Wall-clock seconds.
    pub wall_s: f64,
    /// Simulated runs (by this process: a resume does not count the checkpoint's).
    pub runs: u64,
    /// Cells taken from the checkpoint of an interrupted run instead of being computed.
    pub cells_resumed: u64,
}

/// The key values of a cell row: scenario, noise scale, filter label, q_scale, r_scale.
fn cell_key<'a>(scenario: &'a str, noise: f64, f: &'a FilterPlan) -> [Value<'a>; 5] {
    let [q, r] = scale_keys(f);
    [
        Value::Str(scenario),
        Value::F64(Some(noise)),
        Value::Str(&f.label),
        q,
        r,
    ]
}

/// The `q_scale` and `r_scale` key values of a filter variant: null for an external filter,
/// whose tuning is its own and which kfmc never scales.
fn scale_keys(f: &FilterPlan) -> [Value<'static>; 2] {
    let own = |v: f64| Value::F64((!f.external).then_some(v));
    [own(f.q_scale), own(f.r_scale)]
}

/// The across-run quantile levels of the summary and sensors tables.
const LEVELS: [f64; 3] = [0.05, 0.50, 0.95];

/// The per-cell state while its runs are being folded.
struct CellState {
    acc: Vec<StepAccumulator>,
    /// Per filter: the runs' consistency sums folded for the whole cell and each subset
    /// (when the study asks for the tests), in bounded memory.
    consistency: Vec<ConsistencyFold>,
    /// Per filter (when the study asks for the tests): block NEES sums and each run's errors
    /// for the credibility measures.
    credibility: Vec<CredibilityFold>,
    /// Per filter: RMSE rows of the runs that completed (failures excluded), in bounded
    /// memory for the exact quantiles of the summary.
    rmse: Vec<Spill>,
    failed: Vec<u64>,
    /// One row per run: each world metric's value.
    world: Spill,
}

struct Aggregator<'a> {
    plan: &'a Plan,
    trial: &'a dyn Trial,
    states: Vec<&'a str>,
    runs: TableWriter,
    steps: TableWriter,
    summary: TableWriter,
    traces: Option<TableWriter>,
    /// `estimates.parquet` (`--export-estimates`): every run in the exchange format.
    estimates: Option<TableWriter>,
    consistency: Option<TableWriter>,
    sensors: Option<TableWriter>,
    bands: BandCache,
    /// The layout's blocks of quantities, when the study asks for the consistency tests.
    blocks: Vec<QuantityBlock>,
    /// Per (scenario, filter).
    divergence: Vec<DivergenceTracker>,
    cell: Option<(usize, usize, CellState)>,
    /// Where the cells' spills put their scratch files (the folder being written).
    scratch: PathBuf,
    /// The checkpoint being kept, when the study is resumable.
    checkpoint: Option<Checkpointer>,
}

/// Keeps a study's checkpoint: after a complete cell it notes where every journal ends, and
/// once `every` has passed it makes them durable and writes the index.
struct Checkpointer {
    dir: PathBuf,
    every: std::time::Duration,
    last: Instant,
    /// The study's identity; `cells_done` and `tables` describe the last checkpoint written.
    index: crate::output::checkpoint::Index,
    /// The last cell boundary: cells done (from the first cell of the run) and the journals'
    /// positions there.
    boundary: Option<(u64, Vec<crate::output::checkpoint::JournalEntry>)>,
    /// First cell of this folder's range.
    first_cell: usize,
}

impl Aggregator<'_> {
    fn fold(&mut self, r: UnitResult) -> Result<(), OutputError> {
        let plan = self.plan;
        let Unit {
            scenario,
            scale,
            run,
        } = r.unit;
        let nx = self.states.len();
        let nf = plan.filters.len();
        if self
            .cell
            .as_ref()
            .is_none_or(|(s, j, _)| (*s, *j) != (scenario, scale))
        {
            let steps = self.trial.steps(scenario);
            // The whole cell, then each subset: its first N runs.
            let consistency_bounds: Vec<usize> = std::iter::once(usize::MAX)
                .chain(
                    plan.consistency
                        .iter()
                        .flat_map(|c| c.subsets.iter().map(|s| s.0)),
                )
                .collect();
            self.cell = Some((
                scenario,
                scale,
                CellState {
                    // Every run of the cell comes here (shards split by cells).
                    acc: (0..nf)
                        .map(|_| {
                            let mut a = StepAccumulator::with_exact_cap(
                                nx,
                                steps,
                                crate::metrics::abs_err_exact_cap(nf, nx, steps + 1),
                            );
                            a.reserve_runs(plan.runs);
                            a
                        })
                        .collect(),
                    rmse: (0..nf).map(|_| Spill::new(&self.scratch, nx)).collect(),
                    consistency: (0..nf)
                        .map(|_| ConsistencyFold::new(&self.scratch, nx, nx, &consistency_bounds))
                        .collect(),
                    credibility: if plan.consistency.is_some() {
                        (0..nf)
                            .map(|_| {
                                CredibilityFold::new(&self.scratch, nx, self.blocks.len(), steps)
                            })
                            .collect()
                    } else {
                        Vec::new()
                    },
                    failed: vec![0; nf],
                    world: Spill::new(&self.scratch, self.trial.world_metrics().len()),
                },
            ));
        }
        let sname = plan.scenarios[scenario].name.as_str();
        let noise = plan.noise_scales[scale];
        let (_, _, cell) = self.cell.as_mut().expect("set above");
        if !r.world_metrics.is_empty() {
            cell.world.push(&r.world_metrics)?;
        }
        for (fi, fr) in r.filters.iter().enumerate() {
            let failed = matches!(fr.status, RunStatus::NumericalFailure { .. });
            let mut row = cell_key(sname, noise, &plan.filters[fi]).to_vec();
            row.extend([
                Value::I64(Some(run as i64)),
                Value::U64(r.seed),
                Value::Str(fr.status.label()),
                Value::I64(fr.status.step().map(|s| s as i64)),
                Value::Str(fr.status.detail().unwrap_or("")),
            ]);
            row.extend(fr.rmse.iter().map(|v| Value::F64((!failed).then_some(*v))));
            row.extend([
                Value::F64(fr.nees_mean),
                Value::F64(fr.nis_mean),
                Value::I64(Some(fr.covariance_repairs as i64)),
            ]);
            self.runs.push(&row)?;
            cell.acc[fi].fold(&fr.steps);
            if let Some(c) = &fr.consistency {
                cell.consistency[fi].push(run, c)?;
            }
            if let Some(c) = cell.credibility.get_mut(fi) {
                c.push(&fr.steps)?;
            }
            if failed {
                cell.failed[fi] += 1;
            } else {
                cell.rmse[fi].push(&fr.rmse)?;
            }
            if let Some(thr) = &plan.rmse_thresholds {
                let rmse: Vec<f64> = if failed {
                    vec![f64::NAN; nx]
                } else {
                    fr.rmse.clone()
                };
                self.divergence[scenario * nf + fi].observe_run(run, scale, &rmse, thr)?;
            }
        }
        if let (Some(tr), Some(w)) = (&r.trace, self.estimates.as_mut()) {
            write_estimates(w, plan, sname, noise, run, tr, nx)?;
        }
        if let (Some(tr), Some(w), true) = (&r.trace, self.traces.as_mut(), run < plan.trace_runs) {
            let layout = self.trial.layout();
            let (nu, nz) = (layout.inputs.len(), layout.measurements.len());
            let nw = layout.world_states.len();
            let ntri = nx * (nx + 1) / 2;
            let dt = plan.dt_s();
            for (fi, f) in plan.filters.iter().enumerate() {
                for k in 0..tr.truth.len() / nx {
                    let mut row = cell_key(sname, noise, f).to_vec();
                    row.extend([
                        Value::I64(Some(run as i64)),
                        Value::I64(Some(k as i64)),
                        Value::F64(Some(k as f64 * dt)),
                    ]);
                    let f64s =
                        |v: &[f64]| v.iter().map(|x| Value::F64(Some(*x))).collect::<Vec<_>>();
                    row.extend(f64s(&tr.u[k * nu..(k + 1) * nu]));
                    row.extend(f64s(&tr.truth[k * nx..(k + 1) * nx]));
                    row.extend(f64s(&tr.z[k * nz..(k + 1) * nz]));
                    row.extend(f64s(tr.world.get(k * nw..(k + 1) * nw).unwrap_or(&[])));
                    row.extend(f64s(&tr.est[fi][k * nx..(k + 1) * nx]));
                    let cov = &tr.cov[fi][k * ntri..(k + 1) * ntri];
                    // var_<q> is the diagonal, kept for readers of the diagonal alone; the
                    // P_<qi>_<qj> columns follow with the whole lower triangle.
                    row.extend((0..nx).map(|i| Value::F64(Some(cov[i * (i + 1) / 2 + i]))));
                    row.extend(f64s(cov));
                    w.push(&row)?;
                }
            }
        }
        if run + 1 == plan.runs {
            self.finish_cell()?;
            self.cell_boundary(scenario * plan.noise_scales.len() + scale + 1)?;
        }
        Ok(())
    }

    /// The journaled tables, in a fixed order.
    fn journaled_tables(&mut self) -> impl Iterator<Item = &mut TableWriter> {
        [&mut self.runs, &mut self.steps, &mut self.summary]
            .into_iter()
            .chain(self.traces.as_mut())
            .chain(self.estimates.as_mut())
            .chain(self.consistency.as_mut())
            .chain(self.sensors.as_mut())
    }

    /// After the last row of cell `end_cell − 1`: notes the boundary, and checkpoints when it
    /// is time.
    fn cell_boundary(&mut self, end_cell: usize) -> Result<(), OutputError> {
        let Some(first_cell) = self.checkpoint.as_ref().map(|c| c.first_cell) else {
            return Ok(());
        };
        let mut tables = Vec::new();
        let cells = (end_cell - first_cell) as u64;
        for w in self.journaled_tables() {
            if let Some((bytes, rows)) = w.end_journal_cell(cells)? {
                tables.push(crate::output::checkpoint::JournalEntry {
                    name: w.name().to_string(),
                    bytes,
                    rows,
                });
            }
        }
        let c = self.checkpoint.as_mut().expect("checked above");
        c.boundary = Some((cells, tables));
        if c.last.elapsed() >= c.every {
            self.write_checkpoint()?;
        }
        Ok(())
    }

    /// Makes the journals durable and writes the index of the last cell boundary; returns the
    /// cells it holds.
    fn write_checkpoint(&mut self) -> Result<Option<u64>, OutputError> {
        let Some(boundary) = self.checkpoint.as_mut().and_then(|c| c.boundary.take()) else {
            return Ok(self
                .checkpoint
                .as_ref()
                .map(|c| c.index.cells_done)
                .filter(|d| *d > 0));
        };
        for w in self.journaled_tables() {
            w.sync_journal()?;
        }
        let c = self.checkpoint.as_mut().expect("a boundary was noted");
        (c.index.cells_done, c.index.tables) = boundary;
        c.index.write(&c.dir)?;
        c.last = Instant::now();
        Ok(Some(c.index.cells_done))
    }

    fn finish_cell(&mut self) -> Result<(), OutputError> {
        let plan = self.plan;
        let Some((scenario, scale, mut cell)) = self.cell.take() else {
            return Ok(());
        };
        let sname = plan.scenarios[scenario].name.as_str();
        let noise = plan.noise_scales[scale];
        let dt = plan.dt_s();
        let nf = plan.filters.len();
        let n = self.states.len() as u64;
        if let Some(w) = self.sensors.as_mut() {
            let sums = cell.world.summarise(|_, x| x.is_finite(), &LEVELS)?;
            for (name, s) in self.trial.world_metrics().iter().zip(&sums) {
                w.push(&[
                    Value::Str(sname),
                    Value::F64(Some(noise)),
                    Value::Str(name),
                    Value::I64(Some(s.n as i64)),
                    Value::F64(s.mean),
                    Value::F64(s.std),
                    Value::F64(s.quantiles[0]),
                    Value::F64(s.quantiles[1]),
                    Value::F64(s.quantiles[2]),
                ])?;
            }
        }
        for (fi, f) in plan.filters.iter().enumerate() {
            let credibility = match cell.credibility.get_mut(fi) {
                Some(c) => Some(c.finish()?),
                None => None,
            };
            let acc = &cell.acc[fi];
            let (mut nees_in, mut nees_steps, mut nis_in, mut nis_steps) = (0u64, 0u64, 0u64, 0u64);
            for k in 0..acc.len() {
                let s = acc.row(k);
                let nees_band = s
                    .anees
                    .and_then(|_| self.bands.band(s.nees_runs as u64 * n, s.nees_runs as u64));
                let nis_band = s
                    .anis
                    .and_then(|_| self.bands.band(s.nis_dof, s.nis_runs as u64));
                let nees_inside = s.anees.zip(nees_band).map(|(a, b)| b.contains(a));
                let nis_inside = s.anis.zip(nis_band).map(|(a, b)| b.contains(a));
                // Step 0 is the prior, not a filter output: the descriptive fractions skip it.
                if k > 0 {
                    if let Some(i) = nees_inside {
                        nees_steps += 1;
                        nees_in += i as u64;
                    }
                    if let Some(i) = nis_inside {
                        nis_steps += 1;
                        nis_in += i as u64;
                    }
                }
                let mut row = cell_key(sname, noise, f).to_vec();
                row.extend([
                    Value::I64(Some(k as i64)),
                    Value::F64(Some(k as f64 * dt)),
                    Value::I64(Some(s.runs as i64)),
                    Value::F64(s.anees),
                    Value::F64(nees_band.map(|b| b.lo)),
                    Value::F64(nees_band.map(|b| b.hi)),
                    Value::Bool(nees_inside),
                    Value::F64(s.anis),
                    Value::F64(nis_band.map(|b| b.lo)),
                    Value::F64(nis_band.map(|b| b.hi)),
                    Value::Bool(nis_inside),
                ]);
                row.extend(s.mse.iter().map(|v| Value::F64(Some(*v))));
                for q in 0..3 {
                    row.extend(s.abs_err.iter().map(|a| Value::F64(a[q])));
                }
                if let Some(c) = &credibility {
                    row.extend(credibility_step_values(
                        &c[k],
                        &self.blocks,
                        &mut self.bands,
                        self.states.len(),
                    ));
                }
                self.steps.push(&row)?;
            }
            if let (Some(w), Some(cp)) = (self.consistency.as_mut(), plan.consistency.as_ref()) {
                let frac = |i: u64, n: u64| (n > 0).then(|| i as f64 / n as f64);
                // The whole cell at the study's α, then each subset: its first N runs at its α
                // (the per-step fractions are descriptive and kept for the whole cell only).
                let mut evaluations = vec![(
                    cp.alpha,
                    (frac(nees_in, nees_steps), frac(nis_in, nis_steps)),
                )];
                evaluations.extend(cp.subsets.iter().map(|&(_, alpha)| (alpha, (None, None))));
                let folded = cell.consistency[fi].finish()?;
                for (ev, (sums, (alpha, inside))) in folded.into_iter().zip(evaluations).enumerate()
                {
                    let burn_in = sums.burn_in();
                    // The credibility columns describe the whole cell; a subset's rows leave
                    // them null.
                    let cred: Vec<Value<'static>> = match &credibility {
                        Some(c) if ev == 0 => credibility_averages(
                            c,
                            &self.blocks,
                            alpha,
                            burn_in.map_or(1, |b| b + 1).max(1),
                            self.states.len(),
                        ),
                        Some(_) => {
                            vec![Value::F64(None); 4 * self.blocks.len() + 4]
                        }
                        None => Vec::new(),
                    };
                    for t in sums.tests(&self.states, alpha, inside) {
                        let mut row = cell_key(sname, noise, f).to_vec();
                        row.extend([
                            Value::Str(&t.test),
                            Value::F64(Some(t.statistic)),
                            Value::F64(t.lower),
                            Value::F64(t.upper),
                            Value::F64(t.dof),
                            Value::F64(t.p_value),
                            Value::Bool(Some(t.pass)),
                            Value::Str(t.direction.map_or("", |d| d.label())),
                            Value::F64(Some(alpha)),
                            Value::I64(Some(sums.runs() as i64)),
                            Value::I64(burn_in.map(|b| b as i64)),
                        ]);
                        row.extend(cred.iter().cloned());
                        w.push(&row)?;
                    }
                }
            }
            let mut means = Vec::with_capacity(self.states.len());
            let sums = cell.rmse[fi].summarise(|_, _| true, &LEVELS)?;
            for (state, s) in self.states.iter().zip(&sums) {
                means.push(s.mean.unwrap_or(f64::NAN));
                let mut row = cell_key(sname, noise, f).to_vec();
                row.extend([
                    Value::Str(state),
                    Value::I64(Some(s.n as i64)),
                    Value::I64(Some(cell.failed[fi] as i64)),
                    Value::F64(s.mean),
                    Value::F64(s.std),
                    Value::F64(s.quantiles[0]),
                    Value::F64(s.quantiles[1]),
                    Value::F64(s.quantiles[2]),
                ]);
                self.summary.push(&row)?;
            }
            if let Some(thr) = &plan.rmse_thresholds {
                self.divergence[scenario * nf + fi].observe_mean(scale, &means, thr);
            }
        }
        Ok(())
    }
}

/// Runs the study described by `plan`, writing its tables and manifest into `plan.output`.
pub fn run(
    plan: &Plan,
    opts: &ExecOptions,
    observer: &dyn RunObserver,
) -> Result<StudyReport, KfmcError> {
    run_locked(plan, opts, observer).map(|(report, _)| report)
}

/// The kind of folder a study of `plan` writes: estimates read from files make a scored
/// study, kfmc's own filters alone a run.
pub fn study_kind(plan: &Plan) -> StudyKind {
    if plan.filters.iter().any(|f| f.external) {
        StudyKind::Score
    } else {
        StudyKind::Run
    }
}

/// [`run`], returning the folder still locked, so that a caller that reads the committed
/// tables back (`kfmc check`) reads this study's, not a later writer's.
pub fn run_locked(
    plan: &Plan,
    opts: &ExecOptions,
    observer: &dyn RunObserver,
) -> Result<(StudyReport, StudyFolder), KfmcError> {
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
    if plan.export_estimates
        && let Some(f) = plan
            .filters
            .iter()
            .enumerate()
            .find(|(i, f)| plan.filters[..*i].iter().any(|g| g.label == f.label))
    {
        return Err(KfmcError::Spec(crate::error::SpecErrors(vec![
            crate::error::SpecError {
                file: plan.spec_path.clone(),
                key_path: "filters".into(),
                message: format!(
                    "--export-estimates needs one variant per label, but `{}` has several q_scale/r_scale variants (the estimates format keys a filter by its label alone)",
                    f.1.label
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
    let folder = StudyFolder::open(dir, study_kind(plan), opts.force)?;
    let n_cells = plan.scenarios.len() * plan.noise_scales.len();
    let cells = opts.shard.map_or(0..n_cells, |s| s.cells(n_cells));
    let result = run_in(
        plan,
        opts,
        observer,
        dir,
        &folder,
        n_cells,
        cells,
        started,
        started_unix_s,
    );
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

/// [`run`] once the folder is held.
#[allow(clippy::too_many_arguments)]
fn run_in(
    plan: &Plan,
    opts: &ExecOptions,
    observer: &dyn RunObserver,
    dir: &std::path::Path,
    folder: &StudyFolder,
    n_cells: usize,
    cells: std::ops::Range<usize>,
    started: Instant,
    started_unix_s: u64,
) -> Result<StudyReport, KfmcError> {
    let trial = build(plan);
    let layout = plan.layout();
    let states = layout.quantity_names();
    let resume = existing_checkpoint(plan, opts, dir, n_cells, &cells)?;
    let journaling = opts.checkpoints.is_some();
    // A table of the study: journaled when the study is resumable, and on a resume first
    // refilled from its journal, each replayed row also shown to `on_row`.
    let open = |name: &str,
                columns: Vec<crate::output::schema::ColumnDef>,
                on_row: &mut dyn FnMut(&[Value<'_>]) -> Result<(), OutputError>|
     -> Result<TableWriter, OutputError> {
        let metadata = crate::score::table_metadata(name, plan);
        if !journaling {
            return TableWriter::create_with_metadata(dir, name, columns, &metadata);
        }
        let journal = crate::output::checkpoint::journal_path(dir, name);
        let from = match &resume {
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
        TableWriter::journaled(dir, name, columns, &metadata, &journal, from, on_row)
    };
    let mut ignore = |_: &[Value<'_>]| Ok(());
    // The divergence trackers look across cells: a resume rebuilds them from the replayed
    // runs and summary rows, as `kfmc merge` does from the parts' tables.
    let mut feed = DivergenceFeed::new(plan, dir);
    let damaged = |why: &str| OutputError::Mismatch {
        path: crate::output::checkpoint::dir(dir),
        why: format!(
            "is a damaged checkpoint: a row {why}; start over with `kfmc run SPEC --restart`"
        ),
    };
    let runs = open("runs", feed.runs_columns().to_vec(), &mut |row| {
        feed.run_row(row, &damaged)
    })?;
    let summary = open("summary", feed.summary_columns().to_vec(), &mut |row| {
        feed.summary_row(row, &damaged)
    })?;
    let divergence = feed.into_trackers();
    let cells_resumed = resume.as_ref().map_or(0, |i| i.cells_done as usize);
    // The blocks the runs keep NEES for (none when they do not fit the runs' masks).
    let blocks = if plan.consistency.is_some()
        && !crate::trial::ConsistencyOptions::blocks_of(plan).is_empty()
    {
        crate::trial::layout_blocks(layout)
    } else {
        Vec::new()
    };
    let block_names: Vec<String> = blocks.iter().map(QuantityBlock::column_name).collect();
    let block_names: Vec<&str> = block_names.iter().map(String::as_str).collect();
    let mut agg = Aggregator {
        plan,
        trial: trial.as_ref(),
        runs,
        steps: open(
            "steps",
            schema::steps(&states, plan.consistency.as_ref().map(|_| &block_names[..])),
            &mut ignore,
        )?,
        summary,
        traces: if plan.trace_runs > 0 {
            Some(open(
                "traces",
                schema::traces(
                    &states,
                    &layout.input_names(),
                    &layout.measurement_names(),
                    &layout.world_state_names(),
                ),
                &mut ignore,
            )?)
        } else {
            None
        },
        consistency: if plan.consistency.is_some() {
            Some(open(
                "consistency",
                schema::consistency(Some(&block_names)),
                &mut ignore,
            )?)
        } else {
            None
        },
        sensors: if trial.world_metrics().is_empty() {
            None
        } else {
            Some(open("sensors", schema::sensors(), &mut ignore)?)
        },
        estimates: if plan.export_estimates {
            Some(open(
                "estimates",
                crate::score::estimate_columns_with(
                    &states,
                    &layout.measurement_names(),
                    &layout.rotations(),
                ),
                &mut ignore,
            )?)
        } else {
            None
        },
        bands: BandCache::new(plan.alpha),
        blocks,
        divergence,
        states,
        cell: None,
        scratch: dir.to_path_buf(),
        checkpoint: opts.checkpoints.as_ref().map(|c| Checkpointer {
            dir: dir.to_path_buf(),
            every: c.every,
            last: Instant::now(),
            index: resume
                .clone()
                .unwrap_or_else(|| checkpoint_identity(plan, n_cells, &cells)),
            boundary: None,
            first_cell: cells.start,
        }),
    };

    // Unit i ↔ (scenario, scale, run) in scenario-major order, so cells complete in order.
    let (n_scales, n_runs) = (plan.noise_scales.len(), plan.runs);
    let unit_of = |i: usize| Unit {
        scenario: i / (n_scales * n_runs),
        scale: i / n_runs % n_scales,
        run: i % n_runs,
    };
    let first_unit = (cells.start + cells_resumed) * n_runs;
    // An exported run's result carries its whole trajectory, and with the consistency tests
    // each filter's signed errors and block NEES per step: the window holds fewer of them.
    let unit_bytes = if plan.export_estimates {
        trajectory_bytes(plan)
    } else {
        0
    } + credibility_bytes(plan);
    let executed = execute_windowed::<_, KfmcError>(
        (cells.end - cells.start - cells_resumed) * n_runs,
        opts.threads,
        window_for(unit_bytes, opts.threads),
        |i| trial.run(&unit_of(first_unit + i)),
        observer,
        |r| agg.fold(r).map_err(KfmcError::from),
    );
    if let Err(KfmcError::Output(OutputError::Interrupted)) = executed {
        // Keep every cell that completed: the next `--resume` starts after it.
        if let Some(done) = agg.write_checkpoint()? {
            return Err(KfmcError::Output(OutputError::InterruptedCheckpointed {
                dir: crate::output::checkpoint::dir(dir),
                cells_done: done,
                cells: (cells.end - cells.start) as u64,
            }));
        }
    }
    executed?;

    let mut written: Vec<TableWriter> = Vec::new();
    // Divergence points look across every noise scale of a scenario: a part has only some,
    // so `kfmc merge` computes them from the merged runs and summary.
    if let (Some(thr), None) = (&plan.rmse_thresholds, opts.shard) {
        let (d, dr) = divergence_tables(plan, dir, &mut agg.divergence, &agg.states, thr)?;
        written.extend([d, dr]);
    }
    let Aggregator {
        runs,
        steps,
        summary,
        traces,
        estimates,
        consistency,
        sensors,
        ..
    } = agg;
    written.extend([runs, steps, summary]);
    written.extend(sensors);
    written.extend(consistency);
    written.extend(traces);
    written.extend(estimates);

    let finished = written
        .into_iter()
        .map(TableWriter::finish)
        .collect::<Result<Vec<_>, _>>()?;
    let wall_s = started.elapsed().as_secs_f64();
    let manifest = manifest_for(plan, opts, started_unix_s, wall_s, cells.clone());
    let tables = folder.commit(finished, manifest)?;
    // Committed: the tables are complete, and a checkpoint of them would only mislead.
    crate::output::checkpoint::remove(dir)?;
    let done = ((cells.end - cells.start - cells_resumed) * n_runs) as u64;
    Ok(StudyReport {
        output: dir.to_path_buf(),
        tables,
        wall_s,
        runs: done,
        cells_resumed: cells_resumed as u64,
    })
}

/// About the bytes a run's result holds when it keeps its trajectories for every filter of
/// `plan` (the longest scenario's truth, z, u and world states, and per filter the estimate,
/// P's lower triangle, ν, S and A per step), for [`crate::runner::window_for`].
/// Bytes of one run's per-step values kept for the credibility measures (signed errors and
/// block NEES of every filter; [`crate::metrics::StepValues::enable_credibility`]); 0 without
/// `[consistency]`.
fn credibility_bytes(plan: &Plan) -> u64 {
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

/// The identity a checkpoint of this run carries, with nothing done yet.
fn checkpoint_identity(
    plan: &Plan,
    n_cells: usize,
    cells: &std::ops::Range<usize>,
) -> crate::output::checkpoint::Index {
    crate::output::checkpoint::Index {
        kfmc_version: env!("CARGO_PKG_VERSION").to_string(),
        spec_hash: plan.spec_hash.clone(),
        master_seed: plan.master_seed,
        runs_per_cell: plan.runs as u64,
        cells: n_cells as u64,
        first_cell: cells.start as u64,
        end_cell: cells.end as u64,
        trace_runs: plan.trace_runs as u64,
        export_estimates: plan.export_estimates,
        journal_format: crate::output::checkpoint::JOURNAL_FORMAT,
        cells_done: 0,
        tables: Vec::new(),
    }
}

/// The checkpoint this run continues from, after applying `opts.checkpoints.existing` to
/// whatever checkpoint is in `dir`.
fn existing_checkpoint(
    plan: &Plan,
    opts: &ExecOptions,
    dir: &std::path::Path,
    n_cells: usize,
    cells: &std::ops::Range<usize>,
) -> Result<Option<crate::output::checkpoint::Index>, OutputError> {
    use crate::output::checkpoint;
    let Some(c) = &opts.checkpoints else {
        return Ok(None);
    };
    let Some(found) = checkpoint::Index::read(dir)? else {
        return Ok(None);
    };
    let change = found.change_from(&checkpoint_identity(plan, n_cells, cells));
    let at = checkpoint::dir(dir);
    match (c.existing, change) {
        (ExistingCheckpoint::Resume, None) => {
            // The identity matched; the counts must be coherent before anything is replayed.
            found.check(dir)?;
            Ok(Some(found))
        }
        (ExistingCheckpoint::Resume, Some(why)) => Err(OutputError::Mismatch {
            path: at,
            why: format!(
                "is a checkpoint of another study: {why}; start over with `kfmc run SPEC --restart`"
            ),
        }),
        (ExistingCheckpoint::Refuse, None) if found.cells_done > 0 => Err(OutputError::Mismatch {
            path: at,
            why: format!(
                "holds the checkpoint of an interrupted run of this study ({} of {} cells complete): continue it with `kfmc run SPEC --resume`, or discard it with `--restart`",
                found.cells_done,
                found.end_cell.saturating_sub(found.first_cell)
            ),
        }),
        _ => {
            checkpoint::remove(dir)?;
            Ok(None)
        }
    }
}

/// Rebuilds the divergence trackers from rows already written, in the order a study writes
/// them: a resume replays its journals, `kfmc merge` reads its parts' tables. (The trackers
/// look across the noise scales of a scenario, so no single cell's rows give them.)
pub(crate) struct DivergenceFeed<'a> {
    plan: &'a Plan,
    /// Per (scenario, filter variant), as the study keeps them.
    trackers: Vec<DivergenceTracker>,
    runs: Vec<crate::output::schema::ColumnDef>,
    summary: Vec<crate::output::schema::ColumnDef>,
    /// Positions of `run` and of the `rmse_<state>` columns in `runs`.
    run_col: usize,
    rmse_cols: Vec<usize>,
    /// Position of `rmse_mean` in `summary`.
    mean_col: usize,
    /// The means of the (cell, filter) whose summary rows are being read: they come one row
    /// per state, in state order, possibly across row groups.
    means: Vec<f64>,
}

impl<'a> DivergenceFeed<'a> {
    /// Trackers of every (scenario, filter variant) of `plan`, nothing observed yet, with
    /// their scratch files in `dir`.
    pub(crate) fn new(plan: &'a Plan, dir: &std::path::Path) -> Self {
        let states = plan.quantity_names();
        let runs = schema::runs(&states);
        let summary = schema::summary();
        let position = |columns: &[crate::output::schema::ColumnDef], name: &str| {
            columns
                .iter()
                .position(|c| c.name == name)
                .unwrap_or_else(|| panic!("the schema has a column {name}"))
        };
        DivergenceFeed {
            plan,
            trackers: (0..plan.scenarios.len() * plan.filters.len())
                .map(|_| DivergenceTracker::new(dir, states.len()))
                .collect(),
            run_col: position(&runs, "run"),
            rmse_cols: states
                .iter()
                .map(|s| position(&runs, &format!("rmse_{s}")))
                .collect(),
            mean_col: position(&summary, "rmse_mean"),
            means: Vec::with_capacity(states.len()),
            runs,
            summary,
        }
    }

    /// The columns of the runs table, the order [`DivergenceFeed::run_row`] reads.
    pub(crate) fn runs_columns(&self) -> &[crate::output::schema::ColumnDef] {
        &self.runs
    }

    /// The columns of the summary table, the order [`DivergenceFeed::summary_row`] reads.
    pub(crate) fn summary_columns(&self) -> &[crate::output::schema::ColumnDef] {
        &self.summary
    }

    /// Observes one row of the runs table (each noise scale's runs in run order, as the
    /// study writes them). A row that does not fit the plan is `bad(why)`, `why` completing
    /// "a row …", for the caller to say where the row came from.
    pub(crate) fn run_row(
        &mut self,
        row: &[Value<'_>],
        bad: &dyn Fn(&str) -> OutputError,
    ) -> Result<(), OutputError> {
        let Some(thr) = &self.plan.rmse_thresholds else {
            return Ok(());
        };
        let (si, scale, fi) = self.cell(row).ok_or_else(|| bad(NO_CELL))?;
        // A null RMSE (a failed run) is NaN, as the study feeds it.
        let rmse: Vec<f64> = self
            .rmse_cols
            .iter()
            .map(|&c| f64_of(&row[c]).unwrap_or(f64::NAN))
            .collect();
        let run = match row[self.run_col] {
            Value::I64(Some(r)) => r as usize,
            _ => return Err(bad("has no run index")),
        };
        let nf = self.plan.filters.len();
        self.trackers[si * nf + fi].observe_run(run, scale, &rmse, thr)
    }

    /// Observes one row of the summary table; a (cell, filter)'s mean RMSE is observed at
    /// its last state's row. A bad row is `bad(why)` as in [`DivergenceFeed::run_row`].
    pub(crate) fn summary_row(
        &mut self,
        row: &[Value<'_>],
        bad: &dyn Fn(&str) -> OutputError,
    ) -> Result<(), OutputError> {
        let Some(thr) = &self.plan.rmse_thresholds else {
            return Ok(());
        };
        self.means
            .push(f64_of(&row[self.mean_col]).unwrap_or(f64::NAN));
        if self.means.len() == self.rmse_cols.len() {
            let (si, scale, fi) = self.cell(row).ok_or_else(|| bad(NO_CELL))?;
            let nf = self.plan.filters.len();
            self.trackers[si * nf + fi].observe_mean(scale, &self.means, thr);
            self.means.clear();
        }
        Ok(())
    }

    /// The trackers, for [`divergence_tables`] or for the study to go on observing.
    pub(crate) fn into_trackers(self) -> Vec<DivergenceTracker> {
        self.trackers
    }

    /// (scenario, noise scale, filter variant) indices of a row keyed by [`cell_key`].
    fn cell(&self, row: &[Value<'_>]) -> Option<(usize, usize, usize)> {
        let p = self.plan;
        let [
            Value::Str(s),
            Value::F64(Some(noise)),
            Value::Str(label),
            Value::F64(q),
            Value::F64(r),
            ..,
        ] = row
        else {
            return None;
        };
        let si = p.scenarios.iter().position(|x| x.name == *s)?;
        let scale = p.noise_scales.iter().position(|x| x == noise)?;
        // An external filter's multipliers are null, a kfmc filter's are numbers.
        let fi = p.filters.iter().position(|f| {
            let own = |v: f64| (!f.external).then_some(v);
            f.label == *label && own(f.q_scale) == *q && own(f.r_scale) == *r
        })?;
        Some((si, scale, fi))
    }
}

/// Why [`DivergenceFeed`] refuses a row whose key is not one of the plan's cells.
const NO_CELL: &str = "names a cell the spec does not have";

fn f64_of(v: &Value<'_>) -> Option<f64> {
    match v {
        Value::F64(x) => *x,
        _ => None,
    }
}

/// The manifest of a study (or a part, or a simulation) of `plan` over `cells`; the commit
/// fills in its tables.
pub(crate) fn manifest_for(
    plan: &Plan,
    opts: &ExecOptions,
    started_unix_s: u64,
    wall_s: f64,
    cells: std::ops::Range<usize>,
) -> Manifest {
    let size = plan.size();
    let threads = if opts.threads == 0 {
        crate::runner::default_threads()
    } else {
        opts.threads
    };
    Manifest {
        kfmc_version: env!("CARGO_PKG_VERSION").to_string(),
        experiment: plan.name.clone(),
        system: plan.kind.clone(),
        kind: Some(study_kind(plan)),
        quantities: plan
            .layout()
            .quantities
            .iter()
            .map(|q| QuantityEntry {
                name: q.name.clone(),
                unit: q.unit.clone(),
                angle: q.angle,
                rotation: q.rotation.map(|side| side.name().to_string()),
            })
            .collect(),
        inputs: plan.layout().inputs.clone(),
        measurements: plan.layout().measurements.clone(),
        dt_s: plan.dt_s(),
        spec_path: plan.spec_path.display().to_string(),
        spec_hash: plan.spec_hash.clone(),
        world_stamp: plan.world_stamp(),
        master_seed: plan.master_seed,
        runs_per_cell: plan.runs as u64,
        cells: size.cells as u64,
        runs: size.runs as u64,
        filter_runs: size.filter_runs as u64,
        filter_steps: size.filter_steps,
        threads: threads as u64,
        started_unix_s,
        wall_s,
        runs_per_s: size.runs as f64 / wall_s.max(1e-9),
        // Filled in by the commit, with each table's size and checksum.
        tables: Vec::new(),
        exchange: None,
        shard: opts.shard.map(|s| crate::output::manifest::ShardEntry {
            index: s.index as u64,
            count: s.count as u64,
            first_cell: cells.start as u64,
            end_cell: cells.end as u64,
        }),
        spec: plan.spec_text.clone(),
    }
}

/// Writes one run's rows of `estimates.parquet`: every kfmc filter (external ones are what
/// is being scored, not exported), in the exchange format of [`crate::score`].
fn write_estimates(
    w: &mut TableWriter,
    plan: &Plan,
    scenario: &str,
    noise: f64,
    run: usize,
    tr: &crate::trial::RunTrace,
    nq: usize,
) -> Result<(), OutputError> {
    let ntri = nq * (nq + 1) / 2;
    let nz = plan.layout().measurements.len();
    let ztri = nz * (nz + 1) / 2;
    let f64s = |v: &[f64]| v.iter().map(|x| Value::F64(Some(*x))).collect::<Vec<_>>();
    let rotations = plan.layout().rotations();
    // A rotation is written as its quaternion, in place of its three Euler angles (its
    // covariance is already the rotation error's).
    let estimate = |e: &[f64]| {
        let mut out = f64s(e);
        for r in rotations.iter().rev() {
            let q = crate::linalg::so3::quaternion_of(&r.matrix(e));
            out.splice(r.first..r.first + 3, q.map(|c| Value::F64(Some(c))));
        }
        out
    };
    for (fi, f) in plan.filters.iter().enumerate() {
        let Some(Some(x)) = tr.export.get(fi) else {
            continue;
        };
        for k in 0..tr.truth.len() / nq {
            let mut row = vec![
                Value::Str(scenario),
                Value::F64(Some(noise)),
                Value::I64(Some(run as i64)),
                Value::I64(Some(k as i64)),
                Value::Str(&f.label),
            ];
            row.extend(estimate(&tr.est[fi][k * nq..(k + 1) * nq]));
            row.extend(f64s(&tr.cov[fi][k * ntri..(k + 1) * ntri]));
            row.extend(f64s(&x.nu[k * nz..(k + 1) * nz]));
            row.extend(f64s(&x.s[k * ztri..(k + 1) * ztri]));
            row.extend(f64s(&x.a[k * nq * nq..(k + 1) * nq * nq]));
            w.push(&row)?;
        }
    }
    Ok(())
}

/// The divergence tables from the trackers of every (scenario, filter variant); shared with
/// `kfmc merge`, which rebuilds the trackers from the merged runs and summary.
pub(crate) fn divergence_tables(
    plan: &Plan,
    dir: &std::path::Path,
    trackers: &mut [DivergenceTracker],
    states: &[&str],
    thr: &[f64],
) -> Result<(TableWriter, TableWriter), OutputError> {
    let mut d = TableWriter::create(dir, "divergence", schema::divergence())?;
    let mut dr = TableWriter::create(dir, "divergence_runs", schema::divergence_runs())?;
    let nf = plan.filters.len();
    let max_scale = plan.noise_scales.last().copied();
    let scale_of = |j: Option<usize>| j.map(|j| plan.noise_scales[j]);
    for (si, s) in plan.scenarios.iter().enumerate() {
        for (fi, f) in plan.filters.iter().enumerate() {
            let tracker = &mut trackers[si * nf + fi];
            let [q, r] = scale_keys(f);
            let key = [Value::Str(&s.name), Value::Str(&f.label), q, r];
            for (i, state) in states.iter().enumerate() {
                // Runs that never crossed are censored beyond the largest scale: +∞ in the
                // ordering, so a quantile that needs them is unknown (null), not invented.
                // robustness.m records the largest multiplier tried for a state that never
                // crossed; by default such a run is censored instead.
                let never = if plan.never_crossed_largest {
                    max_scale.unwrap_or(f64::INFINITY)
                } else {
                    f64::INFINITY
                };
                // One pass over the runs per state writes its rows and spills the values
                // whose exact quantiles the summary row needs.
                let mut per_run = Spill::new(dir, 1);
                let mut diverged = 0i64;
                tracker.for_each_run(|r, crossings| {
                    let crossing = scale_of(crossings[i]);
                    let v = crossing.unwrap_or(never);
                    diverged += crossing.is_some() as i64;
                    per_run.push(&[v])?;
                    let mut row = key.to_vec();
                    row.extend([
                        Value::I64(Some(r as i64)),
                        Value::Str(state),
                        Value::F64(v.is_finite().then_some(v)),
                        Value::Bool(Some(crossing.is_none())),
                    ]);
                    dr.push(&row)
                })?;
                let q = &per_run.summarise(|_, _| true, &LEVELS)?[0].quantiles;
                let mut row = key.to_vec();
                row.extend([
                    Value::Str(state),
                    Value::F64(Some(thr[i])),
                    Value::F64(max_scale),
                    Value::F64(scale_of(tracker.mc_crossing(i))),
                    Value::I64(Some(plan.runs as i64)),
                    Value::I64(Some(diverged)),
                    Value::F64(q[0]),
                    Value::F64(q[1]),
                    Value::F64(q[2]),
                ]);
                d.push(&row)?;
            }
        }
    }
    Ok((d, dr))
}

/// The credibility columns of one `steps.parquet` row ([`schema::credibility_steps`]): per
/// block its ANEES with the per-step χ² band at the study's α, then NCI, inclination and the
/// credible filter's values at the step's run count.
fn credibility_step_values(
    c: &CredibilityStep,
    blocks: &[QuantityBlock],
    bands: &mut BandCache,
    nx: usize,
) -> Vec<Value<'static>> {
    let mut row = Vec::with_capacity(4 * blocks.len() + 4);
    for (b, blk) in blocks.iter().enumerate() {
        let a = c.block_anees(b);
        let band = a.and_then(|(_, m)| bands.band(m as u64 * blk.indices.len() as u64, m as u64));
        row.extend([
            Value::F64(a.map(|x| x.0)),
            Value::F64(band.map(|b| b.lo)),
            Value::F64(band.map(|b| b.hi)),
            Value::Bool(a.zip(band).map(|(x, b)| b.contains(x.0))),
        ]);
    }
    let reference = c.nci.and_then(|_| credible_reference(c.runs as usize, nx));
    row.extend([
        Value::F64(c.nci),
        Value::F64(c.inclination),
        Value::F64(reference.map(|r| r.0)),
        Value::F64(reference.map(|r| r.1)),
    ]);
    row
}

/// The credibility columns of the whole cell's `consistency.parquet` rows
/// ([`schema::consistency`]), over steps `first..=K`: per block the ANEES pooled over runs and
/// steps with the χ² band of that average at `alpha` if the steps were independent (N·K·n_b
/// degrees of freedom) and the fraction of steps whose block ANEES lies inside its per-step
/// band; then the time averages of NCI, inclination and their credible references.
fn credibility_averages(
    steps: &[CredibilityStep],
    blocks: &[QuantityBlock],
    alpha: f64,
    first: usize,
    nx: usize,
) -> Vec<Value<'static>> {
    let after = steps.get(first..).unwrap_or(&[]);
    let mut bands = BandCache::new(alpha);
    let mut row = Vec::with_capacity(4 * blocks.len() + 4);
    for (b, blk) in blocks.iter().enumerate() {
        let nb = blk.indices.len() as u64;
        let (mut sum, mut count, mut inside, mut judged) = (0.0, 0u64, 0u64, 0u64);
        for c in after {
            let (s, n) = c.blocks[b];
            if n == 0 {
                continue;
            }
            sum += s;
            count += u64::from(n);
            if let Some(band) = bands.band(u64::from(n) * nb, u64::from(n)) {
                judged += 1;
                inside += u64::from(band.contains(s / f64::from(n)));
            }
        }
        let mean = (count > 0).then(|| sum / count as f64);
        let band = mean.and_then(|_| average_chi2_band(nb as f64, count as f64, alpha));
        row.extend([
            Value::F64(mean),
            Value::F64(band.map(|b| b.lo)),
            Value::F64(band.map(|b| b.hi)),
            Value::F64((judged > 0).then(|| inside as f64 / judged as f64)),
        ]);
    }
    let (mut nci, mut incl, mut r_nci, mut r_incl, mut n) = (0.0, 0.0, 0.0, 0.0, 0usize);
    for c in after {
        if let (Some(a), Some(b), Some(r)) = (
            c.nci,
            c.inclination,
            credible_reference(c.runs as usize, nx),
        ) {
            nci += a;
            incl += b;
            r_nci += r.0;
            r_incl += r.1;
            n += 1;
        }
    }
    let avg = |s: f64| (n > 0).then(|| s / n as f64);
    row.extend([
        Value::F64(avg(nci)),
        Value::F64(avg(incl)),
        Value::F64(avg(r_nci)),
        Value::F64(avg(r_incl)),
    ]);
    row
}

#[cfg(test)]
mod tests {
    use super::*;

    const SPEC: &str = r#"
name = "feed"
runs = 2
[model]
kind = "planar_quadrotor"
[[scenarios]]
name = "basic"
duration_s = 1.0
[[filters]]
label = "ekf"
kind = "ekf"
[noise]
scales = [0.5, 1.0]
[divergence]
rmse_thresholds = [1.0, 1.0, 1.0, 1.0, 1.0, 1.0]
"#;

    fn plan() -> Plan {
        crate::experiment::parse(SPEC, std::path::Path::new("feed.toml")).expect("a valid spec")
    }

    /// A runs row as the study writes it: state 0's RMSE `x0`, state 1's `x1`, the others 0.5.
    fn run_row(
        plan: &Plan,
        scale: usize,
        run: Option<i64>,
        x0: f64,
        x1: Option<f64>,
    ) -> Vec<Value<'_>> {
        let mut row = cell_key(
            &plan.scenarios[0].name,
            plan.noise_scales[scale],
            &plan.filters[0],
        )
        .to_vec();
        row.extend([
            Value::I64(run),
            Value::U64(7),
            Value::Str("ok"),
            Value::I64(None),
            Value::Str(""),
            Value::F64(Some(x0)),
            Value::F64(x1),
        ]);
        row.extend([Value::F64(Some(0.5)); 4]);
        row.extend([Value::F64(None), Value::F64(None), Value::I64(Some(0))]);
        row
    }

    /// The summary rows of a (cell, filter): state `i`'s mean RMSE `means[i]`.
    fn summary_rows<'a>(plan: &'a Plan, scale: usize, means: &[f64]) -> Vec<Vec<Value<'a>>> {
        means
            .iter()
            .map(|m| {
                let mut row = cell_key(
                    &plan.scenarios[0].name,
                    plan.noise_scales[scale],
                    &plan.filters[0],
                )
                .to_vec();
                row.extend([
                    Value::Str("x"),
                    Value::I64(Some(2)),
                    Value::I64(Some(0)),
                    Value::F64(Some(*m)),
                ]);
                row.extend([Value::F64(None); 4]);
                row
            })
            .collect()
    }

    fn why(e: OutputError) -> String {
        match e {
            OutputError::Mismatch { why, .. } => why,
            other => panic!("{other}"),
        }
    }

    const BAD: &dyn Fn(&str) -> OutputError = &|why: &str| OutputError::Mismatch {
        path: "t".into(),
        why: why.into(),
    };

    #[test]
    fn the_feed_gives_the_crossings_of_the_rows_it_reads() {
        let dir = tempfile::tempdir().unwrap();
        let plan = plan();
        let mut feed = DivergenceFeed::new(&plan, dir.path());
        let runs = [
            run_row(&plan, 0, Some(0), 0.5, Some(0.5)),
            // A failed run's RMSE is null: it counts as crossed.
            run_row(&plan, 0, Some(1), 2.0, None),
            run_row(&plan, 1, Some(0), 1.5, Some(0.5)),
            run_row(&plan, 1, Some(1), 0.5, Some(0.5)),
        ];
        for row in &runs {
            assert_eq!(row.len(), feed.runs_columns().len());
            feed.run_row(row, BAD).unwrap();
        }
        let mut summary = summary_rows(&plan, 0, &[0.5, 0.5, 3.0, 0.5, 0.5, 0.5]);
        summary.extend(summary_rows(&plan, 1, &[0.5, 0.5, 0.5, 5.0, 0.5, 0.5]));
        for row in &summary {
            assert_eq!(row.len(), feed.summary_columns().len());
            feed.summary_row(row, BAD).unwrap();
        }
        let mut trackers = feed.into_trackers();
        assert_eq!(trackers.len(), 1);
        let t = &mut trackers[0];
        let mc: Vec<Option<usize>> = (0..6).map(|i| t.mc_crossing(i)).collect();
        assert_eq!(mc, [None, None, Some(0), Some(1), None, None]);
        let mut per_run = Vec::new();
        t.for_each_run(|r, c| {
            per_run.push((r, c[..2].to_vec(), c[2..].iter().all(Option::is_none)));
            Ok(())
        })
        .unwrap();
        assert_eq!(
            per_run,
            [
                (0, vec![Some(1), None], true),
                (1, vec![Some(0), Some(0)], true)
            ]
        );
    }

    #[test]
    fn a_row_the_plan_does_not_have_is_refused_for_the_caller_to_name() {
        let dir = tempfile::tempdir().unwrap();
        let plan = plan();
        let mut feed = DivergenceFeed::new(&plan, dir.path());
        let mut row = run_row(&plan, 0, Some(0), 0.5, Some(0.5));
        row[0] = Value::Str("elsewhere");
        let e = feed.run_row(&row, BAD).unwrap_err();
        assert_eq!(why(e), "names a cell the spec does not have");
        let row = run_row(&plan, 0, None, 0.5, Some(0.5));
        assert_eq!(
            why(feed.run_row(&row, BAD).unwrap_err()),
            "has no run index"
        );
        let mut rows = summary_rows(&plan, 0, &[0.5; 6]);
        rows[5][1] = Value::F64(Some(3.0));
        for row in &rows[..5] {
            feed.summary_row(row, BAD).unwrap();
        }
        let e = feed.summary_row(&rows[5], BAD).unwrap_err();
        assert_eq!(why(e), "names a cell the spec does not have");
    }
}
