//! `[noise]`: the sweep of truth-noise multipliers, the filters' noise mode, the draws.

use super::filters::scale_list;
use crate::experiment::spec::Spec;
use crate::system::checker::{Checker, non_negative};
use crate::system::settings::{Draws, FilterNoiseMode};

/// `[noise]` as validated.
pub(super) struct Noise {
    pub(super) scales: Vec<f64>,
    pub(super) filter_noise: FilterNoiseMode,
    pub(super) draws: Draws,
}

/// `[noise]`: the sweep of truth-noise multipliers, the filters' noise mode, the draws.
pub(super) fn noise_table(c: &mut Checker, spec: &Spec) -> Noise {
    let noise = spec.noise.as_deref();
    let scales = scale_list(
        c,
        "noise.scales",
        noise.and_then(|n| n.scales.as_ref()),
        1.0,
        non_negative,
        "a non-negative number",
    );
    let filter_noise = c.choice(
        "noise.filter_noise",
        noise.and_then(|n| n.filter_noise.as_deref()),
        "nominal",
        &["nominal", "matched"],
    );
    let draws = c.choice(
        "noise.draws",
        noise.and_then(|n| n.draws.as_deref()),
        "common",
        &["common", "fresh"],
    );
    Noise {
        scales,
        filter_noise: if filter_noise == "matched" {
            FilterNoiseMode::Matched
        } else {
            FilterNoiseMode::Nominal
        },
        draws: if draws == "fresh" {
            Draws::Fresh
        } else {
            Draws::Common
        },
    }
}
