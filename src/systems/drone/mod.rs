//! The 9-state drone of seed 004 (`model.kind = "drone"`): GPS, IMU and barometer, multi-rate
//! and delayed (kfmc's D1; the readings of the seed are in `docs/src/systems/drone.md`).
//!
//! The world ([`world::DroneWorld`]) is the seed's rigid body on a closed-form route with an
//! IMU (white noise, turn-on bias, bias random walk), a GPS (white noise, Gauss–Markov drift,
//! velocity latency) and a barometer (white noise, random-walk drift, delay), plus the seed's
//! IMU pseudo-measurements (strapdown position and gyro-integrated Euler angles). It is not
//! the filters' model: each filter kind carries its own ([`filters`]), and all are scored on
//! the same nine quantities `px, py, pz, vx, vy, vz, roll, pitch, yaw` (m, m/s, deg).
//!
//! The world also reports each raw sensor's RMSE against the truth per run (natively and on
//! the seed's 100 Hz grid), which fills the `sensors` table beside the filters' `summary`:
//! the seed's Tables 1–3 with a Monte Carlo mean and p5–p95.

pub mod error_state;
pub mod filters;
pub mod kinematics;
pub mod world;

use std::sync::Arc;

use serde::Deserialize;

use crate::linalg::so3::ErrorSide;
use crate::linalg::{Matrix, Vector};
use crate::model::Measurement;
use crate::system::checker::{Checker, non_negative, positive};
use crate::system::settings::InitialMode;
use crate::system::spec_values::OneOrMany;
use crate::system::world::{NoiseSettings, Realisation, WorldFilter, WorldFilterEntry, WorldPlan};
use crate::system::{
    Catalogue, FilterInfo, FilterTable, Layout, PositionAxis, Quantity, ScenarioInfo, System,
    SystemPlan, SystemSpec,
};
use crate::trial::{Prior, RunContext, run_filter};
use filters::{Augmentation, Degrees, PaperModel, Principled, SeqEkf, clone_prior};
use world::{DroneParams, DroneScenario, DroneWorld, ImuOutput, Route, WORLD_STATES};

/// `model.kind` of this system.
pub const KIND: &str = "drone";
/// Evaluated quantities.
pub const NQ: usize = 9;
/// Inputs: the IMU sample [f_x, f_y, f_z, ω_x, ω_y, ω_z].
pub const NU: usize = 6;
/// Measurement components (see [`z`]).
pub const NZ: usize = 13;

/// Measurement component indices, in the paper's update order.
pub mod z {
    /// GPS position x, y, z (NED, m).
    pub const GPS_P: usize = 0;
    /// GPS velocity (m/s), latent.
    pub const GPS_V: usize = 3;
    /// IMU strapdown position (pseudo-measurement, m).
    pub const IMU_P: usize = 6;
    /// Barometric altitude (−z, m), delayed.
    pub const BARO: usize = 9;
    /// IMU gyro-integrated roll, pitch, yaw (pseudo-measurement, rad).
    pub const ROLL: usize = 10;
}

/// Measurement component names (trace columns `z_<name>`).
pub const MEASUREMENTS: [&str; NZ] = [
    "gps_px",
    "gps_py",
    "gps_pz",
    "gps_vx",
    "gps_vy",
    "gps_vz",
    "imu_px",
    "imu_py",
    "imu_pz",
    "baro_alt",
    "imu_roll",
    "imu_pitch",
    "imu_yaw",
];

/// The seed's sensor RMSE (Tables 1–3) per route, in component order (angles in degrees):
/// the paper's EKF uses their squares as R.
pub const SEED_TABLES: [[f64; NZ]; 3] = [
    [
        0.914, 0.921, 2.643, 0.242, 0.123, 0.150, 3.034, 3.353, 2.861, 0.959, 3.406, 3.748, 3.114,
    ],
    [
        0.915, 0.921, 2.643, 0.152, 0.213, 0.150, 3.060, 3.389, 2.861, 1.419, 3.406, 3.748, 3.114,
    ],
    [
        0.914, 0.921, 2.643, 0.227, 0.149, 0.150, 3.108, 3.353, 2.861, 2.311, 3.406, 3.748, 3.114,
    ],
];

/// The seed's EKF RMSE (Tables 1–3) per route, in quantity order (angles in degrees).
pub const SEED_EKF_RMSE: [[f64; NQ]; 3] = [
    [
        0.358, 0.350, 0.296, 0.242, 0.122, 0.150, 3.406, 3.748, 3.114,
    ],
    [
        0.399, 0.369, 0.316, 0.152, 0.213, 0.149, 3.404, 3.746, 3.111,
    ],
    [
        0.691, 0.832, 0.734, 0.227, 0.148, 0.150, 3.406, 3.748, 3.114,
    ],
];

/// The largest pitch (degrees) a route with `attitude_offset_deg` may reach.
pub const PITCH_LIMIT_DEG: f64 = 89.99;

/// The built-in routes and the seed table each one's paper filter takes its R from.
pub const BUILTIN_ROUTES: [(&str, usize, &str); 4] = [
    ("linear", 1, "R1: a = (1.00, 0.15, 0.02) m/s²"),
    (
        "sinusoidal",
        2,
        "R2: a = (0.65 cos(2πt/20), 1.25 cos(2πt/10), 0.095) m/s²",
    ),
    ("ramp", 3, "R3: a = k t, k = (0.0835, 0.038, 0.0238) m/s³"),
    (
        "maneuver",
        1,
        "R2's acceleration with attitude motion: Θ = B (1 − cos 2πt/P)/2, B = (20°, 15°, 90°), P = (8, 12, 20) s",
    ),
];

#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct ModelKeys {
    dt_s: Option<f64>,
    gravity_m_s2: Option<f64>,
    imu_output: Option<String>,
    accel_white_std: Option<OneOrMany>,
    accel_bias_std: Option<OneOrMany>,
    accel_bias_rw: Option<OneOrMany>,
    gyro_white_std: Option<OneOrMany>,
    gyro_bias_std: Option<OneOrMany>,
    gyro_bias_rw: Option<OneOrMany>,
    gps_rate_hz: Option<f64>,
    gps_position_std: Option<OneOrMany>,
    gps_drift_std: Option<OneOrMany>,
    gps_drift_tau_s: Option<f64>,
    gps_velocity_std: Option<OneOrMany>,
    gps_velocity_latency_s: Option<f64>,
    baro_rate_hz: Option<f64>,
    baro_std: Option<f64>,
    baro_drift_rw: Option<f64>,
    baro_delay_s: Option<f64>,
    initial_attitude_std_deg: Option<OneOrMany>,
    attitude_error: Option<String>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct ScenarioKeys {
    name: String,
    base: Option<String>,
    duration_s: Option<f64>,
    start_ned_m: Option<Vec<f64>>,
    accel_m_s2: Option<OneOrMany>,
    jerk_m_s3: Option<OneOrMany>,
    wave_m_s2: Option<OneOrMany>,
    wave_period_s: Option<OneOrMany>,
    attitude_deg: Option<OneOrMany>,
    attitude_period_s: Option<OneOrMany>,
    attitude_offset_deg: Option<OneOrMany>,
    seed_table: Option<i64>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct PaperKeys {
    protocol: Option<String>,
    r_std: Option<OneOrMany>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct Ekf9Keys {
    baro_drift: Option<bool>,
    latency: Option<bool>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct ErrorStateKeys {}

/// The drone system.
#[derive(Clone, Copy, Debug, Default)]
pub struct DroneSystem;

impl DroneSystem {
    /// The built-in system.
    pub fn new() -> Self {
        DroneSystem
    }
}

fn arr3(v: &[f64]) -> [f64; 3] {
    [v[0], v[1], v[2]]
}

impl System for DroneSystem {
    fn kind(&self) -> &str {
        KIND
    }

    fn catalogue(&self) -> Catalogue {
        Catalogue {
            about: "9-state drone of seed 004: IMU (100 Hz), GPS (10 Hz, drift, velocity latency), barometer (50 Hz, drift, delay); quantities px, py, pz, vx, vy, vz, roll, pitch, yaw (m, m/s, deg)".into(),
            sections: vec![
                (
                    "scenarios (built-in; base = …, duration_s, start_ned_m, accel_m_s2, jerk_m_s3, wave_m_s2, wave_period_s, attitude_deg, attitude_period_s, attitude_offset_deg, seed_table)".into(),
                    BUILTIN_ROUTES
                        .iter()
                        .map(|(n, t, d)| (n.to_string(), format!("{d}; paper R from seed Table {t}")))
                        .collect(),
                ),
                (
                    "filters (filters[].kind)".into(),
                    vec![
                        ("paper".into(), "the seed's EKF as written; protocol = \"grid\" (every sensor interpolated to 100 Hz, reading the next epoch) or \"native\"; r_std (13) overrides the seed table's R".into()),
                        ("ekf9".into(), "principled 9-state EKF, IMU as input, Joseph update; baro_drift = true adds a drift state, latency = true clones past velocities for the GPS latency and compensates the barometer delay".into()),
                        ("error_state".into(), "19-state error-state EKF: p, v, attitude error, accelerometer and gyro biases, GPS drift (Gauss–Markov), barometer drift; velocity clones for the GPS latency (up to 3 GPS periods), barometer delay compensated".into()),
                    ],
                ),
                (
                    "model keys".into(),
                    vec![(
                        "[model]".into(),
                        "dt_s, gravity_m_s2, imu_output (gravity_subtracted | specific_force), accel_white_std, accel_bias_std, accel_bias_rw, gyro_white_std, gyro_bias_std, gyro_bias_rw, gps_rate_hz, gps_position_std, gps_drift_std, gps_drift_tau_s, gps_velocity_std, gps_velocity_latency_s, baro_rate_hz, baro_std, baro_drift_rw, baro_delay_s, initial_attitude_std_deg, attitude_error (rotation | rotation_left | euler)".into(),
                    )],
                ),
                (
                    "initial estimates (initial_estimate.mode)".into(),
                    vec![("sampled".into(), "required: the filters start from the first GPS fix, a draw of the initial error".into())],
                ),
            ],
        }
    }

    fn configure(&self, spec: &SystemSpec<'_>, c: &mut Checker) -> Option<Arc<dyn SystemPlan>> {
        let params = params(spec.model, c);
        let scenarios = scenarios(spec.scenarios, &params, c);
        check_initial(spec, c);
        let mut entries: Vec<Arc<dyn WorldFilterEntry<NQ, NU, NZ>>> = Vec::new();
        for f in spec.filters {
            // The entry's place in the spec's list, not in this one: external filters are
            // not passed to the system.
            let key = f.key.clone();
            let entry = match f.kind.as_str() {
                "paper" => paper_entry(&key, f, &params, &scenarios, c),
                "ekf9" => ekf9_entry(&key, f, &params, c),
                "error_state" => error_state_entry(key, f, &params, c),
                other => {
                    c.err(
                        format!("{key}.kind"),
                        format!(
                            "unknown value `{other}` for the drone; expected one of: paper, ekf9, error_state"
                        ),
                    );
                    None
                }
            };
            entries.extend(entry);
        }
        let layout = layout(&params);
        let info = scenarios
            .iter()
            .map(|s| ScenarioInfo {
                name: s.name.clone(),
                steps: s.steps,
            })
            .collect();
        c.is_clean().then(|| {
            Arc::new(
                WorldPlan::new(
                    Arc::new(DroneWorld { params, scenarios }),
                    layout,
                    info,
                    entries,
                )
                .with_world_metrics(world::sensor_metric_names()),
            ) as Arc<dyn SystemPlan>
        })
    }
}

/// The drone's filters start from the first GPS fix and carry their own P0: reports an
/// `[initial_estimate]` that asks for anything else.
fn check_initial(spec: &SystemSpec<'_>, c: &mut Checker) {
    if spec.initial.mode != InitialMode::Sampled {
        // Name a key that is in the file: the mode, the section, or the file itself.
        let key = if c.has("initial_estimate.mode") {
            "initial_estimate.mode"
        } else if c.has("initial_estimate") {
            "initial_estimate"
        } else {
            ""
        };
        c.err(
            key,
            "the drone's filters start from the first GPS fix, a draw of the initial error: set initial_estimate.mode = \"sampled\"",
        );
    }
    if spec.initial.p0_std.is_some() {
        c.err(
            "initial_estimate.p0_std",
            "not used by the drone: each filter's P0 is its own (the paper's I, the principled filters' initial-error distribution)",
        );
    }
}

/// A `kind = "paper"` filter: the seed's EKF, on the grid or native protocol.
fn paper_entry(
    key: &str,
    f: &FilterTable,
    params: &DroneParams,
    scenarios: &[DroneScenario],
    c: &mut Checker,
) -> Option<Arc<dyn WorldFilterEntry<NQ, NU, NZ>>> {
    let k = c.parse::<PaperKeys>(key, &f.keys)?;
    let grid = c.choice(
        &format!("{key}.protocol"),
        k.protocol.as_deref(),
        "grid",
        &["grid", "native"],
    ) == "grid";
    let r_std = k.r_std.as_ref().map(|v| {
        c.vector(
            &format!("{key}.r_std"),
            Some(v),
            NZ,
            &SEED_TABLES[0],
            positive,
            "a positive number",
        )
    });
    Some(Arc::new(PaperEntry {
        grid,
        r_std,
        tables: scenarios.iter().map(|s| s.seed_table).collect(),
        params: params.clone(),
    }))
}

/// A `kind = "ekf9"` filter; with `latency`, the GPS velocity latency must be a whole number
/// (at most 2) of GPS periods, one velocity clone per period.
fn ekf9_entry(
    key: &str,
    f: &FilterTable,
    params: &DroneParams,
    c: &mut Checker,
) -> Option<Arc<dyn WorldFilterEntry<NQ, NU, NZ>>> {
    let k = c.parse::<Ekf9Keys>(key, &f.keys)?;
    let latency = k.latency.unwrap_or(false);
    let mut clones = 0;
    if latency {
        let (l, period) = (
            params.gps_velocity_latency_s / params.dt_s,
            params.gps_period(),
        );
        let per = l / period as f64;
        if (per - per.round()).abs() > 1e-6 || per.round() > 2.0 {
            c.err(
                format!("{key}.latency"),
                format!(
                    "velocity cloning needs model.gps_velocity_latency_s to be 0, 1 or 2 GPS periods; it is {} s with a period of {} s",
                    params.gps_velocity_latency_s,
                    period as f64 * params.dt_s
                ),
            );
        } else {
            clones = per.round() as usize;
        }
    }
    Some(Arc::new(Ekf9Entry {
        baro_drift: k.baro_drift.unwrap_or(false),
        latency,
        clones,
        params: params.clone(),
    }))
}

/// A `kind = "error_state"` filter, when the GPS latency needs no more clones than it carries.
fn error_state_entry(
    key: String,
    f: &FilterTable,
    params: &DroneParams,
    c: &mut Checker,
) -> Option<Arc<dyn WorldFilterEntry<NQ, NU, NZ>>> {
    c.parse::<ErrorStateKeys>(&key, &f.keys)?;
    let entry = error_state::ErrorStateEntry {
        params: params.clone(),
    };
    if entry.clones() > error_state::MAX_CLONES {
        c.err(
            key,
            format!(
                "error_state carries one velocity clone per GPS epoch within the latency, at most {}: model.gps_velocity_latency_s = {} s needs {} with a GPS period of {} s",
                error_state::MAX_CLONES,
                params.gps_velocity_latency_s,
                entry.clones(),
                params.gps_period() as f64 * params.dt_s
            ),
        );
        return None;
    }
    Some(Arc::new(entry))
}

/// The evaluated quantities (the attitude as Euler angles or as a rotation error), the IMU
/// inputs and the measurement components.
fn layout(params: &DroneParams) -> Layout {
    Layout {
        quantities: vec![
            // North–east–down positions, each fixed by its GPS component.
            Quantity::position("px", "m", PositionAxis::North).measured_by("gps", "gps_px"),
            Quantity::position("py", "m", PositionAxis::East).measured_by("gps", "gps_py"),
            Quantity::position("pz", "m", PositionAxis::Down).measured_by("gps", "gps_pz"),
            Quantity::new("vx", "m/s"),
            Quantity::new("vy", "m/s"),
            Quantity::new("vz", "m/s"),
        ]
        .into_iter()
        .chain(match params.attitude_error {
            None => [
                Quantity::angle("roll", "deg"),
                Quantity::angle("pitch", "deg"),
                Quantity::angle("yaw", "deg"),
            ],
            Some(side) => Quantity::rotation(["roll", "pitch", "yaw"], "deg", side),
        })
        .collect(),
        inputs: ["f_x", "f_y", "f_z", "w_x", "w_y", "w_z"]
            .iter()
            .map(|s| s.to_string())
            .collect(),
        measurements: MEASUREMENTS.iter().map(|s| s.to_string()).collect(),
        world_states: WORLD_STATES.iter().map(|s| s.to_string()).collect(),
        dt_s: params.dt_s,
    }
}

const NON_NEGATIVE: &str = "a non-negative number";
const POSITIVE: &str = "a positive number";

/// A scalar key of `[model]`: its value, or `def` when it is absent or fails `ok` (reported).
fn scalar(
    c: &mut Checker,
    key: &str,
    v: Option<f64>,
    def: f64,
    ok: fn(f64) -> bool,
    what: &str,
) -> f64 {
    let x = v.unwrap_or(def);
    if v.is_some() && !c.number(&format!("model.{key}"), x, ok, what) {
        return def;
    }
    x
}

/// The scalar and choice keys of `[model]` over the defaults `d`.
fn scalar_params(m: &ModelKeys, d: &DroneParams, c: &mut Checker) -> DroneParams {
    let pos = |c: &mut Checker, key: &str, v: Option<f64>, def: f64| {
        scalar(c, key, v, def, positive, POSITIVE)
    };
    let nn = |c: &mut Checker, key: &str, v: Option<f64>, def: f64| {
        scalar(c, key, v, def, non_negative, NON_NEGATIVE)
    };
    DroneParams {
        dt_s: pos(c, "dt_s", m.dt_s, d.dt_s),
        gravity_m_s2: nn(c, "gravity_m_s2", m.gravity_m_s2, d.gravity_m_s2),
        imu_output: match c.choice(
            "model.imu_output",
            m.imu_output.as_deref(),
            "gravity_subtracted",
            &["gravity_subtracted", "specific_force"],
        ) {
            "specific_force" => ImuOutput::SpecificForce,
            _ => ImuOutput::GravitySubtracted,
        },
        gps_rate_hz: pos(c, "gps_rate_hz", m.gps_rate_hz, d.gps_rate_hz),
        gps_drift_tau_s: pos(c, "gps_drift_tau_s", m.gps_drift_tau_s, d.gps_drift_tau_s),
        gps_velocity_latency_s: nn(
            c,
            "gps_velocity_latency_s",
            m.gps_velocity_latency_s,
            d.gps_velocity_latency_s,
        ),
        baro_rate_hz: pos(c, "baro_rate_hz", m.baro_rate_hz, d.baro_rate_hz),
        baro_std: nn(c, "baro_std", m.baro_std, d.baro_std),
        baro_drift_rw: nn(c, "baro_drift_rw", m.baro_drift_rw, d.baro_drift_rw),
        baro_delay_s: nn(c, "baro_delay_s", m.baro_delay_s, d.baro_delay_s),
        attitude_error: match c.choice(
            "model.attitude_error",
            m.attitude_error.as_deref(),
            "rotation",
            &["rotation", "rotation_left", "euler"],
        ) {
            "euler" => None,
            "rotation_left" => Some(ErrorSide::Left),
            _ => Some(ErrorSide::Right),
        },
        ..d.clone()
    }
}

/// The per-axis noise keys of `[model]` (three non-negative numbers each) into `p`.
fn noise_vectors(p: &mut DroneParams, m: &ModelKeys, d: &DroneParams, c: &mut Checker) {
    let mut v3 = |key: &str, v: &Option<OneOrMany>, def: [f64; 3]| {
        arr3(&c.vector(
            &format!("model.{key}"),
            v.as_ref(),
            3,
            &def,
            non_negative,
            NON_NEGATIVE,
        ))
    };
    p.accel_white_std = v3("accel_white_std", &m.accel_white_std, d.accel_white_std);
    p.accel_bias_std = v3("accel_bias_std", &m.accel_bias_std, d.accel_bias_std);
    p.accel_bias_rw = v3("accel_bias_rw", &m.accel_bias_rw, d.accel_bias_rw);
    p.gyro_white_std = v3("gyro_white_std", &m.gyro_white_std, d.gyro_white_std);
    p.gyro_bias_std = v3("gyro_bias_std", &m.gyro_bias_std, d.gyro_bias_std);
    p.gyro_bias_rw = v3("gyro_bias_rw", &m.gyro_bias_rw, d.gyro_bias_rw);
    p.gps_position_std = v3("gps_position_std", &m.gps_position_std, d.gps_position_std);
    p.gps_drift_std = v3("gps_drift_std", &m.gps_drift_std, d.gps_drift_std);
    p.gps_velocity_std = v3("gps_velocity_std", &m.gps_velocity_std, d.gps_velocity_std);
    p.initial_attitude_std_deg = v3(
        "initial_attitude_std_deg",
        &m.initial_attitude_std_deg,
        d.initial_attitude_std_deg,
    );
}

/// Reports sensors the filters cannot model: no white noise, or a rate that is not a whole
/// number of steps (which then falls back to the default rate, or one report per step).
fn check_sensors(p: &mut DroneParams, d: &DroneParams, c: &mut Checker) {
    // The filters assume white noise where the world has it: a sensor with none would make
    // its R zero and the update exact, which no real sensor is.
    for (key, v) in [
        ("accel_white_std", p.accel_white_std),
        ("gyro_white_std", p.gyro_white_std),
        ("gps_position_std", p.gps_position_std),
        ("gps_velocity_std", p.gps_velocity_std),
    ] {
        if v.contains(&0.0) {
            c.err(
                format!("model.{key}"),
                "must be positive on every axis (a filter's R or Q would be singular)",
            );
        }
    }
    if p.baro_std == 0.0 {
        c.err(
            "model.baro_std",
            "must be positive (the filters' R would be singular)",
        );
    }
    // Each sensor reports on a whole number of steps.
    for (key, rate) in [
        ("gps_rate_hz", p.gps_rate_hz),
        ("baro_rate_hz", p.baro_rate_hz),
    ] {
        let steps = 1.0 / (rate * p.dt_s);
        if positive(rate)
            && positive(p.dt_s)
            && ((steps - steps.round()).abs() > 1e-6 || steps.round() < 1.0)
        {
            c.err(
                format!("model.{key}"),
                format!(
                    "{rate} Hz is not a whole number of steps of dt_s = {} s (1/(rate·dt) = {steps})",
                    p.dt_s
                ),
            );
            if key == "gps_rate_hz" {
                p.gps_rate_hz = d.gps_rate_hz.min(1.0 / p.dt_s);
            } else {
                p.baro_rate_hz = d.baro_rate_hz.min(1.0 / p.dt_s);
            }
        }
    }
}

/// `[model]` over the defaults, every problem reported.
fn params(table: &toml::Table, c: &mut Checker) -> DroneParams {
    let m: ModelKeys = c.parse("model", table).unwrap_or_default();
    let d = DroneParams::default();
    let mut p = scalar_params(&m, &d, c);
    noise_vectors(&mut p, &m, &d, c);
    check_sensors(&mut p, &d, c);
    p
}

fn scenarios(tables: &[toml::Table], p: &DroneParams, c: &mut Checker) -> Vec<DroneScenario> {
    let mut out = Vec::new();
    let names: Vec<&str> = BUILTIN_ROUTES.iter().map(|r| r.0).collect();
    for (i, t) in tables.iter().enumerate() {
        let key = format!("scenarios[{i}]");
        let Some(s) = c.parse::<ScenarioKeys>(&key, t) else {
            continue;
        };
        let base_name = s.base.as_deref().unwrap_or(&s.name);
        let Some(mut route) = Route::builtin(base_name) else {
            let k = if s.base.is_some() { "base" } else { "name" };
            c.err(
                format!("{key}.{k}"),
                format!(
                    "unknown route `{base_name}`; a drone scenario is a built-in route ({}) by name or by base = …, with overrides",
                    names.join(", ")
                ),
            );
            continue;
        };
        let mut table = BUILTIN_ROUTES
            .iter()
            .find(|r| r.0 == base_name)
            .map_or(1, |r| r.1);
        let finite = |x: f64| x.is_finite();
        let v3 = |c: &mut Checker,
                  k: &str,
                  v: &Option<OneOrMany>,
                  def: [f64; 3],
                  ok: fn(f64) -> bool,
                  what: &str| {
            arr3(&c.vector(&format!("{key}.{k}"), v.as_ref(), 3, &def, ok, what))
        };
        if let Some(start) = &s.start_ned_m {
            if start.len() != 3 || !start.iter().all(|x| x.is_finite()) {
                c.err(
                    format!("{key}.start_ned_m"),
                    format!("expected 3 finite numbers (NED, m), got {start:?}"),
                );
            } else {
                route.start_m = arr3(start);
            }
        }
        route.accel_m_s2 = v3(
            c,
            "accel_m_s2",
            &s.accel_m_s2,
            route.accel_m_s2,
            finite,
            "a finite number",
        );
        route.jerk_m_s3 = v3(
            c,
            "jerk_m_s3",
            &s.jerk_m_s3,
            route.jerk_m_s3,
            finite,
            "a finite number",
        );
        route.wave_m_s2 = v3(
            c,
            "wave_m_s2",
            &s.wave_m_s2,
            route.wave_m_s2,
            finite,
            "a finite number",
        );
        route.wave_period_s = v3(
            c,
            "wave_period_s",
            &s.wave_period_s,
            route.wave_period_s,
            positive,
            "a positive number of seconds",
        );
        let deg = route.attitude_rad.map(f64::to_degrees);
        let att = v3(
            c,
            "attitude_deg",
            &s.attitude_deg,
            deg,
            |x| x.is_finite() && x.abs() <= 360.0,
            "an angle within ±360°",
        );
        let offset = v3(
            c,
            "attitude_offset_deg",
            &s.attitude_offset_deg,
            [0.0; 3],
            |x| x.is_finite() && x.abs() <= 360.0,
            "an angle within ±360°",
        );
        if s.attitude_offset_deg.is_none() {
            if att[1].abs() >= 80.0 {
                c.err(
                    format!("{key}.attitude_deg[1]"),
                    format!("a pitch swing of {}° comes within 10° of the Euler singularity at 90°; at most ±80° (a route meant to come closer sets attitude_offset_deg)", att[1]),
                );
            }
        } else {
            // A route that sets its held attitude may approach the singularity on purpose (the
            // rotation error is defined there), but its truth stays on the Euler branch
            // |θ| < 90°, where T(Θ) and so the body rates of the closed form exist.
            let reach = [offset[1], offset[1] + att[1]];
            if let Some(p) = reach.iter().find(|p| p.abs() > PITCH_LIMIT_DEG) {
                c.err(
                    format!("{key}.attitude_offset_deg[1]"),
                    format!("the route's pitch reaches {p}°; it must stay within ±{PITCH_LIMIT_DEG}° (the Euler angles' singularity is at ±90°)"),
                );
            }
        }
        route.attitude_rad = att.map(f64::to_radians);
        route.attitude_offset_rad = offset.map(f64::to_radians);
        route.attitude_period_s = v3(
            c,
            "attitude_period_s",
            &s.attitude_period_s,
            route.attitude_period_s,
            positive,
            "a positive number of seconds",
        );
        if let Some(tb) = s.seed_table {
            if (1..=3).contains(&tb) {
                table = tb as usize;
            } else {
                c.err(
                    format!("{key}.seed_table"),
                    format!("{tb} is not one of the seed's tables 1, 2, 3"),
                );
            }
        }
        let duration = s.duration_s.unwrap_or(20.0);
        let Some(steps) = c.scenario_steps(&key, duration, p.dt_s) else {
            continue;
        };
        out.push(DroneScenario {
            name: s.name.clone(),
            route,
            steps,
            seed_table: table,
        });
    }
    out
}

/// Scales of one cell, as the filters apply them.
fn scales(s: &NoiseSettings) -> (f64, f64, f64) {
    let fs2 = s.filter_scale * s.filter_scale;
    (fs2, s.q_scale, s.r_scale)
}

#[derive(Debug)]
struct PaperEntry {
    grid: bool,
    r_std: Option<Vec<f64>>,
    /// Per system scenario: its seed table (1–3).
    tables: Vec<usize>,
    params: DroneParams,
}

impl WorldFilterEntry<NQ, NU, NZ> for PaperEntry {
    fn info(&self) -> FilterInfo {
        FilterInfo {
            kind: "paper".into(),
            has_covariance: true,
            q_scale: true,
            r_scale: true,
        }
    }
    fn prepare(&self, s: &NoiseSettings) -> Box<dyn WorldFilter<NQ, NU, NZ>> {
        let (fs2, qs, rs) = scales(s);
        let q = Matrix::<9, 9>::from_diagonal(&Vector::<9>::from_fn(|i, _| {
            [1e-2, 1e-1, 1e-3][i / 3] * fs2 * qs
        }));
        let model_for = |table: usize| {
            let std: Vec<f64> = match &self.r_std {
                Some(v) => v.clone(),
                None => SEED_TABLES[table - 1].to_vec(),
            };
            let mut r = [0.0; NZ];
            for i in 0..NZ {
                // The seed's angles are in degrees; the filter's state is in radians.
                let sd = if i >= z::ROLL {
                    std[i].to_radians()
                } else {
                    std[i]
                };
                r[i] = sd * sd * fs2 * rs;
            }
            PaperModel {
                dt: self.params.dt_s,
                imu: self.params.imu_output,
                g: self.params.gravity(),
                q,
                r,
            }
        };
        Box::new(PaperFilter {
            grid: self.grid,
            models: self.tables.iter().map(|&t| model_for(t)).collect(),
            attitude_error: self.params.attitude_error,
        })
    }
}

struct PaperFilter {
    grid: bool,
    models: Vec<PaperModel>,
    attitude_error: Option<ErrorSide>,
}

/// The context of a run with another measurement stream (the grid protocol's).
fn with_measurements<'a>(
    ctx: &RunContext<'a, NQ, NU, NZ>,
    measurements: &'a [Measurement<NZ>],
) -> RunContext<'a, NQ, NU, NZ> {
    RunContext {
        measurements,
        ..*ctx
    }
}

impl WorldFilter<NQ, NU, NZ> for PaperFilter {
    fn run(
        &self,
        real: &Realisation<NQ, NU, NZ>,
        ctx: &RunContext<'_, NQ, NU, NZ>,
    ) -> crate::trial::FilterOutput {
        let model = &self.models[real.scenario];
        // x̂0: the first GPS position, v = 0, the IMU Euler angles; P0 = I (seed §4).
        let z0 = &real.measurements[0].z;
        let mut x0 = Vector::<9>::zeros();
        for i in 0..3 {
            x0[i] = z0[z::GPS_P + i];
            x0[6 + i] = z0[z::ROLL + i];
        }
        let p0 = Matrix::<9, 9>::identity();
        let prior = Prior {
            x0_hat: &x0,
            p0: &p0,
        };
        let eval = Degrees {
            rotation: self.attitude_error,
        };
        if self.grid {
            let g = world::grid(&real.measurements);
            run_filter(model, &SeqEkf, &eval, &prior, &with_measurements(ctx, &g))
        } else {
            run_filter(model, &SeqEkf, &eval, &prior, ctx)
        }
    }
}

#[derive(Debug)]
struct Ekf9Entry {
    baro_drift: bool,
    latency: bool,
    clones: usize,
    params: DroneParams,
}

/// The principled filters' prior: x̂0 from the first GPS fix (position and velocity), the
/// attitude the truth's plus N(0, diag(σ_Θ²)); P0 that distribution.
pub(crate) fn gps_fix_prior(
    real: &Realisation<NQ, NU, NZ>,
    p: &DroneParams,
    noise_scale: f64,
    fs2: f64,
) -> (Vector<9>, Vector<9>) {
    let z0 = &real.measurements[0].z;
    let mut x = Vector::<9>::zeros();
    let mut var = Vector::<9>::zeros();
    for i in 0..3 {
        x[i] = z0[z::GPS_P + i];
        x[3 + i] = z0[z::GPS_V + i];
        let sa = p.initial_attitude_std_deg[i].to_radians();
        x[6 + i] = real.truth[0][6 + i].to_radians() + sa * noise_scale * real.prior_draws[i];
        var[i] = (p.gps_position_std[i].powi(2) + p.gps_drift_std[i].powi(2)) * fs2;
        var[3 + i] = p.gps_velocity_std[i].powi(2) * fs2;
        var[6 + i] = sa * sa * fs2;
    }
    (x, var)
}

struct PrincipledFilter<const NX: usize> {
    model: Principled<NX>,
    params: DroneParams,
    noise_scale: f64,
    fs2: f64,
}

impl<const NX: usize> WorldFilter<NQ, NU, NZ> for PrincipledFilter<NX> {
    fn run(
        &self,
        real: &Realisation<NQ, NU, NZ>,
        ctx: &RunContext<'_, NQ, NU, NZ>,
    ) -> crate::trial::FilterOutput {
        let (x9, var9) = gps_fix_prior(real, &self.params, self.noise_scale, self.fs2);
        let mut x0 = Vector::<NX>::zeros();
        let mut p0 = Matrix::<NX, NX>::zeros();
        for i in 0..9 {
            x0[i] = x9[i];
            p0[(i, i)] = var9[i];
        }
        // The barometer drift starts at 0 exactly (its state is known at t = 0).
        clone_prior(&self.model.aug, &mut x0, &mut p0);
        let prior = Prior {
            x0_hat: &x0,
            p0: &p0,
        };
        let eval = Degrees {
            rotation: self.params.attitude_error,
        };
        run_filter(&self.model, &SeqEkf, &eval, &prior, ctx)
    }
}

impl Ekf9Entry {
    fn build<const NX: usize>(&self, s: &NoiseSettings) -> Box<dyn WorldFilter<NQ, NU, NZ>> {
        let p = &self.params;
        let (fs2, qs, rs) = scales(s);
        let sq = |a: [f64; 3]| Vector::<3>::from(a).map(|x| x * x * fs2 * qs);
        let mut next = 9;
        let baro_drift = self.baro_drift.then(|| {
            next += 1;
            next - 1
        });
        let clones: Vec<usize> = (0..self.clones)
            .map(|_| {
                next += 3;
                next - 3
            })
            .collect();
        debug_assert_eq!(next, NX);
        let accel_var = sq(p.accel_white_std);
        let delay = (self.latency && p.baro_delay_s > 0.0).then_some(p.baro_delay_s);
        let mut r = [0.0; NZ];
        for i in 0..3 {
            r[z::GPS_P + i] =
                (p.gps_position_std[i].powi(2) + p.gps_drift_std[i].powi(2)) * fs2 * rs;
            r[z::GPS_V + i] = p.gps_velocity_std[i].powi(2) * fs2 * rs;
        }
        r[z::BARO] = p.baro_std.powi(2) * fs2 * rs;
        if let Some(d) = delay {
            // ½ D² a_z rests on one IMU sample: its white noise adds to the barometer's.
            r[z::BARO] += (0.5 * d * d).powi(2) * accel_var[2];
        }
        Box::new(PrincipledFilter::<NX> {
            model: Principled {
                dt: p.dt_s,
                imu: p.imu_output,
                g: p.gravity(),
                accel_var,
                gyro_var: sq(p.gyro_white_std),
                baro_drift_var: p.baro_drift_rw.powi(2) * p.dt_s * fs2 * qs,
                r,
                aug: Augmentation {
                    baro_drift,
                    clones,
                    baro_delay_s: delay,
                },
                gps_period: p.gps_period(),
            },
            params: p.clone(),
            noise_scale: s.noise_scale,
            fs2,
        })
    }
}

impl WorldFilterEntry<NQ, NU, NZ> for Ekf9Entry {
    fn info(&self) -> FilterInfo {
        FilterInfo {
            kind: "ekf9".into(),
            has_covariance: true,
            q_scale: true,
            r_scale: true,
        }
    }
    fn prepare(&self, s: &NoiseSettings) -> Box<dyn WorldFilter<NQ, NU, NZ>> {
        match 9 + self.baro_drift as usize + 3 * self.clones {
            9 => self.build::<9>(s),
            10 => self.build::<10>(s),
            12 => self.build::<12>(s),
            13 => self.build::<13>(s),
            15 => self.build::<15>(s),
            _ => self.build::<16>(s),
        }
    }
}
