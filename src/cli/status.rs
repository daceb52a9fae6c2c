//! `kfmc status`: show which parts of a sharded study are complete.

use super::*;

/// The arguments of `kfmc status`.
#[derive(Debug, clap::Args)]
pub struct Status {
    /// The study's output folder (holding `parts/`).
    pub dir: PathBuf,
}

impl Status {
    /// Runs the command.
    pub(super) fn execute(self) -> anyhow::Result<()> {
        let Self { dir } = self;
        let text = crate::merge::status(&dir)
            .map_err(KfmcError::from)
            .map_err(|e| anyhow::Error::from(e).context(format!("reading {}", dir.display())))?;
        emit(&text);
        Ok(())
    }
}
