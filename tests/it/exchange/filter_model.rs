//! The filter-side model (`SystemPlan::filter_model`, `kfmc describe`'s `[filter_model]`,
//! the step convention of `manifest.toml` and `kfmc schema`) against what the simulation
//! really wrote:
//!
//! * the planar truth of `kfmc simulate` is f(previous row, **this** row's input) plus the
//!   run's drawn process noise, bit for bit, and z is h of the row plus its drawn noise; with
//!   the previous row's input the identity breaks at most steps (so the test can fail on a
//!   wrong step convention);
//! * L1's F, G, H and Q are the matrices its model multiplies with, bit for bit, also after the
//!   round trip through describe.toml; a `kind = "linear"` model's G has the spec's inputs only;
//! * what wraps: P1's θ is continuous (truth and z pass π, the error is not wrapped), its
//!   innovation is wrapped by kfmc's filters; the drone's Euler angles are wrapped errors;
//!   the manifest and the schema say exactly that.

use std::path::Path;

use kfmc::linalg::Vector;
use kfmc::model::Model;
use kfmc::sim::NoiseDraws;
use kfmc::system::additive::AdditivePlan;
use kfmc::systems::linear_quadrotor::model::Linear;

use crate::common::{f64s_or_nan, kfmc, read, spec_in_tempdir};

fn plan_of(text: &str) -> kfmc::experiment::Plan {
    kfmc::experiment::parse_with(text, Path::new("spec.toml"), &kfmc::systems::builtin())
        .unwrap_or_else(|e| panic!("{e}"))
}

const P1_ROLL: &str = r#"
name = "fm_p1"
master_seed = 5
runs = 3
output = "OUT"
[model]
kind = "planar_quadrotor"
process_noise_std = 0.003
measurement_noise_std = 0.01
[[scenarios]]
name = "roll"
duration_s = 10.0
[[filters]]
label = "ekf"
kind = "ekf"
"#;

#[test]
fn the_planar_truth_is_f_of_the_previous_row_with_this_rows_input_plus_its_noise() {
    let (dir, _) = spec_in_tempdir("");
    let out = dir.path().join("sim");
    let text = P1_ROLL.replace("OUT", &out.display().to_string());
    let spec = dir.path().join("p1.toml");
    std::fs::write(&spec, &text).unwrap();
    let st = kfmc()
        .arg("simulate")
        .arg(&spec)
        .arg("-q")
        .status()
        .unwrap();
    assert!(st.success());
    let plan = plan_of(&text);
    let fm = plan
        .system
        .filter_model()
        .expect("P1 has a filter-side model");
    let m = fm.model.as_ref();
    assert_eq!((m.states(), m.inputs(), m.measurements()), (6, 2, 3));
    let truth = read(&out.join("truth.parquet"));
    let meas = read(&out.join("measurements.parquet"));
    let initial = read(&out.join("initial.parquet"));
    let seeds: Vec<u64> = initial
        .column("seed")
        .unwrap()
        .u64()
        .unwrap()
        .into_no_null_iter()
        .collect();
    let states = ["x", "xdot", "y", "ydot", "theta", "thetadot"];
    let xs: Vec<Vec<f64>> = states
        .iter()
        .map(|s| f64s_or_nan(&truth, &format!("truth_{s}")))
        .collect();
    let us: Vec<Vec<f64>> = ["u1", "u2"]
        .iter()
        .map(|s| f64s_or_nan(&meas, &format!("u_{s}")))
        .collect();
    let zs: Vec<Vec<f64>> = ["y", "theta", "thetadot"]
        .iter()
        .map(|s| f64s_or_nan(&meas, &format!("z_{s}")))
        .collect();
    let steps = 1000;
    assert_eq!(truth.height(), 3 * (steps + 1));
    let row = |v: &[Vec<f64>], i: usize| v.iter().map(|c| c[i]).collect::<Vec<f64>>();
    let (mut checked, mut broken_by_lag, mut theta_max) = (0, 0, 0.0f64);
    for (run, &seed) in seeds.iter().enumerate() {
        let draws = NoiseDraws::<6, 3>::draw(seed, steps);
        let base = run * (steps + 1);
        assert!(zs.iter().all(|z| z[base].is_nan()), "z at step 0 is null");
        for k in 1..=steps {
            let (prev, now) = (row(&xs, base + k - 1), row(&xs, base + k));
            let u = row(&us, base + k);
            let fx = m.propagate(&prev, &u).unwrap();
            for i in 0..6 {
                let w = 0.003 * draws.process[k][i];
                assert_eq!(
                    now[i].to_bits(),
                    (fx[i] + w).to_bits(),
                    "run {run} step {k} state {i}"
                );
            }
            let hz = m.measure(&now, &[]).unwrap();
            for i in 0..3 {
                let v = 0.01 * draws.measurement[k][i];
                assert_eq!(zs[i][base + k].to_bits(), (hz[i] + v).to_bits());
            }
            let lagged = m.propagate(&prev, &row(&us, base + k - 1)).unwrap();
            if (0..6)
                .any(|i| (lagged[i] + 0.003 * draws.process[k][i]).to_bits() != now[i].to_bits())
            {
                broken_by_lag += 1;
            }
            theta_max = theta_max.max(now[4]).max(zs[1][base + k]);
            checked += 1;
        }
    }
    assert_eq!(checked, 3 * steps);
    // The ripple changes u at every step, so the previous row's input misses the truth's
    // bits at most steps (2,703 of 3,000 here; at the others the ripple's change is lost in
    // the rounding of f).
    assert!(
        broken_by_lag * 10 > 9 * checked,
        "{broken_by_lag} of {checked}"
    );
    // θ and z_θ are continuous: the roll passes π and neither is wrapped.
    assert!(theta_max > 2.0 * std::f64::consts::PI, "θ max {theta_max}");

    // The manifest says so.
    let manifest: toml::Table =
        toml::from_str(&std::fs::read_to_string(out.join("manifest.toml")).unwrap()).unwrap();
    let conv = &manifest["exchange"]["step_convention"];
    let list = |k: &str| -> Vec<String> {
        conv[k]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_str().unwrap().to_string())
            .collect()
    };
    assert_eq!(list("wrapped_errors"), Vec::<String>::new());
    assert_eq!(list("continuous_angles"), vec!["theta"]);
    assert_eq!(list("wrapped_innovations"), vec!["theta"]);
    assert!(conv["transition"].as_str().unwrap().contains("u_k"));
    let theta = manifest["quantities"]
        .as_array()
        .unwrap()
        .iter()
        .find(|q| q["name"].as_str() == Some("theta"))
        .unwrap();
    assert_eq!(theta["angle"].as_bool(), Some(false));
    // So does the schema.
    let o = kfmc()
        .args(["schema", "measurements"])
        .arg(&spec)
        .output()
        .unwrap();
    let s = String::from_utf8(o.stdout).unwrap();
    assert!(s.contains("errors wrapped (angle quantities): none"), "{s}");
    assert!(
        s.contains("continuous angles (truth, z and error not wrapped): theta"),
        "{s}"
    );
    assert!(s.contains("wrap to [-pi, pi)"), "{s}");
    assert!(s.contains("u_k drives the step from k-1 to k"), "{s}");
}

const L1: &str = r#"
name = "fm_l1"
master_seed = 5
runs = 2
output = "OUT"
[model]
kind = "linear_quadrotor"
sensor = "positions"
[[scenarios]]
name = "hover"
x0 = [1.0, 0.0, 1.0, 0.0, 1.0, 0.0]
duration_s = 2.0
[[filters]]
label = "kf"
kind = "ekf"
[initial_estimate]
mode = "sampled"
p0_std = [1.0, 0.5, 1.0, 0.5, 2.0, 0.25]
"#;

fn bits(v: &[f64]) -> Vec<u64> {
    v.iter().map(|x| x.to_bits()).collect()
}

fn toml_rows(v: &toml::Value) -> Vec<f64> {
    v.as_array()
        .unwrap()
        .iter()
        .flat_map(|r| r.as_array().unwrap().iter().map(|x| x.as_float().unwrap()))
        .collect()
}

#[test]
fn linear_matrices_are_the_models_own_bit_for_bit_also_through_describe() {
    let (dir, _) = spec_in_tempdir("");
    let text = L1.replace("OUT", &dir.path().join("o").display().to_string());
    let plan = plan_of(&text);
    let additive = plan
        .system
        .as_any()
        .downcast_ref::<AdditivePlan<6, 4, 3, Linear<3>>>()
        .expect("L1 with positions");
    let disc = additive.model.discrete();
    let fm = plan.system.filter_model().unwrap();
    let (f, g, h) = fm.model.linear().expect("L1 is linear");
    assert_eq!(bits(&f.data), bits(disc.f.transpose().as_slice()));
    assert_eq!(bits(&g.data), bits(disc.g.transpose().as_slice()));
    assert_eq!(
        bits(&h.data),
        bits(additive.model.h().transpose().as_slice())
    );
    assert_eq!(
        bits(&fm.process_noise.data),
        bits(disc.q.transpose().as_slice())
    );
    let p0 = [1.0f64, 0.5, 1.0, 0.5, 2.0, 0.25];
    for (i, s) in p0.iter().enumerate() {
        assert_eq!(fm.initial_covariance.data[i * 7], s * s);
    }
    assert_eq!(fm.initial_states[0].x0, vec![1.0, 0.0, 1.0, 0.0, 1.0, 0.0]);
    // f is the model's own propagate.
    let x = [0.3, -0.2, 1.5, 0.1, -0.7, 0.05];
    let u = [1.0, 2.0, 3.0, 4.0];
    let want = additive.model.propagate(
        &Vector::<6>::from_column_slice(&x),
        &Vector::<4>::from_column_slice(&u),
    );
    assert_eq!(
        bits(&fm.model.propagate(&x, &u).unwrap()),
        bits(want.as_slice())
    );
    // describe.toml carries them at full precision.
    let spec = dir.path().join("l1.toml");
    std::fs::write(&spec, &text).unwrap();
    let out = dir.path().join("describe.toml");
    let st = kfmc()
        .arg("describe")
        .arg(&spec)
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    assert!(st.status.success());
    let stdout = String::from_utf8(st.stdout).unwrap();
    assert!(stdout.contains("filter-side model (linear"), "{stdout}");
    let d: toml::Table = toml::from_str(&std::fs::read_to_string(&out).unwrap()).unwrap();
    let m = &d["filter_model"];
    assert_eq!(m["form"].as_str(), Some("linear"));
    assert_eq!(bits(&toml_rows(&m["f"])), bits(&f.data));
    assert_eq!(bits(&toml_rows(&m["g"])), bits(&g.data));
    assert_eq!(bits(&toml_rows(&m["h"])), bits(&h.data));
    assert_eq!(bits(&toml_rows(&m["q"])), bits(&fm.process_noise.data));
    assert_eq!(bits(&toml_rows(&m["r"])), bits(&fm.measurement_noise.data));
    assert_eq!(
        bits(&toml_rows(&m["p0"])),
        bits(&fm.initial_covariance.data)
    );
    assert_eq!(
        m["convention"]["wrapped_errors"].as_array().map(Vec::len),
        Some(0)
    );
}

#[test]
fn a_linear_spec_model_takes_only_its_own_inputs() {
    let text =
        std::fs::read_to_string(crate::common::repo().join("experiments/linear_cv_target.toml"))
            .unwrap();
    let plan = plan_of(&text);
    let fm = plan.system.filter_model().unwrap();
    let nu = plan.layout().inputs.len();
    assert!(nu < kfmc::systems::linear::NU_MAX, "the test needs padding");
    let (f, g, _) = fm.model.linear().unwrap();
    assert_eq!((g.rows, g.cols), (f.rows, nu));
    let x = vec![0.5; f.rows];
    assert!(fm.model.propagate(&x, &vec![0.0; nu]).is_ok());
    let e = fm.model.propagate(&x, &[0.0; 4]).unwrap_err().to_string();
    assert!(e.contains(&format!("the model has {nu} inputs")), "{e}");
}

#[test]
fn the_drone_has_no_filter_model_and_scores_its_attitude_as_a_rotation() {
    let text =
        std::fs::read_to_string(crate::common::repo().join("experiments/drone_consistency.toml"))
            .unwrap();
    let plan = plan_of(&text);
    assert!(plan.system.filter_model().is_none());
    let c = kfmc::system::filter_model::convention_of(plan.system.as_ref());
    assert!(c.wrapped_errors.is_empty(), "{:?}", c.wrapped_errors);
    assert_eq!(c.rotation_errors, vec!["roll, pitch, yaw (right error)"]);
    assert!(c.continuous_angles.is_empty() && c.wrapped_innovations.is_empty());
    // With the seed's Euler-angle errors, the three are wrapped angles again.
    let euler = plan_of(&text.replace("[model]\n", "[model]\nattitude_error = \"euler\"\n"));
    let c = kfmc::system::filter_model::convention_of(euler.system.as_ref());
    assert_eq!(c.wrapped_errors, vec!["roll", "pitch", "yaw"]);
    assert!(c.rotation_errors.is_empty());
}
