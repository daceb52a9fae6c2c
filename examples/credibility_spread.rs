//! How much one step's NCI and inclination of a perfectly credible filter spread, per state
//! dimension n and run count M: the table of the book's credibility chapter.
//!
//! ```text
//! cargo run --release --example credibility_spread [-- REPLICATIONS]
//! ```
//!
//! For n ∈ {2, 3, 6, 9} and M ∈ {5, 20, 200, 1000}, REPLICATIONS (default 20,000) independent
//! steps of M errors e ~ N(0, I_n) with P = I (`kfmc::metrics::credibility::simulate_spread`,
//! seed 2024): the mean and standard deviation of the step's NCI and inclination, the
//! large-M limits of the two standard deviations
//! (`asymptotic_nci_sd`, `asymptotic_inclination_sd`), and the Monte Carlo standard error of
//! the reference kfmc writes beside every NCI (`nci_credible_reference`, from
//! `reference_replications(M)` replications), as a percentage of the NCI and in dB of the
//! inclination.

use kfmc::metrics::credibility::{
    asymptotic_inclination_sd, asymptotic_nci_sd, reference_replications, simulate_spread,
};

/// The seed of every cell of the table.
const SEED: u64 = 2024;

fn main() {
    let replications: usize = std::env::args()
        .nth(1)
        .map(|a| a.parse().expect("REPLICATIONS: a whole number"))
        .unwrap_or(20_000);
    println!(
        "| n | M | NCI mean | NCI sd | NCI sd, large-M limit | inclination mean | inclination sd | inclination sd, large-M limit | reference SE, % of NCI | reference SE, inclination (dB) |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|");
    for n in [2usize, 3, 6, 9] {
        for m in [5usize, 20, 200, 1000] {
            let Some(s) = simulate_spread(m, n, replications, SEED) else {
                println!("| {n} | {m} | — (M < n) | | | | | | | |");
                continue;
            };
            let reference_reps = (reference_replications(m) as f64).sqrt();
            println!(
                "| {n} | {m} | {:.3} | {:.4} | {:.4} | {:.3} | {:.4} | {:.4} | {:.2} | {:.4} |",
                s.nci_mean,
                s.nci_sd,
                asymptotic_nci_sd(m, n),
                s.inclination_mean,
                s.inclination_sd,
                asymptotic_inclination_sd(m, n),
                100.0 * s.nci_sd / reference_reps / s.nci_mean,
                s.inclination_sd / reference_reps,
            );
        }
    }
}
