//! The `[model]` table and the scenarios of a `kind = "linear"` spec, read at runtime sizes
//! and validated with key-path errors (`model.q[2][1]: …`) before anything is monomorphised.

use nalgebra::DMatrix;
use serde::Deserialize;

use crate::model::Availability;
use crate::system::checker::{Checker, positive};

use super::model::SensorGroup;
use crate::system::{PositionAxis, PositionFix};

/// The most states, inputs and measurement components a name list may have (the sizes the
/// step loop is compiled for are a subset, see [`super::SUPPORTED`]).
pub const MAX_STATES: usize = 9;

/// `[model]` of a linear spec.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct ModelKeys {
    states: Option<Vec<String>>,
    state_units: Option<Vec<String>>,
    inputs: Option<Vec<String>>,
    measurements: Option<Vec<String>>,
    dt_s: Option<f64>,
    f: Option<Vec<Vec<f64>>>,
    g: Option<Vec<Vec<f64>>>,
    h: Option<Vec<Vec<f64>>>,
    q: Option<Vec<Vec<f64>>>,
    a: Option<Vec<Vec<f64>>>,
    b: Option<Vec<Vec<f64>>>,
    c: Option<Vec<Vec<f64>>>,
    gamma: Option<Vec<Vec<f64>>>,
    q_tilde: Option<Vec<Vec<f64>>>,
    r: Option<Vec<Vec<f64>>>,
    sensor_groups: Option<Vec<GroupKeys>>,
    positions: Option<Vec<String>>,
    position_frame: Option<String>,
}

/// `[[model.sensor_groups]]`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct GroupKeys {
    components: Vec<String>,
    period_steps: Option<u64>,
    rate_hz: Option<f64>,
}

/// `[[scenarios]]` of a linear spec.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct ScenarioKeys {
    name: String,
    x0: Option<Vec<f64>>,
    duration_s: Option<f64>,
    stages: Option<Vec<StageKeys>>,
}

/// One input stage: u from `from_step` until the next stage.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct StageKeys {
    from_step: u64,
    u: Vec<f64>,
}

/// How the spec gives the dynamics.
#[derive(Clone, Debug, PartialEq)]
pub enum Dynamics {
    /// x_k = F x_{k−1} + G u_k + w_k, w_k ~ N(0, Q).
    Discrete {
        /// F (NX × NX).
        f: DMatrix<f64>,
        /// G (NX × NU).
        g: DMatrix<f64>,
        /// Q (NX × NX, symmetric positive semidefinite).
        q: DMatrix<f64>,
    },
    /// ẋ = A x + B u + Γ ω, ω ~ N(0, Q̃), discretised by zero-order hold and Van Loan.
    Continuous {
        /// A (NX × NX).
        a: DMatrix<f64>,
        /// B (NX × NU).
        b: DMatrix<f64>,
        /// W = Γ Q̃ Γᵀ (NX × NX).
        w: DMatrix<f64>,
    },
}

/// A validated linear model at runtime sizes.
#[derive(Clone, Debug, PartialEq)]
pub struct LinearSpec {
    /// State names.
    pub states: Vec<String>,
    /// State units (empty strings by default).
    pub units: Vec<String>,
    /// Input names.
    pub inputs: Vec<String>,
    /// Measurement-component names.
    pub measurements: Vec<String>,
    /// Δt in seconds.
    pub dt_s: f64,
    /// The dynamics as given.
    pub dynamics: Dynamics,
    /// H (NZ × NX).
    pub h: DMatrix<f64>,
    /// The diagonal of R.
    pub r_diag: Vec<f64>,
    /// The multi-rate groups.
    pub groups: Vec<SensorGroup>,
    /// The position role of each state (`positions`, `position_frame`).
    pub positions: Vec<Option<PositionAxis>>,
}

impl LinearSpec {
    /// Which key holds Q's source, for messages about the discretised Q.
    pub fn q_key(&self) -> &'static str {
        match self.dynamics {
            Dynamics::Discrete { .. } => "model.q",
            Dynamics::Continuous { .. } => "model.q_tilde",
        }
    }
}

/// A validated scenario at runtime sizes: x0 and u_0..u_K (NU per step).
#[derive(Clone, Debug, PartialEq)]
pub struct ScenarioSpec {
    /// Name.
    pub name: String,
    /// x0.
    pub x0: Vec<f64>,
    /// u_0..u_K.
    pub controls: Vec<Vec<f64>>,
}

/// A list of names: non-empty identifiers (they become column names), unique.
fn names(
    c: &mut Checker,
    key: &str,
    v: Option<&Vec<String>>,
    required: bool,
    max: usize,
) -> Vec<String> {
    let Some(v) = v else {
        if required {
            c.err(key, "required: a list of names");
        }
        return vec![];
    };
    if required && v.is_empty() {
        c.err(key, "needs at least one name");
    }
    if v.len() > max {
        c.err(key, format!("at most {max} names, got {}", v.len()));
    }
    for (i, n) in v.iter().enumerate() {
        if n.is_empty() || !n.chars().all(|ch| ch.is_ascii_alphanumeric() || ch == '_') {
            c.err(
                format!("{key}[{i}]"),
                format!("`{n}` is not a name (letters, digits and _; it becomes a column name)"),
            );
        } else if v[..i].contains(n) {
            c.err(format!("{key}[{i}]"), format!("duplicate name `{n}`"));
        }
    }
    v.clone()
}

/// A row-major matrix of `rows` × `cols` finite numbers; `None` after reporting a problem.
fn matrix(
    c: &mut Checker,
    key: &str,
    v: &[Vec<f64>],
    rows: (usize, &str),
    cols: (usize, &str),
) -> Option<DMatrix<f64>> {
    if v.len() != rows.0 {
        c.err(
            key,
            format!(
                "expected {} rows (one per {}), got {}",
                rows.0,
                rows.1,
                v.len()
            ),
        );
        return None;
    }
    let before = c.error_count();
    for (i, row) in v.iter().enumerate() {
        if row.len() != cols.0 {
            c.err(
                format!("{key}[{i}]"),
                format!(
                    "expected {} columns (one per {}), got {}",
                    cols.0,
                    cols.1,
                    row.len()
                ),
            );
            continue;
        }
        if let Some(j) = row.iter().position(|x| !x.is_finite()) {
            c.err(
                format!("{key}[{i}][{j}]"),
                format!("{} is not a finite number", row[j]),
            );
        }
    }
    (c.error_count() == before).then(|| DMatrix::from_fn(rows.0, cols.0, |i, j| v[i][j]))
}

/// Checks a covariance-like matrix: symmetric (to round-off) and positive semidefinite.
/// Returns it exactly symmetric.
fn covariance(c: &mut Checker, key: &str, m: DMatrix<f64>) -> Option<DMatrix<f64>> {
    let n = m.nrows();
    let scale = m.amax();
    for i in 0..n {
        for j in 0..i {
            if (m[(i, j)] - m[(j, i)]).abs() > 1e-12 * scale {
                let short = key.trim_start_matches("model.");
                c.err(
                    format!("{key}[{i}][{j}]"),
                    format!(
                        "{} differs from {short}[{j}][{i}] = {}: the matrix must be symmetric",
                        m[(i, j)],
                        m[(j, i)]
                    ),
                );
                return None;
            }
        }
    }
    let m = (&m + m.transpose()) * 0.5;
    let eig = m.clone().symmetric_eigenvalues();
    let min = eig.iter().cloned().fold(f64::INFINITY, f64::min);
    if min < -1e-12 * scale.max(f64::MIN_POSITIVE) {
        c.err(
            key,
            format!("not positive semidefinite (smallest eigenvalue {min:.3e})"),
        );
        return None;
    }
    Some(m)
}

/// R: diagonal (the truth draws independent noise per component and filters assume
/// diag(r_std²)) with a positive diagonal. Returns the diagonal.
fn measurement_noise(c: &mut Checker, m: &DMatrix<f64>) -> Option<Vec<f64>> {
    let before = c.error_count();
    for i in 0..m.nrows() {
        for j in 0..m.ncols() {
            if i != j && m[(i, j)] != 0.0 {
                c.err(
                    format!("model.r[{i}][{j}]"),
                    "R must be diagonal: the truth draws independent noise per component and filters assume diag(r_std²)",
                );
                return None;
            }
        }
        if m[(i, i)] <= 0.0 {
            c.err(
                format!("model.r[{i}][{i}]"),
                format!(
                    "{} is not positive (R must be positive definite)",
                    m[(i, i)]
                ),
            );
        }
    }
    (c.error_count() == before).then(|| (0..m.nrows()).map(|i| m[(i, i)]).collect())
}

const DISCRETE: &str = "the discrete form (f, g, h, q)";
const CONTINUOUS: &str = "the continuous form (a, b, c, gamma, q_tilde)";

/// A matrix as a spec gives it: rows of numbers.
type Rows = Option<Vec<Vec<f64>>>;

/// The names and the sample time of `[model]`.
struct Header {
    states: Vec<String>,
    units: Vec<String>,
    inputs: Vec<String>,
    measurements: Vec<String>,
    dt_s: f64,
}

/// Reads the names and the sample time; `None` unless they are valid and of a compiled size.
fn header(c: &mut Checker, m: &ModelKeys) -> Option<Header> {
    let states = names(c, "model.states", m.states.as_ref(), true, MAX_STATES);
    let inputs = names(c, "model.inputs", m.inputs.as_ref(), false, super::NU_MAX);
    let measurements = names(
        c,
        "model.measurements",
        m.measurements.as_ref(),
        true,
        super::MAX_MEASUREMENTS,
    );
    let (nx, nz) = (states.len(), measurements.len());
    let units = match &m.state_units {
        None => vec![String::new(); nx],
        Some(u) if u.len() == nx => u.clone(),
        Some(u) => {
            c.err(
                "model.state_units",
                format!("expected {nx} units (one per state), got {}", u.len()),
            );
            vec![String::new(); nx]
        }
    };
    let dt_s = match m.dt_s {
        Some(dt) if positive(dt) => dt,
        Some(dt) => {
            c.err("model.dt_s", format!("{dt} is not a positive number"));
            return None;
        }
        None => {
            c.err("model.dt_s", "required: the sample time in seconds");
            return None;
        }
    };
    if nx == 0 || nz == 0 || !c.is_clean() {
        return None;
    }
    if !super::compiled(nx, nz) {
        let key = if super::SUPPORTED.iter().any(|(x, _)| *x == nx) {
            "model.measurements"
        } else {
            "model.states"
        };
        c.err(
            key,
            format!(
                "{nx} states with {nz} measurement components is not a compiled size; compiled: {}",
                super::supported_list()
            ),
        );
        return None;
    }
    Some(Header {
        states,
        units,
        inputs,
        measurements,
        dt_s,
    })
}

/// The form the dynamics are given in, with the keys (and values) of F, G and H: a, b and c
/// in the continuous form.
struct Form<'m> {
    continuous: bool,
    f: (&'static str, &'m Rows),
    g: (&'static str, &'m Rows),
    h: (&'static str, &'m Rows),
}

/// Which form `[model]` gives, with every key that form requires present; `None` when the
/// forms are mixed, absent, or incomplete.
fn form<'m>(c: &mut Checker, m: &'m ModelKeys, nu: usize) -> Option<Form<'m>> {
    let discrete = [("f", &m.f), ("g", &m.g), ("h", &m.h), ("q", &m.q)];
    let continuous = [
        ("a", &m.a),
        ("b", &m.b),
        ("c", &m.c),
        ("gamma", &m.gamma),
        ("q_tilde", &m.q_tilde),
    ];
    let any = |keys: &[(&str, &Rows)]| keys.iter().any(|(_, v)| v.is_some());
    let is_continuous = match (any(&discrete), any(&continuous)) {
        (true, true) => {
            for (k, v) in continuous {
                if v.is_some() {
                    c.err(
                        format!("model.{k}"),
                        format!("give either {DISCRETE} or {CONTINUOUS}, not both"),
                    );
                }
            }
            return None;
        }
        (false, false) => {
            c.err(
                "model",
                format!(
                    "needs the dynamics: {DISCRETE}, or {CONTINUOUS}, discretised by zero-order hold and Van Loan (g or b only with inputs, gamma defaults to I)"
                ),
            );
            return None;
        }
        (_, c) => c,
    };
    let require = |c: &mut Checker, key: &str, v: &Rows, form: &str| {
        if v.is_none() {
            c.err(format!("model.{key}"), format!("required by {form}"));
        }
    };
    let form = if is_continuous { CONTINUOUS } else { DISCRETE };
    let f = Form {
        continuous: is_continuous,
        f: if is_continuous {
            ("a", &m.a)
        } else {
            ("f", &m.f)
        },
        g: if is_continuous {
            ("b", &m.b)
        } else {
            ("g", &m.g)
        },
        h: if is_continuous {
            ("c", &m.c)
        } else {
            ("h", &m.h)
        },
    };
    require(c, f.f.0, f.f.1, form);
    require(c, f.h.0, f.h.1, form);
    require(
        c,
        if is_continuous { "q_tilde" } else { "q" },
        if is_continuous { &m.q_tilde } else { &m.q },
        form,
    );
    require(c, "r", &m.r, "both forms (R is always discrete)");
    match (nu, f.g.1) {
        (0, Some(_)) => c.err(
            format!("model.{}", f.g.0),
            "the model has no inputs (model.inputs); omit it",
        ),
        (_, None) if nu > 0 => c.err(
            format!("model.{}", f.g.0),
            format!("required: the model has {nu} inputs"),
        ),
        _ => {}
    }
    c.is_clean().then_some(f)
}

/// The continuous dynamics from A (`a`), B (`b`), Γ and Q̃; `None` when any is invalid.
fn continuous(
    c: &mut Checker,
    m: &ModelKeys,
    a: Option<DMatrix<f64>>,
    b: Option<DMatrix<f64>>,
    nx: usize,
) -> Option<Dynamics> {
    let state = (nx, "state");
    let (gamma, nw) = match &m.gamma {
        Some(gm) => {
            let nw = gm.first().map_or(0, Vec::len);
            if nw == 0 {
                c.err(
                    "model.gamma",
                    "expected a matrix with one column per noise input",
                );
                return None;
            }
            (matrix(c, "model.gamma", gm, state, (nw, "noise input")), nw)
        }
        None => (Some(DMatrix::identity(nx, nx)), nx),
    };
    let q_tilde = matrix(
        c,
        "model.q_tilde",
        m.q_tilde.as_ref()?,
        (nw, "noise input"),
        (nw, "noise input"),
    )
    .and_then(|q| covariance(c, "model.q_tilde", q));
    let (a, b, gamma, q_tilde) = (a?, b?, gamma?, q_tilde?);
    Some(Dynamics::Continuous {
        w: &gamma * q_tilde * gamma.transpose(),
        a,
        b,
    })
}

/// Validates `[model]`; `None` after reporting every problem found.
pub(super) fn model(c: &mut Checker, table: &toml::Table) -> Option<LinearSpec> {
    let m: ModelKeys = c.parse("model", table)?;
    let head = header(c, &m)?;
    let (nx, nu, nz) = (
        head.states.len(),
        head.inputs.len(),
        head.measurements.len(),
    );
    let form = form(c, &m, nu)?;

    let state = (nx, "state");
    let input = (nu, "input");
    let meas = (nz, "measurement component");
    let (fk, fv) = form.f;
    let (gk, gv) = form.g;
    let (hk, hv) = form.h;
    let fm = matrix(c, &format!("model.{fk}"), fv.as_ref()?, state, state);
    let gm = match gv {
        Some(g) => matrix(c, &format!("model.{gk}"), g, state, input),
        None => Some(DMatrix::zeros(nx, 0)),
    };
    let hm = matrix(c, &format!("model.{hk}"), hv.as_ref()?, meas, state);
    let rm = matrix(c, "model.r", m.r.as_ref()?, meas, meas).and_then(|r| measurement_noise(c, &r));
    let dynamics = if form.continuous {
        continuous(c, &m, fm, gm, nx)?
    } else {
        let q = matrix(c, "model.q", m.q.as_ref()?, state, state)
            .and_then(|q| covariance(c, "model.q", q));
        Dynamics::Discrete {
            f: fm?,
            g: gm?,
            q: q?,
        }
    };
    let groups = sensor_groups(c, m.sensor_groups.as_deref(), &head.measurements, head.dt_s);
    let positions = positions(c, &m, &head.states)?;
    Some(LinearSpec {
        states: head.states,
        units: head.units,
        inputs: head.inputs,
        measurements: head.measurements,
        dt_s: head.dt_s,
        dynamics,
        h: hm?,
        r_diag: rm?,
        groups: groups?,
        positions,
    })
}

/// `positions` (state names in axis order: x, y[, z] or north, east[, down]) in the frame
/// `position_frame` (`xyz`, the default, or `ned`): each state's position role; `None` after
/// reporting a problem.
fn positions(
    c: &mut Checker,
    m: &ModelKeys,
    states: &[String],
) -> Option<Vec<Option<PositionAxis>>> {
    let mut out = vec![None; states.len()];
    let Some(list) = &m.positions else {
        if m.position_frame.is_some() {
            c.err(
                "model.position_frame",
                "needs model.positions (the position states in axis order)",
            );
            return None;
        }
        return Some(out);
    };
    let frame = c.choice(
        "model.position_frame",
        m.position_frame.as_deref(),
        "xyz",
        &["xyz", "ned"],
    );
    let (axes, order) = match frame {
        "ned" => (
            [PositionAxis::North, PositionAxis::East, PositionAxis::Down],
            "north, east[, down]",
        ),
        _ => (
            [PositionAxis::X, PositionAxis::Y, PositionAxis::Z],
            "x, y[, z]",
        ),
    };
    let before = c.error_count();
    if !(2..=3).contains(&list.len()) {
        c.err(
            "model.positions",
            format!(
                "expected 2 or 3 state names in axis order ({order}), got {}",
                list.len()
            ),
        );
        return None;
    }
    for (i, name) in list.iter().enumerate() {
        match states.iter().position(|s| s == name) {
            None => c.err(
                format!("model.positions[{i}]"),
                format!(
                    "unknown state `{name}`; expected one of: {}",
                    states.join(", ")
                ),
            ),
            Some(_) if list[..i].contains(name) => c.err(
                format!("model.positions[{i}]"),
                format!("`{name}` is listed twice"),
            ),
            Some(j) => out[j] = Some(axes[i]),
        }
    }
    (c.error_count() == before).then_some(out)
}

impl LinearSpec {
    /// The measurement components that measure a position state directly (their row of H is
    /// that state's unit row), per state. The components of one sensor group (or those
    /// reporting every step) form one sensor, named after them (`px/py`).
    pub fn position_fixes(&self) -> Vec<Vec<PositionFix>> {
        let nx = self.states.len();
        // (state, component) of every direct measurement of a position state.
        let direct: Vec<(usize, usize)> = (0..self.h.nrows())
            .filter_map(|i| {
                let row = self.h.row(i);
                let j = (0..nx).find(|&j| row[j] == 1.0)?;
                let unit = (0..nx).all(|k| k == j || row[k] == 0.0);
                (unit && self.positions[j].is_some()).then_some((j, i))
            })
            .collect();
        let group_of = |i: usize| {
            self.groups
                .iter()
                .position(|g| g.components.0 & (1 << i) != 0)
        };
        let sensor = |i: usize| {
            direct
                .iter()
                .filter(|(_, k)| group_of(*k) == group_of(i))
                .map(|(_, k)| self.measurements[*k].as_str())
                .collect::<Vec<_>>()
                .join("/")
        };
        let mut out = vec![Vec::new(); nx];
        for &(j, i) in &direct {
            out[j].push(PositionFix {
                sensor: sensor(i),
                component: self.measurements[i].clone(),
            });
        }
        out
    }
}

/// `[[model.sensor_groups]]`: each a set of components reporting every `period_steps` (or at
/// `rate_hz`, which must divide the sample rate); a component is in at most one group.
fn sensor_groups(
    c: &mut Checker,
    groups: Option<&[GroupKeys]>,
    measurements: &[String],
    dt_s: f64,
) -> Option<Vec<SensorGroup>> {
    let before = c.error_count();
    let mut out = Vec::new();
    let mut owner: Vec<Option<usize>> = vec![None; measurements.len()];
    for (gi, g) in groups.unwrap_or_default().iter().enumerate() {
        let key = format!("model.sensor_groups[{gi}]");
        if g.components.is_empty() {
            c.err(format!("{key}.components"), "needs at least one component");
        }
        let mut mask = 0u32;
        for (j, name) in g.components.iter().enumerate() {
            match measurements.iter().position(|m| m == name) {
                None => c.err(
                    format!("{key}.components[{j}]"),
                    format!(
                        "unknown measurement `{name}`; expected one of: {}",
                        measurements.join(", ")
                    ),
                ),
                Some(i) => match owner[i] {
                    Some(other) if other == gi => c.err(
                        format!("{key}.components[{j}]"),
                        format!("`{name}` is listed twice"),
                    ),
                    Some(other) => c.err(
                        format!("{key}.components[{j}]"),
                        format!("`{name}` is already in sensor_groups[{other}]"),
                    ),
                    None => {
                        owner[i] = Some(gi);
                        mask |= 1 << i;
                    }
                },
            }
        }
        let period = match (g.period_steps, g.rate_hz) {
            (Some(_), Some(_)) => {
                c.err(
                    format!("{key}.rate_hz"),
                    "give period_steps or rate_hz, not both",
                );
                continue;
            }
            (None, None) => {
                c.err(
                    key.clone(),
                    "needs period_steps (report every N steps) or rate_hz",
                );
                continue;
            }
            (Some(0), None) => {
                c.err(format!("{key}.period_steps"), "must be at least 1");
                continue;
            }
            (Some(p), None) => p as usize,
            (None, Some(hz)) => {
                let steps = 1.0 / (hz * dt_s);
                let n = steps.round();
                if !positive(hz) || n < 1.0 || (steps - n).abs() > 1e-9 * steps {
                    c.err(
                        format!("{key}.rate_hz"),
                        format!(
                            "{hz} Hz is not the sample rate {} Hz divided by a whole number (it would report every {steps:.4} steps); use period_steps",
                            1.0 / dt_s
                        ),
                    );
                    continue;
                }
                n as usize
            }
        };
        out.push(SensorGroup {
            components: Availability(mask),
            period,
        });
    }
    (c.error_count() == before).then_some(out)
}

/// Validates the scenarios: x0 (default zeros), `duration_s` (required) and input stages
/// (default zero input). Each control is padded with zeros to `nu_padded` inputs.
pub(super) fn scenarios(
    c: &mut Checker,
    tables: &[toml::Table],
    spec: &LinearSpec,
    nu_padded: usize,
) -> Vec<ScenarioSpec> {
    let (nx, nu, dt_s) = (spec.states.len(), spec.inputs.len(), spec.dt_s);
    let mut out = Vec::new();
    for (i, t) in tables.iter().enumerate() {
        let key = format!("scenarios[{i}]");
        let Some(s) = c.parse::<ScenarioKeys>(&key, t) else {
            continue;
        };
        let x0 = match &s.x0 {
            None => vec![0.0; nx],
            Some(v) if v.len() == nx && v.iter().all(|v| v.is_finite()) => v.clone(),
            Some(v) => {
                c.err(
                    format!("{key}.x0"),
                    format!("expected {nx} finite numbers (one per state), got {v:?}"),
                );
                continue;
            }
        };
        let Some(duration_s) = s.duration_s else {
            c.err(
                format!("{key}.duration_s"),
                "required: the run length in seconds",
            );
            continue;
        };
        // K = round(duration / Δt), bounded by the per-run and per-spec limits before
        // anything is expanded (the shared check every system uses).
        let Some(steps) = c.scenario_steps(&key, duration_s, dt_s) else {
            continue;
        };
        let mut stages: Vec<(usize, Vec<f64>)> = Vec::new();
        if let Some(list) = &s.stages {
            if nu == 0 {
                c.err(
                    format!("{key}.stages"),
                    "the model has no inputs (model.inputs)",
                );
                continue;
            }
            if list.is_empty() {
                c.err(format!("{key}.stages"), "at least one stage is required");
            }
            for (j, st) in list.iter().enumerate() {
                let skey = format!("{key}.stages[{j}]");
                if st.u.len() != nu || !st.u.iter().all(|v| v.is_finite()) {
                    c.err(
                        format!("{skey}.u"),
                        format!(
                            "expected {nu} finite numbers [{}], got {:?}",
                            spec.inputs.join(", "),
                            st.u
                        ),
                    );
                }
                let from = st.from_step as usize;
                if (j == 0 && from != 0) || stages.last().is_some_and(|p| from <= p.0) {
                    c.err(
                        format!("{skey}.from_step"),
                        "stages must start at step 0 and increase strictly",
                    );
                }
                stages.push((from, st.u.clone()));
            }
        }
        let mut stage = 0;
        let controls = (0..=steps)
            .map(|k| {
                let mut u = vec![0.0; nu_padded];
                if !stages.is_empty() {
                    while stage + 1 < stages.len() && stages[stage + 1].0 <= k {
                        stage += 1;
                    }
                    for (ui, v) in u.iter_mut().zip(&stages[stage].1) {
                        *ui = *v;
                    }
                }
                u
            })
            .collect();
        out.push(ScenarioSpec {
            name: s.name,
            x0,
            controls,
        });
    }
    out
}
