//! A [`Model`] behind a dyn-safe interface of slices and row-major matrices, for callers that
//! do not know its sizes at compile time: the Python package (`Simulation.f`, `.h`,
//! `.jacobians`) and `kfmc describe`'s filter-side model. Every call runs the model's own
//! f, h and Jacobians — the functions the truth simulator and kfmc's filters call — so a
//! filter written elsewhere uses the world's model, not a transcription of it.
//!
//! Lengths are checked and reported as a [`CallError`], never a panic: the caller may be
//! another language.

use serde::Serialize;

use super::Model;
use crate::linalg::{Matrix, Vector};
use crate::output::manifest::StepConvention;

/// A call whose vectors do not fit the model.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct CallError(pub String);

impl std::fmt::Display for CallError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for CallError {}

/// A matrix with its shape, row-major.
#[derive(Clone, Debug, PartialEq)]
pub struct DynMatrix {
    /// Rows.
    pub rows: usize,
    /// Columns.
    pub cols: usize,
    /// The entries, row by row.
    pub data: Vec<f64>,
}

impl DynMatrix {
    /// The entries of `m` (all of its columns).
    pub fn of<const R: usize, const C: usize>(m: &Matrix<R, C>) -> Self {
        Self::columns_of(m, C)
    }

    /// The first `cols` columns of `m`.
    pub fn columns_of<const R: usize, const C: usize>(m: &Matrix<R, C>, cols: usize) -> Self {
        let cols = cols.min(C);
        DynMatrix {
            rows: R,
            cols,
            data: (0..R)
                .flat_map(|i| (0..cols).map(move |j| m[(i, j)]))
                .collect(),
        }
    }

    /// The rows as vectors (TOML's and Python's nested lists).
    pub fn to_rows(&self) -> Vec<Vec<f64>> {
        if self.cols == 0 {
            return vec![Vec::new(); self.rows];
        }
        self.data.chunks(self.cols).map(<[f64]>::to_vec).collect()
    }
}

/// A model of any size, through slices: see the module docs.
pub trait DynModel: Send + Sync {
    /// State dimension n.
    fn states(&self) -> usize;
    /// Inputs the caller passes (a model padded to more inputs takes zeros for the rest).
    fn inputs(&self) -> usize;
    /// Measurement components.
    fn measurements(&self) -> usize;
    /// Sample time Δt (s).
    fn dt_s(&self) -> f64;
    /// f(x_{k−1}, u_k) ([`Model::propagate`]).
    fn propagate(&self, x: &[f64], u: &[f64]) -> Result<Vec<f64>, CallError>;
    /// h(x_k, u_k) ([`Model::measure`]); `u` may be empty when h does not read it
    /// ([`DynModel::measurement_uses_input`]).
    fn measure(&self, x: &[f64], u: &[f64]) -> Result<Vec<f64>, CallError>;
    /// F = ∂f/∂x at (x, u).
    fn transition_jacobian(&self, x: &[f64], u: &[f64]) -> Result<DynMatrix, CallError>;
    /// H = ∂h/∂x at (x, u); `u` as for [`DynModel::measure`].
    fn measurement_jacobian(&self, x: &[f64], u: &[f64]) -> Result<DynMatrix, CallError>;
    /// The innovation z − ẑ with the angle measurements wrapped ([`Model::residual`]).
    fn residual(&self, z: &[f64], z_pred: &[f64]) -> Result<Vec<f64>, CallError>;
    /// The angle states ([`Model::angle_states`]).
    fn angle_states(&self) -> Vec<usize>;
    /// The angle measurement components, whose residual is wrapped.
    fn angle_measurements(&self) -> Vec<usize>;
    /// Which components report at `step` ([`Model::availability`]).
    fn availability(&self, step: usize) -> Vec<bool>;
    /// The model's own full Q ([`Model::process_noise_covariance`]).
    fn process_noise_covariance(&self) -> Option<DynMatrix>;
    /// (F, G, H) of a linear model ([`Model::linear`]), G with the caller's inputs only.
    fn linear(&self) -> Option<(DynMatrix, DynMatrix, DynMatrix)>;
    /// Whether h reads u ([`Model::measurement_uses_input`]).
    fn measurement_uses_input(&self) -> bool;
}

/// [`DynModel`] over a borrowed [`Model`].
#[derive(Debug)]
pub struct ModelView<'a, M, const NX: usize, const NU: usize, const NZ: usize> {
    model: &'a M,
    inputs: usize,
}

impl<'a, M, const NX: usize, const NU: usize, const NZ: usize> ModelView<'a, M, NX, NU, NZ> {
    /// The model with all of its `NU` inputs.
    pub fn new(model: &'a M) -> Self {
        ModelView { model, inputs: NU }
    }

    /// The model with only its first `inputs` inputs given by the caller, the rest zero (a
    /// model compiled with more inputs than its spec names, e.g. a `kind = "linear"` one).
    pub fn with_inputs(model: &'a M, inputs: usize) -> Self {
        ModelView {
            model,
            inputs: inputs.min(NU),
        }
    }
}

fn vector<const N: usize>(v: &[f64], what: &str) -> Result<Vector<N>, CallError> {
    if v.len() != N {
        return Err(CallError(format!(
            "{what} has {} components; the model's has {N}",
            v.len()
        )));
    }
    Ok(Vector::<N>::from_column_slice(v))
}

impl<M, const NX: usize, const NU: usize, const NZ: usize> ModelView<'_, M, NX, NU, NZ>
where
    M: Model<NX, NU, NZ>,
{
    fn input(&self, u: &[f64], optional: bool) -> Result<Vector<NU>, CallError> {
        if optional && u.is_empty() {
            return Ok(Vector::<NU>::zeros());
        }
        if u.len() != self.inputs {
            return Err(CallError(format!(
                "u has {} components; the model has {} inputs",
                u.len(),
                self.inputs
            )));
        }
        let mut padded = Vector::<NU>::zeros();
        padded.as_mut_slice()[..u.len()].copy_from_slice(u);
        Ok(padded)
    }
}

impl<M, const NX: usize, const NU: usize, const NZ: usize> DynModel for ModelView<'_, M, NX, NU, NZ>
where
    M: Model<NX, NU, NZ>,
{
    fn states(&self) -> usize {
        NX
    }
    fn inputs(&self) -> usize {
        self.inputs
    }
    fn measurements(&self) -> usize {
        NZ
    }
    fn dt_s(&self) -> f64 {
        self.model.dt_s()
    }
    fn propagate(&self, x: &[f64], u: &[f64]) -> Result<Vec<f64>, CallError> {
        let x = vector::<NX>(x, "x")?;
        let u = self.input(u, false)?;
        Ok(self.model.propagate(&x, &u).as_slice().to_vec())
    }
    fn measure(&self, x: &[f64], u: &[f64]) -> Result<Vec<f64>, CallError> {
        let x = vector::<NX>(x, "x")?;
        let u = self.input(u, !self.model.measurement_uses_input())?;
        Ok(self.model.measure(&x, &u).as_slice().to_vec())
    }
    fn transition_jacobian(&self, x: &[f64], u: &[f64]) -> Result<DynMatrix, CallError> {
        let x = vector::<NX>(x, "x")?;
        let u = self.input(u, false)?;
        Ok(DynMatrix::of(&self.model.transition_jacobian(&x, &u)))
    }
    fn measurement_jacobian(&self, x: &[f64], u: &[f64]) -> Result<DynMatrix, CallError> {
        let x = vector::<NX>(x, "x")?;
        let u = self.input(u, !self.model.measurement_uses_input())?;
        Ok(DynMatrix::of(&self.model.measurement_jacobian(&x, &u)))
    }
    fn residual(&self, z: &[f64], z_pred: &[f64]) -> Result<Vec<f64>, CallError> {
        let z = vector::<NZ>(z, "z")?;
        let z_pred = vector::<NZ>(z_pred, "the predicted z")?;
        Ok(self.model.residual(&z, &z_pred).as_slice().to_vec())
    }
    fn angle_states(&self) -> Vec<usize> {
        self.model.angle_states().to_vec()
    }
    fn angle_measurements(&self) -> Vec<usize> {
        self.model.angle_measurements().to_vec()
    }
    fn availability(&self, step: usize) -> Vec<bool> {
        let a = self.model.availability(step);
        (0..NZ).map(|i| a.has(i)).collect()
    }
    fn process_noise_covariance(&self) -> Option<DynMatrix> {
        self.model
            .process_noise_covariance()
            .map(|q| DynMatrix::of(&q))
    }
    fn linear(&self) -> Option<(DynMatrix, DynMatrix, DynMatrix)> {
        self.model.linear().map(|l| {
            (
                DynMatrix::of(&l.f),
                DynMatrix::columns_of(&l.g, self.inputs),
                DynMatrix::of(&l.h),
            )
        })
    }
    fn measurement_uses_input(&self) -> bool {
        self.model.measurement_uses_input()
    }
}

/// The filter-side model as `kfmc describe` writes it (`[filter_model]` of describe.toml):
/// every number at full precision (TOML floats round-trip f64 exactly).
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct FilterModelRecord {
    /// `linear` (F, G and H given) or `nonlinear` (f and h are code: the Python package
    /// calls them).
    pub form: String,
    /// Sample time Δt (s).
    pub dt_s: f64,
    /// State names, in the order of every vector and matrix below.
    pub states: Vec<String>,
    /// Input names.
    pub inputs: Vec<String>,
    /// Measurement component names.
    pub measurements: Vec<String>,
    /// F of x_k = F x_{k−1} + G u_k + w_k (linear models).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub f: Option<Vec<Vec<f64>>>,
    /// G (linear models).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub g: Option<Vec<Vec<f64>>>,
    /// H of z_k = H x_k + v_k (linear models).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub h: Option<Vec<Vec<f64>>>,
    /// Q: the truth's process-noise covariance at noise scale 1 (noise scale s: s² Q).
    pub q: Vec<Vec<f64>>,
    /// R: the truth's measurement-noise covariance at noise scale 1 (noise scale s: s² R).
    pub r: Vec<Vec<f64>>,
    /// P_0 = diag(p0_std²): the prior's covariance in the `truth` and `sampled` modes.
    pub p0: Vec<Vec<f64>>,
    /// Each scenario's true initial state x_0.
    pub x0: Vec<ScenarioStart>,
    /// Which input drives a step, what row 0 is, and what wraps.
    pub convention: StepConvention,
}

/// A scenario's initial state.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct ScenarioStart {
    /// Scenario name.
    pub scenario: String,
    /// x_0.
    pub x0: Vec<f64>,
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::systems::planar::model::{PlanarImu, PlanarP1, PlanarParams};

    #[test]
    fn the_view_calls_the_model_and_refuses_wrong_lengths() {
        let model = PlanarP1::new(PlanarParams::default());
        let view = ModelView::<_, 6, 2, 3>::new(&model);
        let x = [0.1, 0.2, 1.0, -0.3, 7.0, 0.5];
        let u = [2.5, 2.4];
        let xv = Vector::<6>::from_column_slice(&x);
        let uv = Vector::<2>::from_column_slice(&u);
        assert_eq!(
            view.propagate(&x, &u).unwrap(),
            model.propagate(&xv, &uv).as_slice()
        );
        let f = view.transition_jacobian(&x, &u).unwrap();
        assert_eq!((f.rows, f.cols), (6, 6));
        let fm = model.transition_jacobian(&xv, &uv);
        assert_eq!(f.data[6 + 4], fm[(1, 4)]);
        // P1's h reads only x: u may be left out.
        assert_eq!(view.measure(&x, &[]).unwrap(), vec![1.0, 7.0, 0.5]);
        assert_eq!(
            view.residual(&[0.0, 7.0, 0.0], &[0.0, 0.5, 0.0]).unwrap()[1],
            crate::model::wrap_angle(6.5)
        );
        let e = view.propagate(&x[..5], &u).unwrap_err().to_string();
        assert!(e.contains("x has 5 components; the model's has 6"), "{e}");
        let e = view.propagate(&x, &[]).unwrap_err().to_string();
        assert!(
            e.contains("u has 0 components; the model has 2 inputs"),
            "{e}"
        );
        // The IMU set's h reads u (accelerations): it is required.
        let imu = PlanarImu::new(PlanarParams::default());
        assert!(ModelView::<_, 6, 2, 4>::new(&imu).measure(&x, &[]).is_err());
        assert_eq!(
            ModelView::<_, 6, 2, 4>::new(&imu)
                .measure(&x, &u)
                .unwrap()
                .len(),
            4
        );
    }
}
