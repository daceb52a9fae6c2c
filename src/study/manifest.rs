//! The manifest a finished study commits with its tables.

use super::options::*;
use crate::experiment::Plan;
use crate::output::manifest::{FixEntry, Manifest, QuantityEntry, StudyKind};

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
        format: Some(crate::output::manifest::FORMAT.into()),
        kfmc_version: env!("CARGO_PKG_VERSION").to_string(),
        program: Some(plan.program.name.to_string()),
        program_version: Some(plan.program.version.to_string()),
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
                position: q.position.map(|a| a.name().to_string()),
                fixes: q
                    .fixes
                    .iter()
                    .map(|f| FixEntry {
                        sensor: f.sensor.clone(),
                        component: f.component.clone(),
                    })
                    .collect(),
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
        lanes: Some(plan.lanes.width() as u64),
        isa: Some(plan.lanes.isa().name().to_string()),
        started_unix_s,
        wall_s,
        runs_per_s: size.runs as f64 / wall_s.max(1e-9),
        // Filled in by the commit, with each table's size and checksum.
        tables: Vec::new(),
        files: Vec::new(),
        folders: Vec::new(),
        replacing: None,
        exchange: None,
        shard: opts.shard.map(|s| crate::output::manifest::ShardEntry {
            index: s.index as u64,
            count: s.count as u64,
            first_cell: cells.start as u64,
            end_cell: cells.end as u64,
        }),
        sequential: plan.sequential.as_ref().map(|gate| {
            let settings = plan.check_sequential.clone().unwrap_or_default();
            crate::output::manifest::SequentialEntry {
                looks: gate.looks.iter().map(|&n| n as u64).collect(),
                spending: settings.spending_name(),
                futility_beta: settings.futility_beta,
                futility_rho: settings.futility_beta.map(|_| settings.futility_rho),
                alpha: plan.consistency.as_ref().map_or(plan.alpha, |c| c.alpha),
            }
        }),
        spec: plan.spec_text.clone(),
    }
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
