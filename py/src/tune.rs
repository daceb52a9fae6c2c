//! `tune`: a filter's noise covariances tuned, by the methods `kfmc tune` has.

use std::path::PathBuf;

use kfmc::experiment::tune_spec::{TuneElement, TuneMethod, method_of};
use kfmc::tune::conditions::TruthObjective;
use kfmc::tune::estimate::Estimate;
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};

use crate::errors::{Failure, SpecError, guarded};
use crate::progress::run_study;
use crate::spec::prepared;
use crate::study::clamp_threads;

/// `kfmc tune`: tunes the spec's filter and returns what the command prints, as a dict
/// (`method`, `folder`, and the method's own keys); the tables are in `folder`.
#[pyfunction]
#[pyo3(signature = (spec, *, method=None, elements=None, measurements=None, objective="consistency", tune_r=false, filter=None, out=None, runs=None, seed=None, threads=None, quiet=false, force=false, allow_large=false, lanes=None))]
#[allow(
    clippy::too_many_arguments,
    reason = "each argument is one of the Python function's keyword arguments, its public API"
)]
pub(crate) fn tune<'py>(
    py: Python<'py>,
    spec: &Bound<'py, PyAny>,
    method: Option<&str>,
    elements: Option<Vec<String>>,
    measurements: Option<PathBuf>,
    objective: &str,
    tune_r: bool,
    filter: Option<String>,
    out: Option<PathBuf>,
    runs: Option<usize>,
    seed: Option<u64>,
    threads: Option<usize>,
    quiet: bool,
    force: bool,
    allow_large: bool,
    lanes: Option<&str>,
) -> PyResult<Bound<'py, PyDict>> {
    guarded(|| {
        let method = method
            .map(|m| method_of(m).map_err(|e| SpecError::new_err(format!("method={m:?}: {e}"))))
            .transpose()?;
        if !["consistency", "rmse", "mse"].contains(&objective) {
            return Err(SpecError::new_err(format!(
                "objective={objective:?}: not an objective (\"consistency\" or \"rmse\" for the consistency method, \"consistency\" or \"mse\" for truth)"
            )));
        }
        let (mut plan, path) = prepared(spec, out, runs, seed, allow_large, None)?;
        plan.lanes = crate::study::lanes_mode(lanes)?;
        // As the command: the keyword, else the spec's `tune.method`, else `consistency`.
        let method = method
            .or_else(|| plan.tune.as_ref().and_then(|t| t.method))
            .unwrap_or(TuneMethod::Consistency);
        let threads = clamp_threads(threads.unwrap_or(0));
        let d = PyDict::new(py);
        d.set_item("method", method.name())?;
        d.set_item("folder", plan.output.clone())?;
        match method {
            TuneMethod::Ml => {
                if objective != "consistency" {
                    return Err(SpecError::new_err(
                        "objective= belongs to the consistency and truth methods; the ml method maximises the likelihood",
                    ));
                }
                if tune_r || filter.is_some() {
                    return Err(SpecError::new_err(
                        "tune_r= and filter= belong to the consistency method; the ml method estimates the elements= of Q and R of the spec's filter model",
                    ));
                }
                let opts = kfmc::tune::ml::MlOptions {
                    elements,
                    measurements,
                    search: Default::default(),
                    force,
                    threads,
                };
                let report = run_study(py, quiet, move |obs| {
                    kfmc::tune::ml::tune_ml(&plan, &opts, obs, &|_| {})
                        .map_err(|e| Failure::from(e).context(format!("tuning {}", path.display())))
                })?;
                estimate_items(
                    &d,
                    &report.estimate,
                    &report.elements,
                    report.runs,
                    &report.data,
                )?;
                d.set_item("measurements", report.measurements)?;
            }
            TuneMethod::Truth => {
                if tune_r || filter.is_some() || measurements.is_some() {
                    return Err(SpecError::new_err(
                        "tune_r=, filter= and measurements= do not belong to the truth method, which estimates the elements= of Q and R of the spec's filter model on its simulated runs",
                    ));
                }
                let objective = match objective {
                    "consistency" => TruthObjective::Consistency,
                    "mse" => TruthObjective::Mse,
                    other => {
                        return Err(SpecError::new_err(format!(
                            "objective={other:?} belongs to the consistency method; the truth method takes \"consistency\" or \"mse\""
                        )));
                    }
                };
                let opts = kfmc::tune::truth::TruthOptions {
                    elements,
                    objective,
                    search: Default::default(),
                    force,
                    threads,
                };
                let report = run_study(py, quiet, move |obs| {
                    kfmc::tune::truth::tune_truth(&plan, &opts, obs, &|_| {})
                        .map_err(|e| Failure::from(e).context(format!("tuning {}", path.display())))
                })?;
                estimate_items(
                    &d,
                    &report.estimate,
                    &report.elements,
                    report.runs,
                    &report.data,
                )?;
                let residuals = PyDict::new(py);
                for (g, e) in report.residuals.iter().zip(&report.elements) {
                    residuals.set_item(&e.name, g)?;
                }
                d.set_item("conditions", residuals)?;
                d.set_item("notes", report.notes.clone())?;
            }
            TuneMethod::Consistency => {
                if elements.is_some() || measurements.is_some() {
                    return Err(SpecError::new_err(
                        "elements= and measurements= belong to the ml method (method=\"ml\"); the consistency method tunes a Q scale and an R scale",
                    ));
                }
                let objective = match objective {
                    "consistency" => kfmc::tune::Objective::Consistency,
                    "rmse" => kfmc::tune::Objective::Rmse,
                    other => {
                        return Err(SpecError::new_err(format!(
                            "objective={other:?} belongs to the truth method (method=\"truth\"); the consistency method takes \"consistency\" or \"rmse\""
                        )));
                    }
                };
                let opts = kfmc::tune::TuneOptions {
                    objective,
                    tune_r,
                    filter,
                    threads,
                    force,
                };
                let report = run_study(py, quiet, move |obs| {
                    kfmc::tune::tune(&plan, &opts, obs)
                        .map_err(|e| Failure::from(e).context(format!("tuning {}", path.display())))
                })?;
                let (q, r, o) = report.best;
                let best = report.averages(q, r, None);
                d.set_item("filter", &report.filter)?;
                d.set_item("q_scale", q)?;
                d.set_item("r_scale", r)?;
                d.set_item("objective", o)?;
                d.set_item("anees", best.anees)?;
                d.set_item("anis", best.anis)?;
            }
        }
        Ok(d)
    })
}

/// What the `ml` and `truth` methods both report: the objective at the estimate, whether the
/// search converged, the runs and where they came from, and the directions the data do not
/// identify (one dict per direction, element name → its component in ln units).
fn estimate_items(
    d: &Bound<'_, PyDict>,
    est: &Estimate,
    elements: &[TuneElement],
    runs: usize,
    data: &str,
) -> PyResult<()> {
    d.set_item("objective", est.objective)?;
    d.set_item("converged", est.converged)?;
    d.set_item("runs", runs)?;
    d.set_item("data", data)?;
    let flat = PyList::empty(d.py());
    for direction in &est.flat {
        let entry = PyDict::new(d.py());
        for (c, e) in direction.components.iter().zip(elements) {
            entry.set_item(&e.name, c)?;
        }
        flat.append(entry)?;
    }
    d.set_item("not_identified", flat)
}
