//! The `rejection_rate` assertions, judged on `kfmc power`'s replications (power.parquet).

use std::path::Path;

use super::CaseResult;
use super::judge::settle;
use super::tables::{Cells, Table, fmt, fmt_g};
use crate::error::OutputError;
use crate::experiment::Plan;
use crate::experiment::plan::Assertion;

/// Evaluates the `rejection_rate` assertions of `plan` against `power.parquet` in `dir`
/// (written by `kfmc power`).
pub fn evaluate_power(plan: &Plan, dir: &Path) -> Result<Vec<CaseResult>, OutputError> {
    crate::output::folder::verify(dir)?;
    let t = Table::open(&dir.join("power.parquet"))?;
    let Cells {
        names,
        scenario: sc,
        filter: f,
    } = t.cells()?;
    let test = t.str("test")?;
    let (q, r, runs, alpha) = (
        t.f64("q_scale")?,
        t.f64("r_scale")?,
        t.i64("runs")?,
        t.f64("alpha")?,
    );
    let (reps, rejections) = (t.i64("replications")?, t.i64("rejections")?);
    let (rate, lo, hi) = (
        t.f64("rejection_rate")?,
        t.f64("rejection_ci_lo")?,
        t.f64("rejection_ci_hi")?,
    );
    let mut out = Vec::new();
    for a in &plan.assertions {
        let Assertion::RejectionRate {
            test: want,
            select,
            runs: want_runs,
            min,
            max,
            interval,
            ..
        } = a
        else {
            continue;
        };
        let before = out.len();
        for i in 0..names.len() {
            let keep = &test[i] == want
                && select.covers(&sc[i], &f[i], q[i], r[i])
                && want_runs.is_none_or(|n| runs[i] == Some(n as i64));
            if !keep {
                continue;
            }
            let name = format!(
                "rejection_rate[{} N={} α={} {}]",
                names[i],
                runs[i].unwrap_or(0),
                fmt_g(alpha[i]),
                test[i]
            );
            let (Some(p), Some(l), Some(h)) = (rate[i], lo[i], hi[i]) else {
                out.push(CaseResult::incomplete(
                    "rejection_rate",
                    name,
                    format!(
                        "the rejection rate of {} could not be computed ({} of {} replications judged)",
                        names[i],
                        rejections[i].map_or("null".into(), |r| r.to_string()),
                        reps[i].unwrap_or(0)
                    ),
                ));
                continue;
            };
            let (low, high) = if *interval { (l, h) } else { (p, p) };
            let pass = min.is_none_or(|m| low >= m) && max.is_none_or(|m| high <= m);
            let bounds = match (min, max) {
                (Some(a), Some(b)) => format!("in [{a}, {b}]"),
                (Some(a), None) => format!("≥ {a}"),
                (None, Some(b)) => format!("≤ {b}"),
                (None, None) => String::new(),
            };
            let what = if *interval {
                "its 95 % interval must lie"
            } else {
                "must be"
            };
            out.push(CaseResult::judged(
                "rejection_rate",
                name,
                pass,
                format!(
                    "rejected in {} of {} replications: rate {} [{}, {}] ({what} {bounds})",
                    rejections[i].unwrap_or(0),
                    reps[i].unwrap_or(0),
                    fmt(Some(p)),
                    fmt(Some(l)),
                    fmt(Some(h)),
                ),
            ));
        }
        settle(a, "rejection_rate", &mut out, before);
    }
    Ok(out)
}
