//! `kfmc.ulog_nis`: the NIS verdicts of PX4 flight logs (`kfmc ulog nis`), one call into
//! `kfmc::ulog::nis`; the pure-Python layer (`python/kfmc/_ulog.py`) reads the tables it wrote
//! as DataFrames.

use std::path::PathBuf;

use pyo3::prelude::*;
use pyo3::types::PyDict;

use super::{Error, StudyError, guarded};

/// Judges a log or a folder of logs; returns a dict: `out`, `cases` (name, kind, outcome,
/// detail), `failed`, `incomplete`, `logs`, `seconds`, `report` (the command's text).
#[pyfunction]
#[pyo3(signature = (path, *, out, instance="primary", sensors=Vec::new(), alpha=0.05, holdoff=None, include_ground=false, baseline=None, tolerance=None, force=false))]
#[allow(
    clippy::too_many_arguments,
    reason = "each argument is one of the Python function's keyword arguments, its public API"
)]
fn ulog_nis<'py>(
    py: Python<'py>,
    path: PathBuf,
    out: PathBuf,
    instance: &str,
    sensors: Vec<String>,
    alpha: f64,
    holdoff: Option<f64>,
    include_ground: bool,
    baseline: Option<PathBuf>,
    tolerance: Option<f64>,
    force: bool,
) -> PyResult<Bound<'py, PyDict>> {
    guarded(|| {
        let mut opts = kfmc::ulog::NisOptions::new(out.clone());
        opts.instance = instance
            .parse()
            .map_err(|e: String| Error::new_err(format!("invalid instance: {e}")))?;
        opts.sensors = sensors;
        opts.alpha = alpha;
        opts.holdoff_s = holdoff.unwrap_or(kfmc::ulog::DEFAULT_HOLDOFF_S);
        opts.include_ground = include_ground;
        opts.baseline = baseline;
        opts.tolerance = tolerance.unwrap_or(kfmc::ulog::DEFAULT_TOLERANCE);
        opts.force = force;
        let outcome = py
            .detach(|| kfmc::ulog::nis(&path, &opts, |_, _| {}))
            .map_err(|e| {
                let message = format!("judging {}: {}", path.display(), chain(&e));
                match e {
                    kfmc::ulog::NisError::Output(
                        kfmc::error::OutputError::Locked { .. }
                        | kfmc::error::OutputError::OtherKind { .. }
                        | kfmc::error::OutputError::Foreign { .. },
                    ) => StudyError::new_err(message),
                    _ => Error::new_err(message),
                }
            })?;
        let (failed, incomplete) = outcome.tally();
        let d = PyDict::new(py);
        d.set_item("out", out)?;
        let cases: Vec<(String, String, &str, String)> = outcome
            .cases
            .iter()
            .map(|c| {
                let o = if c.incomplete {
                    "incomplete"
                } else if c.pass {
                    "pass"
                } else {
                    "fail"
                };
                (c.name.clone(), c.kind.clone(), o, c.detail.clone())
            })
            .collect();
        d.set_item("cases", cases)?;
        d.set_item("failed", failed)?;
        d.set_item("incomplete", incomplete)?;
        d.set_item("logs", outcome.logs)?;
        d.set_item("seconds", outcome.seconds)?;
        d.set_item("report", outcome.render())?;
        Ok(d)
    })
}

/// The error and its causes, as the command prints them.
fn chain(e: &dyn std::error::Error) -> String {
    let mut s = e.to_string();
    let mut next = e.source();
    while let Some(c) = next {
        s.push_str(": ");
        s.push_str(&c.to_string());
        next = c.source();
    }
    s
}

/// Adds `ulog_nis` to the module.
pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_function(wrap_pyfunction!(ulog_nis, m)?)
}
