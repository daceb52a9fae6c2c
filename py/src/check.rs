//! `check`: the spec's assertions judged, on kfmc's filters and on estimates given.

use std::path::PathBuf;

use kfmc::runner::RunObserver;
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};

use crate::errors::{Failure, guarded};
use crate::estimates::attach;
use crate::progress::{Observer, run_study};
use crate::spec::prepared;
use crate::study::{clamp_threads, gate_override_error, gate_overrides};

/// `kfmc check`: returns (exit code, report text, JUnit XML, cases, folder).
#[pyfunction]
#[pyo3(signature = (spec, paths, streams, *, out=None, runs=None, seed=None, threads=None, quiet=false, replications=None, allow_unstamped=false, force=false, allow_large=false, sequential=false, looks=None, spending=None, futility=None, futility_rho=None, truth=None, lanes=None))]
#[allow(
    clippy::too_many_arguments,
    reason = "each argument is one of the Python function's keyword arguments, its public API"
)]
pub(crate) fn check<'py>(
    py: Python<'py>,
    spec: &Bound<'py, PyAny>,
    paths: Vec<PathBuf>,
    streams: Bound<'py, PyAny>,
    out: Option<PathBuf>,
    runs: Option<usize>,
    seed: Option<u64>,
    threads: Option<usize>,
    quiet: bool,
    replications: Option<usize>,
    allow_unstamped: bool,
    force: bool,
    allow_large: bool,
    sequential: bool,
    looks: Option<&Bound<'py, PyAny>>,
    spending: Option<&str>,
    futility: Option<f64>,
    futility_rho: Option<f64>,
    truth: Option<Bound<'py, PyAny>>,
    lanes: Option<&str>,
) -> PyResult<Bound<'py, PyDict>> {
    guarded(|| {
        let overrides = gate_overrides(sequential, looks, spending, futility, futility_rho)?;
        let (mut plan, path) = prepared(spec, out, runs, seed, allow_large, None)?;
        plan.lanes = crate::study::lanes_mode(lanes)?;
        // As `kfmc check --sequential …`: the keywords over the spec's `[check]` keys; whether
        // they make a gate for the study's runs is judged with the spec (a SpecError naming
        // the `check.*` key).
        plan.check_sequential = overrides
            .apply(plan.check_sequential.as_ref())
            .map_err(gate_override_error)?;
        // A user's own runs (`kfmc check --truth`): the truth first, so that estimates of a run
        // it leaves out are refused as they are read.
        if let Some(truth) = &truth {
            crate::estimates::attach_truth(&mut plan, truth)?;
        }
        // An iterable without a length (a generator) may yield estimates: it is read.
        if !(paths.is_empty() && streams.len().is_ok_and(|n| n == 0)) {
            let unstamped = if allow_unstamped {
                kfmc::check::Unstamped::Warn
            } else {
                kfmc::check::Unstamped::Refuse
            };
            attach(&mut plan, &paths, &streams, unstamped)?;
        }
        let folder = plan.output.clone();
        let exec = kfmc::study::ExecOptions {
            threads: clamp_threads(threads.unwrap_or(0)),
            force,
            shard: None,
            checkpoints: None,
        };
        // The observer of each of check's studies is the one the caller waits on.
        let outcome = run_study(py, quiet, move |obs| {
            let shared = SharedObserver(obs);
            kfmc::check::run(plan, &path, replications, allow_large, &exec, || shared).map_err(
                |e| match e {
                    kfmc::check::RunError::Invalid(e) => Failure::from(e),
                    kfmc::check::RunError::Stage { context, source } => {
                        Failure::from(*source).context(context)
                    }
                },
            )
        })?;
        let d = PyDict::new(py);
        d.set_item("exit_code", outcome.exit_code())?;
        d.set_item("report", outcome.render())?;
        d.set_item("junit", outcome.junit())?;
        d.set_item("folder", folder)?;
        let cases = PyList::empty(py);
        for c in &outcome.cases {
            let case = PyDict::new(py);
            case.set_item("kind", &c.kind)?;
            case.set_item("name", &c.name)?;
            case.set_item("passed", c.pass)?;
            case.set_item("incomplete", c.incomplete)?;
            case.set_item("detail", &c.detail)?;
            cases.append(case)?;
        }
        d.set_item("cases", cases)?;
        Ok(d)
    })
}

/// The study thread's observer, lent to each of check's studies.
#[derive(Clone, Copy)]
struct SharedObserver<'a>(&'a Observer);

impl RunObserver for SharedObserver<'_> {
    fn on_start(&self, total_units: u64) {
        self.0.on_start(total_units);
    }
    fn on_units_done(&self, n: u64) {
        self.0.on_units_done(n);
    }
    fn cancelled(&self) -> bool {
        self.0.cancelled()
    }
}
