//! The per-cell assertions judged on one study's tables: consistency tests, RMSE bounds and
//! paired comparisons, each case on the runs the spec declares or else incomplete.

use std::collections::HashMap;
use std::path::Path;

use super::paired::{paired_excess_test, rmse_pairs, run_rmse};
use super::tables::{
    CellKey, PlannedCell, RunCounts, Table, count_runs, fmt, fmt_p, planned_cells, runs_problem,
};
use super::{CaseResult, NO_INNOVATIONS};
use crate::error::OutputError;
use crate::experiment::Plan;
use crate::experiment::plan::{Assertion, Selection};
use crate::metrics::consistency::{SEQUENTIAL, VERDICT, test_names};

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

/// Why test `want` of `cell` has no row: what the cell's evaluation did compute says which
/// part was missing.
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
pub(super) fn settle(a: &Assertion, kind: &str, out: &mut Vec<CaseResult>, before: usize) {
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
