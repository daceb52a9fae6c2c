//! The identifying conditions of `kfmc tune --method truth`, evaluated on simulated runs whose
//! truth is known, and the M-estimator sandwich of their root.
//!
//! For candidate log-parameters θ (θ_i = ln of a diagonal element of Q or R, every other
//! element fixed), a Kalman filter with the model's F, G, H and the candidate (Q, R) runs over
//! each run r from the run's own prior, and the run's condition vector g_r(θ) has one entry per
//! tuned element:
//!
//! * `consistency`: for `Q[i,i]`, the run's mean over steps 1..K of e_i²/P_ii − 1 (e = x̂_k|k −
//!   x_k, P = P_k|k); for `R[j,j]`, the mean over the steps where component j reported of
//!   ν_j²/S_jj − 1. Both vanish in expectation at the true Q and R when the filter's model is
//!   the world's and the prior is the distribution of x_0 (e ~ N(0, P), ν ~ N(0, S) at every
//!   step).
//! * `mse`: the gradient in θ of the run's estimation MSE, Σ_i mean_k e_i² / m_i (m_i the mean
//!   over runs of state i's MSE at the spec's values, so every state counts equally whatever
//!   its units), by central differences.
//!
//! θ̂ solves ḡ(θ) = (1/N) Σ_r g_r(θ) = 0 in the least-squares sense (Levenberg–Marquardt on
//! ½|ḡ|² with the curvature JᵀJ, J = ∂ḡ/∂θ by central differences; for `mse` the search
//! minimises the mean MSE itself with the gradient ḡ and |J| as its curvature). Every
//! candidate sees the same runs (common random numbers), so ḡ is a smooth function of θ and
//! its differences are not noise. The covariance of θ̂ is the sandwich J⁻¹ V J⁻ᵀ / N, V the
//! covariance of the g_r across runs (an M-estimator's: the runs are independent, the steps
//! within a run are not, so the runs are the units).

use nalgebra::{DMatrix, DVector, SymmetricEigen};
use rayon::prelude::*;

use super::estimate::{Objective, RCOND};
use super::likelihood::{Evaluation, LinearModel, Parameter, Problem, Series, symmetrise};
use crate::experiment::tune_spec::NoiseMatrix;

/// The step (ln units) of the central differences of ḡ that give J.
pub const JACOBIAN_STEP: f64 = 1e-4;

/// The step (ln units) of the central differences of a run's MSE that give the `mse`
/// conditions.
pub const MSE_STEP: f64 = 1e-3;

/// What the conditions identify.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum TruthObjective {
    /// E[e_i²/P_ii] = 1 per tuned state, E[ν_j²/S_jj] = 1 per tuned measurement component.
    Consistency,
    /// The least estimation MSE against truth (cannot fix an absolute scale of Q and R).
    Mse,
}

impl TruthObjective {
    /// The name in flags and messages.
    pub fn name(self) -> &'static str {
        match self {
            TruthObjective::Consistency => "consistency",
            TruthObjective::Mse => "mse",
        }
    }
}

/// One simulated run: its data and its true states x_0..x_K (`n` per step).
#[derive(Clone, Debug, PartialEq)]
pub struct TruthRun {
    /// The prior, inputs and measurements.
    pub series: Series,
    /// x_0..x_K, row by row.
    pub truth: Vec<f64>,
}

/// What a filter run with a candidate (Q, R) gives of one run.
#[derive(Clone, Debug, PartialEq)]
pub struct RunStats {
    /// Per state: the mean over steps 1..K of e_i²/P_ii.
    pub nees: Vec<f64>,
    /// Per state: the mean over steps 1..K of e_i².
    pub mse: Vec<f64>,
    /// Per measurement component: the mean of ν_j²/S_jj over the steps it reported (NaN when
    /// it never did).
    pub nis: Vec<f64>,
}

/// Runs the Kalman filter of `model` with (`q`, `r`) over one run and averages its
/// normalised errors and innovations; `None` when some S_k is not positive definite.
pub fn run_stats(
    model: &LinearModel,
    q: &DMatrix<f64>,
    r: &DMatrix<f64>,
    run: &TruthRun,
) -> Option<RunStats> {
    let LinearModel { f, g, h, .. } = model;
    let s = &run.series;
    let (n, p, nu) = (f.nrows(), h.nrows(), g.ncols());
    let steps = s.z.len() / p.max(1);
    let ft = f.transpose();
    let mut x = s.x0.clone();
    let mut pm = s.p0.clone();
    let (mut nees, mut mse) = (vec![0.0; n], vec![0.0; n]);
    let (mut nis, mut reports) = (vec![0.0; p], vec![0usize; p]);
    let mut avail: Vec<usize> = Vec::with_capacity(p);
    for k in 1..steps {
        let u = DVector::from_column_slice(&s.u[k * nu..(k + 1) * nu]);
        let xp = f * &x + g * u;
        let mut pp = f * &pm * &ft + q;
        symmetrise(&mut pp);
        avail.clear();
        avail.extend((0..p).filter(|&j| s.z[k * p + j].is_finite()));
        if avail.is_empty() {
            (x, pm) = (xp, pp);
        } else {
            let ha = h.select_rows(avail.iter());
            let hat = ha.transpose();
            let ra = DMatrix::from_fn(avail.len(), avail.len(), |a, b| r[(avail[a], avail[b])]);
            let za = DVector::from_iterator(avail.len(), avail.iter().map(|&j| s.z[k * p + j]));
            let innovation = za - &ha * &xp;
            let pht = &pp * &hat;
            let mut sm = &ha * &pht + &ra;
            symmetrise(&mut sm);
            let chol = sm.clone().cholesky()?;
            for (a, &j) in avail.iter().enumerate() {
                nis[j] += innovation[a] * innovation[a] / sm[(a, a)];
                reports[j] += 1;
            }
            let gain = chol.solve(&pht.transpose()).transpose();
            // Joseph form, as kfmc's filters update: stays positive semi-definite.
            let a = DMatrix::<f64>::identity(n, n) - &gain * &ha;
            let mut pnew = &a * &pp * a.transpose() + &gain * &ra * gain.transpose();
            symmetrise(&mut pnew);
            x = &xp + &gain * &innovation;
            pm = pnew;
        }
        for i in 0..n {
            let e = x[i] - run.truth[k * n + i];
            nees[i] += e * e / pm[(i, i)];
            mse[i] += e * e;
        }
    }
    let k = steps.saturating_sub(1).max(1) as f64;
    Some(RunStats {
        nees: nees.iter().map(|v| v / k).collect(),
        mse: mse.iter().map(|v| v / k).collect(),
        nis: nis
            .iter()
            .zip(&reports)
            .map(|(v, &c)| if c > 0 { v / c as f64 } else { f64::NAN })
            .collect(),
    })
}

/// The conditions of a set of runs in the tuned parameters.
#[derive(Clone, Debug)]
pub struct Conditions<'a> {
    /// The model (its Q and R hold the untuned elements and the start of the tuned ones).
    pub model: &'a LinearModel,
    /// The runs (independent).
    pub runs: &'a [TruthRun],
    /// The tuned diagonal elements.
    pub params: &'a [Parameter],
    /// Which conditions.
    pub objective: TruthObjective,
    /// Per state: the MSE that normalises it in the `mse` objective (the mean over runs at
    /// the spec's values); unused by `consistency`.
    pub reference: Vec<f64>,
}

impl<'a> Conditions<'a> {
    /// The conditions of `runs`, with the `mse` normalisation taken at the spec's values;
    /// `None` when the spec's values make no valid filter.
    pub fn new(
        model: &'a LinearModel,
        runs: &'a [TruthRun],
        params: &'a [Parameter],
        objective: TruthObjective,
    ) -> Option<Self> {
        let mut c = Conditions {
            model,
            runs,
            params,
            objective,
            reference: Vec::new(),
        };
        if objective == TruthObjective::Mse {
            let stats = c.stats(&c.likelihood().start())?;
            let n = model.f.nrows();
            c.reference = (0..n)
                .map(|i| {
                    let m = stats.iter().map(|s| s.mse[i]).sum::<f64>() / stats.len() as f64;
                    if m > 0.0 && m.is_finite() { m } else { 1.0 }
                })
                .collect();
        }
        Some(c)
    }

    /// The same parameters as a likelihood problem, for its start and covariances.
    fn likelihood(&self) -> Problem<'_> {
        Problem {
            model: self.model,
            series: &[],
            params: self.params,
        }
    }

    /// Q and R at θ.
    pub fn covariances(&self, theta: &[f64]) -> (DMatrix<f64>, DMatrix<f64>) {
        self.likelihood().covariances(theta)
    }

    /// Every run's statistics at θ, in run order (evaluated in parallel on the current pool).
    fn stats(&self, theta: &[f64]) -> Option<Vec<RunStats>> {
        let (q, r) = self.covariances(theta);
        let out: Vec<Option<RunStats>> = self
            .runs
            .par_iter()
            .map(|run| run_stats(self.model, &q, &r, run))
            .collect();
        out.into_iter().collect()
    }

    /// A run's normalised MSE (the `mse` objective of one run).
    fn run_mse(&self, s: &RunStats) -> f64 {
        s.mse.iter().zip(&self.reference).map(|(v, m)| v / m).sum()
    }

    /// Every run's condition vector g_r(θ), in run order; `None` where the filter fails or a
    /// condition is not finite.
    pub fn per_run(&self, theta: &[f64]) -> Option<Vec<DVector<f64>>> {
        let m = self.params.len();
        let out: Vec<DVector<f64>> = match self.objective {
            TruthObjective::Consistency => self
                .stats(theta)?
                .iter()
                .map(|s| {
                    DVector::from_iterator(
                        m,
                        self.params.iter().map(|p| match p.matrix {
                            NoiseMatrix::Q => s.nees[p.index] - 1.0,
                            NoiseMatrix::R => s.nis[p.index] - 1.0,
                        }),
                    )
                })
                .collect(),
            TruthObjective::Mse => {
                let mut g = vec![DVector::zeros(m); self.runs.len()];
                for k in 0..m {
                    let mut t = theta.to_vec();
                    t[k] = theta[k] + MSE_STEP;
                    let plus = self.stats(&t)?;
                    t[k] = theta[k] - MSE_STEP;
                    let minus = self.stats(&t)?;
                    for (r, (a, b)) in plus.iter().zip(&minus).enumerate() {
                        g[r][k] = (self.run_mse(a) - self.run_mse(b)) / (2.0 * MSE_STEP);
                    }
                }
                g
            }
        };
        out.iter()
            .all(|g| g.iter().all(|v| v.is_finite()))
            .then_some(out)
    }

    /// ḡ(θ): the mean of the runs' condition vectors (summed in run order).
    pub fn mean(&self, theta: &[f64]) -> Option<DVector<f64>> {
        let per_run = self.per_run(theta)?;
        Some(mean_of(&per_run, self.params.len()))
    }

    /// J = ∂ḡ/∂θ at θ by central differences (step [`JACOBIAN_STEP`]).
    pub fn jacobian(&self, theta: &[f64]) -> Option<DMatrix<f64>> {
        let m = theta.len();
        let mut j = DMatrix::zeros(m, m);
        for k in 0..m {
            let mut t = theta.to_vec();
            t[k] = theta[k] + JACOBIAN_STEP;
            let plus = self.mean(&t)?;
            t[k] = theta[k] - JACOBIAN_STEP;
            let minus = self.mean(&t)?;
            j.set_column(k, &((plus - minus) / (2.0 * JACOBIAN_STEP)));
        }
        Some(j)
    }

    /// The mean normalised MSE over the runs at θ (the `mse` objective's value).
    fn mean_mse(&self, theta: &[f64]) -> Option<f64> {
        let stats = self.stats(theta)?;
        Some(stats.iter().map(|s| self.run_mse(s)).sum::<f64>() / stats.len() as f64)
    }
}

/// The mean of vectors of length `m`, summed in order.
fn mean_of(vectors: &[DVector<f64>], m: usize) -> DVector<f64> {
    let mut sum = DVector::zeros(m);
    for v in vectors {
        sum += v;
    }
    sum / vectors.len().max(1) as f64
}

impl Objective for Conditions<'_> {
    fn start(&self) -> Vec<f64> {
        self.likelihood().start()
    }

    fn evaluate(&self, theta: &[f64], derivatives: bool) -> Option<Evaluation> {
        match self.objective {
            TruthObjective::Consistency => {
                let g = self.mean(theta)?;
                let value = 0.5 * g.norm_squared();
                if !derivatives {
                    return Some(Evaluation {
                        value,
                        gradient: Vec::new(),
                        information: DMatrix::zeros(0, 0),
                    });
                }
                let j = self.jacobian(theta)?;
                Some(Evaluation {
                    value,
                    gradient: (j.transpose() * &g).iter().copied().collect(),
                    information: j.transpose() * &j,
                })
            }
            TruthObjective::Mse => {
                let value = self.mean_mse(theta)?;
                if !derivatives {
                    return Some(Evaluation {
                        value,
                        gradient: Vec::new(),
                        information: DMatrix::zeros(0, 0),
                    });
                }
                let g = self.mean(theta)?;
                let h = self.jacobian(theta)?;
                Some(Evaluation {
                    value,
                    gradient: g.iter().copied().collect(),
                    information: absolute(&(0.5 * (&h + h.transpose()))),
                })
            }
        }
    }
}

/// |H|: the symmetric matrix with H's eigenvectors and the absolute values of its eigenvalues
/// (a positive semi-definite curvature for a Newton step away from a minimum).
fn absolute(h: &DMatrix<f64>) -> DMatrix<f64> {
    let eig = SymmetricEigen::new(h.clone());
    let d = DMatrix::from_diagonal(&eig.eigenvalues.map(f64::abs));
    &eig.eigenvectors * d * eig.eigenvectors.transpose()
}

/// The sandwich covariance of θ̂: J⁺ V J⁺ᵀ / N, with V the covariance across the N runs of
/// their condition vectors and J⁺ the pseudo-inverse of J over its identified directions
/// (singular values σ with σ² > [`RCOND`] σ²_max and σ² > `min_info`: the thresholds the
/// identifiability report applies to JᵀJ).
pub fn sandwich(per_run: &[DVector<f64>], j: &DMatrix<f64>, min_info: f64) -> DMatrix<f64> {
    let m = j.ncols();
    let n = per_run.len();
    let mean = mean_of(per_run, m);
    let mut v = DMatrix::zeros(m, m);
    for g in per_run {
        let d = g - &mean;
        v += &d * d.transpose();
    }
    v /= (n.max(2) - 1) as f64;
    let svd = j.clone().svd(true, true);
    let largest = svd.singular_values.iter().copied().fold(0.0, f64::max);
    let eps = (RCOND.sqrt() * largest).max(min_info.sqrt());
    let pinv = svd
        .pseudo_inverse(eps)
        .unwrap_or_else(|_| DMatrix::zeros(m, m));
    &pinv * v * pinv.transpose() / n.max(1) as f64
}
