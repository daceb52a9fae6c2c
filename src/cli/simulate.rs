//! `kfmc simulate`: write every run's world for an estimator outside kfmc: truth.parquet,
//! measurements.parquet, initial.parquet and a manifest saying what they mean. The runs are
//! those `kfmc run` gives its own filters.

use super::*;

/// The arguments of `kfmc simulate`.
#[derive(Debug, clap::Args)]
pub struct Simulate {
    /// The spec and the shared overrides.
    #[command(flatten)]
    pub study: StudyArgs,
    /// Simulate only part I of N (0-based), into `<out>/parts/` (or from SLURM_ARRAY_TASK_ID,
    /// or JOB_COMPLETION_INDEX with --shards).
    #[arg(long, value_name = "I/N", conflicts_with = "shards")]
    pub shard: Option<String>,
    /// The number of parts when the index comes from the scheduler's environment.
    #[arg(long, value_name = "N")]
    pub shards: Option<usize>,
}

impl Simulate {
    /// Runs the command.
    pub(super) fn execute(self, registry: &Registry) -> anyhow::Result<()> {
        let Self {
            study,
            shard,
            shards,
        } = self;
        let shard = shard_arg(&study.spec, shard.as_deref(), shards)?;
        let plan = study.plan(registry, None)?;
        let threads = study.threads(study.quiet);
        let observer = ProgressObserver::new(!study.quiet);
        let report = crate::simulate::simulate(
            &plan,
            &crate::study::ExecOptions {
                threads,
                force: study.force,
                shard,
                checkpoints: None,
            },
            &observer,
        )
        .map_err(anyhow::Error::from)
        .map_err(|e| e.context(format!("simulating {}", study.spec.display())))?;
        if !study.quiet {
            outln!(
                "{} runs simulated in {:.1} s → {}",
                report.runs,
                report.wall_s,
                report.output.display()
            );
            print_tables(&report.tables);
        }
        Ok(())
    }
}
