//! `kfmc schema`: print the columns of an exchange table for a spec.

use super::*;

/// The arguments of `kfmc schema`.
#[derive(Debug, clap::Args)]
pub struct Schema {
    /// Which table.
    #[arg(value_enum)]
    pub table: SchemaTable,
    /// The experiment spec (TOML).
    pub spec: PathBuf,
}

impl Schema {
    /// Runs the command.
    pub(super) fn execute(self, registry: &Registry) -> anyhow::Result<()> {
        let Self { table, spec } = self;
        let plan = experiment::load_with(&spec, registry).map_err(KfmcError::from)?;
        emit(&schema_text(table, &plan));
        Ok(())
    }
}
