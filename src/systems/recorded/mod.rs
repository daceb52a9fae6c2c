//! A world kfmc does not simulate (`model.kind = "recorded"`): a user's own Monte Carlo, or
//! real runs with reference truth, judged from files.
//!
//! The spec declares what the truth table holds and which runs exist, so that a run left out
//! is missing exactly as one of kfmc's own runs would be:
//!
//! ```toml
//! runs = 50                       # runs per (scenario, noise scale)
//! [model]
//! kind = "recorded"
//! states = ["theta", "omega"]     # truth_theta, truth_omega; est_theta, est_omega
//! state_units = ["rad", "rad/s"]  # optional
//! angles = ["theta"]              # optional: errors wrapped
//! measurements = ["theta"]        # optional: nu_theta, S_theta_theta of the estimates
//! dt_s = 0.05
//! steps = 200                     # K: every run has steps 0..=K
//! [[filters]]
//! label = "ukf"
//! kind = "external"
//! ```
//!
//! Without `[[scenarios]]` the spec has one scenario, `recorded`; without `[noise] scales`
//! one noise scale, 1. `rotations = [["roll", "pitch", "yaw"]]` scores three consecutive
//! states as one rotation (ZYX Euler angles, error log(R̂ᵀR)), as the drone's attitude is.
//!
//! The system cannot simulate: its trial reads each run's truth from the table attached to
//! the study ([`crate::system::RunSettings::truth`], `kfmc score --truth`), and `kfmc run`
//! and `kfmc simulate` refuse it. Its filters are outside ones (`kind = "external"`),
//! replayed from their estimates.
//!
//! # Sizes
//! The step loop is monomorphised over the number of states and measurement components; the
//! pairs of [`SUPPORTED`] are compiled, another is a spec error listing them.

use std::sync::Arc;

use serde::Deserialize;

use crate::linalg::Vector;
use crate::model::{Availability, Measurement};
use crate::system::checker::{Checker, positive};
use crate::system::world::{Realisation, World, WorldFilterEntry, WorldPlan};
use crate::system::{
    Catalogue, ErrorSide, Layout, Quantity, ScenarioInfo, System, SystemPlan, SystemSpec,
};

/// `model.kind` of this system.
pub const KIND: &str = "recorded";

/// The scenario of a spec without `[[scenarios]]`.
pub const DEFAULT_SCENARIO: &str = "recorded";

/// `[model]` of a recorded spec.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct ModelSpec {
    states: Vec<String>,
    #[serde(default)]
    state_units: Option<Vec<String>>,
    #[serde(default)]
    angles: Vec<String>,
    #[serde(default)]
    rotations: Vec<[String; 3]>,
    #[serde(default)]
    measurements: Vec<String>,
    dt_s: f64,
    #[serde(default)]
    steps: Option<usize>,
}

/// A `[[scenarios]]` entry of a recorded spec.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct ScenarioSpec {
    name: String,
    #[serde(default)]
    steps: Option<usize>,
}

type Build = fn(Layout, Vec<ScenarioInfo>) -> Arc<dyn SystemPlan>;

macro_rules! sizes {
    ($( $nq:literal => [$($nz:literal),*] ),* $(,)?) => {
        /// The compiled sizes: per state count, the measurement-component counts.
        pub const SUPPORTED: &[(usize, &[usize])] = &[ $( ($nq, &[$($nz),*]) ),* ];

        fn builder(nq: usize, nz: usize) -> Option<Build> {
            match (nq, nz) {
                $( $( ($nq, $nz) => Some(build::<$nq, $nz>), )* )*
                _ => None,
            }
        }
    };
}

// A replayed filter compiles the step loop and the metrics, not a filter family, so the list
// is wider than the linear system's; each pair still adds to the build.
#[cfg(not(test))]
sizes! {
    1 => [0, 1],
    2 => [0, 1, 2],
    3 => [0, 1, 2, 3],
    4 => [0, 1, 2, 4],
    6 => [0, 2, 3, 6],
    9 => [0, 3, 6],
    12 => [0, 3, 6],
}

// The unit-test build configures no recorded spec (the integration tests link the normal
// build): one pair keeps it cheap.
#[cfg(test)]
sizes! {
    2 => [1],
}

fn supported_list() -> String {
    SUPPORTED
        .iter()
        .map(|(nq, nz)| {
            let z: Vec<String> = nz.iter().map(|z| z.to_string()).collect();
            format!("{nq} states: {}", z.join("/"))
        })
        .collect::<Vec<_>>()
        .join("; ")
}

fn build<const NQ: usize, const NZ: usize>(
    layout: Layout,
    scenarios: Vec<ScenarioInfo>,
) -> Arc<dyn SystemPlan> {
    let world = RecordedWorld {
        steps: scenarios.iter().map(|s| s.steps).collect(),
    };
    let entries: Vec<Arc<dyn WorldFilterEntry<NQ, 0, NZ>>> = Vec::new();
    Arc::new(WorldPlan::new(Arc::new(world), layout, scenarios, entries).with_recorded_truth())
}

/// The world of a recorded spec: it has no simulator. Its trial reads the attached truth;
/// without one (a command that does not refuse a recorded spec) every run is NaN, so no
/// statistic counts it and its outside filters fail for want of estimates.
struct RecordedWorld {
    steps: Vec<usize>,
}

impl<const NQ: usize, const NZ: usize> World<NQ, 0, NZ> for RecordedWorld {
    fn simulate(&self, scenario: usize, _: f64, _: u64) -> Realisation<NQ, 0, NZ> {
        let n = self.steps.get(scenario).copied().unwrap_or(0) + 1;
        Realisation {
            truth: vec![Vector::<NQ>::from_element(f64::NAN); n],
            inputs: vec![Vector::<0>::zeros(); n],
            measurements: vec![
                Measurement {
                    z: Vector::<NZ>::zeros(),
                    available: Availability(0),
                };
                n
            ],
            scenario,
            ..Realisation::default()
        }
    }
}

/// The recorded system.
#[derive(Clone, Copy, Debug, Default)]
pub struct RecordedSystem;

impl RecordedSystem {
    /// The built-in system.
    pub fn new() -> Self {
        RecordedSystem
    }
}

impl System for RecordedSystem {
    fn kind(&self) -> &str {
        KIND
    }

    fn default_scenario(&self) -> Option<&str> {
        Some(DEFAULT_SCENARIO)
    }

    fn catalogue(&self) -> Catalogue {
        let keys = |list: &[(&str, &str)]| {
            list.iter()
                .map(|(k, v)| (k.to_string(), v.to_string()))
                .collect::<Vec<_>>()
        };
        Catalogue {
            about: "a world kfmc does not simulate: your own Monte Carlo or real runs, truth and estimates from files (kfmc score --truth)".into(),
            sections: vec![
                (
                    "model keys".into(),
                    keys(&[
                        ("states", "state names (required): truth_<q> and est_<q> columns"),
                        ("state_units", "units, one per state (optional)"),
                        ("angles", "states whose error is wrapped (rad, or deg by unit)"),
                        ("rotations", "[[roll, pitch, yaw], …]: three consecutive states scored as a rotation"),
                        ("measurements", "measurement-component names (optional): nu_<z> and S_ of the estimates"),
                        ("dt_s", "sample time in s (required)"),
                        ("steps", "K, transitions per run (every run has steps 0..=K); per scenario `steps` overrides"),
                    ]),
                ),
                (
                    "defaults".into(),
                    keys(&[
                        ("scenarios", "none listed: one scenario `recorded`"),
                        ("noise scales", "none listed: one noise scale 1.0"),
                        ("filters", "kind = \"external\" only: estimates from files"),
                    ]),
                ),
                (
                    "sizes (states: measurement components)".into(),
                    SUPPORTED
                        .iter()
                        .map(|(nq, nz)| {
                            let z: Vec<String> = nz.iter().map(|z| z.to_string()).collect();
                            (format!("{nq}"), z.join(", "))
                        })
                        .collect(),
                ),
            ],
        }
    }

    fn configure(&self, spec: &SystemSpec<'_>, c: &mut Checker) -> Option<Arc<dyn SystemPlan>> {
        for f in spec.filters {
            c.err(
                format!("{}.kind", f.key),
                format!(
                    "`{}`: a recorded world runs no filter of kfmc's; its filters are outside ones, kind = \"external\", whose estimates come from files",
                    f.kind
                ),
            );
        }
        let model: ModelSpec = c.parse("model", spec.model)?;
        let layout = layout(&model, c)?;
        let mut scenarios = Vec::new();
        for (i, table) in spec.scenarios.iter().enumerate() {
            let key = format!("scenarios[{i}]");
            let Some(s) = c.parse::<ScenarioSpec>(&key, table) else {
                continue;
            };
            match s.steps.or(model.steps) {
                Some(k) if k >= 1 => scenarios.push(ScenarioInfo {
                    name: s.name,
                    steps: k,
                }),
                Some(_) => c.err(
                    format!("{key}.steps"),
                    "must be at least 1 (K transitions: a run has steps 0..=K)",
                ),
                None => c.err(
                    format!("{key}.steps"),
                    "missing: set model.steps (K of every run) or this scenario's steps",
                ),
            }
        }
        let nq = layout.quantities.len();
        let nz = layout.measurements.len();
        let Some(build) = builder(nq, nz) else {
            c.err(
                "model.states",
                format!(
                    "{nq} states with {nz} measurement components are not compiled; the compiled sizes are {}",
                    supported_list()
                ),
            );
            return None;
        };
        c.is_clean().then(|| build(layout, scenarios))
    }
}

/// The layout a spec declares, its names checked.
fn layout(m: &ModelSpec, c: &mut Checker) -> Option<Layout> {
    let clean = c.error_count();
    if m.states.is_empty() {
        c.err("model.states", "at least one state is required");
    }
    c.number(
        "model.dt_s",
        m.dt_s,
        positive,
        "a positive number of seconds",
    );
    let mut seen = std::collections::BTreeSet::new();
    for (i, n) in m.states.iter().chain(&m.measurements).enumerate() {
        let key = if i < m.states.len() {
            format!("model.states[{i}]")
        } else {
            format!("model.measurements[{}]", i - m.states.len())
        };
        let ok = !n.is_empty() && n.chars().all(|ch| ch.is_ascii_alphanumeric() || ch == '_');
        if !ok {
            c.err(
                key,
                format!("`{n}` is not a column name part ([A-Za-z0-9_], not empty)"),
            );
        } else if i < m.states.len() && !seen.insert(n.clone()) {
            c.err(key, format!("duplicate state `{n}`"));
        }
    }
    let mut meas = std::collections::BTreeSet::new();
    for (i, n) in m.measurements.iter().enumerate() {
        if !meas.insert(n) {
            c.err(
                format!("model.measurements[{i}]"),
                format!("duplicate component `{n}`"),
            );
        }
    }
    let units: Vec<String> = match &m.state_units {
        Some(u) if u.len() != m.states.len() => {
            c.err(
                "model.state_units",
                format!("{} units for {} states", u.len(), m.states.len()),
            );
            vec![String::new(); m.states.len()]
        }
        Some(u) => u.clone(),
        None => vec![String::new(); m.states.len()],
    };
    let index = |n: &str| m.states.iter().position(|s| s == n);
    let mut quantities: Vec<Quantity> = m
        .states
        .iter()
        .zip(&units)
        .map(|(n, u)| Quantity::new(n.clone(), u.clone()))
        .collect();
    for (i, a) in m.angles.iter().enumerate() {
        match index(a) {
            Some(j) => quantities[j].angle = true,
            None => c.err(
                format!("model.angles[{i}]"),
                format!("`{a}` is not a state (states: {})", m.states.join(", ")),
            ),
        }
    }
    for (i, r) in m.rotations.iter().enumerate() {
        let key = format!("model.rotations[{i}]");
        let at: Vec<Option<usize>> = r.iter().map(|n| index(n)).collect();
        match at[..] {
            [Some(a), Some(b), Some(c3)] if b == a + 1 && c3 == a + 2 => {
                let unit = &units[a];
                if units[b] != *unit || units[c3] != *unit || !(unit == "deg" || unit == "rad") {
                    c.err(
                        key,
                        "a rotation's three states share one unit, `deg` or `rad` (state_units)",
                    );
                    continue;
                }
                for q in &mut quantities[a..=c3] {
                    if q.angle || q.rotation.is_some() {
                        c.err(
                            key.clone(),
                            format!("`{}` is in angles or another rotation already", q.name),
                        );
                    }
                    q.rotation = Some(ErrorSide::Right);
                }
            }
            _ => c.err(
                key,
                "three consecutive states, in the order roll, pitch, yaw (ZYX Euler angles)",
            ),
        }
    }
    (c.error_count() == clean).then(|| Layout {
        quantities,
        inputs: Vec::new(),
        measurements: m.measurements.clone(),
        world_states: Vec::new(),
        dt_s: m.dt_s,
    })
}
