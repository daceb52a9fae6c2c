//! The metrics role: per-step values of one run (errors, NEES, NIS) and the accumulators that
//! fold runs into per-cell statistics without keeping per-run step data.
//!
//! * e_k = x_k − x̂_k (the planar θ is an unwrapped angle in the seeds, so it is not wrapped);
//! * RMSE per state over all samples k = 0..=K, as the seeds compute it (k = 0 included);
//! * NEES_k = e_kᵀ P_k⁻¹ e_k (n dof) and NIS_k = ν_kᵀ S_k⁻¹ ν_k (p dof) through Cholesky
//!   factors; `nees_mean` averages k = 1..=K (k = 0 is the prior, not a filter output) and
//!   `nis_mean` the steps with a measurement update.

pub mod batch_means;
pub mod blocks;
pub mod consistency;
pub mod credibility;
pub mod divergence;
pub mod quantile;
pub mod spill;

use quantile::QuantileSketch;

/// The quantiles of |e_k| across runs in `steps.parquet` (`abs_err_p05_<state>` …).
pub const ABS_ERR_QUANTILES: [f64; 3] = [0.05, 0.50, 0.95];

/// The |e| quantiles are kept on a grid of at most about this many steps per run. Their
/// sketches are fed serially, in run order (for bit-identical tables), so a dense grid made
/// the fold, not the filters, the bottleneck of large sweeps (2.5× slower at 1,001 steps); a
/// figure needs no more points than this.
pub const ABS_ERR_MAX_POINTS: usize = 200;

/// Runs whose |e| values are buffered before they are pushed into the quantile sketches: each
/// sketch then takes this many values in a row (in run order, so the estimates do not change)
/// while it is in cache, instead of one value per run across a cell's thousand sketches.
pub const ABS_ERR_BLOCK: usize = 64;

/// Bytes of |e| values the cell being folded keeps, over all its filters, so that its |e|
/// quantiles are exact: each sketch keeps `abs_err_exact_cap` values (8 bytes each) before P²
/// takes over. 32 MiB keeps 4,186 runs of P1's six states exact (1,001 samples: a 167-point
/// grid).
pub const ABS_ERR_EXACT_BYTES: usize = 32 << 20;

/// Values each |e| sketch keeps exact in a cell of `filters` filters and `nx` quantities over
/// `samples` samples: [`ABS_ERR_EXACT_BYTES`] shared by the cell's sketches (at least
/// [`quantile::EXACT_CAP`]).
pub fn abs_err_exact_cap(filters: usize, nx: usize, samples: usize) -> usize {
    let sketches = abs_err_grid_points(samples) * nx.max(1) * filters.max(1);
    (ABS_ERR_EXACT_BYTES / (8 * sketches)).max(quantile::EXACT_CAP)
}

/// Points of the |e| quantile grid for K + 1 = `samples` samples.
pub fn abs_err_grid_points(samples: usize) -> usize {
    (samples.max(1) - 1) / abs_err_stride(samples) + 1
}

/// The step stride of the |e| quantile grid for K + 1 = `samples` samples.
pub fn abs_err_stride(samples: usize) -> usize {
    samples.div_ceil(ABS_ERR_MAX_POINTS).max(1)
}

/// How a run ended.
#[derive(Clone, Debug, PartialEq)]
pub enum RunStatus {
    /// Completed, no threshold crossed.
    Ok,
    /// Completed, but the run's RMSE of a state exceeds its divergence threshold. `step` is the
    /// first step at which the squared errors accumulated so far already exceed the threshold,
    /// i.e. where the crossing became certain.
    Diverged {
        /// The step.
        step: usize,
        /// What crossed, e.g. `rmse_x > 5`.
        detail: String,
    },
    /// The filter failed numerically at `step`; the run stops there.
    NumericalFailure {
        /// The step.
        step: usize,
        /// The filter's error message.
        detail: String,
    },
    /// The run has no data at all (an external filter's estimates leave it out): it was not
    /// run, so it is neither a success nor a failure, and a case judged on the runs the spec
    /// declares is incomplete without it.
    Missing {
        /// Why, e.g. which filter's estimates lack it.
        detail: String,
    },
}

impl RunStatus {
    /// The value of the `status` column.
    pub fn label(&self) -> &'static str {
        match self {
            RunStatus::Ok => "ok",
            RunStatus::Diverged { .. } => "diverged",
            RunStatus::NumericalFailure { .. } => "numerical_failure",
            RunStatus::Missing { .. } => "missing",
        }
    }
    /// Whether the run is left out of every statistic (a numerical failure, or a missing
    /// run): its RMSE is null in `runs.parquet` and it is no term of the summary.
    pub fn left_out(&self) -> bool {
        matches!(
            self,
            RunStatus::NumericalFailure { .. } | RunStatus::Missing { .. }
        )
    }
    /// The step of a divergence or failure.
    pub fn step(&self) -> Option<usize> {
        match self {
            RunStatus::Ok | RunStatus::Missing { .. } => None,
            RunStatus::Diverged { step, .. } | RunStatus::NumericalFailure { step, .. } => {
                Some(*step)
            }
        }
    }
    /// The human-readable detail.
    pub fn detail(&self) -> Option<&str> {
        match self {
            RunStatus::Ok => None,
            RunStatus::Diverged { detail, .. }
            | RunStatus::NumericalFailure { detail, .. }
            | RunStatus::Missing { detail } => Some(detail),
        }
    }
}

/// Per-step values of one filter on one run, flattened (`nx` values per step for errors),
/// recorded step by step with [`StepValues::record`]. `NaN` marks "not defined" (no
/// covariance, no update, or after a numerical failure).
///
/// Recording also keeps what the run's record and the cell's |e| quantiles need — the sums
/// behind the RMSE and the mean NEES and NIS, and |e| on the quantile grid — so that neither
/// [`StepValues::finish`] nor [`StepAccumulator::fold`] reads the per-step arrays again:
/// a run's values are written by the worker that ran it and folded by the sink's thread, and
/// a second pass over them from there is a pass over another core's cache.
#[derive(Clone, Debug, PartialEq)]
pub struct StepValues {
    nx: usize,
    /// e_k,i², row-major by step.
    sq_err: Vec<f64>,
    nees: Vec<f64>,
    nis: Vec<f64>,
    /// NIS degrees of freedom per step (0 without an update).
    nis_dof: Vec<u8>,
    /// Steps recorded (K + 1 unless the run failed).
    completed: usize,
    /// Σ_k e_k,i² per state, in step order (NaN once a NaN is added).
    sq_err_sum: Vec<f64>,
    /// Σ and count of the defined NEES_k for k ≥ 1, and of the defined NIS_k.
    nees_sum: (f64, usize),
    nis_sum: (f64, usize),
    /// |e_k,i| = √(e_k,i²) on the quantile grid (every `abs_err_stride`-th step), `nx` per
    /// grid step, NaN at grid steps not reached.
    abs_err: Vec<f64>,
    abs_err_stride: usize,
    /// The next grid step to record.
    next_grid_step: usize,
    /// The signed errors e_k (`nx` per step) and the block NEES (`cred_nb` per step) that the
    /// credibility measures need ([`credibility`]); empty unless
    /// [`StepValues::enable_credibility`] was called.
    cred_err: Vec<f64>,
    cred_blocks: Vec<f64>,
    cred_nb: usize,
}

impl Drop for StepValues {
    fn drop(&mut self) {
        Recycled::give(Recycled {
            sq_err: std::mem::take(&mut self.sq_err),
            nees: std::mem::take(&mut self.nees),
            nis: std::mem::take(&mut self.nis),
            nis_dof: std::mem::take(&mut self.nis_dof),
            abs_err: std::mem::take(&mut self.abs_err),
        });
    }
}

/// Bytes of per-step buffers kept for reuse (`Recycled`): more than two windows of runs
/// of a typical study need, far less than the windows themselves hold.
pub const RECYCLED_BYTES: usize = 64 << 20;

/// The per-step buffers of a dropped [`StepValues`], kept for the next run's.
///
/// A run's values are allocated by the worker that ran it and freed by the sink's thread
/// after the fold; freed there, they went back to the worker's malloc arena in pieces the
/// arena returned to the kernel and faulted in again for the next window. Reused, they stay
/// mapped (with the cell's sketches reserved at once, a P1 study's system CPU time fell
/// from about 4.5 % of its CPU to 1.7 %).
#[derive(Default)]
struct Recycled {
    sq_err: Vec<f64>,
    nees: Vec<f64>,
    nis: Vec<f64>,
    nis_dof: Vec<u8>,
    abs_err: Vec<f64>,
}

/// The buffers kept, and their bytes.
static RECYCLED: std::sync::Mutex<(Vec<Recycled>, usize)> = std::sync::Mutex::new((Vec::new(), 0));

impl Recycled {
    fn bytes(&self) -> usize {
        8 * (self.sq_err.capacity()
            + self.nees.capacity()
            + self.nis.capacity()
            + self.abs_err.capacity())
            + self.nis_dof.capacity()
    }

    /// Kept buffers, or empty ones.
    fn take() -> Recycled {
        let mut kept = RECYCLED
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        match kept.0.pop() {
            Some(b) => {
                kept.1 -= b.bytes();
                b
            }
            None => Recycled::default(),
        }
    }

    /// Keeps `b` while the budget allows; frees it otherwise.
    fn give(b: Recycled) {
        let n = b.bytes();
        if n == 0 {
            return;
        }
        let mut kept = RECYCLED
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        if kept.1 + n <= RECYCLED_BYTES {
            kept.1 += n;
            kept.0.push(b);
        }
    }
}

/// Per-run sums for the consistency tests, over the steps after the burn-in.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct RunConsistency {
    /// First step included in the sums; `None` when the initial-error term never fell below
    /// its threshold (the prior is never forgotten) and every step from 1 was used.
    pub first_step: Option<usize>,
    /// Σ NEES_k.
    pub nees_sum: f64,
    /// Steps in `nees_sum`.
    pub nees_n: u64,
    /// Σ tr(P_k⁻¹ W_k), `None` when the filter exposes no error transition.
    pub rho_sum: Option<f64>,
    /// Σ NIS_k.
    pub nis_sum: f64,
    /// Σ p_k (degrees of freedom of the NIS terms).
    pub nis_dof: u64,
    /// Update steps in `nis_sum`.
    pub nis_n: u64,
    /// Per state: Σ e_k,i / √P_k,ii (the normalised error, for the bias test).
    pub nme_sum: Vec<f64>,
    /// Per lag l = 1..L: Σ w_kᵀ w_{k+l} over whitened innovations.
    pub lag_prod: Vec<f64>,
    /// Per lag: number of component pairs in `lag_prod`.
    pub lag_pairs: Vec<u64>,
    /// Σ ‖w_k‖² over the steps after the whiteness burn-in.
    pub w_sq: f64,
    /// Components in `w_sq`: `nis_dof` less the whiteness burn-in's.
    pub w_n: u64,
    /// NEES of x̂_0 under P_0, when x̂_0 is an estimate whose covariance is under test.
    pub initial_nees: Option<f64>,
}

/// The per-run record of one filter (one row of `runs.parquet`).
#[derive(Clone, Debug, PartialEq)]
pub struct FilterRun {
    /// RMSE per state.
    pub rmse: Vec<f64>,
    /// Mean NEES over k = 1..=K, `None` without a covariance.
    pub nees_mean: Option<f64>,
    /// Mean NIS over update steps, `None` without innovations.
    pub nis_mean: Option<f64>,
    /// How the run ended.
    pub status: RunStatus,
    /// Covariance repairs made during the run.
    pub covariance_repairs: u32,
    /// Per-step values for the cell accumulators.
    pub steps: StepValues,
    /// Consistency sums, when the study asks for them and the filter has a covariance.
    pub consistency: Option<RunConsistency>,
}

impl StepValues {
    /// Empty values for `steps + 1` samples of `nx` states.
    pub fn new(nx: usize, steps: usize) -> Self {
        let samples = steps + 1;
        let grid = abs_err_grid_points(samples) * nx;
        let mut b = Recycled::take();
        let fill = |v: &mut Vec<f64>, n: usize| {
            v.clear();
            v.resize(n, f64::NAN);
        };
        fill(&mut b.sq_err, samples * nx);
        fill(&mut b.nees, samples);
        fill(&mut b.nis, samples);
        fill(&mut b.abs_err, grid);
        b.nis_dof.clear();
        b.nis_dof.resize(samples, 0);
        StepValues {
            nx,
            sq_err: b.sq_err,
            nees: b.nees,
            nis: b.nis,
            nis_dof: b.nis_dof,
            completed: 0,
            sq_err_sum: vec![0.0; nx],
            nees_sum: (0.0, 0),
            nis_sum: (0.0, 0),
            abs_err: b.abs_err,
            abs_err_stride: abs_err_stride(samples),
            next_grid_step: 0,
            cred_err: Vec::new(),
            cred_blocks: Vec::new(),
            cred_nb: 0,
        }
    }

    /// Keeps, from now on, what the credibility measures need: the signed errors and the NEES
    /// of `blocks` blocks per step ([`StepValues::record_credibility`]).
    pub fn enable_credibility(&mut self, blocks: usize) {
        let samples = self.nees.len();
        self.cred_err.clear();
        self.cred_err.resize(samples * self.nx, f64::NAN);
        self.cred_blocks.clear();
        self.cred_blocks.resize(samples * blocks, f64::NAN);
        self.cred_nb = blocks;
    }

    /// Records step `k`'s signed error (`nx` values) and its block NEES (one per block), when
    /// [`StepValues::enable_credibility`] was called; nothing otherwise.
    #[inline]
    pub fn record_credibility(&mut self, k: usize, error: &[f64], block_nees: &[f64]) {
        let (nx, nb) = (self.nx, self.cred_nb);
        if let Some(row) = self.cred_err.get_mut(k * nx..(k + 1) * nx) {
            row.copy_from_slice(&error[..nx]);
        }
        if let Some(row) = self.cred_blocks.get_mut(k * nb..(k + 1) * nb) {
            row.copy_from_slice(&block_nees[..nb]);
        }
    }

    /// Records the next step, k = [`StepValues::completed`]: the error e_k (`N` = `nx`
    /// values), NEES_k and NIS_k (NaN when not defined) and the NIS degrees of freedom (0
    /// without an update).
    ///
    /// # Panics
    /// When every step has been recorded, or `N` is not `nx`.
    // Inlined into the step loop with a constant N: the per-state loops unroll and the
    // slices' bounds are checked once per step (out of line it cost ~130 instructions a step).
    #[inline(always)]
    pub fn record<const N: usize>(&mut self, error: &[f64; N], nees: f64, nis: f64, nis_dof: u8) {
        assert_eq!(N, self.nx, "one error per state");
        let k = self.completed;
        let row: &mut [f64; N] = (&mut self.sq_err[k * N..(k + 1) * N])
            .try_into()
            .expect("N values");
        let sums: &mut [f64; N] = self.sq_err_sum.as_mut_slice().try_into().expect("N sums");
        for i in 0..N {
            row[i] = error[i] * error[i];
            sums[i] += row[i];
        }
        if k == self.next_grid_step {
            let g = k / self.abs_err_stride;
            let grid: &mut [f64; N] = (&mut self.abs_err[g * N..(g + 1) * N])
                .try_into()
                .expect("N values");
            for i in 0..N {
                grid[i] = row[i].sqrt();
            }
            self.next_grid_step += self.abs_err_stride;
        }
        self.nees[k] = nees;
        if k > 0 && !nees.is_nan() {
            self.nees_sum.0 += nees;
            self.nees_sum.1 += 1;
        }
        self.nis[k] = nis;
        if !nis.is_nan() {
            self.nis_sum.0 += nis;
            self.nis_sum.1 += 1;
        }
        self.nis_dof[k] = nis_dof;
        self.completed = k + 1;
    }

    /// Steps recorded so far (K + 1 when the run completed).
    pub fn completed(&self) -> usize {
        self.completed
    }

    /// NEES_k (NaN when not defined or not reached).
    pub fn nees(&self) -> &[f64] {
        &self.nees
    }

    /// NIS_k (NaN when not defined or not reached).
    pub fn nis(&self) -> &[f64] {
        &self.nis
    }

    /// The NIS degrees of freedom per step (0 where no measurement updated the step).
    pub fn nis_dof(&self) -> &[u8] {
        &self.nis_dof
    }

    /// e_k,i², row-major by step (NaN where not reached).
    pub fn sq_err(&self) -> &[f64] {
        &self.sq_err
    }

    /// Where the run's sums overflowed although each step's value was finite (errors near
    /// 1e154 over a few steps overflow the sum of their squares): an infinite RMSE or mean
    /// NEES is a numerical failure at the step whose term made it so, never a run that is
    /// "ok". (A NaN error stops the step loop itself; a NaN sum is no overflow.)
    fn overflow(&self, state_names: &[&str]) -> Option<(usize, String)> {
        let nx = self.nx;
        let done = &self.sq_err[..self.completed * nx];
        fn first_k(values: impl Iterator<Item = f64>) -> Option<usize> {
            let mut s = 0.0f64;
            values
                .enumerate()
                .find(|&(_, v)| {
                    s += v;
                    s.is_infinite()
                })
                .map(|(k, _)| k)
        }
        if let Some(i) = (0..nx).find(|&i| self.sq_err_sum[i].is_infinite()) {
            let k = first_k(done.chunks_exact(nx).map(|row| row[i]))?;
            return Some((
                k,
                format!(
                    "the sum of squared errors of {} is not finite: its RMSE cannot be computed",
                    state_names.get(i).unwrap_or(&"?")
                ),
            ));
        }
        if self.nees_sum.0.is_infinite() {
            let nees = self.nees[..self.completed].iter().enumerate().skip(1);
            let k = first_k(nees.map(|(_, &v)| if v.is_nan() { 0.0 } else { v }))?;
            return Some((
                k + 1,
                "the sum of NEES is not finite: its mean cannot be computed".into(),
            ));
        }
        None
    }

    /// Summarises the run: RMSE, means and the threshold-based status.
    pub fn finish(
        self,
        failure: Option<(usize, String)>,
        thresholds: Option<&[f64]>,
        state_names: &[&str],
        covariance_repairs: u32,
    ) -> FilterRun {
        let nx = self.nx;
        let failure = failure.or_else(|| self.overflow(state_names));
        let n = self.completed.max(1) as f64;
        let sums = &self.sq_err_sum;
        // The first step where Σ_{j≤k} e_j² > thr²·(K+1) per state: the crossing is certain.
        let total = self.nees.len() as f64;
        let mut crossed: Option<(usize, usize)> = None;
        // Without thresholds no sum exceeds an infinite limit.
        let limit: Vec<f64> = match thresholds {
            Some(t) => t.iter().map(|t| t * t * total).collect(),
            None => vec![f64::INFINITY; nx],
        };
        let done = &self.sq_err[..self.completed * nx];
        // A running sum of squares never decreases, so a state whose total stays within its
        // limit never crossed it, and only the others are summed again to find the step; a
        // NaN total (NaN never compares above) may hide a crossing before it, so it is
        // rescanned too. Most runs cross nothing and skip the per-step comparisons.
        for i in 0..nx {
            if sums[i] <= limit[i] {
                continue;
            }
            let mut s = 0.0;
            let first = done.chunks_exact(nx).position(|row| {
                s += row[i];
                s > limit[i]
            });
            // The first step in step order, then the lowest state at that step.
            if let Some(k) = first
                && crossed.is_none_or(|(k0, _)| k < k0)
            {
                crossed = Some((k, i));
            }
        }
        let rmse: Vec<f64> = sums.iter().map(|s| (s / n).sqrt()).collect();
        let mean = |(s, c): (f64, usize)| (c > 0).then(|| s / c as f64);
        let nees_mean = mean(self.nees_sum);
        let nis_mean = mean(self.nis_sum);
        let status = match (failure, crossed) {
            (Some((step, detail)), _) => RunStatus::NumericalFailure { step, detail },
            (None, Some((step, i))) => RunStatus::Diverged {
                step,
                detail: format!(
                    "rmse_{} > {}",
                    state_names[i],
                    thresholds.map_or(f64::NAN, |t| t[i])
                ),
            },
            (None, None) => RunStatus::Ok,
        };
        FilterRun {
            rmse,
            nees_mean,
            nis_mean,
            status,
            covariance_repairs,
            steps: self,
            consistency: None,
        }
    }
}

/// Sums over the runs of one cell and filter, per step. Runs are folded in run order, so the
/// floating-point sums — and the tables — are identical for any thread count.
#[derive(Clone, Debug, PartialEq)]
pub struct StepAccumulator {
    nx: usize,
    runs: Vec<u32>,
    sum_sq: Vec<f64>,
    nees_sum: Vec<f64>,
    nees_n: Vec<u32>,
    nis_sum: Vec<f64>,
    nis_n: Vec<u32>,
    nis_dof: Vec<u64>,
    /// Per (grid step, state): quantiles of |e| across runs, [`ABS_ERR_QUANTILES`]; the grid
    /// is every `abs_err_stride`-th step. The values of the last runs wait in `pending`
    /// ([`ABS_ERR_BLOCK`]); reading a row pushes them first, hence the cell.
    abs_err: std::cell::RefCell<AbsErr>,
    abs_err_stride: usize,
}

/// The |e| sketches and the values not yet pushed into them.
#[derive(Clone, Debug, PartialEq)]
struct AbsErr {
    sketches: Vec<QuantileSketch>,
    /// `ABS_ERR_BLOCK` rows, one per pending run, of one value per sketch (NaN for a run that
    /// did not reach the step; the sketch skips non-finite values): a run is one contiguous
    /// copy of its grid values.
    pending: Vec<f64>,
    /// Runs in `pending`.
    runs: usize,
}

impl AbsErr {
    /// Pushes the pending values, sketch by sketch, each in run order.
    fn flush(&mut self) {
        let n = self.runs;
        let width = self.sketches.len();
        for (col, s) in self.sketches.iter_mut().enumerate() {
            for run in 0..n {
                s.push(self.pending[run * width + col]);
            }
        }
        self.runs = 0;
    }
}

/// One row of the per-step table after folding.
#[derive(Clone, Debug, PartialEq)]
pub struct StepRow {
    /// Runs contributing at this step.
    pub runs: u32,
    /// ANEES_k, `None` when no run had a covariance.
    pub anees: Option<f64>,
    /// ANIS_k.
    pub anis: Option<f64>,
    /// Runs with a NEES at this step.
    pub nees_runs: u32,
    /// Runs with a NIS at this step.
    pub nis_runs: u32,
    /// Σ over runs of the NIS degrees of freedom at this step.
    pub nis_dof: u64,
    /// Mean squared error per state.
    pub mse: Vec<f64>,
    /// Per state, the [`ABS_ERR_QUANTILES`] of |e| across runs (`None` without runs).
    pub abs_err: Vec<[Option<f64>; 3]>,
}

impl StepAccumulator {
    /// An empty accumulator for `steps + 1` samples of `nx` states whose |e| quantiles are
    /// exact up to [`quantile::EXACT_CAP`] runs.
    pub fn new(nx: usize, steps: usize) -> Self {
        Self::with_exact_cap(nx, steps, quantile::EXACT_CAP)
    }

    /// An empty accumulator whose |e| quantiles are exact up to `exact_cap` runs (P² beyond;
    /// see [`abs_err_exact_cap`]).
    pub fn with_exact_cap(nx: usize, steps: usize, exact_cap: usize) -> Self {
        StepAccumulator {
            nx,
            runs: vec![0; steps + 1],
            sum_sq: vec![0.0; (steps + 1) * nx],
            nees_sum: vec![0.0; steps + 1],
            nees_n: vec![0; steps + 1],
            nis_sum: vec![0.0; steps + 1],
            nis_n: vec![0; steps + 1],
            nis_dof: vec![0; steps + 1],
            abs_err: std::cell::RefCell::new(AbsErr {
                sketches: vec![
                    QuantileSketch::with_exact_cap(&ABS_ERR_QUANTILES, exact_cap);
                    abs_err_grid_points(steps + 1) * nx
                ],
                pending: vec![f64::NAN; abs_err_grid_points(steps + 1) * nx * ABS_ERR_BLOCK],
                runs: 0,
            }),
            abs_err_stride: abs_err_stride(steps + 1),
        }
    }

    /// Makes room in the |e| sketches for `runs` runs (up to their exact cap) at once.
    pub fn reserve_runs(&mut self, runs: usize) {
        for s in &mut self.abs_err.get_mut().sketches {
            s.reserve(runs);
        }
    }

    /// Adds one run.
    pub fn fold(&mut self, v: &StepValues) {
        let nx = self.nx;
        let abs = self.abs_err.get_mut();
        let width = abs.sketches.len();
        abs.pending[abs.runs * width..(abs.runs + 1) * width].copy_from_slice(&v.abs_err);
        abs.runs += 1;
        if abs.runs == ABS_ERR_BLOCK {
            abs.flush();
        }
        // Slices of equal length instead of indexed loops: no bounds checks, and the sums
        // vectorise. A NaN adds 0.0, which leaves the sum's bits as they were: the sums start
        // at +0.0 and a round-to-nearest sum is never −0.0 after that.
        let c = v.completed;
        self.runs[..c].iter_mut().for_each(|r| *r += 1);
        for (s, x) in self.sum_sq[..c * nx].iter_mut().zip(&v.sq_err[..c * nx]) {
            *s += x;
        }
        for ((s, n), &x) in self.nees_sum[..c]
            .iter_mut()
            .zip(&mut self.nees_n[..c])
            .zip(&v.nees[..c])
        {
            let defined = !x.is_nan();
            *s += if defined { x } else { 0.0 };
            *n += u32::from(defined);
        }
        for (((s, n), d), (&x, &dof)) in self.nis_sum[..c]
            .iter_mut()
            .zip(&mut self.nis_n[..c])
            .zip(&mut self.nis_dof[..c])
            .zip(v.nis[..c].iter().zip(&v.nis_dof[..c]))
        {
            let defined = !x.is_nan();
            *s += if defined { x } else { 0.0 };
            *n += u32::from(defined);
            *d += if defined { u64::from(dof) } else { 0 };
        }
    }

    /// Number of samples (K + 1).
    pub fn len(&self) -> usize {
        self.runs.len()
    }

    /// Whether there are no samples.
    pub fn is_empty(&self) -> bool {
        self.runs.is_empty()
    }

    /// The statistics at step `k`.
    pub fn row(&self, k: usize) -> StepRow {
        let n = self.runs[k];
        let avg = |s: f64, c: u32| (c > 0).then(|| s / c as f64);
        StepRow {
            runs: n,
            anees: avg(self.nees_sum[k], self.nees_n[k]),
            anis: avg(self.nis_sum[k], self.nis_n[k]),
            nees_runs: self.nees_n[k],
            nis_runs: self.nis_n[k],
            nis_dof: self.nis_dof[k],
            mse: (0..self.nx)
                .map(|i| {
                    if n > 0 {
                        self.sum_sq[k * self.nx + i] / n as f64
                    } else {
                        f64::NAN
                    }
                })
                .collect(),
            abs_err: if k.is_multiple_of(self.abs_err_stride) {
                let g = k / self.abs_err_stride;
                let mut abs = self.abs_err.borrow_mut();
                if abs.runs > 0 {
                    abs.flush();
                }
                abs.sketches[g * self.nx..(g + 1) * self.nx]
                    .iter()
                    .map(|q| {
                        let e = q.estimates();
                        [e[0], e[1], e[2]]
                    })
                    .collect()
            } else {
                vec![[None; 3]; self.nx]
            },
        }
    }
}

/// The `q`-quantile of sorted data by linear interpolation between order statistics
/// (Hyndman–Fan type 7, the default of NumPy, pandas, polars and R).
pub fn quantile_sorted(sorted: &[f64], q: f64) -> Option<f64> {
    quantile_type7(sorted.len(), q, |i| sorted[i])
}

/// Type 7 of `len` values from their order statistics: `nth(i)` is the i-th smallest. It is
/// asked for ⌊h⌋ and then, between two values, for ⌊h⌋ + 1 — so a caller may find them by
/// selection instead of sorting.
pub(crate) fn quantile_type7(len: usize, q: f64, mut nth: impl FnMut(usize) -> f64) -> Option<f64> {
    if len == 0 {
        return None;
    }
    let h = (len - 1) as f64 * q;
    let lo = h.floor() as usize;
    let hi = h.ceil() as usize;
    let a = nth(lo);
    if lo == hi {
        return Some(a);
    }
    let b = nth(hi);
    if a.is_infinite() || b.is_infinite() {
        // A censored value takes part: the quantile is not known.
        return None;
    }
    Some(a + (h - lo as f64) * (b - a))
}

/// Mean and sample standard deviation (n − 1 in the denominator; `None` below two values).
pub fn mean_std(v: &[f64]) -> (Option<f64>, Option<f64>) {
    if v.is_empty() {
        return (None, None);
    }
    let n = v.len() as f64;
    let mean = v.iter().sum::<f64>() / n;
    if v.len() < 2 {
        return (Some(mean), None);
    }
    let var = v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0);
    (Some(mean), Some(var.sqrt()))
}

#[cfg(test)]
mod tests;
