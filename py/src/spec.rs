//! Specs across the boundary: a spec given as a path, a dict or TOML text, loaded and
//! validated; TOML as Python values; `describe` and `schema`.

use std::path::PathBuf;

use kfmc::experiment::{self, Overrides, Plan};
use kfmc::system::Registry;
use pyo3::exceptions::{PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyBool, PyDict, PyFloat, PyInt, PyList, PyString, PyTuple};

use crate::errors::{Error, Failure, SpecError, StudyError, guarded};

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
    // numpy scalars and arrays (and anything else with numpy's `tolist`, a pandas Series)
    // become the Python values they hold; a 0-d array gives its scalar.
    if let Ok(tolist) = v.getattr("tolist")
        && tolist.is_callable()
        && let Ok(plain) = tolist.call0()
        && !plain.get_type().is(v.get_type())
    {
        return to_toml(&plain, key, depth + 1);
    }
    Err(spec_err(&format!(
        "a {} has no TOML form (use bool, int, float, str, list or dict)",
        v.get_type().name()?
    )))
}

/// A spec given as a path, a dict or TOML text (a `str` with a newline), loaded and
/// validated.
pub(crate) fn load_spec(spec: &Bound<'_, PyAny>, registry: &Registry) -> PyResult<(Plan, PathBuf)> {
    let loaded = if let Ok(d) = spec.cast::<PyDict>() {
        let text = dict_to_toml(d)?;
        let path = PathBuf::from("<dict>");
        // The TOML text is ours, not the caller's: its line numbers would point nowhere.
        let parsed = experiment::parse_with(&text, &path, registry).map_err(|mut e| {
            for problem in &mut e.0 {
                problem.message = without_position(&problem.message);
            }
            e
        });
        (parsed, path)
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

/// A dict spec as TOML text.
fn dict_to_toml(d: &Bound<'_, PyDict>) -> PyResult<String> {
    let toml::Value::Table(table) = to_toml(d.as_any(), "", 0)? else {
        unreachable!("a dict is a table");
    };
    toml::to_string(&table)
        .map_err(|e| SpecError::new_err(format!("<dict>: cannot write it as TOML: {e}")))
}

/// `message` without the ` (line N, column M)` positions the TOML parser gives.
fn without_position(message: &str) -> String {
    let mut out = String::with_capacity(message.len());
    let mut rest = message;
    while let Some(at) = rest.find(" (line ") {
        out.push_str(&rest[..at]);
        let tail = &rest[at..];
        let end = tail.find(')').map(|e| e + 1);
        let is_position = end.is_some_and(|e| {
            let inner = &tail[" (line ".len()..e - 1];
            inner.split_once(", column ").is_some_and(|(l, c)| {
                [l, c]
                    .iter()
                    .all(|n| !n.is_empty() && n.bytes().all(|b| b.is_ascii_digit()))
            })
        });
        match end {
            Some(e) if is_position => rest = &tail[e..],
            _ => {
                out.push_str(" (line ");
                rest = &tail[" (line ".len()..];
            }
        }
    }
    out.push_str(rest);
    out
}

/// A dict spec written as the TOML text `kfmc validate` reads (numpy values as the numbers
/// they hold); raises `SpecError` for a value TOML cannot hold.
#[pyfunction]
pub(crate) fn to_toml_text(spec: &Bound<'_, PyDict>) -> PyResult<String> {
    guarded(|| dict_to_toml(spec))
}

/// The overrides every study command takes, applied and checked against the limits.
pub(crate) fn prepared(
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
pub(crate) fn load_toml<'py>(py: Python<'py>, path: PathBuf) -> PyResult<Bound<'py, PyAny>> {
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
pub(crate) fn describe<'py>(
    py: Python<'py>,
    spec: &Bound<'py, PyAny>,
) -> PyResult<Bound<'py, PyAny>> {
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
pub(crate) fn schema<'py>(
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

pub(crate) fn convention_dict<'py>(
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
