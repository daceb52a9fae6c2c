//! The linear 3-axis quadrotor of seed 002 (`model.kind = "linear_quadrotor"`, L1).
//!
//! The world is the discretised model plus additive noise (the full Q of Van Loan's method),
//! run with zero input, so a scenario is an initial state and a duration. Filter kinds: the
//! common ones plus the fixed-gain kinds of a linear model ([`linear_kinds`]), which need the
//! position sensor (the only detectable and observable set); `initial_estimate.mode =
//! "batch_ls"` gives x̂0 and P0 by least squares on each run's measurements.

pub mod model;

use std::any::Any;
use std::sync::Arc;

use serde::Deserialize;

use crate::filter::BatchInitial;
use crate::linalg::{Matrix, Vector};
use crate::scenario::Scenario;
use crate::sim::TruthNoise;
use crate::system::additive::{AdditivePlan, FilterKinds, FilterSetup, linear_kinds};
use crate::system::checker::{Checker, non_negative, positive};
use crate::system::settings::InitialMode;
use crate::system::spec_values::OneOrMany;
use crate::system::{Catalogue, Layout, PositionAxis, Quantity, System, SystemPlan, SystemSpec};
use model::{ContinuousLinear, LINEAR_DT_S, LINEAR_R_DIAG, LINEAR_STATES, Linear, LinearSensor};

/// `model.kind` of this system.
pub const KIND: &str = "linear_quadrotor";

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct ModelKeys {
    sensor: Option<String>,
    dt_s: Option<f64>,
    measurement_noise_std: Option<OneOrMany>,
    process_noise_std: Option<toml::Value>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct ScenarioKeys {
    name: String,
    x0: Option<Vec<f64>>,
    duration_s: Option<f64>,
}

/// The linear-quadrotor system.
#[derive(Clone)]
pub struct LinearQuadrotorSystem {
    three: FilterKinds<6, 4, 3, Linear<3>>,
    two: FilterKinds<6, 4, 2, Linear<2>>,
}

impl Default for LinearQuadrotorSystem {
    fn default() -> Self {
        LinearQuadrotorSystem::new()
    }
}

/// The steady state and the pole placement need the position sensor.
fn positions_only(model: &dyn Any) -> Option<String> {
    let positions = model
        .downcast_ref::<Linear<3>>()
        .is_some_and(|m| m.sensor() == LinearSensor::Positions);
    (!positions).then(|| {
        "steady_state needs model.kind = \"linear_quadrotor\" with sensor = \"positions\" (the only detectable sensor set)".to_string()
    })
}

impl LinearQuadrotorSystem {
    /// The built-in system.
    pub fn new() -> Self {
        LinearQuadrotorSystem {
            three: linear_kinds(positions_only),
            two: linear_kinds(positions_only),
        }
    }
}

impl System for LinearQuadrotorSystem {
    fn kind(&self) -> &str {
        KIND
    }

    fn catalogue(&self) -> Catalogue {
        Catalogue {
            about: "linear 3-axis quadrotor, state [x, xdot, y, ydot, z, zdot], input [t1..t4] = 0, dt 0.1 s (seed 002)".into(),
            sections: vec![
                (
                    "sensors (model.sensor)".into(),
                    vec![
                        ("positions".into(), "[x, y, z]  (C, default)".into()),
                        ("velocities".into(), "[xdot, ydot, zdot]  (C1)".into()),
                        ("xy".into(), "[x, y]  (C2)".into()),
                    ],
                ),
                (
                    "model keys".into(),
                    vec![("[model]".into(), "sensor, dt_s, measurement_noise_std".into())],
                ),
                (
                    "scenarios (any name; x0, duration_s)".into(),
                    vec![("hover".into(), "x0 = [1, 0, 1, 0, 1, 0], 40 s (the defaults)".into())],
                ),
                ("filters (filters[].kind)".into(), self.three.catalogue()),
                (
                    "initial estimates (initial_estimate.mode)".into(),
                    vec![
                        ("truth".into(), "x̂0 = x0, P0 = diag(p0_std²)".into()),
                        ("sampled".into(), "x̂0 ~ N(x0, P0), one draw per run shared by all filters".into()),
                        ("batch_ls".into(), "x̂0, P0 by generalised least squares on z_1..z_K (sensor positions)".into()),
                    ],
                ),
            ],
        }
    }

    fn configure(&self, spec: &SystemSpec<'_>, c: &mut Checker) -> Option<Arc<dyn SystemPlan>> {
        // A planar spec switched to this kind keeps its planar keys: name the mix-up.
        let model = c.reject_foreign(
            "model",
            spec.model,
            &["mass_kg", "arm_m", "inertia_kg_m2", "gravity_m_s2"],
            "a planar_quadrotor key, not used by linear_quadrotor (its model is seed 002's; `kfmc list` shows its keys)",
        );
        let m: ModelKeys = c.parse("model", &model).unwrap_or_default();
        let sensor = match c.choice(
            "model.sensor",
            m.sensor.as_deref(),
            "positions",
            &["positions", "velocities", "xy"],
        ) {
            "velocities" => LinearSensor::Velocities,
            "xy" => LinearSensor::Xy,
            _ => LinearSensor::Positions,
        };
        if m.process_noise_std.is_some() {
            c.err(
                "model.process_noise_std",
                "not used by linear_quadrotor (its process noise is the discretised Q of the seed's Q̃)",
            );
        }
        let dt_s = m.dt_s.unwrap_or(LINEAR_DT_S);
        if !positive(dt_s) {
            c.err("model.dt_s", format!("{dt_s} is not a positive number"));
            return None;
        }
        match sensor.nz() {
            2 => self.build::<2>(&self.two, sensor, dt_s, &m, spec, c),
            _ => self.build::<3>(&self.three, sensor, dt_s, &m, spec, c),
        }
    }
}

impl LinearQuadrotorSystem {
    fn build<const NZ: usize>(
        &self,
        kinds: &FilterKinds<6, 4, NZ, Linear<NZ>>,
        sensor: LinearSensor,
        dt_s: f64,
        m: &ModelKeys,
        spec: &SystemSpec<'_>,
        c: &mut Checker,
    ) -> Option<Arc<dyn SystemPlan>> {
        let model = Linear::<NZ>::new(sensor, dt_s).expect("the sensor's size selects NZ");
        // √diag Q, informational: the truth and the filters use the full Q.
        let q = ContinuousLinear::seed().discretise(dt_s).q;
        let process_std: Vec<f64> = (0..6).map(|i| q[(i, i)].sqrt()).collect();
        // The seed gives one R (for its position sensor); the velocity sensor reuses it and xy
        // takes its first two entries.
        let default_r: Vec<f64> = LINEAR_R_DIAG[..NZ].iter().map(|v| v.sqrt()).collect();
        let measurement_std = c.vector(
            "model.measurement_noise_std",
            m.measurement_noise_std.as_ref(),
            NZ,
            &default_r,
            non_negative,
            "a non-negative number",
        );
        let scenarios = scenarios(spec.scenarios, dt_s, c);
        let entries = kinds.configure_entries(
            spec.filters,
            &FilterSetup::new(&model, KIND, &process_std, &measurement_std),
            c,
        );
        let batch_ls = spec.initial.mode == InitialMode::BatchLs;
        let p0_std = initial_std(spec, sensor, batch_ls, c);
        let batch = (batch_ls && sensor == LinearSensor::Positions && c.is_clean())
            .then(|| batch_estimators(&model, &scenarios, &measurement_std, c));
        if !c.is_clean() {
            return None;
        }
        let layout = layout(&model, dt_s);
        let noise = TruthNoise {
            process_std: Vector::<6>::from_column_slice(&process_std),
            measurement_std: Vector::<NZ>::from_column_slice(&measurement_std),
        };
        let mut plan = AdditivePlan::new(
            model,
            layout,
            scenarios,
            noise,
            Vector::<6>::from_column_slice(&p0_std),
            entries,
        );
        plan.batch = batch;
        plan.analysis_sections.push(sensor_set_ranks(dt_s, sensor));
        Some(Arc::new(plan))
    }
}

/// The scenarios: x0 (default [1, 0, 1, 0, 1, 0]) and a duration (default 40 s), unforced.
fn scenarios(tables: &[toml::Table], dt_s: f64, c: &mut Checker) -> Vec<Scenario<6, 4>> {
    let mut scenarios = Vec::new();
    for (i, t) in tables.iter().enumerate() {
        let key = format!("scenarios[{i}]");
        let t = c.reject_foreign(
            &key,
            t,
            &["base", "stages", "ripple", "ripple_rad_s"],
            "a planar_quadrotor scenario key, not used by linear_quadrotor (its scenarios are x0 and duration_s, unforced)",
        );
        let Some(s) = c.parse::<ScenarioKeys>(&key, &t) else {
            continue;
        };
        let mut x0 = [1.0, 0.0, 1.0, 0.0, 1.0, 0.0];
        match &s.x0 {
            Some(v) if v.len() != 6 || !v.iter().all(|v| v.is_finite()) => c.err(
                format!("{key}.x0"),
                format!("expected 6 finite numbers, got {v:?}"),
            ),
            Some(v) => x0.copy_from_slice(v),
            None => {}
        }
        let Some(steps) = c.scenario_steps(&key, s.duration_s.unwrap_or(40.0), dt_s) else {
            continue;
        };
        scenarios.push(Scenario::unforced(
            &s.name,
            Vector::<6>::from_column_slice(&x0),
            steps,
        ));
    }
    scenarios
}

/// The initial estimate's standard deviations `initial_estimate.p0_std`; with `batch_ls`,
/// reports a sensor set that cannot determine x0 and a p0_std it would not use.
fn initial_std(
    spec: &SystemSpec<'_>,
    sensor: LinearSensor,
    batch_ls: bool,
    c: &mut Checker,
) -> Vec<f64> {
    if batch_ls {
        if sensor != LinearSensor::Positions {
            c.err(
                "initial_estimate.mode",
                "batch_ls needs model.kind = \"linear_quadrotor\" with sensor = \"positions\": the other sensor sets leave x0 undetermined (observability rank 3 or 4 of 6)",
            );
        }
        c.reject_present(
            "initial_estimate",
            &[("p0_std", spec.initial.p0_std.is_some())],
            "not used with mode = \"batch_ls\" (P0 is the least-squares covariance)",
        );
    }
    c.vector(
        "initial_estimate.p0_std",
        spec.initial.p0_std.as_ref(),
        6,
        &[1.0; 6],
        positive,
        "a positive number",
    )
}

/// Each scenario's batch least-squares estimator of x0, built now: a sensor schedule or noise
/// level that cannot determine x0 is a spec error, and the study can then rely on it.
fn batch_estimators<const NZ: usize>(
    model: &Linear<NZ>,
    scenarios: &[Scenario<6, 4>],
    measurement_std: &[f64],
    c: &mut Checker,
) -> Vec<BatchInitial<6>> {
    let r = Matrix::<NZ, NZ>::from_fn(|i, j| {
        if i == j {
            measurement_std[i].powi(2)
        } else {
            0.0
        }
    });
    let mut all = Vec::new();
    let max_rows = crate::system::limits::MAX_BATCH_LS_ROWS;
    for (i, sc) in scenarios.iter().enumerate() {
        let rows = sc.steps() * NZ;
        if rows > max_rows {
            c.err(
                "initial_estimate.mode",
                format!(
                    "batch_ls for scenarios[{i}] (`{}`) stacks K·n_z = {rows} measurements; at most {max_rows} (the fit's covariance is dense, {rows}² numbers): shorten duration_s or use mode = \"sampled\"",
                    sc.name
                ),
            );
            continue;
        }
        match BatchInitial::new(model, &sc.controls, &model.discrete().q, &r) {
            Ok(b) => all.push(b),
            Err(e) => c.err(
                "initial_estimate.mode",
                format!("batch_ls for scenarios[{i}] (`{}`): {e}", sc.name),
            ),
        }
    }
    all
}

/// The six states with their units, the four rotor thrusts and the sensor's components.
fn layout<const NZ: usize>(model: &Linear<NZ>, dt_s: f64) -> Layout {
    Layout {
        quantities: LINEAR_STATES
            .iter()
            .zip(["m", "m/s", "m", "m/s", "m", "m/s"])
            .map(|(n, u)| {
                let q = Quantity::new(*n, u);
                // x, y, z are the positions of a Cartesian frame with z up; the sensor's
                // position components are the positions plus noise.
                let q = match *n {
                    "x" => q.with_position(PositionAxis::X),
                    "y" => q.with_position(PositionAxis::Y),
                    "z" => q.with_position(PositionAxis::Z),
                    _ => q,
                };
                if q.position.is_some() && model.measurement_names().contains(n) {
                    q.measured_by(model.sensor().name(), *n)
                } else {
                    q
                }
            })
            .collect(),
        inputs: ["t1", "t2", "t3", "t4"].map(String::from).to_vec(),
        measurements: model
            .measurement_names()
            .iter()
            .map(|s| s.to_string())
            .collect(),
        world_states: Vec::new(),
        dt_s,
    }
}

/// `kfmc describe`'s section on the sensor sets the spec did not choose: the seed compares
/// all three (eq. 9), and which one to fly is the question the ranks answer.
fn sensor_set_ranks(dt_s: f64, chosen: LinearSensor) -> crate::analysis::Section {
    let sets = [
        ("positions", "x, y, z", LinearSensor::Positions),
        ("velocities", "ẋ, ẏ, ż", LinearSensor::Velocities),
        ("xy", "x, y", LinearSensor::Xy),
    ];
    let rows = sets
        .iter()
        .map(|&(name, what, sensor)| {
            let rank = match sensor.nz() {
                2 => Linear::<2>::new(sensor, dt_s)
                    .ok()
                    .map(|m| m.observability_rank()),
                _ => Linear::<3>::new(sensor, dt_s)
                    .ok()
                    .map(|m| m.observability_rank()),
            };
            crate::analysis::SectionRow {
                name: format!("sensor = \"{name}\" ({what})"),
                value: match rank {
                    Some(r) => format!(
                        "rank {r} of 6{}",
                        if sensor == chosen { " (this spec)" } else { "" }
                    ),
                    None => "not built".into(),
                },
            }
        })
        .collect();
    crate::analysis::Section {
        title: "observability rank of [H; HF; …; HF⁵] by sensor set (model.sensor)".into(),
        rows,
    }
}
