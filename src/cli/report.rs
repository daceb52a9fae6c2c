//! `kfmc report`: write one self-contained HTML report (spec, provenance, tables, figures).

use super::*;

/// The arguments of `kfmc report`.
#[derive(Debug, clap::Args)]
pub struct Report {
    /// A folder written by `kfmc run`.
    pub dir: PathBuf,
    /// The HTML file (default: DIR/report.html).
    #[arg(long)]
    pub out: Option<PathBuf>,
}

impl Report {
    /// Runs the command.
    pub(super) fn execute(self) -> anyhow::Result<()> {
        let Self { dir, out } = self;
        let path = crate::plot::write_report(&dir, out.as_deref())
            .map_err(KfmcError::from)
            .map_err(|e| {
                anyhow::Error::from(e).context(format!("writing the report of {}", dir.display()))
            })?;
        outln!("{}", path.display());
        Ok(())
    }
}
