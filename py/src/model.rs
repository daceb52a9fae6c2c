//! The filter-side model of a spec or a simulation, and the layout an estimates table of
//! a study holds.

use std::path::PathBuf;
use std::sync::Arc;

use kfmc::experiment::Plan;
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};

use crate::errors::{Error, Failure, Kind, guarded};
use crate::spec::{convention_dict, load_spec};

/// The model kfmc's filters use for a spec or a simulation (its
/// [`kfmc::system::SystemPlan::filter_model`]): every call runs the Rust model. Vectors are
/// lists of floats and matrices lists of rows; the Python layer (`kfmc.Model`) makes numpy
/// arrays of them.
#[pyclass(frozen, module = "kfmc._kfmc")]
pub(crate) struct FilterModel {
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

/// Row `i` of a batch's companion, or its only row (one `u` for every state); empty when
/// there is none (an h that does not read the input).
fn row(rows: &[Vec<f64>], i: usize) -> &[f64] {
    match rows {
        [] => &[],
        [only] => only,
        _ => rows.get(i).map_or(&[], Vec::as_slice),
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
    /// f of each row of `xs` with the row of `us` beside it (one `u` for every row when
    /// `us` has one row): one call for a batch of states (sigma points, particles).
    fn f_many(&self, xs: Vec<Vec<f64>>, us: Vec<Vec<f64>>) -> PyResult<Vec<Vec<f64>>> {
        self.with(|m| {
            xs.iter()
                .enumerate()
                .map(|(i, x)| m.model.propagate(x, row(&us, i)))
                .collect()
        })
    }
    /// h of each row of `xs` (with `us` as in [`Self::f_many`]; empty rows when h does not
    /// read the input).
    fn h_many(&self, xs: Vec<Vec<f64>>, us: Vec<Vec<f64>>) -> PyResult<Vec<Vec<f64>>> {
        self.with(|m| {
            xs.iter()
                .enumerate()
                .map(|(i, x)| m.model.measure(x, row(&us, i)))
                .collect()
        })
    }
    /// The residual of each row of `zs` against the row of `z_preds` (or its one row).
    fn residual_many(&self, zs: Vec<Vec<f64>>, z_preds: Vec<Vec<f64>>) -> PyResult<Vec<Vec<f64>>> {
        self.with(|m| {
            zs.iter()
                .enumerate()
                .map(|(i, z)| m.model.residual(z, row(&z_preds, i)))
                .collect()
        })
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
pub(crate) fn filter_model(spec: &Bound<'_, PyAny>) -> PyResult<FilterModel> {
    guarded(|| {
        let registry = kfmc::systems::builtin();
        let (plan, _) = load_spec(spec, &registry)?;
        FilterModel::new(&plan)
    })
}

/// The filter-side model of a `kfmc simulate` folder (the spec its manifest records).
#[pyfunction]
pub(crate) fn simulation_model(folder: PathBuf) -> PyResult<FilterModel> {
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
pub(crate) fn estimates_layout<'py>(
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
