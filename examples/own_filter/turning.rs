//! A world that is not the filters' model, `model.kind = "turning_target"`: the target of
//! [`super::model`] flies a coordinated turn at `turn_rate_deg_s` (its velocity rotates; the
//! constant-velocity model the filters assume does not know) on top of the model's white
//! acceleration, seen by the same range-bearing sensor. kfmc's own filter kinds (`ekf`,
//! `ukf`, …) and the user's `user_ekf` run on it by name through [`WorldKinds`]: the system
//! writes the world, nothing of the filters.

use std::sync::Arc;

use kfmc::prelude::*;

use super::model::{CvRangeBearing, MEASUREMENTS, STATES, UNITS};
use super::user_ekf::user_ekf_kind;

/// `[model]` (without `kind`); the filters' model is the constant-velocity one.
#[derive(Debug, Default, Deserialize)]
#[serde(crate = "kfmc::serde", deny_unknown_fields)]
struct ModelKeys {
    accel_psd: Option<f64>,
    range_std_m: Option<f64>,
}

/// `[[scenarios]]`: a start, a length and the turn rate (0: the world is the model).
#[derive(Debug, Deserialize)]
#[serde(crate = "kfmc::serde", deny_unknown_fields)]
struct ScenarioKeys {
    name: String,
    x0: [f64; 4],
    duration_s: f64,
    turn_rate_deg_s: f64,
}

const DT_S: f64 = 1.0;
const BEARING_STD_RAD: f64 = 0.002;
const P0_STD: [f64; 4] = [20.0, 2.0, 20.0, 2.0];

/// The turning target.
pub struct TurningSystem;

/// The world: one turn rate per scenario, the model's noise, the sensor's noise.
struct TurningWorld {
    model: CvRangeBearing,
    measurement_std: [f64; 2],
    scenarios: Vec<ScenarioKeys>,
}

impl World<4, 0, 2> for TurningWorld {
    fn simulate(&self, scenario: usize, noise_scale: f64, seed: u64) -> Realisation<4, 0, 2> {
        let s = &self.scenarios[scenario];
        let steps = (s.duration_s / DT_S).round() as usize;
        let turn = (s.turn_rate_deg_s * DT_S).to_radians();
        let (sin, cos) = turn.sin_cos();
        let w_factor = self.model.q().cholesky().map(|c| c.l() * noise_scale);
        let (mut process, mut sensor) = (world_normals(seed, 0), world_normals(seed, 1));
        let mut x = Vector::<4>::from_column_slice(&s.x0);
        let mut real = Realisation {
            prior_draws: world_normals(seed, 2).take(4).collect(),
            ..Realisation::default()
        };
        for k in 0..=steps {
            if k > 0 {
                let (vx, vy) = (x[1], x[3]);
                x = self.model.propagate(&x, &Vector::<0>::zeros());
                // The turn: the velocity rotates by ω Δt over the step.
                (x[1], x[3]) = (cos * vx - sin * vy, sin * vx + cos * vy);
                if let Some(l) = &w_factor {
                    x += l * Vector::<4>::from_iterator(process.by_ref().take(4));
                }
            }
            let mut z = self.model.measure(&x, &Vector::<0>::zeros());
            for (i, std) in self.measurement_std.iter().enumerate() {
                // z_0 is noise-free, as in kfmc's additive worlds.
                z[i] += if k > 0 {
                    std * noise_scale * sensor.next().unwrap_or(0.0)
                } else {
                    0.0
                };
            }
            real.truth.push(x);
            real.inputs.push(Vector::<0>::zeros());
            real.measurements.push(Measurement {
                z,
                available: Availability::all(2),
            });
        }
        real
    }
}

impl System for TurningSystem {
    fn kind(&self) -> &str {
        "turning_target"
    }

    fn catalogue(&self) -> Catalogue {
        Catalogue {
            about: "the cv_range_bearing target in a coordinated turn its CV filters do not model (own_filter example)".into(),
            sections: vec![(
                "scenarios (any name)".into(),
                vec![("x0, duration_s, turn_rate_deg_s".into(), "required".into())],
            )],
        }
    }

    fn configure(&self, spec: &SystemSpec<'_>, c: &mut Checker) -> Option<Arc<dyn SystemPlan>> {
        let m: ModelKeys = c.parse("model", spec.model).unwrap_or_default();
        let model = CvRangeBearing::new(DT_S, m.accel_psd.unwrap_or(0.01), [0.0, 0.0]);
        let measurement_std = [m.range_std_m.unwrap_or(5.0), BEARING_STD_RAD];
        let mut scenarios: Vec<ScenarioKeys> = Vec::new();
        for (i, t) in spec.scenarios.iter().enumerate() {
            let Some(s) = c.parse::<ScenarioKeys>(&format!("scenarios[{i}]"), t) else {
                continue;
            };
            // A NaN duration is refused too.
            if s.duration_s.is_nan() || s.duration_s < DT_S {
                let msg = format!("{} is shorter than one sample ({DT_S} s)", s.duration_s);
                c.err(format!("scenarios[{i}].duration_s"), msg);
            }
            scenarios.push(s);
        }
        let q = model.q();
        let process_std: Vec<f64> = (0..4).map(|i| q[(i, i)].sqrt()).collect();
        // kfmc's kinds and the user's, on filters that assume the constant-velocity model.
        let kinds = WorldKinds::new(
            common_kinds().with(user_ekf_kind()),
            model.clone(),
            &process_std,
            &measurement_std,
            &P0_STD,
        );
        let entries = kinds.configure(spec, "turning_target", c);
        let layout = Layout {
            quantities: (STATES.iter().zip(UNITS))
                .map(|(n, u)| Quantity::new(*n, u))
                .collect(),
            inputs: Vec::new(),
            measurements: MEASUREMENTS.iter().map(|s| s.to_string()).collect(),
            world_states: Vec::new(),
            dt_s: DT_S,
        };
        let info = (scenarios.iter())
            .map(|s| ScenarioInfo {
                name: s.name.clone(),
                steps: (s.duration_s / DT_S).round() as usize,
            })
            .collect();
        let world = TurningWorld {
            model,
            measurement_std,
            scenarios,
        };
        c.is_clean().then(|| {
            Arc::new(WorldPlan::new(Arc::new(world), layout, info, entries)) as Arc<dyn SystemPlan>
        })
    }
}
