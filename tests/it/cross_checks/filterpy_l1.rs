//! Cross-check against FilterPy's `KalmanFilter` (an independent implementation).
//!
//! `tests/golden/filterpy_l1_input.csv` holds L1's F, H, Q, R (positions sensor) at full
//! precision and a fixed 300-step measurement sequence with predict-only gaps; it is written by
//! this file with `KFMC_BLESS=1 cargo test --release --test it cross_checks::filterpy_l1::`.
//! `tests/reference/filterpy_l1.py` reads it, runs FilterPy and writes
//! `tests/golden/filterpy_l1.csv` (x̂_k and P_k per step). The test replays the same
//! measurements through kfmc's KF (the EKF on L1; a gap is a measurement with no component
//! available) and requires agreement to 1e-9.

use std::fmt::Write as _;

use crate::common::{Csv, repo};
use kfmc::filter::{CovarianceUpdate, Ekf, Filter};
use kfmc::linalg::{Matrix, Vector};
use kfmc::model::{Availability, Measurement, Model};
use kfmc::scenario::Scenario;
use kfmc::sim::{NoiseDraws, simulate};
use kfmc::systems::linear_quadrotor::model::{Linear, LinearSensor};

const STEPS: usize = 300;

fn model() -> Linear<3> {
    Linear::<3>::new(LinearSensor::Positions, 0.1).unwrap()
}

/// Step k reports nothing on every 10th step and for k in 150..=165.
fn gap(k: usize) -> bool {
    k.is_multiple_of(10) || (150..=165).contains(&k)
}

fn matrix_row<const R: usize, const C: usize>(name: &str, m: &Matrix<R, C>) -> String {
    let mut s = format!("{name},{R},{C}");
    for i in 0..R {
        for j in 0..C {
            write!(s, ",{:?}", m[(i, j)]).unwrap();
        }
    }
    s
}

/// The input file's text (model matrices, then `k,available,z_x,z_y,z_z` rows).
fn input_text() -> String {
    let m = model();
    let mut s = String::new();
    for line in [
        matrix_row("F", &m.discrete().f),
        matrix_row("H", m.h()),
        matrix_row("Q", &m.discrete().q),
        matrix_row("R", &m.r()),
    ] {
        s += &line;
        s.push('\n');
    }
    let draws = NoiseDraws::<6, 3>::draw(42, STEPS);
    let x_hat0 = Vector::<6>::new(1.0, 0.0, 1.0, 0.0, 1.0, 0.0);
    let sc = Scenario::unforced("filterpy", x_hat0 + draws.initial, STEPS);
    let noise = m.truth_noise();
    let t = simulate(&m, &sc, &noise, 1.0, None, &draws);
    for (k, z) in t.measurements.iter().enumerate().skip(1) {
        let a = u8::from(!gap(k));
        writeln!(s, "z,{k},{a},{:?},{:?},{:?}", z.z[0], z.z[1], z.z[2]).unwrap();
    }
    s
}

#[test]
fn kf_matches_filterpy_to_1e_9() {
    let dir = repo().join("tests/golden");
    let input = dir.join("filterpy_l1_input.csv");
    if std::env::var_os("KFMC_BLESS").is_some() {
        std::fs::write(&input, input_text()).unwrap();
    }
    // The committed input must still be what the model produces (guards against a stale file).
    assert_eq!(
        std::fs::read_to_string(&input).unwrap(),
        input_text(),
        "regenerate with KFMC_BLESS=1 and rerun tests/reference/filterpy_l1.py"
    );
    let m = model();
    let kf = Ekf {
        q: m.discrete().q,
        r: m.r(),
        // FilterPy's KalmanFilter.update uses the Joseph form.
        update_form: CovarianceUpdate::Joseph,
    };
    let golden = Csv::read(&dir.join("filterpy_l1.csv"));
    assert_eq!(golden.rows.len(), STEPS + 1);
    let text = std::fs::read_to_string(&input).unwrap();
    let zs: Vec<Measurement<3>> = text
        .lines()
        .filter(|l| l.starts_with("z,"))
        .map(|l| {
            let v: Vec<f64> = l.split(',').skip(2).map(|c| c.parse().unwrap()).collect();
            let available = if v[0] == 1.0 {
                Availability::all(3)
            } else {
                Availability(0)
            };
            Measurement {
                z: Vector::<3>::new(v[1], v[2], v[3]),
                available,
            }
        })
        .collect();
    let u = Vector::<4>::zeros();
    let x0 = Vector::<6>::new(1.0, 0.0, 1.0, 0.0, 1.0, 0.0);
    let mut b = kf.init(&m, &x0, &Matrix::identity(), &zs[0]);
    let mut worst = 0.0f64;
    for k in 0..=STEPS {
        if k > 0 {
            Filter::<6, 4, 3, _>::predict(&kf, &m, &mut b, &u).unwrap();
            Filter::<6, 4, 3, _>::update(&kf, &m, &mut b, &u, &zs[k - 1]).unwrap();
        }
        assert_eq!(golden.f(k, "k") as usize, k);
        for i in 0..6 {
            let e = (b.x[i] - golden.f(k, &format!("x{i}"))).abs();
            worst = worst.max(e);
            for j in 0..6 {
                let e = (b.p[(i, j)] - golden.f(k, &format!("p{i}{j}"))).abs();
                worst = worst.max(e);
            }
        }
        assert!(
            worst <= 1e-9,
            "step {k}: differs from FilterPy by {worst:e}"
        );
    }
    println!("max |Δx̂|, |ΔP| against FilterPy over {STEPS} steps: {worst:.2e}");
    // Sanity: the gaps are real predict-only steps, and the replay is not trivially zero.
    assert!(zs.iter().filter(|z| z.available.count() == 0).count() > 30);
    assert!(m.measure(&b.x, &u).amax() > 0.0);
}
