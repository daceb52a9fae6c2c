//! `kfmc simulate`: the world of every run written as files, for estimators outside kfmc.
//!
//! The runs are the very runs `kfmc run` gives its own filters (same seeds, same streams), so
//! estimates made from these files and scored by `kfmc score` are paired with kfmc's filters
//! run by run. Tables: `truth` (the true quantities and world states), `measurements` (what
//! a filter receives: z with nulls where a sensor did not report, and the inputs) and
//! `initial` (each run's seed and the prior kfmc's filters start from); the manifest says
//! what they mean ([`crate::output::manifest::ExchangeEntry`]) and gives the world stamp an
//! estimates file made from them carries. A run's step-0 row of `measurements` has null z:
//! the run starts from its prior, and no sensor reports at step 0.

use std::time::{Instant, SystemTime, UNIX_EPOCH};

use crate::error::{KfmcError, OutputError};
use crate::experiment::Plan;
use crate::output::folder::StudyFolder;
use crate::output::manifest::{ExchangeEntry, ExternalFilterEntry, StudyKind};
use crate::output::{TableWriter, Value, schema};
use crate::runner::{RunObserver, execute_groups, window_for};
use crate::study::{ExecOptions, StudyReport};
use crate::trial::Unit;

/// The plan that scores outside estimates against the `kfmc simulate` folder `dir` (`kfmc
/// score DIR`, Python's `kfmc.score`): the spec recorded in the folder, checked against its
/// manifest (a whole simulation, unaltered), with the folder's runs and master seed, writing
/// into `out` (default `DIR/score`). The estimates are the caller's to attach
/// ([`crate::check::attach_estimates_from`]).
pub fn scoring_plan(
    dir: &std::path::Path,
    out: Option<std::path::PathBuf>,
    registry: &crate::system::Registry,
) -> Result<Plan, KfmcError> {
    let refuse = |why: String| {
        KfmcError::from(OutputError::Mismatch {
            path: dir.to_path_buf(),
            why,
        })
    };
    if dir.is_file() {
        return Err(refuse(
            "is a file; kfmc score takes the folder `kfmc simulate` wrote: kfmc score SIM_DIR --estimates FILE…".into(),
        ));
    }
    let manifest = crate::output::folder::verify(dir)?;
    if manifest.exchange.is_none() {
        return Err(refuse(
            "was not written by `kfmc simulate` (its manifest has no [exchange] section)".into(),
        ));
    }
    if manifest.shard.is_some() {
        return Err(refuse(
            "is one part of a sharded simulation; score the whole simulation's folder (`kfmc merge` puts the parts together)".into(),
        ));
    }
    let spec_path = std::path::PathBuf::from(&manifest.spec_path);
    let mut plan = crate::experiment::parse_with(&manifest.spec, &spec_path, registry)?;
    if plan.spec_hash != manifest.spec_hash {
        return Err(refuse(format!(
            "holds an altered simulation: its recorded spec hashes to {}, its manifest says {}",
            plan.spec_hash, manifest.spec_hash
        )));
    }
    plan.apply(&crate::experiment::Overrides {
        runs: Some(manifest.runs_per_cell as usize),
        master_seed: Some(manifest.master_seed),
        output: Some(out.unwrap_or_else(|| dir.join("score"))),
        trace_runs: None,
    })?;
    Ok(plan)
}

/// Writes the simulation of `plan` into `plan.output` (or its part folder): streamed, one run
/// at a time, committed like every study.
pub fn simulate(
    plan: &Plan,
    opts: &ExecOptions,
    observer: &dyn RunObserver,
) -> Result<StudyReport, KfmcError> {
    if plan.system.recorded() {
        return Err(KfmcError::Spec(crate::error::SpecErrors(vec![
            crate::error::SpecError {
                file: plan.spec_path.clone(),
                key_path: "model.kind".into(),
                message: format!(
                    "`{}` cannot simulate: its truth is recorded; judge its runs with `kfmc score --truth TRUTH --estimates EST --spec SPEC`",
                    plan.kind
                ),
            },
        ])));
    }
    let started = Instant::now();
    let started_unix_s = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_secs());
    // The world alone: no filter runs, and every run keeps its trajectories.
    let mut world_only = plan.clone();
    world_only.filters.clear();
    world_only.trace_runs = plan.runs;
    world_only.consistency = None;
    world_only.rmse_thresholds = None;
    world_only.export_estimates = false;
    let part_dir = opts.shard.map(|s| s.folder(&plan.output));
    let dir = part_dir.as_ref().unwrap_or(&plan.output);
    if opts.shard.is_some() {
        crate::output::folder::refuse_link(&plan.output.join("parts"))?;
    }
    let folder = StudyFolder::open_with(
        dir,
        StudyKind::Simulate,
        opts.force,
        &crate::study::inputs(plan),
    )?;
    let n_cells = plan.scenarios.len() * plan.noise_scales.len();
    let cells = opts.shard.map_or(0..n_cells, |s| s.cells(n_cells));
    let trial = world_only.trial();
    let layout = plan.layout();
    let states = layout.quantity_names();
    let (inputs, meas, world) = (
        layout.input_names(),
        layout.measurement_names(),
        layout.world_state_names(),
    );
    let (nq, nu, nz, nw) = (states.len(), inputs.len(), meas.len(), world.len());
    let mut truth = TableWriter::create(dir, "truth", schema::truth(&states, &world))?;
    let mut measurements =
        TableWriter::create(dir, "measurements", schema::measurements(&meas, &inputs))?;
    let mut initial: Option<TableWriter> = None;
    let dt = plan.dt_s();

    let (n_scales, n_runs) = (plan.noise_scales.len(), plan.runs);
    let unit_of = |i: usize| Unit {
        scenario: i / (n_scales * n_runs),
        scale: i / n_runs % n_scales,
        run: i % n_runs,
    };
    let first_unit = cells.start * n_runs;
    // Every run keeps its trajectory: the window holds as many as fit its bytes.
    execute_groups::<_, KfmcError>(
        (cells.end - cells.start) * n_runs,
        opts.threads,
        window_for(crate::study::trajectory_bytes(&world_only), opts.threads),
        (n_runs, trial.lanes()),
        |g| crate::study::run_group(trial.as_ref(), g, first_unit, &unit_of),
        observer,
        |r| {
            let u = r.unit;
            let scenario = plan.scenarios[u.scenario].name.as_str();
            let noise = plan.noise_scales[u.scale];
            let tr = r.trace.as_ref().ok_or_else(|| OutputError::Format {
                path: dir.clone(),
                message: format!("the {} system gave no trajectories to write", plan.kind),
            })?;
            let f64s = |v: &[f64]| v.iter().map(|x| Value::F64(Some(*x))).collect::<Vec<_>>();
            for k in 0..tr.truth.len() / nq {
                let key = [
                    Value::Str(scenario),
                    Value::F64(Some(noise)),
                    Value::I64(Some(u.run as i64)),
                    Value::I64(Some(k as i64)),
                    Value::F64(Some(k as f64 * dt)),
                ];
                let mut row = key.to_vec();
                row.extend(f64s(&tr.truth[k * nq..(k + 1) * nq]));
                row.extend(f64s(tr.world.get(k * nw..(k + 1) * nw).unwrap_or(&[])));
                truth.push(&row)?;
                let mut row = key.to_vec();
                if k == 0 {
                    // A run starts from its prior: no sensor reports at step 0. (The seeds'
                    // running mean is handed the noise-free h(x0) there, inside kfmc; that
                    // is not a measurement, and an external filter must not receive it.)
                    row.extend((0..nz).map(|_| Value::F64(None)));
                } else {
                    row.extend(f64s(&tr.z[k * nz..(k + 1) * nz]));
                }
                row.extend(f64s(&tr.u[k * nu..(k + 1) * nu]));
                measurements.push(&row)?;
            }
            if let Some((x0, p0)) = &tr.initial {
                if initial.is_none() {
                    initial = Some(TableWriter::create(
                        dir,
                        "initial",
                        schema::initial(&states),
                    )?);
                }
                let mut row = vec![
                    Value::Str(scenario),
                    Value::F64(Some(noise)),
                    Value::I64(Some(u.run as i64)),
                    Value::U64(r.seed),
                ];
                row.extend(f64s(x0));
                row.extend(f64s(p0));
                initial.as_mut().expect("created above").push(&row)?;
            }
            Ok(())
        },
    )?;
    let mut written = vec![truth, measurements];
    written.extend(initial);
    let finished = written
        .into_iter()
        .map(TableWriter::finish)
        .collect::<Result<Vec<_>, _>>()?;
    let wall_s = started.elapsed().as_secs_f64();
    let mut manifest =
        crate::study::manifest_for(&world_only, opts, started_unix_s, wall_s, cells.clone());
    manifest.kind = Some(StudyKind::Simulate);
    manifest.exchange = Some(ExchangeEntry {
        schema_version: crate::score::SCHEMA_VERSION,
        error_convention: crate::score::ERROR_CONVENTION.into(),
        run_seeds: "per run: seed column of initial.parquet (from the master seed, the scenario name and the run index)".into(),
        estimates_metadata: vec![
            crate::score::STAMP_KEY.into(),
            crate::score::SEED_KEY.into(),
        ],
        step_convention: Some(crate::system::filter_model::convention_of(
            plan.system.as_ref(),
        )),
        external_filters: external_filters(plan),
    });
    let tables = folder.commit(finished, manifest)?;
    Ok(StudyReport {
        output: dir.clone(),
        tables,
        wall_s,
        runs: ((cells.end - cells.start) * n_runs) as u64,
        cells_resumed: 0,
    })
}

/// The plan's external filters as the manifest lists them: each label once, with the
/// multipliers of the axes it declares (its variants are every pair of them).
pub fn external_filters(plan: &Plan) -> Vec<ExternalFilterEntry> {
    let mut out: Vec<ExternalFilterEntry> = Vec::new();
    for f in plan.filters.iter().filter(|f| f.external) {
        let i = match out.iter().position(|e| e.label == f.label) {
            Some(i) => i,
            None => {
                out.push(ExternalFilterEntry {
                    label: f.label.clone(),
                    q_scale: f.declared.q_scale.then(Vec::new),
                    r_scale: f.declared.r_scale.then(Vec::new),
                });
                out.len() - 1
            }
        };
        let e = &mut out[i];
        for (list, v) in [(&mut e.q_scale, f.q_scale), (&mut e.r_scale, f.r_scale)] {
            if let Some(list) = list
                && !list.contains(&v)
            {
                list.push(v);
            }
        }
    }
    out
}
