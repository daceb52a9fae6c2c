//! `[consistency]`: α, the whiteness lags and burn-in, and the subsets of the first runs.

use crate::experiment::spec::Spec;
use crate::system::checker::Checker;
use crate::system::limits;
use crate::system::settings::ConsistencyPlan;

/// `[consistency]` as validated (also when the table is absent, for the steps' bands).
pub(super) struct Consistency {
    pub(super) alpha: f64,
    pub(super) whiteness_lags: usize,
    /// The consistency tests, when the spec has the table.
    pub(super) plan: Option<ConsistencyPlan>,
}

/// `[consistency]`: α, the whiteness lags and burn-in, and the subsets evaluated on the first
/// runs. `shortest`: the (steps, name) of the shortest scenario, when the system is known.
pub(super) fn consistency_table(
    c: &mut Checker,
    spec: &Spec,
    runs: u64,
    shortest: Option<(usize, String)>,
) -> Consistency {
    let cs = spec.consistency.as_deref();
    let alpha = cs.and_then(|c| c.alpha).unwrap_or(0.05);
    if !(alpha > 0.0 && alpha < 1.0) {
        c.err("consistency.alpha", format!("{alpha} is not in (0, 1)"));
    }
    let whiteness_lags = cs
        .and_then(|c| c.whiteness_lags)
        .unwrap_or(ConsistencyPlan::DEFAULT_WHITENESS_LAGS as u64);
    if whiteness_lags > limits::MAX_WHITENESS_LAGS {
        c.err(
            "consistency.whiteness_lags",
            format!(
                "{whiteness_lags} lags; at most {}",
                limits::MAX_WHITENESS_LAGS
            ),
        );
    }
    let whiteness_burn_in = cs.and_then(|c| c.whiteness_burn_in).unwrap_or(0);
    if whiteness_burn_in > 0 && whiteness_lags == 0 {
        c.err(
            "consistency.whiteness_burn_in",
            "drops steps from a whiteness test that whiteness_lags = 0 does not compute",
        );
    }
    // Without a burn-in, lags beyond the run are the lags' business, not this key's.
    if let Some((steps, name)) = shortest
        && whiteness_burn_in > 0
        && whiteness_burn_in.saturating_add(whiteness_lags) >= steps as u64
    {
        c.err(
            "consistency.whiteness_burn_in",
            format!(
                "{whiteness_burn_in} steps dropped and {whiteness_lags} lags leave no lag pair in scenario {name:?} ({steps} steps)"
            ),
        );
    }
    let mut subsets = Vec::new();
    for (i, sub) in cs.iter().flat_map(|c| c.subsets.iter()).enumerate() {
        let key = format!("consistency.subsets[{i}]");
        if sub.runs < 2 || sub.runs > runs {
            c.err(
                format!("{key}.runs"),
                format!("{} is not in 2..={runs} (the study's runs)", sub.runs),
            );
        }
        if !(sub.alpha > 0.0 && sub.alpha < 1.0) {
            c.err(
                format!("{key}.alpha"),
                format!("{} is not in (0, 1)", sub.alpha),
            );
        }
        if subsets.contains(&(sub.runs as usize, sub.alpha))
            || (sub.runs == runs && sub.alpha == alpha)
        {
            c.err(key, "duplicates another (runs, alpha) evaluation");
        }
        subsets.push((sub.runs as usize, sub.alpha));
    }
    Consistency {
        alpha,
        whiteness_lags: whiteness_lags as usize,
        plan: cs.map(|_| ConsistencyPlan {
            alpha,
            whiteness_lags: whiteness_lags as usize,
            whiteness_burn_in: whiteness_burn_in as usize,
            subsets,
        }),
    }
}
