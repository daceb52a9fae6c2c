//! `[tune]`: which tuning method `kfmc tune` runs and which elements of the noise covariances
//! it estimates, by state and measurement names (`q[px,px]`, `r[gps_x,gps_x]`).
//!
//! The table is optional; `kfmc tune`'s flags (`--method`, `--elements`) win over it. Every
//! element not listed keeps the spec's value. Elements are read here against the system's
//! layout, so an unknown name is a spec error with its key path (`tune.elements[2]`); what
//! only the data can decide (enough measurements for the unknowns) is checked when tuning.

use serde::Deserialize;

use crate::system::SystemPlan;
use crate::system::checker::Checker;

/// `[tune]` as written.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TuneSpec {
    /// `consistency` (the two-scalar grid search, the default), `ml` or `truth`.
    pub method: Option<String>,
    /// The elements to estimate, e.g. `["q[px,px]", "r[zx,zx]"]`.
    pub elements: Option<Vec<String>>,
}

/// How `kfmc tune` tunes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum TuneMethod {
    /// The two-scalar grid search of a Q multiplier (and an R multiplier) for consistency or
    /// RMSE: `tuning.parquet`.
    Consistency,
    /// Maximum likelihood of the innovations, element by element, with intervals from the
    /// observed information (linear systems): `tuned.parquet`.
    Ml,
    /// Identifying conditions against simulated truth (E[e_i²/P_ii] = 1 per tuned state,
    /// E[ν_j²/S_jj] = 1 per tuned measurement component), element by element, with sandwich
    /// intervals (linear systems): `tuned.parquet`.
    Truth,
}

impl TuneMethod {
    /// The name in specs, flags and the `method` column.
    pub fn name(self) -> &'static str {
        match self {
            TuneMethod::Consistency => "consistency",
            TuneMethod::Ml => "ml",
            TuneMethod::Truth => "truth",
        }
    }
}

/// Which noise covariance an element belongs to.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum NoiseMatrix {
    /// The process noise Q (indexed by states).
    Q,
    /// The measurement noise R (indexed by measurement components).
    R,
}

/// One tuned element of Q or R.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct TuneElement {
    /// The matrix.
    pub matrix: NoiseMatrix,
    /// Row index (a state for Q, a measurement component for R).
    pub row: usize,
    /// Column index.
    pub col: usize,
    /// The name in tables and messages: `Q[px,px]`, `R[zx,zx]`.
    pub name: String,
}

/// The validated `[tune]` table.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct TunePlan {
    /// `tune.method` (`None` when the table does not set it).
    pub method: Option<TuneMethod>,
    /// `tune.elements` (empty when the table does not list them).
    pub elements: Vec<TuneElement>,
}

/// The method of a name: `als` is named in the design but not built, and says so.
pub fn method_of(name: &str) -> Result<TuneMethod, String> {
    match name {
        "consistency" => Ok(TuneMethod::Consistency),
        "ml" => Ok(TuneMethod::Ml),
        "truth" => Ok(TuneMethod::Truth),
        "als" => Err(format!(
            "method `{name}` is not built yet; expected one of: consistency, ml, truth"
        )),
        other => Err(format!(
            "unknown method `{other}`; expected one of: consistency, ml, truth"
        )),
    }
}

/// Reads one element, `q[a,b]` by state names or `r[a,b]` by measurement names, against the
/// names of a system. Off-diagonal elements are refused: only diagonal elements are tuned
/// today (each log-parametrised, so it stays positive).
pub fn parse_element(
    text: &str,
    states: &[&str],
    measurements: &[&str],
) -> Result<TuneElement, String> {
    let grammar = "an element is q[state,state] or r[measurement,measurement], e.g. q[px,px]";
    let t = text.trim();
    let (head, rest) = t
        .split_once('[')
        .ok_or_else(|| format!("`{text}` is not an element: {grammar}"))?;
    let inner = rest
        .strip_suffix(']')
        .ok_or_else(|| format!("`{text}` is not an element: {grammar}"))?;
    let (matrix, names, what) = match head.trim().to_ascii_lowercase().as_str() {
        "q" => (NoiseMatrix::Q, states, "state"),
        "r" => (NoiseMatrix::R, measurements, "measurement component"),
        other => {
            return Err(format!(
                "`{text}`: the system has no matrix `{other}` to tune; {grammar}"
            ));
        }
    };
    let parts: Vec<&str> = inner.split(',').map(str::trim).collect();
    let [a, b] = parts.as_slice() else {
        return Err(format!(
            "`{text}`: expected two names between the brackets; {grammar}"
        ));
    };
    let index = |n: &str| {
        names.iter().position(|s| *s == n).ok_or_else(|| {
            format!(
                "`{text}`: unknown {what} `{n}`; expected one of: {}",
                names.join(", ")
            )
        })
    };
    let (row, col) = (index(a)?, index(b)?);
    if row != col {
        return Err(format!(
            "`{text}`: off-diagonal elements (a full block by log-Cholesky) are not built yet; tune the diagonal elements"
        ));
    }
    let letter = match matrix {
        NoiseMatrix::Q => "Q",
        NoiseMatrix::R => "R",
    };
    Ok(TuneElement {
        matrix,
        row,
        col,
        name: format!("{letter}[{},{}]", names[row], names[col]),
    })
}

/// Reads a list of elements; problems are `(index, message)`, duplicates included.
pub fn parse_elements(
    list: &[String],
    states: &[&str],
    measurements: &[&str],
) -> (Vec<TuneElement>, Vec<(usize, String)>) {
    let mut out: Vec<TuneElement> = Vec::new();
    let mut problems = Vec::new();
    for (i, text) in list.iter().enumerate() {
        match parse_element(text, states, measurements) {
            Ok(e) if out.iter().any(|o| o.name == e.name) => {
                problems.push((i, format!("`{text}`: {} is listed twice", e.name)));
            }
            Ok(e) => out.push(e),
            Err(m) => problems.push((i, m)),
        }
    }
    (out, problems)
}

/// Validates `[tune]` against the configured system (its names), reporting into `c`.
pub fn validate(
    c: &mut Checker,
    spec: Option<&TuneSpec>,
    system: Option<&dyn SystemPlan>,
) -> Option<TunePlan> {
    let spec = spec?;
    let method = spec
        .method
        .as_deref()
        .and_then(|m| method_of(m).map_err(|e| c.err("tune.method", e)).ok());
    let mut elements = Vec::new();
    if let (Some(list), Some(system)) = (&spec.elements, system) {
        let layout = system.layout();
        let (states, meas) = (layout.quantity_names(), layout.measurement_names());
        let (found, problems) = parse_elements(list, &states, &meas);
        for (i, m) in problems {
            c.err(format!("tune.elements[{i}]"), m);
        }
        if list.is_empty() {
            c.err("tune.elements", "needs at least one element, e.g. q[px,px]");
        }
        elements = found;
    }
    Some(TunePlan { method, elements })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn elements_are_read_by_name_and_refused_with_a_reason() {
        let (s, m) = (["px", "vx"], ["zx"]);
        let e = parse_element(" q[ vx , vx ] ", &s, &m).unwrap();
        assert_eq!((e.matrix, e.row, e.col), (NoiseMatrix::Q, 1, 1));
        assert_eq!(e.name, "Q[vx,vx]");
        assert_eq!(parse_element("R[zx,zx]", &s, &m).unwrap().name, "R[zx,zx]");
        for (bad, why) in [
            ("q[px,zz]", "unknown state `zz`"),
            ("r[px,px]", "unknown measurement component `px`"),
            ("p[px,px]", "no matrix `p`"),
            ("q[px,vx]", "off-diagonal"),
            ("q[px]", "two names"),
            ("qpx", "not an element"),
        ] {
            let e = parse_element(bad, &s, &m).unwrap_err();
            assert!(e.contains(why), "{bad}: {e}");
        }
        let (ok, problems) = parse_elements(&["q[px,px]".into(), "q[px,px]".into()], &s, &m);
        assert_eq!(ok.len(), 1);
        assert_eq!(problems[0].0, 1);
        assert!(problems[0].1.contains("listed twice"));
        assert!(method_of("als").unwrap_err().contains("not built yet"));
    }
}
