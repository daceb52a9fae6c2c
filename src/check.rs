//! `kfmc check`: evaluates a spec's `[check]` assertions against the tables a study wrote,
//! and renders them as a readable table and as JUnit XML for CI systems.

use std::fmt::Write as _;
use std::path::Path;

use polars::prelude::*;

use crate::error::{KfmcError, OutputError};
use std::collections::HashMap;

use crate::experiment::Plan;
use crate::experiment::plan::{Assertion, FilterPlan, Selection};
use crate::metrics::consistency::{SEQUENTIAL, VERDICT, test_names};
use crate::output::table::read;

/// What the verdict of a filter without innovations says, in the check's report and in
/// Python's `Study.verdict()`: the NIS half of the verdict has no data.
pub const NO_INNOVATIONS: &str = "not judged: no innovations";

/// One evaluated test case (an assertion applied to one cell the spec declares).
#[derive(Clone, Debug, PartialEq)]
pub struct CaseResult {
    /// The assertion kind (`consistent`, `rmse_below`, …).
    pub kind: String,
    /// The case name, e.g. `consistent[basic noise=1 ekf q=1 r=1]` (an external filter,
    /// which carries no multipliers, by its label alone: `consistent[basic noise=1 mine]`).
    pub name: String,
    /// Whether it holds: judged on every run the spec declares, and the assertion holds.
    pub pass: bool,
    /// Whether it could not be judged on the runs the spec declares (runs missing, too many
    /// numerical failures, a test that could not be computed): never a pass, and reported
    /// apart from a failure (`kfmc check` exits 4 when nothing failed but something is
    /// incomplete).
    pub incomplete: bool,
    /// The numbers behind the outcome.
    pub detail: String,
}

impl CaseResult {
    /// A case judged on its data: it holds or it fails.
    fn judged(kind: &str, name: String, pass: bool, detail: String) -> Self {
        CaseResult {
            kind: kind.into(),
            name,
            pass,
            incomplete: false,
            detail,
        }
    }
    /// A case that could not be judged on the runs the spec declares.
    fn incomplete(kind: &str, name: String, why: String) -> Self {
        CaseResult {
            kind: kind.into(),
            name,
            pass: false,
            incomplete: true,
            detail: format!("incomplete: {why}"),
        }
    }
}

/// Per row: the cell's display name, its scenario and its filter label.
struct Cells {
    names: Vec<String>,
    scenario: Vec<String>,
    filter: Vec<String>,
}

struct Table {
    df: DataFrame,
    path: std::path::PathBuf,
}

impl Table {
    fn open(path: &Path) -> Result<Self, OutputError> {
        Ok(Table {
            df: read(path)?,
            path: path.to_path_buf(),
        })
    }
    fn of(df: DataFrame, path: &Path) -> Self {
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
    fn str(&self, c: &str) -> Result<Vec<String>, OutputError> {
        let col = self.df.column(c).map_err(|e| self.err(e))?;
        Ok(col
            .str()
            .map_err(|e| self.err(e))?
            .iter()
            .map(|s| s.unwrap_or("").to_string())
            .collect())
    }
    fn f64(&self, c: &str) -> Result<Vec<Option<f64>>, OutputError> {
        let col = self.df.column(c).map_err(|e| self.err(e))?;
        Ok(col.f64().map_err(|e| self.err(e))?.iter().collect())
    }
    fn i64(&self, c: &str) -> Result<Vec<Option<i64>>, OutputError> {
        let col = self.df.column(c).map_err(|e| self.err(e))?;
        Ok(col.i64().map_err(|e| self.err(e))?.iter().collect())
    }
    fn bool(&self, c: &str) -> Result<Vec<Option<bool>>, OutputError> {
        let col = self.df.column(c).map_err(|e| self.err(e))?;
        Ok(col.bool().map_err(|e| self.err(e))?.iter().collect())
    }
    /// Each row's cell key.
    fn keys(&self) -> Result<Vec<CellKey>, OutputError> {
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
    fn cells(&self) -> Result<Cells, OutputError> {
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
fn cell_name(scenario: &str, noise: Option<f64>, filter: &str, qr: Option<(f64, f64)>) -> String {
    match qr {
        Some((q, r)) => format!("{scenario} noise={} {filter} q={q} r={r}", fmt_g(noise)),
        None => format!("{scenario} noise={} {filter}", fmt_g(noise)),
    }
}

/// The key columns of a cell row, floats by their bits (as the tables hold them).
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
struct CellKey {
    scenario: String,
    noise: Option<u64>,
    filter: String,
    q: Option<u64>,
    r: Option<u64>,
}

/// One cell the spec declares, as `check` expects to find it in the tables.
struct PlannedCell<'a> {
    key: CellKey,
    name: String,
    scenario: &'a str,
    filter: &'a FilterPlan,
}

/// The plan's cells (scenario × noise scale × filter variant), in table order.
fn planned_cells(plan: &Plan) -> Vec<PlannedCell<'_>> {
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
struct RunCounts {
    /// Per bound: rows with `run` below it.
    present: Vec<u64>,
    /// Per bound: of those, runs with status `numerical_failure`.
    failed: Vec<u64>,
    /// The failed run of lowest index, and why it failed.
    first_failure: Option<(i64, String)>,
    /// The run of lowest index whose row says it is missing.
    first_missing: Option<i64>,
}

/// Counts the runs of every cell of `runs.parquet` below each of `bounds`, one row group at
/// a time (the table holds a row per run).
fn count_runs(path: &Path, bounds: &[usize]) -> Result<HashMap<CellKey, RunCounts>, OutputError> {
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
fn runs_problem(
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

fn fmt_g(v: Option<f64>) -> String {
    v.map_or("—".into(), |x| format!("{x}"))
}

/// A p-value or level, in scientific notation when four decimals would show only zeros.
fn fmt_p(v: Option<f64>) -> String {
    match v {
        Some(x) if x != 0.0 && x.abs() < 1e-3 => format!("{x:.2e}"),
        other => fmt(other),
    }
}

fn fmt(v: Option<f64>) -> String {
    v.map_or("null".into(), |x| format!("{x:.4}"))
}

/// One evaluation of the consistency tests: the whole cell at the study's α, or a subset's
/// first `runs` runs at its own α.
#[derive(Clone, Copy, Debug)]
struct Evaluation {
    runs: usize,
    alpha: f64,
}

/// Per evaluation of a cell: its rows of consistency.parquet, `None` when it has none.
type EvaluationRows = Vec<Option<Vec<usize>>>;

/// The rows of consistency.parquet of each cell, split into its evaluations: the study
/// writes a cell's evaluations one after the other, each with its tests in the fixed order
/// of [`test_names`], so a test that does not come after the previous one starts the next
/// evaluation. An evaluation that computed no test has no rows, so each block goes to the
/// next evaluation in the plan's order whose α it has and whose run count it does not
/// exceed.
fn consistency_blocks(
    t: &Table,
    order: &[String],
    evaluations: &[Evaluation],
) -> Result<HashMap<CellKey, EvaluationRows>, OutputError> {
    let keys = t.keys()?;
    let (test, alpha, runs) = (t.str("test")?, t.f64("alpha")?, t.i64("runs")?);
    // Per cell: blocks of (α, largest runs value, rows, the last row's test position).
    type Block = (Option<f64>, i64, Vec<usize>, usize);
    let mut blocks: HashMap<CellKey, Vec<Block>> = HashMap::new();
    for (i, key) in keys.into_iter().enumerate() {
        let at = order
            .iter()
            .position(|n| *n == test[i])
            .unwrap_or(usize::MAX);
        let list = blocks.entry(key).or_default();
        let new_block = match list.last() {
            Some((a, _, _, last)) => *a != alpha[i] || at == usize::MAX || at <= *last,
            None => true,
        };
        if new_block {
            list.push((alpha[i], 0, Vec::new(), at));
        }
        let b = list.last_mut().expect("pushed above");
        b.1 = b.1.max(runs[i].unwrap_or(0));
        b.2.push(i);
        b.3 = at;
    }
    Ok(blocks
        .into_iter()
        .map(|(key, list)| {
            let mut assigned: Vec<Option<Vec<usize>>> = vec![None; evaluations.len()];
            let mut e = 0;
            for (a, runs, rows, _) in list {
                while e < evaluations.len()
                    && !(a == Some(evaluations[e].alpha) && runs <= evaluations[e].runs as i64)
                {
                    e += 1;
                }
                if e == evaluations.len() {
                    break;
                }
                assigned[e] = Some(rows);
                e += 1;
            }
            (key, assigned)
        })
        .collect())
}

/// Evaluates every assertion of `plan` against the tables in `dir`: one case per assertion
/// and cell the spec declares, each judged on the runs the spec declares or else
/// incomplete.
pub fn evaluate(plan: &Plan, dir: &Path) -> Result<Vec<CaseResult>, OutputError> {
    crate::output::folder::verify(dir)?;
    let judge = Judge::new(plan, dir)?;
    let mut out = Vec::new();
    for a in plan.assertions.iter().filter(|a| !a.needs_replications()) {
        let before = out.len();
        let kind = match a {
            Assertion::RejectionRate { .. } => unreachable!("filtered above"),
            Assertion::TestPasses { kind, tests, .. } => {
                judge.tests(kind, tests, a.selection(), &mut out)?;
                kind.as_str()
            }
            Assertion::RmseBelow { state, max, .. } => {
                judge.rmse_below(state, *max, a.selection(), &mut out)?;
                "rmse_below"
            }
            Assertion::NoWorseThan {
                reference,
                states,
                margin,
                ..
            } => {
                judge.no_worse_than(reference, states, *margin, a.selection(), &mut out)?;
                "no_worse_than"
            }
        };
        settle(a, kind, &mut out, before);
    }
    Ok(out)
}

/// What every assertion of one study is judged with: the cells the spec declares, their run
/// counts per evaluation, and the tables.
struct Judge<'a> {
    plan: &'a Plan,
    dir: &'a Path,
    cells: Vec<PlannedCell<'a>>,
    /// The whole cell, then each subset, as the study evaluates them.
    evaluations: Vec<Evaluation>,
    counts: HashMap<CellKey, RunCounts>,
    /// Under a sequential gate: per (scenario, noise-scale bits), the runs the gate's
    /// decisions declared (the look of the last gating filter to decide, as the study's
    /// `sequential` rows record them). A cell without its rows is held to the spec's runs.
    gated_runs: Option<HashMap<(String, u64), usize>>,
    /// The tables read so far, each read once however many assertions use it.
    tables: std::cell::RefCell<HashMap<&'static str, std::rc::Rc<Table>>>,
}

impl<'a> Judge<'a> {
    fn new(plan: &'a Plan, dir: &'a Path) -> Result<Self, OutputError> {
        let mut evaluations = vec![Evaluation {
            runs: plan.runs,
            alpha: plan.consistency.as_ref().map_or(plan.alpha, |c| c.alpha),
        }];
        if let Some(c) = &plan.consistency {
            evaluations.extend(
                c.subsets
                    .iter()
                    .map(|&(runs, alpha)| Evaluation { runs, alpha }),
            );
        }
        let bounds: Vec<usize> = evaluations.iter().map(|e| e.runs).collect();
        let counts = count_runs(&dir.join("runs.parquet"), &bounds)?;
        let mut judge = Self {
            plan,
            dir,
            cells: planned_cells(plan),
            evaluations,
            counts,
            gated_runs: None,
            tables: Default::default(),
        };
        if plan.sequential.is_some() {
            judge.gated_runs = Some(judge.read_gated_runs()?);
        }
        Ok(judge)
    }

    /// Per (scenario, noise-scale bits): the largest `runs` of its `sequential` rows in
    /// consistency.parquet, which is where the gate stopped the cell.
    fn read_gated_runs(&self) -> Result<HashMap<(String, u64), usize>, OutputError> {
        let t = self.table("consistency.parquet")?;
        let (scenario, noise, test, runs) = (
            t.str("scenario")?,
            t.f64("noise_scale")?,
            t.str("test")?,
            t.i64("runs")?,
        );
        let mut out: HashMap<(String, u64), usize> = HashMap::new();
        for i in 0..test.len() {
            if test[i] != SEQUENTIAL {
                continue;
            }
            let (Some(noise), Some(runs)) = (noise[i], runs[i].filter(|r| *r > 0)) else {
                continue;
            };
            let e = out
                .entry((scenario[i].clone(), noise.to_bits()))
                .or_default();
            *e = (*e).max(runs as usize);
        }
        Ok(out)
    }

    /// The runs evaluation `e` of `c` is judged on: the spec's (or the subset's), or under a
    /// sequential gate the look that settled the cell.
    fn declared_runs(&self, c: &PlannedCell<'_>, e: usize) -> usize {
        let fixed = self.evaluations[e].runs;
        match (&self.gated_runs, c.key.noise) {
            (Some(gated), Some(noise)) => gated
                .get(&(c.scenario.to_string(), noise))
                .copied()
                .map_or(fixed, |n| n.min(fixed)),
            _ => fixed,
        }
    }

    /// `name` of the study's folder, read on first use.
    fn table(&self, name: &'static str) -> Result<std::rc::Rc<Table>, OutputError> {
        if let Some(t) = self.tables.borrow().get(name) {
            return Ok(t.clone());
        }
        let t = std::rc::Rc::new(Table::open(&self.dir.join(name))?);
        self.tables.borrow_mut().insert(name, t.clone());
        Ok(t)
    }

    /// Why `cell` cannot be judged on the declared runs of evaluation `e`, if it cannot.
    fn runs_problem(&self, c: &PlannedCell<'_>, e: usize, cell: &str) -> Option<String> {
        runs_problem(
            self.counts.get(&c.key),
            e,
            self.declared_runs(c, e),
            self.plan.runs,
            self.plan.check_max_failed_runs,
            cell,
        )
    }

    /// Consistency tests named by `tests` pass, in every evaluation of every covered cell.
    fn tests(
        &self,
        kind: &str,
        tests: &[String],
        select: &Selection,
        out: &mut Vec<CaseResult>,
    ) -> Result<(), OutputError> {
        let t = self.table("consistency.parquet")?;
        let order = test_names(&self.plan.system.layout().quantity_names());
        let evaluations = &self.evaluations;
        let blocks = consistency_blocks(&t, &order, evaluations)?;
        let test = t.str("test")?;
        // With subsets, one cell holds the same test at several (runs, α): name them.
        let subsets = evaluations.len() > 1;
        let (stat, lo, hi, p, pass, dir) = (
            t.f64("statistic")?,
            t.f64("lower")?,
            t.f64("upper")?,
            t.f64("p_value")?,
            t.bool("pass")?,
            t.str("direction")?,
        );
        let runs = t.i64("runs")?;
        // Without a filter named, the assertion covers the filters that have tests (a
        // filter without a covariance has none, by its kind).
        let covered = |c: &&PlannedCell<'_>| {
            select.covers_variant(c.scenario, c.filter)
                && (select.filter.is_some() || self.plan.has_covariance(c.filter))
        };
        for c in self.cells.iter().filter(covered) {
            for (e, ev) in evaluations.iter().enumerate() {
                let mut cell = c.name.clone();
                if subsets {
                    cell += &format!(" N={} α={}", ev.runs, ev.alpha);
                }
                let rows = blocks
                    .get(&c.key)
                    .and_then(|b| b[e].as_deref())
                    .unwrap_or(&[]);
                for want in tests {
                    // The per-step fractions are descriptive, kept for the whole cell only.
                    if e > 0 && want.ends_with("_steps_inside") {
                        continue;
                    }
                    let label = if tests.len() > 1 || kind == "test_passes" {
                        format!("{kind}[{cell} {want}]")
                    } else {
                        format!("{kind}[{cell}]")
                    };
                    // Under a sequential gate the verdict is the gate's decision on it.
                    let gated = self.gated_runs.is_some() && want == VERDICT;
                    let want = if gated { SEQUENTIAL } else { want.as_str() };
                    if let Some(why) = self.runs_problem(c, e, &cell) {
                        out.push(CaseResult::incomplete(kind, label, why));
                        continue;
                    }
                    let Some(&i) = rows.iter().find(|&&i| test[i] == *want) else {
                        out.push(CaseResult::incomplete(
                            kind,
                            label,
                            not_computed(want, &cell, rows, &test),
                        ));
                        continue;
                    };
                    // A p-value is part of every test but the descriptive fractions.
                    let needs_p = !want.ends_with("_steps_inside");
                    // An infinite statistic with a p-value is a rejection (a t-test whose
                    // spread is rounding, away from μ); NaN or null is not computed.
                    let computed = stat[i].is_some_and(|s| !s.is_nan())
                        && pass[i].is_some()
                        && (!needs_p || p[i].is_some_and(f64::is_finite));
                    if gated && !computed {
                        out.push(CaseResult::incomplete(
                            kind,
                            label,
                            format!(
                                "the sequential gate left the verdict of {cell} undecided at its last look ({} runs): it could not be computed",
                                runs[i].unwrap_or(0)
                            ),
                        ));
                        continue;
                    }
                    if !computed {
                        out.push(CaseResult::incomplete(
                            kind,
                            label,
                            format!(
                                "{want} of {cell} could not be computed (statistic {}, p-value {})",
                                fmt(stat[i]),
                                fmt(p[i])
                            ),
                        ));
                        continue;
                    }
                    // "in" or "outside" by the row's own verdict, so the line never reads
                    // "in" beside a failure.
                    let ok = pass[i] == Some(true);
                    let bounds = match (lo[i], hi[i]) {
                        (Some(l), Some(h)) => format!(
                            "{} [{}, {}]",
                            if ok { "in" } else { "outside" },
                            fmt(Some(l)),
                            fmt(Some(h))
                        ),
                        (Some(l), None) => {
                            format!("{} {}", if ok { "≥" } else { "<" }, fmt(Some(l)))
                        }
                        _ => String::new(),
                    };
                    let d = if dir[i].is_empty() {
                        String::new()
                    } else {
                        format!(", {}", dir[i])
                    };
                    let detail = if gated {
                        sequential_detail(ok, stat[i], lo[i], hi[i], runs[i], &dir[i])
                    } else if want == VERDICT {
                        format!(
                            "Bonferroni p-value 2·min(p_NEES, p_NIS) = {} (must exceed α = {}){d}",
                            fmt(stat[i]),
                            fmt(lo[i])
                        )
                    } else {
                        format!("{want} = {} {bounds} (p = {}{d})", fmt(stat[i]), fmt(p[i]))
                    };
                    out.push(CaseResult::judged(kind, label, ok, detail));
                }
            }
        }
        Ok(())
    }

    /// The mean RMSE over runs of `state` stays below `max` in every covered cell.
    fn rmse_below(
        &self,
        state: &str,
        max: f64,
        select: &Selection,
        out: &mut Vec<CaseResult>,
    ) -> Result<(), OutputError> {
        let kind = "rmse_below";
        let summary = self.table("summary.parquet")?;
        let st = summary.str("state")?;
        let mean = summary.f64("rmse_mean")?;
        // The state's row of each cell.
        let rows: HashMap<CellKey, usize> = summary
            .keys()?
            .into_iter()
            .enumerate()
            .filter(|(i, _)| st[*i] == state)
            .map(|(i, k)| (k, i))
            .collect();
        for c in self
            .cells
            .iter()
            .filter(|c| select.covers_variant(c.scenario, c.filter))
        {
            let label = format!("rmse_below[{} {state}]", c.name);
            if let Some(why) = self.runs_problem(c, 0, &c.name) {
                out.push(CaseResult::incomplete(kind, label, why));
                continue;
            }
            match rows.get(&c.key).map(|&i| mean[i]) {
                Some(Some(m)) if m.is_finite() => out.push(CaseResult::judged(
                    kind,
                    label,
                    m < max,
                    format!("rmse_mean = {} (must be < {max})", fmt(Some(m))),
                )),
                other => out.push(CaseResult::incomplete(
                    kind,
                    label,
                    format!(
                        "rmse_mean of {} {state} could not be computed ({})",
                        c.name,
                        match other {
                            None => "no row in summary.parquet".to_string(),
                            Some(v) => format!("rmse_mean = {}", fmt(v)),
                        }
                    ),
                )),
            }
        }
        Ok(())
    }

    /// Every covered filter variant is no worse than `reference` on the same runs, per state:
    /// [`paired_excess_test`] of its per-run RMSE against (1 + margin) × the reference's, at α
    /// shared by the states (Bonferroni), so one case's false-alarm rate is at most α.
    fn no_worse_than(
        &self,
        reference: &str,
        states: &[String],
        margin: f64,
        select: &Selection,
        out: &mut Vec<CaseResult>,
    ) -> Result<(), OutputError> {
        let kind = "no_worse_than";
        let judged = |c: &&PlannedCell<'_>| {
            select.covers_variant(c.scenario, c.filter) && c.filter.label != reference
        };
        let pairs: Vec<(&PlannedCell<'_>, &PlannedCell<'_>)> = self
            .cells
            .iter()
            .filter(judged)
            .filter_map(|c| {
                let r = self.cells.iter().find(|r| {
                    r.filter.label == reference
                        && r.key.scenario == c.key.scenario
                        && r.key.noise == c.key.noise
                })?;
                Some((c, r))
            })
            .collect();
        let mut wanted: Vec<CellKey> = Vec::new();
        for (c, r) in &pairs {
            wanted.extend([c.key.clone(), r.key.clone()]);
        }
        let rmse = run_rmse(
            &self.dir.join("runs.parquet"),
            &wanted,
            states,
            self.plan.runs,
        )?;
        let alpha = self.evaluations[0].alpha / states.len() as f64;
        let share = if states.len() > 1 {
            format!(" = α/{}, Bonferroni over the states", states.len())
        } else {
            String::new()
        };
        for (c, r) in pairs {
            let problem = self
                .runs_problem(c, 0, &c.name)
                .or_else(|| self.runs_problem(r, 0, &r.name));
            for (s, state) in states.iter().enumerate() {
                let label = format!("no_worse_than[{} vs {reference} {state}]", c.name);
                if let Some(why) = &problem {
                    out.push(CaseResult::incomplete(kind, label, why.clone()));
                    continue;
                }
                let (Some(mine), Some(theirs)) = (rmse.get(&c.key), rmse.get(&r.key)) else {
                    out.push(CaseResult::incomplete(
                        kind,
                        label,
                        format!("no per-run RMSE of {state} in runs.parquet"),
                    ));
                    continue;
                };
                let pairs = match rmse_pairs(mine, theirs, s, state, (&c.name, &r.name)) {
                    Ok(p) => p,
                    Err(why) => {
                        out.push(CaseResult::incomplete(kind, label, why));
                        continue;
                    }
                };
                match paired_excess_test(&pairs, margin) {
                    None => out.push(CaseResult::incomplete(
                        kind,
                        label,
                        format!(
                            "{} runs have an RMSE of {state} for both filters; the paired test needs 2",
                            pairs.len()
                        ),
                    )),
                    Some(t) => {
                        let pass = t.p_value > alpha;
                        out.push(CaseResult::judged(
                            kind,
                            label,
                            pass,
                            format!(
                                "rmse {} vs {} ({:+.1} %, margin {} %): paired t = {:.3} over {} runs, p = {} (fails at p ≤ {}{share})",
                                fmt(Some(t.mean)),
                                fmt(Some(t.reference_mean)),
                                100.0 * (t.mean / t.reference_mean - 1.0),
                                100.0 * margin,
                                t.t,
                                t.runs,
                                fmt(Some(t.p_value)),
                                fmt(Some(alpha)),
                            ),
                        ));
                    }
                }
            }
        }
        Ok(())
    }
}

/// One cell's runs: per state, each run's value (`None` where the run has none), and per
/// run whether it is left out of the statistics (a numerical failure, a missing run, or a
/// run without a row, which `runs_problem` has judged already).
#[derive(Clone, Debug)]
struct StateRuns {
    values: Vec<Vec<Option<f64>>>,
    left_out: Vec<bool>,
}

/// The (filter, reference) RMSE pairs of state `s` over the runs: runs left out (failed
/// within the tolerance, or missing) are no pair; any other run without a finite RMSE for
/// both is data the paired test cannot judge (`Err`, naming the first), never a pair
/// dropped without a word. `names`: the two cells, for the message.
fn rmse_pairs(
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
fn run_rmse(
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

/// Why test `want` of `cell` has no row: what the cell's evaluation did compute says which
/// part was missing.
/// The detail of a sequential gate's decision (`p`: the verdict's Bonferroni p-value at the
/// deciding look of `runs` runs; `reject_p`/`accept_p`: that look's boundaries on it).
fn sequential_detail(
    ok: bool,
    p: Option<f64>,
    reject_p: Option<f64>,
    accept_p: Option<f64>,
    runs: Option<i64>,
    direction: &str,
) -> String {
    let n = runs.unwrap_or(0);
    let why = if ok {
        match accept_p {
            Some(a) if a < 1.0 && p.is_some_and(|p| p > a) => {
                format!("exceeds the futility bound {}", fmt_p(Some(a)))
            }
            _ => format!(
                "above the reject bound {} at the last look",
                fmt_p(reject_p)
            ),
        }
    } else {
        format!("at or below the reject bound {}", fmt_p(reject_p))
    };
    let d = if direction.is_empty() {
        String::new()
    } else {
        format!(", {direction}")
    };
    format!(
        "sequential gate: {} after {n} runs: Bonferroni p-value {} {why}{d}",
        if ok { "consistent" } else { "inconsistent" },
        fmt_p(p)
    )
}

fn not_computed(want: &str, cell: &str, rows: &[usize], test: &[String]) -> String {
    if rows.is_empty() {
        return format!("{cell} has no consistency tests at all: {want} could not be computed");
    }
    let has = |n: &str| rows.iter().any(|&i| test[i] == n);
    if want == VERDICT && !has("nis_time_average") {
        return format!(
            "the verdict of {cell} could not be computed: {NO_INNOVATIONS} (no NIS test: the filter reports no innovation ν with its covariance S; an outside filter's estimates give them as nu_<z> and S_<zi>_<zj>)"
        );
    }
    if want == VERDICT && !has("nees_time_average") && has("nees_run_average_t") {
        return format!(
            "the verdict of {cell} could not be computed: the calibrated NEES test needs every run's error transition (the filter gave it for some runs only), or, for a filter that gives none, at least 20 runs for the model-free test"
        );
    }
    format!("{want} of {cell} could not be computed (no row in consistency.parquet)")
}

/// Closes one assertion's cases: none at all is a case of its own that could not be
/// judged, and a negative control passes exactly when the assertion's own cases fail (an
/// incomplete case stays incomplete: it was not judged either way).
fn settle(a: &Assertion, kind: &str, out: &mut Vec<CaseResult>, before: usize) {
    if out.len() == before {
        out.push(CaseResult::incomplete(
            kind,
            format!("{kind}[no matching rows]"),
            "no table row matches this assertion (does the filter carry a covariance?)".into(),
        ));
    } else if a.expect_fail() {
        for case in &mut out[before..] {
            case.name = format!("negative_control:{}", case.name);
            if case.incomplete {
                case.detail = format!(
                    "expected to fail, but it could not be judged: {}",
                    case.detail
                );
                continue;
            }
            case.detail = format!(
                "expected to fail, and it {}: {}",
                if case.pass { "passed" } else { "failed" },
                case.detail
            );
            case.pass = !case.pass;
        }
    }
}

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

/// Counts of a check's cases: (failed, incomplete); the rest passed.
pub fn tally(cases: &[CaseResult]) -> (usize, usize) {
    let incomplete = cases.iter().filter(|c| c.incomplete).count();
    let failed = cases.iter().filter(|c| !c.pass && !c.incomplete).count();
    (failed, incomplete)
}

/// The readable report.
pub fn render(experiment: &str, cases: &[CaseResult]) -> String {
    let (failed, incomplete) = tally(cases);
    let mut s = format!(
        "kfmc check {experiment}: {} cases, {} passed, {failed} failed, {incomplete} incomplete\n",
        cases.len(),
        cases.len() - failed - incomplete
    );
    let w = cases
        .iter()
        .map(|c| c.name.chars().count())
        .max()
        .unwrap_or(10);
    // The outcome column is as wide as its widest word.
    let o = if incomplete > 0 { 10 } else { 4 };
    for c in cases {
        let _ = writeln!(
            s,
            "  {:<o$}  {:<w$}  {}",
            if c.incomplete {
                "INCOMPLETE"
            } else if c.pass {
                "PASS"
            } else {
                "FAIL"
            },
            c.name,
            c.detail
        );
    }
    s
}

fn xml_escape(s: &str) -> String {
    s.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
        .replace('\'', "&apos;")
}

/// JUnit XML: one `<testcase>` per case, failures with their numbers; an incomplete case is
/// a `<failure type="incomplete">` whose message names the cell and the count.
pub fn junit(experiment: &str, cases: &[CaseResult], seconds: f64) -> String {
    let (failed, incomplete) = tally(cases);
    let failures = failed + incomplete;
    let mut s = String::from("<?xml version=\"1.0\" encoding=\"UTF-8\"?>\n");
    let _ = writeln!(
        s,
        "<testsuites name=\"kfmc check\" tests=\"{}\" failures=\"{failures}\" time=\"{seconds:.3}\">",
        cases.len()
    );
    let _ = writeln!(
        s,
        "  <testsuite name=\"{}\" tests=\"{}\" failures=\"{failures}\" errors=\"0\" time=\"{seconds:.3}\">",
        xml_escape(experiment),
        cases.len()
    );
    for c in cases {
        let _ = write!(
            s,
            "    <testcase classname=\"kfmc.{}.{}\" name=\"{}\"",
            xml_escape(experiment),
            xml_escape(&c.kind),
            xml_escape(&c.name)
        );
        if c.pass {
            let _ = writeln!(
                s,
                ">\n      <system-out>{}</system-out>\n    </testcase>",
                xml_escape(&c.detail)
            );
        } else {
            let kind = if c.incomplete { "incomplete" } else { "failed" };
            let _ = writeln!(
                s,
                ">\n      <failure type=\"{kind}\" message=\"{}\">{}</failure>\n    </testcase>",
                xml_escape(&c.detail),
                xml_escape(&c.detail)
            );
        }
    }
    s.push_str("  </testsuite>\n</testsuites>\n");
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_paired_excess_test_matches_a_hand_calculation() {
        // d = (0, 1, 2): mean 1, s = 1, t = 1/(1/√3) = √3. With 2 degrees of freedom the
        // t distribution's tail has the closed form ½(1 − t/√(t² + 2)).
        let t = paired_excess_test(&[(1.0, 1.0), (2.0, 1.0), (3.0, 1.0)], 0.0).unwrap();
        let root3 = 3f64.sqrt();
        assert!((t.t - root3).abs() < 1e-12, "{t:?}");
        let closed = 0.5 * (1.0 - root3 / (3.0f64 + 2.0).sqrt());
        assert!(
            (t.p_value - closed).abs() < 1e-9,
            "{} vs {closed}",
            t.p_value
        );
        assert_eq!((t.runs, t.mean, t.reference_mean), (3, 2.0, 1.0));
        // The margin scales the reference: 2 = (1 + 1) × 1 makes the mean difference 0 − 1.
        let m = paired_excess_test(&[(1.0, 1.0), (2.0, 1.0), (3.0, 1.0)], 1.0).unwrap();
        assert!(
            (m.t - 0.0).abs() < 1e-12 && (m.p_value - 0.5).abs() < 1e-12,
            "{m:?}"
        );
        // Equal runs: no spread, not worse.
        let same = paired_excess_test(&[(0.5, 0.5), (0.7, 0.7)], 0.0).unwrap();
        assert_eq!(same.p_value, 1.0);
        assert!(paired_excess_test(&[(1.0, 1.0)], 0.0).is_none());
    }

    #[test]
    fn the_paired_excess_test_rejects_at_rate_alpha_on_its_boundary_and_catches_an_excess() {
        // Runs share a difficulty c_i (lognormal, spread 30 %); the filter's RMSE is
        // (1 + margin)·c_i·(1 + δ) + noise and the reference's c_i + noise. On the boundary
        // (δ = 0) the rejection rate must be α within 3 binomial standard deviations; 5 % worse
        // than the margin allows, with 30 runs, it must be caught in most replications.
        use rand::{RngExt, SeedableRng};
        let normal = |rng: &mut rand_pcg::Pcg64| {
            let (u, v): (f64, f64) = (rng.random(), rng.random());
            (-2.0 * (1.0 - u).ln()).sqrt() * (std::f64::consts::TAU * v).cos()
        };
        let (alpha, margin, n, reps) = (0.05, 0.1, 30, 4000);
        let mut rng = rand_pcg::Pcg64::seed_from_u64(36);
        let mut rate = |delta: f64| {
            let mut rejected = 0;
            for _ in 0..reps {
                let pairs: Vec<(f64, f64)> = (0..n)
                    .map(|_| {
                        let c = (0.3 * normal(&mut rng)).exp();
                        let a = (1.0 + margin) * c * (1.0 + delta) + 0.02 * normal(&mut rng);
                        let b = c + 0.02 * normal(&mut rng);
                        (a, b)
                    })
                    .collect();
                let t = paired_excess_test(&pairs, margin).unwrap();
                rejected += usize::from(t.p_value <= alpha);
            }
            rejected as f64 / reps as f64
        };
        let null = rate(0.0);
        let sd = (alpha * (1.0 - alpha) / reps as f64).sqrt();
        assert!((null - alpha).abs() <= 3.0 * sd, "false-alarm rate {null}");
        let power = rate(0.05);
        assert!(power > 0.8, "power {power}");
        // Better than the reference by the margin: never failed.
        assert!(rate(-0.2) < 0.001);
    }

    #[test]
    fn rmse_pairs_refuse_a_non_finite_rmse_of_a_run_that_did_not_fail() {
        let runs = |values: Vec<Option<f64>>, left_out: Vec<bool>| StateRuns {
            values: vec![values],
            left_out,
        };
        let theirs = runs(vec![Some(1.0), Some(1.0), Some(2.0)], vec![false; 3]);
        // A failed run (null RMSE) is left out; the others pair.
        let mine = runs(vec![Some(1.5), None, Some(2.5)], vec![false, true, false]);
        assert_eq!(
            rmse_pairs(&mine, &theirs, 0, "x", ("a", "b")),
            Ok(vec![(1.5, 1.0), (2.5, 2.0)])
        );
        // An infinite or NaN RMSE, or a null one of a run that did not fail, is no pair to
        // drop: the case cannot be judged.
        for bad in [Some(f64::INFINITY), Some(f64::NAN), None] {
            let mine = runs(vec![Some(1.5), bad, Some(2.5)], vec![false; 3]);
            let why = rmse_pairs(&mine, &theirs, 0, "x", ("a", "b")).unwrap_err();
            assert!(why.starts_with("run 1 is not a failure"), "{why}");
        }
    }

    fn counts(present: u64, failed: u64) -> RunCounts {
        RunCounts {
            present: vec![present],
            failed: vec![failed],
            first_failure: (failed > 0).then(|| (4, "non-finite estimate".into())),
            first_missing: None,
        }
    }

    #[test]
    fn a_case_is_judged_only_on_the_declared_runs() {
        let cell = "basic noise=1 ekf q=1 r=1";
        assert_eq!(
            runs_problem(Some(&counts(10, 0)), 0, 10, 10, 0.0, cell),
            None
        );
        // Missing runs: named with their count, whatever the tolerance for failures.
        let why = runs_problem(Some(&counts(2, 0)), 0, 10, 10, 1.0, cell).unwrap();
        assert_eq!(
            why,
            "8 of the 10 runs of basic noise=1 ekf q=1 r=1 the spec declares are missing"
        );
        assert!(runs_problem(None, 0, 10, 10, 1.0, cell).is_some());
        // Failures: beyond the fraction of the declared runs, not within it (1/10 ≤ 0.1).
        let why = runs_problem(Some(&counts(10, 1)), 0, 10, 10, 0.0, cell).unwrap();
        assert!(
            why.starts_with("1 of the 10 runs of basic noise=1 ekf q=1 r=1 failed numerically")
                && why.ends_with("first: run 4: non-finite estimate"),
            "{why}"
        );
        assert_eq!(
            runs_problem(Some(&counts(10, 1)), 0, 10, 10, 0.1, cell),
            None
        );
        assert!(runs_problem(Some(&counts(10, 2)), 0, 10, 10, 0.1, cell).is_some());
        // A subset of more runs than the study ran (a --runs override) is not judged on fewer.
        let why = runs_problem(Some(&counts(10, 0)), 0, 50, 10, 0.0, cell).unwrap();
        assert!(why.starts_with("the study ran 10 runs per cell"), "{why}");
    }

    #[test]
    fn incomplete_cases_are_counted_apart_and_never_pass() {
        let cases = vec![
            CaseResult::judged("consistent", "a".into(), true, String::new()),
            CaseResult::judged("consistent", "b".into(), false, String::new()),
            CaseResult::incomplete("consistent", "c".into(), "2 of 10 runs".into()),
        ];
        assert_eq!(tally(&cases), (1, 1));
        let text = render("x", &cases);
        assert!(
            text.starts_with("kfmc check x: 3 cases, 1 passed, 1 failed, 1 incomplete\n"),
            "{text}"
        );
        assert!(
            text.contains("INCOMPLETE  c  incomplete: 2 of 10 runs"),
            "{text}"
        );
        let xml = junit("x", &cases, 0.0);
        assert!(xml.contains("tests=\"3\" failures=\"2\""), "{xml}");
        assert!(
            xml.contains("<failure type=\"incomplete\" message=\"incomplete: 2 of 10 runs\">"),
            "{xml}"
        );
        // A negative control that could not be judged stays incomplete.
        let a = Assertion::TestPasses {
            kind: "consistent".into(),
            tests: vec![VERDICT.into()],
            select: Selection::default(),
            expect_fail: true,
        };
        let mut out = vec![CaseResult::incomplete(
            "consistent",
            "c".into(),
            "why".into(),
        )];
        settle(&a, "consistent", &mut out, 0);
        assert!(out[0].incomplete && !out[0].pass, "{:?}", out[0]);
    }
}

/// The gate's exit code when an assertion failed.
pub const EXIT_CHECK_FAILED: u8 = 3;
/// The gate's exit code when no assertion failed but a case could not be judged on the runs
/// the spec declares (incomplete).
pub const EXIT_CHECK_INCOMPLETE: u8 = 4;

/// What `kfmc check` found: the evaluated cases of one spec, as the CLI prints them and the
/// Python module returns them.
#[derive(Clone, Debug, PartialEq)]
pub struct CheckOutcome {
    /// The experiment's name.
    pub experiment: String,
    /// Every evaluated case, in the order the report lists them.
    pub cases: Vec<CaseResult>,
    /// Wall-clock seconds of the studies behind the cases.
    pub wall_s: f64,
}

impl CheckOutcome {
    /// Failed and incomplete cases ([`tally`]).
    pub fn tally(&self) -> (usize, usize) {
        tally(&self.cases)
    }
    /// The readable report ([`render`]).
    pub fn render(&self) -> String {
        render(&self.experiment, &self.cases)
    }
    /// The JUnit XML ([`junit`]).
    pub fn junit(&self) -> String {
        junit(&self.experiment, &self.cases, self.wall_s)
    }
    /// The gate's exit code: 0 all hold, 3 one failed (a judged failure outranks a case that
    /// could not be judged), 4 none failed but one is incomplete.
    pub fn exit_code(&self) -> u8 {
        match self.tally() {
            (0, 0) => 0,
            (0, _) => EXIT_CHECK_INCOMPLETE,
            _ => EXIT_CHECK_FAILED,
        }
    }
}

/// Why [`run`] stopped: an invalid request (reported as it is), or a failure of one stage,
/// which the CLI prefixes with `context` (`running SPEC`, `evaluating the assertions`).
#[derive(Debug, thiserror::Error)]
pub enum RunError {
    /// The spec or the request is invalid (no assertion, no replications, over a limit).
    #[error(transparent)]
    Invalid(KfmcError),
    /// A stage failed.
    #[error("{context}")]
    Stage {
        /// What was being done.
        context: String,
        /// The cause (boxed: a `Result` carrying it stays small).
        #[source]
        source: Box<KfmcError>,
    },
}

impl RunError {
    /// The library error underneath, whatever the stage.
    pub fn error(&self) -> &KfmcError {
        match self {
            RunError::Invalid(e) => e,
            RunError::Stage { source, .. } => source,
        }
    }
}

/// Runs `kfmc check`'s studies for `plan` (loaded from `spec`, overrides applied, external
/// filters' estimates attached) and evaluates its `[check]` assertions: the study itself for
/// the per-cell assertions, `replications` (or `check.replications`) replications of it for
/// the rejection-rate ones. Each study gets its own observer from `observer`. Printing and
/// exit codes are the caller's ([`CheckOutcome`]).
pub fn run<O: crate::runner::RunObserver>(
    mut plan: Plan,
    spec: &Path,
    replications: Option<usize>,
    allow_large: bool,
    exec: &crate::study::ExecOptions,
    observer: impl Fn() -> O,
) -> Result<CheckOutcome, RunError> {
    use crate::error::{SpecError, SpecErrors};
    if plan.assertions.is_empty() {
        return Err(RunError::Invalid(KfmcError::Spec(SpecErrors(vec![
            SpecError {
                file: spec.to_path_buf(),
                key_path: "check.assert".into(),
                message: "kfmc check needs at least one [[check.assert]]".into(),
            },
        ]))));
    }
    // Consistency assertions need the tests even when the spec did not ask for them.
    let alpha = plan.alpha;
    plan.consistency
        .get_or_insert(crate::experiment::plan::ConsistencyPlan::at_level(alpha));
    plan.sequential = plan
        .check_gate()
        .map_err(|e| RunError::Invalid(KfmcError::Spec(e)))?;
    let needs_power = plan.assertions.iter().any(|a| a.needs_replications());
    let replications = replications.or(plan.check_replications);
    if let Some(r) = replications.filter(|_| needs_power) {
        crate::study::check_replications(&plan, r, allow_large)
            .map_err(|e| RunError::Invalid(e.into()))?;
    }
    if needs_power && replications.is_none_or(|r| r == 0) {
        return Err(RunError::Invalid(KfmcError::Spec(SpecErrors(vec![
            SpecError {
                file: spec.to_path_buf(),
                key_path: "check.replications".into(),
                message: "a rejection_rate assertion is judged over replications of the whole study: set check.replications ≥ 1 or pass --replications R".into(),
            },
        ]))));
    }
    let stage = |context: String| {
        move |source: KfmcError| RunError::Stage {
            context,
            source: Box::new(source),
        }
    };
    let mut cases = Vec::new();
    let mut wall_s = 0.0;
    if plan.assertions.iter().any(|a| !a.needs_replications()) {
        // Judged while still held: the tables read back are this study's.
        let (report, _held) = crate::study::run_locked(&plan, exec, &observer())
            .map_err(stage(format!("running {}", spec.display())))?;
        wall_s += report.wall_s;
        cases.extend(
            evaluate(&plan, &report.output)
                .map_err(KfmcError::from)
                .map_err(stage("evaluating the assertions".into()))?,
        );
    }
    if let Some(r) = replications.filter(|_| needs_power) {
        let out = plan.output.join("power");
        let mut power_plan = plan.clone();
        power_plan.output = out.clone();
        // Rejection rates are those of the fixed-N tests the assertions name.
        power_plan.sequential = None;
        let report = crate::power::power(&power_plan, r, plan.master_seed, &out, exec, &observer())
            .map_err(stage(format!(
                "running {} replications of {}",
                r,
                spec.display()
            )))?;
        wall_s += report.wall_s;
        cases.extend(
            evaluate_power(&plan, &report.output)
                .map_err(KfmcError::from)
                .map_err(stage("evaluating the rejection-rate assertions".into()))?,
        );
    }
    Ok(CheckOutcome {
        experiment: plan.name.clone(),
        cases,
        wall_s,
    })
}

/// What a command does with an estimates file that carries no world stamp.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Unstamped {
    /// Read it, with a warning on stderr (`kfmc score`, `kfmc check --allow-unstamped`).
    Warn,
    /// Refuse it (`kfmc check`: a CI gate passes only on data tied to its spec's runs).
    Refuse,
}

/// Reads the external filters' estimates into `plan`; files without a world stamp are
/// warned about or refused, as `unstamped` says.
pub fn attach_estimates(
    plan: &mut Plan,
    files: &[std::path::PathBuf],
    unstamped: Unstamped,
) -> Result<(), KfmcError> {
    attach_estimates_with_tables(plan, files, &[], unstamped)
}

/// [`attach_estimates`] with tables already in memory besides the files
/// ([`crate::score::InMemoryTable`]: their stamp is looked for in their metadata, and one
/// without is unstamped as a file without is).
pub fn attach_estimates_with_tables(
    plan: &mut Plan,
    files: &[std::path::PathBuf],
    tables: &[crate::score::InMemoryTable],
    unstamped: Unstamped,
) -> Result<(), KfmcError> {
    let sources = (files
        .iter()
        .cloned()
        .map(crate::score::EstimatesSource::File))
    .chain(
        tables
            .iter()
            .cloned()
            .map(crate::score::EstimatesSource::Table),
    )
    .map(Ok);
    attach_estimates_from(plan, sources, unstamped)
}

/// [`attach_estimates_with_tables`] from sources taken one at a time
/// ([`crate::score::EstimateSet::load_from`]): a producer's tables are read and dropped as
/// they come.
pub fn attach_estimates_from(
    plan: &mut Plan,
    sources: impl IntoIterator<Item = Result<crate::score::EstimatesSource, crate::error::OutputError>>,
    unstamped: Unstamped,
) -> Result<(), KfmcError> {
    let set = crate::score::EstimateSet::load_from(&plan.study_keys(), sources)?;
    if let Some(truth) = &plan.truth {
        refuse_runs_without_truth(plan, truth, &set)?;
    }
    let stamp = format!(
        "{} = {}, {} = {}",
        crate::score::STAMP_KEY,
        plan.world_stamp(),
        crate::score::SEED_KEY,
        plan.master_seed
    );
    for path in set.unstamped() {
        match unstamped {
            Unstamped::Warn => eprintln!(
                "warning: {} carries no world stamp: nothing ties its rows to this study's runs (estimates of another simulation would be judged as data). A writer stamps its file with the metadata {stamp} (`kfmc schema estimates SPEC` shows them)",
                path.display()
            ),
            Unstamped::Refuse => {
                return Err(OutputError::Format {
                    path: path.clone(),
                    message: format!(
                        "carries no world stamp; kfmc check judges only estimates tied to the spec's runs: stamp the file with the metadata {stamp}, or pass --allow-unstamped{}",
                        if set.is_table(path) {
                            " (in Python: allow_unstamped=True; a kfmc.Estimates made on the simulation, or a pyarrow Table read from a stamped file, carries the stamp)"
                        } else {
                            ""
                        }
                    ),
                }
                .into());
            }
        }
    }
    for m in set.missing_runs() {
        eprintln!("warning: {}", missing_runs_text(plan, &m));
    }
    plan.estimates = Some(std::sync::Arc::new(set));
    Ok(())
}

/// Reads a user's truth table into a recorded plan (`kfmc score --truth`, `kfmc check
/// --truth`): `files` and then the tables in memory `frames` (name, rows), checked against
/// the spec ([`crate::exchange::recorded`]). Its content hash becomes the plan's world stamp,
/// so attach it before the estimates. A run the table leaves out is missing (a warning says
/// how many), as is a run an outside filter's estimates leave out.
pub fn attach_truth(
    plan: &mut Plan,
    files: &[std::path::PathBuf],
    frames: &[(String, polars::prelude::DataFrame)],
) -> Result<(), KfmcError> {
    let name = files
        .first()
        .cloned()
        .or_else(|| frames.first().map(|(n, _)| n.into()))
        .unwrap_or_else(|| "--truth".into());
    if !plan.system.recorded() {
        return Err(OutputError::Mismatch {
            path: name,
            why: format!(
                "is a truth table, but the spec {} simulates its own truth (model.kind = \"{}\"); a truth table is judged with a spec of model.kind = \"recorded\", and a kfmc simulation with `kfmc score SIM_DIR --estimates …`",
                plan.spec_path.display(),
                plan.kind
            ),
        }
        .into());
    }
    let table = crate::exchange::recorded::RecordedTable::read(plan.truth_keys(), files, frames)?;
    let missing = table.missing_runs();
    if let Some(&(cell, run)) = missing.first() {
        let scales = plan.noise_scales.len();
        eprintln!(
            "warning: {}: the truth leaves {} of the spec's {} runs out (first: scenario {}, noise scale {}, run {run}); they are missing, and a `kfmc check` case judged on the declared runs is incomplete without them",
            name.display(),
            missing.len(),
            plan.runs * plan.scenarios.len() * scales,
            plan.scenarios[cell / scales].name,
            plan.noise_scales[cell % scales]
        );
    }
    plan.settings.truth = Some(std::sync::Arc::new(table));
    Ok(())
}

/// The plan that judges a user's truth table `truth` with the recorded spec `spec` (`kfmc
/// score --truth`): the spec parsed, its output `out` (default the spec's `output`), and the
/// truth attached ([`attach_truth`]). The estimates are the caller's.
pub fn recorded_plan(
    spec: &Path,
    truth: &Path,
    out: Option<std::path::PathBuf>,
    registry: &crate::system::Registry,
) -> Result<Plan, KfmcError> {
    let mut plan = crate::experiment::load_with(spec, registry)?;
    if let Some(out) = out {
        plan.output = out;
    }
    attach_truth(&mut plan, &[truth.to_path_buf()], &[])?;
    Ok(plan)
}

/// Stamps estimates files with `plan`'s world ([`Plan::stamp_metadata`]: for a recorded plan
/// with its truth attached, the truth's content hash), in place and atomically: the rows and
/// the file's other metadata are kept, the two stamp keys set (`kfmc stamp`). A file is read
/// whole, so this is for files that fit in memory.
pub fn stamp_estimates(plan: &Plan, files: &[std::path::PathBuf]) -> Result<(), KfmcError> {
    let stamp = plan.stamp_metadata();
    for path in files {
        let polars = |action, source| OutputError::Polars {
            action,
            path: path.clone(),
            source,
        };
        let open = || {
            crate::output::atomic::open_input(path).map_err(|source| OutputError::Io {
                action: "cannot open",
                path: path.clone(),
                source,
            })
        };
        if !crate::output::table::starts_as_parquet(&open()?) {
            return Err(OutputError::Format {
                path: path.clone(),
                message: "estimates must be Parquet (got a CSV?): the file does not begin with Parquet's `PAR1` marker".into(),
            }
            .into());
        }
        let mut reader = ParquetReader::new(open()?);
        let meta = reader
            .get_metadata()
            .map_err(|e| polars("cannot read", e))?
            .clone();
        let mut pairs: Vec<(String, String)> = meta
            .key_value_metadata()
            .iter()
            .flatten()
            .filter(|kv| !stamp.iter().any(|(k, _)| *k == kv.key))
            .map(|kv| (kv.key.clone(), kv.value.clone().unwrap_or_default()))
            .collect();
        pairs.extend(stamp.iter().cloned());
        let mut df = ParquetReader::new(open()?)
            .finish()
            .map_err(|e| polars("cannot read", e))?;
        let mut bytes = Vec::new();
        ParquetWriter::new(&mut bytes)
            .with_compression(ParquetCompression::Zstd(None))
            .with_key_value_metadata(Some(
                polars::io::parquet::write::KeyValueMetadata::from_static(pairs),
            ))
            .finish(&mut df)
            .map_err(|e| polars("cannot write", e))?;
        crate::output::atomic::write_atomic(path, &bytes).map_err(|source| OutputError::Io {
            action: "cannot write",
            path: path.clone(),
            source,
        })?;
    }
    Ok(())
}

/// Refuses estimates of a run the truth leaves out: nothing to judge them against.
fn refuse_runs_without_truth(
    plan: &Plan,
    truth: &crate::exchange::recorded::RecordedTable,
    set: &crate::score::EstimateSet,
) -> Result<(), KfmcError> {
    let scales = plan.noise_scales.len();
    for (cell, run) in truth.missing_runs() {
        if let Some((label, path)) = set.gives_run(cell, run) {
            return Err(OutputError::Format {
                path,
                message: format!(
                    "filter {label} gives estimates for scenario {}, noise scale {}, run {run}, which the truth table leaves out: nothing to judge them against",
                    plan.scenarios[cell / scales].name,
                    plan.noise_scales[cell % scales]
                ),
            }
            .into());
        }
    }
    Ok(())
}

/// What `kfmc score` and `kfmc check` say of an external filter's missing runs.
pub fn missing_runs_text(plan: &Plan, m: &crate::score::MissingRuns) -> String {
    let first = m
        .first
        .map(|(cell, run)| {
            let scales = plan.noise_scales.len();
            format!(
                "; first: scenario {}, noise scale {}, run {run}",
                plan.scenarios[cell / scales].name,
                plan.noise_scales[cell % scales]
            )
        })
        .unwrap_or_default();
    format!(
        "the estimates of {} leave {} of its {} runs out{first}: they are missing (status `missing` in runs.parquet), not failures; no statistic counts them, and a `kfmc check` case judged on the declared runs is incomplete without them",
        m.filter, m.runs, m.of
    )
}
