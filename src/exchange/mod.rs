//! Data from outside kfmc, in the formats other tools write: today PX4's ULog flight logs
//! ([`ulog`]), read by field name and never trusted (a truncated or hostile file is an error
//! or a shorter log, never a panic). The estimates format kfmc itself defines is
//! [`crate::score`], beside this module in the same layer. [`recorded`] reads tables keyed as
//! `kfmc simulate`'s that kfmc did not write: a user's own truth or measurements.

pub mod recorded;
pub mod ulog;
