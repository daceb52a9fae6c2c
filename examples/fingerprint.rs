//! A fingerprint of what the step loop computes, to show that a speed change left every
//! output bit where it was: for each spec given, the first runs of every (scenario, noise
//! scale) cell are executed through the same `Trial::run` the study calls, and the full debug
//! form of each unit's result (per-run record, every per-step value, consistency sums, traces)
//! is hashed. Rust prints an `f64` as the shortest text that reads back to the same bits, so
//! two builds print the same hash exactly when their results are bit-identical.
//!
//! ```text
//! cargo run --release --example fingerprint -- experiments/*.toml        # 3 runs per cell
//! cargo run --release --example fingerprint -- --runs 10 experiments/planar_seed_study.toml
//! ```
//!
//! Specs whose system needs files beside the spec (external estimates) are skipped with a note
//! when they do not load.

use std::hash::{DefaultHasher, Hasher};
use std::path::PathBuf;

use kfmc::experiment;
use kfmc::step_loop::Unit;

fn main() {
    let mut runs = 3usize;
    let mut specs: Vec<PathBuf> = Vec::new();
    let mut args = std::env::args().skip(1);
    while let Some(a) = args.next() {
        match a.as_str() {
            "--runs" => runs = args.next().and_then(|v| v.parse().ok()).expect("--runs N"),
            path => specs.push(PathBuf::from(path)),
        }
    }
    let mut all = DefaultHasher::new();
    for path in &specs {
        let plan = match experiment::load(path) {
            Ok(p) => p,
            Err(e) => {
                println!(
                    "{}: skipped ({})",
                    path.display(),
                    e.to_string().lines().next().unwrap_or("")
                );
                continue;
            }
        };
        let trial = plan.trial();
        let mut h = DefaultHasher::new();
        let mut units = 0;
        for scenario in 0..plan.scenarios.len() {
            for scale in 0..plan.noise_scales.len() {
                for run in 0..runs.min(plan.runs) {
                    let r = trial.run(&Unit {
                        scenario,
                        scale,
                        run,
                    });
                    h.write(format!("{r:?}").as_bytes());
                    units += 1;
                }
            }
        }
        let v = h.finish();
        all.write_u64(v);
        println!("{}: {units} units, {v:016x}", path.display());
    }
    println!("all: {:016x}", all.finish());
}
