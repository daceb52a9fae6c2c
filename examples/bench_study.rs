//! Speed of whole studies: `kfmc run`'s library path (plan → executor → in-order folding →
//! Parquet tables in a folder) against a minimal hand-written Monte Carlo kernel doing the same
//! work (simulate the truth, run the filter, keep per-step errors, NEES and NIS, fold them per
//! step across runs), same model, same runs and steps, both on every core with rayon.
//!
//! ```text
//! cargo run --release --example bench_study                 # full size (~4,000 runs per case)
//! cargo run --release --example bench_study -- --scale 0.1  # a tenth of the runs
//! cargo run --release --example bench_study -- --rounds 7 --case p1_ekf --case seed
//! cargo run --release --example bench_study -- --case p1_ekf --only kfmc   # for a profiler
//! cargo run --release --example bench_study -- --case p1_ekf --only trial  # runs without the study
//! ```
//!
//! Cases: `p1_ekf` (P1 planar quadrotor, EKF only, basic scenario, 4,000 runs × 1,001 samples),
//! `seed` (the seeds' study: EKF + running mean on the four scenarios, 1,000 runs each),
//! `l1_kf` (the linear quadrotor L1, positions sensor, the covariance-form KF, 4,000 runs ×
//! 1,001 samples) and `drone_ekf9` (seed 004's drone, the principled 9-state sequential EKF,
//! 1,000 runs of 10 s).
//!
//! Method: kfmc and the kernel alternate, round after round; each round's wall and CPU times
//! give a ratio, and the median and range of the ratios over the rounds are reported (the
//! machine is shared, so absolute times are printed only for context). Before timing, run 0
//! of each case is run by both sides and their mean NEES compared, which shows that the kernel
//! does the same work on the same numbers.
//!
//! The kernels are written for exactly their model: F = I + A·Δt applied as a sparse update,
//! H a row selection, explicit small inverses for S, no masking, no per-run status, no tables.
//! They draw the same normals (the same seeded streams) and fold per-step sums in run order.
//! The drone kernel simulates its world with the library's `World::simulate` (the IMU, GPS and
//! barometer models are the world, not the estimator under test) and writes the sequential
//! Joseph EKF and the metrics by hand on the library's model functions.

use std::hint::black_box;
use std::path::{Path, PathBuf};
use std::time::Instant;

use kfmc::experiment::{self, Plan};
use kfmc::linalg::{Matrix, SmallCholesky, Vector};
use kfmc::model::Model;
use kfmc::runner::NullObserver;
use kfmc::sim::seed::{StreamKind, stream};
use kfmc::step_loop::Unit;
use kfmc::study::{ExecOptions, run};
use kfmc::system::additive::AdditivePlan;
use kfmc::system::world::WorldPlan;
use kfmc::systems::drone::filters::{Augmentation, Nav, Principled};
use kfmc::systems::drone::world::DroneParams;
use kfmc::systems::linear_quadrotor::model::Linear;
use kfmc::systems::planar::model::PlanarP1;
use rand_distr::{Distribution, StandardNormal};
use rayon::prelude::*;

/// Per-step sums across runs: what the kernel keeps of each run (a minimal `steps` table).
struct StepSums {
    nq: usize,
    sq: Vec<f64>,
    nees: Vec<f64>,
    nis: Vec<f64>,
}

impl StepSums {
    fn new(nq: usize, samples: usize) -> Self {
        StepSums {
            nq,
            sq: vec![0.0; samples * nq],
            nees: vec![0.0; samples],
            nis: vec![0.0; samples],
        }
    }
    fn fold(&mut self, r: &RunOut) {
        for (s, v) in self.sq.iter_mut().zip(&r.sq) {
            *s += v;
        }
        for (s, v) in self.nees.iter_mut().zip(&r.nees) {
            *s += v;
        }
        for (s, v) in self.nis.iter_mut().zip(&r.nis) {
            *s += v;
        }
    }
    fn checksum(&self) -> f64 {
        self.sq.iter().sum::<f64>() / self.nq as f64 + self.nees.iter().sum::<f64>()
    }
}

/// One filter's per-step values of one run.
struct RunOut {
    sq: Vec<f64>,
    nees: Vec<f64>,
    nis: Vec<f64>,
}

impl RunOut {
    fn new(nq: usize, samples: usize) -> Self {
        RunOut {
            sq: vec![0.0; samples * nq],
            nees: vec![0.0; samples],
            nis: vec![0.0; samples],
        }
    }
    fn mean_nees(&self) -> f64 {
        self.nees[1..].iter().sum::<f64>() / (self.nees.len() - 1) as f64
    }
}

/// Runs `units` runs on every core in windows of 256 (as the executor does, to bound memory)
/// and folds each window's runs in run order; each run yields one [`RunOut`] per filter.
fn monte_carlo(
    units: usize,
    filters: usize,
    nq: usize,
    samples: impl Fn(usize) -> usize + Sync,
    work: impl Fn(usize) -> Vec<RunOut> + Sync,
) -> f64 {
    let mut sums: Vec<Option<StepSums>> = (0..filters).map(|_| None).collect();
    let mut checksum = 0.0;
    let mut cell_samples = usize::MAX;
    for start in (0..units).step_by(256) {
        let outs: Vec<(usize, Vec<RunOut>)> = (start..(start + 256).min(units))
            .into_par_iter()
            .map(|u| (samples(u), work(u)))
            .collect();
        for (n, out) in outs {
            if n != cell_samples {
                checksum += sums.iter().flatten().map(StepSums::checksum).sum::<f64>();
                sums = (0..filters).map(|_| Some(StepSums::new(nq, n))).collect();
                cell_samples = n;
            }
            for (s, r) in sums.iter_mut().zip(&out) {
                s.as_mut().expect("set above").fold(r);
            }
        }
    }
    checksum + sums.iter().flatten().map(StepSums::checksum).sum::<f64>()
}

/// NEES eᵀP⁻¹e through the library's unrolled Cholesky (the factorisation is not what the
/// comparison is about).
#[inline]
fn nees<const N: usize>(p: &Matrix<N, N>, e: &Vector<N>) -> f64 {
    SmallCholesky::new(p).map_or(f64::NAN, |c| c.inverse_quadratic_form(e))
}

fn normals<const N: usize>(rng: &mut rand_pcg::Pcg64) -> Vector<N> {
    Vector::<N>::from_fn(|_, _| StandardNormal.sample(rng))
}

fn wrap(a: f64) -> f64 {
    (a + std::f64::consts::PI).rem_euclid(2.0 * std::f64::consts::PI) - std::f64::consts::PI
}

// ---------------------------------------------------------------------------------------------
// P1 planar quadrotor: EKF (and the running mean of the seeds).

type P1Plan = AdditivePlan<6, 2, 3, PlanarP1>;

/// P⁻ = F P Fᵀ + Q for F = I + E, E given by its non-zero entries.
#[inline(always)]
fn sparse_fpft<const N: usize>(
    p: &Matrix<N, N>,
    e: &[(usize, usize, f64)],
    q: &Matrix<N, N>,
) -> Matrix<N, N> {
    let mut fp = *p;
    for &(i, j, v) in e {
        for c in 0..N {
            fp[(i, c)] += v * p[(j, c)];
        }
    }
    let mut out = fp;
    for &(i, j, v) in e {
        for r in 0..N {
            out[(r, i)] += v * fp[(r, j)];
        }
    }
    out + q
}

/// One P1 run: truth, EKF and (with `window`) the running mean, as the seeds' code does.
fn p1_run(
    sys: &P1Plan,
    plan: &Plan,
    scenario: usize,
    run: usize,
    window: Option<usize>,
) -> Vec<RunOut> {
    let sc = &sys.scenarios[plan.scenarios[scenario].index];
    let prm = &sys.model.params;
    let (m, arm, inertia, g, dt) = (
        prm.mass_kg,
        prm.arm_m,
        prm.inertia_kg_m2,
        prm.gravity_m_s2,
        prm.dt_s,
    );
    let seed = plan.run_seed(&sc.name, 0, run);
    let mut wr = stream(seed, StreamKind::ProcessNoise);
    let mut vr = stream(seed, StreamKind::MeasurementNoise);
    let w_std = sys.truth_noise.process_std;
    let v_std = sys.truth_noise.measurement_std;
    let fp = &plan.filters[0];
    let (q_std, r_std) = (0.003, 0.01);
    let q = Matrix::<6, 6>::identity() * (q_std * q_std * fp.q_scale);
    let r = Matrix::<3, 3>::identity() * (r_std * r_std * fp.r_scale);
    let samples = sc.steps() + 1;
    let mut ekf = RunOut::new(6, samples);
    let mut rm = window.map(|_| RunOut::new(6, samples));
    let f = |x: &Vector<6>, u: &Vector<2>, s: f64, c: f64| {
        let thrust = u[0] + u[1];
        Vector::<6>::new(
            x[0] + x[1] * dt,
            x[1] - s * thrust / m * dt,
            x[2] + x[3] * dt,
            x[3] + (c * thrust / m - g) * dt,
            x[4] + x[5] * dt,
            x[5] + (arm / inertia * u[0] - arm / inertia * u[1]) * dt,
        )
    };
    let mut x = sc.x0;
    let mut xh = sc.x0;
    let mut p = Matrix::<6, 6>::identity();
    let mut ring = [Vector::<3>::zeros(); 32];
    let w = window.unwrap_or(1);
    ring[0] = Vector::<3>::new(x[2], x[4], x[5]);
    let mut xr = sc.x0;
    ekf.nees[0] = nees(&p, &(x - xh));
    for k in 1..samples {
        let u = &sc.controls[k];
        let (s, c) = x[4].sin_cos();
        x = f(&x, u, s, c) + w_std.component_mul(&normals::<6>(&mut wr));
        let z = Vector::<3>::new(x[2], x[4], x[5]) + v_std.component_mul(&normals::<3>(&mut vr));
        // EKF: F = I + A·Δt at the previous estimate, H selects y, θ, θ̇.
        let thrust = u[0] + u[1];
        let (s, c) = xh[4].sin_cos();
        let e = [
            (0, 1, dt),
            (1, 4, -c * thrust / m * dt),
            (2, 3, dt),
            (3, 4, -s * thrust / m * dt),
            (4, 5, dt),
        ];
        xh = f(&xh, u, s, c);
        let pp = sparse_fpft(&p, &e, &q);
        const SEL: [usize; 3] = [2, 4, 5];
        let sm = Matrix::<3, 3>::from_fn(|i, j| pp[(SEL[i], SEL[j])]) + r;
        let pht = Matrix::<6, 3>::from_fn(|i, j| pp[(i, SEL[j])]);
        let mut nu = z - Vector::<3>::new(xh[2], xh[4], xh[5]);
        nu[1] = wrap(nu[1]);
        let si = sm.try_inverse().expect("S invertible");
        let kg = pht * si;
        xh += kg * nu;
        // P = (I − K H) P⁻ = P⁻ − K (H P⁻), H P⁻ the selected rows.
        let hp = Matrix::<3, 6>::from_fn(|i, j| pp[(SEL[i], j)]);
        p = pp - kg * hp;
        ekf.nis[k] = (nu.transpose() * si * nu)[(0, 0)];
        let err = x - xh;
        ekf.nees[k] = nees(&p, &err);
        for i in 0..6 {
            ekf.sq[k * 6 + i] = err[i] * err[i];
        }
        if let Some(out) = rm.as_mut() {
            ring[k % w] = z;
            let n = (k + 1).min(w);
            let mut sum = Vector::<3>::zeros();
            for j in (k + 1 - n)..=k {
                sum += ring[j % w];
            }
            let sm = sum / n as f64;
            let prev = xr;
            let (s, c) = sm[1].sin_cos();
            xr = Vector::<6>::new(
                prev[0] + prev[1] * dt,
                prev[1] - s * thrust / m * dt,
                sm[0],
                prev[3] + (c * thrust / m - g) * dt,
                sm[1],
                sm[2],
            );
            let err = x - xr;
            for i in 0..6 {
                out.sq[k * 6 + i] = err[i] * err[i];
            }
        }
    }
    let mut v = vec![ekf];
    v.extend(rm);
    v
}

// ---------------------------------------------------------------------------------------------
// L1 linear quadrotor: the covariance-form KF.

type L1Plan = AdditivePlan<6, 4, 3, Linear<3>>;

fn l1_run(sys: &L1Plan, plan: &Plan, run: usize) -> Vec<RunOut> {
    let sc = &sys.scenarios[plan.scenarios[0].index];
    let d = sys.model.discrete();
    let (f, g, h) = (&d.f, &d.g, sys.model.h());
    let qm = sys
        .model
        .process_noise_covariance()
        .expect("L1 has a full Q");
    let l = SmallCholesky::new(&qm).expect("Q positive definite").l();
    let seed = plan.run_seed(&sc.name, 0, run);
    let mut wr = stream(seed, StreamKind::ProcessNoise);
    let mut vr = stream(seed, StreamKind::MeasurementNoise);
    let mut ir = stream(seed, StreamKind::InitialEstimate);
    let v_std = sys.truth_noise.measurement_std;
    let r = Matrix::<3, 3>::from_diagonal(&v_std.component_mul(&v_std));
    let samples = sc.steps() + 1;
    let mut out = RunOut::new(6, samples);
    // The draws of a run come in the library's order: every ξ_k, then ζ.
    let xi: Vec<Vector<6>> = (1..samples).map(|_| normals::<6>(&mut wr)).collect();
    let mut x = sc.x0;
    let mut xh = sc.x0 + normals::<6>(&mut ir);
    let mut p = Matrix::<6, 6>::identity();
    out.nees[0] = nees(&p, &(x - xh));
    for k in 1..samples {
        let u = &sc.controls[k];
        x = f * x + g * u + l * xi[k - 1];
        let z = h * x + v_std.component_mul(&normals::<3>(&mut vr));
        xh = f * xh + g * u;
        let pp = f * p * f.transpose() + qm;
        // The textbook step of `bench_step`'s hand-written KF: K = P⁻Hᵀ S⁻¹, P = (I − KH) P⁻.
        let s = h * pp * h.transpose() + r;
        let si = s.try_inverse().expect("S invertible");
        let kg = pp * h.transpose() * si;
        let nu = z - h * xh;
        xh += kg * nu;
        p = (Matrix::<6, 6>::identity() - kg * h) * pp;
        out.nis[k] = (nu.transpose() * si * nu)[(0, 0)];
        let err = x - xh;
        out.nees[k] = nees(&p, &err);
        for i in 0..6 {
            out.sq[k * 6 + i] = err[i] * err[i];
        }
    }
    vec![out]
}

// ---------------------------------------------------------------------------------------------
// The drone: the principled 9-state sequential EKF (Joseph form), world from the library.

type DronePlan = WorldPlan<9, 6, 13>;

/// The ekf9 model with default parameters, as `kind = "ekf9"` builds it at noise scale 1.
fn drone_model(p: &DroneParams) -> Principled<9> {
    let sq = |a: [f64; 3]| Vector::<3>::from(a).map(|x| x * x);
    let mut r = [0.0; 13];
    for i in 0..3 {
        r[i] = p.gps_position_std[i].powi(2) + p.gps_drift_std[i].powi(2);
        r[3 + i] = p.gps_velocity_std[i].powi(2);
    }
    r[9] = p.baro_std.powi(2);
    Principled {
        dt: p.dt_s,
        imu: p.imu_output,
        g: p.gravity(),
        accel_var: sq(p.accel_white_std),
        gyro_var: sq(p.gyro_white_std),
        baro_drift_var: p.baro_drift_rw.powi(2) * p.dt_s,
        r,
        aug: Augmentation::default(),
        gps_period: p.gps_period(),
    }
}

fn drone_run(
    sys: &DronePlan,
    plan: &Plan,
    model: &Principled<9>,
    params: &DroneParams,
    scenario: usize,
    run: usize,
) -> Vec<RunOut> {
    let si = plan.scenarios[scenario].index;
    let seed = plan.run_seed(&sys.scenario_info[si].name, 0, run);
    let real = sys.world.simulate(si, 1.0, seed);
    let samples = real.truth.len();
    let mut out = RunOut::new(9, samples);
    let deg = 180.0 / std::f64::consts::PI;
    // Prior from the first GPS fix and a drawn attitude error (as ekf9 does).
    let z0 = &real.measurements[0].z;
    let mut xh = Vector::<9>::zeros();
    let mut p = Matrix::<9, 9>::zeros();
    for i in 0..3 {
        let sa = params.initial_attitude_std_deg[i].to_radians();
        xh[i] = z0[i];
        xh[3 + i] = z0[3 + i];
        xh[6 + i] = real.truth[0][6 + i].to_radians() + sa * real.prior_draws[i];
        p[(i, i)] = params.gps_position_std[i].powi(2) + params.gps_drift_std[i].powi(2);
        p[(3 + i, 3 + i)] = params.gps_velocity_std[i].powi(2);
        p[(6 + i, 6 + i)] = sa * sa;
    }
    let err_of = |truth: &Vector<9>, xh: &Vector<9>| {
        let mut e = Vector::<9>::zeros();
        for i in 0..6 {
            e[i] = truth[i] - xh[i];
        }
        for i in 6..9 {
            e[i] = wrap(truth[i] / deg - xh[i]);
        }
        e
    };
    out.nees[0] = nees(&p, &err_of(&real.truth[0], &xh));
    for k in 1..samples {
        let u = &real.inputs[k];
        let f = model.transition_jacobian(&xh, u);
        let q = model.process_noise(&xh, u);
        xh = model.propagate(&xh, u);
        p = f * p * f.transpose() + q;
        let zm = &real.measurements[k];
        let mut nis = 0.0;
        let mut any = false;
        // Position, velocity and barometer are direct reads of states 0–5 and −z: scalar
        // updates on one row each, P h = a column (or minus one).
        let zp = model.measure(&xh, u);
        let x_prior = xh;
        for (i, state, sign) in [
            (0, 0, 1.0),
            (1, 1, 1.0),
            (2, 2, 1.0),
            (3, 3, 1.0),
            (4, 4, 1.0),
            (5, 5, 1.0),
            (9, 2, -1.0),
        ] {
            if !zm.available.has(i) {
                continue;
            }
            any = true;
            let nu = (zm.z[i] - zp[i]) - sign * (xh[state] - x_prior[state]);
            let ph = p.column(state) * sign;
            let s = sign * ph[state] + model.r[i];
            let kg = ph / s;
            xh += kg * nu;
            // Joseph: (I − k hᵀ) P (I − k hᵀ)ᵀ + k kᵀ r = P − k phᵀ − ph kᵀ + k kᵀ (s).
            p += kg * kg.transpose() * s - kg * ph.transpose() - ph * kg.transpose();
            nis += nu * nu / s;
        }
        if any {
            out.nis[k] = nis;
        }
        let e = err_of(&real.truth[k], &xh);
        out.nees[k] = nees(&p, &e);
        for i in 0..9 {
            let ei = if i < 6 { e[i] } else { e[i] * deg };
            out.sq[k * 9 + i] = ei * ei;
        }
    }
    vec![out]
}

// ---------------------------------------------------------------------------------------------
// The harness.

/// A case: a spec, and the kernel that does its work.
struct Case {
    name: &'static str,
    about: &'static str,
    spec: String,
}

fn spec_of(name: &str, runs: usize) -> String {
    match name {
        "p1_ekf" => format!(
            r#"name = "bench_p1_ekf"
master_seed = 47
runs = {runs}
[model]
kind = "planar_quadrotor"
sensor = "p1"
process_noise_std = 0.003
measurement_noise_std = 0.01
[[scenarios]]
name = "basic"
[[filters]]
label = "ekf"
kind = "ekf"
q_std = 0.003
r_std = 0.01
[initial_estimate]
mode = "truth"
p0_std = 1.0
"#
        ),
        "seed" => {
            let path =
                Path::new(env!("CARGO_MANIFEST_DIR")).join("experiments/planar_seed_study.toml");
            let text = std::fs::read_to_string(path).expect("bundled spec");
            text.lines()
                .map(|l| {
                    if l.starts_with("runs =") {
                        format!("runs = {runs}")
                    } else if l.starts_with("trace_runs") || l.starts_with("output") {
                        String::new()
                    } else {
                        l.to_string()
                    }
                })
                .collect::<Vec<_>>()
                .join("\n")
        }
        "l1_kf" => format!(
            r#"name = "bench_l1_kf"
master_seed = 2016
runs = {runs}
[model]
kind = "linear_quadrotor"
sensor = "positions"
[[scenarios]]
name = "hover"
x0 = [1.0, 0.0, 1.0, 0.0, 1.0, 0.0]
duration_s = 100.0
[[filters]]
label = "kf"
kind = "ekf"
[initial_estimate]
mode = "sampled"
p0_std = 1.0
"#
        ),
        "drone_ekf9" => format!(
            r#"name = "bench_drone_ekf9"
master_seed = 11
runs = {runs}
[model]
kind = "drone"
[[scenarios]]
name = "linear"
duration_s = 10.0
[[filters]]
label = "ekf9"
kind = "ekf9"
[initial_estimate]
mode = "sampled"
"#
        ),
        other => panic!("unknown case {other}"),
    }
}

fn cpu_seconds() -> f64 {
    // utime + stime of this process, in clock ticks (Linux; 100 Hz is the common USER_HZ).
    let stat = std::fs::read_to_string("/proc/self/stat").unwrap_or_default();
    let after = stat.rsplit(')').next().unwrap_or("");
    let f: Vec<&str> = after.split_whitespace().collect();
    let tick = |i: usize| f.get(i).and_then(|v| v.parse::<f64>().ok()).unwrap_or(0.0);
    (tick(11) + tick(12)) / 100.0
}

fn timed(f: impl FnOnce()) -> (f64, f64) {
    let (c, t) = (cpu_seconds(), Instant::now());
    f();
    (t.elapsed().as_secs_f64(), cpu_seconds() - c)
}

fn median_range(mut v: Vec<f64>) -> (f64, f64, f64) {
    v.sort_by(f64::total_cmp);
    (v[v.len() / 2], v[0], v[v.len() - 1])
}

/// The kernel of a case, as a closure over its plan.
fn kernel<'a>(name: &str, plan: &'a Plan) -> Box<dyn Fn() -> f64 + 'a> {
    let units = plan.runs * plan.scenarios.len();
    let runs = plan.runs;
    match name {
        "p1_ekf" | "seed" => {
            let sys = plan
                .system
                .as_any()
                .downcast_ref::<P1Plan>()
                .expect("P1 plan");
            let window = (plan.filters.len() > 1).then_some(11);
            let nf = plan.filters.len();
            Box::new(move || {
                monte_carlo(
                    units,
                    nf,
                    6,
                    |u| sys.scenarios[plan.scenarios[u / runs].index].steps() + 1,
                    |u| p1_run(sys, plan, u / runs, u % runs, window),
                )
            })
        }
        "l1_kf" => {
            let sys = plan
                .system
                .as_any()
                .downcast_ref::<L1Plan>()
                .expect("L1 plan");
            Box::new(move || {
                monte_carlo(
                    units,
                    1,
                    6,
                    |_| sys.scenarios[0].steps() + 1,
                    |u| l1_run(sys, plan, u),
                )
            })
        }
        "drone_ekf9" => {
            let sys = plan
                .system
                .as_any()
                .downcast_ref::<DronePlan>()
                .expect("drone plan");
            let params = DroneParams::default();
            let model = drone_model(&params);
            Box::new(move || {
                monte_carlo(
                    units,
                    1,
                    9,
                    |u| sys.scenario_info[plan.scenarios[u / runs].index].steps + 1,
                    |u| drone_run(sys, plan, &model, &params, u / runs, u % runs),
                )
            })
        }
        _ => unreachable!(),
    }
}

/// Run 0's mean NEES by the kernel (for the agreement check).
fn kernel_run0(name: &str, plan: &Plan) -> f64 {
    match name {
        "p1_ekf" | "seed" => {
            let sys = plan
                .system
                .as_any()
                .downcast_ref::<P1Plan>()
                .expect("P1 plan");
            p1_run(sys, plan, 0, 0, None)[0].mean_nees()
        }
        "l1_kf" => {
            let sys = plan
                .system
                .as_any()
                .downcast_ref::<L1Plan>()
                .expect("L1 plan");
            l1_run(sys, plan, 0)[0].mean_nees()
        }
        "drone_ekf9" => {
            let sys = plan
                .system
                .as_any()
                .downcast_ref::<DronePlan>()
                .expect("drone plan");
            let params = DroneParams::default();
            drone_run(sys, plan, &drone_model(&params), &params, 0, 0)[0].mean_nees()
        }
        _ => unreachable!(),
    }
}

const USAGE: &str = "usage: bench_study [--case p1_ekf|seed|l1_kf|drone_ekf9]... [--rounds N] \
[--scale F] [--only kfmc|kernel|trial]
  --case    a case to run (repeatable; default all four)
  --rounds  alternating rounds per case (default 5)
  --scale   multiplies the runs per case (default 1)
  --only    times one side alone, for a profiler (no ratio is reported)";

fn main() {
    let mut scale: f64 = 1.0;
    let mut rounds = 5;
    let mut cases: Vec<String> = Vec::new();
    // `--only kfmc|kernel` times one side alone (for a profiler), `--only trial` kfmc's runs
    // without the study around them; no ratio is reported.
    let mut only: Option<String> = None;
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--scale" => scale = args.next().and_then(|v| v.parse().ok()).expect("--scale F"),
            "--rounds" => {
                rounds = args
                    .next()
                    .and_then(|v| v.parse().ok())
                    .expect("--rounds N")
            }
            "--case" => cases.push(args.next().expect("--case NAME")),
            "--only" => only = Some(args.next().expect("--only kfmc|kernel|trial")),
            "--help" | "-h" => {
                println!("{USAGE}");
                return;
            }
            other => {
                eprintln!("bench_study: unknown argument {other}\n{USAGE}");
                std::process::exit(2);
            }
        }
    }
    if cases.is_empty() {
        cases = ["p1_ekf", "seed", "l1_kf", "drone_ekf9"]
            .map(String::from)
            .to_vec();
    }
    let all = [
        Case {
            name: "p1_ekf",
            about: "P1 EKF only, basic, 4,000 runs × 1,001 samples",
            spec: String::new(),
        },
        Case {
            name: "seed",
            about: "seed study: EKF + running mean, 4 scenarios × 1,000 runs",
            spec: String::new(),
        },
        Case {
            name: "l1_kf",
            about: "L1 KF (positions), 4,000 runs × 1,001 samples",
            spec: String::new(),
        },
        Case {
            name: "drone_ekf9",
            about: "drone ekf9, linear route, 1,000 runs × 1,001 samples",
            spec: String::new(),
        },
    ];
    let base_runs = |n: &str| match n {
        "seed" | "drone_ekf9" => 1000.0,
        _ => 4000.0,
    };
    let tmp: PathBuf =
        std::env::temp_dir().join(format!("kfmc-bench-study-{}", std::process::id()));
    std::fs::create_dir_all(&tmp).expect("temp folder");
    println!(
        "{} threads; {rounds} alternating rounds per case; ratio = kfmc / kernel (median, [min, max])",
        rayon::current_num_threads()
    );
    for name in &cases {
        let case = all
            .iter()
            .find(|c| c.name == name.as_str())
            .expect("known case");
        let runs = ((base_runs(case.name) * scale).round() as usize).max(2);
        let case = Case {
            spec: spec_of(case.name, runs),
            ..*case
        };
        let spec_path = tmp.join(format!("{}.toml", case.name));
        let out = tmp.join(case.name);
        std::fs::write(
            &spec_path,
            format!("output = {:?}\n{}", out.display().to_string(), case.spec),
        )
        .expect("spec");
        let plan = experiment::load(&spec_path).expect("bench spec");
        // Same work: run 0's mean NEES by kfmc's trial and by the kernel.
        let lib = plan
            .trial()
            .run(&Unit {
                scenario: 0,
                scale: 0,
                run: 0,
            })
            .filters[0]
            .nees_mean
            .expect("EKF has NEES");
        let ker = kernel_run0(case.name, &plan);
        let k = kernel(case.name, &plan);
        let (mut wall, mut cpu, mut tk, mut tl) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        let (mut ck_all, mut cl_all) = (Vec::new(), Vec::new());
        let mut checksum = 0.0;
        for _ in 0..rounds {
            let _ = std::fs::remove_dir_all(&out);
            if only.as_deref() == Some("kernel") {
                checksum += black_box(k());
                continue;
            }
            if only.as_deref() == Some("trial") {
                // kfmc's runs alone (simulate, filter, per-run metrics), without folding,
                // quantiles or tables: what a study adds on top is the difference.
                let trial = plan.trial();
                let units: Vec<Unit> = (0..plan.scenarios.len())
                    .flat_map(|scenario| {
                        (0..plan.runs).map(move |run| Unit {
                            scenario,
                            scale: 0,
                            run,
                        })
                    })
                    .collect();
                let (w, c) = timed(|| {
                    checksum += units
                        .par_iter()
                        .map(|u| black_box(trial.run(u)).filters.len() as f64)
                        .sum::<f64>();
                });
                println!("  trial only: wall {w:.3} s, CPU {c:.3} s");
                continue;
            }
            let (wl, cl) = timed(|| {
                black_box(
                    run(
                        &plan,
                        &ExecOptions {
                            threads: 0,
                            force: true,
                            shard: None,
                            checkpoints: None,
                        },
                        &NullObserver,
                    )
                    .expect("study"),
                );
            });
            if only.as_deref() == Some("kfmc") {
                continue;
            }
            let (wk, ck) = timed(|| checksum += black_box(k()));
            wall.push(wl / wk);
            cpu.push(cl / ck);
            tk.push(wk);
            tl.push(wl);
            ck_all.push(ck);
            cl_all.push(cl);
        }
        if only.is_some() {
            println!(
                "{}: {rounds} rounds of one side only (checksum {checksum:.3e})",
                case.name
            );
            continue;
        }
        let (w, w0, w1) = median_range(wall);
        let (c, c0, c1) = median_range(cpu);
        let units = plan.runs * plan.scenarios.len();
        let steps: usize = plan.scenarios.len() * plan.runs * plan.trial().steps(0);
        let (tkm, _, _) = median_range(tk);
        let (tlm, _, _) = median_range(tl);
        let (ckm, _, _) = median_range(ck_all);
        let (clm, _, _) = median_range(cl_all);
        println!(
            "{} — {} ({units} runs, {} runs per cell)",
            case.name, case.about, plan.runs
        );
        println!("  wall ratio {w:.2}× [{w0:.2}, {w1:.2}]   CPU ratio {c:.2}× [{c0:.2}, {c1:.2}]");
        println!(
            "  context: median wall kfmc {tlm:.2} s, kernel {tkm:.2} s; CPU per run step (all filters of the run) kfmc {:.0} ns, kernel {:.0} ns",
            clm / steps as f64 * 1e9,
            ckm / steps as f64 * 1e9,
        );
        println!(
            "  same work: run 0 mean NEES kfmc {lib:.12}, kernel {ker:.12} (checksum {checksum:.3e})"
        );
    }
    let _ = std::fs::remove_dir_all(&tmp);
}
