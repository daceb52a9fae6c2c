//! The regression gate over flights: this folder's `ulog_summary` rows against a stored one
//! (`--baseline`).
//!
//! * **The same flight replayed** (a log of the same name in both): per instance, source and
//!   axis, a regression is a verdict that got worse (pass → incomplete → fail) or a mean NIS
//!   that grew by more than the tolerance (`statistic > (1 + tolerance) · baseline`). A row of
//!   the baseline that this run no longer judges is incomplete.
//! * **Other flights**: per instance, source and axis over the whole folder, the per-log mean
//!   NIS of this folder's unmatched logs against the baseline's unmatched logs: a regression
//!   when the median grew by more than the tolerance *and* a one-sided Mann–Whitney test says
//!   this folder's values are larger (p ≤ α; normal approximation with ties). Fewer than 3
//!   logs on a side is incomplete.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use super::{NisError, NisOptions, SummaryRow, TEST_NIS_MEAN};
use crate::check::CaseResult;

/// One `nis_mean` row of a stored summary.
#[derive(Clone, Debug, PartialEq)]
pub struct BaseRow {
    /// The log's name.
    pub log: String,
    /// Its series' key: (instance or none for the primary, primary, source, axis).
    pub key: (Option<i64>, bool, String, Option<i64>),
    /// Mean NIS.
    pub statistic: Option<f64>,
    /// Its verdict.
    pub verdict: String,
}

/// A stored `ulog_summary.parquet`.
#[derive(Clone, Debug, PartialEq)]
pub struct Baseline {
    /// The file.
    pub path: PathBuf,
    /// Its `nis_mean` rows.
    pub rows: Vec<BaseRow>,
}

/// Reads a stored summary.
pub fn read_baseline(path: &Path) -> Result<Baseline, NisError> {
    let bad = |why: String| NisError::Baseline {
        path: path.to_path_buf(),
        why,
    };
    let df = crate::output::table::read(path)?;
    let col = |name: &str| df.column(name).map_err(|e| bad(e.to_string()));
    let strs = |name: &str| -> Result<Vec<String>, NisError> {
        Ok(col(name)?
            .str()
            .map_err(|e| bad(e.to_string()))?
            .iter()
            .map(|s| s.unwrap_or("").to_string())
            .collect())
    };
    let ints = |name: &str| -> Result<Vec<Option<i64>>, NisError> {
        Ok(col(name)?
            .i64()
            .map_err(|e| bad(e.to_string()))?
            .iter()
            .collect())
    };
    let (log, source, test, verdict) = (
        strs("log")?,
        strs("source")?,
        strs("test")?,
        strs("verdict")?,
    );
    let (instance, axis) = (ints("instance")?, ints("axis")?);
    let primary: Vec<bool> = col("primary")?
        .bool()
        .map_err(|e| bad(e.to_string()))?
        .iter()
        .map(|b| b.unwrap_or(false))
        .collect();
    let statistic: Vec<Option<f64>> = col("statistic")?
        .f64()
        .map_err(|e| bad(e.to_string()))?
        .iter()
        .collect();
    let rows = (0..df.height())
        .filter(|&i| test[i] == TEST_NIS_MEAN)
        .map(|i| BaseRow {
            log: log[i].clone(),
            key: (instance[i], primary[i], source[i].clone(), axis[i]),
            statistic: statistic[i],
            verdict: verdict[i].clone(),
        })
        .collect();
    Ok(Baseline {
        path: path.to_path_buf(),
        rows,
    })
}

fn rank(verdict: &str) -> u8 {
    match verdict {
        "pass" => 0,
        "fail" => 2,
        _ => 1,
    }
}

fn key_of(r: &SummaryRow) -> (Option<i64>, bool, String, Option<i64>) {
    (
        r.instance.map(i64::from),
        r.primary,
        r.source.clone(),
        r.axis.map(|a| a as i64),
    )
}

fn key_name(k: &(Option<i64>, bool, String, Option<i64>)) -> String {
    let inst =
        k.0.map_or("primary".to_string(), |i| format!("instance {i}"));
    let axis = k.3.map_or(String::new(), |a| format!("[{a}]"));
    format!("{inst} {}{axis}", k.2)
}

/// The one-sided Mann–Whitney p-value that `a` tends to be larger than `b` (normal
/// approximation with the tie correction).
pub fn mann_whitney_greater(a: &[f64], b: &[f64]) -> Option<f64> {
    let (n1, n2) = (a.len() as f64, b.len() as f64);
    if a.is_empty() || b.is_empty() {
        return None;
    }
    let mut all: Vec<(f64, bool)> = a
        .iter()
        .map(|v| (*v, true))
        .chain(b.iter().map(|v| (*v, false)))
        .collect();
    all.sort_by(|x, y| x.0.total_cmp(&y.0));
    let n = all.len();
    let (mut rank_a, mut ties) = (0.0, 0.0);
    let mut i = 0;
    while i < n {
        let mut j = i;
        while j + 1 < n && all[j + 1].0 == all[i].0 {
            j += 1;
        }
        let r = (i + j) as f64 / 2.0 + 1.0;
        let t = (j - i + 1) as f64;
        ties += t * t * t - t;
        rank_a += all[i..=j].iter().filter(|x| x.1).count() as f64 * r;
        i = j + 1;
    }
    let u = rank_a - n1 * (n1 + 1.0) / 2.0;
    let nn = n1 + n2;
    let var = n1 * n2 / 12.0 * ((nn + 1.0) - ties / (nn * (nn - 1.0)));
    if var.is_nan() || var <= 0.0 {
        return Some(0.5);
    }
    let z = (u - n1 * n2 / 2.0) / var.sqrt();
    Some(1.0 - normal_cdf(z))
}

/// Φ(z).
fn normal_cdf(z: f64) -> f64 {
    use statrs::distribution::{ContinuousCDF, Normal};
    Normal::new(0.0, 1.0).map_or(0.5, |n| n.cdf(z))
}

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        (v[n / 2 - 1] + v[n / 2]) / 2.0
    }
}

/// The regression cases of `rows` against `base`.
pub fn compare(rows: &[SummaryRow], base: &Baseline, opts: &NisOptions) -> Vec<CaseResult> {
    let tol = opts.tolerance;
    let mine: Vec<&SummaryRow> = rows.iter().filter(|r| r.test == TEST_NIS_MEAN).collect();
    let my_logs: std::collections::BTreeSet<&str> = mine.iter().map(|r| r.log.as_str()).collect();
    let base_logs: std::collections::BTreeSet<&str> =
        base.rows.iter().map(|r| r.log.as_str()).collect();
    let mut out = Vec::new();
    let fmt = |v: Option<f64>| v.map_or("—".into(), |v| format!("{v:.4}"));
    // The same flights.
    for b in base
        .rows
        .iter()
        .filter(|b| my_logs.contains(b.log.as_str()))
    {
        let name = format!("regression[{} {}]", b.log, key_name(&b.key));
        let now = mine.iter().find(|r| r.log == b.log && key_of(r) == b.key);
        let Some(r) = now else {
            out.push(CaseResult {
                kind: "regression".into(),
                name,
                pass: false,
                incomplete: true,
                detail: format!(
                    "incomplete: judged in the baseline ({}), not in this run",
                    b.verdict
                ),
            });
            continue;
        };
        let worse = rank(&r.verdict) > rank(&b.verdict);
        let grew = matches!((r.statistic, b.statistic), (Some(s), Some(t)) if s > (1.0 + tol) * t);
        out.push(CaseResult {
            kind: "regression".into(),
            name,
            pass: !worse && !grew,
            incomplete: false,
            detail: format!(
                "verdict {} (baseline {}), mean NIS {} (baseline {}, tolerance +{:.0} %){}",
                r.verdict,
                b.verdict,
                fmt(r.statistic),
                fmt(b.statistic),
                tol * 100.0,
                match (worse, grew) {
                    (true, true) => ": the verdict got worse and the mean grew",
                    (true, false) => ": the verdict got worse",
                    (false, true) => ": the mean grew beyond the tolerance",
                    _ => "",
                }
            ),
        });
    }
    // Other flights: the distributions of per-log means.
    type Key = (Option<i64>, bool, String, Option<i64>);
    let mut now: BTreeMap<Key, Vec<f64>> = BTreeMap::new();
    let mut then: BTreeMap<Key, Vec<f64>> = BTreeMap::new();
    for r in mine.iter().filter(|r| !base_logs.contains(r.log.as_str())) {
        if let Some(s) = r.statistic.filter(|s| s.is_finite()) {
            now.entry(key_of(r)).or_default().push(s);
        }
    }
    for b in base
        .rows
        .iter()
        .filter(|b| !my_logs.contains(b.log.as_str()))
    {
        if let Some(s) = b.statistic.filter(|s| s.is_finite()) {
            then.entry(b.key.clone()).or_default().push(s);
        }
    }
    if now.is_empty() {
        return out;
    }
    let keys: std::collections::BTreeSet<&Key> = now.keys().chain(then.keys()).collect();
    for k in keys {
        let name = format!("regression[folder {}]", key_name(k));
        let (a, b) = (
            now.get(k).cloned().unwrap_or_default(),
            then.get(k).cloned().unwrap_or_default(),
        );
        if a.len() < 3 || b.len() < 3 {
            out.push(CaseResult {
                kind: "regression".into(),
                name,
                pass: false,
                incomplete: true,
                detail: format!(
                    "incomplete: {} logs here and {} in the baseline have a mean NIS; comparing distributions needs 3 on each side",
                    a.len(),
                    b.len()
                ),
            });
            continue;
        }
        let p = mann_whitney_greater(&a, &b).unwrap_or(1.0);
        let (ma, mb) = (median(&mut a.clone()), median(&mut b.clone()));
        let grew = ma > (1.0 + tol) * mb && p <= opts.alpha;
        out.push(CaseResult {
            kind: "regression".into(),
            name,
            pass: !grew,
            incomplete: false,
            detail: format!(
                "median mean NIS {ma:.4} over {} logs (baseline {mb:.4} over {}), tolerance +{:.0} %; Mann–Whitney p = {p:.4} (larger here; fails at p ≤ {})",
                a.len(),
                b.len(),
                tol * 100.0,
                opts.alpha
            ),
        });
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mann_whitney_matches_a_hand_count() {
        // a = {4, 5, 6}, b = {1, 2, 3}: U = 9 = n1·n2, the most extreme; z = (9 − 4.5)/√5.25.
        let p = mann_whitney_greater(&[4.0, 5.0, 6.0], &[1.0, 2.0, 3.0]).unwrap();
        let z: f64 = 4.5 / 5.25f64.sqrt();
        let want = 1.0 - normal_cdf(z);
        assert!((p - want).abs() < 1e-12, "{p} {want}");
        let p = mann_whitney_greater(&[1.0, 2.0, 3.0], &[4.0, 5.0, 6.0]).unwrap();
        assert!((p - (1.0 - want)).abs() < 1e-12);
    }
}
