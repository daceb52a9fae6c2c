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
pub use crate::system::additive::{
    AdditivePlan, AssumedNoise, AssumedStd, FilterContext, FilterEntry, FilterKind, FilterKinds,
    FilterSetup, FnKind, RunFilter, common_kinds, linear_kinds,
};
pub use crate::system::checker::{non_negative, positive};
pub use crate::system::world::{
    ModelFilter, NoiseSettings, Realisation, World, WorldFilter, WorldFilterEntry, WorldPlan,
};
pub use crate::system::world_kinds::WorldKinds;
pub use crate::system::{
    Catalogue, Checker, FilterInfo, FilterTable, InitialMode, InitialSpec, Layout, OneOrMany,
    PositionAxis, PositionFix, Program, Quantity, Registry, RunSettings, ScenarioInfo, System,
    SystemPlan, SystemSpec,
};
pub use crate::trial::{Evaluate, Identity, Marginal, Trial};
