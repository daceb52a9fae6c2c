//! The checkpoint a resumable study keeps, and what a study does with one it finds.

use super::options::*;
use crate::error::OutputError;
use crate::experiment::Plan;
use std::path::PathBuf;
use std::time::Instant;

/// Keeps a study's checkpoint: after a complete cell it notes where every journal ends, and
/// once `every` has passed it makes them durable and writes the index.
pub(super) struct Checkpointer {
    pub(super) dir: PathBuf,
    pub(super) every: std::time::Duration,
    pub(super) last: Instant,
    /// The study's identity; `cells_done` and `tables` describe the last checkpoint written.
    pub(super) index: crate::output::checkpoint::Index,
    /// The last cell boundary: cells done (from the first cell of the run) and the journals'
    /// positions there.
    pub(super) boundary: Option<(u64, Vec<crate::output::checkpoint::JournalEntry>)>,
    /// First cell of this folder's range.
    pub(super) first_cell: usize,
}

/// The identity a checkpoint of this run carries, with nothing done yet.
pub(super) fn checkpoint_identity(
    plan: &Plan,
    n_cells: usize,
    cells: &std::ops::Range<usize>,
) -> crate::output::checkpoint::Index {
    crate::output::checkpoint::Index {
        kfmc_version: env!("CARGO_PKG_VERSION").to_string(),
        spec_hash: plan.spec_hash.clone(),
        master_seed: plan.master_seed,
        world_stamp: plan.world_stamp(),
        runs_per_cell: plan.runs as u64,
        cells: n_cells as u64,
        first_cell: cells.start as u64,
        end_cell: cells.end as u64,
        trace_runs: plan.trace_runs as u64,
        export_estimates: plan.export_estimates,
        export_f32: plan.export_precision == crate::score::EstimatePrecision::F32,
        journal_format: crate::output::checkpoint::JOURNAL_FORMAT,
        cells_done: 0,
        tables: Vec::new(),
    }
}

/// The checkpoint this run continues from, after applying `opts.checkpoints.existing` to
/// whatever checkpoint is in `dir`.
pub(super) fn existing_checkpoint(
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
    if c.existing == ExistingCheckpoint::Discard {
        // Whatever is there, readable or not, is discarded unread.
        checkpoint::remove(dir)?;
        return Ok(None);
    }
    let found = match checkpoint::Index::read(dir) {
        Ok(None) => return Ok(None),
        Ok(Some(found)) => found,
        // An index that does not parse vouches for nothing a resume could continue: a
        // plain run starts over, `--resume` is told to.
        Err(OutputError::Format { .. }) if c.existing == ExistingCheckpoint::Refuse => {
            checkpoint::remove(dir)?;
            return Ok(None);
        }
        Err(e) => return Err(e),
    };
    let change = found.change_from(&checkpoint_identity(plan, n_cells, cells));
    let at = checkpoint::dir(dir);
    match (c.existing, change) {
        // Likewise an index whose counts contradict themselves.
        (ExistingCheckpoint::Refuse, None) if found.check(dir).is_err() => {
            checkpoint::remove(dir)?;
            Ok(None)
        }
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
