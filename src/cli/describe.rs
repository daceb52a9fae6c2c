//! `kfmc describe`: print a system's analysis for a spec and write it as TOML: per scenario F,
//! G, H, Q and R along the clean trajectory, the observability ranks (whole sensor set, each
//! component, each sensor group), the steady-state gain and its poles, and per filter the NEES
//! variance inflation ρ and the tests' effective degrees of freedom.

use super::*;

/// The arguments of `kfmc describe`.
#[derive(Debug, clap::Args)]
pub struct Describe {
    /// The experiment spec (TOML).
    pub spec: PathBuf,
    /// The TOML file to write (default: the spec's output folder / describe.toml).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Only print; write no file.
    #[arg(long, conflicts_with = "out")]
    pub no_write: bool,
}

impl Describe {
    /// Runs the command.
    pub(super) fn execute(self, registry: &Registry) -> anyhow::Result<()> {
        let Self {
            spec,
            out,
            no_write,
        } = self;
        let plan = experiment::load_with(&spec, registry).map_err(KfmcError::from)?;
        let description = plan.describe();
        emit(&description.render());
        if !no_write {
            let path = out.unwrap_or_else(|| plan.output.join("describe.toml"));
            // Its first line tells it from a file of the same name that kfmc did not write,
            // which is never replaced. The folder's writers share one lock: a study being
            // written there, or another describe, is never written beside.
            let text = format!(
                "{}\n{}",
                crate::output::folder::DESCRIBE_FORMAT_LINE,
                description.to_toml()
            );
            crate::output::folder::write_file(
                &path,
                text.as_bytes(),
                &crate::output::folder::is_kfmc_describe,
            )
            .map_err(KfmcError::from)
            .map_err(|e| anyhow::Error::from(e).context(format!("writing {}", path.display())))?;
            outln!("wrote {}", path.display());
        }
        Ok(())
    }
}
