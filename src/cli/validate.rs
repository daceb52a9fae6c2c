//! `kfmc validate`: check a spec and print the plan size and its estimated memory and disk,
//! without running it. Plans above the documented limits are refused (exit 2).

use super::*;

/// The arguments of `kfmc validate`.
#[derive(Debug, clap::Args)]
pub struct Validate {
    /// The experiment spec (TOML).
    pub spec: PathBuf,
    /// Accept a plan above the memory, disk or step limits.
    #[arg(long)]
    pub allow_large: bool,
}

impl Validate {
    /// Runs the command.
    pub(super) fn execute(self, registry: &Registry) -> anyhow::Result<()> {
        let Self { spec, allow_large } = self;
        let plan = experiment::load_with(&spec, registry).map_err(KfmcError::from)?;
        crate::study::check_limits(&plan, allow_large).map_err(KfmcError::from)?;
        outln!("{}", describe(&plan));
        Ok(())
    }
}
