//! The planar-quadrotor system (`model.kind = "planar_quadrotor"`): P1 and P2 of seeds
//! 000/001/003.
//!
//! The world is the model plus additive noise, so the system only validates its `[model]`
//! table and scenarios and hands everything else to [`AdditivePlan`]. Filter kinds: the
//! common ones ([`common_kinds`]) and, for sensor P1, the seeds' running mean. A user adds
//! kinds of their own with [`PlanarSystem::with_p1_filter`] / [`PlanarSystem::with_imu_filter`]
//! and registers the result in place of the built-in.

pub mod model;
pub mod running_mean;
pub mod scenario;

use std::sync::Arc;

use serde::Deserialize;

use crate::linalg::Vector;
use crate::model::Model;
use crate::sim::TruthNoise;
use crate::system::additive::{
    AdditivePlan, AssumedNoise, FilterContext, FilterEntry, FilterKind, FilterKinds, FilterSetup,
    RunFilter, check_scenarios, common_kinds,
};
use crate::system::checker::{Checker, non_negative, positive};
use crate::system::settings::InitialMode;
use crate::system::spec_values::{OneOrMany, TableOf};
use crate::system::{
    Catalogue, FilterInfo, Layout, PositionAxis, Quantity, System, SystemPlan, SystemSpec,
};
use model::PlanarParams;
use model::{IMU_MEASUREMENTS, P1_MEASUREMENTS, PLANAR_STATES, Planar, PlanarImu, PlanarP1};
use running_mean::RunningMean;
use scenario::{BUILTIN_PLANAR, PlanarScenarioDef, ThrustProfile, ThrustStage, builtin};

/// `model.kind` of this system.
pub const KIND: &str = "planar_quadrotor";

/// `[model]` of a planar spec.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct ModelKeys {
    sensor: Option<String>,
    mass_kg: Option<f64>,
    arm_m: Option<f64>,
    inertia_kg_m2: Option<f64>,
    gravity_m_s2: Option<f64>,
    dt_s: Option<f64>,
    process_noise_std: Option<OneOrMany>,
    measurement_noise_std: Option<OneOrMany>,
}

/// `[[scenarios]]` of a planar spec.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct ScenarioKeys {
    name: String,
    base: Option<String>,
    x0: Option<Vec<f64>>,
    duration_s: Option<f64>,
    stages: Option<Vec<TableOf<StageKeys>>>,
    ripple: Option<f64>,
    ripple_rad_s: Option<f64>,
}

/// One thrust stage.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct StageKeys {
    from_step: u64,
    thrust_n: Vec<f64>,
}

/// The planar-quadrotor system, with its filter kinds per sensor set.
#[derive(Clone)]
pub struct PlanarSystem {
    p1: FilterKinds<6, 2, 3, PlanarP1>,
    imu: FilterKinds<6, 2, 4, PlanarImu>,
}

impl Default for PlanarSystem {
    fn default() -> Self {
        PlanarSystem::new()
    }
}

impl PlanarSystem {
    /// The built-in system: the common filter kinds, plus the running mean on P1.
    pub fn new() -> Self {
        PlanarSystem {
            p1: common_kinds().with(RunningMeanKind),
            imu: common_kinds(),
        }
    }

    /// Adds a filter kind for sensor set P1 (`[y, θ, θ̇]`).
    pub fn with_p1_filter(mut self, kind: impl FilterKind<6, 2, 3, PlanarP1> + 'static) -> Self {
        self.p1 = self.p1.with(kind);
        self
    }

    /// Adds a filter kind for sensor set P2 (`[y, θ̇, ẍ, ÿ]`).
    pub fn with_imu_filter(mut self, kind: impl FilterKind<6, 2, 4, PlanarImu> + 'static) -> Self {
        self.imu = self.imu.with(kind);
        self
    }
}

impl System for PlanarSystem {
    fn kind(&self) -> &str {
        KIND
    }

    fn catalogue(&self) -> Catalogue {
        let scenarios = BUILTIN_PLANAR
            .iter()
            .map(|name| {
                let d = builtin(name).expect("built-in");
                let stages: Vec<String> = d
                    .profile
                    .stages
                    .iter()
                    .map(|st| {
                        format!(
                            "k≥{}: [{}, {}] N",
                            st.from_step, st.thrust_n[0], st.thrust_n[1]
                        )
                    })
                    .collect();
                (
                    name.to_string(),
                    format!(
                        "x0 = {:?}; {}",
                        d.x0.map(|v| (v * 1e4).round() / 1e4),
                        stages.join(", ")
                    ),
                )
            })
            .collect();
        let mut filters = self.p1.catalogue();
        for (tag, about) in &mut filters {
            if self.imu.get(tag).is_none() {
                about.push_str(" (sensor p1 only)");
            }
        }
        for (tag, about) in self.imu.catalogue() {
            if self.p1.get(&tag).is_none() {
                filters.push((tag, about + " (sensor imu only)"));
            }
        }
        Catalogue {
            about: "planar quadrotor, state [x, xdot, y, ydot, theta, thetadot], input [u1, u2] (seeds 000/001/003)".into(),
            sections: vec![
                (
                    "sensors (model.sensor)".into(),
                    vec![
                        ("p1".into(), "[y, theta, thetadot]  (seeds 000/001, default)".into()),
                        ("imu".into(), "[y, thetadot, xddot, yddot]  (seed 003)".into()),
                    ],
                ),
                (
                    "model keys".into(),
                    vec![(
                        "[model]".into(),
                        "mass_kg, arm_m, inertia_kg_m2, gravity_m_s2, dt_s, process_noise_std, measurement_noise_std".into(),
                    )],
                ),
                ("scenarios (built-in; base = …, x0, duration_s, stages, ripple, ripple_rad_s)".into(), scenarios),
                ("filters (filters[].kind)".into(), filters),
                (
                    "initial estimates (initial_estimate.mode)".into(),
                    vec![
                        ("truth".into(), "x̂0 = x0, P0 = diag(p0_std²) (the seeds)".into()),
                        ("sampled".into(), "x̂0 ~ N(x0, P0), one draw per run shared by all filters".into()),
                    ],
                ),
            ],
        }
    }

    fn configure(&self, spec: &SystemSpec<'_>, c: &mut Checker) -> Option<Arc<dyn SystemPlan>> {
        let m: ModelKeys = c.parse("model", spec.model).unwrap_or_default();
        let imu = c.choice("model.sensor", m.sensor.as_deref(), "p1", &["p1", "imu"]) == "imu";
        let parts = PlanarParts::read(&m, imu, spec, c);
        if imu {
            let other = |k: &str| {
                self.p1.get(k).map(|_| {
                    // Only the running mean's reason is known here; another P1 kind (a
                    // user's) is named as what it is.
                    if k == "running_mean" {
                        format!("{k} reads y, θ, θ̇ directly and needs model.sensor = \"p1\"")
                    } else {
                        format!(
                            "filter kind `{k}` is registered for model.sensor = \"p1\" only, and this spec's sensor is \"imu\""
                        )
                    }
                })
            };
            parts.plan(&self.imu, &other, spec, c)
        } else {
            let other = |k: &str| {
                self.imu
                    .get(k)
                    .map(|_| format!("filter kind `{k}` is registered for model.sensor = \"imu\" only, and this spec's sensor is \"p1\""))
            };
            parts.plan(&self.p1, &other, spec, c)
        }
    }
}

/// What a planar spec says besides its filters, the same for either sensor set.
struct PlanarParts {
    params: PlanarParams,
    process_std: Vec<f64>,
    measurement_std: Vec<f64>,
    scenarios: Vec<PlanarScenarioDef>,
    p0_std: Vector<6>,
    layout: Layout,
}

impl PlanarParts {
    /// Validates the `[model]` keys `m` (sensor set IMU when `imu`), the scenarios and the
    /// initial estimate.
    fn read(m: &ModelKeys, imu: bool, spec: &SystemSpec<'_>, c: &mut Checker) -> Self {
        let params = physical_params(m, c);
        let nz = if imu { 4 } else { 3 };
        let process_std = c.vector(
            "model.process_noise_std",
            m.process_noise_std.as_ref(),
            6,
            &[0.003; 6],
            non_negative,
            "a non-negative number",
        );
        let measurement_std = c.vector(
            "model.measurement_noise_std",
            m.measurement_noise_std.as_ref(),
            nz,
            &vec![0.01; nz],
            non_negative,
            "a non-negative number",
        );
        let scenarios = scenarios(spec.scenarios, params.dt_s, c);
        if spec.initial.mode == InitialMode::BatchLs {
            c.err(
                "initial_estimate.mode",
                "batch_ls needs a linear model with an observable sensor set (e.g. model.kind = \"linear_quadrotor\" with sensor = \"positions\")",
            );
        }
        let p0_std = c.vector(
            "initial_estimate.p0_std",
            spec.initial.p0_std.as_ref(),
            6,
            &[1.0; 6],
            positive,
            "a positive number",
        );
        PlanarParts {
            layout: layout(imu, params.dt_s),
            p0_std: Vector::<6>::from_column_slice(&p0_std),
            params,
            process_std,
            measurement_std,
            scenarios,
        }
    }

    /// The plan on the sensor set of `kinds` (`other` explains a kind registered for the other
    /// set only), when the whole spec is clean.
    fn plan<const NZ: usize>(
        self,
        kinds: &FilterKinds<6, 2, NZ, Planar<NZ>>,
        other: &dyn Fn(&str) -> Option<String>,
        spec: &SystemSpec<'_>,
        c: &mut Checker,
    ) -> Option<Arc<dyn SystemPlan>>
    where
        Planar<NZ>: Model<6, 2, NZ>,
    {
        let dt_s = self.params.dt_s;
        let model = Planar::<NZ>::new(self.params);
        let entries = kinds.configure_entries(
            spec.filters,
            &FilterSetup::new(&model, KIND, &self.process_std, &self.measurement_std)
                .explaining_unknown(other),
            c,
        );
        let samples = self
            .scenarios
            .iter()
            .map(|s| s.steps(dt_s) + 1)
            .max()
            .unwrap_or(0);
        if entries.len() == spec.filters.len() && samples > 0 {
            check_scenarios(&entries, spec.filters, samples, c);
        }
        let noise = truth_noise::<NZ>(&self.process_std, &self.measurement_std);
        (c.is_clean()).then(|| {
            Arc::new(AdditivePlan::new(
                model,
                self.layout,
                self.scenarios.iter().map(|s| s.expand(dt_s)).collect(),
                noise,
                self.p0_std,
                entries,
            )) as Arc<dyn SystemPlan>
        })
    }
}

/// The physical parameters of `[model]`, each a positive number (defaults: the seeds').
fn physical_params(m: &ModelKeys, c: &mut Checker) -> PlanarParams {
    let d = PlanarParams::default();
    let mut param = |key: &str, v: Option<f64>, def: f64| {
        let x = v.unwrap_or(def);
        if !positive(x) {
            c.err(
                format!("model.{key}"),
                format!("{x} is not a positive number"),
            );
        }
        x
    };
    PlanarParams {
        mass_kg: param("mass_kg", m.mass_kg, d.mass_kg),
        arm_m: param("arm_m", m.arm_m, d.arm_m),
        inertia_kg_m2: param("inertia_kg_m2", m.inertia_kg_m2, d.inertia_kg_m2),
        gravity_m_s2: param("gravity_m_s2", m.gravity_m_s2, d.gravity_m_s2),
        dt_s: param("dt_s", m.dt_s, d.dt_s),
    }
}

/// The planar layout: the six states as quantities, with x and y the position in the vertical
/// plane, and the measurements of sensor set P1 or (`imu`) the IMU set.
fn layout(imu: bool, dt_s: f64) -> Layout {
    Layout {
        quantities: PLANAR_STATES
            .iter()
            .zip(["m", "m/s", "m", "m/s", "rad", "rad/s"])
            // θ is the seeds' unwrapped attitude (a roll passes ±π continuously), so its
            // error is a plain difference.
            .map(|(n, u)| match *n {
                // The vehicle moves in the vertical x–y plane: x to the right, y up.
                "x" => Quantity::position(*n, u, PositionAxis::X),
                "y" => Quantity::position(*n, u, PositionAxis::Y),
                _ => Quantity::new(*n, u),
            })
            .collect(),
        inputs: vec!["u1".into(), "u2".into()],
        measurements: if imu {
            IMU_MEASUREMENTS.iter().map(|s| s.to_string()).collect()
        } else {
            P1_MEASUREMENTS.iter().map(|s| s.to_string()).collect()
        },
        world_states: Vec::new(),
        dt_s,
    }
}

fn truth_noise<const NZ: usize>(process: &[f64], measurement: &[f64]) -> TruthNoise<6, NZ> {
    let ok = process.len() == 6 && measurement.len() == NZ;
    TruthNoise {
        process_std: if ok {
            Vector::<6>::from_column_slice(process)
        } else {
            Vector::<6>::zeros()
        },
        measurement_std: if ok {
            Vector::<NZ>::from_column_slice(measurement)
        } else {
            Vector::<NZ>::zeros()
        },
    }
}

/// Validates the planar scenarios: a built-in by name (or `base`), with overrides, or a
/// custom one with x0 and stages.
fn scenarios(tables: &[toml::Table], dt_s: f64, c: &mut Checker) -> Vec<PlanarScenarioDef> {
    let mut out = Vec::new();
    for (i, t) in tables.iter().enumerate() {
        let key = format!("scenarios[{i}]");
        let Some(s) = c.parse::<ScenarioKeys>(&key, t) else {
            continue;
        };
        let base_name = s.base.as_deref().unwrap_or(&s.name);
        let base = builtin(base_name);
        if base.is_none() && (s.base.is_some() || s.x0.is_none() || s.stages.is_none()) {
            let k = if s.base.is_some() { "base" } else { "name" };
            c.err(
                format!("{key}.{k}"),
                format!(
                    "unknown built-in scenario `{base_name}` (built-ins: {}); a custom scenario needs x0 and stages",
                    BUILTIN_PLANAR.join(", ")
                ),
            );
            continue;
        }
        let mut def = base.unwrap_or(PlanarScenarioDef {
            name: s.name.clone(),
            x0: [0.0; 6],
            duration_s: 10.0,
            profile: ThrustProfile {
                stages: vec![],
                ripple: 0.0,
                ripple_rad_s: 0.0,
            },
        });
        def.name = s.name.clone();
        if let Some(x0) = &s.x0 {
            if x0.len() != 6 || !x0.iter().all(|v| v.is_finite()) {
                c.err(
                    format!("{key}.x0"),
                    format!("expected 6 finite numbers, got {x0:?}"),
                );
            } else {
                def.x0.copy_from_slice(x0);
            }
        }
        if let Some(dur) = s.duration_s {
            def.duration_s = dur;
        }
        let Some(k_max) = c.scenario_steps(&key, def.duration_s, dt_s) else {
            continue;
        };
        // u = stage ⊙ (1 + a·[cos ωt, sin ωt]): beyond a = 1 a thrust turns negative.
        if let Some(r) = s.ripple
            && c.number(
                &format!("{key}.ripple"),
                r,
                |a| (0.0..=1.0).contains(&a),
                "a relative amplitude in [0, 1]",
            )
        {
            def.profile.ripple = r;
        }
        if let Some(w) = s.ripple_rad_s
            && c.number(
                &format!("{key}.ripple_rad_s"),
                w,
                non_negative,
                "a non-negative frequency",
            )
        {
            def.profile.ripple_rad_s = w;
        }
        if let Some(stages) = &s.stages {
            def.profile.stages.clear();
            for (j, st) in stages.iter().enumerate() {
                let skey = format!("{key}.stages[{j}]");
                if st.thrust_n.len() != 2 || !st.thrust_n.iter().all(|v| non_negative(*v)) {
                    c.err(
                        format!("{skey}.thrust_n"),
                        format!(
                            "expected [u1, u2]: two finite thrusts ≥ 0 in N (rotors push, they do not pull), got {:?}",
                            st.thrust_n
                        ),
                    );
                    continue;
                }
                let prev = def.profile.stages.last().map(|p: &ThrustStage| p.from_step);
                if (j == 0 && st.from_step != 0) || prev.is_some_and(|p| st.from_step as usize <= p)
                {
                    c.err(
                        format!("{skey}.from_step"),
                        "stages must start at step 0 and increase strictly",
                    );
                } else if st.from_step > k_max as u64 {
                    c.err(
                        format!("{skey}.from_step"),
                        format!(
                            "{} lies beyond the scenario's last step K = {k_max} (duration_s / dt_s), so the stage would never act",
                            st.from_step
                        ),
                    );
                }
                def.profile.stages.push(ThrustStage {
                    from_step: st.from_step as usize,
                    thrust_n: [st.thrust_n[0], st.thrust_n[1]],
                });
            }
            if stages.is_empty() {
                c.err(format!("{key}.stages"), "at least one stage is required");
            }
        }
        out.push(def);
    }
    out
}

/// `kind = "running_mean"`: the seeds' baseline (P1 only).
struct RunningMeanKind;

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RunningMeanKeys {
    window: Option<u64>,
}

#[derive(Debug)]
struct RunningMeanEntry {
    filter: RunningMean,
    /// Whether `window` is in the file (else it is the default), for the error's key.
    window_given: bool,
}

impl FilterEntry<6, 2, 3, PlanarP1> for RunningMeanEntry {
    fn info(&self) -> FilterInfo {
        FilterInfo {
            kind: "running_mean".into(),
            has_covariance: false,
            q_scale: false,
            r_scale: false,
        }
    }
    fn assumed_std(&self) -> (&[f64], &[f64]) {
        (&[], &[])
    }
    fn prepare(
        &self,
        _model: &PlanarP1,
        _noise: &AssumedNoise<6, 3>,
    ) -> Box<dyn RunFilter<6, 2, 3, PlanarP1>> {
        Box::new(self.filter.clone())
    }
    fn check_scenarios(&self, key: &str, samples: usize, c: &mut Checker) {
        let w = self.filter.window;
        if w <= samples {
            return;
        }
        let msg = format!(
            "longer than the longest scenario ({samples} samples = K + 1), so it never fills"
        );
        if self.window_given {
            c.err(
                format!("{key}.window"),
                format!("{w} samples is {msg}; at most {samples}"),
            );
        } else {
            c.err(
                key,
                format!("the default window = {w} samples is {msg}; set window ≤ {samples}"),
            );
        }
    }
}

impl FilterKind<6, 2, 3, PlanarP1> for RunningMeanKind {
    fn tag(&self) -> &str {
        "running_mean"
    }
    fn about(&self) -> String {
        "running-mean baseline of seed 000; window (samples, default 11)".into()
    }
    fn configure(
        &self,
        cx: &FilterContext<'_, 6, 3, PlanarP1>,
        c: &mut Checker,
    ) -> Option<Arc<dyn FilterEntry<6, 2, 3, PlanarP1>>> {
        let keys: RunningMeanKeys = c.parse(&cx.key, cx.table)?;
        let w = keys.window.unwrap_or(11);
        if w == 0 {
            c.err(format!("{}.window", cx.key), "must be at least 1");
        }
        Some(Arc::new(RunningMeanEntry {
            filter: RunningMean {
                // Saturating: an absurd window is refused against the scenarios, never wrapped.
                window: usize::try_from(w).unwrap_or(usize::MAX),
            },
            window_given: keys.window.is_some(),
        }))
    }
}
