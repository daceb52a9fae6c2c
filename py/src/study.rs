//! The study commands: `validate`, `run`, `simulate` and `power`, with the gate keywords
//! `check` shares.

use std::path::PathBuf;
use std::time::Duration;

use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::errors::{Failure, SpecError, guarded};
use crate::progress::run_study;
use crate::spec::{load_spec, prepared};

/// More threads than logical CPUs only add contention (as the command clamps them).
pub(crate) fn clamp_threads(threads: usize) -> usize {
    let cpus = std::thread::available_parallelism().map_or(1, |n| n.get());
    threads.min(cpus)
}

pub(crate) fn report_dict<'py>(
    py: Python<'py>,
    r: &kfmc::study::StudyReport,
) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("folder", r.output.clone())?;
    d.set_item("runs", r.runs)?;
    d.set_item("wall_s", r.wall_s)?;
    d.set_item("cells_resumed", r.cells_resumed)?;
    d.set_item("tables", r.tables.clone())?;
    Ok(d)
}

/// The plan's size and resources, or SpecError.
#[pyfunction]
#[pyo3(signature = (spec, *, allow_large = false))]
pub(crate) fn validate<'py>(
    py: Python<'py>,
    spec: &Bound<'py, PyAny>,
    allow_large: bool,
) -> PyResult<Bound<'py, PyDict>> {
    guarded(|| {
        let registry = kfmc::systems::builtin();
        let (plan, _) = load_spec(spec, &registry)?;
        kfmc::study::check_limits(&plan, allow_large).map_err(|e| Failure::from(e).into_py())?;
        let size = plan.size();
        let res = kfmc::study::resources(&plan);
        let d = PyDict::new(py);
        d.set_item("experiment", &plan.name)?;
        d.set_item("cells", size.cells)?;
        d.set_item("runs_per_cell", plan.runs)?;
        d.set_item("runs", size.runs)?;
        d.set_item("filter_runs", size.filter_runs)?;
        d.set_item("filter_steps", size.filter_steps)?;
        d.set_item("memory_bytes", res.memory_bytes)?;
        d.set_item("disk_bytes", res.disk_bytes)?;
        d.set_item("scratch_bytes", res.scratch_bytes)?;
        d.set_item("master_seed", plan.master_seed)?;
        d.set_item("output", plan.output.clone())?;
        d.set_item(
            "scenarios",
            plan.scenarios
                .iter()
                .map(|s| s.name.clone())
                .collect::<Vec<_>>(),
        )?;
        d.set_item(
            "filters",
            plan.filters
                .iter()
                .map(|f| f.label.clone())
                .collect::<Vec<_>>(),
        )?;
        d.set_item("noise_scales", plan.noise_scales.clone())?;
        d.set_item("summary", kfmc::study::resources(&plan).describe())?;
        Ok(d)
    })
}

/// The lanes mode of a Python call: `lanes=` when given (`"auto"` or `"off"`), else
/// `KFMC_LANES`, else auto (`kfmc run --lanes`); a `ValueError` naming what is wrong.
pub(crate) fn lanes_mode(lanes: Option<&str>) -> PyResult<kfmc::runner::lanes::LanesMode> {
    use kfmc::runner::lanes::LanesMode;
    let flag = lanes
        .map(LanesMode::parse)
        .transpose()
        .map_err(|e| PyValueError::new_err(format!("lanes: {e}")))?;
    LanesMode::resolve(flag).map_err(PyValueError::new_err)
}

/// `kfmc run`: returns the report as a dict (folder, runs, wall_s, cells_resumed, tables).
#[pyfunction]
#[pyo3(signature = (spec, *, out=None, runs=None, seed=None, threads=None, quiet=false, resume=false, force=false, allow_large=false, checkpoint_every=10.0, lanes=None))]
#[allow(
    clippy::too_many_arguments,
    reason = "each argument is one of the Python function's keyword arguments, its public API"
)]
pub(crate) fn run<'py>(
    py: Python<'py>,
    spec: &Bound<'py, PyAny>,
    out: Option<PathBuf>,
    runs: Option<usize>,
    seed: Option<u64>,
    threads: Option<usize>,
    quiet: bool,
    resume: bool,
    force: bool,
    allow_large: bool,
    checkpoint_every: f64,
    lanes: Option<&str>,
) -> PyResult<Bound<'py, PyDict>> {
    guarded(|| {
        let every = Duration::try_from_secs_f64(checkpoint_every).map_err(|_| {
            PyValueError::new_err(format!(
                "checkpoint_every: {checkpoint_every} is not a number of seconds ≥ 0"
            ))
        })?;
        let (mut plan, path) = prepared(spec, out, runs, seed, allow_large, None)?;
        plan.lanes = lanes_mode(lanes)?;
        let exec = kfmc::study::ExecOptions {
            threads: clamp_threads(threads.unwrap_or(0)),
            force,
            shard: None,
            checkpoints: Some(kfmc::study::Checkpoints {
                every,
                // Python has no `restart=`: `force=True` is its word for "whatever is there".
                existing: if resume {
                    kfmc::study::ExistingCheckpoint::Resume
                } else if force {
                    kfmc::study::ExistingCheckpoint::Discard
                } else {
                    kfmc::study::ExistingCheckpoint::Refuse
                },
            }),
        };
        let report = run_study(py, quiet, move |obs| {
            kfmc::study::run(&plan, &exec, obs)
                .map_err(|e| Failure::from(e).context(format!("running {}", path.display())))
        })?;
        report_dict(py, &report)
    })
}

/// `kfmc simulate`: returns the report as a dict.
#[pyfunction]
#[pyo3(signature = (spec, *, out=None, runs=None, seed=None, threads=None, quiet=false, force=false, allow_large=false, lanes=None))]
#[allow(
    clippy::too_many_arguments,
    reason = "each argument is one of the Python function's keyword arguments, its public API"
)]
pub(crate) fn simulate<'py>(
    py: Python<'py>,
    spec: &Bound<'py, PyAny>,
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
        let (mut plan, path) = prepared(spec, out, runs, seed, allow_large, None)?;
        plan.lanes = lanes_mode(lanes)?;
        let exec = kfmc::study::ExecOptions {
            threads: clamp_threads(threads.unwrap_or(0)),
            force,
            shard: None,
            checkpoints: None,
        };
        let report = run_study(py, quiet, move |obs| {
            kfmc::simulate::simulate(&plan, &exec, obs)
                .map_err(|e| Failure::from(e).context(format!("simulating {}", path.display())))
        })?;
        report_dict(py, &report)
    })
}

/// `kfmc power`: returns the folder holding power.parquet and, with `target_power` and
/// `against`, the runs-needed text `kfmc power --target-power` prints.
#[pyfunction]
#[pyo3(signature = (spec, replications, *, out=None, runs=None, seed=None, threads=None, quiet=false, force=false, allow_large=false, sequential=false, looks=None, spending=None, futility=None, futility_rho=None, target_power=None, against=None, lanes=None))]
#[allow(
    clippy::too_many_arguments,
    reason = "each argument is one of the Python function's keyword arguments, its public API"
)]
pub(crate) fn power(
    py: Python<'_>,
    spec: &Bound<'_, PyAny>,
    replications: usize,
    out: Option<PathBuf>,
    runs: Option<usize>,
    seed: Option<u64>,
    threads: Option<usize>,
    quiet: bool,
    force: bool,
    allow_large: bool,
    sequential: bool,
    looks: Option<&Bound<'_, PyAny>>,
    spending: Option<&str>,
    futility: Option<f64>,
    futility_rho: Option<f64>,
    target_power: Option<f64>,
    against: Option<&str>,
    lanes: Option<&str>,
) -> PyResult<(PathBuf, Option<String>)> {
    guarded(|| {
        let target = match (target_power, against) {
            (None, None) => None,
            (Some(power), Some(text)) => {
                let against = text
                    .parse()
                    .map_err(|e| SpecError::new_err(format!("against: {e}")))?;
                Some(
                    kfmc::power::PowerTarget::new(power, against)
                        .map_err(|e| SpecError::new_err(format!("target_power: {e}")))?,
                )
            }
            _ => {
                return Err(SpecError::new_err(
                    "target_power and against go together: the power wanted against a variant, e.g. target_power=0.9, against=\"q_scale=0.9\"",
                ));
            }
        };
        // As `kfmc power --sequential …`: the keywords alone (the spec's `[check]` gate is
        // kfmc check's).
        let settings = gate_overrides(sequential, looks, spending, futility, futility_rho)?
            .apply(None)
            .map_err(gate_override_error)?;
        let (mut plan, path) = prepared(spec, None, runs, seed, allow_large, Some(0))?;
        plan.lanes = lanes_mode(lanes)?;
        let gate = settings
            .map(|s| s.gate(plan.runs, plan.alpha))
            .transpose()
            .map_err(|e| SpecError::new_err(format!("sequential gate: {e}")))?;
        let request = kfmc::power::PowerRequest {
            replications,
            out,
            allow_large,
            gate,
            target,
        };
        let exec = kfmc::study::ExecOptions {
            threads: clamp_threads(threads.unwrap_or(0)),
            force,
            shard: None,
            checkpoints: None,
        };
        let outcome = run_study(py, quiet, move |obs| {
            kfmc::power::run(&plan, &request, &exec, obs)
                .map_err(|e| Failure::from(e).context(format!("power of {}", path.display())))
        })?;
        let answer = outcome.runs_needed.map(|r| r.to_string());
        Ok((outcome.report.output, answer))
    })
}

/// The gate keywords of `check` and `power` (`sequential=…, looks=…, spending=…,
/// futility=…, futility_rho=…`) as the library's [`kfmc::sequential::GateOverrides`], the
/// flags of `kfmc check` and `kfmc power` in Python's spelling: `looks` is a count of even
/// looks (≥ 1) or the looks' run counts, `spending` `"obrien-fleming"` (or the spec's
/// `"obrien_fleming"`) or `"pocock"`.
pub(crate) fn gate_overrides(
    sequential: bool,
    looks: Option<&Bound<'_, PyAny>>,
    spending: Option<&str>,
    futility: Option<f64>,
    futility_rho: Option<f64>,
) -> PyResult<kfmc::sequential::GateOverrides> {
    use kfmc::sequential::{GateOverrides, Looks, Spending};
    let looks = match looks {
        None => None,
        Some(v) => Some(match v.extract::<usize>() {
            Ok(0) => return Err(SpecError::new_err("looks: `0` is not an integer ≥ 1")),
            Ok(count) => Looks::Count(count),
            Err(_) => Looks::RunCounts(v.extract::<Vec<usize>>().map_err(|_| {
                SpecError::new_err("looks: a count of looks or a list of run counts")
            })?),
        }),
    };
    let spending = match spending {
        None => None,
        Some("obrien-fleming" | "obrien_fleming") => Some(Spending::OBrienFleming),
        Some("pocock") => Some(Spending::Pocock),
        Some(other) => {
            return Err(SpecError::new_err(format!(
                "spending: `{other}` is not one of obrien-fleming (obrien_fleming), pocock"
            )));
        }
    };
    Ok(GateOverrides {
        sequential,
        looks,
        spending,
        futility_beta: futility,
        futility_rho,
    })
}

/// A gate keyword given without the gate (or `futility_rho` without `futility`), named as
/// Python spells it: `kfmc.SpecError`, as the command's usage error exits 2.
pub(crate) fn gate_override_error(e: kfmc::sequential::GateOverrideError) -> PyErr {
    use kfmc::sequential::{GateOverrideError, GateSetting};
    match e {
        GateOverrideError::NotSequential(setting) => SpecError::new_err(format!(
            "{} is a setting of the sequential gate: pass sequential=True",
            match setting {
                GateSetting::Looks => "looks",
                GateSetting::Spending => "spending",
                GateSetting::Futility => "futility",
                GateSetting::FutilityRho => "futility_rho",
            }
        )),
        GateOverrideError::RhoWithoutFutility => SpecError::new_err(
            "futility_rho is the exponent of the futility bounds' β-spending: pass futility=β",
        ),
    }
}
