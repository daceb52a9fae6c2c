//! The coverage of `kfmc tune --method ml`'s and `--method truth`'s intervals, measured: the
//! tables of the tuning chapter.
//!
//! ```text
//! cargo run --release --example tune_coverage [-- REPLICATIONS [SPEC [ml|truth]]]
//! ```
//!
//! SPEC (default `experiments/tune_ml_cv.toml`) is simulated with REPLICATIONS (default 200)
//! independent master seeds 1, 2, …; each replication tunes the spec's `[tune] elements` by
//! the method (default `ml`: maximum likelihood; `truth`: the consistency conditions against
//! the simulated truth, with sandwich intervals) from its own runs, starting from the spec's
//! values, which are also the truth the runs are simulated with. Per element: the truth, the mean estimate, the bias
//! (mean − truth) ± its standard error, the bias of ln(estimate), the mean standard error
//! the tuning reported against the spread of the estimates, the share of 95 % intervals that
//! hold the truth with its Clopper–Pearson 95 % interval, and the mean of z² =
//! ((ln θ̂ − ln θ)/se)², which is 1 when the standard errors are right.

use std::path::PathBuf;

use kfmc::experiment::Overrides;
use kfmc::experiment::tune_spec::NoiseMatrix;
use kfmc::power::clopper_pearson;
use kfmc::runner::NullObserver;
use kfmc::tune::conditions::TruthObjective;
use kfmc::tune::estimate::Estimate;
use kfmc::tune::estimate::SearchSettings;
use kfmc::tune::ml::{MlOptions, prepare};
use kfmc::tune::truth::TruthOptions;

fn main() {
    let mut args = std::env::args().skip(1);
    let reps: u64 = args
        .next()
        .map(|a| a.parse().expect("REPLICATIONS: a whole number"))
        .unwrap_or(200);
    let spec = args
        .next()
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from("experiments/tune_ml_cv.toml"));
    let method = args.next().unwrap_or_else(|| "ml".into());
    assert!(
        method == "ml" || method == "truth",
        "METHOD: ml or truth, not {method}"
    );
    let base = kfmc::experiment::load(&spec).unwrap_or_else(|e| panic!("{e}"));
    let opts = MlOptions {
        elements: None,
        measurements: None,
        search: SearchSettings::default(),
        force: false,
        threads: 0,
    };
    let truth_opts = TruthOptions {
        elements: None,
        objective: TruthObjective::Consistency,
        search: SearchSettings::default(),
        force: false,
        threads: 0,
    };
    let mut names = Vec::new();
    let mut truth = Vec::new();
    let mut estimates: Vec<Vec<f64>> = Vec::new();
    let mut covered: Vec<u64> = Vec::new();
    let mut z2: Vec<f64> = Vec::new();
    let mut se_sum: Vec<f64> = Vec::new();
    let mut log_err: Vec<f64> = Vec::new();
    let mut unconverged = 0;
    let started = std::time::Instant::now();
    for rep in 0..reps {
        let mut plan = base.clone();
        plan.apply(&Overrides {
            runs: None,
            master_seed: Some(rep + 1),
            output: None,
            trace_runs: None,
        })
        .expect("overrides");
        let (elements, model, est): (_, _, Estimate) = if method == "ml" {
            let prepared = prepare(&plan, &opts, &NullObserver).unwrap_or_else(|e| panic!("{e}"));
            let est = prepared
                .search(&opts.search, opts.threads, &|_| {})
                .unwrap_or_else(|e| panic!("replication {rep}: {e}"));
            (prepared.elements, prepared.model, est)
        } else {
            let prepared = kfmc::tune::truth::prepare(&plan, &truth_opts, &NullObserver)
                .unwrap_or_else(|e| panic!("{e}"));
            let (est, _, _) = prepared
                .search(&truth_opts.search, truth_opts.threads, &|_| {})
                .unwrap_or_else(|e| panic!("replication {rep}: {e}"));
            (prepared.elements, prepared.model, est)
        };
        if names.is_empty() {
            names = elements.iter().map(|e| e.name.clone()).collect();
            truth = elements
                .iter()
                .map(|e| match e.matrix {
                    NoiseMatrix::Q => model.q[(e.row, e.col)],
                    NoiseMatrix::R => model.r[(e.row, e.col)],
                })
                .collect();
            let m = names.len();
            estimates = vec![Vec::new(); m];
            covered = vec![0; m];
            z2 = vec![0.0; m];
            se_sum = vec![0.0; m];
            log_err = vec![0.0; m];
        }
        unconverged += usize::from(!est.converged);
        for i in 0..names.len() {
            let (v, _, ci) = est.natural(i);
            estimates[i].push(v);
            let se = est.se_log[i].unwrap_or(f64::NAN);
            let e = est.theta[i] - truth[i].ln();
            z2[i] += (e / se).powi(2);
            se_sum[i] += se;
            log_err[i] += e;
            if let Some((lo, hi)) = ci {
                covered[i] += u64::from(lo <= truth[i] && truth[i] <= hi);
            }
        }
    }
    let n = reps as f64;
    println!(
        "{} replications of {} by {method} ({} runs each), {:.1} s; {unconverged} searches not converged",
        reps,
        spec.display(),
        base.runs,
        started.elapsed().as_secs_f64()
    );
    println!();
    println!(
        "| element | truth | mean estimate | bias ± SE | ln bias ± SE | mean se (ln) | sd of ln θ̂ | coverage of 95 % intervals [Clopper–Pearson] | mean z² |"
    );
    println!("|---|---|---|---|---|---|---|---|---|");
    for i in 0..names.len() {
        let v = &estimates[i];
        let mean = v.iter().sum::<f64>() / n;
        let sd = (v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0)).sqrt();
        let logs: Vec<f64> = v.iter().map(|x| x.ln()).collect();
        let lmean = logs.iter().sum::<f64>() / n;
        let lsd = (logs.iter().map(|x| (x - lmean).powi(2)).sum::<f64>() / (n - 1.0)).sqrt();
        let (lo, hi) = clopper_pearson(covered[i], reps);
        println!(
            "| {} | {} | {:.5} | {:+.5} ± {:.5} | {:+.4} ± {:.4} | {:.4} | {:.4} | {}/{} = {:.3} [{:.3}, {:.3}] | {:.3} |",
            names[i],
            truth[i],
            mean,
            mean - truth[i],
            sd / n.sqrt(),
            log_err[i] / n,
            lsd / n.sqrt(),
            se_sum[i] / n,
            lsd,
            covered[i],
            reps,
            covered[i] as f64 / n,
            lo,
            hi,
            z2[i] / n
        );
    }
}
