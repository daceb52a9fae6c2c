//! Speed of the P1 EKF step, of the P1 UKF/CKF steps, of the L1 linear filters' steps and of a
//! whole Monte Carlo run, as ratios against minimal hand-written fixed-size filter steps
//! measured in the same process (the machines are shared and noisy, so absolute times mean
//! little; ratios are what to compare).
//!
//! ```text
//! cargo run --release --example bench_step
//! ```
//!
//! Method: the same 1,000-step trajectory is filtered repeatedly; the baseline and kfmc are
//! interleaved in rounds and the median round is reported.
//!
//! The L1 section also times the square-root filter as it was before its pre-arrays were
//! triangularised on fixed-size blocks ([`OldSqrt`], a private copy that still uses nalgebra's
//! heap-allocated dynamic QR), for the before/after ratio.

use std::hint::black_box;
use std::path::Path;
use std::time::Instant;

use kfmc::experiment;
use kfmc::filter::{
    CovarianceUpdate, Ekf, Filter, FilterError, Information, Innovation, SigmaPointKalman,
    SigmaPoints, SquareRoot,
};
use kfmc::linalg::{Matrix, SmallCholesky, Vector};
use kfmc::model::{Availability, Measurement, Model};
use kfmc::scenario::Scenario;
use kfmc::sim::{NoiseDraws, TruthNoise, seed::run_seed, simulate};
use kfmc::step_loop::Unit;
use kfmc::systems::linear_quadrotor::model::{Linear, LinearSensor};
use kfmc::systems::planar::model::{PlanarP1, PlanarParams};
use kfmc::systems::planar::scenario::builtin;
use nalgebra::DMatrix;

/// The baseline: the seed's EKF step written out by hand for exactly this model, with
/// nalgebra fixed-size matrices, an explicit 3×3 inverse and nothing else.
#[inline(never)]
fn hand_step(
    x: &mut Vector<6>,
    p: &mut Matrix<6, 6>,
    u: &Vector<2>,
    z: &Vector<3>,
    q: &Matrix<6, 6>,
    r: &Matrix<3, 3>,
) {
    let (m, arm, inertia, g, dt) = (0.5, 0.15, 0.005, 9.81, 0.01);
    let thrust = u[0] + u[1];
    let (s, c) = x[4].sin_cos();
    let mut f = Matrix::<6, 6>::identity();
    f[(0, 1)] = dt;
    f[(1, 4)] = -c * thrust / m * dt;
    f[(2, 3)] = dt;
    f[(3, 4)] = -s * thrust / m * dt;
    f[(4, 5)] = dt;
    *x = Vector::<6>::new(
        x[0] + x[1] * dt,
        x[1] - s * thrust / m * dt,
        x[2] + x[3] * dt,
        x[3] + (c * thrust / m - g) * dt,
        x[4] + x[5] * dt,
        x[5] + arm / inertia * (u[0] - u[1]) * dt,
    );
    let pp = f * *p * f.transpose() + q;
    let mut h = Matrix::<3, 6>::zeros();
    h[(0, 2)] = 1.0;
    h[(1, 4)] = 1.0;
    h[(2, 5)] = 1.0;
    let mut nu = z - Vector::<3>::new(x[2], x[4], x[5]);
    nu[1] = (nu[1] + std::f64::consts::PI).rem_euclid(2.0 * std::f64::consts::PI)
        - std::f64::consts::PI;
    let s_mat = h * pp * h.transpose() + r;
    let k = pp * h.transpose() * s_mat.try_inverse().expect("S invertible");
    *x += k * nu;
    *p = (Matrix::<6, 6>::identity() - k * h) * pp;
}

/// One bare hand-written EKF pass over a trajectory; returns the final x̂ for black-boxing.
fn hand_pass(
    x0: &Vector<6>,
    controls: &[Vector<2>],
    zs: &[Measurement<3>],
    q: &Matrix<6, 6>,
    r: &Matrix<3, 3>,
) -> Vector<6> {
    let mut x = *x0;
    let mut p = Matrix::<6, 6>::identity();
    for k in 1..controls.len() {
        hand_step(&mut x, &mut p, &controls[k], &zs[k].z, q, r);
    }
    x
}

/// The L1 baseline: a textbook KF step for F, G, H, Q, R given as fixed-size matrices, with an
/// explicit 3×3 inverse and nothing else (no masking, no innovation statistics).
#[inline(never)]
fn hand_kf_step(
    x: &mut Vector<6>,
    p: &mut Matrix<6, 6>,
    u: &Vector<4>,
    z: &Vector<3>,
    (f, g, h): (&Matrix<6, 6>, &Matrix<6, 4>, &Matrix<3, 6>),
    q: &Matrix<6, 6>,
    r: &Matrix<3, 3>,
) {
    *x = f * *x + g * u;
    let pp = f * *p * f.transpose() + q;
    let s = h * pp * h.transpose() + r;
    let k = pp * h.transpose() * s.try_inverse().expect("S invertible");
    *x += k * (z - h * *x);
    *p = (Matrix::<6, 6>::identity() - k * h) * pp;
}

/// One bare hand-written KF pass over an L1 trajectory; returns the final x̂.
fn hand_kf_pass(
    model: &Linear<3>,
    x0: &Vector<6>,
    controls: &[Vector<4>],
    zs: &[Measurement<3>],
    q: &Matrix<6, 6>,
    r: &Matrix<3, 3>,
) -> Vector<6> {
    let d = model.discrete();
    let mut x = *x0;
    let mut p = Matrix::<6, 6>::identity();
    for k in 1..controls.len() {
        hand_kf_step(
            &mut x,
            &mut p,
            &controls[k],
            &zs[k].z,
            (&d.f, &d.g, model.h()),
            q,
            r,
        );
    }
    x
}

/// One pass of a kfmc filter through the `Filter` trait, as a Monte Carlo run drives it.
fn filter_pass<F: Filter<6, 4, 3, Linear<3>>>(
    filter: &F,
    model: &Linear<3>,
    x0: &Vector<6>,
    controls: &[Vector<4>],
    zs: &[Measurement<3>],
) -> Vector<6> {
    let mut b = filter.init(model, x0, &Matrix::<6, 6>::identity(), &zs[0]);
    for k in 1..controls.len() {
        filter.predict(model, &mut b, &controls[k]).unwrap();
        black_box(filter.update(model, &mut b, &controls[k], &zs[k]).unwrap());
    }
    filter.mean(&b)
}

/// The library's former triangularisation, kept here only for the before/after ratio: L with
/// L Lᵀ = A Aᵀ from nalgebra's dynamic QR of Aᵀ, which allocates on every call.
fn triangularize_dynamic(a: &DMatrix<f64>) -> DMatrix<f64> {
    let r = a.transpose().qr().r();
    let n = a.nrows();
    let mut l = r.transpose().view((0, 0), (n, n)).into_owned();
    for j in 0..n {
        if l[(j, j)] < 0.0 {
            for i in 0..n {
                l[(i, j)] = -l[(i, j)];
            }
        }
    }
    l
}

/// The square-root filter exactly as it was before the fixed-size triangularisation (the same
/// algebra, masking and checks), so that only the triangularisation differs.
struct OldSqrt<const NX: usize, const NZ: usize> {
    q: Matrix<NX, NX>,
    r: Matrix<NZ, NZ>,
}

#[derive(Clone)]
struct OldSqrtBelief<const NX: usize> {
    x: Vector<NX>,
    s: Matrix<NX, NX>,
    f: Matrix<NX, NX>,
    i_kh: Matrix<NX, NX>,
}

fn old_factor<const N: usize>(
    a: &Matrix<N, N>,
    which: &'static str,
) -> Result<Matrix<N, N>, FilterError> {
    SmallCholesky::new(a)
        .map(|c| c.l())
        .ok_or(FilterError::NotPositiveDefinite { which })
}

fn old_check_finite<const NX: usize>(
    x: &Vector<NX>,
    m: &Matrix<NX, NX>,
) -> Result<(), FilterError> {
    if !x.sum().is_finite() || !m.trace().is_finite() {
        return Err(FilterError::NonFinite { what: "state" });
    }
    Ok(())
}

fn old_mask_rows<const NX: usize, const NZ: usize>(
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

impl<const NX: usize, const NU: usize, const NZ: usize, M: Model<NX, NU, NZ>> Filter<NX, NU, NZ, M>
    for OldSqrt<NX, NZ>
{
    type Belief = OldSqrtBelief<NX>;

    fn init(
        &self,
        _model: &M,
        x0_hat: &Vector<NX>,
        p0: &Matrix<NX, NX>,
        _z0: &Measurement<NZ>,
    ) -> OldSqrtBelief<NX> {
        OldSqrtBelief {
            x: *x0_hat,
            s: old_factor(p0, "P0").unwrap(),
            f: Matrix::<NX, NX>::identity(),
            i_kh: Matrix::<NX, NX>::identity(),
        }
    }

    fn predict(
        &self,
        model: &M,
        b: &mut OldSqrtBelief<NX>,
        u: &Vector<NU>,
    ) -> Result<(), FilterError> {
        let f = model.transition_jacobian(&b.x, u);
        let l_q = old_factor(&self.q, "process noise Q")?;
        let fs = f * b.s;
        let pre = DMatrix::<f64>::from_fn(NX, 2 * NX, |i, j| {
            if j < NX { fs[(i, j)] } else { l_q[(i, j - NX)] }
        });
        let post = triangularize_dynamic(&pre);
        b.s = Matrix::<NX, NX>::from_fn(|i, j| post[(i, j)]);
        b.x = model.propagate(&b.x, u);
        b.f = f;
        b.i_kh = Matrix::<NX, NX>::identity();
        old_check_finite(&b.x, &b.s)
    }

    fn update(
        &self,
        model: &M,
        b: &mut OldSqrtBelief<NX>,
        u: &Vector<NU>,
        z: &Measurement<NZ>,
    ) -> Result<Option<Innovation<NZ>>, FilterError> {
        if z.available.count() == 0 {
            return Ok(None);
        }
        let mut h = model.measurement_jacobian(&b.x, u);
        let mut nu = model.residual(&z.z, &model.measure(&b.x, u));
        let r = old_mask_rows(&self.r, z.available, &mut h, &mut nu);
        let l_r = old_factor(&r, "measurement noise R")?;
        let hs = h * b.s;
        let n = NZ + NX;
        let mut pre = DMatrix::<f64>::zeros(n, n);
        for i in 0..NZ {
            for j in 0..NZ {
                pre[(i, j)] = l_r[(i, j)];
            }
            for j in 0..NX {
                pre[(i, NZ + j)] = hs[(i, j)];
            }
        }
        for i in 0..NX {
            for j in 0..NX {
                pre[(NZ + i, NZ + j)] = b.s[(i, j)];
            }
        }
        let post = triangularize_dynamic(&pre);
        let l_s = Matrix::<NZ, NZ>::from_fn(|i, j| post[(i, j)]);
        let k_bar = Matrix::<NX, NZ>::from_fn(|i, j| post[(NZ + i, j)]);
        if (0..NZ).any(|i| l_s[(i, i)].partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater)) {
            return Err(FilterError::NotPositiveDefinite {
                which: "innovation covariance S",
            });
        }
        let whitened = l_s
            .solve_lower_triangular(&nu)
            .ok_or(FilterError::NotPositiveDefinite {
                which: "innovation covariance S",
            })?;
        b.x += k_bar * whitened;
        b.s = Matrix::<NX, NX>::from_fn(|i, j| post[(NZ + i, NZ + j)]);
        if let Some(kt) = l_s.transpose().solve_upper_triangular(&k_bar.transpose()) {
            b.i_kh = Matrix::<NX, NX>::identity() - kt.transpose() * h;
        }
        old_check_finite(&b.x, &b.s)?;
        Ok(Some(Innovation::new(nu, whitened, z.available)))
    }

    fn mean(&self, b: &OldSqrtBelief<NX>) -> Vector<NX> {
        b.x
    }

    fn covariance(&self, b: &OldSqrtBelief<NX>) -> Option<Matrix<NX, NX>> {
        Some(b.s * b.s.transpose())
    }

    fn error_transition(&self, b: &OldSqrtBelief<NX>) -> Option<Matrix<NX, NX>> {
        Some(b.i_kh * b.f)
    }
}

/// The L1 linear filters (positions sensor, Δt = 0.1 s) against the hand-written KF step.
fn bench_l1() {
    let model = Linear::<3>::new(LinearSensor::Positions, 0.1).unwrap();
    let q = model.process_noise_covariance().unwrap();
    let r = model.r();
    let steps = 1000;
    let draws = NoiseDraws::<6, 3>::draw(run_seed(1, "hover", 0), steps);
    let x_hat0 = Vector::<6>::new(1.0, 0.0, 1.0, 0.0, 1.0, 0.0);
    let sc = Scenario::unforced("hover", x_hat0 + draws.initial, steps);
    let noise = model.truth_noise();
    let traj = simulate(&model, &sc, &noise, 1.0, None, &draws);
    let (controls, zs) = (&sc.controls, &traj.measurements);
    let kf = Ekf {
        q,
        r,
        update_form: CovarianceUpdate::Standard,
    };
    let info = Information::new(q, r);
    let sqrt_old = OldSqrt { q, r };
    let sqrt_new = SquareRoot::new(q, r);

    // All five compute the same estimate; a wrong "fast" filter would show here.
    let reference = hand_kf_pass(&model, &x_hat0, controls, zs, &q, &r);
    let finals = [
        filter_pass(&kf, &model, &x_hat0, controls, zs),
        filter_pass(&info, &model, &x_hat0, controls, zs),
        filter_pass(&sqrt_old, &model, &x_hat0, controls, zs),
        filter_pass(&sqrt_new, &model, &x_hat0, controls, zs),
    ];
    let agree = finals
        .iter()
        .map(|x| (x - reference).amax())
        .fold(0.0, f64::max);
    assert!(agree < 1e-9, "the L1 filters disagree by {agree:e}");

    let reps = 40;
    let rounds = 15;
    let names = [
        "hand-written fixed-size KF baseline",
        "kfmc Ekf (covariance-form KF)",
        "kfmc Information",
        "kfmc SquareRoot, old dynamic QR",
        "kfmc SquareRoot, fixed-size Householder",
    ];
    let mut times = vec![Vec::new(); names.len()];
    let per_step = |t: Instant| t.elapsed().as_secs_f64() / (reps * steps) as f64;
    for _round in 0..rounds {
        let t = Instant::now();
        for _ in 0..reps {
            black_box(hand_kf_pass(&model, &x_hat0, controls, zs, &q, &r));
        }
        times[0].push(per_step(t));
        let t = Instant::now();
        for _ in 0..reps {
            black_box(filter_pass(&kf, &model, &x_hat0, controls, zs));
        }
        times[1].push(per_step(t));
        let t = Instant::now();
        for _ in 0..reps {
            black_box(filter_pass(&info, &model, &x_hat0, controls, zs));
        }
        times[2].push(per_step(t));
        let t = Instant::now();
        for _ in 0..reps {
            black_box(filter_pass(&sqrt_old, &model, &x_hat0, controls, zs));
        }
        times[3].push(per_step(t));
        let t = Instant::now();
        for _ in 0..reps {
            black_box(filter_pass(&sqrt_new, &model, &x_hat0, controls, zs));
        }
        times[4].push(per_step(t));
    }
    let med: Vec<f64> = times.into_iter().map(median).collect();
    println!(
        "L1 linear step (predict + update; 6 states, 3 positions), median of {rounds} rounds × {reps} runs × {steps} steps:"
    );
    println!("  {:<42}{:8.1} ns/step", names[0], med[0] * 1e9);
    for (name, t) in names.iter().zip(&med).skip(1) {
        println!(
            "  {name:<42}{:8.1} ns/step   ratio {:.2}×",
            t * 1e9,
            t / med[0]
        );
    }
    println!(
        "  square-root filter old / new: {:.2}×   (final x̂ of all five agree to {agree:.1e})",
        med[3] / med[4]
    );
}

/// The UKF baseline: one step of the UKF with α = 1, β = 2, κ = 0 written out by hand for
/// exactly P1 — 13 points, the circular mean of θ and of its measurement, wrapped θ deviations
/// and residual, points redrawn from (x̂⁻, P⁻) — with fixed-size matrices, kfmc's unrolled
/// Cholesky (the same factorisation the library uses, so only the structure differs), an
/// explicit 3×3 inverse and nothing else (no masking, no innovation statistics, no error
/// transition).
#[inline(never)]
fn hand_ukf_step(
    x: &mut Vector<6>,
    p: &mut Matrix<6, 6>,
    u: &Vector<2>,
    z: &Vector<3>,
    q: &Matrix<6, 6>,
    r: &Matrix<3, 3>,
) {
    let (m, arm, inertia, g, dt) = (0.5, 0.15, 0.005, 9.81, 0.01);
    let wrap = |a: f64| {
        (a + std::f64::consts::PI).rem_euclid(2.0 * std::f64::consts::PI) - std::f64::consts::PI
    };
    let f = |s: &Vector<6>| {
        let thrust = u[0] + u[1];
        let (sn, c) = s[4].sin_cos();
        Vector::<6>::new(
            s[0] + s[1] * dt,
            s[1] - sn * thrust / m * dt,
            s[2] + s[3] * dt,
            s[3] + (c * thrust / m - g) * dt,
            s[4] + s[5] * dt,
            s[5] + (arm / inertia * u[0] - arm / inertia * u[1]) * dt,
        )
    };
    let spread = 6f64.sqrt();
    let (w, wc0) = (1.0 / 12.0, 2.0);
    // Predict.
    let l = SmallCholesky::new(p).expect("P is SPD").l();
    let mut ys = [Vector::<6>::zeros(); 13];
    ys[0] = f(x);
    for j in 0..6 {
        let d = l.column(j) * spread;
        ys[1 + j] = f(&(*x + d));
        ys[7 + j] = f(&(*x - d));
    }
    let mut mean = Vector::<6>::zeros();
    let (a, mut sn, mut cs) = (ys[0][4], 0.0, 0.0);
    for y in &ys[1..] {
        mean += y * w;
        let (s1, c1) = (y[4] - a).sin_cos();
        sn += w * s1;
        cs += w * c1;
    }
    mean[4] = a + sn.atan2(cs);
    let mut pp = *q;
    for (i, y) in ys.iter().enumerate() {
        let mut d = y - mean;
        d[4] = wrap(d[4]);
        pp += d * d.transpose() * if i == 0 { wc0 } else { w };
    }
    // Update, from points redrawn from (x̂⁻, P⁻).
    let l = SmallCholesky::new(&pp).expect("P⁻ is SPD").l();
    let mut dx = [Vector::<6>::zeros(); 13];
    let mut zs = [Vector::<3>::zeros(); 13];
    for j in 0..6 {
        dx[1 + j] = l.column(j) * spread;
        dx[7 + j] = -dx[1 + j];
    }
    for i in 0..13 {
        let s = mean + dx[i];
        zs[i] = Vector::<3>::new(s[2], s[4], s[5]);
    }
    let mut zm = Vector::<3>::zeros();
    let (a, mut sn, mut cs) = (zs[0][1], 0.0, 0.0);
    for zi in &zs[1..] {
        zm += zi * w;
        let (s1, c1) = (zi[1] - a).sin_cos();
        sn += w * s1;
        cs += w * c1;
    }
    zm[1] = a + sn.atan2(cs);
    let mut s_mat = *r;
    let mut pxz = Matrix::<6, 3>::zeros();
    for i in 0..13 {
        let mut e = zs[i] - zm;
        e[1] = wrap(e[1]);
        let wi = if i == 0 { wc0 } else { w };
        s_mat += e * e.transpose() * wi;
        pxz += dx[i] * e.transpose() * wi;
    }
    let k = pxz * s_mat.try_inverse().expect("S invertible");
    let mut nu = z - zm;
    nu[1] = wrap(nu[1]);
    *x = mean + k * nu;
    *p = pp - k * s_mat * k.transpose();
}

/// One bare hand-written UKF pass over a trajectory; returns the final x̂.
fn hand_ukf_pass(
    x0: &Vector<6>,
    controls: &[Vector<2>],
    zs: &[Measurement<3>],
    q: &Matrix<6, 6>,
    r: &Matrix<3, 3>,
) -> Vector<6> {
    let mut x = *x0;
    let mut p = Matrix::<6, 6>::identity();
    for k in 1..controls.len() {
        hand_ukf_step(&mut x, &mut p, &controls[k], &zs[k].z, q, r);
    }
    x
}

/// One pass of a kfmc filter on P1 through the `Filter` trait, as a Monte Carlo run drives it.
fn planar_pass<F: Filter<6, 2, 3, PlanarP1>>(
    filter: &F,
    model: &PlanarP1,
    x0: &Vector<6>,
    controls: &[Vector<2>],
    zs: &[Measurement<3>],
) -> Vector<6> {
    let mut b = filter.init(model, x0, &Matrix::<6, 6>::identity(), &zs[0]);
    for k in 1..controls.len() {
        filter.predict(model, &mut b, &controls[k]).unwrap();
        black_box(filter.update(model, &mut b, &controls[k], &zs[k]).unwrap());
    }
    filter.mean(&b)
}

/// The P1 sigma-point steps against the hand-written UKF step and against the EKF step.
fn bench_sigma_points(
    model: &PlanarP1,
    x0: &Vector<6>,
    controls: &[Vector<2>],
    zs: &[Measurement<3>],
    q: &Matrix<6, 6>,
    r: &Matrix<3, 3>,
) {
    let ukf = SigmaPointKalman::new(*q, *r, SigmaPoints::DEFAULT_UNSCENTED).unwrap();
    let ckf = SigmaPointKalman::new(*q, *r, SigmaPoints::Cubature).unwrap();
    let ekf = Ekf {
        q: *q,
        r: *r,
        update_form: CovarianceUpdate::Standard,
    };
    // The baseline and kfmc's UKF compute the same estimates; a wrong "fast" one shows here.
    let agree =
        (hand_ukf_pass(x0, controls, zs, q, r) - planar_pass(&ukf, model, x0, controls, zs)).amax();
    assert!(
        agree < 1e-9,
        "the hand-written UKF and kfmc's disagree by {agree:e}"
    );
    let steps = controls.len() - 1;
    let (reps, rounds) = (40, 15);
    let names = [
        "hand-written fixed-size UKF baseline",
        "kfmc UKF (SigmaPointKalman, unscented)",
        "kfmc CKF (SigmaPointKalman, cubature)",
        "kfmc Ekf",
        "hand-written fixed-size EKF",
    ];
    let mut times = vec![Vec::new(); names.len()];
    let per_step = |t: Instant| t.elapsed().as_secs_f64() / (reps * steps) as f64;
    for _round in 0..rounds {
        let t = Instant::now();
        for _ in 0..reps {
            black_box(hand_ukf_pass(x0, controls, zs, q, r));
        }
        times[0].push(per_step(t));
        let t = Instant::now();
        for _ in 0..reps {
            black_box(planar_pass(&ukf, model, x0, controls, zs));
        }
        times[1].push(per_step(t));
        let t = Instant::now();
        for _ in 0..reps {
            black_box(planar_pass(&ckf, model, x0, controls, zs));
        }
        times[2].push(per_step(t));
        let t = Instant::now();
        for _ in 0..reps {
            black_box(planar_pass(&ekf, model, x0, controls, zs));
        }
        times[3].push(per_step(t));
        let t = Instant::now();
        for _ in 0..reps {
            black_box(hand_pass(x0, controls, zs, q, r));
        }
        times[4].push(per_step(t));
    }
    let med: Vec<f64> = times.into_iter().map(median).collect();
    println!(
        "P1 sigma-point step (predict + update), median of {rounds} rounds × {reps} runs × {steps} steps:"
    );
    println!("  {:<42}{:8.1} ns/step", names[0], med[0] * 1e9);
    for (name, t) in names.iter().zip(&med).skip(1) {
        println!(
            "  {name:<42}{:8.1} ns/step   ratio {:.2}×",
            t * 1e9,
            t / med[0]
        );
    }
    println!(
        "  kfmc UKF / kfmc EKF: {:.2}×   kfmc CKF / kfmc EKF: {:.2}×   (final x̂ of kfmc's and the hand-written UKF agree to {agree:.1e})",
        med[1] / med[3],
        med[2] / med[3]
    );
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn main() {
    let model = PlanarP1::new(PlanarParams::default());
    let sc = builtin("roll").unwrap().expand(0.01);
    let noise = TruthNoise {
        process_std: Vector::<6>::repeat(0.003),
        measurement_std: Vector::<3>::repeat(0.01),
    };
    let draws = NoiseDraws::<6, 3>::draw(run_seed(1, "roll", 0), sc.steps());
    let traj = simulate(&model, &sc, &noise, 1.0, None, &draws);
    let q = Matrix::<6, 6>::identity() * 0.003f64.powi(2);
    let r = Matrix::<3, 3>::identity() * 0.01f64.powi(2);
    let ekf = Ekf {
        q,
        r,
        update_form: CovarianceUpdate::Standard,
    };
    let steps = sc.steps();
    let reps = 200;

    let mut base = Vec::new();
    let mut kf = Vec::new();
    let mut checksum = 0.0;
    for _round in 0..15 {
        let t = Instant::now();
        for _ in 0..reps {
            let x = hand_pass(&traj.x0_hat, &sc.controls, &traj.measurements, &q, &r);
            checksum += black_box(x[0]);
        }
        base.push(t.elapsed().as_secs_f64() / (reps * steps) as f64);

        let t = Instant::now();
        for _ in 0..reps {
            let mut b = Filter::<6, 2, 3, PlanarP1>::init(
                &ekf,
                &model,
                &traj.x0_hat,
                &Matrix::<6, 6>::identity(),
                &traj.measurements[0],
            );
            for k in 1..=steps {
                let u = &sc.controls[k];
                let z: &Measurement<3> = &traj.measurements[k];
                ekf.predict(&model, &mut b, u).unwrap();
                black_box(ekf.update(&model, &mut b, u, z).unwrap());
            }
            checksum -= black_box(b.x[0]);
        }
        kf.push(t.elapsed().as_secs_f64() / (reps * steps) as f64);
    }
    let (b, k) = (median(base), median(kf));
    println!("P1 EKF step (predict + update), median of 15 rounds × {reps} runs × {steps} steps:");
    println!(
        "  hand-written fixed-size baseline  {:8.1} ns/step",
        b * 1e9
    );
    println!(
        "  kfmc Ekf via the Filter trait      {:8.1} ns/step   ratio {:.2}×",
        k * 1e9,
        k / b
    );
    println!(
        "  (checksum {:.3e}: both compute the same estimates)",
        checksum
    );

    bench_sigma_points(
        &model,
        &traj.x0_hat,
        &sc.controls,
        &traj.measurements,
        &q,
        &r,
    );

    bench_l1();

    // Whole Monte Carlo run: simulate + EKF + running mean + per-step metrics, one thread.
    let spec = Path::new(env!("CARGO_MANIFEST_DIR")).join("experiments/planar_robustness.toml");
    let plan = experiment::load(&spec).expect("bundled spec");
    let trial = plan.trial();
    let mut per_run = Vec::new();
    let mut base_run = Vec::new();
    for round in 0..9 {
        let t = Instant::now();
        for run in 0..50 {
            black_box(trial.run(&Unit {
                scenario: 2,
                scale: 4,
                run: round * 50 + run,
            }));
        }
        per_run.push(t.elapsed().as_secs_f64() / 50.0);
        let t = Instant::now();
        for _ in 0..50 {
            black_box(hand_pass(
                &traj.x0_hat,
                &sc.controls,
                &traj.measurements,
                &q,
                &r,
            ));
        }
        base_run.push(t.elapsed().as_secs_f64() / 50.0);
    }
    let (pr, br) = (median(per_run), median(base_run));
    println!(
        "Whole Monte Carlo run (1,001 samples: truth + measurements, EKF, running mean, errors, NEES/NIS), one thread:"
    );
    println!(
        "  kfmc run                 {:8.1} µs   = {:.2}× one bare hand-written EKF pass over the same steps",
        pr * 1e6,
        pr / br
    );
    println!("  bare EKF pass (baseline) {:8.1} µs", br * 1e6);
}
