//! `kfmc check`: run a study and evaluate its `[check]` assertions (consistency verdicts, RMSE
//! bounds, whiteness) for CI. Exit 0 when all hold, 3 when one fails, 4 when none fails but one
//! could not be judged on the runs the spec declares (incomplete), 2 for an invalid spec.

use super::*;

/// The arguments of `kfmc check`.
#[derive(Debug, clap::Args)]
pub struct Check {
    /// The spec (with a `[check]` section) and the shared overrides.
    #[command(flatten)]
    pub study: StudyArgs,
    /// Also write the results as JUnit XML to this file.
    #[arg(long)]
    pub junit: Option<PathBuf>,
    /// Judge the spec's external filters from these estimates files (made from `kfmc
    /// simulate`'s tables of the same spec, runs and seed).
    #[arg(long, num_args = 1..)]
    pub estimates: Vec<PathBuf>,
    /// Judge estimates files that carry no world stamp (`kfmc.world_stamp`), with a
    /// warning: nothing then ties them to this spec's runs.
    #[arg(long, requires = "estimates")]
    pub allow_unstamped: bool,
    /// The truth table of a spec of `model.kind = "recorded"` (a user's own runs): its
    /// external filters are judged against it, from `--estimates`.
    #[arg(long, requires = "estimates")]
    pub truth: Option<PathBuf>,
    /// Replications for the `rejection_rate` assertions (overrides `check.replications`):
    /// they are judged on `kfmc power`'s table, written to `<out>/power`.
    #[arg(long, short = 'R', value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..))]
    pub replications: Option<usize>,
    /// Judge the consistency verdicts with a group-sequential gate (`check.sequential`
    /// in the spec): each cell stops at the first look that settles its verdicts, and
    /// `sequential.parquet` records every look.
    #[command(flatten)]
    pub sequential: SequentialArgs,
}

impl Check {
    /// Runs the command.
    pub(super) fn execute(self, registry: &Registry) -> anyhow::Result<()> {
        let Self {
            study,
            junit,
            estimates,
            allow_unstamped,
            truth,
            replications,
            sequential,
        } = self;
        let mut plan = study.plan(registry, None)?;
        plan.check_sequential = sequential.settings(plan.check_sequential.as_ref())?;
        if let Some(truth) = &truth {
            crate::check::attach_truth(&mut plan, std::slice::from_ref(truth), &[])
                .map_err(|e| anyhow::Error::from(e).context("reading the truth"))?;
        }
        if !estimates.is_empty() {
            let unstamped = if allow_unstamped {
                Unstamped::Warn
            } else {
                Unstamped::Refuse
            };
            attach_estimates(&mut plan, &estimates, unstamped)?;
        }
        let threads = study.threads(study.quiet);
        let StudyArgs {
            spec,
            quiet,
            force,
            allow_large,
            ..
        } = study;
        let exec = crate::study::ExecOptions {
            threads,
            force,
            shard: None,
            checkpoints: None,
        };
        let outcome = crate::check::run(plan, &spec, replications, allow_large, &exec, || {
            ProgressObserver::new(!quiet)
        })
        .map_err(|e| match e {
            crate::check::RunError::Invalid(e) => anyhow::Error::from(e),
            crate::check::RunError::Stage { context, source } => {
                anyhow::Error::from(*source).context(context)
            }
        })?;
        emit(&outcome.render());
        if let Some(path) = junit {
            std::fs::write(&path, outcome.junit()).map_err(|e| {
                anyhow::Error::from(e).context(format!("writing {}", path.display()))
            })?;
        }
        let cases = &outcome.cases;
        let (failed, incomplete) = crate::check::tally(cases);
        if failed + incomplete > 0 {
            return Err(CheckFailed {
                failed,
                incomplete,
                total: cases.len(),
            }
            .into());
        }
        Ok(())
    }
}
