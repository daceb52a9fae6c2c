//! The options of a study execution and what it reports: settings that do not change its
//! results (threads, shards, checkpoints).

use std::path::PathBuf;

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
