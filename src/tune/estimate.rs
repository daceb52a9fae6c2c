//! The search every element-wise method shares: Levenberg–Marquardt in the log-parameters
//! from a few starts within bounds ([`minimise`], on any [`Objective`]: the likelihood's
//! Fisher scoring for `ml`, Gauss–Newton on the identifying conditions for `truth`), and the
//! identifiability of each element from the curvature at the optimum ([`intervals`]). For
//! `ml`, [`estimate`] adds the observed information at the optimum for the intervals.
//!
//! Everything is deterministic: the objectives sum their runs in run order, the starts are
//! fixed, and the observed information is a fixed set of central differences of the analytic
//! score, so the estimates are the same bits on any number of threads.

use nalgebra::{DMatrix, SymmetricEigen};
use rayon::prelude::*;

use super::likelihood::{Evaluation, Problem};

/// What [`minimise`] searches: a function of the log-parameters θ with its gradient and a
/// positive semi-definite curvature to step with (the Fisher information of a likelihood, or
/// JᵀJ of a least-squares problem).
pub trait Objective: Sync {
    /// θ of the spec's own values (the centre of the starts and of the bounds).
    fn start(&self) -> Vec<f64>;
    /// The value at θ, with the gradient and the curvature when `derivatives`; `None` where
    /// θ makes no valid model.
    fn evaluate(&self, theta: &[f64], derivatives: bool) -> Option<Evaluation>;
}

impl Objective for Problem<'_> {
    fn start(&self) -> Vec<f64> {
        Problem::start(self)
    }

    fn evaluate(&self, theta: &[f64], derivatives: bool) -> Option<Evaluation> {
        Problem::evaluate(self, theta, derivatives)
    }
}

/// The best optimum over the starts.
#[derive(Clone, Debug, PartialEq)]
pub struct Minimum {
    /// θ̂.
    pub theta: Vec<f64>,
    /// The objective at θ̂.
    pub objective: f64,
    /// The start it came from.
    pub best_start: usize,
    /// Whether that start's search met the tolerance.
    pub converged: bool,
    /// Per element: whether θ̂ sits on a bound of the search.
    pub at_bound: Vec<bool>,
    /// Every iteration of every start.
    pub trace: Vec<TraceRow>,
}

/// z_{0.975}: the 95 % two-sided normal quantile.
pub const Z95: f64 = 1.959_963_984_540_054;

/// The reciprocal condition number below which a direction of the observed information is
/// called unidentified: an eigenvalue λ ≤ `RCOND` · λ_max. With λ in log-parameters, a
/// direction 10⁸ times less informed than the best one is numerically flat.
pub const RCOND: f64 = 1e-8;

/// The absolute floor of the information in a direction (log-parameters): λ ≤ `MIN_INFO` is
/// a standard error of at least 1000 in ln units, no information at all.
pub const MIN_INFO: f64 = 1e-6;

/// An element takes part in an unidentified direction when its component in the unit
/// eigenvector is at least this large.
pub const DIRECTION_SHARE: f64 = 0.1;

/// The step of the central differences of the score that give the observed information
/// (in ln units: a relative change of 10⁻⁴ of each element).
pub const HESSIAN_STEP: f64 = 1e-4;

/// The search's settings.
#[derive(Clone, Debug, PartialEq)]
pub struct SearchSettings {
    /// Iterations per start at most.
    pub max_iterations: usize,
    /// The search stops when the Newton decrement ½ gᵀ I⁻¹ g (the predicted decrease of −ln L)
    /// is below this.
    pub tolerance: f64,
    /// The starts, as multipliers of every tuned element's spec value (the first is 1: the
    /// spec itself).
    pub starts: Vec<f64>,
    /// Each θ is kept within ln(`bound`) of its spec value.
    pub bound: f64,
}

impl Default for SearchSettings {
    fn default() -> Self {
        SearchSettings {
            max_iterations: 200,
            tolerance: 1e-9,
            starts: vec![1.0, 0.1, 10.0],
            bound: 1e6,
        }
    }
}

/// One iteration of the search (`tune_trace.parquet`).
#[derive(Clone, Debug, PartialEq)]
pub struct TraceRow {
    /// Which start (index into [`SearchSettings::starts`]).
    pub start: usize,
    /// Iteration (0: the start itself).
    pub iteration: usize,
    /// The objective (−ln L for `ml`, ½|ḡ|² of the conditions for `truth`).
    pub objective: f64,
    /// The elements' values (natural scale).
    pub parameters: Vec<f64>,
}

/// An unidentified direction of the observed information.
#[derive(Clone, Debug, PartialEq)]
pub struct FlatDirection {
    /// Its eigenvalue.
    pub eigenvalue: f64,
    /// The largest eigenvalue, for the ratio.
    pub largest: f64,
    /// The unit eigenvector's components (one per element, in ln units).
    pub components: Vec<f64>,
}

/// The estimate of every element, with its intervals.
#[derive(Clone, Debug, PartialEq)]
pub struct Estimate {
    /// θ̂ (ln of each element).
    pub theta: Vec<f64>,
    /// The objective at θ̂ (−ln L for `ml`).
    pub objective: f64,
    /// The start the best optimum came from.
    pub best_start: usize,
    /// Whether that start's search met the tolerance (else it ran out of iterations or of
    /// damping).
    pub converged: bool,
    /// The curvature the identifiability is judged on, in θ at θ̂: the observed information
    /// (the Hessian of −ln L) for `ml`, JᵀJ of the conditions' Jacobian for `truth`.
    pub observed: DMatrix<f64>,
    /// Per element: the standard error of θ̂ (ln units); `None` when unidentified.
    pub se_log: Vec<Option<f64>>,
    /// Per element: whether it is identified.
    pub identifiable: Vec<bool>,
    /// Per element: whether θ̂ sits on a bound of the search.
    pub at_bound: Vec<bool>,
    /// The unidentified directions.
    pub flat: Vec<FlatDirection>,
    /// Every iteration of every start.
    pub trace: Vec<TraceRow>,
}

impl Estimate {
    /// The iterations the best start's search took.
    pub fn best_start_iterations(&self) -> usize {
        (self.trace.iter())
            .filter(|r| r.start == self.best_start)
            .map(|r| r.iteration)
            .max()
            .unwrap_or(0)
    }

    /// Element `i` on the natural scale: (estimate, standard error by the delta method, 95 %
    /// interval mapped back from ln space, so it stays positive).
    pub fn natural(&self, i: usize) -> (f64, Option<f64>, Option<(f64, f64)>) {
        let t = self.theta[i];
        let v = t.exp();
        match self.se_log[i] {
            Some(s) => (
                v,
                Some(v * s),
                Some(((t - Z95 * s).exp(), (t + Z95 * s).exp())),
            ),
            None => (v, None, None),
        }
    }
}

/// Why the search could not run.
#[derive(Clone, Debug, PartialEq)]
pub struct SearchError(pub String);

/// Maximises the likelihood of `problem` from every start of `settings`, reporting each
/// iteration to `on_iteration`, and forms the intervals at the best optimum.
pub fn estimate(
    problem: &Problem<'_>,
    settings: &SearchSettings,
    on_iteration: &(dyn Fn(&TraceRow) + Sync),
) -> Result<Estimate, SearchError> {
    let Minimum {
        theta,
        objective,
        best_start,
        converged,
        at_bound,
        trace,
    } = minimise(problem, settings, on_iteration)?;
    let observed = observed_information(problem, &theta)?;
    let (se_log, identifiable, flat) = intervals(&observed);
    Ok(Estimate {
        theta,
        objective,
        best_start,
        converged,
        observed,
        se_log,
        identifiable,
        at_bound,
        flat,
        trace,
    })
}

/// Minimises `objective` from every start of `settings` (each θ within ln(`bound`) of the
/// spec's value), reporting each iteration to `on_iteration`; the best optimum wins, ties to
/// the earlier start.
pub fn minimise<O: Objective + ?Sized>(
    objective: &O,
    settings: &SearchSettings,
    on_iteration: &(dyn Fn(&TraceRow) + Sync),
) -> Result<Minimum, SearchError> {
    let centre = objective.start();
    let half = settings.bound.ln();
    let lower: Vec<f64> = centre.iter().map(|c| c - half).collect();
    let upper: Vec<f64> = centre.iter().map(|c| c + half).collect();
    // The starts run in parallel; each keeps its own trace, and both the traces and the
    // choice of the best are taken in start order, so neither depends on the threads.
    let searched: Vec<_> = settings
        .starts
        .par_iter()
        .enumerate()
        .map(|(si, &mult)| {
            let theta0: Vec<f64> = centre.iter().map(|c| c + mult.ln()).collect();
            let mut trace = Vec::new();
            let result = search(
                objective,
                settings,
                si,
                theta0,
                &lower,
                &upper,
                &mut trace,
                on_iteration,
            );
            (result, trace)
        })
        .collect();
    let mut trace = Vec::new();
    let mut best: Option<(Vec<f64>, f64, usize, bool)> = None;
    let mut first_error = None;
    for (si, (result, rows)) in searched.into_iter().enumerate() {
        trace.extend(rows);
        match result {
            Ok((theta, value, converged)) => {
                if best.as_ref().is_none_or(|b| value < b.1) {
                    best = Some((theta, value, si, converged));
                }
            }
            Err(e) => {
                first_error.get_or_insert(e);
            }
        }
    }
    let Some((theta, value, best_start, converged)) = best else {
        return Err(first_error.unwrap_or(SearchError("no start to search from".into())));
    };
    let at_bound = theta
        .iter()
        .zip(lower.iter().zip(&upper))
        .map(|(t, (l, u))| *t <= *l || *t >= *u)
        .collect();
    Ok(Minimum {
        theta,
        objective: value,
        best_start,
        converged,
        at_bound,
        trace,
    })
}

/// One start's Levenberg–Marquardt search: (θ̂, the objective, converged).
#[allow(clippy::too_many_arguments)]
fn search<O: Objective + ?Sized>(
    problem: &O,
    settings: &SearchSettings,
    start: usize,
    theta0: Vec<f64>,
    lower: &[f64],
    upper: &[f64],
    trace: &mut Vec<TraceRow>,
    on_iteration: &(dyn Fn(&TraceRow) + Sync),
) -> Result<(Vec<f64>, f64, bool), SearchError> {
    let m = theta0.len();
    let mut theta: Vec<f64> = theta0
        .iter()
        .enumerate()
        .map(|(i, t)| t.clamp(lower[i], upper[i]))
        .collect();
    let mut ev = problem.evaluate(&theta, true).ok_or_else(|| {
        SearchError(format!(
            "start {start}: the objective cannot be evaluated there (an innovation covariance S is not positive definite)"
        ))
    })?;
    let mut push = |iteration: usize, value: f64, theta: &[f64]| {
        let row = TraceRow {
            start,
            iteration,
            objective: value,
            parameters: theta.iter().map(|t| t.exp()).collect(),
        };
        on_iteration(&row);
        trace.push(row);
    };
    push(0, ev.value, &theta);
    let mut lambda = 1e-3;
    let mut converged = false;
    let mut iteration = 0;
    while iteration < settings.max_iterations {
        let Evaluation {
            value,
            ref gradient,
            ref information,
        } = ev;
        // The Newton decrement: the decrease a full scoring step predicts.
        if let Some(chol) = information.clone().cholesky() {
            let g = nalgebra::DVector::from_column_slice(gradient);
            let decrement = 0.5 * g.dot(&chol.solve(&g));
            if decrement < settings.tolerance {
                converged = true;
                break;
            }
        }
        let mut damped = information.clone();
        for i in 0..m {
            damped[(i, i)] += lambda * information[(i, i)].max(1e-12);
        }
        let step = damped
            .cholesky()
            .map(|c| c.solve(&-nalgebra::DVector::from_column_slice(gradient)));
        let Some(step) = step else {
            lambda *= 10.0;
            if lambda > 1e12 {
                break;
            }
            continue;
        };
        let trial: Vec<f64> = (0..m)
            .map(|i| (theta[i] + step[i]).clamp(lower[i], upper[i]))
            .collect();
        match problem.evaluate(&trial, true) {
            Some(next) if next.value < value => {
                iteration += 1;
                let small = (value - next.value) <= 1e-13 * value.abs().max(1.0);
                theta = trial;
                ev = next;
                push(iteration, ev.value, &theta);
                lambda = (lambda / 10.0).max(1e-12);
                if small {
                    converged = true;
                    break;
                }
            }
            _ => {
                lambda *= 10.0;
                if lambda > 1e12 {
                    // No step decreases −ln L: a minimum to rounding, or a bound.
                    converged = true;
                    break;
                }
            }
        }
    }
    Ok((theta, ev.value, converged))
}

/// The Hessian of −ln L in θ at `theta` by central differences of the analytic score,
/// symmetrised (the 2m scores run in parallel; each is the same sum in the same order).
pub fn observed_information(
    problem: &Problem<'_>,
    theta: &[f64],
) -> Result<DMatrix<f64>, SearchError> {
    let m = theta.len();
    let h = HESSIAN_STEP;
    let grads: Vec<Option<Vec<f64>>> = (0..2 * m)
        .into_par_iter()
        .map(|c| {
            let mut t = theta.to_vec();
            t[c / 2] += if c % 2 == 0 { h } else { -h };
            problem.evaluate(&t, true).map(|e| e.gradient)
        })
        .collect();
    let mut hess = DMatrix::zeros(m, m);
    for j in 0..m {
        let (plus, minus) = match (&grads[2 * j], &grads[2 * j + 1]) {
            (Some(p), Some(q)) => (p, q),
            _ => {
                return Err(SearchError(
                    "the likelihood cannot be evaluated next to the optimum (S not positive definite)".into(),
                ));
            }
        };
        for i in 0..m {
            hess[(i, j)] = (plus[i] - minus[i]) / (2.0 * h);
        }
    }
    Ok(0.5 * (&hess + hess.transpose()))
}

type Intervals = (Vec<Option<f64>>, Vec<bool>, Vec<FlatDirection>);

/// Standard errors in θ from the inverse observed information, and the unidentified
/// directions (eigenvalues at or below [`RCOND`] · λ_max or [`MIN_INFO`]); an element with a
/// share of at least [`DIRECTION_SHARE`] in such a direction gets no standard error. The
/// others' come from the inverse over the identified directions.
pub fn intervals(observed: &DMatrix<f64>) -> Intervals {
    let m = observed.nrows();
    let eig = SymmetricEigen::new(observed.clone());
    let largest = eig.eigenvalues.iter().copied().fold(0.0, f64::max);
    let mut identifiable = vec![true; m];
    let mut flat = Vec::new();
    let mut cov = DMatrix::zeros(m, m);
    let mut order: Vec<usize> = (0..m).collect();
    order.sort_by(|&a, &b| eig.eigenvalues[a].total_cmp(&eig.eigenvalues[b]));
    for k in order {
        let l = eig.eigenvalues[k];
        let v = eig.eigenvectors.column(k);
        if !(l > RCOND * largest && l > MIN_INFO) {
            // A sign fixed by the largest component, so the direction prints the same way.
            let big = (0..m)
                .max_by(|&a, &b| v[a].abs().total_cmp(&v[b].abs()))
                .unwrap_or(0);
            let sign = if v[big] < 0.0 { -1.0 } else { 1.0 };
            let components: Vec<f64> = v.iter().map(|c| sign * c).collect();
            for (i, c) in components.iter().enumerate() {
                if c.abs() >= DIRECTION_SHARE {
                    identifiable[i] = false;
                }
            }
            flat.push(FlatDirection {
                eigenvalue: l,
                largest,
                components,
            });
        } else {
            cov += (v * v.transpose()) / l;
        }
    }
    let se = (0..m)
        .map(|i| identifiable[i].then(|| cov[(i, i)].sqrt()))
        .collect();
    (se, identifiable, flat)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_flat_direction_is_named_and_its_elements_get_no_interval() {
        // Information about a + b only (a rank-one matrix) and about c alone.
        let h = DMatrix::from_row_slice(3, 3, &[4.0, 4.0, 0.0, 4.0, 4.0, 0.0, 0.0, 0.0, 9.0]);
        let (se, ok, flat) = intervals(&h);
        assert_eq!(ok, vec![false, false, true]);
        assert_eq!(flat.len(), 1);
        let c = &flat[0].components;
        assert!((c[0].abs() - 0.5f64.sqrt()).abs() < 1e-12 && (c[0] + c[1]).abs() < 1e-12);
        assert!(se[0].is_none() && se[1].is_none());
        assert!((se[2].unwrap() - 1.0 / 3.0).abs() < 1e-12);
        // A well-conditioned matrix: the standard errors are the inverse's diagonal.
        let h = DMatrix::from_row_slice(2, 2, &[4.0, 1.0, 1.0, 2.0]);
        let (se, ok, flat) = intervals(&h);
        let inv = h.try_inverse().unwrap();
        assert!(ok.iter().all(|&b| b) && flat.is_empty());
        for i in 0..2 {
            assert!((se[i].unwrap() - inv[(i, i)].sqrt()).abs() < 1e-12);
        }
    }
}
