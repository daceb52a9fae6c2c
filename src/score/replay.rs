//! Replay: one run's rows of an external filter, turned into the very filter records an
//! in-process filter produces.

use std::os::unix::fs::FileExt;

use crate::filter::{Filter, FilterError, Innovation};
use crate::linalg::so3::{self, EulerRotation};
use crate::linalg::{Matrix, SmallCholesky, Vector};
use crate::model::{Availability, Measurement, Model};
use crate::step_loop::{Evaluate, FilterOutput, Prior, RunContext, Unit, run_filter};

use super::columns::{CovarianceForm, EstimateColumns};
use super::rotation::quaternion_columns;
use super::{EstimateSet, FAILED_COLUMN};

impl EstimateSet {
    fn unit_rows(&self, filter: usize, unit: &Unit) -> Option<UnitRows<'_>> {
        let e = &self.externals[self.by_filter.get(filter).copied().flatten()?];
        let (base, samples) = self.cells[unit.scenario * self.n_scales + unit.scale];
        let first = base + (unit.run * samples) as u64;
        let width = e.columns.width();
        let mut values = vec![0f64; samples * width];
        let read = e.spill.read_exact_at(
            bytemuck::cast_slice_mut(&mut values),
            first * width as u64 * 8,
        );
        let bit = |bits: &[u64], k: u64| {
            let row = first + k;
            bits[(row / 64) as usize] & (1 << (row % 64)) != 0
        };
        let present: Vec<bool> = (0..samples as u64).map(|k| bit(&e.present, k)).collect();
        let failed_at = (0..samples as u64)
            .find(|&k| bit(&e.failed, k))
            .map(|k| k as usize);
        // A spill shorter than this run (its last rows never written) reads as absent rows.
        if read.is_err() {
            values.fill(f64::NAN);
            for (k, p) in present.iter().enumerate() {
                let row = &mut values[k * width..(k + 1) * width];
                if *p
                    && e.spill
                        .read_exact_at(
                            bytemuck::cast_slice_mut(row),
                            (first + k as u64) * width as u64 * 8,
                        )
                        .is_err()
                {
                    row.fill(f64::NAN);
                }
            }
        }
        Some(UnitRows {
            columns: &e.columns,
            values,
            present,
            failed_at,
            width,
        })
    }
}

/// One run's rows of one external filter.
struct UnitRows<'a> {
    columns: &'a EstimateColumns,
    values: Vec<f64>,
    present: Vec<bool>,
    /// The first step whose `failed` flag is true.
    failed_at: Option<usize>,
    width: usize,
}

impl UnitRows<'_> {
    fn row(&self, k: usize) -> &[f64] {
        &self.values[k * self.width..(k + 1) * self.width]
    }
    fn mean<const NQ: usize>(&self, k: usize) -> Vector<NQ> {
        Vector::<NQ>::from_column_slice(&self.row(k)[..NQ])
    }
    fn covariance<const NQ: usize>(&self, k: usize) -> Matrix<NQ, NQ> {
        let tri = &self.row(k)[NQ..NQ + NQ * (NQ + 1) / 2];
        let mut m = Matrix::<NQ, NQ>::zeros();
        let mut t = 0;
        for i in 0..NQ {
            for j in 0..=i {
                m[(i, j)] = tri[t];
                if self.columns.covariance != CovarianceForm::Cholesky {
                    m[(j, i)] = tri[t];
                }
                t += 1;
            }
        }
        match self.columns.covariance {
            CovarianceForm::Lower => m,
            CovarianceForm::Cholesky => m * m.transpose(),
            CovarianceForm::Correlation => {
                // m holds the variances on its diagonal and the correlations off it.
                let sd: [f64; NQ] = std::array::from_fn(|i| m[(i, i)].sqrt());
                Matrix::<NQ, NQ>::from_fn(|i, j| {
                    if i == j {
                        m[(i, i)]
                    } else {
                        m[(i, j)] * sd[i] * sd[j]
                    }
                })
            }
        }
    }
    /// Why row k cannot be used, if it cannot.
    fn problem<const NQ: usize>(&self, k: usize) -> Option<String> {
        if !self.present[k] {
            return Some(format!("estimates: no row for step {k}"));
        }
        if self.failed_at.is_some_and(|f| f <= k) {
            return Some(format!(
                "estimates: the filter failed at step {k} (`{FAILED_COLUMN}` = true)"
            ));
        }
        let row = self.row(k);
        let names = &self.columns.quantities;
        if let Some(i) = (0..NQ).find(|&i| !row[i].is_finite()) {
            if let Some(r) = self
                .columns
                .quaternions
                .iter()
                .find(|r| (r.first..r.first + 3).contains(&i))
            {
                return Some(format!(
                    "estimates: the quaternion {} is null, zero or non-finite",
                    quaternion_columns(names, r)[..].join(", ")
                ));
            }
            return Some(format!("estimates: est_{} is null or non-finite", names[i]));
        }
        let tri = &row[NQ..NQ + NQ * (NQ + 1) / 2];
        if tri.iter().any(|v| !v.is_finite()) {
            return Some("estimates: a covariance entry is null or non-finite".into());
        }
        if self.columns.covariance == CovarianceForm::Correlation {
            let q: Vec<&str> = names.iter().map(String::as_str).collect();
            let mut t = 0;
            for i in 0..NQ {
                for j in 0..=i {
                    let v = tri[t];
                    t += 1;
                    let bad = if i == j { v < 0.0 } else { v.abs() > 1.0 };
                    if bad {
                        let what = if i == j {
                            "is negative"
                        } else {
                            "is outside [-1, 1]"
                        };
                        return Some(format!(
                            "estimates: {} = {v} {what}",
                            CovarianceForm::Correlation.column(&q, i, j)
                        ));
                    }
                }
            }
        }
        None
    }
}

/// The filter that replays a file's rows: its belief is the step.
struct Replay<'a> {
    rows: &'a UnitRows<'a>,
}

impl<const NQ: usize, const NU: usize, const NZ: usize, M: Model<NQ, NU, NZ>> Filter<NQ, NU, NZ, M>
    for Replay<'_>
{
    type Belief = usize;

    fn init(&self, _: &M, _: &Vector<NQ>, _: &Matrix<NQ, NQ>, _: &Measurement<NZ>) -> usize {
        0
    }

    fn predict(&self, _: &M, k: &mut usize, _: &Vector<NU>) -> Result<(), FilterError> {
        *k += 1;
        match self.rows.problem::<NQ>(*k) {
            Some(why) => Err(FilterError::Estimates(why)),
            None => Ok(()),
        }
    }

    fn update(
        &self,
        _: &M,
        k: &mut usize,
        _: &Vector<NU>,
        _: &Measurement<NZ>,
    ) -> Result<Option<Innovation<NZ>>, FilterError> {
        let cols = self.rows.columns;
        if !cols.innovations {
            return Ok(None);
        }
        let row = self.rows.row(*k);
        let at = NQ + NQ * (NQ + 1) / 2;
        let nu_row = &row[at..at + NZ];
        let s_row = &row[at + NZ..at + NZ + NZ * (NZ + 1) / 2];
        let mut available = 0u32;
        let mut nu = Vector::<NZ>::zeros();
        for (i, v) in nu_row.iter().enumerate() {
            if v.is_finite() {
                available |= 1 << i;
                nu[i] = *v;
            }
        }
        let available = Availability(available);
        if available.count() == 0 {
            return Ok(None);
        }
        // Components that did not report get identity rows, as the EKF masks them, so the
        // factor and the whitened innovation equal the in-process ones.
        let mut s = Matrix::<NZ, NZ>::identity();
        let mut t = 0;
        for i in 0..NZ {
            for j in 0..=i {
                if available.has(i) && available.has(j) {
                    if !s_row[t].is_finite() {
                        return Err(FilterError::Estimates(format!(
                            "estimates: S_{}_{} is null or non-finite where nu reported",
                            cols.measurements[i], cols.measurements[j]
                        )));
                    }
                    s[(i, j)] = s_row[t];
                    s[(j, i)] = s_row[t];
                }
                t += 1;
            }
        }
        let chol = SmallCholesky::new(&s).ok_or(FilterError::NotPositiveDefinite {
            which: "innovation covariance S",
        })?;
        let whitened = chol.solve_lower(&nu);
        Ok(Some(
            Innovation::new(nu, whitened, available).with_covariance(s),
        ))
    }

    fn mean(&self, k: &usize) -> Vector<NQ> {
        self.rows.mean(*k)
    }

    fn covariance(&self, k: &usize) -> Option<Matrix<NQ, NQ>> {
        Some(self.rows.covariance(*k))
    }

    fn error_transition(&self, k: &usize) -> Option<Matrix<NQ, NQ>> {
        let cols = self.rows.columns;
        if !cols.transition {
            return None;
        }
        let row = self.rows.row(*k);
        let at = row.len() - NQ * NQ;
        let a = &row[at..];
        a.iter()
            .all(|v| v.is_finite())
            .then(|| Matrix::<NQ, NQ>::from_fn(|i, j| a[i * NQ + j]))
    }
}

/// Scores study filter `filter` (an external one, labelled `label`) on one run from its rows
/// in `estimates`: the same step loop, metrics and record as an in-process filter. `model` is
/// only there to satisfy the step loop's types; the replay never evaluates it.
pub fn replay<const NQ: usize, const NU: usize, const NZ: usize, M: Model<NQ, NU, NZ>>(
    estimates: Option<&EstimateSet>,
    filter: usize,
    label: &str,
    model: &M,
    ctx: &RunContext<'_, NQ, NU, NZ>,
) -> FilterOutput {
    let rows = estimates.and_then(|set| set.unit_rows(filter, &ctx.unit));
    let fail = |why: String| FilterOutput::failed_at_start(ctx, why);
    let Some(rows) = rows else {
        return fail(format!(
            "no estimates were given for the external filter `{label}`"
        ));
    };
    // A run left out whole was not run: missing, which no tolerance for failures covers.
    if !rows.present.iter().any(|&p| p) {
        return FilterOutput::missing(
            ctx,
            format!("the estimates of `{label}` leave this run out"),
        );
    }
    if let Some(why) = rows.problem::<NQ>(0) {
        return fail(why);
    }
    let (x0, p0) = (rows.mean::<NQ>(0), rows.covariance::<NQ>(0));
    // Rotations the file gives as Euler angles have an Euler-angle covariance to map.
    let charts: Vec<EulerRotation> = ctx
        .rotations
        .iter()
        .filter(|r| !rows.columns.quaternions.contains(r))
        .copied()
        .collect();
    run_filter(
        model,
        &Replay { rows: &rows },
        &Charted { charts: &charts },
        &Prior {
            x0_hat: &x0,
            p0: &p0,
        },
        ctx,
    )
}

/// The replay's evaluation: the identity, except that each rotation given as Euler angles
/// has its covariance (and error transition) mapped into the rotation error's tangent space
/// by the chart Jacobian at the estimate.
struct Charted<'a> {
    charts: &'a [EulerRotation],
}

impl Charted<'_> {
    fn blocks<const N: usize>(&self, x: &Vector<N>) -> Vec<(usize, Matrix<3, 3>)> {
        self.charts
            .iter()
            .map(|r| (r.first, r.chart_jacobian(x.as_slice())))
            .collect()
    }
}

impl<const N: usize> Evaluate<N, N> for Charted<'_> {
    fn mean(&self, x: &Vector<N>) -> Vector<N> {
        *x
    }
    fn covariance(&self, x: &Vector<N>, p: &Matrix<N, N>) -> Matrix<N, N> {
        so3::transform_blocks(p, &self.blocks(x))
    }
    fn covariance_ref<'p>(&self, p: &'p Matrix<N, N>) -> Option<&'p Matrix<N, N>> {
        self.charts.is_empty().then_some(p)
    }
    fn transition(&self, a: &Matrix<N, N>) -> Option<Matrix<N, N>> {
        self.charts.is_empty().then_some(*a)
    }
    fn transition_at(&self, x: &Vector<N>, a: &Matrix<N, N>) -> Option<Matrix<N, N>> {
        so3::conjugate_blocks(a, &self.blocks(x))
    }
}
/// The model a world system's external filters are replayed on: kfmc does not know their
/// model, and the replay never asks it anything; it only carries Δt.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Unmodelled {
    /// Sample time Δt in seconds.
    pub dt_s: f64,
}

impl<const NX: usize, const NU: usize, const NZ: usize> Model<NX, NU, NZ> for Unmodelled {
    fn dt_s(&self) -> f64 {
        self.dt_s
    }
    fn propagate(&self, x: &Vector<NX>, _: &Vector<NU>) -> Vector<NX> {
        *x
    }
    fn transition_jacobian(&self, _: &Vector<NX>, _: &Vector<NU>) -> Matrix<NX, NX> {
        Matrix::<NX, NX>::identity()
    }
    fn measure(&self, _: &Vector<NX>, _: &Vector<NU>) -> Vector<NZ> {
        Vector::<NZ>::zeros()
    }
    fn measurement_jacobian(&self, _: &Vector<NX>, _: &Vector<NU>) -> Matrix<NZ, NX> {
        Matrix::<NZ, NX>::zeros()
    }
}
