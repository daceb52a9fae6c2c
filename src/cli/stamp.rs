//! `kfmc stamp`: stamps estimates files with the world they were made on, for writers that
//! cannot set Parquet metadata themselves (MATLAB's `parquetwrite`, a CSV turned Parquet).

use super::*;

/// The arguments of `kfmc stamp`.
#[derive(Debug, clap::Args)]
pub struct Stamp {
    /// Estimates files (Parquet), stamped in place.
    #[arg(required = true, num_args = 1..)]
    pub files: Vec<PathBuf>,
    /// The truth table the estimates were made on (a user's own runs).
    #[arg(long)]
    pub truth: PathBuf,
    /// The spec of `--truth` (`model.kind = "recorded"`).
    #[arg(long)]
    pub spec: PathBuf,
}

impl Stamp {
    /// Runs the command.
    pub(super) fn execute(self, registry: &Registry) -> anyhow::Result<()> {
        let plan = crate::check::recorded_plan(&self.spec, &self.truth, None, registry)
            .map_err(anyhow::Error::from)
            .map_err(|e| e.context(format!("reading the truth {}", self.truth.display())))?;
        crate::check::stamp_estimates(&plan, &self.files)
            .map_err(anyhow::Error::from)
            .map_err(|e| e.context("stamping the estimates"))?;
        let stamp: Vec<String> = plan
            .stamp_metadata()
            .into_iter()
            .map(|(k, v)| format!("{k} = {v}"))
            .collect();
        outln!("{} file(s) stamped: {}", self.files.len(), stamp.join(", "));
        Ok(())
    }
}
