//! The in-order fold: each unit's result into its cell's accumulators, and a finished cell
//! into the rows of the runs, steps, summary, consistency, sensors, traces and estimates
//! tables.

use super::resume::*;
use super::rows::*;
use crate::error::OutputError;
use crate::experiment::Plan;
use crate::metrics::blocks::QuantityBlock;
use crate::metrics::consistency::{
    BandCache, ConsistencyFold, SEQUENTIAL, VERDICT, average_chi2_band,
};
use crate::metrics::credibility::{CredibilityFold, CredibilityStep, credible_reference};
use crate::metrics::divergence::DivergenceTracker;
use crate::metrics::spill::Spill;
use crate::metrics::{FilterRun, RunStatus, StepAccumulator};
use crate::output::{TableWriter, Value};
use crate::sequential::{Decision, Gate};
use crate::trial::{RunTrace, Trial, Unit, UnitResult};
use std::path::PathBuf;
use std::time::Instant;

/// The per-cell state while its runs are being folded.
pub(super) struct CellState {
    pub(super) acc: Vec<StepAccumulator>,
    /// Per filter: the runs' consistency sums folded for the whole cell and each subset
    /// (when the study asks for the tests), in bounded memory.
    pub(super) consistency: Vec<ConsistencyFold>,
    /// Per filter (when the study asks for the tests): block NEES sums and each run's errors
    /// for the credibility measures.
    pub(super) credibility: Vec<CredibilityFold>,
    /// Per filter: RMSE rows of the runs that completed (failures excluded), in bounded
    /// memory for the exact quantiles of the summary.
    pub(super) rmse: Vec<Spill>,
    pub(super) failed: Vec<u64>,
    /// One row per run: each world metric's value.
    pub(super) world: Spill,
    /// Per filter, under a sequential gate: its decision once a look made it (or the last
    /// look left it undecided).
    pub(super) decisions: Vec<Option<Decided>>,
}

/// A sequential gate over a study's cells: the gate, which filters it waits for, and the
/// table of its looks.
pub(super) struct SequentialState<'a> {
    pub(super) gate: &'a Gate,
    /// Per filter: whether its verdict gates the cell (a filter that has a covariance; one
    /// without has no verdict to wait for).
    pub(super) gating: Vec<bool>,
    /// `sequential.parquet`.
    pub(super) table: TableWriter,
}

/// The look that settled one filter's verdict in a cell.
#[derive(Clone, Debug)]
pub(super) struct Decided {
    /// The deciding look's runs.
    pub(super) runs: usize,
    /// The verdict's Bonferroni p-value at that look, `None` when it could not be computed.
    pub(super) p_value: Option<f64>,
    /// The look's boundaries on that p-value ([`Gate::p_boundaries`]).
    pub(super) reject_p: f64,
    pub(super) accept_p: Option<f64>,
    /// Consistent (the gate accepted), inconsistent, or `None`: undecided at the last look.
    pub(super) pass: Option<bool>,
    pub(super) direction: &'static str,
    pub(super) burn_in: Option<usize>,
}

/// `estimates.parquet` (`--export-estimates`) and what its rows of each filter variant
/// write in its variant columns ([`Plan::export_variant_keys`]).
pub(super) struct EstimatesTable {
    pub(super) table: TableWriter,
    /// Per filter variant: its values in the file's variant columns, in their order.
    pub(super) variant_keys: Vec<Vec<Value<'static>>>,
}

pub(super) struct Aggregator<'a> {
    pub(super) plan: &'a Plan,
    pub(super) trial: &'a dyn Trial,
    pub(super) states: Vec<&'a str>,
    pub(super) runs: TableWriter,
    pub(super) steps: TableWriter,
    /// `run_steps.parquet` (`consistency.per_step_runs`): every run's NEES and NIS per step.
    pub(super) run_steps: Option<TableWriter>,
    pub(super) summary: TableWriter,
    pub(super) traces: Option<TableWriter>,
    /// `estimates.parquet` (`--export-estimates`): every run in the exchange format.
    pub(super) estimates: Option<EstimatesTable>,
    pub(super) consistency: Option<TableWriter>,
    pub(super) sensors: Option<TableWriter>,
    pub(super) bands: BandCache,
    /// The layout's blocks of quantities, when the study asks for the consistency tests.
    pub(super) blocks: Vec<QuantityBlock>,
    /// Per (scenario, filter).
    pub(super) divergence: Vec<DivergenceTracker>,
    pub(super) cell: Option<(usize, usize, CellState)>,
    /// Where the cells' spills put their scratch files (the folder being written).
    pub(super) scratch: PathBuf,
    /// The checkpoint being kept, when the study is resumable.
    pub(super) checkpoint: Option<Checkpointer>,
    /// The sequential gate, when the study runs under one: cells then end where it says,
    /// not at the declared runs.
    pub(super) sequential: Option<SequentialState<'a>>,
}

impl Aggregator<'_> {
    /// Folds one unit's result: its rows of the runs, run_steps, estimates and traces
    /// tables, and its filters into the cell's accumulators; the cell's last run (in a fixed
    /// study) finishes the cell.
    pub(super) fn fold(&mut self, r: UnitResult) -> Result<(), OutputError> {
        let plan = self.plan;
        let Unit {
            scenario,
            scale,
            run,
        } = r.unit;
        if self
            .cell
            .as_ref()
            .is_none_or(|(s, j, _)| (*s, *j) != (scenario, scale))
        {
            self.cell = Some((scenario, scale, self.new_cell(scenario)));
        }
        let sname = plan.scenarios[scenario].name.as_str();
        let noise = plan.noise_scales[scale];
        if !r.world_metrics.is_empty() {
            self.open_cell().world.push(&r.world_metrics)?;
        }
        for (fi, fr) in r.filters.iter().enumerate() {
            let key = cell_key(sname, noise, &plan.filters[fi]);
            self.write_run(key, run, r.seed, fr)?;
            self.accumulate(scenario, scale, run, fi, fr)?;
        }
        if let (Some(tr), Some(w)) = (&r.trace, self.estimates.as_mut()) {
            // A filter that failed numerically is marked failed from its failing step on.
            let failed_from: Vec<Option<usize>> = r
                .filters
                .iter()
                .map(|f| match f.status {
                    RunStatus::NumericalFailure { step, .. } => Some(step),
                    _ => None,
                })
                .collect();
            write_estimates(w, plan, sname, noise, run, tr, &failed_from)?;
        }
        if let Some(tr) = r.trace.as_ref().filter(|_| run < plan.trace_runs) {
            self.write_traces(sname, noise, run, tr)?;
        }
        if run + 1 == plan.runs && self.sequential.is_none() {
            self.finish_cell()?;
            self.cell_boundary(scenario * plan.noise_scales.len() + scale + 1)?;
        }
        Ok(())
    }

    /// The empty accumulators of a cell of `scenario`, for every filter.
    fn new_cell(&self, scenario: usize) -> CellState {
        let plan = self.plan;
        let nx = self.states.len();
        let nf = plan.filters.len();
        let steps = self.trial.steps(scenario);
        // The whole cell, then each subset: its first N runs.
        let consistency_bounds: Vec<usize> = std::iter::once(usize::MAX)
            .chain(
                plan.consistency
                    .iter()
                    .flat_map(|c| c.subsets.iter().map(|s| s.0)),
            )
            .collect();
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
                    .map(|_| CredibilityFold::new(&self.scratch, nx, self.blocks.len(), steps))
                    .collect()
            } else {
                Vec::new()
            },
            failed: vec![0; nf],
            world: Spill::new(&self.scratch, self.trial.world_metrics().len()),
            decisions: vec![None; nf],
        }
    }

    /// The cell being folded.
    fn open_cell(&mut self) -> &mut CellState {
        &mut self.cell.as_mut().expect("fold opens the cell").2
    }

    /// One filter's run: its row of `runs.parquet`, and its steps in `run_steps.parquet`
    /// when the study keeps them.
    fn write_run(
        &mut self,
        key: [Value<'_>; 5],
        run: usize,
        seed: u64,
        fr: &FilterRun,
    ) -> Result<(), OutputError> {
        let left_out = fr.status.left_out();
        let mut row = key.to_vec();
        row.extend([
            Value::I64(Some(run as i64)),
            Value::U64(seed),
            Value::Str(fr.status.label()),
            Value::I64(fr.status.step().map(|s| s as i64)),
            Value::Str(fr.status.detail().unwrap_or("")),
        ]);
        row.extend(
            fr.rmse
                .iter()
                .map(|v| Value::F64((!left_out).then_some(*v))),
        );
        row.extend([
            Value::F64(fr.nees_mean),
            Value::F64(fr.nis_mean),
            Value::I64(Some(fr.covariance_repairs as i64)),
        ]);
        self.runs.push(&row)?;
        if let Some(w) = self.run_steps.as_mut() {
            write_run_steps(w, key, run, &fr.steps, self.plan.dt_s())?;
        }
        Ok(())
    }

    /// Filter `fi`'s run into the open cell's accumulators (steps, consistency, credibility,
    /// RMSE or a failure) and its scenario's divergence tracker.
    fn accumulate(
        &mut self,
        scenario: usize,
        scale: usize,
        run: usize,
        fi: usize,
        fr: &FilterRun,
    ) -> Result<(), OutputError> {
        let plan = self.plan;
        let failed = matches!(fr.status, RunStatus::NumericalFailure { .. });
        let left_out = fr.status.left_out();
        let (_, _, cell) = self.cell.as_mut().expect("fold opens the cell");
        cell.acc[fi].fold(&fr.steps);
        if let Some(c) = &fr.consistency {
            cell.consistency[fi].push(run, c)?;
        }
        if let Some(c) = cell.credibility.get_mut(fi) {
            c.push(&fr.steps)?;
        }
        // A missing run is neither a completed run nor a failure (`runs_failed`).
        if failed {
            cell.failed[fi] += 1;
        } else if !left_out {
            cell.rmse[fi].push(&fr.rmse)?;
        }
        if let Some(thr) = &plan.rmse_thresholds {
            let rmse: Vec<f64> = if left_out {
                vec![f64::NAN; self.states.len()]
            } else {
                fr.rmse.clone()
            };
            self.divergence[scenario * plan.filters.len() + fi]
                .observe_run(run, scale, &rmse, thr)?;
        }
        Ok(())
    }

    /// A traced run's rows of `traces.parquet`: per filter and step, the inputs, truth,
    /// measurements, world states, estimate and covariance.
    fn write_traces(
        &mut self,
        sname: &str,
        noise: f64,
        run: usize,
        tr: &RunTrace,
    ) -> Result<(), OutputError> {
        let Some(w) = self.traces.as_mut() else {
            return Ok(());
        };
        let plan = self.plan;
        let layout = self.trial.layout();
        let nx = self.states.len();
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
                let f64s = |v: &[f64]| v.iter().map(|x| Value::F64(Some(*x))).collect::<Vec<_>>();
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
        Ok(())
    }

    /// The journaled tables, in a fixed order.
    pub(super) fn journaled_tables(&mut self) -> impl Iterator<Item = &mut TableWriter> {
        [&mut self.runs, &mut self.steps, &mut self.summary]
            .into_iter()
            .chain(self.run_steps.as_mut())
            .chain(self.traces.as_mut())
            .chain(self.estimates.as_mut().map(|e| &mut e.table))
            .chain(self.consistency.as_mut())
            .chain(self.sensors.as_mut())
            .chain(self.sequential.as_mut().map(|q| &mut q.table))
    }

    /// Look `k` of the sequential gate at the open cell, whose first `gate.looks[k]` runs
    /// are folded: judges each gating filter not yet decided and writes its row of
    /// `sequential.parquet`. Returns whether the cell is settled: every gating filter
    /// decided (a cell without one runs to the last look), or the last look.
    pub(super) fn look(&mut self, k: usize) -> Result<bool, OutputError> {
        let plan = self.plan;
        let Some(seq) = self.sequential.as_mut() else {
            return Ok(true);
        };
        let Some((scenario, scale, cell)) = self.cell.as_mut() else {
            return Ok(true);
        };
        let (gate, last) = (seq.gate, k + 1 == seq.gate.looks.len());
        let alpha = plan.consistency.as_ref().map_or(plan.alpha, |c| c.alpha);
        let (reject_p, accept_p) = gate.p_boundaries(k);
        for (fi, f) in plan.filters.iter().enumerate() {
            if !seq.gating[fi] || cell.decisions[fi].is_some() {
                continue;
            }
            let sums = cell.consistency[fi].current()?;
            let tests = sums.tests(&self.states, alpha, (None, None));
            let verdict = tests.iter().find(|t| t.test == VERDICT);
            let p_value = verdict.and_then(|t| t.p_value).filter(|p| p.is_finite());
            let decision = p_value.map(|p| gate.decide(k, p));
            let direction = verdict
                .and_then(|t| t.direction)
                .filter(|_| decision == Some(Decision::Reject))
                .map_or("", |d| d.label());
            let label = match decision {
                Some(Decision::Reject) => "reject",
                Some(Decision::Accept) => "accept",
                Some(Decision::Continue) => "continue",
                None if last => "undecided",
                None => "continue",
            };
            let mut row = cell_key(
                &plan.scenarios[*scenario].name,
                plan.noise_scales[*scale],
                f,
            )
            .to_vec();
            row.extend([
                Value::I64(Some(k as i64 + 1)),
                Value::I64(Some(gate.looks[k] as i64)),
                Value::F64(p_value),
                Value::F64(Some(gate.design.efficacy[k])),
                Value::F64(gate.design.futility.as_ref().map(|b| b[k])),
                Value::F64(Some(reject_p)),
                Value::F64(accept_p),
                Value::Str(label),
                Value::Str(direction),
                Value::F64(Some(alpha)),
            ]);
            seq.table.push(&row)?;
            if decision != Some(Decision::Continue) && (decision.is_some() || last) {
                cell.decisions[fi] = Some(Decided {
                    runs: gate.looks[k],
                    p_value,
                    reject_p,
                    accept_p,
                    pass: decision.map(|d| d == Decision::Accept),
                    direction,
                    burn_in: sums.burn_in(),
                });
            }
        }
        let gating = seq.gating.iter().any(|g| *g);
        let decided = seq
            .gating
            .iter()
            .zip(&cell.decisions)
            .all(|(g, d)| !g || d.is_some());
        Ok(last || (gating && decided))
    }

    /// After the last row of cell `end_cell − 1`: notes the boundary, and checkpoints when it
    /// is time.
    pub(super) fn cell_boundary(&mut self, end_cell: usize) -> Result<(), OutputError> {
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
    pub(super) fn write_checkpoint(&mut self) -> Result<Option<u64>, OutputError> {
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

    pub(super) fn finish_cell(&mut self) -> Result<(), OutputError> {
        let plan = self.plan;
        let Some((scenario, scale, mut cell)) = self.cell.take() else {
            return Ok(());
        };
        let sname = plan.scenarios[scenario].name.as_str();
        let noise = plan.noise_scales[scale];
        self.write_sensors(&mut cell, sname, noise)?;
        for (fi, f) in plan.filters.iter().enumerate() {
            let key = cell_key(sname, noise, f);
            let credibility = match cell.credibility.get_mut(fi) {
                Some(c) => Some(c.finish()?),
                None => None,
            };
            let inside = self.write_steps(&key, &cell.acc[fi], credibility.as_deref())?;
            self.write_consistency(&key, fi, &mut cell, credibility.as_deref(), inside)?;
            let means = self.write_summary(&key, fi, &mut cell)?;
            if let Some(thr) = &plan.rmse_thresholds {
                self.divergence[scenario * plan.filters.len() + fi]
                    .observe_mean(scale, &means, thr);
            }
        }
        Ok(())
    }

    /// The cell's rows of `sensors.parquet`: each world metric summarised over its runs.
    fn write_sensors(
        &mut self,
        cell: &mut CellState,
        sname: &str,
        noise: f64,
    ) -> Result<(), OutputError> {
        let Some(w) = self.sensors.as_mut() else {
            return Ok(());
        };
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
        Ok(())
    }

    /// One filter's rows of `steps.parquet`; returns the fractions of steps 1..K whose ANEES
    /// and ANIS lie inside their per-step bands (the descriptive `*_steps_inside` tests).
    fn write_steps(
        &mut self,
        key: &[Value<'_>],
        acc: &StepAccumulator,
        credibility: Option<&[CredibilityStep]>,
    ) -> Result<(Option<f64>, Option<f64>), OutputError> {
        let dt = self.plan.dt_s();
        let n = self.states.len() as u64;
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
            let mut row = key.to_vec();
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
            if let Some(c) = credibility {
                row.extend(credibility_step_values(
                    &c[k],
                    &self.blocks,
                    &mut self.bands,
                    self.states.len(),
                ));
            }
            self.steps.push(&row)?;
        }
        let frac = |i: u64, n: u64| (n > 0).then(|| i as f64 / n as f64);
        Ok((frac(nees_in, nees_steps), frac(nis_in, nis_steps)))
    }

    /// One filter's rows of `consistency.parquet`: the whole cell at the study's α, then each
    /// subset (its first N runs at its α), then a sequential gate's decision.
    fn write_consistency(
        &mut self,
        key: &[Value<'_>],
        fi: usize,
        cell: &mut CellState,
        credibility: Option<&[CredibilityStep]>,
        inside: (Option<f64>, Option<f64>),
    ) -> Result<(), OutputError> {
        let (Some(w), Some(cp)) = (self.consistency.as_mut(), self.plan.consistency.as_ref())
        else {
            return Ok(());
        };
        // The per-step fractions are descriptive and kept for the whole cell only, as are the
        // credibility columns (null on a subset's and the gate's rows).
        let mut evaluations = vec![(cp.alpha, inside)];
        evaluations.extend(cp.subsets.iter().map(|&(_, alpha)| (alpha, (None, None))));
        let nulls = vec![Value::F64(None); 4 * self.blocks.len() + 4];
        let folded = cell.consistency[fi].finish()?;
        for (ev, (sums, (alpha, inside))) in folded.into_iter().zip(evaluations).enumerate() {
            let burn_in = sums.burn_in();
            let cred: Vec<Value<'static>> = match credibility {
                Some(c) if ev == 0 => credibility_averages(
                    c,
                    &self.blocks,
                    alpha,
                    burn_in.map_or(1, |b| b + 1).max(1),
                    self.states.len(),
                ),
                Some(_) => nulls.clone(),
                None => Vec::new(),
            };
            for t in sums.tests(&self.states, alpha, inside) {
                let mut row = key.to_vec();
                row.extend([
                    Value::Str(&t.test),
                    Value::F64(Some(t.statistic)),
                    Value::F64(t.lower),
                    Value::F64(t.upper),
                    Value::F64(t.dof),
                    Value::F64(t.p_value),
                    // A test that could not be computed neither passed nor failed.
                    Value::Bool(t.computed().then_some(t.pass)),
                    Value::Str(t.direction.map_or("", |d| d.label())),
                    Value::F64(Some(alpha)),
                    Value::I64(Some(sums.runs() as i64)),
                    Value::I64(burn_in.map(|b| b as i64)),
                ]);
                row.extend(cred.iter().cloned());
                w.push(&row)?;
            }
        }
        if let Some(d) = &cell.decisions[fi] {
            let mut row = key.to_vec();
            row.extend(sequential_values(d, cp.alpha));
            if credibility.is_some() {
                row.extend(nulls);
            }
            w.push(&row)?;
        }
        Ok(())
    }

    /// One filter's rows of `summary.parquet`; returns each state's mean RMSE over the runs
    /// (NaN where none completed) for the divergence trackers.
    fn write_summary(
        &mut self,
        key: &[Value<'_>],
        fi: usize,
        cell: &mut CellState,
    ) -> Result<Vec<f64>, OutputError> {
        let mut means = Vec::with_capacity(self.states.len());
        let sums = cell.rmse[fi].summarise(|_, _| true, &LEVELS)?;
        for (state, s) in self.states.iter().zip(&sums) {
            means.push(s.mean.unwrap_or(f64::NAN));
            let mut row = key.to_vec();
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
        Ok(means)
    }
}

/// Writes one run's rows of `run_steps.parquet` for one filter: every step it reached, NEES
/// and NIS as recorded (NaN, "not defined", as null).
fn write_run_steps(
    w: &mut TableWriter,
    key: [Value<'_>; 5],
    run: usize,
    steps: &crate::metrics::StepValues,
    dt: f64,
) -> Result<(), OutputError> {
    let defined = |x: f64| (!x.is_nan()).then_some(x);
    let (nees, nis, dof) = (steps.nees(), steps.nis(), steps.nis_dof());
    for k in 0..steps.completed() {
        let mut row = key.to_vec();
        row.extend([
            Value::I64(Some(run as i64)),
            Value::I64(Some(k as i64)),
            Value::F64(Some(k as f64 * dt)),
            Value::F64(defined(nees[k])),
            Value::F64(defined(nis[k])),
            Value::I64(Some(i64::from(dof[k]))),
        ]);
        w.push(&row)?;
    }
    Ok(())
}

/// The `sequential` row of consistency.parquet after its cell key: the gate's decision as a
/// test row (statistic and p-value: the verdict's p at the deciding look; lower and upper:
/// that look's reject and accept boundaries on it; runs: the look's).
fn sequential_values(d: &Decided, alpha: f64) -> [Value<'static>; 11] {
    [
        Value::Str(SEQUENTIAL),
        Value::F64(d.p_value),
        Value::F64(Some(d.reject_p)),
        Value::F64(d.accept_p),
        Value::F64(None),
        Value::F64(d.p_value),
        Value::Bool(d.pass),
        Value::Str(d.direction),
        Value::F64(Some(alpha)),
        Value::I64(Some(d.runs as i64)),
        Value::I64(d.burn_in.map(|b| b as i64)),
    ]
}

/// Writes one run's rows of `estimates.parquet`: every kfmc filter (external ones are what
/// is being scored, not exported), in the exchange format of [`crate::score`].
pub(super) fn write_estimates(
    w: &mut EstimatesTable,
    plan: &Plan,
    scenario: &str,
    noise: f64,
    run: usize,
    tr: &RunTrace,
    failed_from: &[Option<usize>],
) -> Result<(), OutputError> {
    let nq = plan.layout().quantities.len();
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
            row.extend_from_slice(&w.variant_keys[fi]);
            row.push(Value::Bool(Some(failed_from[fi].is_some_and(|f| f <= k))));
            row.extend(estimate(&tr.est[fi][k * nq..(k + 1) * nq]));
            row.extend(f64s(&tr.cov[fi][k * ntri..(k + 1) * ntri]));
            row.extend(f64s(&x.nu[k * nz..(k + 1) * nz]));
            row.extend(f64s(&x.s[k * ztri..(k + 1) * ztri]));
            row.extend(f64s(&x.a[k * nq * nq..(k + 1) * nq * nq]));
            w.table.push(&row)?;
        }
    }
    Ok(())
}

/// The credibility columns of one `steps.parquet` row ([`schema::credibility_steps`]): per
/// block its ANEES with the per-step χ² band at the study's α, then NCI, inclination and the
/// credible filter's values at the step's run count.
pub(super) fn credibility_step_values(
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
pub(super) fn credibility_averages(
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
