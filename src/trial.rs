//! One Monte Carlo run as a plugin writes it: the object-safe [`Trial`] the executor
//! ([`crate::runner`]) calls once per run, and the shared step loop
//! ([`crate::step_loop::run_filter`]) a trial runs every filter with. This module gathers
//! them where a plugin looks for them; they are defined in [`crate::system::trial`] and
//! [`crate::step_loop`].

pub(crate) use crate::step_loop::{
    Evaluate, FilterOutput, Prior, RunContext, RunTrace, Unit, UnitResult, run_filter, wrap_angle,
};
pub(crate) use crate::system::settings::layout_blocks;
pub(crate) use crate::system::trial::Trial;
