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
//!   Ctrl-C cancels the study through its [`CancelToken`](kfmc::runner::CancelToken) (the
//!   executor's checkpoint path, as SIGINT does for the command) and is re-raised as
//!   `KeyboardInterrupt` unless the study had already committed; SIGTERM stops it the same
//!   way and then ends the process. No process-wide signal handler of kfmc's is installed:
//!   SIGTERM's, while a study runs, is Python's own mechanism, put back afterwards;
//! * library errors become `kfmc.Error` subclasses by their kind, with the whole cause chain
//!   as the message (as the command prints it).

mod check;
mod errors;
mod estimates;
mod folder;
mod model;
mod progress;
mod spec;
mod study;
mod tune;
mod ulog;

use pyo3::prelude::*;

use errors::{
    CheckFailedError, Error, EstimatesError, IncompleteError, SpecError, StudyError, guarded,
};
use estimates::{score, stamp};
use model::{FilterModel, estimates_layout, filter_model, simulation_model};
use spec::{describe, load_toml, schema, to_toml_text};
use study::{power, run, simulate, validate};

/// The console script `kfmc`: the command line with argv (program name first); returns the
/// binary's exit code. This is the command, so it handles SIGINT as the binary does.
#[pyfunction]
fn cli_main(py: Python<'_>, argv: Vec<std::ffi::OsString>) -> PyResult<u8> {
    guarded(|| Ok(py.detach(|| kfmc::cli::main_from_args(argv, &kfmc::systems::builtin()))))
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
    m.add_function(wrap_pyfunction!(check::check, m)?)?;
    m.add_function(wrap_pyfunction!(power, m)?)?;
    m.add_function(wrap_pyfunction!(tune::tune, m)?)?;
    m.add_function(wrap_pyfunction!(stamp, m)?)?;
    m.add_function(wrap_pyfunction!(describe, m)?)?;
    m.add_function(wrap_pyfunction!(schema, m)?)?;
    m.add_function(wrap_pyfunction!(load_toml, m)?)?;
    m.add_function(wrap_pyfunction!(to_toml_text, m)?)?;
    m.add_function(wrap_pyfunction!(folder::summary, m)?)?;
    m.add_function(wrap_pyfunction!(folder::plot, m)?)?;
    m.add_function(wrap_pyfunction!(folder::report, m)?)?;
    m.add_function(wrap_pyfunction!(folder::list, m)?)?;
    m.add_function(wrap_pyfunction!(filter_model, m)?)?;
    m.add_function(wrap_pyfunction!(simulation_model, m)?)?;
    m.add_function(wrap_pyfunction!(estimates_layout, m)?)?;
    m.add_class::<FilterModel>()?;
    Ok(())
}
