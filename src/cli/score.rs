//! `kfmc score`: score estimates made outside kfmc against a `kfmc simulate` folder: writes the
//! tables `kfmc run` writes (runs, steps, summary, consistency, divergence), with kfmc's own
//! filters of the spec run beside them on the same runs. With `--truth TRUTH --spec SPEC` the
//! runs are a user's own (a spec of `model.kind = "recorded"`), judged the same way.

use super::*;

/// The arguments of `kfmc score`.
#[derive(Debug, clap::Args)]
pub struct Score {
    /// A folder written by `kfmc simulate` (not with `--truth`).
    #[arg(required_unless_present = "truth", conflicts_with = "truth")]
    pub dir: Option<PathBuf>,
    /// A truth table of runs kfmc did not simulate (Parquet: scenario, noise_scale, run,
    /// step, t, `truth_<q>`), judged with `--spec`, a spec of `model.kind = "recorded"`.
    #[arg(long, requires = "spec")]
    pub truth: Option<PathBuf>,
    /// The recorded spec of `--truth`: its quantities, runs, scenarios and outside filters.
    #[arg(long, requires = "truth")]
    pub spec: Option<PathBuf>,
    /// Estimates files (Parquet; `kfmc schema estimates SPEC` lists the columns).
    #[arg(long, required = true, num_args = 1..)]
    pub estimates: Vec<PathBuf>,
    /// Output folder for the tables (default: DIR/score; with --truth, the spec's output).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Worker threads; 0 = all cores.
    #[arg(long, default_value_t = 0)]
    pub threads: usize,
    /// No progress bar and no report.
    #[arg(long, short)]
    pub quiet: bool,
    /// Write into a non-empty output folder that is not a kfmc result folder, or replace
    /// a folder that holds another command's result.
    #[arg(long)]
    pub force: bool,
    /// Runs of a cell in groups (`auto`) or one at a time (`off`); see `kfmc run --lanes`.
    #[arg(long, value_parser = super::lanes_mode, value_name = "auto|off")]
    pub lanes: Option<crate::runner::lanes::LanesMode>,
}

impl Score {
    /// Runs the command.
    pub(super) fn execute(self, registry: &Registry) -> anyhow::Result<()> {
        let Self {
            dir,
            truth,
            spec,
            estimates,
            out,
            threads,
            quiet,
            force,
            lanes,
        } = self;
        let lanes = super::lanes(lanes)?;
        let (mut plan, against) = match (dir, truth, spec) {
            (_, Some(truth), Some(spec)) => {
                let plan = crate::check::recorded_plan(&spec, &truth, out, registry)
                    .map_err(anyhow::Error::from)
                    .map_err(|e| e.context(format!("reading the truth {}", truth.display())))?;
                (plan, truth)
            }
            (Some(dir), _, _) => {
                let plan = crate::simulate::scoring_plan(&dir, out, registry)
                    .map_err(anyhow::Error::from)
                    .map_err(|e| e.context(format!("scoring against {}", dir.display())))?;
                (plan, dir)
            }
            _ => {
                anyhow::bail!("give the folder `kfmc simulate` wrote, or --truth TRUTH --spec SPEC")
            }
        };
        let dir = against;
        attach_estimates(&mut plan, &estimates, Unstamped::Warn)?;
        plan.lanes = lanes;
        let cpus = std::thread::available_parallelism().map_or(1, |n| n.get());
        let observer = ProgressObserver::new(!quiet);
        let report = crate::study::run(
            &plan,
            &crate::study::ExecOptions {
                threads: if threads == 0 { 0 } else { threads.min(cpus) },
                force,
                shard: None,
                checkpoints: None,
            },
            &observer,
        )
        .map_err(anyhow::Error::from)
        .map_err(|e| e.context(format!("scoring against {}", dir.display())))?;
        if !quiet {
            outln!(
                "{} runs scored in {:.1} s → {}",
                report.runs,
                report.wall_s,
                report.output.display()
            );
            print_tables(&report.tables);
        }
        Ok(())
    }
}
