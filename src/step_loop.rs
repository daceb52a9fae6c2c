//! The monomorphised step loop every system shares, and what one run produces.
//!
//! [`run_filter`] is the step loop: predict, update, and the per-step metrics on the evaluated
//! quantities, for one filter on one simulated run. A system's trial
//! ([`crate::trial::Trial`]) simulates the world once per run and calls it for every filter
//! (paired comparison); the exchange format replays an outside filter's rows through it, so
//! an outside filter is scored by the same code. Nothing here knows a system or a study.

use crate::filter::{Filter, FilterError, Innovation};
use crate::linalg::{Matrix, SmallCholesky, Vector};
use crate::metrics::{FilterRun, RunConsistency, RunStatus, StepValues};
use crate::model::{Measurement, Model};

/// One unit of work: a run of one (scenario, noise scale) cell.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Unit {
    /// Index into the plan's scenarios.
    pub scenario: usize,
    /// Index into the plan's noise scales.
    pub scale: usize,
    /// Run index within the cell.
    pub run: usize,
}

/// Full trajectories of a traced run, flattened row-major by step.
#[derive(Clone, Debug, PartialEq)]
pub struct RunTrace {
    /// The filters' inputs u_k, `nu` per step.
    pub u: Vec<f64>,
    /// The true evaluated quantities, `nq` per step.
    pub truth: Vec<f64>,
    /// z_k, `nz` per step (NaN where a component did not report).
    pub z: Vec<f64>,
    /// The world's own states, `world_states` per step (empty when it has none).
    pub world: Vec<f64>,
    /// Per filter: the estimated quantities, `nq` per step (NaN after a failure).
    pub est: Vec<Vec<f64>>,
    /// Per filter: the lower triangle of the quantities' covariance, row by row
    /// ((0,0), (1,0), (1,1), (2,0), …), `nq(nq+1)/2` per step (NaN without a covariance).
    pub cov: Vec<Vec<f64>>,
    /// Per filter, when the plan exports estimates: what `estimates.parquet` adds to the
    /// estimate and covariance (empty otherwise).
    pub export: Vec<Option<ExportTrace>>,
    /// The prior every filter of the run starts from, x̂_0 and the lower triangle of P_0,
    /// when the system forms one prior for all of them (`initial.parquet`).
    pub initial: Option<(Vec<f64>, Vec<f64>)>,
}

impl RunTrace {
    /// The world's part of a trace (inputs, truth, measurements with NaN where a component
    /// did not report, and the world's own states); the filters' parts are pushed after.
    pub fn of_world<const NQ: usize, const NU: usize, const NZ: usize>(
        inputs: &[Vector<NU>],
        truth: &[Vector<NQ>],
        measurements: &[Measurement<NZ>],
        world: Vec<f64>,
    ) -> Self {
        RunTrace {
            u: inputs.iter().flat_map(|u| u.iter().copied()).collect(),
            truth: truth.iter().flat_map(|x| x.iter().copied()).collect(),
            z: measurements
                .iter()
                .flat_map(|m| {
                    (0..NZ).map(move |i| if m.available.has(i) { m.z[i] } else { f64::NAN })
                })
                .collect(),
            world,
            est: Vec::new(),
            cov: Vec::new(),
            export: Vec::new(),
            initial: None,
        }
    }

    /// Adds one filter's output (a filter that kept no trajectory adds NaN rows, so every
    /// filter has its columns).
    pub fn push_filter(&mut self, out: &mut FilterOutput, nq: usize) {
        let samples = self.truth.len() / nq.max(1);
        let (e, c) = out.trace.take().unwrap_or_else(|| {
            (
                vec![f64::NAN; samples * nq],
                vec![f64::NAN; samples * nq * (nq + 1) / 2],
            )
        });
        self.est.push(e);
        self.cov.push(c);
        self.export.push(out.export.take());
    }
}

/// The lower triangle of a symmetric matrix, row by row ((0,0), (1,0), (1,1), …).
pub fn lower_triangle<const N: usize>(m: &Matrix<N, N>) -> Vec<f64> {
    (0..N)
        .flat_map(|i| (0..=i).map(move |j| m[(i, j)]))
        .collect()
}

/// What an exported run adds to the estimates, per step, flattened row-major: ν, the lower
/// triangle of S (both NaN where a component did not report, and at step 0) and the error
/// transition A_k in quantity space, row-major (NaN when the filter has none).
#[derive(Clone, Debug, PartialEq)]
pub struct ExportTrace {
    /// ν_k, `nz` per step.
    pub nu: Vec<f64>,
    /// The lower triangle of S_k, `nz(nz+1)/2` per step.
    pub s: Vec<f64>,
    /// A_k, `nq²` per step.
    pub a: Vec<f64>,
}

/// What one unit produces.
#[derive(Clone, Debug, PartialEq)]
pub struct UnitResult {
    /// The unit.
    pub unit: Unit,
    /// The run's seed (all its streams derive from it).
    pub seed: u64,
    /// One record per filter variant, in plan order.
    pub filters: Vec<FilterRun>,
    /// Present for traced runs.
    pub trace: Option<RunTrace>,
    /// The world's per-run metrics ([`crate::trial::Trial::world_metrics`] order; empty without).
    pub world_metrics: Vec<f64>,
}

/// What the consistency tests need computed during a run.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ConsistencyOptions {
    /// Innovation-whiteness lags 1..=L.
    pub lags: usize,
    /// Steps 1..=B whose innovations stay out of the whiteness sums (and out of their lag
    /// products with later steps).
    pub whiteness_burn_in: usize,
    /// Whether the prior is not an independent draw (x̂_0 = x_0, or a batch estimate from the
    /// same measurements), so a burn-in is needed until it is forgotten.
    pub burn_in: bool,
    /// Whether to record the NEES of x̂_0 (an estimate whose covariance is to be tested).
    pub initial_nees: bool,
    /// The layout's blocks of quantities, whose NEES and the signed errors are kept per step
    /// for the credibility measures ([`crate::metrics::credibility`]).
    pub blocks: crate::metrics::blocks::BlockMasks,
}

/// The initial-error term tr(P_k⁻¹ G_k) below which a step counts as free of the prior.
pub const BURN_IN_THRESHOLD: f64 = 1e-3;

/// Maps a filter's belief (state x̂ of dimension NX and its covariance) onto the NQ evaluated
/// quantities. A filter whose state holds bias or clone states, or another parameterisation,
/// is scored on the same quantities as one whose state *is* the quantities.
pub trait Evaluate<const NX: usize, const NQ: usize>: Sync {
    /// The estimated quantities q̂ = g(x̂).
    fn mean(&self, x: &Vector<NX>) -> Vector<NQ>;
    /// Their covariance: the marginal block, or G P Gᵀ with G = ∂g/∂x at x̂.
    fn covariance(&self, x: &Vector<NX>, p: &Matrix<NX, NX>) -> Matrix<NQ, NQ>;
    /// The covariance by reference when it *is* `p` (the identity evaluation): the step loop
    /// then reads the filter's P without copying it. `None` (the default): the loop forms
    /// [`Evaluate::covariance`].
    fn covariance_ref<'p>(&self, _p: &'p Matrix<NX, NX>) -> Option<&'p Matrix<NQ, NQ>> {
        None
    }
    /// The error transition in quantity space, when it exists. The calibrated NEES verdict
    /// and the burn-in rule need it; only an identity evaluation has one (a marginal of a
    /// larger state does not evolve on its own), others leave the model-free test.
    fn transition(&self, a: &Matrix<NX, NX>) -> Option<Matrix<NQ, NQ>>;
    /// The error transition at the estimate x̂_k, for an evaluation whose map depends on the
    /// estimate (a rotation's chart Jacobian J: J A J⁻¹, to first order in the step); the
    /// default is [`Evaluate::transition`].
    fn transition_at(&self, _x: &Vector<NX>, a: &Matrix<NX, NX>) -> Option<Matrix<NQ, NQ>> {
        self.transition(a)
    }
}

/// The evaluation of a filter whose state is the quantities.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Identity;

impl<const N: usize> Evaluate<N, N> for Identity {
    #[inline]
    fn mean(&self, x: &Vector<N>) -> Vector<N> {
        *x
    }
    #[inline]
    fn covariance(&self, _x: &Vector<N>, p: &Matrix<N, N>) -> Matrix<N, N> {
        *p
    }
    #[inline]
    fn covariance_ref<'p>(&self, p: &'p Matrix<N, N>) -> Option<&'p Matrix<N, N>> {
        Some(p)
    }
    #[inline]
    fn transition(&self, a: &Matrix<N, N>) -> Option<Matrix<N, N>> {
        Some(*a)
    }
}

/// The evaluation that picks quantities out of a larger state: q = x\[indices\], its covariance
/// the marginal block.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Marginal<const NQ: usize> {
    /// State index of each quantity.
    pub indices: [usize; NQ],
}

impl<const NX: usize, const NQ: usize> Evaluate<NX, NQ> for Marginal<NQ> {
    fn mean(&self, x: &Vector<NX>) -> Vector<NQ> {
        Vector::<NQ>::from_fn(|i, _| x[self.indices[i]])
    }
    fn covariance(&self, _x: &Vector<NX>, p: &Matrix<NX, NX>) -> Matrix<NQ, NQ> {
        Matrix::<NQ, NQ>::from_fn(|i, j| p[(self.indices[i], self.indices[j])])
    }
    fn transition(&self, _a: &Matrix<NX, NX>) -> Option<Matrix<NQ, NQ>> {
        None
    }
}

/// Wraps an angle error to [−π, π) (radians) or [−180, 180) (degrees).
#[inline]
pub fn wrap_angle(e: f64, degrees: bool) -> f64 {
    crate::model::wrap_symmetric(e, if degrees { 180.0 } else { std::f64::consts::PI })
}

/// What a consistency window reads of one step: the quantities' P_k (with its factor) and
/// P_{k−1}, the error transition A_k when the filter has one, the error, its NEES and the
/// step's innovation.
#[derive(Clone, Copy)]
struct WindowStep<'s, const NX: usize, const NZ: usize> {
    k: usize,
    chol: &'s SmallCholesky<NX>,
    p: &'s Matrix<NX, NX>,
    p_prev: &'s Matrix<NX, NX>,
    a: Option<&'s Matrix<NX, NX>>,
    e: &'s Vector<NX>,
    nees: f64,
    innovation: Option<&'s Innovation<NZ>>,
}

/// Consistency sums from one starting step on: W_k for ρ, the whitened-innovation lags, …
struct Window<const NX: usize, const NZ: usize> {
    first: usize,
    /// The first step whose innovation enters the whiteness sums.
    white_from: usize,
    w: Matrix<NX, NX>,
    started: bool,
    sums: RunConsistency,
    recent: std::collections::VecDeque<(Vector<NZ>, crate::model::Availability)>,
}

impl<const NX: usize, const NZ: usize> Window<NX, NZ> {
    fn new(first: usize, lags: usize, white_from: usize) -> Self {
        Window {
            first,
            white_from,
            w: Matrix::<NX, NX>::zeros(),
            started: false,
            sums: RunConsistency {
                first_step: Some(first),
                rho_sum: Some(0.0),
                nme_sum: vec![0.0; NX],
                lag_prod: vec![0.0; lags],
                lag_pairs: vec![0; lags],
                ..Default::default()
            },
            recent: std::collections::VecDeque::with_capacity(lags + 1),
        }
    }

    /// Adds step k.
    fn observe(&mut self, step: &WindowStep<'_, NX, NZ>) {
        let WindowStep {
            k,
            chol,
            p,
            p_prev,
            a,
            e,
            nees,
            innovation,
        } = *step;
        // The window keeps one lag product per lag.
        let lags = self.sums.lag_prod.len();
        match (a, self.started, &mut self.sums.rho_sum) {
            (Some(a), true, Some(rho)) => {
                self.w = a * (self.w + p_prev) * a.transpose();
                *rho += chol.solve(&self.w).trace();
            }
            (None, _, rho) => *rho = None,
            _ => {}
        }
        self.started = true;
        let s = &mut self.sums;
        s.nees_sum += nees;
        s.nees_n += 1;
        for i in 0..NX {
            s.nme_sum[i] += e[i] / p[(i, i)].sqrt();
        }
        if let Some(inn) = innovation {
            s.nis_sum += inn.nis;
            s.nis_dof += inn.dof as u64;
            s.nis_n += 1;
        }
        if let Some(inn) = innovation.filter(|_| k >= self.white_from) {
            s.w_sq += inn.whitened.norm_squared();
            s.w_n += inn.dof as u64;
            for (l, (w_old, av_old)) in self.recent.iter().rev().enumerate() {
                s.lag_prod[l] += w_old.dot(&inn.whitened);
                s.lag_pairs[l] += (av_old.0 & inn.available.0).count_ones() as u64;
            }
            if lags > 0 {
                if self.recent.len() == lags {
                    self.recent.pop_front();
                }
                self.recent.push_back((inn.whitened, inn.available));
            }
        }
    }
}

/// The initial belief every filter of a run starts from, in the filters' state space.
#[derive(Clone, Copy, Debug)]
pub struct Prior<'a, const NX: usize> {
    /// x̂_0.
    pub x0_hat: &'a Vector<NX>,
    /// P_0.
    pub p0: &'a Matrix<NX, NX>,
}

/// Everything a filter run needs besides the filter: the world's output for this run.
pub struct RunContext<'a, const NQ: usize, const NU: usize, const NZ: usize> {
    /// The true evaluated quantities q_0..q_K.
    pub truth: &'a [Vector<NQ>],
    /// The inputs the filter receives, u_0..u_K (u_k drives the transition k−1 → k): the
    /// controls, or measured IMU samples.
    pub inputs: &'a [Vector<NU>],
    /// z_0..z_K with their availability.
    pub measurements: &'a [Measurement<NZ>],
    /// Indices of the angle quantities (their errors are wrapped), and whether in degrees.
    pub angles: &'a [(usize, bool)],
    /// The rotations among the quantities ([`crate::system::Layout::rotations`]): their error
    /// is the rotation error, and the evaluation reports its covariance.
    pub rotations: &'a [crate::linalg::so3::EulerRotation],
    /// Divergence thresholds per quantity.
    pub thresholds: Option<&'a [f64]>,
    /// Quantity names (for status details).
    pub quantity_names: &'a [&'a str],
    /// Whether to keep the estimate trajectory.
    pub trace: bool,
    /// Whether to keep what `estimates.parquet` needs beyond the trajectory (ν, S, A); implies
    /// `trace`.
    pub export: bool,
    /// Consistency sums to compute, if any.
    pub consistency: Option<ConsistencyOptions>,
    /// The unit being run (external estimates are looked up by it).
    pub unit: Unit,
}

/// One filter's run: the record, and the trajectories when traced.
pub struct FilterOutput {
    /// The per-run record and per-step values.
    pub run: FilterRun,
    /// The estimated quantities and their covariance's lower triangle when traced (see
    /// [`RunTrace`]).
    pub trace: Option<(Vec<f64>, Vec<f64>)>,
    /// ν, S and A when the run is exported.
    pub export: Option<ExportTrace>,
}

impl FilterOutput {
    /// The record of a run that failed before its first step (no usable prior): every
    /// per-step value null, `why` in its failure column. The batch goes on.
    pub fn failed_at_start<const NQ: usize, const NU: usize, const NZ: usize>(
        ctx: &RunContext<'_, NQ, NU, NZ>,
        why: String,
    ) -> Self {
        FilterOutput {
            run: StepValues::new(NQ, ctx.truth.len() - 1).finish(
                Some((0, why)),
                ctx.thresholds,
                ctx.quantity_names,
                0,
            ),
            trace: None,
            export: None,
        }
    }

    /// The record of a run the filter has no data for (an external filter's estimates leave
    /// it out): status `missing`, every per-step value null. It is no failure: the study
    /// counts it apart, and a case judged on the declared runs is incomplete without it.
    pub fn missing<const NQ: usize, const NU: usize, const NZ: usize>(
        ctx: &RunContext<'_, NQ, NU, NZ>,
        why: String,
    ) -> Self {
        let mut run =
            StepValues::new(NQ, ctx.truth.len() - 1).finish(None, None, ctx.quantity_names, 0);
        run.status = RunStatus::Missing { detail: why };
        FilterOutput {
            run,
            trace: None,
            export: None,
        }
    }
}

/// The monomorphised step loop: predict, update, and per-step metrics on the quantities that
/// `eval` maps the filter's belief to.
///
/// It is one long function on purpose: it is the hot loop of every study, and keeping the
/// step's error, NEES, consistency sums and trace in one body lets the compiler keep the
/// fixed-size matrices in registers and form the quantities' covariance once per step for all
/// of them; the parts it calls out to are the ones that are not per step.
pub fn run_filter<const NX: usize, const NU: usize, const NZ: usize, const NQ: usize, M, F, E>(
    model: &M,
    filter: &F,
    eval: &E,
    prior: &Prior<'_, NX>,
    ctx: &RunContext<'_, NQ, NU, NZ>,
) -> FilterOutput
where
    M: Model<NX, NU, NZ>,
    F: Filter<NX, NU, NZ, M>,
    E: Evaluate<NX, NQ>,
{
    let steps = ctx.truth.len() - 1;
    let ntri = NQ * (NQ + 1) / 2;
    let mut values = StepValues::new(NQ, steps);
    let traced = ctx.trace || ctx.export;
    let mut est = traced.then(|| vec![f64::NAN; (steps + 1) * NQ]);
    let mut cov = traced.then(|| vec![f64::NAN; (steps + 1) * ntri]);
    let ztri = NZ * (NZ + 1) / 2;
    let mut export = ctx.export.then(|| ExportTrace {
        nu: vec![f64::NAN; (steps + 1) * NZ],
        s: vec![f64::NAN; (steps + 1) * ztri],
        a: vec![f64::NAN; (steps + 1) * NQ * NQ],
    });
    let mut repairs = 0u32;
    let mut failure: Option<(usize, String)> = None;
    let mut belief = filter.init(model, prior.x0_hat, prior.p0, &ctx.measurements[0]);
    let opts = ctx.consistency;
    let lags = opts.map_or(0, |o| o.lags);
    let mut block_nees = [f64::NAN; crate::metrics::blocks::MAX_BLOCKS];
    if let Some(o) = opts {
        values.enable_credibility(o.blocks.len());
    }
    // Truth mode: one window from step 1 and one from the end of the burn-in (G_k tracks the
    // prior's share of P_k); sampled mode: the prior is real, so every step from 1 counts.
    let white_from = opts.map_or(1, |o| o.whiteness_burn_in + 1);
    let mut from_start = opts.map(|_| Window::<NQ, NZ>::new(1, lags, white_from));
    let mut after_burn_in: Option<Window<NQ, NZ>> = None;
    let p0_q = eval.covariance(prior.x0_hat, prior.p0);
    let mut g = opts.filter(|o| o.burn_in).map(|_| p0_q);
    let mut p_prev = p0_q;

    // The quantities' covariance when it cannot be borrowed from the belief, and P's factor:
    // both live across steps, so neither is moved out of a return value every step.
    let mut p_own = p0_q;
    let mut chol = SmallCholesky::<NQ>::unfactored();

    for k in 0..=steps {
        let mut nis = f64::NAN;
        let mut nis_dof = 0;
        let innovation = if k > 0 {
            let u = &ctx.inputs[k];
            let step = filter
                .predict(model, &mut belief, u)
                .and_then(|()| filter.update(model, &mut belief, u, &ctx.measurements[k]));
            match step {
                Ok(inn) => inn,
                Err(e) => {
                    failure = Some((k, e.to_string()));
                    break;
                }
            }
        } else {
            None
        };
        if let Some(inn) = &innovation {
            if let Some(x) = export.as_mut() {
                record_innovation(x, k, inn);
            }
            nis = inn.nis;
            nis_dof = inn.dof as u8;
        }
        let x = filter.mean(&belief);
        let mean = eval.mean(&x);
        let mut e: Vector<NQ> = ctx.truth[k] - mean;
        for &(i, degrees) in ctx.angles {
            e[i] = wrap_angle(e[i], degrees);
        }
        for r in ctx.rotations {
            r.error_into(ctx.truth[k].as_slice(), mean.as_slice(), e.as_mut_slice());
        }
        // An error whose square is not finite makes the RMSE infinite or NaN: the run fails
        // numerically at this step, as it does when the filter reports an error (after the
        // covariance's own check, which names the cause when P broke down with it).
        let bad_error = (0..NQ).find(|&i| !(e[i] * e[i]).is_finite());
        let mut nees = f64::NAN;
        // The quantities' covariance, formed once per step (after a repair, the repaired
        // one): NEES, the consistency sums and the trace all read this one value.
        let mut factored = quantity_covariance(model, filter, eval, &belief, &x, &mut p_own)
            .map(|p| chol.factor(p));
        if factored == Some(false) && filter.repair_covariance(&mut belief) {
            repairs += 1;
            factored = Some(
                quantity_covariance(model, filter, eval, &belief, &x, &mut p_own)
                    .is_some_and(|p| chol.factor(p)),
            );
        }
        if let Some(ok) = factored {
            if !ok {
                let err = FilterError::NotPositiveDefinite {
                    which: "state covariance P",
                };
                failure = Some((k, err.to_string()));
                break;
            }
            if let Some(i) = bad_error {
                failure = Some((k, non_finite_error(ctx.quantity_names[i], e[i])));
                break;
            }
            // Formed above: borrowed from the belief, or in `p_own`.
            let p_now = filter
                .covariance_ref(&belief)
                .and_then(|p| eval.covariance_ref(p))
                .unwrap_or(&p_own);
            nees = chol.inverse_quadratic_form(&e);
            if !nees.is_finite() {
                failure = Some((
                    k,
                    format!("NEES eᵀP⁻¹e = {nees} is not finite (P is singular to this error)"),
                ));
                break;
            }
            if let Some(o) = opts {
                o.blocks.nees(&e, p_now, nees, &mut block_nees);
                values.record_credibility(k, e.as_slice(), &block_nees);
            }
            if k > 0 && opts.is_some() {
                let a = filter
                    .error_transition(&belief)
                    .and_then(|a| eval.transition_at(&x, &a));
                if let (Some(gm), Some(a)) = (g.as_mut(), a.as_ref()) {
                    *gm = a * *gm * a.transpose();
                    if after_burn_in.is_none() && chol.solve(gm).trace() <= BURN_IN_THRESHOLD {
                        after_burn_in = Some(Window::new(k, lags, white_from));
                    }
                }
                let step = WindowStep {
                    k,
                    chol: &chol,
                    p: p_now,
                    p_prev: &p_prev,
                    a: a.as_ref(),
                    e: &e,
                    nees,
                    innovation: innovation.as_ref(),
                };
                for w in [from_start.as_mut(), after_burn_in.as_mut()]
                    .into_iter()
                    .flatten()
                {
                    w.observe(&step);
                }
            }
            if opts.is_some() {
                p_prev = *p_now;
            }
            if let Some(cov) = cov.as_mut() {
                let row = &mut cov[k * ntri..(k + 1) * ntri];
                let mut t = 0;
                for i in 0..NQ {
                    for j in 0..=i {
                        row[t] = p_now[(i, j)];
                        t += 1;
                    }
                }
            }
        }
        if let Some(i) = bad_error {
            failure = Some((k, non_finite_error(ctx.quantity_names[i], e[i])));
            break;
        }
        if let Some(est) = est.as_mut() {
            est[k * NQ..(k + 1) * NQ].copy_from_slice(eval.mean(&filter.mean(&belief)).as_slice());
        }
        if k > 0
            && let Some(x) = export.as_mut()
            && let Some(a) = filter
                .error_transition(&belief)
                .and_then(|a| eval.transition_at(&filter.mean(&belief), &a))
        {
            x.a[k * NQ * NQ..(k + 1) * NQ * NQ]
                .iter_mut()
                .enumerate()
                .for_each(|(t, v)| *v = a[(t / NQ, t % NQ)]);
        }
        values.record(&e.data.0[0], nees, nis, nis_dof);
    }
    repairs += filter.internal_repairs(&belief);
    let nees0 = values.nees()[0];
    let mut run = values.finish(failure, ctx.thresholds, ctx.quantity_names, repairs);
    run.consistency = match (after_burn_in, from_start) {
        (Some(w), _) => Some(w.sums),
        (None, Some(w)) if w.started => {
            let mut sums = w.sums;
            // In truth mode the burn-in was never reached: say so; sampled mode starts at 1.
            sums.first_step = (!opts.is_some_and(|o| o.burn_in)).then_some(w.first);
            Some(sums)
        }
        _ => None,
    };
    if let Some(c) = run.consistency.as_mut() {
        c.initial_nees = opts.is_some_and(|o| o.initial_nees).then_some(nees0);
    }
    FilterOutput {
        run,
        trace: est.zip(cov),
        export,
    }
}

/// Why a run stops at an error e = truth − estimate of quantity `name` whose square is not
/// finite.
#[cold]
fn non_finite_error(name: &str, e: f64) -> String {
    if e.is_nan() {
        format!("the error of {name} is NaN (a non-finite estimate)")
    } else {
        format!("the error of {name}, {e:e}, squares to a non-finite value")
    }
}

/// The quantities' covariance of a belief: borrowed when the filter holds P and the
/// evaluation is the identity, otherwise formed into `own`; `None` without a covariance.
#[inline(always)]
fn quantity_covariance<
    'a,
    const NX: usize,
    const NU: usize,
    const NZ: usize,
    const NQ: usize,
    M,
    F,
    E,
>(
    _model: &M,
    filter: &F,
    eval: &E,
    belief: &'a F::Belief,
    x: &Vector<NX>,
    own: &'a mut Matrix<NQ, NQ>,
) -> Option<&'a Matrix<NQ, NQ>>
where
    M: Model<NX, NU, NZ>,
    F: Filter<NX, NU, NZ, M>,
    E: Evaluate<NX, NQ>,
{
    if let Some(p) = filter.covariance_ref(belief) {
        return Some(match eval.covariance_ref(p) {
            Some(q) => q,
            None => {
                *own = eval.covariance(x, p);
                own
            }
        });
    }
    let p = filter.covariance(belief)?;
    *own = eval.covariance(x, &p);
    Some(own)
}

/// Writes ν_k and S_k's lower triangle over the reporting components into an export.
///
/// A filter that never forms S (the drone's sequential scalar updates) exports its whitened
/// innovation L⁻¹ν with S = I instead: the pair has the same NIS ‖L⁻¹ν‖² and the same
/// whitened sequence, so `kfmc score` recomputes exactly the NIS and whiteness tests the
/// filter's own study computed, where ν alone without S could not be judged at all.
fn record_innovation<const NZ: usize>(x: &mut ExportTrace, k: usize, inn: &Innovation<NZ>) {
    let ztri = NZ * (NZ + 1) / 2;
    let row = &mut x.nu[k * NZ..(k + 1) * NZ];
    let values = if inn.covariance.is_some() {
        &inn.residual
    } else {
        &inn.whitened
    };
    for (i, v) in row.iter_mut().enumerate() {
        if inn.available.has(i) {
            *v = values[i];
        }
    }
    if inn.covariance.is_none() {
        let row = &mut x.s[k * ztri..(k + 1) * ztri];
        for i in 0..NZ {
            if inn.available.has(i) {
                // The diagonal of the lower triangle: entry i(i+1)/2 + i.
                row[i * (i + 1) / 2 + i] = 1.0;
                for j in 0..i {
                    if inn.available.has(j) {
                        row[i * (i + 1) / 2 + j] = 0.0;
                    }
                }
            }
        }
    }
    if let Some(s) = &inn.covariance {
        let row = &mut x.s[k * ztri..(k + 1) * ztri];
        let mut t = 0;
        for i in 0..NZ {
            for j in 0..=i {
                if inn.available.has(i) && inn.available.has(j) {
                    row[t] = s[(i, j)];
                }
                t += 1;
            }
        }
    }
}
