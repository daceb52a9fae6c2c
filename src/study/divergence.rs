//! Divergence points: the feed that rebuilds the per-run trackers from rows (a resumed
//! study, `kfmc merge`), and the divergence tables written from the trackers.

use super::rows::*;
use crate::error::OutputError;
use crate::experiment::Plan;
use crate::metrics::divergence::DivergenceTracker;
use crate::metrics::spill::Spill;
use crate::output::{TableWriter, Value, schema};

/// Rebuilds the divergence trackers from rows already written, in the order a study writes
/// them: a resume replays its journals, `kfmc merge` reads its parts' tables. (The trackers
/// look across the noise scales of a scenario, so no single cell's rows give them.)
pub(crate) struct DivergenceFeed<'a> {
    pub(super) plan: &'a Plan,
    /// Per (scenario, filter variant), as the study keeps them.
    pub(super) trackers: Vec<DivergenceTracker>,
    pub(super) runs: Vec<crate::output::schema::ColumnDef>,
    pub(super) summary: Vec<crate::output::schema::ColumnDef>,
    /// Positions of `run` and of the `rmse_<state>` columns in `runs`.
    pub(super) run_col: usize,
    pub(super) rmse_cols: Vec<usize>,
    /// Position of `rmse_mean` in `summary`.
    pub(super) mean_col: usize,
    /// The means of the (cell, filter) whose summary rows are being read: they come one row
    /// per state, in state order, possibly across row groups.
    pub(super) means: Vec<f64>,
}

impl<'a> DivergenceFeed<'a> {
    /// Trackers of every (scenario, filter variant) of `plan`, nothing observed yet, with
    /// their scratch files in `dir`.
    pub(crate) fn new(plan: &'a Plan, dir: &std::path::Path) -> Self {
        let states = plan.quantity_names();
        let runs = schema::runs(&states);
        let summary = schema::summary();
        let position = |columns: &[crate::output::schema::ColumnDef], name: &str| {
            columns
                .iter()
                .position(|c| c.name == name)
                .unwrap_or_else(|| panic!("the schema has a column {name}"))
        };
        DivergenceFeed {
            plan,
            trackers: (0..plan.scenarios.len() * plan.filters.len())
                .map(|_| DivergenceTracker::new(dir, states.len()))
                .collect(),
            run_col: position(&runs, "run"),
            rmse_cols: states
                .iter()
                .map(|s| position(&runs, &format!("rmse_{s}")))
                .collect(),
            mean_col: position(&summary, "rmse_mean"),
            means: Vec::with_capacity(states.len()),
            runs,
            summary,
        }
    }

    /// The columns of the runs table, the order [`DivergenceFeed::run_row`] reads.
    pub(crate) fn runs_columns(&self) -> &[crate::output::schema::ColumnDef] {
        &self.runs
    }

    /// The columns of the summary table, the order [`DivergenceFeed::summary_row`] reads.
    pub(crate) fn summary_columns(&self) -> &[crate::output::schema::ColumnDef] {
        &self.summary
    }

    /// Observes one row of the runs table (each noise scale's runs in run order, as the
    /// study writes them). A row that does not fit the plan is `bad(why)`, `why` completing
    /// "a row …", for the caller to say where the row came from.
    pub(crate) fn run_row(
        &mut self,
        row: &[Value<'_>],
        bad: &dyn Fn(&str) -> OutputError,
    ) -> Result<(), OutputError> {
        let Some(thr) = &self.plan.rmse_thresholds else {
            return Ok(());
        };
        let (si, scale, fi) = self.cell(row).ok_or_else(|| bad(NO_CELL))?;
        // A null RMSE (a failed run) is NaN, as the study feeds it.
        let rmse: Vec<f64> = self
            .rmse_cols
            .iter()
            .map(|&c| f64_of(&row[c]).unwrap_or(f64::NAN))
            .collect();
        let run = match row[self.run_col] {
            Value::I64(Some(r)) => r as usize,
            _ => return Err(bad("has no run index")),
        };
        let nf = self.plan.filters.len();
        self.trackers[si * nf + fi].observe_run(run, scale, &rmse, thr)
    }

    /// Observes one row of the summary table; a (cell, filter)'s mean RMSE is observed at
    /// its last state's row. A bad row is `bad(why)` as in [`DivergenceFeed::run_row`].
    pub(crate) fn summary_row(
        &mut self,
        row: &[Value<'_>],
        bad: &dyn Fn(&str) -> OutputError,
    ) -> Result<(), OutputError> {
        let Some(thr) = &self.plan.rmse_thresholds else {
            return Ok(());
        };
        self.means
            .push(f64_of(&row[self.mean_col]).unwrap_or(f64::NAN));
        if self.means.len() == self.rmse_cols.len() {
            let (si, scale, fi) = self.cell(row).ok_or_else(|| bad(NO_CELL))?;
            let nf = self.plan.filters.len();
            self.trackers[si * nf + fi].observe_mean(scale, &self.means, thr);
            self.means.clear();
        }
        Ok(())
    }

    /// The trackers, for [`divergence_tables`] or for the study to go on observing.
    pub(crate) fn into_trackers(self) -> Vec<DivergenceTracker> {
        self.trackers
    }

    /// (scenario, noise scale, filter variant) indices of a row keyed by [`cell_key`].
    pub(super) fn cell(&self, row: &[Value<'_>]) -> Option<(usize, usize, usize)> {
        let p = self.plan;
        let [
            Value::Str(s),
            Value::F64(Some(noise)),
            Value::Str(label),
            Value::F64(q),
            Value::F64(r),
            ..,
        ] = row
        else {
            return None;
        };
        let si = p.scenarios.iter().position(|x| x.name == *s)?;
        let scale = p.noise_scales.iter().position(|x| x == noise)?;
        // An external filter's multipliers are null unless it declares variants.
        let fi = p.filters.iter().position(|f| {
            let (fq, fr) = f.multipliers().unzip();
            f.label == *label && fq == *q && fr == *r
        })?;
        Some((si, scale, fi))
    }
}

/// Why [`DivergenceFeed`] refuses a row whose key is not one of the plan's cells.
pub(super) const NO_CELL: &str = "names a cell the spec does not have";

pub(super) fn f64_of(v: &Value<'_>) -> Option<f64> {
    match v {
        Value::F64(x) => *x,
        _ => None,
    }
}

/// The divergence tables from the trackers of every (scenario, filter variant); shared with
/// `kfmc merge`, which rebuilds the trackers from the merged runs and summary.
pub(crate) fn divergence_tables(
    plan: &Plan,
    dir: &std::path::Path,
    trackers: &mut [DivergenceTracker],
    states: &[&str],
    thr: &[f64],
) -> Result<(TableWriter, TableWriter), OutputError> {
    let mut d = TableWriter::create(dir, "divergence", schema::divergence())?;
    let mut dr = TableWriter::create(dir, "divergence_runs", schema::divergence_runs())?;
    let nf = plan.filters.len();
    let max_scale = plan.noise_scales.last().copied();
    let scale_of = |j: Option<usize>| j.map(|j| plan.noise_scales[j]);
    for (si, s) in plan.scenarios.iter().enumerate() {
        for (fi, f) in plan.filters.iter().enumerate() {
            let tracker = &mut trackers[si * nf + fi];
            let [q, r] = scale_keys(f);
            let key = [Value::Str(&s.name), Value::Str(&f.label), q, r];
            for (i, state) in states.iter().enumerate() {
                // Runs that never crossed are censored beyond the largest scale: +∞ in the
                // ordering, so a quantile that needs them is unknown (null), not invented.
                // robustness.m records the largest multiplier tried for a state that never
                // crossed; by default such a run is censored instead.
                let never = if plan.never_crossed_largest {
                    max_scale.unwrap_or(f64::INFINITY)
                } else {
                    f64::INFINITY
                };
                // One pass over the runs per state writes its rows and spills the values
                // whose exact quantiles the summary row needs.
                let mut per_run = Spill::new(dir, 1);
                let mut diverged = 0i64;
                tracker.for_each_run(|r, crossings| {
                    let crossing = scale_of(crossings[i]);
                    let v = crossing.unwrap_or(never);
                    diverged += crossing.is_some() as i64;
                    per_run.push(&[v])?;
                    let mut row = key.to_vec();
                    row.extend([
                        Value::I64(Some(r as i64)),
                        Value::Str(state),
                        Value::F64(v.is_finite().then_some(v)),
                        Value::Bool(Some(crossing.is_none())),
                    ]);
                    dr.push(&row)
                })?;
                let q = &per_run.summarise(|_, _| true, &LEVELS)?[0].quantiles;
                let mut row = key.to_vec();
                row.extend([
                    Value::Str(state),
                    Value::F64(Some(thr[i])),
                    Value::F64(max_scale),
                    Value::F64(scale_of(tracker.mc_crossing(i))),
                    Value::I64(Some(plan.runs as i64)),
                    Value::I64(Some(diverged)),
                    Value::F64(q[0]),
                    Value::F64(q[1]),
                    Value::F64(q[2]),
                ]);
                d.push(&row)?;
            }
        }
    }
    Ok((d, dr))
}

#[cfg(test)]
mod tests {
    use super::*;

    const SPEC: &str = r#"
name = "feed"
runs = 2
[model]
kind = "planar_quadrotor"
[[scenarios]]
name = "basic"
duration_s = 1.0
[[filters]]
label = "ekf"
kind = "ekf"
[noise]
scales = [0.5, 1.0]
[divergence]
rmse_thresholds = [1.0, 1.0, 1.0, 1.0, 1.0, 1.0]
"#;

    fn plan() -> Plan {
        crate::experiment::parse(SPEC, std::path::Path::new("feed.toml")).expect("a valid spec")
    }

    /// A runs row as the study writes it: state 0's RMSE `x0`, state 1's `x1`, the others 0.5.
    fn run_row(
        plan: &Plan,
        scale: usize,
        run: Option<i64>,
        x0: f64,
        x1: Option<f64>,
    ) -> Vec<Value<'_>> {
        let mut row = cell_key(
            &plan.scenarios[0].name,
            plan.noise_scales[scale],
            &plan.filters[0],
        )
        .to_vec();
        row.extend([
            Value::I64(run),
            Value::U64(7),
            Value::Str("ok"),
            Value::I64(None),
            Value::Str(""),
            Value::F64(Some(x0)),
            Value::F64(x1),
        ]);
        row.extend([Value::F64(Some(0.5)); 4]);
        row.extend([Value::F64(None), Value::F64(None), Value::I64(Some(0))]);
        row
    }

    /// The summary rows of a (cell, filter): state `i`'s mean RMSE `means[i]`.
    fn summary_rows<'a>(plan: &'a Plan, scale: usize, means: &[f64]) -> Vec<Vec<Value<'a>>> {
        means
            .iter()
            .map(|m| {
                let mut row = cell_key(
                    &plan.scenarios[0].name,
                    plan.noise_scales[scale],
                    &plan.filters[0],
                )
                .to_vec();
                row.extend([
                    Value::Str("x"),
                    Value::I64(Some(2)),
                    Value::I64(Some(0)),
                    Value::F64(Some(*m)),
                ]);
                row.extend([Value::F64(None); 4]);
                row
            })
            .collect()
    }

    fn why(e: OutputError) -> String {
        match e {
            OutputError::Mismatch { why, .. } => why,
            other => panic!("{other}"),
        }
    }

    const BAD: &dyn Fn(&str) -> OutputError = &|why: &str| OutputError::Mismatch {
        path: "t".into(),
        why: why.into(),
    };

    #[test]
    fn the_feed_gives_the_crossings_of_the_rows_it_reads() {
        let dir = tempfile::tempdir().unwrap();
        let plan = plan();
        let mut feed = DivergenceFeed::new(&plan, dir.path());
        let runs = [
            run_row(&plan, 0, Some(0), 0.5, Some(0.5)),
            // A failed run's RMSE is null: it counts as crossed.
            run_row(&plan, 0, Some(1), 2.0, None),
            run_row(&plan, 1, Some(0), 1.5, Some(0.5)),
            run_row(&plan, 1, Some(1), 0.5, Some(0.5)),
        ];
        for row in &runs {
            assert_eq!(row.len(), feed.runs_columns().len());
            feed.run_row(row, BAD).unwrap();
        }
        let mut summary = summary_rows(&plan, 0, &[0.5, 0.5, 3.0, 0.5, 0.5, 0.5]);
        summary.extend(summary_rows(&plan, 1, &[0.5, 0.5, 0.5, 5.0, 0.5, 0.5]));
        for row in &summary {
            assert_eq!(row.len(), feed.summary_columns().len());
            feed.summary_row(row, BAD).unwrap();
        }
        let mut trackers = feed.into_trackers();
        assert_eq!(trackers.len(), 1);
        let t = &mut trackers[0];
        let mc: Vec<Option<usize>> = (0..6).map(|i| t.mc_crossing(i)).collect();
        assert_eq!(mc, [None, None, Some(0), Some(1), None, None]);
        let mut per_run = Vec::new();
        t.for_each_run(|r, c| {
            per_run.push((r, c[..2].to_vec(), c[2..].iter().all(Option::is_none)));
            Ok(())
        })
        .unwrap();
        assert_eq!(
            per_run,
            [
                (0, vec![Some(1), None], true),
                (1, vec![Some(0), Some(0)], true)
            ]
        );
    }

    #[test]
    fn a_row_the_plan_does_not_have_is_refused_for_the_caller_to_name() {
        let dir = tempfile::tempdir().unwrap();
        let plan = plan();
        let mut feed = DivergenceFeed::new(&plan, dir.path());
        let mut row = run_row(&plan, 0, Some(0), 0.5, Some(0.5));
        row[0] = Value::Str("elsewhere");
        let e = feed.run_row(&row, BAD).unwrap_err();
        assert_eq!(why(e), "names a cell the spec does not have");
        let row = run_row(&plan, 0, None, 0.5, Some(0.5));
        assert_eq!(
            why(feed.run_row(&row, BAD).unwrap_err()),
            "has no run index"
        );
        let mut rows = summary_rows(&plan, 0, &[0.5; 6]);
        rows[5][1] = Value::F64(Some(3.0));
        for row in &rows[..5] {
            feed.summary_row(row, BAD).unwrap();
        }
        let e = feed.summary_row(&rows[5], BAD).unwrap_err();
        assert_eq!(why(e), "names a cell the spec does not have");
    }
}
