//! The study's tables as `kfmc check` reads them: each row's cell, the cells the spec
//! declares, and per cell the runs present and failed.

use std::collections::HashMap;
use std::path::Path;

use polars::prelude::*;

use crate::error::OutputError;
use crate::experiment::Plan;
use crate::experiment::plan::FilterPlan;
use crate::output::table::read;

/// Per row: the cell's display name, its scenario and its filter label.
pub(super) struct Cells {
    pub(super) names: Vec<String>,
    pub(super) scenario: Vec<String>,
    pub(super) filter: Vec<String>,
}

pub(super) struct Table {
    df: DataFrame,
    path: std::path::PathBuf,
}

impl Table {
    pub(super) fn open(path: &Path) -> Result<Self, OutputError> {
        Ok(Table {
            df: read(path)?,
            path: path.to_path_buf(),
        })
    }
    pub(super) fn of(df: DataFrame, path: &Path) -> Self {
        Table {
            df,
            path: path.to_path_buf(),
        }
    }
    fn err(&self, e: PolarsError) -> OutputError {
        OutputError::Polars {
            action: "unexpected columns in",
            path: self.path.clone(),
            source: e,
        }
    }
    pub(super) fn str(&self, c: &str) -> Result<Vec<String>, OutputError> {
        let col = self.df.column(c).map_err(|e| self.err(e))?;
        Ok(col
            .str()
            .map_err(|e| self.err(e))?
            .iter()
            .map(|s| s.unwrap_or("").to_string())
            .collect())
    }
    pub(super) fn f64(&self, c: &str) -> Result<Vec<Option<f64>>, OutputError> {
        let col = self.df.column(c).map_err(|e| self.err(e))?;
        Ok(col.f64().map_err(|e| self.err(e))?.iter().collect())
    }
    pub(super) fn i64(&self, c: &str) -> Result<Vec<Option<i64>>, OutputError> {
        let col = self.df.column(c).map_err(|e| self.err(e))?;
        Ok(col.i64().map_err(|e| self.err(e))?.iter().collect())
    }
    pub(super) fn bool(&self, c: &str) -> Result<Vec<Option<bool>>, OutputError> {
        let col = self.df.column(c).map_err(|e| self.err(e))?;
        Ok(col.bool().map_err(|e| self.err(e))?.iter().collect())
    }
    /// Each row's cell key.
    pub(super) fn keys(&self) -> Result<Vec<CellKey>, OutputError> {
        let sc = self.str("scenario")?;
        let f = self.str("filter")?;
        let noise = self.f64("noise_scale")?;
        let q = self.f64("q_scale")?;
        let r = self.f64("r_scale")?;
        Ok((0..sc.len())
            .map(|i| CellKey {
                scenario: sc[i].clone(),
                noise: noise[i].map(f64::to_bits),
                filter: f[i].clone(),
                q: q[i].map(f64::to_bits),
                r: r[i].map(f64::to_bits),
            })
            .collect())
    }
    /// Cell names per row and the (scenario, filter) columns for matching.
    pub(super) fn cells(&self) -> Result<Cells, OutputError> {
        let sc = self.str("scenario")?;
        let f = self.str("filter")?;
        let noise = self.f64("noise_scale")?;
        let q = self.f64("q_scale")?;
        let r = self.f64("r_scale")?;
        let names = (0..sc.len())
            .map(|i| cell_name(&sc[i], noise[i], &f[i], q[i].zip(r[i])))
            .collect();
        Ok(Cells {
            names,
            scenario: sc,
            filter: f,
        })
    }
}

/// A cell's display name: an external filter without declared variants has no multipliers
/// (null `q_scale`/`r_scale`), so it is named by its label alone.
pub(super) fn cell_name(
    scenario: &str,
    noise: Option<f64>,
    filter: &str,
    qr: Option<(f64, f64)>,
) -> String {
    match qr {
        Some((q, r)) => format!("{scenario} noise={} {filter} q={q} r={r}", fmt_g(noise)),
        None => format!("{scenario} noise={} {filter}", fmt_g(noise)),
    }
}

/// The key columns of a cell row, floats by their bits (as the tables hold them).
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub(super) struct CellKey {
    pub(super) scenario: String,
    pub(super) noise: Option<u64>,
    pub(super) filter: String,
    pub(super) q: Option<u64>,
    pub(super) r: Option<u64>,
}

/// One cell the spec declares, as `check` expects to find it in the tables.
pub(super) struct PlannedCell<'a> {
    pub(super) key: CellKey,
    pub(super) name: String,
    pub(super) scenario: &'a str,
    pub(super) filter: &'a FilterPlan,
}

/// The plan's cells (scenario × noise scale × filter variant), in table order.
pub(super) fn planned_cells(plan: &Plan) -> Vec<PlannedCell<'_>> {
    let mut out = Vec::new();
    for s in &plan.scenarios {
        for &noise in &plan.noise_scales {
            for f in &plan.filters {
                let qr = f.multipliers();
                out.push(PlannedCell {
                    key: CellKey {
                        scenario: s.name.clone(),
                        noise: Some(noise.to_bits()),
                        filter: f.label.clone(),
                        q: qr.map(|(q, _)| q.to_bits()),
                        r: qr.map(|(_, r)| r.to_bits()),
                    },
                    name: cell_name(&s.name, Some(noise), &f.label, qr),
                    scenario: &s.name,
                    filter: f,
                });
            }
        }
    }
    out
}

/// Per cell of runs.parquet: which runs below each evaluation's bound have a row, and which
/// of them failed numerically.
#[derive(Clone, Debug, Default)]
pub(super) struct RunCounts {
    /// Per bound: rows with `run` below it.
    pub(super) present: Vec<u64>,
    /// Per bound: of those, runs with status `numerical_failure`.
    pub(super) failed: Vec<u64>,
    /// The failed run of lowest index, and why it failed.
    pub(super) first_failure: Option<(i64, String)>,
    /// The run of lowest index whose row says it is missing.
    pub(super) first_missing: Option<i64>,
}

/// Counts the runs of every cell of `runs.parquet` below each of `bounds`, one row group at
/// a time (the table holds a row per run).
pub(super) fn count_runs(
    path: &Path,
    bounds: &[usize],
) -> Result<HashMap<CellKey, RunCounts>, OutputError> {
    let mut out: HashMap<CellKey, RunCounts> = HashMap::new();
    crate::output::table::for_each_row_group(path, |df| {
        let t = Table::of(df, path);
        let keys = t.keys()?;
        let (run, status, detail) = (t.i64("run")?, t.str("status")?, t.str("status_detail")?);
        for (i, key) in keys.into_iter().enumerate() {
            let c = out.entry(key).or_insert_with(|| RunCounts {
                present: vec![0; bounds.len()],
                failed: vec![0; bounds.len()],
                first_failure: None,
                first_missing: None,
            });
            let Some(run) = run[i].filter(|r| *r >= 0) else {
                continue;
            };
            // A run whose status says it is missing (an outside filter's estimates left it
            // out) has a row but no data: it is no more present than a run without a row.
            if status[i] == "missing" {
                if c.first_missing.is_none_or(|r| run < r) {
                    c.first_missing = Some(run);
                }
                continue;
            }
            let failed = status[i] == "numerical_failure";
            for (b, &bound) in bounds.iter().enumerate() {
                if (run as u64) < bound as u64 {
                    c.present[b] += 1;
                    c.failed[b] += u64::from(failed);
                }
            }
            if failed && c.first_failure.as_ref().is_none_or(|(r, _)| run < *r) {
                c.first_failure = Some((run, detail[i].clone()));
            }
        }
        Ok(())
    })?;
    Ok(out)
}

/// Why a case of `cell` on its first `runs` runs cannot be judged on the runs the spec
/// declares (`bound` indexes the evaluation's counts; the study ran `ran` runs per cell), or
/// `None` when it can.
pub(super) fn runs_problem(
    counts: Option<&RunCounts>,
    bound: usize,
    runs: usize,
    ran: usize,
    max_failed: f64,
    cell: &str,
) -> Option<String> {
    let Some(c) = counts else {
        return Some(format!(
            "no runs of {cell} in runs.parquet; the spec declares {runs}"
        ));
    };
    let (present, failed) = (c.present[bound], c.failed[bound]);
    if runs > ran {
        return Some(format!(
            "the study ran {ran} runs per cell (a --runs override?), fewer than the {runs} of {cell}"
        ));
    }
    if present < runs as u64 {
        let first = c
            .first_missing
            .map(|r| format!(" (the estimates leave them out; first: run {r})"))
            .unwrap_or_default();
        return Some(format!(
            "{} of the {runs} runs of {cell} the spec declares are missing{first}",
            runs as u64 - present
        ));
    }
    // A fraction of the declared runs: the tolerance does not grow as runs go missing.
    if failed as f64 > max_failed * runs as f64 {
        let first = c
            .first_failure
            .as_ref()
            .map(|(r, d)| format!("; first: run {r}: {d}"))
            .unwrap_or_default();
        return Some(format!(
            "{failed} of the {runs} runs of {cell} failed numerically, more than check.max_failed_runs = {max_failed} allows{first}"
        ));
    }
    None
}

pub(super) fn fmt_g(v: Option<f64>) -> String {
    v.map_or("—".into(), |x| format!("{x}"))
}

/// A p-value or level, in scientific notation when four decimals would show only zeros.
pub(super) fn fmt_p(v: Option<f64>) -> String {
    match v {
        Some(x) if x != 0.0 && x.abs() < 1e-3 => format!("{x:.2e}"),
        other => fmt(other),
    }
}

pub(super) fn fmt(v: Option<f64>) -> String {
    v.map_or("null".into(), |x| format!("{x:.4}"))
}
