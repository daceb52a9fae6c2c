//! The user's system, `model.kind = "cv_range_bearing"`: what its spec keys mean.
//!
//! It parses its own `[model]` table and scenarios (unknown keys are errors with the key path
//! and line), offers kfmc's common filter kinds plus the user's EKF, and hands the rest to
//! kfmc's `AdditivePlan`, since the world is the model plus additive Gaussian noise.

use std::sync::Arc;

use kfmc::prelude::*;

use super::model::{CvRangeBearing, MEASUREMENTS, STATES, UNITS};
use super::user_ekf::user_ekf_kind;

/// `model.kind` of this system.
pub const KIND: &str = "cv_range_bearing";

/// `[model]` (without `kind`).
#[derive(Debug, Default, Deserialize)]
#[serde(crate = "kfmc::serde", deny_unknown_fields)]
struct ModelKeys {
    dt_s: Option<f64>,
    accel_psd: Option<f64>,
    sensor_xy: Option<Vec<f64>>,
    range_std_m: Option<f64>,
    bearing_std_rad: Option<f64>,
}

/// `[[scenarios]]`.
#[derive(Debug, Deserialize)]
#[serde(crate = "kfmc::serde", deny_unknown_fields)]
struct ScenarioKeys {
    name: String,
    x0: Vec<f64>,
    duration_s: Option<f64>,
}

const DEFAULT_DT_S: f64 = 1.0;
const DEFAULT_ACCEL_PSD: f64 = 0.01;
const DEFAULT_RANGE_STD_M: f64 = 5.0;
const DEFAULT_BEARING_STD_RAD: f64 = 0.002;
const DEFAULT_DURATION_S: f64 = 100.0;
const DEFAULT_P0_STD: [f64; 4] = [20.0, 2.0, 20.0, 2.0];

/// The constant-velocity range-bearing system and its filter kinds.
#[derive(Clone)]
pub struct TargetSystem {
    kinds: FilterKinds<4, 0, 2, CvRangeBearing>,
}

impl TargetSystem {
    /// kfmc's common kinds (`ekf`, `information`, `sqrt`, `open_loop`) and `user_ekf`.
    pub fn new() -> Self {
        TargetSystem {
            kinds: common_kinds().with(user_ekf_kind()),
        }
    }
}

impl System for TargetSystem {
    fn kind(&self) -> &str {
        KIND
    }

    fn catalogue(&self) -> Catalogue {
        Catalogue {
            about: "2-D constant-velocity target, state [px, vx, py, vy], range-bearing sensor (own_filter example)".into(),
            sections: vec![
                (
                    "model keys".into(),
                    vec![
                        ("dt_s".into(), format!("sample time, s (default {DEFAULT_DT_S})")),
                        ("accel_psd".into(), format!("white-acceleration spectral density q, m²/s³, per axis; Q is the full CV Q (default {DEFAULT_ACCEL_PSD})")),
                        ("sensor_xy".into(), "sensor position [x, y], m (default [0, 0])".into()),
                        ("range_std_m".into(), format!("range noise std, m (default {DEFAULT_RANGE_STD_M})")),
                        ("bearing_std_rad".into(), format!("bearing noise std, rad (default {DEFAULT_BEARING_STD_RAD})")),
                    ],
                ),
                (
                    "scenarios (any name)".into(),
                    vec![
                        ("x0".into(), "[px, vx, py, vy], required".into()),
                        ("duration_s".into(), format!("default {DEFAULT_DURATION_S}")),
                    ],
                ),
                ("filters (filters[].kind)".into(), self.kinds.catalogue()),
                (
                    "initial estimates (initial_estimate.mode)".into(),
                    vec![
                        ("truth".into(), "x̂0 = x0, P0 = diag(p0_std²)".into()),
                        ("sampled".into(), format!("x̂0 ~ N(x0, P0), one draw per run shared by all filters; p0_std default {DEFAULT_P0_STD:?}")),
                    ],
                ),
            ],
        }
    }

    fn configure(&self, spec: &SystemSpec<'_>, c: &mut Checker) -> Option<Arc<dyn SystemPlan>> {
        let m: ModelKeys = c.parse("model", spec.model).unwrap_or_default();
        let mut number = |key: &str, v: Option<f64>, default: f64, non_zero: bool| {
            let x = v.unwrap_or(default);
            let (ok, what) = if non_zero {
                (positive(x), "a positive number")
            } else {
                (non_negative(x), "a non-negative number")
            };
            if !ok {
                c.err(format!("model.{key}"), format!("{x} is not {what}"));
            }
            x
        };
        let dt_s = number("dt_s", m.dt_s, DEFAULT_DT_S, true);
        let accel_psd = number("accel_psd", m.accel_psd, DEFAULT_ACCEL_PSD, false);
        // Zero measurement noise would make R singular, which every Kalman update inverts.
        let range_std = number("range_std_m", m.range_std_m, DEFAULT_RANGE_STD_M, true);
        let bearing_std = number(
            "bearing_std_rad",
            m.bearing_std_rad,
            DEFAULT_BEARING_STD_RAD,
            true,
        );
        let sensor_xy = match m.sensor_xy.as_deref() {
            None => [0.0, 0.0],
            Some([x, y]) if x.is_finite() && y.is_finite() => [*x, *y],
            Some(v) => {
                c.err("model.sensor_xy", format!("expected [x, y], got {v:?}"));
                [0.0, 0.0]
            }
        };
        let model = CvRangeBearing::new(dt_s, accel_psd, sensor_xy);

        let mut scenarios = Vec::new();
        for (i, t) in spec.scenarios.iter().enumerate() {
            let key = format!("scenarios[{i}]");
            let Some(s) = c.parse::<ScenarioKeys>(&key, t) else {
                continue;
            };
            if s.x0.len() != 4 || !s.x0.iter().all(|v| v.is_finite()) {
                c.err(
                    format!("{key}.x0"),
                    format!(
                        "expected [px, vx, py, vy] (4 finite numbers), got {:?}",
                        s.x0
                    ),
                );
                continue;
            }
            let duration_s = s.duration_s.unwrap_or(DEFAULT_DURATION_S);
            if !positive(duration_s) || duration_s < dt_s {
                c.err(
                    format!("{key}.duration_s"),
                    format!("{duration_s} is shorter than one sample"),
                );
                continue;
            }
            let steps = (duration_s / dt_s).round() as usize;
            scenarios.push(Scenario::unforced(
                &s.name,
                Vector::<4>::from_column_slice(&s.x0),
                steps,
            ));
        }

        if spec.initial.mode == InitialMode::BatchLs {
            c.err(
                "initial_estimate.mode",
                "cv_range_bearing has no batch initialiser; use truth or sampled",
            );
        }
        let p0_std = c.vector(
            "initial_estimate.p0_std",
            spec.initial.p0_std.as_ref(),
            4,
            &DEFAULT_P0_STD,
            positive,
            "a positive number",
        );

        // The truth samples the model's full Q, so these per-state stds only give the
        // filters' default `q_std`, which the full Q refuses anyway.
        let q = model.q();
        let process_std: Vec<f64> = (0..4).map(|i| q[(i, i)].sqrt()).collect();
        let measurement_std = [range_std, bearing_std];
        let entries = self.kinds.configure_entries(
            spec.filters,
            &FilterSetup::new(&model, KIND, &process_std, &measurement_std),
            c,
        );
        if !c.is_clean() {
            return None;
        }
        let layout = Layout {
            quantities: STATES
                .iter()
                .zip(UNITS)
                .map(|(n, u)| Quantity::new(*n, u))
                .collect(),
            inputs: Vec::new(),
            measurements: MEASUREMENTS.iter().map(|s| s.to_string()).collect(),
            world_states: Vec::new(),
            dt_s,
        };
        let noise = TruthNoise {
            process_std: Vector::<4>::from_column_slice(&process_std),
            measurement_std: Vector::<2>::from_column_slice(&measurement_std),
        };
        Some(Arc::new(AdditivePlan::new(
            model,
            layout,
            scenarios,
            noise,
            Vector::<4>::from_column_slice(&p0_std),
            entries,
        )))
    }
}
