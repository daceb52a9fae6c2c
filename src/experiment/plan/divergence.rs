//! `[divergence]`: the RMSE thresholds and what a run that never crosses records.

use super::POSITIVE;
use crate::experiment::spec::{OneOrMany, Spec};
use crate::system::checker::{Checker, positive};

/// `divergence.never_crossed`: whether a run that never crosses records the largest scale.
pub(super) fn never_crossed(c: &mut Checker, spec: &Spec) -> bool {
    c.choice(
        "divergence.never_crossed",
        spec.divergence
            .as_deref()
            .and_then(|d| d.never_crossed.as_deref()),
        "null",
        &["null", "largest_scale"],
    ) == "largest_scale"
}

/// `divergence.rmse_thresholds`, one per evaluated quantity (`nq` of them).
pub(super) fn rmse_thresholds(
    c: &mut Checker,
    spec: &Spec,
    configured: bool,
    nq: usize,
) -> Option<Vec<f64>> {
    let t = spec.divergence.as_deref()?.rmse_thresholds.as_ref()?;
    // Without a configured system the dimension is unknown; the values can still be
    // checked, so a second run of validate does not bring up a new error.
    let n = match (configured, t) {
        (false, OneOrMany::Many(v)) => v.len(),
        (false, _) => 1,
        _ => nq,
    };
    Some(c.vector(
        "divergence.rmse_thresholds",
        Some(t),
        n,
        &vec![f64::INFINITY; n],
        positive,
        POSITIVE,
    ))
}
