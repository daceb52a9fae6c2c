//! `kfmc._kfmc`: the compiled half of the Python package. Every function here is one call
//! into the kfmc library (the same functions the command line calls, never its printed
//! text); the typed, documented API users import is the pure-Python layer in
//! `python/kfmc/__init__.py`.
//!
//! Three rules hold at this boundary:
//! * no panic crosses it: every entry point runs under `catch_unwind`, and a study's thread
//!   is joined, its panic turned into `kfmc.Error`;
//! * the GIL is released while Rust works, and a study runs on its own thread while the
//!   caller waits in short released-GIL slices, checking Python's signals between them: a
//!   Ctrl-C cancels the study through its [`CancelToken`] (the executor's checkpoint path,
//!   as SIGINT does for the command) and is re-raised as `KeyboardInterrupt` unless the
//!   study had already committed; SIGTERM stops it the same way and then ends the process.
//!   No process-wide signal handler of kfmc's is installed: SIGTERM's, while a study runs,
//!   is Python's own mechanism, put back afterwards;
//! * library errors become `kfmc.Error` subclasses by their kind, with the whole cause chain
//!   as the message (as the command prints it).

mod ulog;
use std::panic::AssertUnwindSafe;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use kfmc::error::{KfmcError, OutputError};
use kfmc::experiment::{self, Overrides, Plan};
use kfmc::runner::{CancelToken, RunObserver};
use kfmc::system::Registry;
use polars::prelude::*;
use pyo3::exceptions::{PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyBool, PyCapsule, PyDict, PyFloat, PyInt, PyList, PyString, PyTuple};

pyo3::create_exception!(_kfmc, Error, PyValueError, "Any kfmc error (a ValueError).");
pyo3::create_exception!(
    _kfmc,
    SpecError,
    Error,
    "An invalid spec: the message names the file, the key path and what is wrong."
);
pyo3::create_exception!(
    _kfmc,
    EstimatesError,
    Error,
    "Estimates kfmc cannot judge: the message names the table, the column and the first offending key."
);
pyo3::create_exception!(
    _kfmc,
    StudyError,
    Error,
    "A result folder that is locked by another kfmc, holds another kind of result, or is not a kfmc study."
);
pyo3::create_exception!(
    _kfmc,
    IncompleteError,
    Error,
    "kfmc check: no assertion failed, but a case could not be judged on the runs the spec declares."
);
pyo3::create_exception!(
    _kfmc,
    CheckFailedError,
    Error,
    "kfmc check: at least one assertion failed."
);

/// Which Python exception a failure becomes when its library error does not say more.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Kind {
    /// Decided by the library error's variant.
    Auto,
    /// Reading the caller's estimates: every problem is the estimates'.
    Estimates,
    /// A result folder the caller named.
    Study,
}

/// A failure on the Rust side: the error with its context chain, and how to classify it.
struct Failure {
    kind: Kind,
    error: anyhow::Error,
}

impl Failure {
    fn new(kind: Kind, error: impl Into<anyhow::Error>) -> Self {
        Failure {
            kind,
            error: error.into(),
        }
    }
    fn auto(error: impl Into<anyhow::Error>) -> Self {
        Self::new(Kind::Auto, error)
    }
    fn context(self, context: String) -> Self {
        Failure {
            kind: self.kind,
            error: self.error.context(context),
        }
    }
    fn into_py(self) -> PyErr {
        let message = format!("{:#}", self.error);
        let library = self
            .error
            .chain()
            .find_map(|e| e.downcast_ref::<KfmcError>());
        match (self.kind, library) {
            (_, Some(KfmcError::Spec(_))) => SpecError::new_err(message),
            (Kind::Estimates, _) => EstimatesError::new_err(message),
            (Kind::Study, _) => StudyError::new_err(message),
            (
                Kind::Auto,
                Some(KfmcError::Output(
                    OutputError::Locked { .. }
                    | OutputError::OtherKind { .. }
                    | OutputError::Foreign { .. }
                    | OutputError::NotAStudy { .. }
                    | OutputError::Mismatch { .. }
                    | OutputError::NotPlain { .. }
                    | OutputError::NotOurs { .. }
                    | OutputError::ForeignManifest { .. }
                    | OutputError::DamagedManifest { .. }
                    | OutputError::InputInOutput { .. },
                )),
            ) => StudyError::new_err(message),
            _ => Error::new_err(message),
        }
    }
}

impl From<KfmcError> for Failure {
    fn from(e: KfmcError) -> Self {
        Failure::auto(e)
    }
}

impl From<kfmc::error::SpecErrors> for Failure {
    fn from(e: kfmc::error::SpecErrors) -> Self {
        Failure::auto(KfmcError::from(e))
    }
}

/// Runs `f`, turning a panic into `kfmc.Error` instead of unwinding into Python.
fn guarded<T>(f: impl FnOnce() -> PyResult<T>) -> PyResult<T> {
    match std::panic::catch_unwind(AssertUnwindSafe(f)) {
        Ok(r) => r,
        Err(panic) => Err(Error::new_err(format!(
            "internal error in kfmc (please report it): {}",
            panic_message(&*panic)
        ))),
    }
}

fn panic_message(panic: &(dyn std::any::Any + Send)) -> String {
    panic
        .downcast_ref::<&str>()
        .map(|s| s.to_string())
        .or_else(|| panic.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "a panic".into())
}

/// Counts a study's units for the progress line and carries its cancellation.
#[derive(Default)]
struct Observer {
    token: CancelToken,
    total: AtomicU64,
    done: AtomicU64,
}

impl RunObserver for Observer {
    fn on_start(&self, total_units: u64) {
        // A command may run the executor several times (power's replications): the line
        // counts all of them.
        self.total.fetch_add(total_units, Ordering::Relaxed);
    }
    fn on_units_done(&self, n: u64) {
        self.done.fetch_add(n, Ordering::Relaxed);
    }
    fn cancelled(&self) -> bool {
        self.token.is_cancelled()
    }
}

/// A progress line written through Python's `sys.stderr` (so a terminal and a Jupyter cell
/// both show it): `\r` redraws it in place.
struct Progress {
    started: Instant,
    last: Option<Instant>,
    shown: bool,
}

impl Progress {
    fn show(&mut self, py: Python<'_>, obs: &Observer, last: bool) {
        let now = Instant::now();
        if !last
            && self
                .last
                .is_some_and(|t| now - t < Duration::from_millis(250))
        {
            return;
        }
        self.last = Some(now);
        let (done, total) = (
            obs.done.load(Ordering::Relaxed),
            obs.total.load(Ordering::Relaxed),
        );
        let elapsed = (now - self.started).as_secs_f64();
        // A study done within half a second prints nothing: a loop of short calls stays quiet.
        if total == 0 || (!self.shown && elapsed < 0.5) {
            return;
        }
        let text = if last {
            if !self.shown {
                return;
            }
            format!("\r{done}/{total} runs in {elapsed:.1} s\n")
        } else {
            format!(
                "\r{done}/{total} runs  {:.0} runs/s  {elapsed:.0} s",
                done as f64 / elapsed.max(1e-9)
            )
        };
        self.shown = true;
        // Progress is best effort: a closed or replaced stderr does not stop the study.
        if let Ok(stderr) = py.import("sys").and_then(|s| s.getattr("stderr")) {
            let _ = stderr.call_method1("write", (text,));
            let _ = stderr.call_method0("flush");
        }
    }
}

/// Runs `job` on its own thread while the caller waits in released-GIL slices; between
/// slices Python's signal handlers run (`py.check_signals`), and an exception there (Ctrl-C's
/// `KeyboardInterrupt`) cancels the study, which stops at its next window (keeping its
/// checkpoint). SIGTERM does the same ([`SigtermStop`]) and then ends the process as SIGTERM
/// would have. What is raised depends on what the study did, not on when the signal came:
/// a study that committed its tables before it saw the request returns its result (the
/// interrupt is taken and dropped), one that was stopped raises the interrupt.
fn run_study<T: Send + 'static>(
    py: Python<'_>,
    quiet: bool,
    job: impl FnOnce(&Observer) -> Result<T, Failure> + Send + 'static,
) -> PyResult<T> {
    let observer = Arc::new(Observer::default());
    let theirs = observer.clone();
    let handle = std::thread::Builder::new()
        .name("kfmc-study".into())
        .spawn(move || job(&theirs))
        .map_err(|e| Error::new_err(format!("cannot start the study's thread: {e}")))?;
    // Best effort: without it SIGTERM keeps Python's default (the process ends at once).
    let sigterm = SigtermStop::install(py).ok().flatten();
    let mut progress = (!quiet).then(|| Progress {
        started: Instant::now(),
        last: None,
        shown: false,
    });
    let mut interrupt: Option<PyErr> = None;
    loop {
        let finished = py.detach(|| {
            let until = Instant::now() + Duration::from_millis(100);
            while !handle.is_finished() && Instant::now() < until {
                std::thread::sleep(Duration::from_millis(5));
            }
            handle.is_finished()
        });
        if finished {
            break;
        }
        if interrupt.is_none()
            && let Err(e) = py.check_signals()
        {
            observer.token.cancel();
            interrupt = Some(e);
        }
        if let Some(p) = progress.as_mut() {
            p.show(py, &observer, false);
        }
    }
    let joined = py.detach(|| handle.join());
    // A signal that came while the study was finishing is taken here, where what the study
    // did is known, rather than raised by Python as soon as this returns.
    if interrupt.is_none()
        && let Err(e) = py.check_signals()
    {
        interrupt = Some(e);
    }
    let terminated = sigterm.map(|s| s.restore(py)).transpose()?.unwrap_or(false);
    if let Some(p) = progress.as_mut() {
        p.show(py, &observer, true);
    }
    let result = match joined {
        Ok(r) => r,
        Err(panic) => {
            return Err(Error::new_err(format!(
                "internal error in kfmc (please report it): {}",
                panic_message(&*panic)
            )));
        }
    };
    if terminated {
        // Stopped cleanly or committed: now end as SIGTERM asked, with its default action.
        py.import("signal")?
            .call_method1("raise_signal", (sigterm_number(py)?,))?;
        // Still here (the signal blocked): say so as an exit would.
        return Err(pyo3::exceptions::PySystemExit::new_err(128 + 15));
    }
    match (result, interrupt) {
        // Committed: a KeyboardInterrupt that came too late to stop it is dropped; any other
        // exception a signal handler raised (a `SystemExit`, say) is the caller's.
        (Ok(r), Some(e)) if e.is_instance_of::<pyo3::exceptions::PyKeyboardInterrupt>(py) => Ok(r),
        (Ok(r), None) => Ok(r),
        (_, Some(e)) => Err(e),
        (Err(f), None) => Err(f.into_py()),
    }
}

/// SIGTERM's number, from Python's `signal` module.
fn sigterm_number(py: Python<'_>) -> PyResult<Bound<'_, PyAny>> {
    py.import("signal")?.getattr("SIGTERM")
}

/// While a study runs, SIGTERM stops it as Ctrl-C does (its handler raises
/// `KeyboardInterrupt` where `run_study` checks signals, and records that it came), so that
/// a terminated Python process leaves a final checkpoint and no partial files instead of
/// dying mid-write. Installed only over SIGTERM's default action and only on the main
/// thread (where Python runs handlers); a handler of the caller's own is left alone.
struct SigtermStop {
    came: Arc<std::sync::atomic::AtomicBool>,
}

impl SigtermStop {
    fn install(py: Python<'_>) -> PyResult<Option<SigtermStop>> {
        let threading = py.import("threading")?;
        let main = threading
            .call_method0("current_thread")?
            .is(&threading.call_method0("main_thread")?);
        let signal = py.import("signal")?;
        let sigterm = signal.getattr("SIGTERM")?;
        if !main
            || !signal
                .call_method1("getsignal", (&sigterm,))?
                .eq(signal.getattr("SIG_DFL")?)?
        {
            return Ok(None);
        }
        let came = Arc::new(std::sync::atomic::AtomicBool::new(false));
        let flag = came.clone();
        let handler = pyo3::types::PyCFunction::new_closure(
            py,
            Some(c"kfmc_sigterm"),
            None,
            move |_, _| -> PyResult<()> {
                flag.store(true, Ordering::SeqCst);
                Err(pyo3::exceptions::PyKeyboardInterrupt::new_err(
                    "SIGTERM: the study was stopped",
                ))
            },
        )?;
        signal.call_method1("signal", (&sigterm, handler))?;
        Ok(Some(SigtermStop { came }))
    }

    /// Puts SIGTERM's default action back; returns whether SIGTERM came meanwhile.
    fn restore(self, py: Python<'_>) -> PyResult<bool> {
        let signal = py.import("signal")?;
        signal.call_method1(
            "signal",
            (signal.getattr("SIGTERM")?, signal.getattr("SIG_DFL")?),
        )?;
        Ok(self.came.load(Ordering::SeqCst))
    }
}

/// A Python value as TOML: dicts are tables, lists and tuples arrays, at most
/// [`MAX_SPEC_DEPTH`](kfmc::system::limits::MAX_SPEC_DEPTH) deep (`depth` is `v`'s).
fn to_toml(v: &Bound<'_, PyAny>, key: &str, depth: usize) -> PyResult<toml::Value> {
    use kfmc::system::limits::MAX_SPEC_DEPTH;
    let spec_err = |what: &str| {
        SpecError::new_err(format!(
            "<dict>: {}: {what}",
            if key.is_empty() { "(top level)" } else { key }
        ))
    };
    // A dict or list that contains itself would recurse until the stack overflows.
    if depth > MAX_SPEC_DEPTH {
        return Err(spec_err(&format!(
            "nested more than {MAX_SPEC_DEPTH} tables or arrays deep (a dict or list that contains itself?)"
        )));
    }
    if v.is_instance_of::<PyBool>() {
        return Ok(toml::Value::Boolean(v.extract()?));
    }
    if v.is_instance_of::<PyInt>() {
        return v
            .extract::<i64>()
            .map(toml::Value::Integer)
            .map_err(|_| spec_err("an integer outside TOML's 64-bit range"));
    }
    if v.is_instance_of::<PyFloat>() {
        return Ok(toml::Value::Float(v.extract()?));
    }
    if v.is_instance_of::<PyString>() {
        return Ok(toml::Value::String(v.extract()?));
    }
    if let Ok(d) = v.cast::<PyDict>() {
        let mut table = toml::Table::new();
        for (k, item) in d.iter() {
            let k: String = k
                .extract()
                .map_err(|_| spec_err("a key that is not a string"))?;
            let path = if key.is_empty() {
                k.clone()
            } else {
                format!("{key}.{k}")
            };
            table.insert(k, to_toml(&item, &path, depth + 1)?);
        }
        return Ok(toml::Value::Table(table));
    }
    if v.is_instance_of::<PyList>() || v.is_instance_of::<PyTuple>() {
        let mut items = Vec::new();
        for (i, item) in v.try_iter()?.enumerate() {
            items.push(to_toml(&item?, &format!("{key}[{i}]"), depth + 1)?);
        }
        return Ok(toml::Value::Array(items));
    }
    if v.is_none() {
        return Err(spec_err(
            "None has no TOML form: leave the key out to take its default",
        ));
    }
    Err(spec_err(&format!(
        "a {} has no TOML form (use bool, int, float, str, list or dict)",
        v.get_type().name()?
    )))
}

/// A spec given as a path, a dict or TOML text (a `str` with a newline), loaded and
/// validated.
fn load_spec(spec: &Bound<'_, PyAny>, registry: &Registry) -> PyResult<(Plan, PathBuf)> {
    let loaded = if let Ok(d) = spec.cast::<PyDict>() {
        let toml::Value::Table(table) = to_toml(d.as_any(), "", 0)? else {
            unreachable!("a dict is a table");
        };
        let text = toml::to_string(&table)
            .map_err(|e| SpecError::new_err(format!("<dict>: cannot write it as TOML: {e}")))?;
        let path = PathBuf::from("<dict>");
        (experiment::parse_with(&text, &path, registry), path)
    } else if let Ok(text) = spec.extract::<String>()
        && text.contains('\n')
    {
        let path = PathBuf::from("<string>");
        (experiment::parse_with(&text, &path, registry), path)
    } else {
        let path: PathBuf = spec.extract().map_err(|_| {
            PyTypeError::new_err(format!(
                "a spec is a path, a dict or TOML text, not a {}",
                spec.get_type()
                    .name()
                    .map(|n| n.to_string())
                    .unwrap_or_default()
            ))
        })?;
        (experiment::load_with(&path, registry), path)
    };
    match loaded {
        (Ok(plan), path) => Ok((plan, path)),
        (Err(e), _) => Err(Failure::from(e).into_py()),
    }
}

/// The overrides every study command takes, applied and checked against the limits.
fn prepared(
    spec: &Bound<'_, PyAny>,
    out: Option<PathBuf>,
    runs: Option<usize>,
    seed: Option<u64>,
    allow_large: bool,
    trace_runs: Option<usize>,
) -> PyResult<(Plan, PathBuf)> {
    let registry = kfmc::systems::builtin();
    let (mut plan, path) = load_spec(spec, &registry)?;
    plan.apply(&Overrides {
        runs,
        master_seed: seed,
        output: out,
        trace_runs,
    })
    .map_err(|e| Failure::from(e).into_py())?;
    kfmc::study::check_limits(&plan, allow_large).map_err(|e| Failure::from(e).into_py())?;
    Ok((plan, path))
}

/// More threads than logical CPUs only add contention (as the command clamps them).
fn clamp_threads(threads: usize) -> usize {
    let cpus = std::thread::available_parallelism().map_or(1, |n| n.get());
    threads.min(cpus)
}

fn report_dict<'py>(py: Python<'py>, r: &kfmc::study::StudyReport) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("folder", r.output.clone())?;
    d.set_item("runs", r.runs)?;
    d.set_item("wall_s", r.wall_s)?;
    d.set_item("cells_resumed", r.cells_resumed)?;
    d.set_item("tables", r.tables.clone())?;
    Ok(d)
}

/// The console script `kfmc`: the command line with argv (program name first); returns the
/// binary's exit code. This is the command, so it handles SIGINT as the binary does.
#[pyfunction]
fn cli_main(py: Python<'_>, argv: Vec<std::ffi::OsString>) -> PyResult<u8> {
    guarded(|| Ok(py.detach(|| kfmc::cli::main_from_args(argv, &kfmc::systems::builtin()))))
}

/// The plan's size and resources, or SpecError.
#[pyfunction]
#[pyo3(signature = (spec, *, allow_large = false))]
fn validate<'py>(
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

/// `kfmc run`: returns the report as a dict (folder, runs, wall_s, cells_resumed, tables).
#[pyfunction]
#[pyo3(signature = (spec, *, out=None, runs=None, seed=None, threads=None, quiet=false, resume=false, force=false, allow_large=false, checkpoint_every=10.0))]
#[allow(
    clippy::too_many_arguments,
    reason = "each argument is one of the Python function's keyword arguments, its public API"
)]
fn run<'py>(
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
) -> PyResult<Bound<'py, PyDict>> {
    guarded(|| {
        let every = Duration::try_from_secs_f64(checkpoint_every).map_err(|_| {
            PyValueError::new_err(format!(
                "checkpoint_every: {checkpoint_every} is not a number of seconds ≥ 0"
            ))
        })?;
        let (plan, path) = prepared(spec, out, runs, seed, allow_large, None)?;
        let exec = kfmc::study::ExecOptions {
            threads: clamp_threads(threads.unwrap_or(0)),
            force,
            shard: None,
            checkpoints: Some(kfmc::study::Checkpoints {
                every,
                existing: if resume {
                    kfmc::study::ExistingCheckpoint::Resume
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
#[pyo3(signature = (spec, *, out=None, runs=None, seed=None, threads=None, quiet=false, force=false, allow_large=false))]
#[allow(
    clippy::too_many_arguments,
    reason = "each argument is one of the Python function's keyword arguments, its public API"
)]
fn simulate<'py>(
    py: Python<'py>,
    spec: &Bound<'py, PyAny>,
    out: Option<PathBuf>,
    runs: Option<usize>,
    seed: Option<u64>,
    threads: Option<usize>,
    quiet: bool,
    force: bool,
    allow_large: bool,
) -> PyResult<Bound<'py, PyDict>> {
    guarded(|| {
        let (plan, path) = prepared(spec, out, runs, seed, allow_large, None)?;
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

/// One object with `__arrow_c_stream__` (a polars or pandas DataFrame, a pyarrow Table, a
/// RecordBatchReader, a DuckDB relation), or a list of them that are the consecutive parts of
/// one table (a polars DataFrame's chunks, which the Python layer hands over one by one
/// because polars' own export first copies a DataFrame of several chunks into one), as a
/// table whose batches the estimates reader takes one at a time through the Arrow C stream
/// interface, checking them as it checks a file's row groups: no copy of the values, no
/// file, and each batch let go before the next is asked for.
///
/// The table's stamp is the metadata of its stream's schema (a pyarrow Table read from a
/// stamped file keeps it there), or, for a `(table, metadata)` pair, the dict the Python
/// layer hands over with a `kfmc.Estimates` made on the simulation: the reader refuses a
/// table stamped with another world, and lists one without a stamp as a file without one.
fn import_table(obj: &Bound<'_, PyAny>, name: String) -> PyResult<kfmc::score::TableStream> {
    let (table, given) = match obj.cast::<PyTuple>() {
        Ok(pair) if pair.len() == 2 => {
            let meta: std::collections::HashMap<String, String> = pair.get_item(1)?.extract()?;
            (pair.get_item(0)?, Some(meta))
        }
        _ => (obj.clone(), None),
    };
    let readers = if let Ok(parts) = table.cast::<PyList>() {
        parts
            .iter()
            .map(|part| open_stream(&part, &name))
            .collect::<PyResult<Vec<_>>>()?
    } else {
        vec![open_stream(&table, &name)?]
    };
    let mut metadata: Vec<(String, String)> = match given {
        Some(meta) => meta.into_iter().collect(),
        None => readers
            .first()
            .and_then(|r| r.field().metadata.as_deref())
            .map(|m| {
                m.iter()
                    .map(|(k, v)| (k.to_string(), v.to_string()))
                    .collect()
            })
            .unwrap_or_default(),
    };
    metadata.sort();
    Ok(kfmc::score::TableStream {
        batches: Box::new(Batches {
            name: PathBuf::from(&name),
            readers: readers.into_iter(),
            current: None,
        }),
        name,
        metadata,
    })
}

type StreamReader =
    polars_arrow::ffi::ArrowArrayStreamReader<Box<polars_arrow::ffi::ArrowArrayStream>>;

/// Takes the Arrow C stream of one object with `__arrow_c_stream__`.
fn open_stream(obj: &Bound<'_, PyAny>, name: &str) -> PyResult<StreamReader> {
    let bad = |what: String| EstimatesError::new_err(format!("{name}: {what}"));
    let capsule = obj
        .call_method0("__arrow_c_stream__")?
        .cast_into::<PyCapsule>()
        .map_err(|_| bad("__arrow_c_stream__ did not return a capsule".into()))?;
    let ptr = capsule
        .pointer_checked(Some(c"arrow_array_stream"))
        .map_err(|_| {
            bad("__arrow_c_stream__ did not return an `arrow_array_stream` capsule".into())
        })?;
    // SAFETY: the capsule holds an ArrowArrayStream (its name says so, as the Arrow
    // PyCapsule interface specifies); moving it out and leaving a released (empty) one
    // behind is how a consumer takes ownership of the stream under that interface.
    let stream = unsafe {
        std::ptr::replace(
            ptr.as_ptr().cast::<polars_arrow::ffi::ArrowArrayStream>(),
            polars_arrow::ffi::ArrowArrayStream::empty(),
        )
    };
    // SAFETY: a stream from the Arrow PyCapsule interface fulfils the C stream interface.
    unsafe { polars_arrow::ffi::ArrowArrayStreamReader::try_new(Box::new(stream)) }
        .map_err(|e| bad(format!("not an Arrow stream: {e}")))
}

/// The batches of a table's streams, in order, each made a DataFrame when asked for.
struct Batches {
    name: PathBuf,
    readers: std::vec::IntoIter<StreamReader>,
    current: Option<StreamReader>,
}

impl Iterator for Batches {
    type Item = Result<DataFrame, kfmc::error::OutputError>;

    fn next(&mut self) -> Option<Self::Item> {
        let bad = |what: String| kfmc::error::OutputError::Format {
            path: self.name.clone(),
            message: what,
        };
        loop {
            let reader = match self.current.as_mut() {
                Some(r) => r,
                None => self.current.insert(self.readers.next()?),
            };
            // SAFETY: as in `open_stream`, the producer fulfils the C data interface.
            let Some(chunk) = (unsafe { reader.next() }) else {
                self.current = None;
                continue;
            };
            let chunk = match chunk {
                Ok(c) => c,
                Err(e) => return Some(Err(bad(format!("cannot read a batch: {e}")))),
            };
            let Some(batch) = chunk
                .as_any()
                .downcast_ref::<polars_arrow::array::StructArray>()
            else {
                return Some(Err(bad(format!(
                    "a stream of {:?}, not of table rows (a struct per row)",
                    chunk.dtype()
                ))));
            };
            let mut columns = Vec::with_capacity(batch.fields().len());
            for (field, values) in batch.fields().iter().zip(batch.values()) {
                // Before polars sees it: a decimal or map column would stop it outright.
                if let Err(e) =
                    kfmc::score::check_arrow_column(&self.name, &field.name, &field.dtype)
                {
                    return Some(Err(e));
                }
                match Series::from_arrow(field.name.clone(), values.clone()) {
                    Ok(s) => columns.push(s.into_column()),
                    Err(e) => return Some(Err(bad(format!("column `{}`: {e}", field.name)))),
                }
            }
            return Some(
                DataFrame::new(batch.len(), columns)
                    .map_err(|e| bad(format!("cannot form a table: {e}"))),
            );
        }
    }
}

/// Attaches estimates to `plan`, as EstimatesError on trouble: the files `paths`, then what
/// `streams` yields (any iterable: objects with `__arrow_c_stream__`, or a file's path as a
/// `str`). The iterable is taken one item at a time and each table is read and dropped
/// before the next is asked for, so a generator yielding each run's estimates is never held
/// whole. An exception the iterable raises is raised as it is.
fn attach(
    plan: &mut Plan,
    paths: &[PathBuf],
    streams: &Bound<'_, PyAny>,
    unstamped: kfmc::check::Unstamped,
) -> PyResult<()> {
    use kfmc::score::EstimatesSource;
    let mut raised: Option<PyErr> = None;
    let mut items = streams.try_iter()?.enumerate();
    let mut next_item = |raised: &mut Option<PyErr>| -> Option<EstimatesSource> {
        let (i, item) = items.next()?;
        let read = item.and_then(|obj| {
            if let Ok(path) = obj.extract::<String>() {
                Ok(EstimatesSource::File(PathBuf::from(path)))
            } else {
                import_table(&obj, format!("<estimates {i}>")).map(EstimatesSource::Stream)
            }
        });
        match read {
            Ok(source) => Some(source),
            Err(e) => {
                *raised = Some(e);
                None
            }
        }
    };
    let from_streams = std::iter::from_fn(|| next_item(&mut raised).map(Ok));
    let sources = paths
        .iter()
        .cloned()
        .map(|p| Ok(EstimatesSource::File(p)))
        .chain(from_streams);
    let result = kfmc::check::attach_estimates_from(plan, sources, unstamped);
    if let Some(e) = raised {
        return Err(e);
    }
    result.map_err(|e| {
        Failure::new(Kind::Estimates, e)
            .context("reading the estimates".into())
            .into_py()
    })
}

/// `kfmc score`: `simulation` is a `kfmc simulate` folder; estimates are files and/or
/// objects with `__arrow_c_stream__`.
#[pyfunction]
#[pyo3(signature = (simulation, paths, streams, *, out=None, threads=None, quiet=false, force=false))]
#[allow(
    clippy::too_many_arguments,
    reason = "each argument is one of the Python function's keyword arguments, its public API"
)]
fn score<'py>(
    py: Python<'py>,
    simulation: PathBuf,
    paths: Vec<PathBuf>,
    streams: Bound<'py, PyAny>,
    out: Option<PathBuf>,
    threads: Option<usize>,
    quiet: bool,
    force: bool,
) -> PyResult<Bound<'py, PyDict>> {
    guarded(|| {
        let registry = kfmc::systems::builtin();
        let mut plan = kfmc::simulate::scoring_plan(&simulation, out, &registry)
            .map_err(|e| Failure::new(Kind::Study, e).into_py())?;
        attach(&mut plan, &paths, &streams, kfmc::check::Unstamped::Warn)?;
        // Per external filter variant, the runs its estimates leave out (status `missing`).
        let missing = PyDict::new(py);
        for m in plan.estimates.iter().flat_map(|e| e.missing_runs()) {
            missing.set_item(m.filter.replace('`', ""), m.runs)?;
        }
        let exec = kfmc::study::ExecOptions {
            threads: clamp_threads(threads.unwrap_or(0)),
            force,
            shard: None,
            checkpoints: None,
        };
        let report = run_study(py, quiet, move |obs| {
            kfmc::study::run(&plan, &exec, obs).map_err(|e| {
                Failure::from(e).context(format!("scoring against {}", simulation.display()))
            })
        })?;
        let d = report_dict(py, &report)?;
        d.set_item("runs_missing", missing)?;
        Ok(d)
    })
}

/// `kfmc check`: returns (exit code, report text, JUnit XML, cases, folder).
#[pyfunction]
#[pyo3(signature = (spec, paths, streams, *, out=None, runs=None, seed=None, threads=None, quiet=false, replications=None, allow_unstamped=false, force=false, allow_large=false, sequential=false, looks=None, spending=None, futility=None, futility_rho=None))]
#[allow(
    clippy::too_many_arguments,
    reason = "each argument is one of the Python function's keyword arguments, its public API"
)]
fn check<'py>(
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
) -> PyResult<Bound<'py, PyDict>> {
    guarded(|| {
        let overrides = gate_overrides(sequential, looks, spending, futility, futility_rho)?;
        let (mut plan, path) = prepared(spec, out, runs, seed, allow_large, None)?;
        // As `kfmc check --sequential …`: the keywords over the spec's `[check]` keys; whether
        // they make a gate for the study's runs is judged with the spec (a SpecError naming
        // the `check.*` key).
        plan.check_sequential = overrides
            .apply(plan.check_sequential.as_ref())
            .map_err(gate_override_error)?;
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

/// `kfmc power`: returns the folder holding power.parquet and, with `target_power` and
/// `against`, the runs-needed text `kfmc power --target-power` prints.
#[pyfunction]
#[pyo3(signature = (spec, replications, *, out=None, runs=None, seed=None, threads=None, quiet=false, force=false, allow_large=false, sequential=false, looks=None, spending=None, futility=None, futility_rho=None, target_power=None, against=None))]
#[allow(
    clippy::too_many_arguments,
    reason = "each argument is one of the Python function's keyword arguments, its public API"
)]
fn power(
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
        let (plan, path) = prepared(spec, None, runs, seed, allow_large, Some(0))?;
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
/// looks (≥ 1) or the looks' run counts, `spending` `"obrien-fleming"` or `"pocock"`.
fn gate_overrides(
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
        Some("obrien-fleming") => Some(Spending::OBrienFleming),
        Some("pocock") => Some(Spending::Pocock),
        Some(other) => {
            return Err(SpecError::new_err(format!(
                "spending: `{other}` is not one of obrien-fleming, pocock"
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
fn gate_override_error(e: kfmc::sequential::GateOverrideError) -> PyErr {
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

/// TOML text as Python values (tables as dicts).
fn toml_to_py<'py>(py: Python<'py>, v: &toml::Value) -> PyResult<Bound<'py, PyAny>> {
    Ok(match v {
        toml::Value::String(s) => s.into_pyobject(py)?.into_any(),
        toml::Value::Integer(i) => i.into_pyobject(py)?.into_any(),
        toml::Value::Float(f) => f.into_pyobject(py)?.into_any(),
        toml::Value::Boolean(b) => b.into_pyobject(py)?.to_owned().into_any(),
        toml::Value::Datetime(d) => d.to_string().into_pyobject(py)?.into_any(),
        toml::Value::Array(a) => {
            let l = PyList::empty(py);
            for item in a {
                l.append(toml_to_py(py, item)?)?;
            }
            l.into_any()
        }
        toml::Value::Table(t) => {
            let d = PyDict::new(py);
            for (k, item) in t {
                d.set_item(k, toml_to_py(py, item)?)?;
            }
            d.into_any()
        }
    })
}

/// A TOML file (a result folder's manifest) as a dict.
#[pyfunction]
fn load_toml<'py>(py: Python<'py>, path: PathBuf) -> PyResult<Bound<'py, PyAny>> {
    guarded(|| {
        let text = kfmc::output::atomic::read_input_to_string(&path)
            .map_err(|e| StudyError::new_err(format!("cannot read {}: {e}", path.display())))?;
        let table: toml::Table = toml::from_str(&text)
            .map_err(|e| StudyError::new_err(format!("{}: {e}", path.display())))?;
        toml_to_py(py, &toml::Value::Table(table))
    })
}

/// `kfmc describe`: the system's analysis for a spec, as a dict (what `describe.toml` holds).
#[pyfunction]
fn describe<'py>(py: Python<'py>, spec: &Bound<'py, PyAny>) -> PyResult<Bound<'py, PyAny>> {
    guarded(|| {
        let registry = kfmc::systems::builtin();
        let (plan, _) = load_spec(spec, &registry)?;
        let text = py.detach(|| plan.describe().to_toml());
        let table: toml::Table = toml::from_str(&text)
            .map_err(|e| Error::new_err(format!("the description is not TOML: {e}")))?;
        toml_to_py(py, &toml::Value::Table(table))
    })
}

/// `kfmc schema KIND SPEC`: the columns (name → type) of an exchange table, and for the
/// estimates the stamp a writer puts in the file's metadata.
#[pyfunction]
fn schema<'py>(
    py: Python<'py>,
    kind: &str,
    spec: &Bound<'py, PyAny>,
) -> PyResult<Bound<'py, PyDict>> {
    guarded(|| {
        use kfmc::output::schema::{self as s, Dtype};
        let registry = kfmc::systems::builtin();
        let (plan, _) = load_spec(spec, &registry)?;
        let l = plan.layout();
        let (q, z, u, w) = (
            l.quantity_names(),
            l.measurement_names(),
            l.input_names(),
            l.world_state_names(),
        );
        let cols = match kind {
            "estimates" => plan.estimate_schema(),
            "truth" => s::truth(&q, &w),
            "measurements" => s::measurements(&z, &u),
            "initial" => s::initial(&q),
            other => {
                return Err(PyValueError::new_err(format!(
                    "unknown table `{other}`: one of estimates, truth, measurements, initial"
                )));
            }
        };
        let columns = PyDict::new(py);
        for c in &cols {
            let ty = match c.dtype {
                Dtype::Str => "string",
                Dtype::F64 => "float64",
                Dtype::F32 => "float32",
                Dtype::I64 => "int64",
                Dtype::U64 => "uint64",
                Dtype::Bool => "bool",
            };
            columns.set_item(&c.name, ty)?;
        }
        let d = PyDict::new(py);
        d.set_item("columns", columns)?;
        if kind == "estimates" {
            let meta = PyDict::new(py);
            for (k, v) in plan.stamp_metadata() {
                meta.set_item(k, v)?;
            }
            d.set_item("metadata", meta)?;
            d.set_item("error_convention", kfmc::score::ERROR_CONVENTION)?;
            // The covariance forms a file may give instead of the P_ columns listed.
            let forms = PyDict::new(py);
            for (name, form) in [
                ("lower", kfmc::score::CovarianceForm::Lower),
                ("cholesky", kfmc::score::CovarianceForm::Cholesky),
                ("correlation", kfmc::score::CovarianceForm::Correlation),
            ] {
                forms.set_item(name, form.columns(&q))?;
            }
            d.set_item("covariance_forms", forms)?;
        }
        let convention = kfmc::system::filter_model::convention_of(plan.system.as_ref());
        d.set_item("step_convention", convention_dict(py, &convention)?)?;
        Ok(d)
    })
}

fn convention_dict<'py>(
    py: Python<'py>,
    c: &kfmc::output::manifest::StepConvention,
) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("transition", &c.transition)?;
    d.set_item("measurement", &c.measurement)?;
    d.set_item("row_0", &c.row_0)?;
    d.set_item("wrapped_errors", c.wrapped_errors.clone())?;
    d.set_item("continuous_angles", c.continuous_angles.clone())?;
    d.set_item("wrapped_innovations", c.wrapped_innovations.clone())?;
    d.set_item("rotation_errors", c.rotation_errors.clone())?;
    Ok(d)
}

/// The model kfmc's filters use for a spec or a simulation (its
/// [`kfmc::system::SystemPlan::filter_model`]): every call runs the Rust model. Vectors are
/// lists of floats and matrices lists of rows; the Python layer (`kfmc.Model`) makes numpy
/// arrays of them.
#[pyclass(frozen, module = "kfmc._kfmc")]
struct FilterModel {
    system: Arc<dyn kfmc::system::SystemPlan>,
    kind: String,
}

impl FilterModel {
    fn new(plan: &Plan) -> PyResult<Self> {
        if plan.system.filter_model().is_none() {
            return Err(Error::new_err(format!(
                "model.kind = \"{}\" has no filter-side model: its world is not one model plus additive noise (each of its filter kinds carries a model of its own)",
                plan.kind
            )));
        }
        Ok(FilterModel {
            system: plan.system.clone(),
            kind: plan.kind.clone(),
        })
    }

    /// Runs `f` on the model; `filter_model` is checked to exist when `self` is made.
    fn with<T>(
        &self,
        f: impl FnOnce(
            &kfmc::system::filter_model::FilterModel<'_>,
        ) -> Result<T, kfmc::model::exposed::CallError>,
    ) -> PyResult<T> {
        guarded(|| {
            let m = self
                .system
                .filter_model()
                .ok_or_else(|| Error::new_err("the system has no filter-side model"))?;
            f(&m).map_err(|e| Error::new_err(e.to_string()))
        })
    }
}

/// A matrix as Python's nested lists.
type Rows = Vec<Vec<f64>>;

fn rows(m: &kfmc::model::exposed::DynMatrix) -> Rows {
    m.to_rows()
}

#[pymethods]
impl FilterModel {
    /// `model.kind`.
    #[getter]
    fn kind(&self) -> String {
        self.kind.clone()
    }
    /// State names (the evaluated quantities).
    #[getter]
    fn states(&self) -> Vec<String> {
        self.system
            .layout()
            .quantities
            .iter()
            .map(|q| q.name.clone())
            .collect()
    }
    /// Input names.
    #[getter]
    fn inputs(&self) -> Vec<String> {
        self.system.layout().inputs.clone()
    }
    /// Measurement component names.
    #[getter]
    fn measurements(&self) -> Vec<String> {
        self.system.layout().measurements.clone()
    }
    /// Δt (s).
    #[getter]
    fn dt_s(&self) -> PyResult<f64> {
        self.with(|m| Ok(m.model.dt_s()))
    }
    /// Whether h reads u.
    #[getter]
    fn measurement_uses_input(&self) -> PyResult<bool> {
        self.with(|m| Ok(m.model.measurement_uses_input()))
    }
    /// Indices of the angle states.
    #[getter]
    fn angle_states(&self) -> PyResult<Vec<usize>> {
        self.with(|m| Ok(m.model.angle_states()))
    }
    /// Indices of the measurement components whose residual is wrapped.
    #[getter]
    fn angle_measurements(&self) -> PyResult<Vec<usize>> {
        self.with(|m| Ok(m.model.angle_measurements()))
    }
    /// f(x, u).
    fn f(&self, x: Vec<f64>, u: Vec<f64>) -> PyResult<Vec<f64>> {
        self.with(|m| m.model.propagate(&x, &u))
    }
    /// h(x, u); `u` empty when h does not read it.
    fn h(&self, x: Vec<f64>, u: Vec<f64>) -> PyResult<Vec<f64>> {
        self.with(|m| m.model.measure(&x, &u))
    }
    /// ∂f/∂x at (x, u), as rows.
    fn transition_jacobian(&self, x: Vec<f64>, u: Vec<f64>) -> PyResult<Vec<Vec<f64>>> {
        self.with(|m| m.model.transition_jacobian(&x, &u).map(|j| rows(&j)))
    }
    /// ∂h/∂x at (x, u), as rows.
    fn measurement_jacobian(&self, x: Vec<f64>, u: Vec<f64>) -> PyResult<Vec<Vec<f64>>> {
        self.with(|m| m.model.measurement_jacobian(&x, &u).map(|j| rows(&j)))
    }
    /// z − ẑ with the angle components wrapped.
    fn residual(&self, z: Vec<f64>, z_pred: Vec<f64>) -> PyResult<Vec<f64>> {
        self.with(|m| m.model.residual(&z, &z_pred))
    }
    /// Which components report at `step`.
    fn availability(&self, step: usize) -> PyResult<Vec<bool>> {
        self.with(|m| Ok(m.model.availability(step)))
    }
    /// (F, G, H) of a linear model, else None.
    fn linear(&self) -> PyResult<Option<(Rows, Rows, Rows)>> {
        self.with(|m| {
            Ok(m.model
                .linear()
                .map(|(f, g, h)| (rows(&f), rows(&g), rows(&h))))
        })
    }
    /// Q at noise scale 1.
    #[getter]
    fn q(&self) -> PyResult<Vec<Vec<f64>>> {
        self.with(|m| Ok(rows(&m.process_noise)))
    }
    /// R at noise scale 1.
    #[getter]
    fn r(&self) -> PyResult<Vec<Vec<f64>>> {
        self.with(|m| Ok(rows(&m.measurement_noise)))
    }
    /// P_0 = diag(p0_std²).
    #[getter]
    fn p0(&self) -> PyResult<Vec<Vec<f64>>> {
        self.with(|m| Ok(rows(&m.initial_covariance)))
    }
    /// Each scenario's x_0, as (name, x0) pairs.
    #[getter]
    fn x0(&self) -> PyResult<Vec<(String, Vec<f64>)>> {
        self.with(|m| {
            Ok(m.initial_states
                .iter()
                .map(|s| (s.scenario.clone(), s.x0.clone()))
                .collect())
        })
    }
    /// The step convention, as a dict.
    #[getter]
    fn step_convention<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let c = kfmc::system::filter_model::convention_of(self.system.as_ref());
        convention_dict(py, &c)
    }
    fn __repr__(&self) -> String {
        let l = self.system.layout();
        format!(
            "kfmc._kfmc.FilterModel(kind={:?}, states={}, inputs={}, measurements={})",
            self.kind,
            l.quantities.len(),
            l.inputs.len(),
            l.measurements.len()
        )
    }
}

/// The filter-side model of a spec.
#[pyfunction]
fn filter_model(spec: &Bound<'_, PyAny>) -> PyResult<FilterModel> {
    guarded(|| {
        let registry = kfmc::systems::builtin();
        let (plan, _) = load_spec(spec, &registry)?;
        FilterModel::new(&plan)
    })
}

/// The filter-side model of a `kfmc simulate` folder (the spec its manifest records).
#[pyfunction]
fn simulation_model(folder: PathBuf) -> PyResult<FilterModel> {
    guarded(|| {
        let registry = kfmc::systems::builtin();
        let plan = kfmc::simulate::scoring_plan(&folder, None, &registry)
            .map_err(|e| Failure::new(Kind::Study, e).into_py())?;
        FilterModel::new(&plan)
    })
}

/// What an estimates table of a study holds and is checked against (the study's
/// [`kfmc::experiment::Plan::study_keys`]): quantities, measurements, rotations (the index of
/// the first of three and the four quaternion columns that may replace them), scenarios with
/// their transitions K, noise scales, runs per cell, filters (label, external), the external
/// filters with their declared variants and the stamp.
fn layout_dict<'py>(py: Python<'py>, plan: &Plan) -> PyResult<Bound<'py, PyDict>> {
    let keys = plan.study_keys();
    let d = PyDict::new(py);
    d.set_item("experiment", keys.experiment)?;
    d.set_item("quantities", keys.quantities.clone())?;
    d.set_item("measurements", keys.measurements.clone())?;
    let names: Vec<String> = keys.quantities.iter().map(|q| q.to_string()).collect();
    let rotations = PyList::empty(py);
    for r in &keys.rotations {
        let rd = PyDict::new(py);
        rd.set_item("first", r.first)?;
        rd.set_item("quaternion", kfmc::score::quaternion_columns(&names, r))?;
        rotations.append(rd)?;
    }
    d.set_item("rotations", rotations)?;
    d.set_item("scenarios", keys.scenarios.clone())?;
    d.set_item("noise_scales", keys.noise_scales.to_vec())?;
    d.set_item("runs", keys.runs)?;
    let filters: Vec<(&str, bool)> = keys.filters.iter().map(|f| (f.label, f.external)).collect();
    d.set_item("filters", filters)?;
    d.set_item("external_filters", external_filters_list(py, plan)?)?;
    d.set_item("world_stamp", &keys.world_stamp)?;
    d.set_item("master_seed", keys.master_seed)?;
    let meta = PyDict::new(py);
    for (k, v) in plan.stamp_metadata() {
        meta.set_item(k, v)?;
    }
    d.set_item("metadata", meta)?;
    Ok(d)
}

/// The spec's external filters as the simulation manifest lists them: dicts with `label` and,
/// for a label that declares variants, `q_scale` and/or `r_scale` (the values its rows take).
fn external_filters_list<'py>(py: Python<'py>, plan: &Plan) -> PyResult<Bound<'py, PyList>> {
    let out = PyList::empty(py);
    for e in kfmc::simulate::external_filters(plan) {
        let d = PyDict::new(py);
        d.set_item("label", &e.label)?;
        if let Some(q) = &e.q_scale {
            d.set_item("q_scale", q.clone())?;
        }
        if let Some(r) = &e.r_scale {
            d.set_item("r_scale", r.clone())?;
        }
        out.append(d)?;
    }
    Ok(out)
}

/// [`layout_dict`] of a `kfmc simulate` folder (`simulation = true`, the spec its manifest
/// records) or of a spec.
#[pyfunction]
#[pyo3(signature = (source, *, simulation))]
fn estimates_layout<'py>(
    py: Python<'py>,
    source: &Bound<'py, PyAny>,
    simulation: bool,
) -> PyResult<Bound<'py, PyDict>> {
    guarded(|| {
        let registry = kfmc::systems::builtin();
        let plan = if simulation {
            let folder: PathBuf = source.extract()?;
            kfmc::simulate::scoring_plan(&folder, None, &registry)
                .map_err(|e| Failure::new(Kind::Study, e).into_py())?
        } else {
            load_spec(source, &registry)?.0
        };
        layout_dict(py, &plan)
    })
}

/// The compiled module.
#[pymodule]
fn _kfmc(m: &Bound<'_, PyModule>) -> PyResult<()> {
    let py = m.py();
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add("Error", py.get_type::<Error>())?;
    m.add("SpecError", py.get_type::<SpecError>())?;
    m.add("EstimatesError", py.get_type::<EstimatesError>())?;
    m.add("StudyError", py.get_type::<StudyError>())?;
    m.add("IncompleteError", py.get_type::<IncompleteError>())?;
    m.add("CheckFailedError", py.get_type::<CheckFailedError>())?;
    ulog::register(m)?;
    m.add_function(wrap_pyfunction!(cli_main, m)?)?;
    m.add_function(wrap_pyfunction!(validate, m)?)?;
    m.add_function(wrap_pyfunction!(run, m)?)?;
    m.add_function(wrap_pyfunction!(simulate, m)?)?;
    m.add_function(wrap_pyfunction!(score, m)?)?;
    m.add_function(wrap_pyfunction!(check, m)?)?;
    m.add_function(wrap_pyfunction!(power, m)?)?;
    m.add_function(wrap_pyfunction!(describe, m)?)?;
    m.add_function(wrap_pyfunction!(schema, m)?)?;
    m.add_function(wrap_pyfunction!(load_toml, m)?)?;
    m.add_function(wrap_pyfunction!(filter_model, m)?)?;
    m.add_function(wrap_pyfunction!(simulation_model, m)?)?;
    m.add_function(wrap_pyfunction!(estimates_layout, m)?)?;
    m.add_class::<FilterModel>()?;
    Ok(())
}
