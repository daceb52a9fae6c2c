//! The commands that read a result folder or the registry: `summary`, `plot`, `report` and
//! `list`, each the library function its command prints from.

use std::path::PathBuf;

use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyDict;

use crate::errors::{Failure, Kind, guarded};

/// `kfmc summary DIR`: the RMSE table as the command prints it.
#[pyfunction]
#[pyo3(signature = (folder, *, noise_scale=None))]
pub(crate) fn summary(
    py: Python<'_>,
    folder: PathBuf,
    noise_scale: Option<f64>,
) -> PyResult<String> {
    guarded(|| {
        py.detach(|| kfmc::cli::summary::render(&folder, noise_scale))
            .map_err(|e| Failure::new(Kind::Study, kfmc::error::KfmcError::from(e)).into_py())
    })
}

/// `kfmc plot DIR`: draws every figure the folder's tables support; returns the files.
#[pyfunction]
#[pyo3(signature = (folder, *, out=None, format="png"))]
pub(crate) fn plot(
    py: Python<'_>,
    folder: PathBuf,
    out: Option<PathBuf>,
    format: &str,
) -> PyResult<Vec<PathBuf>> {
    guarded(|| {
        use kfmc::plot::{Format, PlotOptions};
        let format = match format {
            "png" => Format::Png,
            "svg" => Format::Svg,
            other => {
                return Err(PyValueError::new_err(format!(
                    "format: `{other}` is not one of png, svg"
                )));
            }
        };
        let options = PlotOptions {
            out,
            format,
            only: Vec::new(),
        };
        py.detach(|| kfmc::plot::plot_all(&folder, &options))
            .map_err(|e| {
                Failure::new(Kind::Auto, kfmc::error::KfmcError::from(e))
                    .context(format!("plotting {}", folder.display()))
                    .into_py()
            })
    })
}

/// `kfmc report DIR`: writes the HTML report; returns its path.
#[pyfunction]
#[pyo3(signature = (folder, *, out=None))]
pub(crate) fn report(py: Python<'_>, folder: PathBuf, out: Option<PathBuf>) -> PyResult<PathBuf> {
    guarded(|| {
        py.detach(|| kfmc::plot::write_report(&folder, out.as_deref()))
            .map_err(|e| {
                Failure::new(Kind::Auto, kfmc::error::KfmcError::from(e))
                    .context(format!("writing the report of {}", folder.display()))
                    .into_py()
            })
    })
}

/// `kfmc list`: per system (`model.kind`) its one-line `about` and its titled sections
/// (scenarios, filter kinds, sensors, model keys, …) as name → description.
#[pyfunction]
pub(crate) fn list(py: Python<'_>) -> PyResult<Bound<'_, PyDict>> {
    guarded(|| {
        let registry = kfmc::systems::builtin();
        let systems = PyDict::new(py);
        for system in registry.systems() {
            let catalogue = system.catalogue();
            let sections = PyDict::new(py);
            for (title, entries) in &catalogue.sections {
                let section = PyDict::new(py);
                for (name, about) in entries {
                    section.set_item(name, about)?;
                }
                sections.set_item(title, section)?;
            }
            let d = PyDict::new(py);
            d.set_item("about", &catalogue.about)?;
            d.set_item("sections", sections)?;
            systems.set_item(system.kind(), d)?;
        }
        Ok(systems)
    })
}
