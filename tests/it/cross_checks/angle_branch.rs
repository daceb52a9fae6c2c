//! An angle's branch is a matter of reporting, not of estimation: on runs whose attitude
//! passes θ = ±π, the EKF, UKF and CKF give the same RMSE whichever branch the angle is
//! reported on, for the θ measurement (continuous, on [−π, π), or shifted by 2π·j) and for the
//! state θ (the continuous planar θ, or a model that keeps θ on [−π, π), where the sigma
//! points straddle the cut and only a circular mean and wrapped deviations keep the filter
//! right). The last test shows the comparison can fail: the same model without its angle
//! declared gives a very different RMSE.

use kfmc::filter::{CovarianceUpdate, Ekf, Filter, SigmaPointKalman, SigmaPoints};
use kfmc::linalg::{Matrix, Vector};
use kfmc::model::{Measurement, Model, wrap_angle};
use kfmc::sim::{NoiseDraws, Trajectory, TruthNoise, seed::run_seed, simulate};
use kfmc::systems::planar::model::{PlanarP1, PlanarParams};
use kfmc::systems::planar::scenario::builtin;

/// P1 with θ kept on [−π, π) by the transition (a model that reports its attitude on the
/// principal branch). `declared`: whether it tells the filters that θ is an angle.
struct PrincipalP1 {
    inner: PlanarP1,
    declared: bool,
}

impl Model<6, 2, 3> for PrincipalP1 {
    fn dt_s(&self) -> f64 {
        self.inner.dt_s()
    }
    fn propagate(&self, x: &Vector<6>, u: &Vector<2>) -> Vector<6> {
        let mut y = self.inner.propagate(x, u);
        y[4] = wrap_angle(y[4]);
        y
    }
    fn transition_jacobian(&self, x: &Vector<6>, u: &Vector<2>) -> Matrix<6, 6> {
        self.inner.transition_jacobian(x, u)
    }
    fn measure(&self, x: &Vector<6>, u: &Vector<2>) -> Vector<3> {
        self.inner.measure(x, u)
    }
    fn measurement_jacobian(&self, x: &Vector<6>, u: &Vector<2>) -> Matrix<3, 6> {
        self.inner.measurement_jacobian(x, u)
    }
    fn angle_states(&self) -> &[usize] {
        if self.declared { &[4] } else { &[] }
    }
    fn angle_measurements(&self) -> &[usize] {
        &[1]
    }
}

const Q_STD: f64 = 0.003;
const R_STD: f64 = 0.01;

/// Runs one filter through a [`Runner`].
type RunWith = Box<dyn Fn(&dyn Runner) -> [f64; 6]>;

/// The filters compared, by name.
fn filters() -> Vec<(&'static str, RunWith)> {
    let q = Matrix::<6, 6>::identity() * Q_STD * Q_STD;
    let r = Matrix::<3, 3>::identity() * R_STD * R_STD;
    vec![
        (
            "ekf",
            Box::new(move |run: &dyn Runner| {
                run.ekf(&Ekf {
                    q,
                    r,
                    update_form: CovarianceUpdate::Standard,
                })
            }),
        ),
        (
            "ukf",
            Box::new(move |run: &dyn Runner| {
                run.sigma(&SigmaPointKalman::new(q, r, SigmaPoints::DEFAULT_UNSCENTED).unwrap())
            }),
        ),
        (
            "ckf",
            Box::new(move |run: &dyn Runner| {
                run.sigma(&SigmaPointKalman::new(q, r, SigmaPoints::Cubature).unwrap())
            }),
        ),
    ]
}

/// One run of a filter on a model with given measurements: RMSE per state over k = 1..=K,
/// with the θ error wrapped (NaN if the run fails).
trait Runner {
    fn ekf(&self, f: &Ekf<6, 3>) -> [f64; 6];
    fn sigma(&self, f: &SigmaPointKalman<6, 3>) -> [f64; 6];
}

struct Run<'a, M> {
    model: &'a M,
    x0_hat: Vector<6>,
    controls: &'a [Vector<2>],
    zs: Vec<Measurement<3>>,
    truth: &'a [Vector<6>],
}

impl<M: Model<6, 2, 3>> Run<'_, M> {
    fn rmse<F: Filter<6, 2, 3, M>>(&self, f: &F) -> [f64; 6] {
        let p0 = Matrix::<6, 6>::identity();
        let mut b = f.init(self.model, &self.x0_hat, &p0, &self.zs[0]);
        let mut sum = [0.0; 6];
        for k in 1..self.zs.len() {
            let u = &self.controls[k];
            let step = f
                .predict(self.model, &mut b, u)
                .and_then(|()| f.update(self.model, &mut b, u, &self.zs[k]));
            if step.is_err() {
                return [f64::NAN; 6];
            }
            let mut e = self.truth[k] - f.mean(&b);
            e[4] = wrap_angle(e[4]);
            for i in 0..6 {
                sum[i] += e[i] * e[i];
            }
        }
        sum.map(|s| (s / (self.zs.len() - 1) as f64).sqrt())
    }
}

impl<M: Model<6, 2, 3>> Runner for Run<'_, M> {
    fn ekf(&self, f: &Ekf<6, 3>) -> [f64; 6] {
        self.rmse(f)
    }
    fn sigma(&self, f: &SigmaPointKalman<6, 3>) -> [f64; 6] {
        self.rmse(f)
    }
}

/// A seeded roll run (sampled start, P0 = I), starting at attitude `theta0`.
fn roll(theta0: f64, seed: u64) -> (Vec<Vector<2>>, Trajectory<6, 3>) {
    let model = PlanarP1::new(PlanarParams::default());
    let mut sc = builtin("roll").unwrap().expand(0.01);
    sc.x0[4] = theta0;
    let noise = TruthNoise {
        process_std: Vector::<6>::repeat(Q_STD),
        measurement_std: Vector::<3>::repeat(R_STD),
    };
    let draws = NoiseDraws::<6, 3>::draw(run_seed(seed, "roll", 0), sc.steps());
    let t = simulate(
        &model,
        &sc,
        &noise,
        1.0,
        Some(&Matrix::<6, 6>::identity()),
        &draws,
    );
    (sc.controls, t)
}

fn relative_gap(a: &[f64; 6], b: &[f64; 6]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs() / x.abs().max(1e-12))
        .fold(0.0, f64::max)
}

/// Both attitudes pass ±π: the seeds' roll (θ from 0 to about 2π + 0.9) and the same roll
/// started at θ = 3, where the prior's sigma points (σ_θ = 1) straddle the cut from step 1.
const STARTS: [f64; 2] = [0.0, 3.0];

#[test]
fn the_measured_angle_branch_does_not_change_the_rmse() {
    let model = PlanarP1::new(PlanarParams::default());
    for theta0 in STARTS {
        for seed in 0..3 {
            let (controls, t) = roll(theta0, seed);
            let run = |zs: Vec<Measurement<3>>| Run {
                model: &model,
                x0_hat: t.x0_hat,
                controls: &controls,
                zs,
                truth: &t.truth,
            };
            let continuous = run(t.measurements.clone());
            let branch = |shift: &dyn Fn(usize, f64) -> f64| {
                let mut zs = t.measurements.clone();
                for (k, m) in zs.iter_mut().enumerate() {
                    m.z[1] = shift(k, m.z[1]);
                }
                run(zs)
            };
            let principal = branch(&|_, z| wrap_angle(z));
            let hopping = branch(&|k, z| z + 2.0 * std::f64::consts::PI * ((k % 3) as f64 - 1.0));
            assert!(t.truth.iter().any(|x| x[4] > std::f64::consts::PI));
            for (name, f) in filters() {
                let base = f(&continuous);
                for (label, other) in [("[−π, π)", &principal), ("2π·j", &hopping)] {
                    let gap = relative_gap(&base, &f(other));
                    assert!(
                        gap < 1e-9,
                        "{name}, θ0 = {theta0}, seed {seed}: θ measured on {label} changes the RMSE by {gap:e}"
                    );
                }
            }
        }
    }
}

#[test]
fn the_state_angle_branch_does_not_change_the_rmse() {
    let model = PlanarP1::new(PlanarParams::default());
    let principal = PrincipalP1 {
        inner: model,
        declared: true,
    };
    for theta0 in STARTS {
        for seed in 0..3 {
            let (controls, t) = roll(theta0, seed);
            let continuous = Run {
                model: &model,
                x0_hat: t.x0_hat,
                controls: &controls,
                zs: t.measurements.clone(),
                truth: &t.truth,
            };
            let mut x0_hat = t.x0_hat;
            x0_hat[4] = wrap_angle(x0_hat[4]);
            let wrapped = Run {
                model: &principal,
                x0_hat,
                controls: &controls,
                zs: t.measurements.clone(),
                truth: &t.truth,
            };
            for (name, f) in filters() {
                let (a, b) = (f(&continuous), f(&wrapped));
                let gap = relative_gap(&a, &b);
                println!(
                    "{name}, θ0 = {theta0}, seed {seed}: RMSE θ {:.6e}, gap {gap:.1e}",
                    a[4]
                );
                assert!(
                    gap < 1e-9,
                    "{name}, θ0 = {theta0}, seed {seed}: θ kept on [−π, π) changes the RMSE by {gap:e}: {a:?} vs {b:?}"
                );
            }
        }
    }
}

#[test]
fn an_undeclared_angle_state_breaks_the_sigma_point_filters() {
    // The same principal-branch model without `angle_states`: the points that cross the cut
    // are averaged arithmetically and their deviations are 2π off.
    let model = PlanarP1::new(PlanarParams::default());
    let undeclared = PrincipalP1 {
        inner: model,
        declared: false,
    };
    let (controls, t) = roll(3.0, 0);
    let mut x0_hat = t.x0_hat;
    x0_hat[4] = wrap_angle(x0_hat[4]);
    let base = Run {
        model: &model,
        x0_hat: t.x0_hat,
        controls: &controls,
        zs: t.measurements.clone(),
        truth: &t.truth,
    };
    let broken = Run {
        model: &undeclared,
        x0_hat,
        controls: &controls,
        zs: t.measurements.clone(),
        truth: &t.truth,
    };
    for (name, f) in filters().into_iter().skip(1) {
        let (a, b) = (f(&base), f(&broken));
        let gap = relative_gap(&a, &b);
        println!(
            "{name}: RMSE θ {:.3e} declared, {:.3e} undeclared",
            a[4], b[4]
        );
        assert!(
            gap.is_nan() || gap > 1e-3,
            "{name}: {a:?} vs {b:?} (the comparison cannot tell)"
        );
    }
}
