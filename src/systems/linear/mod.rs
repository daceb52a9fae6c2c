//! A linear-Gaussian system from TOML (`model.kind = "linear"`).
//!
//! The spec names the states, inputs and measurement components and gives the matrices,
//! either discrete (`f, g, h, q, r`) or continuous (`a, b, c, gamma, q_tilde`, with the
//! discrete `r`), which are discretised by zero-order hold and Van Loan's method
//! ([`discretise::zoh_van_loan`], the same function L1 uses). Components may report at lower
//! rates in sensor groups ([`model::LinearModel`]'s availability). The world is the model plus
//! additive Gaussian noise, so the system is an [`AdditivePlan`] with the linear filter kinds
//! ([`linear_kinds`], the steady state and pole placement behind a real detectability check).
//! It is built only from the public API a downstream crate would use.
//!
//! # Sizes
//! The step loop is monomorphised: a spec's sizes are dispatched once, at configure time, to
//! an `AdditivePlan<NX, NU_MAX, NZ, LinearModel<NX, NU_MAX, NZ>>`. Each instantiation compiles
//! the whole filter family, so only the (states, measurement components) pairs of
//! [`SUPPORTED`] are compiled, and the inputs are padded with zero columns of G (and zero
//! controls) up to [`NU_MAX`] = 4, which changes no result (the padding adds exact zeros;
//! `discretise`'s tests check F and Q bit for bit). The traces keep only the real inputs.
//! Another size is a spec error that lists the compiled ones; adding a pair is one entry in
//! the `sizes!` list below.

pub mod discretise;
pub mod model;
pub mod spec;

use std::any::Any;
use std::sync::Arc;

use nalgebra::DMatrix;

use crate::filter::BatchInitial;
use crate::linalg::{Matrix, SmallCholesky, Vector};
use crate::scenario::Scenario;
use crate::sim::TruthNoise;
use crate::system::additive::{AdditivePlan, FilterSetup, linear_kinds};
use crate::system::checker::{Checker, positive};
use crate::system::settings::{InitialMode, RunSettings};
use crate::system::{
    Catalogue, FilterInfo, Layout, Quantity, ScenarioInfo, System, SystemPlan, SystemSpec,
};
use crate::trial::{Trial, Unit, UnitResult};
use discretise::zoh_van_loan;
use model::{LinearModel, detectable};
use spec::{Dynamics, LinearSpec};

/// `model.kind` of this system.
pub const KIND: &str = "linear";

/// The input dimension every linear system is compiled with; a spec has at most this many
/// inputs, and fewer are padded with zero columns.
pub const NU_MAX: usize = 4;

/// The most measurement components a spec may name.
pub const MAX_MEASUREMENTS: usize = 6;

type Build = fn(&LinearSpec, &SystemSpec<'_>, &mut Checker) -> Option<Arc<dyn SystemPlan>>;

/// The compiled (states, measurement components) pairs, and the dispatch to them.
macro_rules! sizes {
    ($( $nx:literal => [$($nz:literal),*] ),* $(,)?) => {
        /// The compiled sizes: per state count, the measurement-component counts.
        pub const SUPPORTED: &[(usize, &[usize])] = &[ $( ($nx, &[$($nz),*]) ),* ];

        fn builder(nx: usize, nz: usize) -> Option<Build> {
            match (nx, nz) {
                $( $( ($nx, $nz) => Some(build::<$nx, $nz, { $nx + NU_MAX }, { 2 * $nx }>), )* )*
                _ => None,
            }
        }
    };
}

// The common linear models: a random walk (1 state); 1-D constant velocity (2) and acceleration
// (3); 2-D constant velocity (4); 3-D constant velocity, L1 and 2-D constant acceleration (6);
// 3-D constant acceleration (9), each with its positions and with more sensors. Every pair adds
// a whole filter family to the library build (`docs/src/systems/linear-toml.md`).
#[cfg(not(test))]
sizes! {
    1 => [1],
    2 => [1, 2],
    3 => [1, 2, 3],
    4 => [2, 4],
    6 => [2, 3, 4, 6],
    9 => [3, 6],
}

// The library's unit-test build compiles every instantiation a second time, and no unit test
// configures a linear spec (the integration tests link the normal build, which has every
// pair): one pair keeps that build as cheap as before.
#[cfg(test)]
sizes! {
    6 => [3],
}

/// Whether `nx` states with `nz` measurement components are compiled.
fn compiled(nx: usize, nz: usize) -> bool {
    builder(nx, nz).is_some()
}

/// The compiled sizes, for messages.
fn supported_list() -> String {
    SUPPORTED
        .iter()
        .map(|(nx, nz)| {
            let z: Vec<String> = nz.iter().map(|z| z.to_string()).collect();
            format!("{nx} states: {}", z.join("/"))
        })
        .collect::<Vec<_>>()
        .join("; ")
}

/// The generic linear-Gaussian system.
#[derive(Clone, Copy, Debug, Default)]
pub struct LinearSystem;

impl LinearSystem {
    /// The built-in system.
    pub fn new() -> Self {
        LinearSystem
    }
}

impl System for LinearSystem {
    fn kind(&self) -> &str {
        KIND
    }

    fn presentation_keys(&self) -> &[&str] {
        &["positions", "position_frame"]
    }

    fn catalogue(&self) -> Catalogue {
        let kinds =
            linear_kinds::<1, NU_MAX, 1, LinearModel<1, NU_MAX, 1>>(detectable::<1, NU_MAX, 1>);
        let keys = |list: &[(&str, &str)]| {
            list.iter()
                .map(|(k, v)| (k.to_string(), v.to_string()))
                .collect::<Vec<_>>()
        };
        Catalogue {
            about: "linear-Gaussian system from TOML matrices: discrete f, g, h, q, r or continuous a, b, c, gamma, q_tilde (zero-order hold + Van Loan)".into(),
            sections: vec![
                (
                    "model keys".into(),
                    keys(&[
                        ("states", "state names (required); state_units = [...] optional"),
                        ("inputs", "input names (up to 4; default none)"),
                        ("measurements", "measurement-component names (required)"),
                        ("dt_s", "sample time in s (required)"),
                        ("f g h q", "discrete x_k = F x_{k−1} + G u_k + w, z = H x + v, Q (row-major nested arrays)"),
                        ("a b c gamma q_tilde", "continuous ẋ = A x + B u + Γ ω, ω ~ N(0, Q̃), z = C x + v (gamma default I)"),
                        ("r", "measurement-noise covariance (discrete, diagonal, positive)"),
                        ("[[model.sensor_groups]]", "components = [...], period_steps = N or rate_hz; others report every step"),
                    ]),
                ),
                (
                    "sizes (states: measurement components)".into(),
                    SUPPORTED
                        .iter()
                        .map(|(nx, nz)| {
                            let z: Vec<String> = nz.iter().map(|z| z.to_string()).collect();
                            (format!("{nx}"), z.join(", "))
                        })
                        .collect(),
                ),
                (
                    "scenarios (any name)".into(),
                    keys(&[
                        ("x0", "initial state (default zeros)"),
                        ("duration_s", "run length in s (required)"),
                        ("stages", "[{ from_step = 0, u = [...] }, …] (default zero input)"),
                    ]),
                ),
                ("filters (filters[].kind)".into(), kinds.catalogue()),
                (
                    "initial estimates (initial_estimate.mode)".into(),
                    keys(&[
                        ("truth", "x̂0 = x0, P0 = diag(p0_std²)"),
                        ("sampled", "x̂0 ~ N(x0, P0), one draw per run shared by all filters"),
                        ("batch_ls", "x̂0, P0 by generalised least squares on z_1..z_K (observable models)"),
                    ]),
                ),
            ],
        }
    }

    fn configure(&self, spec: &SystemSpec<'_>, c: &mut Checker) -> Option<Arc<dyn SystemPlan>> {
        let lin = spec::model(c, spec.model)?;
        // spec::model has checked that the sizes are compiled.
        let build = builder(lin.states.len(), lin.measurements.len())?;
        build(&lin, spec, c)
    }
}

/// A runtime matrix as a fixed-size one, zero-padded (G and B get their zero input columns).
fn fixed<const R: usize, const C: usize>(m: &DMatrix<f64>) -> Matrix<R, C> {
    Matrix::<R, C>::from_fn(|i, j| {
        if i < m.nrows() && j < m.ncols() {
            m[(i, j)]
        } else {
            0.0
        }
    })
}

/// The configured system at its compiled sizes: `NA` = NX + NU_MAX and `NV` = 2·NX name the
/// augmented matrices of the discretisation.
fn build<const NX: usize, const NZ: usize, const NA: usize, const NV: usize>(
    lin: &LinearSpec,
    spec: &SystemSpec<'_>,
    c: &mut Checker,
) -> Option<Arc<dyn SystemPlan>> {
    let dt_s = lin.dt_s;
    let (f, g, q) = match &lin.dynamics {
        Dynamics::Discrete { f, g, q } => (fixed(f), fixed(g), fixed(q)),
        Dynamics::Continuous { a, b, w } => {
            let d = zoh_van_loan::<NX, NU_MAX, NA, NV>(&fixed(a), &fixed(b), &fixed(w), dt_s);
            (d.f, d.g, d.q)
        }
    };
    let h: Matrix<NZ, NX> = fixed(&lin.h);
    // The truth samples a full Q through the same Cholesky factorisation; a diagonal Q with
    // zero entries is exact as per-state standard deviations instead.
    let full_q = SmallCholesky::new(&q).is_some();
    let diagonal = (0..NX).all(|i| (0..NX).all(|j| i == j || q[(i, j)] == 0.0));
    if !full_q && !diagonal {
        c.err(
            lin.q_key(),
            "the discrete Q is singular and not diagonal: the truth draws w_k through a Cholesky factor of Q, which needs Q positive definite (a diagonal Q may have zeros)",
        );
        return None;
    }
    let model = LinearModel::<NX, NU_MAX, NZ>::new(dt_s, f, g, h, q, full_q, lin.groups.clone());
    let process_std: Vec<f64> = (0..NX).map(|i| q[(i, i)].sqrt()).collect();
    let measurement_std: Vec<f64> = lin.r_diag.iter().map(|v| v.sqrt()).collect();

    let scenarios: Vec<Scenario<NX, NU_MAX>> = spec::scenarios(c, spec.scenarios, lin, NU_MAX)
        .into_iter()
        .map(|s| Scenario {
            name: s.name,
            x0: Vector::<NX>::from_column_slice(&s.x0),
            controls: s
                .controls
                .iter()
                .map(|u| Vector::<NU_MAX>::from_column_slice(u))
                .collect(),
        })
        .collect();

    let kinds =
        linear_kinds::<NX, NU_MAX, NZ, LinearModel<NX, NU_MAX, NZ>>(detectable::<NX, NU_MAX, NZ>);
    let entries = kinds.configure_entries(
        spec.filters,
        &FilterSetup::new(&model, KIND, &process_std, &measurement_std),
        c,
    );

    let batch_ls = spec.initial.mode == InitialMode::BatchLs;
    if batch_ls {
        c.reject_present(
            "initial_estimate",
            &[("p0_std", spec.initial.p0_std.is_some())],
            "not used with mode = \"batch_ls\" (P0 is the least-squares covariance)",
        );
    }
    let p0_std = c.vector(
        "initial_estimate.p0_std",
        spec.initial.p0_std.as_ref(),
        NX,
        &[1.0; NX],
        positive,
        "a positive number",
    );
    let mut batch = None;
    if batch_ls && c.is_clean() {
        // Built now, so a model or schedule that cannot determine x0 is a spec error.
        let r = Matrix::<NZ, NZ>::from_fn(|i, j| {
            if i == j {
                measurement_std[i].powi(2)
            } else {
                0.0
            }
        });
        let mut all = Vec::new();
        for (i, sc) in scenarios.iter().enumerate() {
            match BatchInitial::new(&model, &sc.controls, model.q(), &r) {
                Ok(b) => all.push(b),
                Err(e) => c.err(
                    "initial_estimate.mode",
                    format!("batch_ls for scenarios[{i}] (`{}`): {e}", sc.name),
                ),
            }
        }
        batch = Some(all);
    }
    if !c.is_clean() {
        return None;
    }
    let layout = Layout {
        quantities: lin
            .states
            .iter()
            .zip(&lin.units)
            .zip(lin.positions.iter().zip(lin.position_fixes()))
            .map(|((n, u), (axis, fixes))| {
                let mut q = Quantity::new(n.as_str(), u.as_str());
                q.position = *axis;
                q.fixes = fixes;
                q
            })
            .collect(),
        inputs: lin.inputs.clone(),
        measurements: lin.measurements.clone(),
        world_states: Vec::new(),
        dt_s,
    };
    let noise = TruthNoise {
        process_std: Vector::<NX>::from_column_slice(&process_std),
        measurement_std: Vector::<NZ>::from_column_slice(&measurement_std),
    };
    let mut additive = AdditivePlan::new(
        model,
        layout,
        scenarios,
        noise,
        Vector::<NX>::from_column_slice(&p0_std),
        entries,
    );
    additive.batch = batch;
    Some(Arc::new(LinearPlan {
        additive,
        inputs: lin.inputs.len(),
    }))
}

/// A configured linear system: the [`AdditivePlan`] at the compiled sizes, and the number of
/// real inputs (the traces drop the padding).
#[derive(Debug)]
pub struct LinearPlan<const NX: usize, const NZ: usize> {
    /// The world, filters and scenarios (inputs padded to [`NU_MAX`]).
    pub additive: AdditivePlan<NX, NU_MAX, NZ, LinearModel<NX, NU_MAX, NZ>>,
    /// The spec's input count.
    pub inputs: usize,
}

impl<const NX: usize, const NZ: usize> SystemPlan for LinearPlan<NX, NZ> {
    fn layout(&self) -> &Layout {
        self.additive.layout()
    }
    fn scenarios(&self) -> &[ScenarioInfo] {
        self.additive.scenarios()
    }
    fn filters(&self) -> &[FilterInfo] {
        self.additive.filters()
    }
    fn trial<'a>(&'a self, settings: &'a RunSettings) -> Box<dyn Trial + 'a> {
        Box::new(LinearTrial {
            inner: self.additive.trial(settings),
            inputs: self.inputs,
        })
    }
    fn as_any(&self) -> &dyn Any {
        self
    }
    fn describe(&self, settings: &RunSettings) -> Option<crate::analysis::Description> {
        let mut d = self.additive.describe(settings)?;
        // G's padding columns are not inputs of the spec.
        for s in &mut d.scenarios {
            for row in &mut s.input_matrix {
                row.truncate(self.inputs);
            }
        }
        Some(d)
    }
    fn filter_model(&self) -> Option<crate::system::filter_model::FilterModel<'_>> {
        let a = &self.additive;
        // The padding inputs are not the spec's: callers pass only its inputs.
        Some(crate::system::filter_model::FilterModel::of_additive(
            &a.model,
            self.inputs,
            &a.truth_noise,
            &a.p0_std,
            &a.scenarios,
        ))
    }
}

/// The additive trial with the padded inputs removed from its traces.
struct LinearTrial<'a> {
    inner: Box<dyn Trial + 'a>,
    inputs: usize,
}

impl LinearTrial<'_> {
    /// Drops the padding inputs from a result's trace.
    fn trim(&self, mut r: UnitResult) -> UnitResult {
        if let Some(t) = r.trace.as_mut()
            && self.inputs < NU_MAX
        {
            t.u =
                t.u.chunks_exact(NU_MAX)
                    .flat_map(|u| u[..self.inputs].iter().copied())
                    .collect();
        }
        r
    }
}

impl Trial for LinearTrial<'_> {
    fn run(&self, unit: &Unit) -> UnitResult {
        self.trim(self.inner.run(unit))
    }
    fn run_group(&self, units: &[Unit]) -> Vec<UnitResult> {
        let results = self.inner.run_group(units);
        results.into_iter().map(|r| self.trim(r)).collect()
    }
    fn lanes(&self) -> usize {
        self.inner.lanes()
    }
    fn steps(&self, scenario: usize) -> usize {
        self.inner.steps(scenario)
    }
    fn layout(&self) -> &Layout {
        self.inner.layout()
    }
    fn world_metrics(&self) -> &[String] {
        self.inner.world_metrics()
    }
}
