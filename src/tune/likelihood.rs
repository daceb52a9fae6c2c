//! The innovations likelihood of a linear-Gaussian state-space model, with its score and its
//! Fisher information in the tuned log-parameters.
//!
//! x_k = F x_{k−1} + G u_k + w_k, z_k = H x_k + v_k, w ~ N(0, Q), v ~ N(0, R), prior
//! x_0 ~ N(x̂_0, P_0). A Kalman filter turns the measurements into innovations ν_k with
//! covariances S_k, and by the prediction-error decomposition
//!
//! −ln L = ½ Σ_k [ln det S_k + ν_kᵀ S_k⁻¹ ν_k + p_k ln 2π],
//!
//! exactly, where p_k is the number of components that reported at step k (only those enter
//! ν_k and S_k: a multi-rate sensor set is honoured). Step 0 is the prior and has no
//! measurement, as in `measurements.parquet`.
//!
//! The tuned parameters are θ_i = ln c_i of diagonal elements c_i of Q or R; every other
//! element keeps its value. The score ∂(−ln L)/∂θ comes from the sensitivity recursion (the
//! derivatives of x̂, P through the filter, one set per parameter), and the Fisher information
//! ½ tr(S⁻¹ ∂S_i S⁻¹ ∂S_j) + ∂ν_iᵀ S⁻¹ ∂ν_j (summed over steps) from the same pass: it is
//! the Gauss–Newton matrix the optimiser steps with.
//!
//! This is a filter loop of its own, at runtime sizes (nalgebra's `DMatrix`), not kfmc's
//! step loop: the likelihood needs every innovation at every parameter value, the derivatives
//! need the filter's internals, and neither belongs in a filter that scores estimates.

use nalgebra::{DMatrix, DVector};
use rayon::prelude::*;

use crate::experiment::tune_spec::NoiseMatrix;

/// F, G, H and the Q and R whose untuned elements stay fixed.
#[derive(Clone, Debug, PartialEq)]
pub struct LinearModel {
    /// F (n × n).
    pub f: DMatrix<f64>,
    /// G (n × inputs).
    pub g: DMatrix<f64>,
    /// H (p × n).
    pub h: DMatrix<f64>,
    /// Q (n × n): the values of the untuned elements, and the start of the tuned ones.
    pub q: DMatrix<f64>,
    /// R (p × p), likewise.
    pub r: DMatrix<f64>,
}

/// One run's data: its prior, inputs and measurements.
#[derive(Clone, Debug, PartialEq)]
pub struct Series {
    /// x̂_0.
    pub x0: DVector<f64>,
    /// P_0.
    pub p0: DMatrix<f64>,
    /// u_0..u_K, `inputs` per step, row by row.
    pub u: Vec<f64>,
    /// z_0..z_K, `p` per step, NaN where a component did not report (row 0 is not read).
    pub z: Vec<f64>,
}

impl Series {
    /// The number of scalar measurements after step 0 (the non-NaN entries).
    pub fn measurements(&self, p: usize) -> usize {
        self.z.iter().skip(p).filter(|v| v.is_finite()).count()
    }
}

/// One tuned parameter: θ = ln of the diagonal element `index` of `matrix`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Parameter {
    /// Q or R.
    pub matrix: NoiseMatrix,
    /// The diagonal position.
    pub index: usize,
}

/// −ln L at a point, with (when asked) its gradient and Fisher information in θ.
#[derive(Clone, Debug, PartialEq)]
pub struct Evaluation {
    /// −ln L.
    pub value: f64,
    /// ∂(−ln L)/∂θ (empty without derivatives).
    pub gradient: Vec<f64>,
    /// The Fisher information in θ (0 × 0 without derivatives).
    pub information: DMatrix<f64>,
}

impl Evaluation {
    fn zero(m: usize, derivatives: bool) -> Self {
        let m = if derivatives { m } else { 0 };
        Evaluation {
            value: 0.0,
            gradient: vec![0.0; m],
            information: DMatrix::zeros(m, m),
        }
    }

    fn add(&mut self, other: &Evaluation) {
        self.value += other.value;
        for (a, b) in self.gradient.iter_mut().zip(&other.gradient) {
            *a += b;
        }
        self.information += &other.information;
    }
}

/// The likelihood of a model's runs in the parameters `params`.
#[derive(Clone, Copy, Debug)]
pub struct Problem<'a> {
    /// The model.
    pub model: &'a LinearModel,
    /// The runs (independent: their log-likelihoods add).
    pub series: &'a [Series],
    /// The tuned diagonal elements.
    pub params: &'a [Parameter],
}

const LN_2PI: f64 = 1.837_877_066_409_345_3;

impl Problem<'_> {
    /// θ of the model's own values (the start).
    pub fn start(&self) -> Vec<f64> {
        self.params
            .iter()
            .map(|p| match p.matrix {
                NoiseMatrix::Q => self.model.q[(p.index, p.index)].ln(),
                NoiseMatrix::R => self.model.r[(p.index, p.index)].ln(),
            })
            .collect()
    }

    /// Q and R at θ.
    pub fn covariances(&self, theta: &[f64]) -> (DMatrix<f64>, DMatrix<f64>) {
        let (mut q, mut r) = (self.model.q.clone(), self.model.r.clone());
        for (p, t) in self.params.iter().zip(theta) {
            let m = match p.matrix {
                NoiseMatrix::Q => &mut q,
                NoiseMatrix::R => &mut r,
            };
            m[(p.index, p.index)] = t.exp();
        }
        (q, r)
    }

    /// −ln L at θ (and its derivatives when `derivatives`), summed over the runs in run order
    /// (the runs are evaluated in parallel on the current rayon pool; the sum's order, and so
    /// its bits, do not depend on the threads). `None` where some S_k is not positive
    /// definite (the parameters make no valid model).
    pub fn evaluate(&self, theta: &[f64], derivatives: bool) -> Option<Evaluation> {
        let (q, r) = self.covariances(theta);
        let scale: Vec<f64> = theta.iter().map(|t| t.exp()).collect();
        let parts: Vec<Option<Evaluation>> = self
            .series
            .par_iter()
            .map(|s| self.series_likelihood(s, &q, &r, &scale, derivatives))
            .collect();
        let mut total = Evaluation::zero(self.params.len(), derivatives);
        for part in parts {
            total.add(&part?);
        }
        Some(total)
    }

    /// One run's −ln L (see the module docs for the recursion).
    fn series_likelihood(
        &self,
        s: &Series,
        q: &DMatrix<f64>,
        r: &DMatrix<f64>,
        scale: &[f64],
        derivatives: bool,
    ) -> Option<Evaluation> {
        let LinearModel { f, g, h, .. } = self.model;
        let (n, p, nu) = (f.nrows(), h.nrows(), g.ncols());
        let m = if derivatives { self.params.len() } else { 0 };
        let steps = s.z.len() / p.max(1);
        let ft = f.transpose();
        let mut out = Evaluation::zero(self.params.len(), derivatives);
        let mut x = s.x0.clone();
        let mut pm = s.p0.clone();
        // The sensitivities ∂x̂/∂θ_i and ∂P/∂θ_i: zero at the prior, which does not depend on θ.
        let mut dx: Vec<DVector<f64>> = vec![DVector::zeros(n); m];
        let mut dp: Vec<DMatrix<f64>> = vec![DMatrix::zeros(n, n); m];
        let mut avail: Vec<usize> = Vec::with_capacity(p);
        for k in 1..steps {
            // Predict.
            let u = DVector::from_column_slice(&s.u[k * nu..(k + 1) * nu]);
            let xp = f * &x + g * u;
            let mut pp = f * &pm * &ft + q;
            symmetrise(&mut pp);
            let mut dxp: Vec<DVector<f64>> = dx.iter().map(|d| f * d).collect();
            let mut dpp: Vec<DMatrix<f64>> = dp.iter().map(|d| f * d * &ft).collect();
            for (i, prm) in self.params.iter().enumerate().take(m) {
                if prm.matrix == NoiseMatrix::Q {
                    dpp[i][(prm.index, prm.index)] += scale[i];
                }
            }
            avail.clear();
            avail.extend((0..p).filter(|&j| s.z[k * p + j].is_finite()));
            if avail.is_empty() {
                (x, pm) = (xp, pp);
                std::mem::swap(&mut dx, &mut dxp);
                std::mem::swap(&mut dp, &mut dpp);
                continue;
            }
            let pa = avail.len();
            let ha = h.select_rows(avail.iter());
            let hat = ha.transpose();
            let ra = DMatrix::from_fn(pa, pa, |a, b| r[(avail[a], avail[b])]);
            let za = DVector::from_iterator(pa, avail.iter().map(|&j| s.z[k * p + j]));
            let nu_k = za - &ha * &xp;
            let pht = &pp * &hat;
            let mut sm = &ha * &pht + &ra;
            symmetrise(&mut sm);
            let chol = sm.clone().cholesky()?;
            let ln_det: f64 = 2.0
                * chol
                    .l_dirty()
                    .diagonal()
                    .iter()
                    .map(|d| d.ln())
                    .sum::<f64>();
            let s_nu = chol.solve(&nu_k);
            out.value += 0.5 * (ln_det + nu_k.dot(&s_nu) + pa as f64 * LN_2PI);
            // K = P⁻Hᵀ S⁻¹ (S symmetric: K = (S⁻¹ H P⁻)ᵀ).
            let gain = chol.solve(&pht.transpose()).transpose();
            let a = DMatrix::<f64>::identity(n, n) - &gain * &ha;
            let at = a.transpose();
            let gt = gain.transpose();
            let mut pnew = &a * &pp * &at + &gain * &ra * &gt;
            symmetrise(&mut pnew);
            let xnew = &xp + &gain * &nu_k;
            if m > 0 {
                let s_inv = chol.inverse();
                let mut s_ds: Vec<DMatrix<f64>> = Vec::with_capacity(m);
                let mut dnu: Vec<DVector<f64>> = Vec::with_capacity(m);
                let mut ds_all: Vec<DMatrix<f64>> = Vec::with_capacity(m);
                for (i, prm) in self.params.iter().enumerate() {
                    let mut ds = &ha * &dpp[i] * &hat;
                    if prm.matrix == NoiseMatrix::R
                        && let Some(pos) = avail.iter().position(|&j| j == prm.index)
                    {
                        ds[(pos, pos)] += scale[i];
                    }
                    let dn = -(&ha * &dxp[i]);
                    let sd = &s_inv * &ds;
                    out.gradient[i] +=
                        0.5 * (sd.trace() - s_nu.dot(&(&ds * &s_nu))) + s_nu.dot(&dn);
                    s_ds.push(sd);
                    dnu.push(dn);
                    ds_all.push(ds);
                }
                for i in 0..m {
                    let si_dn = &s_inv * &dnu[i];
                    for j in 0..=i {
                        // tr(A B) of two p × p matrices without forming the product.
                        let tr: f64 = s_ds[i].component_mul(&s_ds[j].transpose()).sum();
                        let v = 0.5 * tr + dnu[j].dot(&si_dn);
                        out.information[(i, j)] += v;
                        if i != j {
                            out.information[(j, i)] += v;
                        }
                    }
                }
                for (i, prm) in self.params.iter().enumerate() {
                    let dk = (&dpp[i] * &hat - &gain * &ds_all[i]) * &s_inv;
                    dx[i] = &dxp[i] + &dk * &nu_k + &gain * &dnu[i];
                    let mut d = &a * &dpp[i] * &at;
                    if prm.matrix == NoiseMatrix::R
                        && let Some(pos) = avail.iter().position(|&j| j == prm.index)
                    {
                        // K ∂R Kᵀ with ∂R = scale·e_pos e_posᵀ.
                        let col = gain.column(pos);
                        d += scale[i] * col * col.transpose();
                    }
                    symmetrise(&mut d);
                    dp[i] = d;
                }
            }
            (x, pm) = (xnew, pnew);
        }
        Some(out)
    }
}

/// (A + Aᵀ)/2 in place: rounding must not make a covariance asymmetric over many steps.
pub(crate) fn symmetrise(a: &mut DMatrix<f64>) {
    let n = a.nrows();
    for i in 0..n {
        for j in 0..i {
            let v = 0.5 * (a[(i, j)] + a[(j, i)]);
            a[(i, j)] = v;
            a[(j, i)] = v;
        }
    }
}
