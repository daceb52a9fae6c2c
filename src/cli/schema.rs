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
        let mut text = schema_text(table, &plan);
        if table == SchemaTable::Estimates {
            // The other covariance forms, before the error convention and the stamp.
            let forms = crate::score::covariance_forms_text(&plan.layout().quantity_names());
            let at = text.find("\nerror convention:").unwrap_or(text.len());
            text.insert_str(at, &forms);
        }
        emit(&text);
        Ok(())
    }
}
