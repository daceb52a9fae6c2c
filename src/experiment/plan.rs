//! Validation: raw [`Spec`] → typed [`Plan`], reporting *every* problem with its key path.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};

use super::spec::{OneOrMany, Scales, Spec};

use crate::error::{SpecError, SpecErrors};
use crate::filter::luenberger::{SeedPoleReading, seed_poles};
use crate::filter::{CovarianceUpdate, Luenberger};
use crate::model::linear::{ContinuousLinear, LINEAR_DT_S, LINEAR_R_DIAG, LINEAR_STATES};
use crate::model::linear::{Linear, LinearSensor};
use crate::model::planar::{PLANAR_STATES, PlanarParams};
use crate::scenario::planar::{
    BUILTIN_PLANAR, PlanarScenarioDef, ThrustProfile, ThrustStage, builtin,
};
use crate::sim::seed::hash_str;

/// Which model (and sensor set) a study uses.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ModelKind {
    /// Planar quadrotor measuring `[y, θ, θ̇]`.
    PlanarP1,
    /// Planar quadrotor measuring `[y, θ̇, ẍ, ÿ]`.
    PlanarImu,
    /// Linear 3-axis quadrotor (seed 002) measuring `[x, y, z]` (C).
    LinearPositions,
    /// Linear 3-axis quadrotor measuring `[ẋ, ẏ, ż]` (C1).
    LinearVelocities,
    /// Linear 3-axis quadrotor measuring `[x, y]` (C2).
    LinearXy,
}

impl ModelKind {
    /// Number of states.
    pub fn nx(self) -> usize {
        6
    }
    /// Number of measurement components.
    pub fn nz(self) -> usize {
        match self {
            ModelKind::PlanarP1 => 3,
            ModelKind::PlanarImu => 4,
            ModelKind::LinearPositions | ModelKind::LinearVelocities => 3,
            ModelKind::LinearXy => 2,
        }
    }
    /// State names.
    pub fn state_names(self) -> &'static [&'static str] {
        if self.is_linear() {
            &LINEAR_STATES
        } else {
            &PLANAR_STATES
        }
    }
    /// Whether this is the linear quadrotor (no thrust stages, model-provided Q).
    pub fn is_linear(self) -> bool {
        matches!(
            self,
            ModelKind::LinearPositions | ModelKind::LinearVelocities | ModelKind::LinearXy
        )
    }
}

/// The validated model section.
#[derive(Clone, Debug, PartialEq)]
pub struct ModelPlan {
    /// Model and sensor set.
    pub kind: ModelKind,
    /// Physical parameters.
    pub params: PlanarParams,
    /// Truth process-noise std per state at scale 1.
    pub process_noise_std: Vec<f64>,
    /// Truth measurement-noise std per component at scale 1.
    pub measurement_noise_std: Vec<f64>,
}

/// Filter variants, with their configuration.
#[derive(Clone, Debug, PartialEq)]
pub enum FilterKind {
    /// Extended Kalman filter.
    Ekf {
        /// Covariance update form.
        update: CovarianceUpdate,
    },
    /// Running-mean baseline.
    RunningMean {
        /// Samples averaged.
        window: usize,
    },
    /// Information filter (propagates Y = P⁻¹ and y = P⁻¹x̂).
    Information,
    /// Square-root covariance filter (propagates a triangular S with P = S Sᵀ).
    Sqrt,
    /// Fixed-gain Kalman filter from the discrete algebraic Riccati equation (linear models).
    SteadyState,
    /// The time update alone: the prior propagated open loop, measurements ignored.
    OpenLoop,
    /// Luenberger observer whose fixed gain places eig((I − K H) F) at `poles` (linear models).
    PolePlacement {
        /// The requested closed-loop poles (re, im), closed under conjugation.
        poles: Vec<(f64, f64)>,
    },
}

impl FilterKind {
    /// The TOML `kind` tag.
    pub fn tag(&self) -> &'static str {
        match self {
            FilterKind::Ekf { .. } => "ekf",
            FilterKind::RunningMean { .. } => "running_mean",
            FilterKind::Information => "information",
            FilterKind::Sqrt => "sqrt",
            FilterKind::SteadyState => "steady_state",
            FilterKind::OpenLoop => "open_loop",
            FilterKind::PolePlacement { .. } => "pole_placement",
        }
    }
}

/// A validated filter entry.
#[derive(Clone, Debug, PartialEq)]
pub struct FilterPlan {
    /// Label (the `filter` column).
    pub label: String,
    /// Variant and its settings.
    pub kind: FilterKind,
    /// Assumed process-noise std per state (at noise scale 1 in `matched` mode).
    pub q_std: Vec<f64>,
    /// Assumed measurement-noise std per component.
    pub r_std: Vec<f64>,
    /// Multiplier of the assumed Q = diag(q_std²) (the `q_scale` column).
    pub q_scale: f64,
    /// Multiplier of the assumed R = diag(r_std²) (the `r_scale` column).
    pub r_scale: f64,
}

/// One validated `[[check.assert]]`.
#[derive(Clone, Debug, PartialEq)]
pub enum Assertion {
    /// The consistency test(s) named must pass (`consistent` → `verdict`,
    /// `white` → `innovation_whiteness`, `unbiased` → `bias_<state>`, `test_passes` → any).
    TestPasses {
        /// The `kind` as written, for reports.
        kind: String,
        /// Test names in consistency.parquet.
        tests: Vec<String>,
        /// Filter label filter.
        filter: Option<String>,
        /// Scenario filter.
        scenario: Option<String>,
    },
    /// The mean RMSE over runs of a state stays below a bound.
    RmseBelow {
        /// Filter label filter.
        filter: Option<String>,
        /// Scenario filter.
        scenario: Option<String>,
        /// The state.
        state: String,
        /// The bound.
        max: f64,
    },
}

/// The validated `[consistency]` section.
#[derive(Clone, Debug, PartialEq)]
pub struct ConsistencyPlan {
    /// Significance level of every test.
    pub alpha: f64,
    /// Whiteness lags 1..=L.
    pub whiteness_lags: usize,
    /// Extra (runs, α) evaluations of the same tests on the first `runs` runs of each cell.
    pub subsets: Vec<(usize, f64)>,
}

/// What the filters assume when the truth noise is scaled.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FilterNoiseMode {
    /// Filters keep their Q/R (the seeds' robustness study).
    Nominal,
    /// Filters' assumed std scale with the truth's.
    Matched,
}

/// How x̂_0 is formed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum InitialMode {
    /// x̂_0 = x_0 (the seeds).
    Truth,
    /// x̂_0 ~ N(x_0, P_0), drawn once per run and shared by all filters.
    Sampled,
    /// x̂_0 and P_0 by batch least squares on the run's measurements z_1..z_K
    /// ([`crate::filter::BatchInitial`]; linear models with an observable sensor set).
    BatchLs,
}

/// A validated, expanded experiment.
#[derive(Clone, Debug, PartialEq)]
pub struct Plan {
    /// Experiment name.
    pub name: String,
    /// Description.
    pub description: Option<String>,
    /// The spec file.
    pub spec_path: PathBuf,
    /// The spec text, recorded in the manifest.
    pub spec_text: String,
    /// FNV-1a 64 hash of the spec text (hex).
    pub spec_hash: String,
    /// Model.
    pub model: ModelPlan,
    /// Scenarios.
    pub scenarios: Vec<PlanarScenarioDef>,
    /// Filters.
    pub filters: Vec<FilterPlan>,
    /// Truth-noise multipliers, ascending.
    pub noise_scales: Vec<f64>,
    /// Filter noise mode.
    pub filter_noise: FilterNoiseMode,
    /// Initial-estimate mode.
    pub initial: InitialMode,
    /// P_0 diagonal std.
    pub p0_std: Vec<f64>,
    /// Runs per cell.
    pub runs: usize,
    /// Master seed.
    pub master_seed: u64,
    /// Traced runs per (scenario, noise scale).
    pub trace_runs: usize,
    /// Output folder.
    pub output: PathBuf,
    /// RMSE divergence thresholds per state.
    pub rmse_thresholds: Option<Vec<f64>>,
    /// Significance level of the per-step ANEES/ANIS bands in steps.parquet.
    pub alpha: f64,
    /// Consistency tests, when the spec asks for them.
    pub consistency: Option<ConsistencyPlan>,
    /// `kfmc check` assertions.
    pub assertions: Vec<Assertion>,
}

/// Command-line overrides of spec values.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Overrides {
    /// `--runs`
    pub runs: Option<usize>,
    /// `--seed`
    pub master_seed: Option<u64>,
    /// `--out`
    pub output: Option<PathBuf>,
    /// `--trace-runs`
    pub trace_runs: Option<usize>,
}

/// The size of a plan.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PlanSize {
    /// (scenario, noise scale) pairs.
    pub cells: usize,
    /// Simulated truths: cells × runs.
    pub runs: usize,
    /// Filter runs: runs × filters.
    pub filter_runs: usize,
    /// Filter steps in total.
    pub filter_steps: u64,
}

impl Plan {
    /// Counts cells, runs and steps.
    pub fn size(&self) -> PlanSize {
        let cells = self.scenarios.len() * self.noise_scales.len();
        let runs = cells * self.runs;
        let steps: u64 = self
            .scenarios
            .iter()
            .map(|s| s.steps(self.model.params.dt_s) as u64)
            .sum::<u64>()
            * (self.noise_scales.len() * self.runs * self.filters.len()) as u64;
        PlanSize {
            cells,
            runs,
            filter_runs: runs * self.filters.len(),
            filter_steps: steps,
        }
    }

    /// Applies command-line overrides (they win over the spec).
    pub fn apply(&mut self, o: &Overrides) -> Result<(), SpecErrors> {
        let mut errs = Vec::new();
        if let Some(r) = o.runs {
            if r == 0 {
                errs.push(self.err("--runs", "must be at least 1"));
            }
            self.runs = r;
        }
        if let Some(s) = o.master_seed {
            self.master_seed = s;
        }
        if let Some(p) = &o.output {
            self.output = p.clone();
        }
        if let Some(t) = o.trace_runs {
            self.trace_runs = t;
        }
        if self.trace_runs > self.runs {
            errs.push(self.err(
                "trace_runs",
                format!(
                    "{} traced runs but only {} runs",
                    self.trace_runs, self.runs
                ),
            ));
        }
        if errs.is_empty() {
            Ok(())
        } else {
            Err(SpecErrors(errs))
        }
    }

    fn err(&self, key: &str, msg: impl Into<String>) -> SpecError {
        SpecError {
            file: self.spec_path.clone(),
            key_path: key.to_string(),
            message: msg.into(),
        }
    }
}

/// Collects validation errors with the file name attached.
struct Checker {
    file: PathBuf,
    errors: Vec<SpecError>,
}

impl Checker {
    fn err(&mut self, key: impl Into<String>, msg: impl Into<String>) {
        self.errors.push(SpecError {
            file: self.file.clone(),
            key_path: key.into(),
            message: msg.into(),
        });
    }

    /// Reports every key of `keys` (name, present) that is set although `prefix`'s kind does
    /// not use it: a silently ignored key would be a silent mistake in the study.
    fn reject_present(&mut self, prefix: &str, keys: &[(&str, bool)], message: &str) {
        for (k, present) in keys {
            if *present {
                self.err(format!("{prefix}.{k}"), message);
            }
        }
    }

    /// Expands a scalar-or-list to `n` components, checking each with `ok`.
    fn vector(
        &mut self,
        key: &str,
        v: Option<&OneOrMany>,
        n: usize,
        default: &[f64],
        ok: fn(f64) -> bool,
        what: &str,
    ) -> Vec<f64> {
        let out = match v {
            None => default.to_vec(),
            Some(OneOrMany::One(x)) => vec![*x; n],
            Some(OneOrMany::Many(xs)) if xs.len() == n => xs.clone(),
            Some(OneOrMany::Many(xs)) => {
                self.err(key, format!("expected 1 or {n} values, got {}", xs.len()));
                return default.to_vec();
            }
        };
        for (i, x) in out.iter().enumerate() {
            if !ok(*x) {
                let k = if matches!(v, Some(OneOrMany::Many(_))) {
                    format!("{key}[{i}]")
                } else {
                    key.to_string()
                };
                self.err(k, format!("{x} is not {what}"));
                break;
            }
        }
        out
    }

    fn choice<'a>(
        &mut self,
        key: &str,
        v: Option<&'a str>,
        default: &'a str,
        allowed: &[&str],
    ) -> &'a str {
        let s = v.unwrap_or(default);
        if !allowed.contains(&s) {
            self.err(
                key,
                format!(
                    "unknown value `{s}`; expected one of: {}",
                    allowed.join(", ")
                ),
            );
        }
        s
    }
}

fn positive(x: f64) -> bool {
    x.is_finite() && x > 0.0
}
fn non_negative(x: f64) -> bool {
    x.is_finite() && x >= 0.0
}

/// Expands `start, start+step, … ≤ stop`; values are rounded to 12 significant digits so a
/// grid like 0.2, 0.4, 0.6 prints as written rather than as 0.6000000000000001.
pub fn expand_range(start: f64, stop: f64, step: f64) -> Vec<f64> {
    let n = ((stop - start) / step + 1e-9).floor() as usize + 1;
    (0..n)
        .map(|i| {
            let v = start + i as f64 * step;
            let mag = 10f64.powi(11 - v.abs().log10().floor() as i32);
            if v == 0.0 {
                0.0
            } else {
                (v * mag).round() / mag
            }
        })
        .collect()
}

/// Expands a list or range of multipliers, checking each is `ok`; `None` gives `default`.
fn scale_list(
    c: &mut Checker,
    key: &str,
    v: Option<&Scales>,
    default: f64,
    ok: fn(f64) -> bool,
    what: &str,
) -> Vec<f64> {
    let mut out = match v {
        None => vec![default],
        Some(Scales::List(v)) => v.clone(),
        Some(Scales::Range { start, stop, step }) => {
            if !(positive(*step) && non_negative(*start) && stop.is_finite() && stop >= start) {
                c.err(key, "a range needs 0 ≤ start ≤ stop and step > 0");
                vec![default]
            } else if (stop - start) / step > 1e6 {
                c.err(key, "more than a million values");
                vec![default]
            } else {
                expand_range(*start, *stop, *step)
            }
        }
    };
    if out.is_empty() {
        c.err(key, "at least one value is required");
    }
    if let Some(bad) = out.iter().find(|x| !ok(**x)) {
        c.err(key, format!("{bad} is not {what}"));
    }
    out.sort_by(f64::total_cmp);
    if out.windows(2).any(|w| w[0] == w[1]) {
        c.err(key, "duplicate values");
    }
    out
}

/// The poles of a pole_placement filter: explicit `poles`, or the seed's list
/// a·{−0.707 ± 0.707i, 1, −0.3536 ± 0.3536i, 0.5} with `pole_scale` = a and `pole_reading`.
fn pole_list(c: &mut Checker, key: &str, f: &super::spec::FilterSpec) -> Option<Vec<(f64, f64)>> {
    match (&f.poles, f.pole_scale) {
        (Some(poles), None) => {
            if f.pole_reading.is_some() {
                c.err(
                    format!("{key}.pole_reading"),
                    "only the seed's list (pole_scale) has a reading; explicit poles are exact",
                );
            }
            let mut out = Vec::with_capacity(poles.len());
            for (i, p) in poles.iter().enumerate() {
                match p.as_slice() {
                    [re, im] if re.is_finite() && im.is_finite() => out.push((*re, *im)),
                    [re] if re.is_finite() => out.push((*re, 0.0)),
                    _ => {
                        c.err(
                            format!("{key}.poles[{i}]"),
                            format!("expected [re, im] (finite numbers), got {p:?}"),
                        );
                        return None;
                    }
                }
            }
            Some(out)
        }
        (None, Some(a)) => {
            if !positive(a) {
                c.err(
                    format!("{key}.pole_scale"),
                    format!("{a} is not a positive number"),
                );
                return None;
            }
            let reading = match c.choice(
                &format!("{key}.pole_reading"),
                f.pole_reading.as_deref(),
                "printed",
                &["printed", "negated"],
            ) {
                "negated" => SeedPoleReading::Negated,
                _ => SeedPoleReading::Printed,
            };
            Some(seed_poles(a, reading).to_vec())
        }
        (Some(_), Some(_)) => {
            c.err(
                format!("{key}.poles"),
                "give either poles or pole_scale (the seed's list times a), not both",
            );
            None
        }
        (None, None) => {
            c.err(
                key.to_string(),
                "a pole_placement filter needs poles = [[re, im], …] or pole_scale = a (the seed's list)",
            );
            None
        }
    }
}

/// Validates a parsed spec into a plan.
pub fn validate(spec: Spec, path: &Path, text: &str) -> Result<Plan, SpecErrors> {
    let mut c = Checker {
        file: path.to_path_buf(),
        errors: Vec::new(),
    };

    // Model.
    let m = &spec.model;
    let linear = m.kind == "linear_quadrotor";
    if m.kind != "planar_quadrotor" && !linear {
        c.err(
            "model.kind",
            format!(
                "unknown model `{}`; expected one of: planar_quadrotor, linear_quadrotor",
                m.kind
            ),
        );
    }
    let kind = if linear {
        match c.choice(
            "model.sensor",
            m.sensor.as_deref(),
            "positions",
            &["positions", "velocities", "xy"],
        ) {
            "velocities" => ModelKind::LinearVelocities,
            "xy" => ModelKind::LinearXy,
            _ => ModelKind::LinearPositions,
        }
    } else if c.choice("model.sensor", m.sensor.as_deref(), "p1", &["p1", "imu"]) == "imu" {
        ModelKind::PlanarImu
    } else {
        ModelKind::PlanarP1
    };
    if linear {
        // The linear model's physics are the seed's A and B; only Δt is a parameter.
        c.reject_present(
            "model",
            &[
                ("mass_kg", m.mass_kg.is_some()),
                ("arm_m", m.arm_m.is_some()),
                ("inertia_kg_m2", m.inertia_kg_m2.is_some()),
                ("gravity_m_s2", m.gravity_m_s2.is_some()),
                ("process_noise_std", m.process_noise_std.is_some()),
            ],
            "not used by linear_quadrotor (its process noise is the discretised Q of the seed's Q̃)",
        );
    }
    let d = PlanarParams {
        dt_s: if linear { LINEAR_DT_S } else { 0.01 },
        ..PlanarParams::default()
    };
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
    let params = PlanarParams {
        mass_kg: param("mass_kg", m.mass_kg, d.mass_kg),
        arm_m: param("arm_m", m.arm_m, d.arm_m),
        inertia_kg_m2: param("inertia_kg_m2", m.inertia_kg_m2, d.inertia_kg_m2),
        gravity_m_s2: param("gravity_m_s2", m.gravity_m_s2, d.gravity_m_s2),
        dt_s: param("dt_s", m.dt_s, d.dt_s),
    };
    let (nx, nz) = (kind.nx(), kind.nz());
    // For the linear model these are informational (√diag Q): truth and filters use the full Q.
    let default_process_std = if linear && positive(params.dt_s) {
        let q = ContinuousLinear::seed().discretise(params.dt_s).q;
        (0..nx).map(|i| q[(i, i)].sqrt()).collect()
    } else {
        vec![0.003; nx]
    };
    // The seed gives one R (for its position sensor); the velocity sensor reuses it and xy
    // takes its first two entries.
    let default_measurement_std = if linear {
        LINEAR_R_DIAG[..nz].iter().map(|v| v.sqrt()).collect()
    } else {
        vec![0.01; nz]
    };
    let process_noise_std = c.vector(
        "model.process_noise_std",
        m.process_noise_std.as_ref(),
        nx,
        &default_process_std,
        non_negative,
        "a non-negative number",
    );
    let measurement_noise_std = c.vector(
        "model.measurement_noise_std",
        m.measurement_noise_std.as_ref(),
        nz,
        &default_measurement_std,
        non_negative,
        "a non-negative number",
    );

    // Scenarios.
    if spec.scenarios.is_empty() {
        c.err("scenarios", "at least one [[scenarios]] entry is required");
    }
    let mut names = BTreeSet::new();
    let mut scenarios = Vec::new();
    for (i, s) in spec.scenarios.iter().enumerate() {
        let key = format!("scenarios[{i}]");
        if !names.insert(s.name.clone()) {
            c.err(
                format!("{key}.name"),
                format!("duplicate scenario name `{}`", s.name),
            );
        }
        if linear {
            // L1 scenarios are an initial state and a duration; the input is zero (see
            // `model::linear`), so there are no thrust stages.
            c.reject_present(
                &key,
                &[
                    ("base", s.base.is_some()),
                    ("stages", s.stages.is_some()),
                    ("ripple", s.ripple.is_some()),
                    ("ripple_rad_s", s.ripple_rad_s.is_some()),
                ],
                "not used by linear_quadrotor (zero input)",
            );
            let mut def = PlanarScenarioDef {
                name: s.name.clone(),
                x0: [1.0, 0.0, 1.0, 0.0, 1.0, 0.0],
                duration_s: 40.0,
                profile: ThrustProfile {
                    stages: vec![],
                    ripple: 0.0,
                    ripple_rad_s: 0.0,
                },
            };
            match &s.x0 {
                Some(x0) if x0.len() != 6 || !x0.iter().all(|v| v.is_finite()) => c.err(
                    format!("{key}.x0"),
                    format!("expected 6 finite numbers, got {x0:?}"),
                ),
                Some(x0) => def.x0.copy_from_slice(x0),
                None => {}
            }
            if let Some(dur) = s.duration_s {
                if !positive(dur) || dur < params.dt_s {
                    c.err(
                        format!("{key}.duration_s"),
                        format!("{dur} is shorter than one sample"),
                    );
                }
                def.duration_s = dur;
            }
            scenarios.push(def);
            continue;
        }
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
            if !positive(dur) || dur < params.dt_s {
                c.err(
                    format!("{key}.duration_s"),
                    format!("{dur} is shorter than one sample"),
                );
            }
            def.duration_s = dur;
        }
        if let Some(r) = s.ripple {
            def.profile.ripple = r;
        }
        if let Some(w) = s.ripple_rad_s {
            def.profile.ripple_rad_s = w;
        }
        if let Some(stages) = &s.stages {
            def.profile.stages.clear();
            for (j, st) in stages.iter().enumerate() {
                let skey = format!("{key}.stages[{j}]");
                if st.thrust_n.len() != 2 || !st.thrust_n.iter().all(|v| v.is_finite()) {
                    c.err(format!("{skey}.thrust_n"), "expected [u1, u2] in N");
                    continue;
                }
                let prev = def.profile.stages.last().map(|p: &ThrustStage| p.from_step);
                if (j == 0 && st.from_step != 0) || prev.is_some_and(|p| st.from_step as usize <= p)
                {
                    c.err(
                        format!("{skey}.from_step"),
                        "stages must start at step 0 and increase strictly",
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
        scenarios.push(def);
    }

    // Filters.
    if spec.filters.is_empty() {
        c.err("filters", "at least one [[filters]] entry is required");
    }
    let mut labels = BTreeSet::new();
    let mut filters = Vec::new();
    for (i, f) in spec.filters.iter().enumerate() {
        let key = format!("filters[{i}]");
        if f.label.trim().is_empty() || f.label.contains(char::is_whitespace) {
            c.err(
                format!("{key}.label"),
                "must be non-empty and contain no spaces",
            );
        }
        if !labels.insert(f.label.clone()) {
            c.err(
                format!("{key}.label"),
                format!("duplicate filter label `{}`", f.label),
            );
        }
        let kind_tag = c.choice(
            &format!("{key}.kind"),
            Some(&f.kind),
            "ekf",
            &[
                "ekf",
                "running_mean",
                "information",
                "sqrt",
                "steady_state",
                "open_loop",
                "pole_placement",
            ],
        );
        if kind_tag != "pole_placement" {
            c.reject_present(
                &key,
                &[
                    ("poles", f.poles.is_some()),
                    ("pole_scale", f.pole_scale.is_some()),
                    ("pole_reading", f.pole_reading.is_some()),
                ],
                "only a pole_placement filter has poles",
            );
        }
        if linear && f.q_std.is_some() {
            c.err(
                format!("{key}.q_std"),
                "linear_quadrotor filters assume the model's full Q; scale it with q_scale",
            );
        }
        let fk = match kind_tag {
            "running_mean" => {
                if kind != ModelKind::PlanarP1 {
                    c.err(
                        format!("{key}.kind"),
                        "running_mean reads y, θ, θ̇ directly and needs model.sensor = \"p1\"",
                    );
                }
                c.reject_present(
                    &key,
                    &[
                        ("q_std", f.q_std.is_some()),
                        ("r_std", f.r_std.is_some()),
                        ("covariance_update", f.covariance_update.is_some()),
                    ],
                    "not used by a running_mean filter",
                );
                let w = f.window.unwrap_or(11);
                if w == 0 {
                    c.err(format!("{key}.window"), "must be at least 1");
                }
                FilterKind::RunningMean { window: w as usize }
            }
            "pole_placement" => {
                c.reject_present(
                    &key,
                    &[
                        ("q_std", f.q_std.is_some()),
                        ("r_std", f.r_std.is_some()),
                        ("covariance_update", f.covariance_update.is_some()),
                        ("window", f.window.is_some()),
                        ("q_scale", f.q_scale.is_some()),
                        ("r_scale", f.r_scale.is_some()),
                    ],
                    "not used by a pole_placement observer (its gain comes from the poles)",
                );
                let poles = pole_list(&mut c, &key, f);
                if kind != ModelKind::LinearPositions {
                    c.err(
                        format!("{key}.kind"),
                        "pole_placement needs model.kind = \"linear_quadrotor\" with sensor = \"positions\" (the only observable sensor set)",
                    );
                } else if let Some(poles) = &poles {
                    // Place now, so an impossible request is a spec error, not 100 failed runs.
                    let model = Linear::<3>::new(LinearSensor::Positions, params.dt_s)
                        .expect("positions has 3 components");
                    if let Err(e) = Luenberger::<6, 3>::from_poles(&model, poles) {
                        c.err(format!("{key}.poles"), e.to_string());
                    }
                }
                FilterKind::PolePlacement {
                    poles: poles.unwrap_or_default(),
                }
            }
            "open_loop" => {
                c.reject_present(
                    &key,
                    &[
                        ("window", f.window.is_some()),
                        ("covariance_update", f.covariance_update.is_some()),
                        ("r_std", f.r_std.is_some()),
                        ("r_scale", f.r_scale.is_some()),
                    ],
                    "not used by an open_loop filter (it never updates)",
                );
                FilterKind::OpenLoop
            }
            "information" | "sqrt" | "steady_state" => {
                c.reject_present(
                    &key,
                    &[
                        ("window", f.window.is_some()),
                        ("covariance_update", f.covariance_update.is_some()),
                    ],
                    &format!("not used by a {kind_tag} filter"),
                );
                match kind_tag {
                    "information" => FilterKind::Information,
                    "sqrt" => FilterKind::Sqrt,
                    _ => {
                        // The DARE has a stabilising solution only for a detectable pair: the
                        // velocity and xy sensors leave an integrator unobserved.
                        if kind != ModelKind::LinearPositions {
                            c.err(
                                format!("{key}.kind"),
                                "steady_state needs model.kind = \"linear_quadrotor\" with sensor = \"positions\" (the only detectable sensor set)",
                            );
                        }
                        FilterKind::SteadyState
                    }
                }
            }
            _ => {
                if f.window.is_some() {
                    c.err(
                        format!("{key}.window"),
                        "only a running_mean filter has a window",
                    );
                }
                let form = c.choice(
                    &format!("{key}.covariance_update"),
                    f.covariance_update.as_deref(),
                    "standard",
                    &["standard", "joseph"],
                );
                FilterKind::Ekf {
                    update: if form == "joseph" {
                        CovarianceUpdate::Joseph
                    } else {
                        CovarianceUpdate::Standard
                    },
                }
            }
        };
        let q_std = c.vector(
            &format!("{key}.q_std"),
            f.q_std.as_ref(),
            nx,
            &process_noise_std,
            non_negative,
            "a non-negative number",
        );
        let r_std = c.vector(
            &format!("{key}.r_std"),
            f.r_std.as_ref(),
            nz,
            &measurement_noise_std,
            positive,
            "a positive number (R must be positive definite)",
        );
        if matches!(
            fk,
            FilterKind::RunningMean { .. } | FilterKind::PolePlacement { .. }
        ) {
            c.reject_present(
                &key,
                &[
                    ("q_scale", f.q_scale.is_some()),
                    ("r_scale", f.r_scale.is_some()),
                ],
                "not used by a running_mean filter",
            );
        }
        let q_scales = scale_list(
            &mut c,
            &format!("{key}.q_scale"),
            f.q_scale.as_ref(),
            1.0,
            positive,
            "a positive number",
        );
        let r_scales = scale_list(
            &mut c,
            &format!("{key}.r_scale"),
            f.r_scale.as_ref(),
            1.0,
            positive,
            "a positive number",
        );
        // Each (q_scale, r_scale) pair is a filter variant with the same label; the scales
        // are key columns of every table.
        for &q_scale in &q_scales {
            for &r_scale in &r_scales {
                filters.push(FilterPlan {
                    label: f.label.clone(),
                    kind: fk.clone(),
                    q_std: q_std.clone(),
                    r_std: r_std.clone(),
                    q_scale,
                    r_scale,
                });
            }
        }
    }

    // Noise sweep.
    let noise = spec.noise.as_ref();
    let noise_scales = scale_list(
        &mut c,
        "noise.scales",
        noise.and_then(|n| n.scales.as_ref()),
        1.0,
        non_negative,
        "a non-negative number",
    );
    let fmode = c.choice(
        "noise.filter_noise",
        noise.and_then(|n| n.filter_noise.as_deref()),
        "nominal",
        &["nominal", "matched"],
    );
    let filter_noise = if fmode == "matched" {
        FilterNoiseMode::Matched
    } else {
        FilterNoiseMode::Nominal
    };

    // Initial estimate.
    let ie = spec.initial_estimate.as_ref();
    let imode = c.choice(
        "initial_estimate.mode",
        ie.and_then(|i| i.mode.as_deref()),
        "truth",
        &["truth", "sampled", "batch_ls"],
    );
    let initial = match imode {
        "sampled" => InitialMode::Sampled,
        "batch_ls" => InitialMode::BatchLs,
        _ => InitialMode::Truth,
    };
    if initial == InitialMode::BatchLs {
        if kind != ModelKind::LinearPositions {
            c.err(
                "initial_estimate.mode",
                "batch_ls needs model.kind = \"linear_quadrotor\" with sensor = \"positions\": the other sensor sets leave x0 undetermined (observability rank 3 or 4 of 6)",
            );
        }
        c.reject_present(
            "initial_estimate",
            &[("p0_std", ie.is_some_and(|i| i.p0_std.is_some()))],
            "not used with mode = \"batch_ls\" (P0 is the least-squares covariance)",
        );
    }
    let p0_std = c.vector(
        "initial_estimate.p0_std",
        ie.and_then(|i| i.p0_std.as_ref()),
        nx,
        &vec![1.0; nx],
        positive,
        "a positive number",
    );

    if initial == InitialMode::BatchLs
        && kind == ModelKind::LinearPositions
        && positive(params.dt_s)
        && c.errors.is_empty()
    {
        // Build each scenario's estimator now: a sensor schedule or noise level that cannot
        // determine x0 is a spec error, and the study can then rely on it.
        let model = Linear::<3>::new(LinearSensor::Positions, params.dt_s)
            .expect("positions has 3 components");
        let r = crate::linalg::Matrix::<3, 3>::from_fn(|i, j| {
            if i == j {
                measurement_noise_std[i].powi(2)
            } else {
                0.0
            }
        });
        for (i, sc) in scenarios.iter().enumerate() {
            let controls = vec![crate::linalg::Vector::<4>::zeros(); sc.steps(params.dt_s) + 1];
            if let Err(e) =
                crate::filter::BatchInitial::new(&model, &controls, &model.discrete().q, &r)
            {
                c.err(
                    "initial_estimate.mode",
                    format!("batch_ls for scenarios[{i}] (`{}`): {e}", sc.name),
                );
            }
        }
    }

    let rmse_thresholds = spec
        .divergence
        .as_ref()
        .and_then(|d| d.rmse_thresholds.as_ref())
        .map(|t| {
            c.vector(
                "divergence.rmse_thresholds",
                Some(t),
                nx,
                &vec![f64::INFINITY; nx],
                positive,
                "a positive number",
            )
        });

    let cs = spec.consistency.as_ref();
    let alpha = cs.and_then(|c| c.alpha).unwrap_or(0.05);
    if !(alpha > 0.0 && alpha < 1.0) {
        c.err("consistency.alpha", format!("{alpha} is not in (0, 1)"));
    }
    let whiteness_lags = cs.and_then(|c| c.whiteness_lags).unwrap_or(5);
    if whiteness_lags > 50 {
        c.err("consistency.whiteness_lags", "at most 50 lags");
    }
    let runs = spec.runs.unwrap_or(100);
    let mut subsets = Vec::new();
    for (i, sub) in cs.iter().flat_map(|c| c.subsets.iter()).enumerate() {
        let key = format!("consistency.subsets[{i}]");
        if sub.runs < 2 || sub.runs > runs {
            c.err(
                format!("{key}.runs"),
                format!("{} is not in 2..={runs} (the study's runs)", sub.runs),
            );
        }
        if !(sub.alpha > 0.0 && sub.alpha < 1.0) {
            c.err(
                format!("{key}.alpha"),
                format!("{} is not in (0, 1)", sub.alpha),
            );
        }
        if subsets.contains(&(sub.runs as usize, sub.alpha))
            || (sub.runs == runs && sub.alpha == alpha)
        {
            c.err(key, "duplicates another (runs, alpha) evaluation");
        }
        subsets.push((sub.runs as usize, sub.alpha));
    }
    let consistency = cs.map(|_| ConsistencyPlan {
        alpha,
        whiteness_lags: whiteness_lags as usize,
        subsets,
    });

    let states = kind.state_names();
    let mut assertions = Vec::new();
    for (i, a) in spec.check.iter().flat_map(|c| c.asserts.iter()).enumerate() {
        let key = format!("check.assert[{i}]");
        if let Some(f) = &a.filter
            && !labels.contains(f)
        {
            c.err(format!("{key}.filter"), format!("no filter labelled `{f}`"));
        }
        if let Some(sc) = &a.scenario
            && !names.contains(sc)
        {
            c.err(
                format!("{key}.scenario"),
                format!("no scenario named `{sc}`"),
            );
        }
        if let Some(st) = &a.state
            && !states.contains(&st.as_str())
        {
            c.err(
                format!("{key}.state"),
                format!("unknown state `{st}`; states: {}", states.join(", ")),
            );
        }
        let unused_msg = format!("not used by kind = \"{}\"", a.kind);
        let unused =
            |c: &mut Checker, keys: &[(&str, bool)]| c.reject_present(&key, keys, &unused_msg);
        let tests = |names: Vec<String>| Assertion::TestPasses {
            kind: a.kind.clone(),
            tests: names,
            filter: a.filter.clone(),
            scenario: a.scenario.clone(),
        };
        let parsed = match a.kind.as_str() {
            "consistent" | "white" => {
                unused(
                    &mut c,
                    &[
                        ("state", a.state.is_some()),
                        ("max", a.max.is_some()),
                        ("test", a.test.is_some()),
                    ],
                );
                let t = if a.kind == "white" {
                    "innovation_whiteness"
                } else {
                    "verdict"
                };
                Some(tests(vec![t.to_string()]))
            }
            "unbiased" => {
                unused(
                    &mut c,
                    &[("max", a.max.is_some()), ("test", a.test.is_some())],
                );
                let which: Vec<String> = match &a.state {
                    Some(s) => vec![format!("bias_{s}")],
                    None => states.iter().map(|s| format!("bias_{s}")).collect(),
                };
                Some(tests(which))
            }
            "test_passes" => {
                unused(
                    &mut c,
                    &[("state", a.state.is_some()), ("max", a.max.is_some())],
                );
                match &a.test {
                    Some(t) => Some(tests(vec![t.clone()])),
                    None => {
                        c.err(
                            format!("{key}.test"),
                            "kind = \"test_passes\" needs a test name",
                        );
                        None
                    }
                }
            }
            "rmse_below" => {
                unused(&mut c, &[("test", a.test.is_some())]);
                match (&a.state, a.max) {
                    (Some(state), Some(max)) if max > 0.0 => Some(Assertion::RmseBelow {
                        filter: a.filter.clone(),
                        scenario: a.scenario.clone(),
                        state: state.clone(),
                        max,
                    }),
                    _ => {
                        c.err(key.clone(), "kind = \"rmse_below\" needs state and max > 0");
                        None
                    }
                }
            }
            other => {
                c.err(
                    format!("{key}.kind"),
                    format!("unknown value `{other}`; expected one of: consistent, white, unbiased, test_passes, rmse_below"),
                );
                None
            }
        };
        assertions.extend(parsed);
    }

    if runs == 0 {
        c.err("runs", "must be at least 1");
    }
    let trace_runs = spec.trace_runs.unwrap_or(0);
    if trace_runs > runs {
        c.err(
            "trace_runs",
            format!("{trace_runs} traced runs but only {runs} runs"),
        );
    }
    let name = spec.name.clone().unwrap_or_else(|| {
        path.file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_else(|| "experiment".into())
    });
    if name.is_empty() || name.contains(['/', '\\']) {
        c.err("name", "must be non-empty and contain no path separators");
    }
    let output = spec
        .output
        .as_ref()
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from("results").join(&name));

    if !c.errors.is_empty() {
        return Err(SpecErrors(c.errors));
    }
    Ok(Plan {
        name,
        description: spec.description,
        spec_path: path.to_path_buf(),
        spec_text: text.to_string(),
        spec_hash: format!("{:016x}", hash_str(text)),
        model: ModelPlan {
            kind,
            params,
            process_noise_std,
            measurement_noise_std,
        },
        scenarios,
        filters,
        noise_scales,
        filter_noise,
        initial,
        p0_std,
        runs: runs as usize,
        master_seed: spec.master_seed.unwrap_or(0),
        trace_runs: trace_runs as usize,
        output,
        rmse_thresholds,
        alpha,
        consistency,
        assertions,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn range_matches_the_seed_sweep() {
        let v = expand_range(0.2, 50.0, 0.2);
        assert_eq!(v.len(), 250);
        assert_eq!(v[0], 0.2);
        assert_eq!(v[2], 0.6);
        assert_eq!(*v.last().unwrap(), 50.0);
    }
}
