//! The top level's counts (runs, scenarios, filter variants, steps, traced runs) within the
//! limits.

use crate::experiment::spec::Spec;
use crate::system::SystemPlan;
use crate::system::checker::Checker;
use crate::system::limits;

/// The top level's counts within [`limits`]: runs, scenarios, filter variants, steps, and
/// `trace_runs` ≤ `runs`.
pub(super) fn check_sizes(
    c: &mut Checker,
    spec: &Spec,
    runs: u64,
    variants: usize,
    system: Option<&dyn SystemPlan>,
) {
    if runs == 0 {
        c.err("runs", "must be at least 1");
    } else if runs > limits::MAX_RUNS {
        c.err(
            "runs",
            format!("{runs} runs per cell; at most {}", limits::MAX_RUNS),
        );
    }
    if spec.scenarios.len() > limits::MAX_ENTRIES {
        c.err(
            "scenarios",
            format!(
                "{} scenarios; at most {}",
                spec.scenarios.len(),
                limits::MAX_ENTRIES
            ),
        );
    }
    if variants > limits::MAX_ENTRIES {
        c.err(
            "filters",
            format!(
                "{variants} filter variants (entries × q_scale × r_scale values); at most {}",
                limits::MAX_ENTRIES
            ),
        );
    }
    for (i, sc) in system.iter().flat_map(|s| s.scenarios().iter()).enumerate() {
        if sc.steps == 0 {
            // A system that does not check its lengths ([`Checker::scenario_steps`] does)
            // would otherwise run scenarios of no step, whose cases `check` then calls
            // incomplete instead of saying what is wrong.
            let own = format!("scenarios[{i}].duration_s");
            let (key, what) = match spec.scenarios.get(i).and_then(|t| t.get("duration_s")) {
                Some(d) => (own, format!("duration_s = {d} gives")),
                None => (format!("scenarios[{i}]"), "its length gives".to_string()),
            };
            c.err(
                key,
                format!(
                    "scenario `{}`: {what} no step (duration / Δt rounds to 0); a run needs at least one",
                    sc.name
                ),
            );
        } else if sc.steps as u64 > limits::MAX_STEPS {
            c.err(
                format!("scenarios[{i}]"),
                format!(
                    "{} steps (duration / Δt); at most {} per run",
                    sc.steps,
                    limits::MAX_STEPS
                ),
            );
        }
    }
    let trace_runs = spec.trace_runs.unwrap_or(0);
    if trace_runs > runs {
        c.err(
            "trace_runs",
            format!("{trace_runs} traced runs but only {runs} runs"),
        );
    }
}
