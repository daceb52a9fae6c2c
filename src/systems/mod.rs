//! The built-in systems. Each registers through the same public API a downstream crate uses
//! ([`crate::system::System`] and [`crate::system::Registry`]); nothing outside its own module
//! names a system, its parameters or its filter kinds.

pub mod drone;
pub mod linear;
pub mod linear_quadrotor;
pub mod planar;
pub mod recorded;

use crate::system::Registry;

/// Every system kfmc ships, registered through the plugin API exactly as a user's crate
/// registers its own: `kfmc::cli::main_with(kfmc::systems::builtin().with(MySystem))`.
pub fn builtin() -> Registry {
    register(Registry::new())
}

/// The registration list: every system kfmc ships, in `kfmc list` order.
pub fn register(registry: Registry) -> Registry {
    registry
        .with(planar::PlanarSystem::new())
        .with(linear_quadrotor::LinearQuadrotorSystem::new())
        .with(linear::LinearSystem::new())
        .with(drone::DroneSystem::new())
        .with(recorded::RecordedSystem::new())
}
