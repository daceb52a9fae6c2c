//! Measures the false-alarm rate and the power of kfmc's consistency verdict.
//!
//! ```text
//! cargo run --release --example calibration [-- SEEDS STEPS [KIND]]
//! ```
//!
//! For each of SEEDS independent master seeds (default 200), the planar filter of kind KIND
//! (default `ekf`; `ukf` and `ckf` test the sigma-point filters' statistical linearisation A_k,
//! which the calibrated NEES test uses) runs N = 200
//! Monte Carlo runs of the `basic` scenario (STEPS steps, default 300) with matched noise and
//! a sampled initial error: a correctly tuned filter. The filter's Q is also mistuned by
//! q_scale ∈ {0.5, 0.8, 1.25, 2, 10, 2500}. The verdict is evaluated on the first N = 50, 100
//! and 200 runs. The rejection rate at q_scale = 1 is the false-alarm rate (stated: ≤ α,
//! ≈ α for nearly independent NEES and NIS tests); at the other scales it is the power.

use kfmc::experiment;
use kfmc::metrics::RunConsistency;
use kfmc::metrics::consistency::{VERDICT, cell_tests};
use kfmc::step_loop::Unit;
use rayon::prelude::*;
use std::path::Path;

const Q_SCALES: [f64; 7] = [1.0, 0.5, 0.8, 1.25, 2.0, 10.0, 2500.0];
const NS: [usize; 3] = [50, 100, 200];

fn spec(seed: u64, steps: usize, kind: &str) -> String {
    format!(
        r#"
master_seed = {seed}
runs = 200
[model]
kind = "planar_quadrotor"
[[scenarios]]
name = "basic"
duration_s = {duration}
[[filters]]
label = "{kind}"
kind = "{kind}"
q_scale = {q:?}
[noise]
filter_noise = "matched"
[initial_estimate]
mode = "sampled"
p0_std = 0.01
[consistency]
alpha = 0.05
whiteness_lags = 5
"#,
        duration = steps as f64 * 0.01,
        q = Q_SCALES.to_vec()
    )
}

fn main() {
    let args: Vec<usize> = std::env::args()
        .skip(1)
        .filter_map(|a| a.parse().ok())
        .collect();
    let seeds = args.first().copied().unwrap_or(200);
    let steps = args.get(1).copied().unwrap_or(300);
    let kind = std::env::args()
        .skip(1)
        .find(|a| a.parse::<usize>().is_err())
        .unwrap_or_else(|| "ekf".to_string());
    let alpha = 0.05;
    let started = std::time::Instant::now();
    // rejections[q][n] over seeds, and the NEES/NIS tests' own rejections at q = 1.
    let per_seed: Vec<(Vec<Vec<bool>>, [bool; 2])> = (1..=seeds as u64)
        .into_par_iter()
        .map(|seed| {
            let plan = experiment::parse(&spec(seed, steps, &kind), Path::new("calibration.toml"))
                .expect("valid spec");
            let trial = plan.trial();
            let runs: Vec<_> = (0..plan.runs)
                .map(|run| {
                    trial.run(&Unit {
                        scenario: 0,
                        scale: 0,
                        run,
                    })
                })
                .collect();
            let states = trial.layout().quantity_names();
            let mut rej = vec![vec![false; NS.len()]; plan.filters.len()];
            let mut parts = [false; 2];
            for (fi, f) in plan.filters.iter().enumerate() {
                let q = Q_SCALES
                    .iter()
                    .position(|q| *q == f.q_scale)
                    .expect("scale");
                for (ni, &n) in NS.iter().enumerate() {
                    let cons: Vec<RunConsistency> = runs[..n]
                        .iter()
                        .filter_map(|r| r.filters[fi].consistency.clone())
                        .collect();
                    let tests = cell_tests(&cons, states.len(), &states, alpha, (None, None));
                    let verdict = tests.iter().find(|t| t.test == VERDICT).expect("verdict");
                    rej[q][ni] = !verdict.pass;
                    if q == 0 && n == 200 {
                        for (k, name) in
                            ["nees_time_average", "nis_time_average"].iter().enumerate()
                        {
                            let t = tests.iter().find(|t| t.test == *name).expect("test");
                            parts[k] = t.p_value.unwrap_or(0.0) <= alpha / 2.0;
                        }
                    }
                }
            }
            (rej, parts)
        })
        .collect();

    let rate = |q: usize, ni: usize| {
        per_seed.iter().filter(|(r, _)| r[q][ni]).count() as f64 / seeds as f64
    };
    let tol = 3.0 * (alpha * (1.0 - alpha) / seeds as f64).sqrt();
    println!(
        "Verdict rejection rate over {seeds} master seeds, planar {kind}, {steps} steps, α = {alpha}"
    );
    println!("(q_scale = 1 is the false-alarm rate; binomial 3σ tolerance around α: ±{tol:.3})\n");
    print!("{:>10}", "q_scale");
    for n in NS {
        print!("  {:>8}", format!("N={n}"));
    }
    println!();
    for (q, qs) in Q_SCALES.iter().enumerate() {
        print!("{qs:>10}");
        for ni in 0..NS.len() {
            print!("  {:>8.3}", rate(q, ni));
        }
        println!();
    }
    let nees = per_seed.iter().filter(|(_, p)| p[0]).count() as f64 / seeds as f64;
    let nis = per_seed.iter().filter(|(_, p)| p[1]).count() as f64 / seeds as f64;
    println!(
        "\nAt q_scale = 1, N = 200: NEES test alone rejects {nees:.3}, NIS test alone {nis:.3} (each at α/2 = {}).",
        alpha / 2.0
    );
    println!("({:.0} s)", started.elapsed().as_secs_f64());
}
