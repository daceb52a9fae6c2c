//! Estimates from Python: tables read through the Arrow C stream interface, attached to a
//! plan, and `score`.

use std::path::PathBuf;

use kfmc::experiment::Plan;
use polars::prelude::*;
use pyo3::prelude::*;
use pyo3::types::{PyCapsule, PyDict, PyList, PyTuple};

use crate::errors::{EstimatesError, Failure, Kind, guarded};
use crate::progress::run_study;
use crate::study::{clamp_threads, report_dict};

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
pub(crate) fn attach(
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

/// The plan of a recorded spec (`model.kind = "recorded"`) with its truth attached
/// ([`attach_truth`]).
fn recorded_plan(
    spec: &std::path::Path,
    truth: &Bound<'_, PyAny>,
    out: Option<PathBuf>,
    registry: &kfmc::system::Registry,
) -> PyResult<Plan> {
    let mut plan = kfmc::experiment::load_with(spec, registry)
        .map_err(|e| Failure::new(Kind::Study, kfmc::error::KfmcError::from(e)).into_py())?;
    if let Some(out) = out {
        plan.output = out;
    }
    attach_truth(&mut plan, truth)?;
    Ok(plan)
}

/// Attaches a user's truth to a recorded plan (`kfmc score|check --truth`): `truth` is a
/// Parquet file's path or a table with `__arrow_c_stream__` (read whole: the runs' truth is
/// held in memory either way).
pub(crate) fn attach_truth(plan: &mut Plan, truth: &Bound<'_, PyAny>) -> PyResult<()> {
    let (files, frames) = if let Ok(path) = truth.extract::<PathBuf>() {
        (vec![path], Vec::new())
    } else {
        let name = "<truth>".to_string();
        let batches = Batches {
            name: PathBuf::from(&name),
            readers: vec![open_stream(truth, &name)?].into_iter(),
            current: None,
        };
        let frames = batches
            .map(|b| b.map(|df| (name.clone(), df)))
            .collect::<Result<Vec<_>, _>>()
            .map_err(|e| Failure::new(Kind::Estimates, e).into_py())?;
        (Vec::new(), frames)
    };
    kfmc::check::attach_truth(plan, &files, &frames).map_err(|e| {
        Failure::new(Kind::Estimates, e)
            .context("reading the truth".into())
            .into_py()
    })
}

/// `kfmc stamp`: the world stamp of estimates made on a user's own runs (a recorded spec and
/// its truth: the truth's content hash), as a dict of the Parquet metadata keys; the files
/// given are stamped in place, as the command stamps them.
#[pyfunction]
#[pyo3(signature = (spec, truth, files))]
pub(crate) fn stamp<'py>(
    py: Python<'py>,
    spec: &Bound<'py, PyAny>,
    truth: &Bound<'py, PyAny>,
    files: Vec<PathBuf>,
) -> PyResult<Bound<'py, PyDict>> {
    guarded(|| {
        let registry = kfmc::systems::builtin();
        let (mut plan, _) = crate::spec::load_spec(spec, &registry)?;
        attach_truth(&mut plan, truth)?;
        kfmc::check::stamp_estimates(&plan, &files).map_err(|e| {
            Failure::new(Kind::Estimates, e)
                .context("stamping the estimates".into())
                .into_py()
        })?;
        let d = PyDict::new(py);
        for (k, v) in plan.stamp_metadata() {
            d.set_item(k, v)?;
        }
        Ok(d)
    })
}

/// `kfmc score`: `simulation` is a `kfmc simulate` folder (or, with `truth`, the recorded
/// spec the truth is judged with); estimates are files and/or objects with
/// `__arrow_c_stream__`.
#[pyfunction]
#[pyo3(signature = (simulation, paths, streams, *, out=None, threads=None, quiet=false, force=false, truth=None))]
#[allow(
    clippy::too_many_arguments,
    reason = "each argument is one of the Python function's keyword arguments, its public API"
)]
pub(crate) fn score<'py>(
    py: Python<'py>,
    simulation: PathBuf,
    paths: Vec<PathBuf>,
    streams: Bound<'py, PyAny>,
    out: Option<PathBuf>,
    threads: Option<usize>,
    quiet: bool,
    force: bool,
    truth: Option<Bound<'py, PyAny>>,
) -> PyResult<Bound<'py, PyDict>> {
    guarded(|| {
        let registry = kfmc::systems::builtin();
        let mut plan = match &truth {
            // A user's own runs: `simulation` is their recorded spec.
            Some(truth) => recorded_plan(&simulation, truth, out, &registry)?,
            None => kfmc::simulate::scoring_plan(&simulation, out, &registry)
                .map_err(|e| Failure::new(Kind::Study, e).into_py())?,
        };
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
