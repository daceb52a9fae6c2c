//! The system role: plugins that the spec's `[model] kind` names.
//!
//! A [`System`] parses and validates its own part of a spec (the `[model]` table, the
//! scenarios and the filter entries' own keys, with key-path errors), names its scenarios and
//! filter kinds for `kfmc list`, and binds a world, filters and the evaluated quantities into
//! a [`SystemPlan`]. The plan builds the [`Trial`] that runs one Monte Carlo run at a time.
//! A [`Registry`] maps `model.kind` to systems.
//!
//! Everything outside a system's own module — the executor, metrics, tables, check, tune,
//! plot and CLI — sees only these traits and the [`Layout`] (quantity, input and measurement
//! names). The built-in systems register through [`crate::systems::builtin`], which uses exactly the
//! public API a downstream crate uses: a user's crate calls
//! `kfmc::cli::main_with(kfmc::systems::builtin().with(MySystem))` and gets every subcommand with
//! its own kinds in its specs.
//!
//! Most systems whose world is the filter's model plus additive Gaussian noise need not write
//! a trial at all: [`additive`] has a generic one ([`additive::AdditivePlan`]) and the filter
//! kinds that work on any [`crate::model::Model`].

pub mod additive;
pub mod checker;
pub mod describe;
pub mod filter_kind;
pub mod filter_model;
pub mod group;
pub mod kinds;
pub mod limits;
mod program;
pub mod settings;
pub mod spec_values;
pub mod trial;
pub mod world;
pub mod world_kinds;

use std::any::Any;
use std::fmt::Debug;
use std::path::Path;
use std::sync::Arc;

use trial::Trial;

pub(crate) use crate::linalg::so3::{ErrorSide, EulerRotation};
pub(crate) use checker::Checker;
pub use program::Program;
pub(crate) use settings::{InitialMode, RunSettings};
pub(crate) use spec_values::OneOrMany;

/// Which axis of which frame a position quantity is: what the position figures (the
/// `trajectory` map, the `route` projections) are chosen and drawn by.
///
/// Two frames: a Cartesian one, x to the right and y ahead on a map with z up (the planar
/// quadrotor's x–y plane, L1's x, y, z), and north–east–down (the drone). A system declares
/// the axes of one frame, each at most once; the horizontal pair (x, y or north, east) gives
/// the map, and a vertical axis (z, or down, drawn as the altitude −down) makes it a route.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum PositionAxis {
    /// x of a Cartesian frame: drawn to the right on the map.
    X,
    /// y of a Cartesian frame: drawn up on the map.
    Y,
    /// z of a Cartesian frame, up: the height.
    Z,
    /// North: drawn up on the map.
    North,
    /// East: drawn to the right on the map.
    East,
    /// Down: the altitude is its negative.
    Down,
}

impl PositionAxis {
    /// Every axis, in declaration order.
    pub const ALL: [PositionAxis; 6] = [
        PositionAxis::X,
        PositionAxis::Y,
        PositionAxis::Z,
        PositionAxis::North,
        PositionAxis::East,
        PositionAxis::Down,
    ];

    /// The name recorded in `manifest.toml` and written in specs: `x`, `y`, `z`, `north`,
    /// `east`, `down`.
    pub fn name(self) -> &'static str {
        match self {
            PositionAxis::X => "x",
            PositionAxis::Y => "y",
            PositionAxis::Z => "z",
            PositionAxis::North => "north",
            PositionAxis::East => "east",
            PositionAxis::Down => "down",
        }
    }

    /// The axis of a name ([`PositionAxis::name`]).
    pub fn from_name(name: &str) -> Option<PositionAxis> {
        PositionAxis::ALL.into_iter().find(|a| a.name() == name)
    }

    /// Whether the axis belongs to the north–east–down frame.
    pub fn is_ned(self) -> bool {
        matches!(
            self,
            PositionAxis::North | PositionAxis::East | PositionAxis::Down
        )
    }
}

/// A measurement component that measures a position quantity directly (a fix): the figures
/// draw it beside the quantity's truth and estimates.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct PositionFix {
    /// The sensor, for the legend (`gps` gives `gps fixes`); the components of one sensor are
    /// drawn together.
    pub sensor: String,
    /// The measurement component (trace column `z_<component>`), one of
    /// [`Layout::measurements`], equal to the quantity plus noise when it reports.
    pub component: String,
}

/// One evaluated quantity: what is scored (RMSE, NEES, divergence, traces).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Quantity {
    /// Name (columns `rmse_<name>`, `truth_<name>`, `est_<name>`, …).
    pub name: String,
    /// Unit, for figures and reports (`m`, `m/s`, `rad`, `deg`, or empty).
    pub unit: String,
    /// Whether the error of this quantity is an angle wrapped to [−π, π) (or [−180°, 180°)
    /// when the unit is `deg`).
    pub angle: bool,
    /// Set on the three quantities of a rotation ([`Quantity::rotation`]): their error is the
    /// rotation error on this side, not three angle differences.
    pub rotation: Option<ErrorSide>,
    /// Set on a position coordinate ([`Quantity::position`]): which axis of which frame it
    /// is. The position figures are chosen by these roles, not by names.
    pub position: Option<PositionAxis>,
    /// The measurement components that measure this quantity directly
    /// ([`Quantity::measured_by`]), drawn as fixes in the position figures.
    pub fixes: Vec<PositionFix>,
}

impl Quantity {
    /// A quantity whose error is a plain difference.
    pub fn new(name: impl Into<String>, unit: impl Into<String>) -> Self {
        Quantity {
            name: name.into(),
            unit: unit.into(),
            angle: false,
            rotation: None,
            position: None,
            fixes: Vec::new(),
        }
    }
    /// An angle quantity: its error is wrapped.
    pub fn angle(name: impl Into<String>, unit: impl Into<String>) -> Self {
        Quantity {
            angle: true,
            ..Quantity::new(name, unit)
        }
    }
    /// A position coordinate along `axis` (its error is a plain difference).
    pub fn position(name: impl Into<String>, unit: impl Into<String>, axis: PositionAxis) -> Self {
        Quantity::new(name, unit).with_position(axis)
    }
    /// This quantity as a position coordinate along `axis`.
    pub fn with_position(mut self, axis: PositionAxis) -> Self {
        self.position = Some(axis);
        self
    }
    /// This quantity measured directly by the measurement component `component` of `sensor`
    /// (the drone's `px` by `gps_px` of `gps`): the position figures draw the fixes.
    pub fn measured_by(mut self, sensor: impl Into<String>, component: impl Into<String>) -> Self {
        self.fixes.push(PositionFix {
            sensor: sensor.into(),
            component: component.into(),
        });
        self
    }
    /// The three quantities of an attitude held as ZYX Euler angles (roll, pitch, yaw, in
    /// that order, in `deg` or `rad`) and scored as a rotation: the error is the rotation
    /// vector log(R̂ᵀR) (`ErrorSide::Right`) or log(RR̂ᵀ) (`Left`) in the quantities' unit, and
    /// the covariance a filter reports for them must be that error's
    /// ([`crate::linalg::so3`]).
    pub fn rotation(names: [&str; 3], unit: &str, side: ErrorSide) -> [Quantity; 3] {
        names.map(|n| Quantity {
            rotation: Some(side),
            ..Quantity::new(n, unit)
        })
    }
}

/// The names and sizes a study's tables are made of.
#[derive(Clone, Debug, PartialEq)]
pub struct Layout {
    /// The evaluated quantities, in order (NEES has as many degrees of freedom).
    pub quantities: Vec<Quantity>,
    /// The inputs the filters receive (trace columns `u_<name>`).
    pub inputs: Vec<String>,
    /// The measurement components (trace columns `z_<name>`; NIS degrees of freedom).
    pub measurements: Vec<String>,
    /// The world's own states beyond the quantities (sensor biases, drifts; trace columns
    /// `world_<name>`); empty when the world is the filters' model.
    pub world_states: Vec<String>,
    /// Sample time Δt in seconds (the `t` column is `step · Δt`).
    pub dt_s: f64,
}

impl Layout {
    /// The angle quantities, whose errors are wrapped: (index, whether in degrees).
    pub fn angles(&self) -> Vec<(usize, bool)> {
        self.quantities
            .iter()
            .enumerate()
            .filter(|(_, q)| q.angle)
            .map(|(i, q)| (i, q.unit == "deg"))
            .collect()
    }
    /// The quantity names, in order.
    pub fn quantity_names(&self) -> Vec<&str> {
        self.quantities.iter().map(|q| q.name.as_str()).collect()
    }
    /// The input names.
    pub fn input_names(&self) -> Vec<&str> {
        self.inputs.iter().map(String::as_str).collect()
    }
    /// The measurement-component names.
    pub fn measurement_names(&self) -> Vec<&str> {
        self.measurements.iter().map(String::as_str).collect()
    }
    /// The world-state names.
    pub fn world_state_names(&self) -> Vec<&str> {
        self.world_states.iter().map(String::as_str).collect()
    }
    /// The rotations: each run of three consecutive quantities declared with
    /// [`Quantity::rotation`].
    pub fn rotations(&self) -> Vec<EulerRotation> {
        let q = &self.quantities;
        let mut out = Vec::new();
        let mut i = 0;
        while i + 3 <= q.len() {
            match q[i].rotation {
                Some(side)
                    if q[i + 1].rotation == Some(side) && q[i + 2].rotation == Some(side) =>
                {
                    out.push(EulerRotation {
                        first: i,
                        degrees: q[i].unit == "deg",
                        side,
                    });
                    i += 3;
                }
                _ => i += 1,
            }
        }
        out
    }
    /// The position quantities: (index, axis), in quantity order.
    pub fn positions(&self) -> Vec<(usize, PositionAxis)> {
        self.quantities
            .iter()
            .enumerate()
            .filter_map(|(i, q)| Some((i, q.position?)))
            .collect()
    }
    /// Indices of the angle quantities.
    pub fn angle_indices(&self) -> Vec<usize> {
        (0..self.quantities.len())
            .filter(|&i| self.quantities[i].angle)
            .collect()
    }
}

/// A validated scenario, as the generic code sees it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ScenarioInfo {
    /// Name (the `scenario` column; it also selects the run seeds).
    pub name: String,
    /// Transitions K (the run has K + 1 samples).
    pub steps: usize,
}

/// A validated filter entry, as the generic code sees it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct FilterInfo {
    /// The `kind` tag.
    pub kind: String,
    /// Whether the filter reports a covariance (NEES, consistency, tuning).
    pub has_covariance: bool,
    /// Whether `q_scale` applies to it.
    pub q_scale: bool,
    /// Whether `r_scale` applies to it.
    pub r_scale: bool,
}

/// One `[[filters]]` entry before validation: its label and kind, and every other key for the
/// system (the generic keys `q_scale` and `r_scale` are taken out).
#[derive(Clone, Debug, PartialEq)]
pub struct FilterTable {
    /// The entry's key path in the spec, `filters[i]` (external entries are not passed to
    /// the system, so `i` need not be the position in the list the system sees).
    pub key: String,
    /// `label`.
    pub label: String,
    /// `kind`.
    pub kind: String,
    /// Every key of the entry except `label`, `kind`, `q_scale` and `r_scale`.
    pub keys: toml::Table,
}

/// `[initial_estimate]` after its generic part is read.
#[derive(Clone, Debug, PartialEq)]
pub struct InitialSpec {
    /// `mode`.
    pub mode: InitialMode,
    /// Whether the table was present at all.
    pub present: bool,
    /// `p0_std`, for the system to check against its state dimension.
    pub p0_std: Option<OneOrMany>,
}

/// What a system is given to validate: its own parts of the spec.
#[derive(Clone, Copy, Debug)]
pub struct SystemSpec<'a> {
    /// The spec file (for messages).
    pub file: &'a Path,
    /// The `[model]` table without `kind`.
    pub model: &'a toml::Table,
    /// The `[[scenarios]]` tables (each with its `name`, already checked unique).
    pub scenarios: &'a [toml::Table],
    /// The `[[filters]]` entries.
    pub filters: &'a [FilterTable],
    /// `[initial_estimate]`.
    pub initial: &'a InitialSpec,
}

/// What `kfmc list` shows of a system.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Catalogue {
    /// One line: what the system is.
    pub about: String,
    /// Titled lists of (name, description): scenarios, filter kinds, sensors, model keys, …
    pub sections: Vec<(String, Vec<(String, String)>)>,
}

/// A plugin system: what one `[model] kind` means.
pub trait System: Send + Sync {
    /// The `model.kind` value that selects it.
    fn kind(&self) -> &str;
    /// What `kfmc list` prints for it.
    fn catalogue(&self) -> Catalogue;
    /// Validates the system's parts of a spec, reporting every problem into `checker` with its
    /// key path; returns the configured system when there is none.
    fn configure(
        &self,
        spec: &SystemSpec<'_>,
        checker: &mut Checker,
    ) -> Option<Arc<dyn SystemPlan>>;
    /// The `[model]` keys that change only how results are shown (figure roles), never the
    /// world: they are left out of the world stamp, so estimates made before such a key was
    /// set are still of this world.
    fn presentation_keys(&self) -> &[&str] {
        &[]
    }
    /// The scenario name a spec without `[[scenarios]]` gets (`recorded` for real runs that
    /// have none); `None` (the default): the spec must list its scenarios.
    fn default_scenario(&self) -> Option<&str> {
        None
    }
}

/// A configured system: the world, the filters and the evaluated quantities of one spec.
pub trait SystemPlan: Send + Sync + Debug {
    /// Names and sizes of the tables.
    fn layout(&self) -> &Layout;
    /// The scenarios, in spec order.
    fn scenarios(&self) -> &[ScenarioInfo];
    /// The filter entries, in spec order.
    fn filters(&self) -> &[FilterInfo];
    /// The executor of one run, for a study's `settings` (whose scenarios and filter variants
    /// index into [`SystemPlan::scenarios`] and [`SystemPlan::filters`]).
    fn trial<'a>(&'a self, settings: &'a RunSettings) -> Box<dyn Trial + 'a>;
    /// For tests and tools that need the concrete plan back.
    fn as_any(&self) -> &dyn Any;
    /// The system's analysis for `kfmc describe` ([`crate::analysis`]) of a study's
    /// `settings`. Systems built on [`additive::AdditivePlan`] get the linearised analysis of
    /// their model; the default, `None`, says that the system offers none, and `describe`
    /// then shows the layout alone.
    fn describe(&self, settings: &RunSettings) -> Option<crate::analysis::Description> {
        let _ = settings;
        None
    }
    /// The model kfmc's filters use, with the world's noise and prior, for filters written
    /// outside kfmc ([`filter_model`]: the Python package's `Simulation.f/h/jacobians`,
    /// `kfmc describe`'s `[filter_model]`). `None` (the default): the system's world is not
    /// one [`crate::model::Model`] plus additive noise.
    fn filter_model(&self) -> Option<filter_model::FilterModel<'_>> {
        None
    }
    /// Whether the system's truth is recorded, never simulated (`model.kind = "recorded"`):
    /// its runs exist only with a truth table attached ([`RunSettings::truth`], `kfmc score
    /// --truth`), and `kfmc run` and `kfmc simulate` refuse it. Such a plan must be a
    /// [`world::WorldPlan`], whose trial reads the truth in place of simulating.
    fn recorded(&self) -> bool {
        false
    }
}

/// Maps `model.kind` to systems.
#[derive(Clone, Default)]
pub struct Registry {
    systems: Vec<Arc<dyn System>>,
    program: Program,
}

impl Debug for Registry {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_list().entries(self.kinds()).finish()
    }
}

impl Registry {
    /// An empty registry.
    pub fn new() -> Self {
        Registry::default()
    }

    /// Adds a system; one of the same kind is replaced (so a user can extend a built-in
    /// system with filter kinds of their own and register it again).
    pub fn with(mut self, system: impl System + 'static) -> Self {
        self.register(Arc::new(system));
        self
    }

    /// Adds a shared system (see [`Registry::with`]).
    pub fn register(&mut self, system: Arc<dyn System>) {
        match self.systems.iter().position(|s| s.kind() == system.kind()) {
            Some(i) => self.systems[i] = system,
            None => self.systems.push(system),
        }
    }

    /// The system of a kind.
    pub fn get(&self, kind: &str) -> Option<&dyn System> {
        self.systems
            .iter()
            .find(|s| s.kind() == kind)
            .map(|s| s.as_ref())
    }

    /// The registered kinds, in registration order.
    pub fn kinds(&self) -> Vec<&str> {
        self.systems.iter().map(|s| s.kind()).collect()
    }

    /// The registered systems.
    pub fn systems(&self) -> impl Iterator<Item = &dyn System> {
        self.systems.iter().map(|s| s.as_ref())
    }

    /// The same systems, run by `program` (kfmc's own command unless set): the plans loaded
    /// through this registry record it in their manifests.
    pub fn named(mut self, program: Program) -> Self {
        self.program = program;
        self
    }

    /// The binary these systems run in ([`Registry::named`]).
    pub fn program(&self) -> Program {
        self.program
    }
}
