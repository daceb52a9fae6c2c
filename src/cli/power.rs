//! `kfmc power`: run the study R times with independent master seeds and write power.parquet:
//! per (cell, filter variant, test) the rejection rate with its 95 % interval and the
//! statistic's distribution — the false-alarm rate at the true Q and R, the power against every
//! q_scale/r_scale variant.

use super::*;
use crate::power::{PowerRequest, PowerTarget};

/// The arguments of `kfmc power`.
#[derive(Debug, clap::Args)]
pub struct Power {
    /// The spec and the shared overrides (`--seed` is the base seed of the replications;
    /// `--out` the folder of power.parquet, default `<output>/power`).
    #[command(flatten)]
    pub study: StudyArgs,
    /// Independent replications of the whole study.
    #[arg(long, short = 'R')]
    pub replications: usize,
    /// Also measure a group-sequential gate: per cell and filter variant, the verdict's
    /// tests looked at after each look's runs, stopping when settled (rows with
    /// `sequential` true, with the runs each replication used).
    #[command(flatten)]
    pub sequential: SequentialArgs,
    /// How many runs do I need: also evaluate the tests on the first N/10, 2N/10, … runs
    /// of each cell and print the smallest run count whose verdict reaches this power
    /// against the `--against` variant.
    #[arg(long, requires = "against", value_name = "POWER")]
    pub target_power: Option<f64>,
    /// The mistuned variant the power is wanted against, e.g. `q_scale=0.9` or
    /// `q_scale=1,r_scale=1.1`.
    #[arg(long, requires = "target_power", value_name = "KEY=VALUE[,…]")]
    pub against: Option<String>,
}

impl Power {
    /// Runs the command.
    pub(super) fn execute(self, registry: &Registry) -> anyhow::Result<()> {
        let Self {
            study,
            replications,
            sequential,
            target_power,
            against,
        } = self;
        let target = match (target_power, against.as_deref()) {
            (Some(power), Some(text)) => {
                let against = text.parse().map_err(|e| usage("--against", e))?;
                Some(PowerTarget::new(power, against).map_err(|e| usage("--target-power", e))?)
            }
            _ => None,
        };
        let plan = study.plan(registry, Some(0))?;
        let request = PowerRequest {
            replications,
            out: study.out.clone(),
            allow_large: study.allow_large,
            gate: sequential.gate(plan.runs, plan.alpha)?,
            target,
        };
        let exec = crate::study::ExecOptions {
            threads: study.threads(study.quiet),
            force: study.force,
            shard: None,
            checkpoints: None,
        };
        let outcome =
            crate::power::run(&plan, &request, &exec, &ProgressObserver::new(!study.quiet))
                .map_err(anyhow::Error::from)
                .map_err(|e| e.context(format!("power of {}", study.spec.display())))?;
        let report = &outcome.report;
        if !study.quiet {
            outln!(
                "{replications} replications ({} runs) in {:.1} s → {}",
                report.runs,
                report.wall_s,
                report.output.display()
            );
            print_tables(&report.tables);
        }
        if let Some(answer) = &outcome.runs_needed {
            emit(&answer.to_string());
        }
        Ok(())
    }
}
