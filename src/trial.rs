//! One Monte Carlo run: simulate the truth once, run every filter on it (paired comparison),
//! and reduce each filter's run to per-step values and a per-run record.
//!
//! This is where the model and filter enums are matched — once per run — before entering the
//! monomorphised step loop [`run_filter`]. The executor ([`crate::runner`]) only sees the
//! object-safe [`Trial`] trait.

use crate::experiment::{FilterKind, FilterNoiseMode, InitialMode, ModelKind, Plan};
use crate::filter::{
    BatchInitial, Ekf, Filter, FilterError, Information, Innovation, Luenberger, OpenLoop,
    RunningMean, SquareRoot, SteadyState,
};
use crate::linalg::{Matrix, SmallCholesky, Vector, diag_from_std};
use crate::metrics::{FilterRun, RunConsistency, StepValues};
use crate::model::linear::{Linear, LinearSensor};
use crate::model::planar::{Planar, PlanarImu, PlanarP1};
use crate::model::{Model, Names};
use crate::scenario::Scenario;
use crate::sim::seed::run_seed;
use crate::sim::{NoiseDraws, Trajectory, TruthNoise, simulate};

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
    /// u_k, `nu` per step.
    pub u: Vec<f64>,
    /// x_k, `nx` per step.
    pub truth: Vec<f64>,
    /// z_k, `nz` per step (NaN where a component did not report).
    pub z: Vec<f64>,
    /// Per filter: x̂_k, `nx` per step (NaN after a failure).
    pub est: Vec<Vec<f64>>,
    /// Per filter: diag P_k, `nx` per step (NaN without a covariance).
    pub var: Vec<Vec<f64>>,
}

/// What one unit produces.
#[derive(Clone, Debug, PartialEq)]
pub struct UnitResult {
    /// The unit.
    pub unit: Unit,
    /// The run's seed (all its streams derive from it).
    pub seed: u64,
    /// One record per filter, in plan order.
    pub filters: Vec<FilterRun>,
    /// Present for traced runs.
    pub trace: Option<RunTrace>,
}

/// A study that can execute units. Implemented once, generically, for every model.
pub trait Trial: Sync {
    /// Runs one unit.
    fn run(&self, unit: &Unit) -> UnitResult;
    /// Number of transitions K of a scenario.
    fn steps(&self, scenario: usize) -> usize;
    /// Column names of the model.
    fn names(&self) -> Names;
}

/// What the consistency tests need computed during a run.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ConsistencyOptions {
    /// Innovation-whiteness lags 1..=L.
    pub lags: usize,
    /// Whether the prior is not an independent draw (x̂_0 = x_0, or a batch estimate from the
    /// same measurements), so a burn-in is needed until it is forgotten.
    pub burn_in: bool,
    /// Whether to record the NEES of x̂_0 (an estimate whose covariance is to be tested).
    pub initial_nees: bool,
}

/// The initial-error term tr(P_k⁻¹ G_k) below which a step counts as free of the prior.
pub const BURN_IN_THRESHOLD: f64 = 1e-3;

/// Consistency sums from one starting step on: W_k for ρ, the whitened-innovation lags, …
struct Window<const NX: usize, const NZ: usize> {
    first: usize,
    w: Matrix<NX, NX>,
    started: bool,
    sums: RunConsistency,
    recent: std::collections::VecDeque<(Vector<NZ>, crate::model::Availability)>,
}

impl<const NX: usize, const NZ: usize> Window<NX, NZ> {
    fn new(first: usize, lags: usize) -> Self {
        Window {
            first,
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

    /// Adds step k; `a` is A_k, `p_prev` is P_{k−1}.
    #[allow(clippy::too_many_arguments)]
    fn observe(
        &mut self,
        chol: &SmallCholesky<NX>,
        p: &Matrix<NX, NX>,
        p_prev: &Matrix<NX, NX>,
        a: Option<&Matrix<NX, NX>>,
        e: &Vector<NX>,
        nees: f64,
        innovation: Option<&Innovation<NZ>>,
        lags: usize,
    ) {
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
            s.w_sq += inn.whitened.norm_squared();
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

/// Everything a filter run needs besides the filter.
pub struct RunContext<'a, const NX: usize, const NU: usize, const NZ: usize> {
    /// The scenario (controls).
    pub scenario: &'a Scenario<NX, NU>,
    /// The simulated run.
    pub trajectory: &'a Trajectory<NX, NZ>,
    /// P_0.
    pub p0: &'a Matrix<NX, NX>,
    /// Divergence thresholds.
    pub thresholds: Option<&'a [f64]>,
    /// State names (for status details).
    pub state_names: &'a [&'static str],
    /// Whether to keep the estimate trajectory.
    pub trace: bool,
    /// Consistency sums to compute, if any.
    pub consistency: Option<ConsistencyOptions>,
}

/// One filter's run: the record, and the trajectories when traced.
pub struct FilterOutput {
    /// The per-run record and per-step values.
    pub run: FilterRun,
    /// x̂_k and diag P_k when traced.
    pub trace: Option<(Vec<f64>, Vec<f64>)>,
}

/// The monomorphised step loop: predict, update, and per-step metrics.
pub fn run_filter<const NX: usize, const NU: usize, const NZ: usize, M, F>(
    model: &M,
    filter: &F,
    ctx: &RunContext<'_, NX, NU, NZ>,
) -> FilterOutput
where
    M: Model<NX, NU, NZ>,
    F: Filter<NX, NU, NZ, M>,
{
    let traj = ctx.trajectory;
    let steps = traj.truth.len() - 1;
    let mut values = StepValues::new(NX, steps);
    let mut est = ctx.trace.then(|| vec![f64::NAN; (steps + 1) * NX]);
    let mut var = ctx.trace.then(|| vec![f64::NAN; (steps + 1) * NX]);
    let mut repairs = 0u32;
    let mut failure: Option<(usize, String)> = None;
    let mut belief = filter.init(model, &traj.x0_hat, ctx.p0, &traj.measurements[0]);
    let opts = ctx.consistency;
    let lags = opts.map_or(0, |o| o.lags);
    // Truth mode: one window from step 1 and one from the end of the burn-in (G_k tracks the
    // prior's share of P_k); sampled mode: the prior is real, so every step from 1 counts.
    let mut from_start = opts.map(|_| Window::<NX, NZ>::new(1, lags));
    let mut after_burn_in: Option<Window<NX, NZ>> = None;
    let mut g = opts.filter(|o| o.burn_in).map(|_| *ctx.p0);
    let mut p_prev = *ctx.p0;

    for k in 0..=steps {
        let mut nis = f64::NAN;
        let mut innovation = None;
        if k > 0 {
            let u = &ctx.scenario.controls[k];
            let step = filter
                .predict(model, &mut belief, u)
                .and_then(|()| filter.update(model, &mut belief, u, &traj.measurements[k]));
            match step {
                Ok(Some(inn)) => {
                    nis = inn.nis;
                    values.nis_dof[k] = inn.dof as u8;
                    innovation = Some(inn);
                }
                Ok(None) => {}
                Err(e) => {
                    failure = Some((k, e.to_string()));
                    break;
                }
            }
        }
        let mean = filter.mean(&belief);
        let e: Vector<NX> = traj.truth[k] - mean;
        let mut nees = f64::NAN;
        if let Some(p) = filter.covariance(&belief) {
            let chol = match SmallCholesky::new(&p) {
                Some(c) => Some(c),
                None if filter.repair_covariance(&mut belief) => {
                    repairs += 1;
                    filter
                        .covariance(&belief)
                        .and_then(|p| SmallCholesky::new(&p))
                }
                None => None,
            };
            let Some(chol) = chol else {
                let err = FilterError::NotPositiveDefinite {
                    which: "state covariance P",
                };
                failure = Some((k, err.to_string()));
                break;
            };
            nees = chol.inverse_quadratic_form(&e);
            let p_now = filter.covariance(&belief).unwrap_or(p);
            if k > 0 && opts.is_some() {
                let a = filter.error_transition(&belief);
                if let (Some(gm), Some(a)) = (g.as_mut(), a.as_ref()) {
                    *gm = a * *gm * a.transpose();
                    if after_burn_in.is_none() && chol.solve(gm).trace() <= BURN_IN_THRESHOLD {
                        after_burn_in = Some(Window::new(k, lags));
                    }
                }
                for w in [from_start.as_mut(), after_burn_in.as_mut()]
                    .into_iter()
                    .flatten()
                {
                    w.observe(
                        &chol,
                        &p_now,
                        &p_prev,
                        a.as_ref(),
                        &e,
                        nees,
                        innovation.as_ref(),
                        lags,
                    );
                }
            }
            p_prev = p_now;
            if let Some(var) = var.as_mut() {
                let p = filter.covariance(&belief).unwrap_or(p);
                for i in 0..NX {
                    var[k * NX + i] = p[(i, i)];
                }
            }
        }
        if let Some(est) = est.as_mut() {
            est[k * NX..(k + 1) * NX].copy_from_slice(filter.mean(&belief).as_slice());
        }
        for i in 0..NX {
            values.sq_err[k * NX + i] = e[i] * e[i];
        }
        values.nees[k] = nees;
        values.nis[k] = nis;
        values.completed = k + 1;
    }
    let nees0 = values.nees[0];
    let mut run = values.finish(failure, ctx.thresholds, ctx.state_names, repairs);
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
        trace: est.zip(var),
    }
}

/// Runs a configured filter kind on a model. Filters that work on any model (the EKF) are
/// dispatched here once; a model adds the filters that only exist for it (the running mean
/// reads P1's measurements directly) in [`FilterSet::run_model_specific`].
pub trait FilterSet<const NX: usize, const NU: usize, const NZ: usize>:
    Model<NX, NU, NZ> + Sized
{
    /// Runs a filter kind that is specific to this model, or `None` if the model has no
    /// such filter (plan validation rejects those combinations).
    fn run_model_specific(
        &self,
        kind: &FilterKind,
        ctx: &RunContext<'_, NX, NU, NZ>,
    ) -> Option<FilterOutput>;

    /// Dispatches `kind` with assumed noise `q`, `r` (every kind except `steady_state` and
    /// `pole_placement`, which a [`Study`] prepares once and runs itself).
    fn run_kind(
        &self,
        kind: &FilterKind,
        q: Matrix<NX, NX>,
        r: Matrix<NZ, NZ>,
        ctx: &RunContext<'_, NX, NU, NZ>,
    ) -> FilterOutput {
        match kind {
            FilterKind::Ekf { update } => run_filter(
                self,
                &Ekf {
                    q,
                    r,
                    update_form: *update,
                },
                ctx,
            ),
            FilterKind::Information => run_filter(self, &Information::new(q, r), ctx),
            FilterKind::Sqrt => run_filter(self, &SquareRoot::new(q, r), ctx),
            FilterKind::OpenLoop => run_filter(
                self,
                &OpenLoop {
                    predictor: Ekf {
                        q,
                        r,
                        update_form: crate::filter::CovarianceUpdate::Standard,
                    },
                },
                ctx,
            ),
            // Filters prepared once per study (a DARE solution, a placed gain) are run by
            // `Study`, which caches them; everything else is cheap to build per run.
            other => self.run_model_specific(other, ctx).unwrap_or_else(|| {
                unreachable!("plan validation rejects {} for this model", other.tag())
            }),
        }
    }
}

impl FilterSet<6, 2, 3> for PlanarP1 {
    fn run_model_specific(
        &self,
        kind: &FilterKind,
        ctx: &RunContext<'_, 6, 2, 3>,
    ) -> Option<FilterOutput> {
        match kind {
            FilterKind::RunningMean { window } => {
                Some(run_filter(self, &RunningMean { window: *window }, ctx))
            }
            _ => None,
        }
    }
}

impl FilterSet<6, 2, 4> for PlanarImu {
    fn run_model_specific(
        &self,
        _kind: &FilterKind,
        _ctx: &RunContext<'_, 6, 2, 4>,
    ) -> Option<FilterOutput> {
        None
    }
}

impl<const NZ: usize> FilterSet<6, 4, NZ> for Linear<NZ> {
    fn run_model_specific(
        &self,
        _kind: &FilterKind,
        _ctx: &RunContext<'_, 6, 4, NZ>,
    ) -> Option<FilterOutput> {
        None
    }
}

/// A plan bound to a concrete model type.
pub struct Study<const NX: usize, const NU: usize, const NZ: usize, M> {
    model: M,
    scenarios: Vec<Scenario<NX, NU>>,
    noise: TruthNoise<NX, NZ>,
    p0: Matrix<NX, NX>,
    p0_factor: Option<Matrix<NX, NX>>,
    /// The model's full discrete Q, which filters assume (times q_scale) when it exists.
    model_q: Option<Matrix<NX, NX>>,
    plan: Plan,
    state_names: Vec<&'static str>,
    /// Per scenario: the batch least-squares estimator of x_0 (initial mode `batch_ls`).
    batch: Option<Vec<BatchInitial<NX>>>,
    /// Per filter entry: the placed observer (pole_placement filters).
    observers: Vec<Option<Luenberger<NX, NZ>>>,
    /// Per (filter entry, noise scale): the DARE solution, solved on first use.
    steady: Vec<std::sync::OnceLock<SteadyState<NX, NZ>>>,
}

impl<const NX: usize, const NU: usize, const NZ: usize, M: FilterSet<NX, NU, NZ>>
    Study<NX, NU, NZ, M>
{
    fn new(model: M, scenarios: Vec<Scenario<NX, NU>>, plan: &Plan) -> Self {
        let p0_std = Vector::<NX>::from_column_slice(&plan.p0_std);
        let p0 = diag_from_std(&p0_std);
        let p0_factor = (plan.initial == InitialMode::Sampled)
            .then(|| Matrix::<NX, NX>::from_diagonal(&p0_std));
        let state_names = model.names().states;
        // The batch estimator assumes the truth's noise at scale 1; validation built the same
        // estimator for every scenario already, so it cannot fail here.
        let batch = (plan.initial == InitialMode::BatchLs).then(|| {
            let q = model.process_noise_covariance().unwrap_or_else(|| {
                diag_from_std(&Vector::<NX>::from_column_slice(
                    &plan.model.process_noise_std,
                ))
            });
            let r = diag_from_std(&Vector::<NZ>::from_column_slice(
                &plan.model.measurement_noise_std,
            ));
            scenarios
                .iter()
                .map(|s| {
                    BatchInitial::new(&model, &s.controls, &q, &r)
                        .expect("plan validation builds the batch estimator of every scenario")
                })
                .collect()
        });
        let observers = plan
            .filters
            .iter()
            .map(|f| match &f.kind {
                FilterKind::PolePlacement { poles } => Some(
                    Luenberger::from_poles(&model, poles)
                        .expect("plan validation places every pole_placement filter"),
                ),
                _ => None,
            })
            .collect();
        let steady = (0..plan.filters.len() * plan.noise_scales.len())
            .map(|_| std::sync::OnceLock::new())
            .collect();
        Study {
            batch,
            observers,
            steady,
            noise: TruthNoise {
                process_std: Vector::<NX>::from_column_slice(&plan.model.process_noise_std),
                measurement_std: Vector::<NZ>::from_column_slice(&plan.model.measurement_noise_std),
            },
            model_q: model.process_noise_covariance(),
            model,
            scenarios,
            p0,
            p0_factor,
            plan: plan.clone(),
            state_names,
        }
    }
}

impl<const NX: usize, const NU: usize, const NZ: usize, M: FilterSet<NX, NU, NZ>> Trial
    for Study<NX, NU, NZ, M>
{
    fn run(&self, unit: &Unit) -> UnitResult {
        let plan = &self.plan;
        let scenario = &self.scenarios[unit.scenario];
        let noise_scale = plan.noise_scales[unit.scale];
        let seed = run_seed(plan.master_seed, &scenario.name, unit.run as u64);
        let draws = NoiseDraws::<NX, NZ>::draw(seed, scenario.steps());
        let mut trajectory = simulate(
            &self.model,
            scenario,
            &self.noise,
            noise_scale,
            self.p0_factor.as_ref(),
            &draws,
        );
        let traced = unit.run < plan.trace_runs;
        let filter_scale = match plan.filter_noise {
            FilterNoiseMode::Nominal => 1.0,
            FilterNoiseMode::Matched => noise_scale,
        };
        let p0 = match &self.batch {
            Some(batch) => {
                let b = &batch[unit.scenario];
                trajectory.x0_hat = b.estimate(&trajectory.measurements);
                b.covariance * (filter_scale * filter_scale)
            }
            None => self.p0,
        };
        let ctx = RunContext {
            scenario,
            trajectory: &trajectory,
            p0: &p0,
            thresholds: plan.rmse_thresholds.as_deref(),
            state_names: &self.state_names,
            trace: traced,
            consistency: plan.consistency.as_ref().map(|c| ConsistencyOptions {
                lags: c.whiteness_lags,
                burn_in: plan.initial != InitialMode::Sampled,
                initial_nees: plan.initial == InitialMode::BatchLs,
            }),
        };
        let mut filters = Vec::with_capacity(plan.filters.len());
        let mut est = Vec::new();
        let mut var = Vec::new();
        for (fi, f) in plan.filters.iter().enumerate() {
            let q = match &self.model_q {
                Some(q) => q * (filter_scale * filter_scale * f.q_scale),
                None => {
                    diag_from_std(&(Vector::<NX>::from_column_slice(&f.q_std) * filter_scale))
                        * f.q_scale
                }
            };
            let r = diag_from_std(&(Vector::<NZ>::from_column_slice(&f.r_std) * filter_scale))
                * f.r_scale;
            let out = match &f.kind {
                FilterKind::SteadyState => {
                    let slot = &self.steady[fi * plan.noise_scales.len() + unit.scale];
                    let filter = slot.get_or_init(|| SteadyState::new(&self.model, &q, &r));
                    run_filter(&self.model, filter, &ctx)
                }
                FilterKind::PolePlacement { .. } => {
                    let observer = self.observers[fi].as_ref().expect("built for this entry");
                    run_filter(&self.model, observer, &ctx)
                }
                kind => self.model.run_kind(kind, q, r, &ctx),
            };
            if let Some((e, v)) = out.trace {
                est.push(e);
                var.push(v);
            }
            filters.push(out.run);
        }
        let trace = traced.then(|| RunTrace {
            u: scenario
                .controls
                .iter()
                .flat_map(|u| u.iter().copied())
                .collect(),
            truth: trajectory
                .truth
                .iter()
                .flat_map(|x| x.iter().copied())
                .collect(),
            z: trajectory
                .measurements
                .iter()
                .flat_map(|m| {
                    (0..NZ).map(move |i| if m.available.has(i) { m.z[i] } else { f64::NAN })
                })
                .collect(),
            est,
            var,
        });
        UnitResult {
            unit: *unit,
            seed,
            filters,
            trace,
        }
    }

    fn steps(&self, scenario: usize) -> usize {
        self.scenarios[scenario].steps()
    }

    fn names(&self) -> Names {
        self.model.names()
    }
}

/// Binds a plan to its model type.
pub fn build(plan: &Plan) -> Box<dyn Trial> {
    let dt = plan.model.params.dt_s;
    let planar =
        || -> Vec<Scenario<6, 2>> { plan.scenarios.iter().map(|s| s.expand(dt)).collect() };
    // L1 runs with zero input (see `model::linear`): a scenario is x0 and a duration.
    let linear = || -> Vec<Scenario<6, 4>> {
        plan.scenarios
            .iter()
            .map(|s| {
                Scenario::unforced(&s.name, Vector::<6>::from_column_slice(&s.x0), s.steps(dt))
            })
            .collect()
    };
    const SIZES: &str = "ModelKind::nz matches the sensor set's size";
    match plan.model.kind {
        ModelKind::PlanarP1 => Box::new(Study::<6, 2, 3, _>::new(
            Planar::<3>::new(plan.model.params),
            planar(),
            plan,
        )),
        ModelKind::PlanarImu => Box::new(Study::<6, 2, 4, _>::new(
            Planar::<4>::new(plan.model.params),
            planar(),
            plan,
        )),
        ModelKind::LinearPositions => Box::new(Study::<6, 4, 3, _>::new(
            Linear::<3>::new(LinearSensor::Positions, dt).expect(SIZES),
            linear(),
            plan,
        )),
        ModelKind::LinearVelocities => Box::new(Study::<6, 4, 3, _>::new(
            Linear::<3>::new(LinearSensor::Velocities, dt).expect(SIZES),
            linear(),
            plan,
        )),
        ModelKind::LinearXy => Box::new(Study::<6, 4, 2, _>::new(
            Linear::<2>::new(LinearSensor::Xy, dt).expect(SIZES),
            linear(),
            plan,
        )),
    }
}
