//! One Monte Carlo run as the executor sees it: the object-safe [`Trial`] a
//! [`super::SystemPlan`] builds. Dynamic dispatch happens once per run, never per step.

use super::Layout;
use crate::step_loop::{Unit, UnitResult};

/// A study that can execute units: what a [`crate::system::SystemPlan`] builds.
pub trait Trial: Sync {
    /// Runs one unit.
    fn run(&self, unit: &Unit) -> UnitResult;
    /// Number of transitions K of a plan scenario.
    fn steps(&self, scenario: usize) -> usize;
    /// Column names.
    fn layout(&self) -> &Layout;
    /// Names of the per-run numbers a world reports about its own sensors
    /// ([`UnitResult::world_metrics`]), summarised per cell in the `sensors` table; none by
    /// default.
    fn world_metrics(&self) -> &[String] {
        &[]
    }
}
