//! A model may declare the structure of its Jacobians (the non-zero pattern of F, H as a row
//! selection) and the EKF then skips the zero terms. The generic dense path — the same model
//! with nothing declared, through nalgebra's dense products — is the independent second
//! algorithm: both must give the same estimates and covariances on P1 and L1, to the bit, step
//! after step (the declared path sums the dense path's terms in the dense path's order and only
//! leaves out zeros), and every declaration must describe its Jacobians at sampled points.

use kfmc::filter::{CovarianceUpdate, Ekf, Filter};
use kfmc::linalg::{Matrix, Vector};
use kfmc::model::{Availability, Measurement, Model};
use kfmc::scenario::Scenario;
use kfmc::sim::seed::run_seed;
use kfmc::sim::{NoiseDraws, TruthNoise, simulate};
use kfmc::systems::linear_quadrotor::model::{Linear, LinearSensor};
use kfmc::systems::planar::model::{PlanarImu, PlanarP1, PlanarParams};
use kfmc::systems::planar::scenario::builtin;
use rand::{RngExt, SeedableRng};

/// The wrapped model with its declarations hidden: the EKF takes the dense path.
struct Dense<'a, M>(&'a M);

impl<const NX: usize, const NU: usize, const NZ: usize, M: Model<NX, NU, NZ>> Model<NX, NU, NZ>
    for Dense<'_, M>
{
    fn dt_s(&self) -> f64 {
        self.0.dt_s()
    }
    fn propagate(&self, x: &Vector<NX>, u: &Vector<NU>) -> Vector<NX> {
        self.0.propagate(x, u)
    }
    fn transition_jacobian(&self, x: &Vector<NX>, u: &Vector<NU>) -> Matrix<NX, NX> {
        self.0.transition_jacobian(x, u)
    }
    fn measure(&self, x: &Vector<NX>, u: &Vector<NU>) -> Vector<NZ> {
        self.0.measure(x, u)
    }
    fn measurement_jacobian(&self, x: &Vector<NX>, u: &Vector<NU>) -> Matrix<NZ, NX> {
        self.0.measurement_jacobian(x, u)
    }
    fn residual(&self, z: &Vector<NZ>, z_pred: &Vector<NZ>) -> Vector<NZ> {
        self.0.residual(z, z_pred)
    }
}

/// The EKF forms one triangle of each covariance product and mirrors it: P is symmetric to
/// the bit, not to a tolerance, after every predict and every update.
fn assert_exactly_symmetric<const N: usize>(p: &Matrix<N, N>, which: &str, step: usize) {
    for i in 0..N {
        for j in 0..i {
            assert!(
                p[(i, j)].to_bits() == p[(j, i)].to_bits(),
                "{which} P at step {step}: P[{i},{j}] = {:e} but P[{j},{i}] = {:e}",
                p[(i, j)],
                p[(j, i)]
            );
        }
    }
}

/// Runs the EKF through a trajectory on the declared and on the dense path; returns the
/// largest difference of x̂ and of P relative to their scale, over all steps (zero when the
/// paths agree to the bit).
fn compare<const NX: usize, const NU: usize, const NZ: usize, M: Model<NX, NU, NZ>>(
    model: &M,
    ekf: &Ekf<NX, NZ>,
    controls: &[Vector<NU>],
    measurements: &[Measurement<NZ>],
    x0: &Vector<NX>,
) -> (f64, f64) {
    let dense = Dense(model);
    let p0 = Matrix::<NX, NX>::identity();
    let mut a = Filter::<NX, NU, NZ, M>::init(ekf, model, x0, &p0, &measurements[0]);
    let mut b = Filter::<NX, NU, NZ, Dense<M>>::init(ekf, &dense, x0, &p0, &measurements[0]);
    let (mut dx, mut dp) = (0.0f64, 0.0f64);
    for k in 1..controls.len() {
        let u = &controls[k];
        ekf.predict(model, &mut a, u).unwrap();
        ekf.predict(&dense, &mut b, u).unwrap();
        assert_exactly_symmetric(&a.p, "declared, predicted", k);
        assert_exactly_symmetric(&b.p, "dense, predicted", k);
        let ia = ekf.update(model, &mut a, u, &measurements[k]).unwrap();
        let ib = ekf.update(&dense, &mut b, u, &measurements[k]).unwrap();
        assert_exactly_symmetric(&a.p, "declared, updated", k);
        assert_exactly_symmetric(&b.p, "dense, updated", k);
        if let (Some(ia), Some(ib)) = (ia, ib) {
            assert!(ia.nis.to_bits() == ib.nis.to_bits(), "NIS at {k}");
        }
        dx = dx.max((a.x - b.x).amax() / b.x.amax().max(1.0));
        dp = dp.max((a.p - b.p).amax() / b.p.amax().max(1e-300));
        let (ta, tb) = (
            Filter::<NX, NU, NZ, M>::error_transition(ekf, &a).unwrap(),
            Filter::<NX, NU, NZ, Dense<M>>::error_transition(ekf, &b).unwrap(),
        );
        assert_eq!(ta, tb, "error transition at {k}");
    }
    (dx, dp)
}

fn ekfs<const NX: usize, const NZ: usize>(
    q: Matrix<NX, NX>,
    r: Matrix<NZ, NZ>,
) -> [Ekf<NX, NZ>; 2] {
    [CovarianceUpdate::Standard, CovarianceUpdate::Joseph].map(|update_form| Ekf {
        q,
        r,
        update_form,
    })
}

#[test]
fn p1_declared_structure_equals_the_dense_path() {
    let model = PlanarP1::new(PlanarParams::default());
    let noise = TruthNoise {
        process_std: Vector::<6>::repeat(0.003),
        measurement_std: Vector::<3>::repeat(0.01),
    };
    for scenario in ["basic", "roll", "fall"] {
        let sc = builtin(scenario).unwrap().expand(0.01);
        let draws = NoiseDraws::<6, 3>::draw(run_seed(47, scenario, 3), sc.steps());
        // A large noise scale drives θ through several turns and the covariance far from its
        // steady state, so every entry of the declared pattern matters.
        let traj = simulate(&model, &sc, &noise, 5.0, None, &draws);
        for ekf in ekfs(
            Matrix::<6, 6>::identity() * 0.003f64.powi(2),
            Matrix::<3, 3>::identity() * 0.01f64.powi(2),
        ) {
            let (dx, dp) = compare(&model, &ekf, &sc.controls, &traj.measurements, &traj.x0_hat);
            assert!(
                dx == 0.0 && dp == 0.0,
                "{scenario} {:?}: {dx:e} {dp:e}",
                ekf.update_form
            );
        }
    }
}

#[test]
fn l1_declared_structure_equals_the_dense_path() {
    for sensor in [LinearSensor::Positions, LinearSensor::Velocities] {
        let model = Linear::<3>::new(sensor, 0.1).unwrap();
        let sc = Scenario {
            name: "hover".into(),
            x0: Vector::<6>::new(1.0, 0.0, 1.0, 0.0, 1.0, 0.0),
            controls: (0..=400)
                .map(|k| Vector::<4>::repeat(0.1 * (k as f64 * 0.05).sin()))
                .collect(),
        };
        let draws = NoiseDraws::<6, 3>::draw(run_seed(2016, "hover", 1), sc.steps());
        let traj = simulate(&model, &sc, &model.truth_noise(), 1.0, None, &draws);
        let q = model.process_noise_covariance().unwrap();
        for ekf in ekfs(q, model.r()) {
            let (dx, dp) = compare(&model, &ekf, &sc.controls, &traj.measurements, &traj.x0_hat);
            assert!(
                dx == 0.0 && dp == 0.0,
                "{sensor:?} {:?}: {dx:e} {dp:e}",
                ekf.update_form
            );
        }
    }
}

#[test]
fn a_missing_component_takes_the_dense_path_and_agrees() {
    // θ̇ alone reports: the selection path must step aside (the rows are masked).
    let model = PlanarP1::new(PlanarParams::default());
    let ekf = &ekfs(
        Matrix::<6, 6>::identity() * 1e-5,
        Matrix::<3, 3>::identity() * 1e-4,
    )[0];
    let z = Measurement {
        z: Vector::<3>::new(0.0, 0.0, 0.3),
        available: Availability(0b100),
    };
    let controls = vec![Vector::<2>::new(4.0, 4.1); 50];
    let zs = vec![z; 50];
    let (dx, dp) = compare(
        &model,
        ekf,
        &controls,
        &zs,
        &Vector::<6>::new(0.0, 1.0, 10.0, 0.0, 0.2, 0.0),
    );
    assert!(dx == 0.0 && dp == 0.0, "{dx:e} {dp:e}");
}

/// Every declaration describes the Jacobians: F is zero outside its pattern (whose columns
/// ascend within each row) and H is exactly the selection, at random states and inputs.
fn check_declarations<const NX: usize, const NU: usize, const NZ: usize>(
    model: &impl Model<NX, NU, NZ>,
    seed: u64,
) {
    let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
    let pattern = model.transition_pattern();
    if let Some(p) = pattern {
        for w in p.windows(2) {
            assert!(w[0].0 != w[1].0 || w[0].1 < w[1].1, "columns ascend: {w:?}");
        }
    }
    for _ in 0..200 {
        let x = Vector::<NX>::from_fn(|_, _| rng.random_range(-10.0..10.0));
        let u = Vector::<NU>::from_fn(|_, _| rng.random_range(-10.0..10.0));
        if let Some(p) = pattern {
            let f = model.transition_jacobian(&x, &u);
            for i in 0..NX {
                for j in 0..NX {
                    if !p.contains(&(i, j)) {
                        assert_eq!(f[(i, j)], 0.0, "F[{i},{j}] outside the pattern");
                    }
                }
            }
        }
        if let Some(sel) = model.measurement_selection() {
            let h = model.measurement_jacobian(&x, &u);
            let want = Matrix::<NZ, NX>::from_fn(|i, j| if sel[i] == j { 1.0 } else { 0.0 });
            assert_eq!(h, want);
        }
    }
}

#[test]
fn declarations_describe_the_jacobians() {
    check_declarations(&PlanarP1::new(PlanarParams::default()), 1);
    check_declarations(&PlanarImu::new(PlanarParams::default()), 2);
    for sensor in [LinearSensor::Positions, LinearSensor::Velocities] {
        check_declarations(&Linear::<3>::new(sensor, 0.1).unwrap(), 3);
    }
    check_declarations(&Linear::<2>::new(LinearSensor::Xy, 0.05).unwrap(), 4);
    assert!(
        PlanarP1::new(PlanarParams::default())
            .transition_pattern()
            .is_some()
    );
    assert!(
        PlanarImu::new(PlanarParams::default())
            .measurement_selection()
            .is_none()
    );
}
