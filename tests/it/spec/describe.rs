//! `kfmc describe`: a system's analysis against independent sources.
//!
//! * L1 (seed 002): the closed-loop poles of the steady-state gain against the published
//!   λ_K = [0.9090 ± 0.0831i, 0.9200 ± 0.0739i, 0.9533 ± 0.0445i], and the observability
//!   ranks 6 / 3 / 4 of the sensor sets C, C1, C2 (seed eq. 9).
//! * ρ of the KF against a second algorithm: a dense Riccati and W_k recursion written here
//!   from the F, H, Q and R that describe reports; and the effective dof against the `dof`
//!   column of a study's consistency table (the same quantity folded over 200 real runs).
//! * P1: the planar EKF's x and ẋ are unobservable (rank 4 of 6), and the model is
//!   time-varying, so no steady state is claimed.
//! * The drone's world is not one model: describe says so instead of inventing an analysis.

use std::path::Path;

use crate::common::{kfmc, repo};
use nalgebra::DMatrix;

fn describe(spec: &Path, out: &Path) -> toml::Table {
    let o = kfmc()
        .arg("describe")
        .arg(spec)
        .arg("--out")
        .arg(out)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    std::fs::read_to_string(out).unwrap().parse().unwrap()
}

fn matrix(v: &toml::Value) -> DMatrix<f64> {
    let rows = v.as_array().unwrap();
    let cols = rows[0].as_array().unwrap().len();
    DMatrix::from_fn(rows.len(), cols, |i, j| {
        rows[i].as_array().unwrap()[j].as_float().unwrap()
    })
}

fn scenario(d: &toml::Table, i: usize) -> &toml::Table {
    d["scenarios"].as_array().unwrap()[i].as_table().unwrap()
}

fn filter<'a>(s: &'a toml::Table, label: &str) -> &'a toml::Table {
    s["filters"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| f.as_table().unwrap())
        .find(|f| f["filter"].as_str() == Some(label))
        .unwrap()
}

/// ρ = 1 + (2/(nK)) Σ_{k=2..K} tr(P_k⁻¹ W_k), W_k = A_k (W_{k−1} + P_{k−1}) A_kᵀ, W_1 = 0,
/// A_k = (I − K_k H) F, for a linear KF from P_0.
fn rho_by_hand(
    f: &DMatrix<f64>,
    h: &DMatrix<f64>,
    q: &DMatrix<f64>,
    r: &DMatrix<f64>,
    p0: &DMatrix<f64>,
    steps: usize,
) -> f64 {
    let n = f.nrows();
    let eye = DMatrix::<f64>::identity(n, n);
    let mut p = p0.clone();
    let mut w = DMatrix::<f64>::zeros(n, n);
    let mut sum = 0.0;
    for k in 1..=steps {
        let prior = f * &p * f.transpose() + q;
        let s = h * &prior * h.transpose() + r;
        let gain = &prior * h.transpose() * s.try_inverse().unwrap();
        let post = (&eye - &gain * h) * &prior;
        let a = (&eye - &gain * h) * f;
        if k > 1 {
            w = &a * (&w + &p) * a.transpose();
            sum += (post.clone().try_inverse().unwrap() * &w).trace();
        }
        p = post;
    }
    1.0 + 2.0 * sum / (n as f64 * steps as f64)
}

#[test]
fn l1_poles_ranks_and_rho_match_independent_sources() {
    let dir = tempfile::tempdir().unwrap();
    let spec = repo().join("experiments/linear_nees.toml");
    let d = describe(&spec, &dir.path().join("describe.toml"));
    let s = scenario(&d, 0);
    assert_eq!(s["time_invariant"].as_bool(), Some(true));
    assert_eq!(s["observability"]["rank"].as_integer(), Some(6));

    // Seed 002 §5.4, printed to 4 decimals: within half a unit of the last digit.
    let published = [(0.9090, 0.0831), (0.9200, 0.0739), (0.9533, 0.0445)];
    let poles: Vec<(f64, f64)> = s["steady_state"]["poles"]
        .as_array()
        .unwrap()
        .iter()
        .map(|p| {
            let p = p.as_array().unwrap();
            (p[0].as_float().unwrap(), p[1].as_float().unwrap())
        })
        .collect();
    assert_eq!(poles.len(), 6);
    for (re, im) in published {
        for sign in [1.0, -1.0] {
            assert!(
                poles.iter().any(|p| (p.0 - re).abs() <= 5.0e-5 + 1e-9
                    && (p.1 - sign * im).abs() <= 5.0e-5 + 1e-9),
                "λ_K {re} ± {im}i not among {poles:?}"
            );
        }
    }

    // The three sensor sets of seed eq. 9.
    let section = d["sections"].as_array().unwrap()[0].as_table().unwrap();
    let ranks: Vec<String> = section["rows"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| r["value"].as_str().unwrap().to_string())
        .collect();
    assert!(ranks[0].starts_with("rank 6 of 6"), "{ranks:?}");
    assert!(ranks[1].starts_with("rank 3 of 6"), "{ranks:?}");
    assert!(ranks[2].starts_with("rank 4 of 6"), "{ranks:?}");

    // ρ by a second algorithm, from the matrices describe reports (the KF assumes the
    // truth's Q and R here) and the spec's P0 = I.
    let (f, h) = (matrix(&s["transition"]), matrix(&s["measurement_matrix"]));
    let (q, r) = (matrix(&s["process_noise"]), matrix(&s["measurement_noise"]));
    let steps = s["steps"].as_integer().unwrap() as usize;
    let hand = rho_by_hand(&f, &h, &q, &r, &DMatrix::identity(6, 6), steps);
    let kf = filter(s, "kf");
    let rho = kf["rho"].as_float().unwrap();
    assert!(
        (rho - hand).abs() <= 1e-9 * hand,
        "describe ρ {rho}, by hand {hand}"
    );
    assert!(rho > 1.0);
    // The information and square-root forms are the same filter.
    for other in ["information", "sqrt"] {
        let r2 = filter(s, other)["rho"].as_float().unwrap();
        assert!((r2 - rho).abs() <= 1e-9 * rho, "{other}: {r2} vs {rho}");
    }

    // The same ν folded over 200 real runs (a linear KF's P_k and A_k do not depend on the
    // data, so every run's ρ is the clean one).
    let out = dir.path().join("study");
    let o = kfmc()
        .args(["run", "--quiet", "--out"])
        .arg(&out)
        .arg(&spec)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let cons = crate::common::read(&out.join("consistency.parquet"));
    let (fl, test, runs, dofs) = (
        cons.column("filter").unwrap().str().unwrap().clone(),
        cons.column("test").unwrap().str().unwrap().clone(),
        cons.column("runs").unwrap().i64().unwrap().clone(),
        cons.column("dof").unwrap().f64().unwrap().clone(),
    );
    let row = (0..cons.height())
        .find(|&i| {
            fl.get(i) == Some("kf")
                && test.get(i) == Some("nees_time_average")
                && runs.get(i) == Some(200)
        })
        .expect("the KF's NEES row at N = 200");
    let dof = dofs.get(row).unwrap();
    // A sampled prior drops no step: the sums start at step 1, as describe reports.
    let burn_in = cons
        .column("burn_in_steps")
        .unwrap()
        .i64()
        .unwrap()
        .get(row);
    assert_eq!(burn_in, Some(0));
    assert_eq!(kf["first_step"].as_integer(), Some(1));
    let nu = kf["dof"]
        .as_array()
        .unwrap()
        .iter()
        .find(|t| t["runs"].as_integer() == Some(200))
        .unwrap()["nees_effective_dof"]
        .as_float()
        .unwrap();
    assert!(
        (dof - nu).abs() <= 1e-9 * nu,
        "study dof {dof}, describe ν {nu}"
    );
}

#[test]
fn planar_x_is_unobservable_and_no_steady_state_is_claimed() {
    let dir = tempfile::tempdir().unwrap();
    let d = describe(
        &repo().join("experiments/planar_seed_study.toml"),
        &dir.path().join("d.toml"),
    );
    let s = scenario(&d, 0);
    assert_eq!(s["time_invariant"].as_bool(), Some(false));
    assert_eq!(s["observability"]["rank"].as_integer(), Some(4));
    assert!(s.get("steady_state").is_none());
    // Nothing measured couples to x: F's x and ẋ columns feed no other state, H has none.
    let h = matrix(&s["measurement_matrix"]);
    assert!(
        h.column(0)
            .iter()
            .chain(h.column(1).iter())
            .all(|v| *v == 0.0)
    );
    // u enters the planar dynamics linearly, so G is exact: Δt·(u1 + u2) / m on ẏ at θ = 0.
    assert_eq!(
        s["input_matrix_method"].as_str(),
        Some("exact: f is affine in u")
    );
    let ekf = filter(s, "ekf");
    assert!(ekf["rho"].as_float().unwrap() > 1.0);
}

#[test]
fn a_world_system_says_it_has_no_linearised_analysis() {
    let o = kfmc()
        .args(["describe", "--no-write"])
        .arg(repo().join("experiments/drone_consistency.toml"))
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(text.contains("offers no linearised analysis"), "{text}");
    assert!(text.contains("px [m]"), "{text}");
}

#[test]
fn a_bad_spec_is_refused_with_its_key_path() {
    let (_d, spec) =
        crate::common::spec_in_tempdir("name = \"x\"\nruns = 0\n[model]\nkind = \"nope\"\n");
    let o = kfmc().arg("describe").arg(&spec).output().unwrap();
    assert_eq!(o.status.code(), Some(2));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("model.kind"), "{err}");
}
