//! `kfmc list`: list the registered systems with their sensors, scenarios and filter kinds.

use super::*;

/// Runs the command.
pub(super) fn execute(registry: &Registry) -> anyhow::Result<()> {
    emit(&list(registry));
    Ok(())
}
