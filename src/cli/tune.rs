//! `kfmc tune`: search a filter's Q scale (and R scale with --tune-r) for consistency or
//! minimum RMSE: a coarse log grid, then a refinement; writes tuning.parquet.

use super::*;

/// The arguments of `kfmc tune`.
#[derive(Debug, clap::Args)]
pub struct Tune {
    /// The spec and the shared overrides.
    #[command(flatten)]
    pub study: StudyArgs,
    /// What to optimise.
    #[arg(long, value_enum, default_value_t = crate::tune::Objective::Consistency)]
    pub objective: crate::tune::Objective,
    /// Also search the R scale (2-D grid).
    #[arg(long)]
    pub tune_r: bool,
    /// The filter label to tune (default: the first EKF).
    #[arg(long)]
    pub filter: Option<String>,
}

impl Tune {
    /// Runs the command.
    pub(super) fn execute(self, registry: &Registry) -> anyhow::Result<()> {
        let Self {
            study,
            objective,
            tune_r,
            filter,
        } = self;
        let plan = study.plan(registry, None)?;
        let threads = study.threads(study.quiet);
        let StudyArgs {
            spec, quiet, force, ..
        } = study;
        let observer = ProgressObserver::new(!quiet);
        let opts = crate::tune::TuneOptions {
            objective,
            tune_r,
            filter,
            threads,
            force,
        };
        let report = crate::tune::tune(&plan, &opts, &observer)
            .map_err(anyhow::Error::from)
            .map_err(|e| e.context(format!("tuning {}", spec.display())))?;
        let (q, r, obj) = report.best;
        let fmt = |v: Option<f64>| v.map_or("—".into(), |x| format!("{x:.4}"));
        outln!(
            "kfmc tune {}: filter {}, objective {:?}, {} candidates evaluated → {}",
            plan.name,
            report.filter,
            objective,
            report.points.len(),
            report.table.display()
        );
        let best = report.averages(q, r, None);
        outln!(
            "best q_scale = {q}, r_scale = {r}: objective {obj:.4}, ANEES {} (n = {}), ANIS {} (p = {})",
            fmt(best.anees),
            plan.layout().quantities.len(),
            fmt(best.anis),
            plan.layout().measurements.len()
        );
        if report.per_noise_scale.len() > 1 {
            outln!("best per truth-noise scale (over the scenarios):");
            for &(s, q, r, o) in &report.per_noise_scale {
                let at = report.averages(q, r, Some(s));
                outln!(
                    "  noise_scale {s:<6} q_scale {q:<10} r_scale {r:<10} objective {o:.4}  ANEES {}  ANIS {}",
                    fmt(at.anees),
                    fmt(at.anis)
                );
            }
        }
        Ok(())
    }
}
