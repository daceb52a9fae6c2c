//! Measures the false-alarm rate and the power of `kfmc ulog nis`'s one-log verdict on
//! AR(1) innovations of known correlation (the table of the book's chapter "Real logs and
//! your own runs").
//!
//! ```text
//! cargo run --release --example ulog_calibration [-- REPLICATIONS]
//! ```
//!
//! For ρ ∈ {0, 0.5, 0.9, 0.99} and series of 1,000, 3,000, 10,000 and 30,000 samples, each of
//! REPLICATIONS (default 1,000) series is judged by the code that judges a log's axis
//! (`kfmc::ulog::calibration::cell`) with S matched (a rejection is a false alarm), halved
//! and doubled, at α = 0.05. Cells run in parallel; the seeds are fixed, so the table is the
//! same on every machine.

use rayon::prelude::*;

fn main() {
    let reps: u64 = std::env::args()
        .nth(1)
        .and_then(|a| a.parse().ok())
        .unwrap_or(1000);
    let alpha = 0.05;
    let grid: Vec<(f64, usize)> = [0.0, 0.5, 0.9, 0.99]
        .iter()
        .flat_map(|&r| [1_000, 3_000, 10_000, 30_000].map(|n| (r, n)))
        .collect();
    let started = std::time::Instant::now();
    let cells: Vec<_> = grid
        .par_iter()
        .map(|&(rho, n)| kfmc::ulog::calibration::cell(rho, n, reps, 20_261_207, alpha))
        .collect();
    print!("{}", kfmc::ulog::calibration::render(&cells, alpha));
    eprintln!(
        "{reps} replications per cell in {:.1} s",
        started.elapsed().as_secs_f64()
    );
}
