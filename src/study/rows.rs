//! The key columns of a cell's rows and the across-run quantile levels, shared by the fold
//! and the divergence tables.

use crate::experiment::FilterPlan;
use crate::output::Value;

/// The key values of a cell row: scenario, noise scale, filter label, q_scale, r_scale.
pub(super) fn cell_key<'a>(scenario: &'a str, noise: f64, f: &'a FilterPlan) -> [Value<'a>; 5] {
    let [q, r] = scale_keys(f);
    [
        Value::Str(scenario),
        Value::F64(Some(noise)),
        Value::Str(&f.label),
        q,
        r,
    ]
}

/// The `q_scale` and `r_scale` key values of a filter variant: null for an external filter
/// without declared variants, whose tuning is its own.
pub(super) fn scale_keys(f: &FilterPlan) -> [Value<'static>; 2] {
    let (q, r) = f.multipliers().unzip();
    [Value::F64(q), Value::F64(r)]
}

/// The across-run quantile levels of the summary and sensors tables.
pub(super) const LEVELS: [f64; 3] = [0.05, 0.50, 0.95];
