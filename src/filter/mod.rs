//! The filter role.
//!
//! A filter value holds **configuration only** (its assumed Q and R, a window length, …) and is
//! shared by reference across threads; the belief (mean and covariance, a measurement window,
//! …) is a value threaded through the step loop. Every filter exposes the common view
//! [`Filter::mean`] / [`Filter::covariance`], so metrics never ask which filter ran; a filter
//! without a covariance (the running mean) returns `None` and NEES/NIS are reported as null.

pub mod batch_ls;
pub mod ekf;
pub mod information;
pub mod luenberger;
pub mod open_loop;
pub mod sigma_point;
pub mod sqrt;
pub mod steady_state;

use crate::linalg::{Matrix, SmallCholesky, Vector, symmetrize};
use crate::model::{Availability, Measurement, Model};

pub use batch_ls::{BatchInitial, BatchLsError};
pub use ekf::{CovarianceUpdate, Ekf};
pub use information::Information;
pub use luenberger::{
    Luenberger, PlacementError, SeedPoleReading, place_observer_poles, seed_poles,
};
pub use open_loop::OpenLoop;
pub use sigma_point::{SigmaPointKalman, SigmaPoints};
pub use sqrt::SquareRoot;
pub use steady_state::SteadyState;

/// Removes the components that did not report from H, ν and R, exactly as the EKF does: their
/// rows of H and ν are zeroed and their block of R replaced by the identity, so every
/// linear-Gaussian update equals one over the reporting rows alone.
pub fn mask_rows<const NX: usize, const NZ: usize>(
    r: &Matrix<NZ, NZ>,
    available: Availability,
    h: &mut Matrix<NZ, NX>,
    nu: &mut Vector<NZ>,
) -> Matrix<NZ, NZ> {
    let mut r = *r;
    if available == Availability::all(NZ) {
        return r;
    }
    for i in 0..NZ {
        if !available.has(i) {
            h.row_mut(i).fill(0.0);
            nu[i] = 0.0;
            r.row_mut(i).fill(0.0);
            r.column_mut(i).fill(0.0);
            r[(i, i)] = 1.0;
        }
    }
    r
}

/// The same non-finite check as the EKF's, for a mean and a matrix.
pub fn check_finite<const NX: usize>(
    x: &Vector<NX>,
    m: &Matrix<NX, NX>,
) -> Result<(), FilterError> {
    if !x.sum().is_finite() {
        return Err(FilterError::NonFinite {
            what: "state estimate",
        });
    }
    if !m.trace().is_finite() {
        return Err(FilterError::NonFinite {
            what: "state covariance",
        });
    }
    Ok(())
}

/// What a measurement update tells the metrics about the innovation.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Innovation<const NZ: usize> {
    /// ν = z − ĥ (zero in components that did not report).
    pub residual: Vector<NZ>,
    /// NIS = νᵀ S⁻¹ ν over the reporting components.
    pub nis: f64,
    /// Degrees of freedom of the NIS (number of reporting components).
    pub dof: usize,
    /// The whitened innovation L⁻¹ν (S = L Lᵀ): i.i.d. N(0, 1) components for a consistent
    /// filter, used by the whiteness test. Zero in components that did not report.
    pub whitened: Vector<NZ>,
    /// The components that reported.
    pub available: Availability,
    /// S, the innovation covariance (identity rows and columns where a component did not
    /// report), when the filter forms it. Only `kfmc run --export-estimates` reads it, to
    /// write the `S_<i>_<j>` columns that let `kfmc score` recompute the NIS and whiteness.
    pub covariance: Option<Matrix<NZ, NZ>>,
}

impl<const NZ: usize> Innovation<NZ> {
    /// The innovation of an update over the `available` components from its residual ν and
    /// its whitened form L⁻¹ν (S = L Lᵀ); the NIS is ‖L⁻¹ν‖².
    pub fn new(residual: Vector<NZ>, whitened: Vector<NZ>, available: Availability) -> Self {
        Innovation {
            residual,
            nis: whitened.norm_squared(),
            dof: available.count(),
            whitened,
            available,
            covariance: None,
        }
    }

    /// The same innovation, also carrying its covariance S.
    pub fn with_covariance(mut self, s: Matrix<NZ, NZ>) -> Self {
        self.covariance = Some(s);
        self
    }
}

/// Numerical trouble inside one run. It becomes that run's status, never a batch abort.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum FilterError {
    /// A covariance that must be positive definite is not (Cholesky failed).
    #[error("{which} is not positive definite")]
    NotPositiveDefinite {
        /// Which matrix: "innovation covariance S", "state covariance P", …
        which: &'static str,
    },
    /// A matrix that must be invertible is singular (the information filter needs F⁻¹).
    #[error("{which} is singular")]
    Singular {
        /// Which matrix.
        which: &'static str,
    },
    /// The Riccati recursion did not converge: the model is not detectable with this sensor.
    #[error("the discrete algebraic Riccati equation has no steady state (not detectable)")]
    NoSteadyState,
    /// An external filter's estimates file cannot give this step (a missing row, a null
    /// estimate): that run's status, as numerical trouble is.
    #[error("{0}")]
    Estimates(String),
    /// The estimate or covariance contains NaN or ±∞.
    #[error("non-finite {what}")]
    NonFinite {
        /// What became non-finite.
        what: &'static str,
    },
}

/// A state estimator for the model `M`.
pub trait Filter<const NX: usize, const NU: usize, const NZ: usize, M: Model<NX, NU, NZ>>:
    Sync
{
    /// The filter's belief: everything that changes from step to step.
    type Belief: Clone + Send;

    /// The belief at k = 0 from the initial estimate x̂_0, its covariance P_0 and the
    /// measurement z_0 (the seeds record a noise-free z_0; only window filters use it).
    fn init(
        &self,
        model: &M,
        x0_hat: &Vector<NX>,
        p0: &Matrix<NX, NX>,
        z0: &Measurement<NZ>,
    ) -> Self::Belief;

    /// Time update from k−1 to k under the control u_k.
    fn predict(
        &self,
        model: &M,
        belief: &mut Self::Belief,
        u: &Vector<NU>,
    ) -> Result<(), FilterError>;

    /// Measurement update at k; returns the innovation when the filter has one.
    fn update(
        &self,
        model: &M,
        belief: &mut Self::Belief,
        u: &Vector<NU>,
        z: &Measurement<NZ>,
    ) -> Result<Option<Innovation<NZ>>, FilterError>;

    /// The state estimate x̂_k.
    fn mean(&self, belief: &Self::Belief) -> Vector<NX>;

    /// The estimate's covariance P_k, or `None` when the filter carries none.
    fn covariance(&self, belief: &Self::Belief) -> Option<Matrix<NX, NX>>;

    /// P_k by reference, when the belief holds it as a matrix. The step loop reads P_k every
    /// step (NEES, consistency sums, traces); borrowing it saves copying 8·NX² bytes out of
    /// the belief each time. `None` (the default) makes the loop call
    /// [`Filter::covariance`] instead, so a filter that forms P_k on demand (from a square
    /// root, an information matrix) needs nothing here. A filter that returns `Some` must
    /// return the matrix [`Filter::covariance`] returns.
    fn covariance_ref<'b>(&self, _belief: &'b Self::Belief) -> Option<&'b Matrix<NX, NX>> {
        None
    }

    /// A_k, the matrix that maps the previous estimation error into the current one to first
    /// order: (I − K_k H_k) F_k after an update, F_k after a prediction alone. The calibrated
    /// NEES test and the burn-in rule need it; filters without one return `None`.
    fn error_transition(&self, _belief: &Self::Belief) -> Option<Matrix<NX, NX>> {
        None
    }

    /// Makes a covariance that failed a Cholesky factorisation usable again (symmetrise and
    /// add jitter). Returns whether a repair was made; every repair is counted per run.
    fn repair_covariance(&self, _belief: &mut Self::Belief) -> bool {
        false
    }

    /// Repairs the filter made inside its own steps so far: a sigma-point filter factors its
    /// predicted covariance to draw points and repairs it as [`repair_spd`] does. They are
    /// counted per run with those of [`Filter::repair_covariance`].
    fn internal_repairs(&self, _belief: &Self::Belief) -> u32 {
        0
    }

    /// The covariance-form Kalman filter this filter is, if it is one: on a linear model a
    /// group of runs of one cell then computes its covariance recursion once and runs only
    /// the estimates per run, with the same bits. `None` (the default) for every other filter.
    fn as_kalman(&self) -> Option<&Ekf<NX, NZ>> {
        None
    }
}

/// The covariance repair every filter shares: symmetrise, then add the smallest jitter
/// (10⁻¹², 10⁻¹⁰, … 10² times the mean variance) that makes the matrix factorable. Returns the
/// factor, or `None` (and leaves `p` alone) when no jitter helps.
pub fn repair_spd<const NX: usize>(p: &mut Matrix<NX, NX>) -> Option<SmallCholesky<NX>> {
    let sym = symmetrize(p);
    // Jitter relative to the covariance's own scale, so units do not matter.
    let scale = (sym.trace() / NX as f64).abs().max(f64::MIN_POSITIVE);
    let mut jitter = 1e-12 * scale;
    for _ in 0..8 {
        let candidate = sym + Matrix::<NX, NX>::identity() * jitter;
        if let Some(chol) = SmallCholesky::new(&candidate) {
            *p = candidate;
            return Some(chol);
        }
        jitter *= 100.0;
    }
    None
}
