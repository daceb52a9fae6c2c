//! `kfmc tune --method truth`: its filter against the study engine's own filter on the same
//! runs, recovery of the true Q and R on a fixed seed, the sandwich standard errors against
//! the spread of the estimates across seeds, the scale the `mse` objective cannot fix,
//! thread independence of the tables, and the bad-input errors.

use std::path::Path;

use kfmc::experiment::{self, Overrides, Plan};
use kfmc::runner::NullObserver;
use kfmc::step_loop::Unit;
use kfmc::tune::conditions::{TruthObjective, run_stats};
use kfmc::tune::estimate::SearchSettings;
use kfmc::tune::truth::{TruthOptions, prepare};

use super::tune_ml::CV_SPEC;
use crate::common::{kfmc, read, spec_in_tempdir, strs, table_bytes};

/// CV_SPEC tuned by the truth method.
fn truth_spec() -> String {
    CV_SPEC.replace(r#"method = "ml""#, r#"method = "truth""#)
}

/// The true values of the tuned elements, in the order of `tune.elements`.
const TRUTH: [f64; 4] = [0.04, 0.09, 0.25, 1.0];

fn plan(text: &str, runs: usize, seed: u64) -> Plan {
    let mut plan = experiment::parse(&text.replace("OUT", "unused"), Path::new("cv.toml")).unwrap();
    plan.apply(&Overrides {
        runs: Some(runs),
        master_seed: Some(seed),
        output: None,
        trace_runs: None,
    })
    .unwrap();
    plan
}

fn options(objective: TruthObjective) -> TruthOptions {
    TruthOptions {
        elements: None,
        objective,
        search: SearchSettings::default(),
        force: false,
        threads: 2,
    }
}

#[test]
fn the_conditions_filter_is_the_study_engines_filter_on_the_same_runs() {
    // At the spec's Q and R (q_scale = r_scale = 1) the study engine's filter, traced with its
    // innovations, gives every run's mean e²/P and ν²/S; the truth method's in-memory filter
    // on the runs it simulated must give the same numbers: the same runs (seeds) and the same
    // filter.
    let mut p = plan(&truth_spec(), 6, 5);
    let prepared = prepare(&p, &options(TruthObjective::Consistency), &NullObserver).unwrap();
    p.trace_runs = p.runs;
    p.export_estimates = true;
    let trial = p.trial();
    let (n, nz) = (4, 2);
    for (run, tr) in prepared.runs.iter().enumerate() {
        let ours = run_stats(&prepared.model, &prepared.model.q, &prepared.model.r, tr).unwrap();
        let unit = trial.run(&Unit {
            scenario: 0,
            scale: 0,
            run,
        });
        let t = unit.trace.unwrap();
        assert_eq!(t.truth, tr.truth, "run {run}: another truth");
        let (est, cov, ex) = (&t.est[0], &t.cov[0], t.export[0].as_ref().unwrap());
        let steps = t.truth.len() / n;
        let (mut nees, mut nis) = (vec![0.0; n], vec![0.0; nz]);
        for k in 1..steps {
            for i in 0..n {
                let e = est[k * n + i] - t.truth[k * n + i];
                // The lower triangle row by row: (i, i) is entry i(i+1)/2 + i.
                let pii = cov[k * n * (n + 1) / 2 + i * (i + 1) / 2 + i];
                nees[i] += e * e / pii;
            }
            for (j, sum) in nis.iter_mut().enumerate() {
                let sjj = ex.s[k * nz * (nz + 1) / 2 + j * (j + 1) / 2 + j];
                *sum += ex.nu[k * nz + j].powi(2) / sjj;
            }
        }
        let k = (steps - 1) as f64;
        for (i, sum) in nees.iter().enumerate() {
            let theirs = sum / k;
            assert!(
                (ours.nees[i] - theirs).abs() <= 1e-9 * theirs,
                "run {run} state {i}: {} vs the engine's {theirs}",
                ours.nees[i]
            );
        }
        for (j, sum) in nis.iter().enumerate() {
            let theirs = sum / k;
            assert!(
                (ours.nis[j] - theirs).abs() <= 1e-9 * theirs,
                "run {run} component {j}: {} vs the engine's {theirs}",
                ours.nis[j]
            );
        }
    }
}

#[test]
fn truth_recovers_the_true_q_and_r_on_a_fixed_seed() {
    // 40 runs of 300 steps: the sandwich se of ln θ̂ is about 0.045 for the velocity noises
    // and 0.015 for the fix noises (docs' coverage table at 20 runs, / √2), so 0.2 in ln units
    // (a factor 1.22) is over 4 standard errors for every element. The search must also land
    // on a root of the conditions and from the ×0.1 and ×10 starts alike.
    let p = plan(&truth_spec(), 40, 3);
    let prepared = prepare(&p, &options(TruthObjective::Consistency), &NullObserver).unwrap();
    let (est, residuals, notes) = prepared
        .search(&SearchSettings::default(), 2, &|_| {})
        .unwrap();
    assert!(est.converged && notes.is_empty());
    for (i, truth) in TRUTH.iter().enumerate() {
        let err = est.theta[i] - truth.ln();
        let se = est.se_log[i].unwrap();
        assert!(
            err.abs() < 0.2 && err.abs() < 4.0 * se,
            "{}: ln error {err} (se {se})",
            prepared.elements[i].name
        );
        assert!(residuals[i].abs() < 1e-6, "not a root: {residuals:?}");
        assert!(est.identifiable[i]);
    }
    // Every start reaches the same root.
    let finals: Vec<&Vec<f64>> = (0..3)
        .map(|s| &est.trace.iter().rfind(|r| r.start == s).unwrap().parameters)
        .collect();
    for f in &finals[1..] {
        for (a, b) in f.iter().zip(finals[0]) {
            assert!((a / b - 1.0).abs() < 1e-5, "{finals:?}");
        }
    }
}

#[test]
fn the_sandwich_standard_error_matches_the_spread_across_seeds() {
    // 30 independent seeds × 12 runs: the standard deviation of ln θ̂ across seeds estimates
    // the true standard error to about ±13 % (1/√(2·29)); the mean sandwich se must be within
    // a factor 1.5 of it (beyond 3 of those standard errors), for every element.
    let seeds = 30;
    let mut logs = vec![Vec::new(); 4];
    let mut ses = vec![0.0; 4];
    for seed in 1..=seeds {
        let p = plan(&truth_spec(), 12, 100 + seed);
        let prepared = prepare(&p, &options(TruthObjective::Consistency), &NullObserver).unwrap();
        let settings = SearchSettings {
            starts: vec![1.0],
            ..SearchSettings::default()
        };
        let (est, _, _) = prepared.search(&settings, 2, &|_| {}).unwrap();
        for (i, (log, se)) in logs.iter_mut().zip(ses.iter_mut()).enumerate() {
            log.push(est.theta[i]);
            *se += est.se_log[i].unwrap() / seeds as f64;
        }
    }
    for (i, (log, se)) in logs.iter().zip(&ses).enumerate() {
        let n = log.len() as f64;
        let mean = log.iter().sum::<f64>() / n;
        let sd = (log.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0)).sqrt();
        let ratio = se / sd;
        assert!(
            (1.0 / 1.5..=1.5).contains(&ratio),
            "element {i}: mean sandwich se {se} vs spread {sd} (ratio {ratio})"
        );
    }
}

#[test]
fn mse_recovers_the_ratio_and_names_the_scale_it_cannot_fix() {
    // No position noise: every non-zero element of Q and R is tuned, so scaling them all
    // together leaves the gain, and so the MSE, unchanged. The ratio Q[vx,vx]/R[zx,zx] (0.16
    // in truth) is what the MSE identifies; no element gets an interval.
    let text = truth_spec()
        .replace("[1e-4, 0.0, 0.0,  0.0]", "[0.0, 0.0, 0.0,  0.0]")
        .replace("[0.0, 0.0,  1e-4, 0.0]", "[0.0, 0.0,  0.0, 0.0]");
    assert_ne!(text, truth_spec());
    let p = plan(&text, 20, 9);
    let prepared = prepare(&p, &options(TruthObjective::Mse), &NullObserver).unwrap();
    let (est, _, notes) = prepared
        .search(&SearchSettings::default(), 2, &|_| {})
        .unwrap();
    assert!(
        est.identifiable.iter().all(|b| !b),
        "{:?}",
        est.identifiable
    );
    assert!(est.se_log.iter().all(Option::is_none));
    assert!(
        notes.iter().any(|n| n.contains("common scale")),
        "{notes:?}"
    );
    assert!(
        est.flat
            .iter()
            .any(|d| d.components.iter().all(|c| (c - 0.5).abs() < 1e-12)),
        "the common scale is not among the flat directions: {:?}",
        est.flat
    );
    let ratio = (est.theta[0] - est.theta[2]).exp();
    assert!(
        (ratio / 0.16 - 1.0).abs() < 0.3,
        "Q[vx,vx]/R[zx,zx] = {ratio}, truth 0.16"
    );
}

#[test]
fn the_truth_tables_are_the_same_bits_on_one_and_two_threads() {
    let dir = tempfile::tempdir().unwrap();
    let (_d, spec) = spec_in_tempdir(&truth_spec().replace("OUT", "unused"));
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
                "8",
                "--threads",
                threads,
                "--quiet",
            ])
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let tuned = read(&out.join("tuned.parquet"));
        assert_eq!(strs(&tuned, "method"), ["truth"; 4]);
        bytes.push((
            table_bytes(&out),
            std::fs::read(out.join("tuned.toml")).unwrap(),
        ));
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
fn bad_input_to_the_truth_method_is_an_error_naming_what_is_wrong() {
    let spec = truth_spec();
    // A prior that is not the distribution of x_0.
    let e = fails(
        &spec.replace(r#"mode = "sampled""#, r#"mode = "truth""#),
        &[],
    );
    assert!(
        e.contains("initial_estimate.mode") && e.contains("sampled"),
        "{e}"
    );
    // Too few runs for the covariance of the conditions.
    let e = fails(&spec, &["--runs", "3"]);
    assert!(e.contains("runs") && e.contains("at least 6"), "{e}");
    // Objectives and data of the other methods.
    let e = fails(&spec, &["--objective", "rmse"]);
    assert!(e.contains("consistency or mse"), "{e}");
    let e = fails(&spec, &["--measurements", "m.parquet"]);
    assert!(e.contains("--measurements belongs to the ml method"), "{e}");
    // An element that does not exist.
    let e = fails(&spec, &["--elements", "q[vx,vz]"]);
    assert!(
        e.contains("--elements[0]") && e.contains("unknown state `vz`"),
        "{e}"
    );
    // A system that is not linear.
    let planar = r#"
name = "p"
runs = 8
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
method = "truth"
elements = ["q[x,x]"]
"#;
    let e = fails(planar, &[]);
    assert!(
        e.contains("model.kind") && e.contains("truth method"),
        "{e}"
    );
}
