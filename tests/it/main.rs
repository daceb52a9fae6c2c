//! kfmc's integration tests, one binary: every file links the library and polars once, not
//! once per file. Modules are grouped by what they test; `common` holds the helpers and the
//! spec texts that several groups share.
//!
//! Run one group or file by its module path, e.g. `cargo test --release --test it
//! pipeline::shards::` or `cargo nextest run --release -E 'test(/^pipeline::shards::/)'`.
//!
//! A new test file goes into the folder of its group (`tests/it/<group>/<name>.rs`) and gets
//! one line in that group's block below; it reaches the helpers as `crate::common::…`.
//!
//! The tests run as threads of one process under `cargo test`: a test must not change
//! process-wide state (environment variables, the working directory, a panic hook that
//! swallows other tests' panics); give a child process its own with `Command::env` and
//! `Command::current_dir` instead.

mod common;

/// Specs: validation, the bad-spec catalogue, `describe`.
mod spec {
    mod all_problems;
    mod bad_specs;
    mod describe;
    mod linear_spec;
}

/// Fuzzing the spec text and everything else a user hands in.
mod fuzz {
    mod input_fuzz;
    mod spec_fuzz;
}

/// The study pipeline through the binary: commands, folders, writers, resume, shards,
/// faults, memory, figures.
mod pipeline {
    mod check_assertions;
    mod cli;
    mod disk_full;
    mod lanes;
    mod memory;
    mod ownership;
    mod per_step_runs;
    mod plot;
    mod reliability;
    mod reproducibility;
    mod resume;
    mod sequential_check;
    mod shards;
    mod writers;
}

/// Statistical facts and the tests of the tests (verdicts, power, draws, whiteness).
mod statistics {
    mod calibration;
    mod credibility;
    mod draws;
    mod power;
    #[allow(clippy::module_inception)]
    mod statistics;
    mod tune_ml;
    mod tune_truth;
    mod unjudgeable;
    mod whiteness_scale;
}

/// Cross-checks against independent implementations, golden files and algebraic identities.
mod cross_checks {
    mod angle_branch;
    mod filter_equivalence;
    mod filterpy_l1;
    mod filterpy_ukf;
    mod golden_seed;
    mod jacobian_structure;
    mod numerical_trouble;
    mod pole_placement;
}

/// The systems: the drone, linear systems from TOML, L1 studies, worlds, a user's own filter.
mod systems {
    mod attitude;
    mod drone;
    mod linear_generic;
    mod linear_studies;
    mod own_filter;
    mod world_bias;
    mod world_kinds;
}

/// The estimates exchange and the tables read by other tools.
mod exchange {
    mod column_types;
    mod compact;
    mod drone_export;
    #[allow(clippy::module_inception)]
    mod exchange;
    mod filter_model;
    mod interop;
    mod recorded;
    mod variants;
}

/// PX4 flight logs: the ULog reader and its fuzz, the one-log NIS verdict and its gate.
mod ulog {
    mod nis;
    mod reader;
}

/// The book and README: runnable blocks, specs, links, the tables reference.
mod docs {
    mod readme_snippets;
}
