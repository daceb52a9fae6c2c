//! `no_worse_than`'s paired comparison: each run's RMSE of two filters, and the one-sided
//! paired t-test on their differences.

use std::collections::HashMap;
use std::path::Path;

use super::tables::{CellKey, Table, fmt};
use crate::error::OutputError;

/// One cell's runs: per state, each run's value (`None` where the run has none), and per
/// run whether it is left out of the statistics (a numerical failure, a missing run, or a
/// run without a row, which `runs_problem` has judged already).
#[derive(Clone, Debug)]
pub(super) struct StateRuns {
    pub(super) values: Vec<Vec<Option<f64>>>,
    pub(super) left_out: Vec<bool>,
}

/// The (filter, reference) RMSE pairs of state `s` over the runs: runs left out (failed
/// within the tolerance, or missing) are no pair; any other run without a finite RMSE for
/// both is data the paired test cannot judge (`Err`, naming the first), never a pair
/// dropped without a word. `names`: the two cells, for the message.
pub(super) fn rmse_pairs(
    mine: &StateRuns,
    theirs: &StateRuns,
    s: usize,
    state: &str,
    names: (&str, &str),
) -> Result<Vec<(f64, f64)>, String> {
    let mut pairs = Vec::new();
    for (run, ((a, b), (la, lb))) in mine.values[s]
        .iter()
        .zip(&theirs.values[s])
        .zip(mine.left_out.iter().zip(&theirs.left_out))
        .enumerate()
    {
        if *la || *lb {
            continue;
        }
        match (a, b) {
            (Some(a), Some(b)) if a.is_finite() && b.is_finite() => pairs.push((*a, *b)),
            _ => {
                return Err(format!(
                    "run {run} is not a failure, yet its rmse_{state} is {} for {} and {} for {}: the paired test cannot use it",
                    fmt(*a),
                    names.0,
                    fmt(*b),
                    names.1
                ));
            }
        }
    }
    Ok(pairs)
}

/// Per cell in `wanted`: per state, each run's RMSE (by run index below `runs`; `None` for a
/// run without one, e.g. a numerical failure), and which runs are left out.
pub(super) fn run_rmse(
    path: &Path,
    wanted: &[CellKey],
    states: &[String],
    runs: usize,
) -> Result<HashMap<CellKey, StateRuns>, OutputError> {
    let mut out: HashMap<CellKey, StateRuns> = wanted
        .iter()
        .map(|k| {
            let runs = StateRuns {
                values: vec![vec![None; runs]; states.len()],
                left_out: vec![true; runs],
            };
            (k.clone(), runs)
        })
        .collect();
    if out.is_empty() {
        return Ok(out);
    }
    crate::output::table::for_each_row_group(path, |df| {
        let t = Table::of(df, path);
        let keys = t.keys()?;
        let (run, status) = (t.i64("run")?, t.str("status")?);
        let columns = states
            .iter()
            .map(|s| t.f64(&format!("rmse_{s}")))
            .collect::<Result<Vec<_>, _>>()?;
        for (i, key) in keys.iter().enumerate() {
            let Some(cell) = out.get_mut(key) else {
                continue;
            };
            let Some(r) = run[i]
                .and_then(|r| usize::try_from(r).ok())
                .filter(|&r| r < runs)
            else {
                continue;
            };
            cell.left_out[r] = matches!(status[i].as_str(), "numerical_failure" | "missing");
            for (s, col) in columns.iter().enumerate() {
                cell.values[s][r] = col[i];
            }
        }
        Ok(())
    })?;
    Ok(out)
}

/// A paired one-sided t-test over runs of d_i = rmse_i − (1 + margin)·rmse_reference_i.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PairedExcess {
    /// Runs paired.
    pub runs: usize,
    /// The filter's mean RMSE over them.
    pub mean: f64,
    /// The reference's mean RMSE over them.
    pub reference_mean: f64,
    /// t = d̄ / (s_d / √n).
    pub t: f64,
    /// P(T ≥ t) with n − 1 degrees of freedom: small when the filter is worse than
    /// (1 + margin) × the reference.
    pub p_value: f64,
}

/// Tests whether the filter's mean RMSE exceeds (1 + `margin`) × the reference's, from
/// (filter, reference) RMSE pairs of the same runs; `None` with fewer than 2 pairs. Pairing
/// removes the runs' common difficulty (the same truth and measurements), so a few runs
/// separate filters whose RMSEs differ by much less than their spread over runs. With no
/// spread in the differences the p-value is 0 or 1 by the sign of their mean.
pub fn paired_excess_test(pairs: &[(f64, f64)], margin: f64) -> Option<PairedExcess> {
    use statrs::distribution::{ContinuousCDF, StudentsT};
    let n = pairs.len();
    if n < 2 {
        return None;
    }
    let nf = n as f64;
    let d: Vec<f64> = pairs.iter().map(|(a, b)| a - (1.0 + margin) * b).collect();
    let mean_d = d.iter().sum::<f64>() / nf;
    let var = d.iter().map(|x| (x - mean_d).powi(2)).sum::<f64>() / (nf - 1.0);
    let se = (var / nf).sqrt();
    let (t, p_value) = if se > 0.0 {
        let t = mean_d / se;
        let dist = StudentsT::new(0.0, 1.0, nf - 1.0).expect("n ≥ 2 gives a valid t");
        (t, dist.sf(t))
    } else if mean_d > 0.0 {
        (f64::INFINITY, 0.0)
    } else {
        (f64::NEG_INFINITY, 1.0)
    };
    Some(PairedExcess {
        runs: n,
        mean: pairs.iter().map(|p| p.0).sum::<f64>() / nf,
        reference_mean: pairs.iter().map(|p| p.1).sum::<f64>() / nf,
        t,
        p_value,
    })
}
