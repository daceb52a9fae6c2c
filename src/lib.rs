//! # kfmc — judge state estimators statistically
//!
//! A TOML experiment spec names a model, scenarios, filters, a truth-noise sweep and a run
//! count; kfmc expands it into seeded Monte Carlo runs, executes them in parallel and writes
//! RMSE, divergence and NEES/NIS results to Parquet tables.
//!
//! ## Data flow
//!
//! ```text
//! spec.toml ─experiment::load─▶ Plan ─study::run─▶ units (scenario, noise scale, run)
//!    ─runner::execute (rayon)─▶ trial: simulate once, run every filter (paired)
//!    ─fold in unit order─▶ per-cell accumulators ─▶ Parquet tables (atomic) + manifest
//! ```
//!
//! ## Roles (one module each)
//! [`model`] (f, h, Jacobians — the only copy), [`scenario`] (x0, controls), [`filter`]
//! (configuration only; beliefs are values), [`sim`] (truth, measurements, seeding),
//! [`metrics`] (errors, NEES, NIS, accumulators, divergence), [`experiment`] (spec →
//! plan), [`runner`] (executor), [`system::trial`] and [`step_loop`] (one run), [`study`] (a whole study),
//! [`output`] (schema, Parquet, manifest), [`plot`] (figures and the HTML report, from the
//! written tables only), [`cli`]. A plugin crate starts from [`prelude`].
//!
//! ## Notation
//! | symbol | meaning |
//! |---|---|
//! | x_k, x̂_k | true state and estimate at step k (k = 0..K) |
//! | u_k | control driving the transition k−1 → k |
//! | z_k, ν_k | measurement and innovation z_k − h(x̂⁻_k, u_k) |
//! | F_k, H_k | Jacobians of f and h |
//! | Q, R | process- and measurement-noise covariances (the filter's *assumed* ones) |
//! | P_k, S_k | estimate and innovation covariances |
//! | NEES_k | e_kᵀ P_k⁻¹ e_k, χ²(n) for a consistent filter, n = state dimension |
//! | NIS_k | ν_kᵀ S_k⁻¹ ν_k, χ²(p), p = measurement components reported |

#![warn(missing_docs)]

pub mod analysis;
pub mod check;
#[cfg(feature = "cli")]
pub mod cli;
pub mod error;
pub mod exchange;
pub mod experiment;
pub mod filter;
pub mod hash;
pub mod linalg;
pub mod merge;
pub mod metrics;
pub mod model;
pub mod output;
#[cfg(feature = "plot")]
pub mod plot;
pub mod power;
pub mod prelude;
pub mod runner;
pub mod scenario;
pub mod score;
pub mod sequential;
pub mod sim;
pub mod simulate;
// The spill of per-run values is part of `metrics`; this path stays for the code that uses it.
pub(crate) use metrics::spill;
pub mod step_loop;
pub mod study;
pub mod system;
pub mod systems;
// What a trial is written with, gathered for the crate's own code (the public paths are
// `system::trial` and `step_loop`).
pub(crate) mod trial;
pub mod tune;
pub mod ulog;

/// The TOML crate kfmc parses specs with: a system's own tables arrive as [`toml::Table`],
/// so a downstream crate can use this one instead of pinning its own.
pub use toml;

/// The serde kfmc derives its spec types with. A plugin's own spec tables derive through it
/// (`#[derive(kfmc::prelude::Deserialize)] #[serde(crate = "kfmc::serde")]`), so a downstream
/// crate needs no serde dependency of its own and cannot pin a second one.
pub use serde;
