//! The exceptions kfmc raises, and how a failure on the Rust side becomes one: by its
//! kind, with the whole cause chain as the message; and no panic crossing into Python.

use std::panic::AssertUnwindSafe;

use kfmc::error::{KfmcError, OutputError};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;

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
pub(crate) enum Kind {
    /// Decided by the library error's variant.
    Auto,
    /// Reading the caller's estimates: every problem is the estimates'.
    Estimates,
    /// A result folder the caller named.
    Study,
}

/// A failure on the Rust side: the error with its context chain, and how to classify it.
pub(crate) struct Failure {
    kind: Kind,
    error: anyhow::Error,
}

impl Failure {
    pub(crate) fn new(kind: Kind, error: impl Into<anyhow::Error>) -> Self {
        Failure {
            kind,
            error: error.into(),
        }
    }
    fn auto(error: impl Into<anyhow::Error>) -> Self {
        Self::new(Kind::Auto, error)
    }
    pub(crate) fn context(self, context: String) -> Self {
        Failure {
            kind: self.kind,
            error: self.error.context(context),
        }
    }
    pub(crate) fn into_py(self) -> PyErr {
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
pub(crate) fn guarded<T>(f: impl FnOnce() -> PyResult<T>) -> PyResult<T> {
    match std::panic::catch_unwind(AssertUnwindSafe(f)) {
        Ok(r) => r,
        Err(panic) => Err(Error::new_err(format!(
            "internal error in kfmc (please report it): {}",
            panic_message(&*panic)
        ))),
    }
}

pub(crate) fn panic_message(panic: &(dyn std::any::Any + Send)) -> String {
    panic
        .downcast_ref::<&str>()
        .map(|s| s.to_string())
        .or_else(|| panic.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "a panic".into())
}
