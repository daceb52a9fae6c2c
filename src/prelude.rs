//! What a plugin crate needs, in one `use kfmc::prelude::*;`.
//!
//! A system ([`System`] → [`SystemPlan`]) is validated with the [`Checker`] and laid out by a
//! [`Layout`] of [`Quantity`]s; a world that is the filters' [`Model`] plus additive Gaussian
//! noise is an [`AdditivePlan`], whose filter kinds come from [`common_kinds`] or
//! [`linear_kinds`] and a user's own [`FilterKind`]s; a world that is not the filters' model
//! implements [`World`] and is run by a [`WorldPlan`]. A filter is anything implementing
//! [`Filter`]. [`Registry`] lists the systems a binary knows, and
//! [`crate::cli::main_with`] turns it into the `kfmc` command line.
//!
//! A spec table a plugin reads with serde derives through kfmc's own serde, so the plugin
//! crate needs no serde dependency of its own:
//!
//! ```
//! use kfmc::prelude::*;
//!
//! #[derive(Deserialize)]
//! #[serde(crate = "kfmc::serde", deny_unknown_fields)]
//! struct MyModelKeys {
//!     dt_s: Option<f64>,
//! }
//! # let keys: MyModelKeys = kfmc::toml::from_str("dt_s = 0.1").unwrap();
//! # assert_eq!(keys.dt_s, Some(0.1));
//! ```

pub use serde::Deserialize;

pub use crate::filter::{Filter, FilterError, Innovation};
pub use crate::linalg::{Matrix, Vector};
pub use crate::model::{Availability, Measurement, Model};
pub use crate::scenario::Scenario;
pub use crate::sim::TruthNoise;
pub use crate::sim::seed::world_normals;
pub use crate::step_loop::{Evaluate, Identity, Marginal};
pub use crate::system::additive::AdditivePlan;
pub use crate::system::checker::{Checker, non_negative, positive};
pub use crate::system::filter_kind::{
    AssumedNoise, AssumedStd, FilterContext, FilterEntry, FilterKind, FilterKinds, FilterSetup,
    FnKind, RunFilter,
};
pub use crate::system::kinds::{common_kinds, linear_kinds};
pub use crate::system::settings::InitialMode;
pub use crate::system::spec_values::OneOrMany;
pub use crate::system::world::{
    ModelFilter, NoiseSettings, Realisation, World, WorldFilter, WorldFilterEntry, WorldPlan,
};
pub use crate::system::world_kinds::WorldKinds;
pub use crate::system::{
    Catalogue, FilterInfo, FilterTable, InitialSpec, Layout, PositionAxis, PositionFix, Program,
    Quantity, Registry, ScenarioInfo, System, SystemPlan, SystemSpec,
};
