//! "Bring your own filter": a downstream crate's whole `kfmc` binary, using only kfmc's public
//! API.
//!
//! * `model.kind = "cv_range_bearing"` — the user's own system ([`system::TargetSystem`]):
//!   a constant-velocity target and a range-bearing sensor ([`model`]), with kfmc's common
//!   filter kinds and the user's EKF, `kind = "user_ekf"` ([`user_ekf`]);
//! * `model.kind = "turning_target"` — a world that is not the filters' model
//!   ([`turning::TurningSystem`]): the same target in a coordinated turn, with kfmc's filter
//!   kinds and `user_ekf` selected by name;
//! * `model.kind = "planar_quadrotor"` — kfmc's built-in system, registered again with the
//!   user's sequential-update EKF for sensor P1, `kind = "user_filter"` ([`sequential`]).
//!
//! Every import of the user's files is `use kfmc::prelude::*;`, and their spec tables derive
//! through kfmc's serde (`#[serde(crate = "kfmc::serde")]`), so the crate needs no other
//! dependency. `own_filter --version` prints its own name and version.
//!
//! ```sh
//! cargo build --release --example own_filter
//! target/release/examples/own_filter list
//! target/release/examples/own_filter check examples/own_filter/cv_range_bearing.toml
//! ```

mod model;
mod sequential;
mod system;
mod turning;
mod user_ekf;

use std::process::ExitCode;

use kfmc::prelude::Program;
use kfmc::systems::planar::PlanarSystem;

fn main() -> ExitCode {
    // A downstream crate writes `version: env!("CARGO_PKG_VERSION")`; inside kfmc's own
    // repository that would be kfmc's version, so the example names one of its own.
    let program = Program {
        name: "own_filter",
        version: "0.1.0",
    };
    kfmc::cli::main_as(
        program,
        kfmc::systems::builtin()
            .with(system::TargetSystem::new())
            .with(turning::TurningSystem)
            // Same kind as the built-in planar system, so this one replaces it.
            .with(PlanarSystem::new().with_p1_filter(sequential::sequential_kind())),
    )
}
