//! `kfmc run`: run a Monte Carlo study and write its Parquet tables.

use super::*;

/// The arguments of `kfmc run`.
#[derive(Debug, clap::Args)]
pub struct Run {
    /// The spec and the overrides every study command shares.
    #[command(flatten)]
    pub study: StudyArgs,
    /// Runs per (scenario, noise scale) whose full trajectories go to traces.parquet.
    #[arg(long)]
    pub trace_runs: Option<usize>,
    /// Draw the figures (PNG) into `<out>/figures` when the run is done.
    #[arg(long)]
    pub plot: bool,
    /// Run only part I of N (0-based) of the plan, into `<out>/parts/`; `kfmc merge`
    /// combines the parts. Also read from a Slurm job array (SLURM_ARRAY_TASK_ID and
    /// SLURM_ARRAY_TASK_COUNT) or, with --shards, a Kubernetes Indexed Job
    /// (JOB_COMPLETION_INDEX).
    #[arg(long, value_name = "I/N", conflicts_with = "shards")]
    pub shard: Option<String>,
    /// The number of parts when the index comes from the scheduler's environment.
    #[arg(long, value_name = "N")]
    pub shards: Option<usize>,
    /// Continue the interrupted run whose checkpoint is in the output folder: its complete
    /// cells are kept and the tables come out byte-identical to an uninterrupted run. A
    /// checkpoint of a changed spec, seed or run count is refused, naming what changed.
    /// Without a checkpoint, the study runs from the start.
    #[arg(long, conflicts_with = "restart")]
    pub resume: bool,
    /// Discard the checkpoint of an interrupted run and start over.
    #[arg(long)]
    pub restart: bool,
    /// Least seconds between two checkpoints (one follows each complete cell once this
    /// much has passed); a kill loses at most this much work plus the cell in progress.
    #[arg(long, value_name = "SECONDS", default_value_t = 10.0, value_parser = seconds)]
    pub checkpoint_every: f64,
    /// Keep no checkpoint (an interrupted run then starts over).
    #[arg(long, conflicts_with_all = ["resume", "checkpoint_every"])]
    pub no_checkpoint: bool,
    /// Also write every run of kfmc's filters in the estimates exchange format
    /// (`estimates.parquet`: est_*, P_*, nu_*, S_*, A_*), as `kfmc score` reads it.
    #[arg(long)]
    pub export_estimates: bool,
    /// The precision of the exported covariance, innovation, S and A columns: f64 (default)
    /// or f32 (about half the file; the estimates est_*/quat_* stay float64).
    #[arg(
        long,
        value_enum,
        value_name = "PRECISION",
        default_value = "f64",
        requires = "export_estimates"
    )]
    pub export_estimates_precision: PrecisionArg,
}

/// `--export-estimates-precision`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum PrecisionArg {
    /// float64 values.
    F64,
    /// float32 covariance, innovation, S and A.
    F32,
}

impl Run {
    /// Runs the command.
    pub(super) fn execute(self, registry: &Registry) -> anyhow::Result<()> {
        let Self {
            study,
            trace_runs,
            plot,
            shard,
            shards,
            resume,
            restart,
            checkpoint_every,
            no_checkpoint,
            export_estimates,
            export_estimates_precision,
        } = self;
        let checkpoints = (!no_checkpoint).then(|| crate::study::Checkpoints {
            every: std::time::Duration::from_secs_f64(checkpoint_every),
            existing: if resume {
                crate::study::ExistingCheckpoint::Resume
            } else if restart {
                crate::study::ExistingCheckpoint::Discard
            } else {
                crate::study::ExistingCheckpoint::Refuse
            },
        });
        let shard = shard_arg(&study.spec, shard.as_deref(), shards)?;
        let mut plan = study.plan(registry, trace_runs)?;
        plan.export_estimates = export_estimates;
        plan.export_precision = match export_estimates_precision {
            PrecisionArg::F64 => crate::score::EstimatePrecision::F64,
            PrecisionArg::F32 => crate::score::EstimatePrecision::F32,
        };
        let threads = study.threads(study.quiet);
        let StudyArgs {
            spec, quiet, force, ..
        } = study;
        let observer = ProgressObserver::new(!quiet);
        let report = crate::study::run(
            &plan,
            &crate::study::ExecOptions {
                threads,
                force,
                shard,
                checkpoints,
            },
            &observer,
        )
        .map_err(anyhow::Error::from)
        .map_err(|e| e.context(format!("running {}", spec.display())))?;
        if !quiet {
            if report.cells_resumed > 0 {
                outln!(
                    "{} cells continued from the checkpoint, not recomputed",
                    report.cells_resumed
                );
            }
            outln!(
                "{} runs in {:.1} s ({:.0} runs/s) → {}",
                report.runs,
                report.wall_s,
                report.runs as f64 / report.wall_s.max(1e-9),
                report.output.display()
            );
            print_tables(&report.tables);
        }
        if plot {
            let files = plot_dir(&report.output, &PlotOptions::default())?;
            if !quiet {
                outln!(
                    "  {} figures in {}",
                    files.len(),
                    report.output.join("figures").display()
                );
            }
        }
        Ok(())
    }
}
