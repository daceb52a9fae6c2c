//! `kfmc tune --method ml`: the innovations likelihood against the joint Gaussian density of
//! the stacked measurements (an independent formula, no filter), its score against finite
//! differences, the coverage of the intervals over seeded replications, convergence from a
//! mistuned start, thread independence of the tables, and the bad-input errors.

use std::path::Path;

use kfmc::experiment::tune_spec::NoiseMatrix;
use kfmc::experiment::{self, Overrides, Plan};
use kfmc::runner::NullObserver;
use kfmc::tune::estimate::SearchSettings;
use kfmc::tune::likelihood::{LinearModel, Parameter, Problem, Series};
use kfmc::tune::ml::{MlOptions, prepare};
use nalgebra::{DMatrix, DVector};

use crate::common::{f64s, kfmc, read, spec_in_tempdir, strs, table_bytes};

/// A 2-D constant-velocity target with position fixes; Q and R diagonal. The tuned elements
/// are the two velocity noises and the two fix noises.
pub const CV_SPEC: &str = r#"
name = "tune_ml_cv"
master_seed = 7
runs = 4
output = "OUT"

[model]
kind = "linear"
states = ["px", "vx", "py", "vy"]
measurements = ["zx", "zy"]
dt_s = 0.1
f = [
  [1.0, 0.1, 0.0, 0.0],
  [0.0, 1.0, 0.0, 0.0],
  [0.0, 0.0, 1.0, 0.1],
  [0.0, 0.0, 0.0, 1.0],
]
h = [
  [1.0, 0.0, 0.0, 0.0],
  [0.0, 0.0, 1.0, 0.0],
]
q = [
  [1e-4, 0.0, 0.0,  0.0],
  [0.0, 0.04, 0.0,  0.0],
  [0.0, 0.0,  1e-4, 0.0],
  [0.0, 0.0,  0.0,  0.09],
]
r = [
  [0.25, 0.0],
  [0.0,  1.0],
]

[[scenarios]]
name = "cruise"
x0 = [0.0, 1.0, 0.0, -1.0]
duration_s = 30.0

[[filters]]
label = "kf"
kind = "ekf"

[initial_estimate]
mode = "sampled"
p0_std = [1.0, 0.5, 1.0, 0.5]

[tune]
method = "ml"
elements = ["q[vx,vx]", "q[vy,vy]", "r[zx,zx]", "r[zy,zy]"]
"#;

/// The true values of CV_SPEC's tuned elements, in the order of `tune.elements`.
const CV_TRUTH: [f64; 4] = [0.04, 0.09, 0.25, 1.0];

fn cv_plan(text: &str, out: &Path, seed: u64) -> Plan {
    let text = text.replace("OUT", &out.display().to_string());
    let mut plan = experiment::parse(&text, Path::new("cv.toml")).unwrap_or_else(|e| panic!("{e}"));
    plan.apply(&Overrides {
        runs: None,
        master_seed: Some(seed),
        output: None,
        trace_runs: None,
    })
    .unwrap();
    plan
}

fn ml_options() -> MlOptions {
    MlOptions {
        elements: None,
        measurements: None,
        search: SearchSettings::default(),
        force: false,
        threads: 2,
    }
}

/// −ln L of one run from the joint density of all its reported measurements: the stacked
/// z is Gaussian with mean H_a m_k and covariance H_a C_jk H_bᵀ + δ_jk R_ab, where m_k and
/// C_jk = F^{k−j} C_jj are the moments of the states (no filter, no recursion in S).
fn joint_density_nll(model: &LinearModel, q: &DMatrix<f64>, r: &DMatrix<f64>, s: &Series) -> f64 {
    let (n, p, nu) = (model.f.nrows(), model.h.nrows(), model.g.ncols());
    let steps = s.z.len() / p;
    let mut means = vec![s.x0.clone()];
    let mut covs = vec![s.p0.clone()];
    for k in 1..steps {
        let u = DVector::from_column_slice(&s.u[k * nu..(k + 1) * nu]);
        means.push(&model.f * &means[k - 1] + &model.g * u);
        covs.push(&model.f * &covs[k - 1] * model.f.transpose() + q);
    }
    // Every reported (step, component).
    let obs: Vec<(usize, usize)> = (1..steps)
        .flat_map(|k| (0..p).map(move |j| (k, j)))
        .filter(|&(k, j)| s.z[k * p + j].is_finite())
        .collect();
    let big = obs.len();
    let mut sigma = DMatrix::zeros(big, big);
    let mut resid = DVector::zeros(big);
    let fpow = |d: usize| (0..d).fold(DMatrix::identity(n, n), |a, _| &model.f * a);
    for (a, &(k, i)) in obs.iter().enumerate() {
        resid[a] = s.z[k * p + i] - (model.h.row(i) * &means[k])[0];
        for (b, &(l, j)) in obs.iter().enumerate() {
            // Cov(x_k, x_l) = F^{k−l} C_l for k ≥ l.
            let c = if k >= l {
                fpow(k - l) * &covs[l]
            } else {
                &covs[k] * fpow(l - k).transpose()
            };
            let mut v = (model.h.row(i) * c * model.h.row(j).transpose())[0];
            if k == l {
                v += r[(i, j)];
            }
            sigma[(a, b)] = v;
        }
    }
    let chol = sigma.cholesky().expect("positive definite");
    let ln_det: f64 = 2.0 * chol.l().diagonal().iter().map(|d| d.ln()).sum::<f64>();
    0.5 * (ln_det + resid.dot(&chol.solve(&resid)) + big as f64 * (2.0 * std::f64::consts::PI).ln())
}

/// A small model (3 states, an input, 2 components) with a full Q, and a run where the second
/// component reports every third step.
fn small_problem() -> (LinearModel, Vec<Series>) {
    let model = LinearModel {
        f: DMatrix::from_row_slice(3, 3, &[0.9, 0.2, 0.0, -0.1, 0.95, 0.1, 0.0, 0.05, 0.8]),
        g: DMatrix::from_row_slice(3, 1, &[0.0, 0.5, 0.2]),
        h: DMatrix::from_row_slice(2, 3, &[1.0, 0.0, 0.0, 0.3, 0.0, 1.0]),
        q: DMatrix::from_row_slice(3, 3, &[0.2, 0.05, 0.0, 0.05, 0.3, 0.02, 0.0, 0.02, 0.1]),
        r: DMatrix::from_row_slice(2, 2, &[0.5, 0.0, 0.0, 0.8]),
    };
    // Deterministic "measurements": any numbers are data to a likelihood.
    let steps = 25;
    let mut z = vec![f64::NAN; 2 * steps];
    let mut u = vec![0.0; steps];
    for k in 1..steps {
        let t = k as f64;
        z[2 * k] = (0.7 * t).sin() * 2.0 + 0.1 * t;
        if k % 3 == 0 {
            z[2 * k + 1] = (0.3 * t).cos() - 0.5;
        }
        u[k] = (0.2 * t).sin();
    }
    let s = Series {
        x0: DVector::from_column_slice(&[0.5, -0.2, 0.1]),
        p0: DMatrix::from_row_slice(3, 3, &[1.0, 0.1, 0.0, 0.1, 0.5, 0.0, 0.0, 0.0, 0.7]),
        u,
        z,
    };
    (model, vec![s])
}

#[test]
fn the_likelihood_equals_the_joint_density_of_the_stacked_measurements() {
    let (model, series) = small_problem();
    let params = [
        Parameter {
            matrix: NoiseMatrix::Q,
            index: 1,
        },
        Parameter {
            matrix: NoiseMatrix::R,
            index: 1,
        },
    ];
    let problem = Problem {
        model: &model,
        series: &series,
        params: &params,
    };
    for theta in [vec![0.3f64.ln(), 0.8f64.ln()], vec![(-3.0f64), 1.5]] {
        let ours = problem.evaluate(&theta, false).unwrap().value;
        let (q, r) = problem.covariances(&theta);
        let joint = joint_density_nll(&model, &q, &r, &series[0]);
        let rel = (ours - joint).abs() / joint.abs();
        assert!(
            rel < 1e-10,
            "θ = {theta:?}: KF {ours} vs joint {joint} (rel {rel:e})"
        );
        // With derivatives the value is the same bits.
        let with = problem.evaluate(&theta, true).unwrap();
        assert_eq!(with.value.to_bits(), ours.to_bits());
        // The score against central differences of the joint density (a 4th-order
        // stencil, h = 1e-3 in ln units: truncation ~1e-12).
        for i in 0..2 {
            let at = |d: f64| {
                let mut t = theta.clone();
                t[i] += d;
                let (q, r) = problem.covariances(&t);
                joint_density_nll(&model, &q, &r, &series[0])
            };
            let h = 1e-3;
            let fd = (-at(2.0 * h) + 8.0 * at(h) - 8.0 * at(-h) + at(-2.0 * h)) / (12.0 * h);
            let g = with.gradient[i];
            assert!(
                (g - fd).abs() <= 1e-6 * fd.abs().max(1.0),
                "θ = {theta:?}, ∂/∂θ_{i}: score {g} vs differences {fd}"
            );
        }
    }
}

#[test]
fn intervals_cover_the_truth_at_their_nominal_rate_over_40_replications() {
    // 40 seeds × 4 elements = 160 intervals. With correct standard errors the count that
    // covers is Binomial(160, 0.95) (mean 152): P(count ≤ 140) < 1e-4 and P(count ≥ 159) =
    // 2.6e-3. The mean of z² = ((θ̂ − θ)/se)² is 1 with a standard deviation of about 0.11;
    // an information matrix off by a factor 2 either way puts it at 2 or ½. Fixed seeds:
    // the result is the same on every machine.
    let dir = tempfile::tempdir().unwrap();
    let reps = 40u64;
    let mut covered = 0;
    let mut z2 = 0.0;
    let mut log_err = [0.0f64; 4];
    let mut se_sum = [0.0f64; 4];
    let settings = SearchSettings {
        starts: vec![1.0],
        ..SearchSettings::default()
    };
    for rep in 0..reps {
        let plan = cv_plan(CV_SPEC, dir.path(), 1000 + rep);
        let prepared = prepare(&plan, &ml_options(), &NullObserver).unwrap();
        let est = prepared.search(&settings, 2, &|_| {}).unwrap();
        assert!(est.converged, "replication {rep} did not converge");
        for (i, truth) in CV_TRUTH.iter().enumerate() {
            let (_, _, ci) = est.natural(i);
            let (lo, hi) = ci.expect("every element is identified");
            covered += usize::from(lo <= *truth && *truth <= hi);
            let se = est.se_log[i].unwrap();
            let e = est.theta[i] - truth.ln();
            z2 += (e / se).powi(2);
            log_err[i] += e;
            se_sum[i] += se;
        }
    }
    let total = 4 * reps as usize;
    let z2 = z2 / total as f64;
    assert!(
        (141..=158).contains(&covered),
        "{covered}/{total} intervals cover the truth"
    );
    assert!((0.6..=1.5).contains(&z2), "mean z² = {z2}");
    // No element is biased in ln units beyond 4 standard errors of the mean error (the
    // error's spread is its mean se, checked through z² above).
    for i in 0..4 {
        let mean = log_err[i] / reps as f64;
        let se_mean = se_sum[i] / reps as f64 / (reps as f64).sqrt();
        assert!(
            mean.abs() < 4.0 * se_mean,
            "element {i}: mean ln error {mean}, its standard error {se_mean}"
        );
    }
}

/// Writes CV_SPEC with the tuned elements' spec values multiplied by (×4, ×0.25, R×10) into
/// `dir`, writing into `out`.
fn mistuned_spec(dir: &Path, out: &Path) -> std::path::PathBuf {
    let text = CV_SPEC
        .replace("OUT", &out.display().to_string())
        .replace("[0.0, 0.04, 0.0,  0.0]", "[0.0, 0.16, 0.0,  0.0]")
        .replace("[0.0, 0.0,  0.0,  0.09]", "[0.0, 0.0,  0.0,  0.0225]")
        .replace("[0.25, 0.0]", "[2.5, 0.0]")
        .replace("[0.0,  1.0]", "[0.0,  10.0]");
    assert_ne!(text, CV_SPEC.replace("OUT", &out.display().to_string()));
    let path = dir.join("mistuned.toml");
    std::fs::write(&path, text).unwrap();
    path
}

#[test]
fn a_mistuned_start_converges_back_and_its_intervals_hold_the_truth() {
    let dir = tempfile::tempdir().unwrap();
    let sim = dir.path().join("sim");
    let (_spec_dir, spec) = spec_in_tempdir(&CV_SPEC.replace("OUT", &sim.display().to_string()));
    let o = kfmc()
        .args(["simulate", spec.to_str().unwrap(), "--runs", "8", "--quiet"])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let out = dir.path().join("tuned");
    let mistuned = mistuned_spec(dir.path(), &out);
    let meas = sim.join("measurements.parquet");
    let o = kfmc()
        .args([
            "tune",
            mistuned.to_str().unwrap(),
            "--method",
            "ml",
            "--measurements",
            meas.to_str().unwrap(),
            "--quiet",
        ])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let t = read(&out.join("tuned.parquet"));
    assert_eq!(
        strs(&t, "element"),
        ["Q[vx,vx]", "Q[vy,vy]", "R[zx,zx]", "R[zy,zy]"]
    );
    let (est, lo, hi) = (
        f64s(&t, "estimate"),
        f64s(&t, "ci_low"),
        f64s(&t, "ci_high"),
    );
    for i in 0..4 {
        let (lo, hi) = (lo[i].unwrap(), hi[i].unwrap());
        assert!(
            lo <= CV_TRUTH[i] && CV_TRUTH[i] <= hi,
            "{i}: truth {} outside [{lo}, {hi}] (estimate {:?})",
            CV_TRUTH[i],
            est[i]
        );
    }
    // The same data tuned from the true values reach the same optimum.
    let plan = cv_plan(CV_SPEC, &dir.path().join("unused"), 7);
    let opts = MlOptions {
        measurements: Some(meas.clone()),
        ..ml_options()
    };
    let prepared = prepare(&plan, &opts, &NullObserver).unwrap();
    let from_truth = prepared
        .search(&SearchSettings::default(), 2, &|_| {})
        .unwrap();
    for (i, (t, b)) in from_truth.theta.iter().zip(&est).enumerate() {
        let (a, b) = (t.exp(), b.unwrap());
        assert!(
            (a - b).abs() <= 1e-5 * a,
            "{i}: {a} from the truth, {b} from the mistuned start"
        );
    }
    // The file's runs are the spec's simulation: the in-memory data give the same estimate.
    let mut plan8 = cv_plan(CV_SPEC, &dir.path().join("unused"), 7);
    plan8
        .apply(&Overrides {
            runs: Some(8),
            master_seed: None,
            output: None,
            trace_runs: None,
        })
        .unwrap();
    let mem = prepare(&plan8, &ml_options(), &NullObserver).unwrap();
    // Compared by bits (NaN marks a component that did not report, and NaN ≠ NaN).
    let bits = |series: &[Series]| -> Vec<Vec<u64>> {
        series
            .iter()
            .map(|s| {
                s.x0.iter()
                    .chain(s.p0.iter())
                    .chain(&s.u)
                    .chain(&s.z)
                    .map(|v| v.to_bits())
                    .collect()
            })
            .collect()
    };
    assert!(
        bits(&mem.series) == bits(&prepared.series),
        "the simulated runs differ from the file's"
    );
    let toml = std::fs::read_to_string(out.join("tuned.toml")).unwrap();
    let doc: toml::Table = toml.parse().unwrap();
    let q = doc["model"]["q"].as_array().unwrap();
    let q11 = q[1].as_array().unwrap()[1].as_float().unwrap();
    assert_eq!(
        q11,
        est[0].unwrap(),
        "tuned.toml's q[vx,vx] is the estimate"
    );
}

#[test]
fn the_tables_are_the_same_bits_on_one_and_two_threads() {
    let dir = tempfile::tempdir().unwrap();
    let (_d, spec) = spec_in_tempdir(&CV_SPEC.replace("OUT", "unused"));
    let mut bytes = Vec::new();
    for threads in ["1", "2"] {
        let out = dir.path().join(format!("t{threads}"));
        let o = kfmc()
            .args([
                "tune",
                spec.to_str().unwrap(),
                "--out",
                out.to_str().unwrap(),
                "--runs",
                "6",
                "--threads",
                threads,
                "--quiet",
            ])
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let tables = table_bytes(&out);
        let names: Vec<&str> = tables.iter().map(|t| t.0.as_str()).collect();
        assert_eq!(names, ["tune_trace.parquet", "tuned.parquet"]);
        bytes.push((tables, std::fs::read(out.join("tuned.toml")).unwrap()));
    }
    assert!(
        bytes[0] == bytes[1],
        "the tables differ between 1 and 2 threads"
    );
}

/// Runs `kfmc tune` on `spec` with `args`, expecting a failure; returns stderr.
fn fails(spec: &str, args: &[&str]) -> String {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    let (_d, path) = spec_in_tempdir(&spec.replace("OUT", &out.display().to_string()));
    let o = kfmc()
        .arg("tune")
        .arg(&path)
        .args(args)
        .arg("--quiet")
        .output()
        .unwrap();
    assert!(!o.status.success(), "kfmc tune {args:?} succeeded");
    String::from_utf8_lossy(&o.stderr).into_owned()
}

#[test]
fn bad_elements_and_data_are_errors_naming_the_key_and_the_file() {
    let with = |elements: &str| {
        CV_SPEC.replace(
            r#"elements = ["q[vx,vx]", "q[vy,vy]", "r[zx,zx]", "r[zy,zy]"]"#,
            &format!("elements = {elements}"),
        )
    };
    let e = fails(&with(r#"["q[vx,vx]", "q[vx,vz]"]"#), &[]);
    assert!(
        e.contains("spec.toml")
            && e.contains("tune.elements[1]")
            && e.contains("unknown state `vz`"),
        "{e}"
    );
    let e = fails(&with(r#"["q[vx,vx]", "q[vy,vy]", "p[px,px]"]"#), &[]);
    assert!(
        e.contains("tune.elements[2]") && e.contains("no matrix `p`"),
        "{e}"
    );
    let e = fails(&with(r#"["r[vx,vx]"]"#), &[]);
    assert!(e.contains("unknown measurement component `vx`"), "{e}");
    // The flag wins over the table, and is named the same way.
    let e = fails(CV_SPEC, &["--elements", "q[vx,vx]", "r[zq,zq]"]);
    assert!(e.contains("--elements[1]") && e.contains("`zq`"), "{e}");
    // Too few measurements: 1 run of 0.2 s has 4 scalar measurements for 4 elements.
    let short = CV_SPEC.replace("duration_s = 30.0", "duration_s = 0.2");
    let e = fails(&short, &["--runs", "1"]);
    assert!(
        e.contains("spec.toml")
            && e.contains("tune.elements")
            && e.contains("at least 40 scalar measurements"),
        "{e}"
    );
    // A measurement file whose columns are not the model's.
    let dir = tempfile::tempdir().unwrap();
    let sim = dir.path().join("sim");
    let other = CV_SPEC
        .replace("OUT", &sim.display().to_string())
        .replace(
            r#"measurements = ["zx", "zy"]"#,
            r#"measurements = ["zx", "zq"]"#,
        )
        .replace(r#""r[zx,zx]", "r[zy,zy]""#, r#""r[zx,zx]""#);
    let (_d, other_spec) = spec_in_tempdir(&other);
    let o = kfmc()
        .args([
            "simulate",
            other_spec.to_str().unwrap(),
            "--runs",
            "1",
            "--quiet",
        ])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let file = sim.join("measurements.parquet");
    let e = fails(CV_SPEC, &["--measurements", file.to_str().unwrap()]);
    assert!(
        e.contains("measurements.parquet") && e.contains("z_zq"),
        "{e}"
    );
    // A system that is not linear.
    let planar = r#"
name = "p"
runs = 2
output = "OUT"
[model]
kind = "planar_quadrotor"
[[scenarios]]
name = "basic"
duration_s = 2.0
[[filters]]
label = "ekf"
kind = "ekf"
[tune]
method = "ml"
elements = ["q[x,x]"]
"#;
    let e = fails(planar, &[]);
    assert!(e.contains("model.kind") && e.contains("not linear"), "{e}");
}
