//! Documented caps on a plan. Beyond them a spec is refused before anything runs (the
//! resource caps can be lifted with `--allow-large`; the count caps cannot).

/// Runs per cell.
pub const MAX_RUNS: u64 = 1_000_000_000;
/// Transitions K of one scenario.
pub const MAX_STEPS: u64 = 10_000_000;
/// Truth-noise multipliers, and Q/R scales of one filter entry.
pub const MAX_SCALES: usize = 100_000;
/// Scenarios, and filter variants.
pub const MAX_ENTRIES: usize = 10_000;
/// Spec file size in bytes.
pub const MAX_SPEC_BYTES: u64 = 1 << 20;
/// Tables and arrays nested in one another in a spec given as a Python dict: a spec needs a
/// handful, and a dict that contains itself is refused here instead of recursing until the
/// stack overflows.
pub const MAX_SPEC_DEPTH: usize = 64;
/// Characters of a scenario name or a filter label (they are parts of figure file names,
/// which most file systems cap at 255 bytes).
pub const MAX_NAME_CHARS: usize = 64;
/// Samples (K + 1) of all scenarios of a spec together: systems expand the scenarios
/// (their inputs per step) while validating, before the resource estimate can refuse.
pub const MAX_TOTAL_SAMPLES: u64 = 20_000_000;
/// Measurement rows K·n_z of one batch least-squares fit: its covariance is a dense
/// matrix of that many rows squared, factorised while validating.
pub const MAX_BATCH_LS_ROWS: usize = 5_000;
/// Innovation-whiteness lags.
pub const MAX_WHITENESS_LAGS: u64 = 50;
/// Estimated peak memory, bytes (lifted by `--allow-large`).
pub const MAX_MEMORY_BYTES: u128 = 8 << 30;
/// Estimated disk use of the tables and scratch files, bytes (lifted by `--allow-large`).
pub const MAX_DISK_BYTES: u128 = 100 << 30;
/// Simulated filter steps in total (lifted by `--allow-large`).
pub const MAX_FILTER_STEPS: u128 = 100_000_000_000_000;
// The looks of a sequential gate are bounded by `crate::sequential::MAX_LOOKS`, kept beside
// the design it bounds.
