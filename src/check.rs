//! `kfmc check`: evaluates a spec's `[check]` assertions against the tables a study wrote,
//! and renders them as a readable table and as JUnit XML for CI systems.

use std::fmt::Write as _;
use std::path::Path;

use polars::prelude::*;

use crate::error::OutputError;
use crate::experiment::Plan;
use crate::experiment::plan::Assertion;
use crate::output::table::read;

/// One evaluated test case (an assertion applied to one matching cell).
#[derive(Clone, Debug, PartialEq)]
pub struct CaseResult {
    /// The assertion kind (`consistent`, `rmse_below`, …).
    pub kind: String,
    /// The case name, e.g. `consistent[basic noise=1 ekf q=1 r=1]`.
    pub name: String,
    /// Whether it holds.
    pub pass: bool,
    /// The numbers behind the outcome.
    pub detail: String,
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
    /// Cell names per row and the (scenario, filter) columns for matching.
    fn cells(&self) -> Result<Cells, OutputError> {
        let sc = self.str("scenario")?;
        let f = self.str("filter")?;
        let noise = self.f64("noise_scale")?;
        let q = self.f64("q_scale")?;
        let r = self.f64("r_scale")?;
        let g = |v: Option<f64>| v.map_or("—".into(), |x| format!("{x}"));
        let names = (0..sc.len())
            .map(|i| {
                format!(
                    "{} noise={} {} q={} r={}",
                    sc[i],
                    g(noise[i]),
                    f[i],
                    g(q[i]),
                    g(r[i])
                )
            })
            .collect();
        Ok(Cells {
            names,
            scenario: sc,
            filter: f,
        })
    }
}

fn fmt_g(v: Option<f64>) -> String {
    v.map_or("—".into(), |x| format!("{x}"))
}

fn fmt(v: Option<f64>) -> String {
    v.map_or("null".into(), |x| format!("{x:.4}"))
}

/// Evaluates every assertion of `plan` against the tables in `dir`.
pub fn evaluate(plan: &Plan, dir: &Path) -> Result<Vec<CaseResult>, OutputError> {
    crate::output::folder::verify(dir)?;
    let mut out = Vec::new();
    let needs = |a: &Assertion| matches!(a, Assertion::TestPasses { .. });
    let cons = if plan.assertions.iter().any(needs) {
        Some(Table::open(&dir.join("consistency.parquet"))?)
    } else {
        None
    };
    let summary = Table::open(&dir.join("summary.parquet"))?;
    for a in plan.assertions.iter().filter(|a| !a.needs_replications()) {
        let before = out.len();
        let (kind, filter, scenario) = match a {
            Assertion::RejectionRate { .. } => unreachable!("filtered above"),
            Assertion::TestPasses {
                kind,
                filter,
                scenario,
                ..
            } => (kind.as_str(), filter, scenario),
            Assertion::RmseBelow {
                filter, scenario, ..
            } => ("rmse_below", filter, scenario),
        };
        let matches = |sc: &str, f: &str| {
            scenario.as_ref().is_none_or(|s| s == sc) && filter.as_ref().is_none_or(|x| x == f)
        };
        match a {
            Assertion::RejectionRate { .. } => {}
            Assertion::TestPasses { tests, .. } => {
                let t = cons.as_ref().expect("opened above");
                let Cells {
                    names,
                    scenario: sc,
                    filter: f,
                } = t.cells()?;
                let test = t.str("test")?;
                // With subsets, one cell holds the same test at several (runs, α): name them.
                let subsets = plan
                    .consistency
                    .as_ref()
                    .is_some_and(|c| !c.subsets.is_empty());
                let (alpha, n_runs) = (t.f64("alpha")?, t.i64("runs")?);
                let (stat, lo, hi, p, pass, dir) = (
                    t.f64("statistic")?,
                    t.f64("lower")?,
                    t.f64("upper")?,
                    t.f64("p_value")?,
                    t.bool("pass")?,
                    t.str("direction")?,
                );
                for i in 0..names.len() {
                    if !matches(&sc[i], &f[i]) || !tests.contains(&test[i]) {
                        continue;
                    }
                    let mut cell = names[i].clone();
                    if subsets {
                        cell += &format!(" N={} α={}", n_runs[i].unwrap_or(0), fmt_g(alpha[i]));
                    }
                    let label = if tests.len() > 1 || kind == "test_passes" {
                        format!("{kind}[{cell} {}]", test[i])
                    } else {
                        format!("{kind}[{cell}]")
                    };
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
                    let detail = if test[i] == "verdict" {
                        format!(
                            "Bonferroni p-value 2·min(p_NEES, p_NIS) = {} (must exceed α = {}){d}",
                            fmt(stat[i]),
                            fmt(lo[i])
                        )
                    } else {
                        format!(
                            "{} = {} {bounds} (p = {}{d})",
                            test[i],
                            fmt(stat[i]),
                            fmt(p[i])
                        )
                    };
                    out.push(CaseResult {
                        kind: kind.into(),
                        name: label,
                        pass: pass[i] == Some(true),
                        detail,
                    });
                }
            }
            Assertion::RmseBelow { state, max, .. } => {
                let Cells {
                    names,
                    scenario: sc,
                    filter: f,
                } = summary.cells()?;
                let st = summary.str("state")?;
                let mean = summary.f64("rmse_mean")?;
                for i in 0..names.len() {
                    if !matches(&sc[i], &f[i]) || &st[i] != state {
                        continue;
                    }
                    out.push(CaseResult {
                        kind: kind.into(),
                        name: format!("rmse_below[{} {state}]", names[i]),
                        pass: mean[i].is_some_and(|m| m < *max),
                        detail: format!("rmse_mean = {} (must be < {max})", fmt(mean[i])),
                    });
                }
            }
        }
        settle(a, kind, &mut out, before);
    }
    Ok(out)
}

/// Closes one assertion's cases: none matched is a failure of its own, and a negative
/// control passes exactly when the assertion's own cases fail.
fn settle(a: &Assertion, kind: &str, out: &mut Vec<CaseResult>, before: usize) {
    if out.len() == before {
        out.push(CaseResult {
            kind: kind.into(),
            name: format!("{kind}[no matching rows]"),
            pass: false,
            detail: "no table row matches this assertion (does the filter carry a covariance?)"
                .into(),
        });
    } else if a.expect_fail() {
        for case in &mut out[before..] {
            case.name = format!("negative_control:{}", case.name);
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
            filter,
            scenario,
            q_scale,
            r_scale,
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
                && scenario.as_ref().is_none_or(|s| s == &sc[i])
                && filter.as_ref().is_none_or(|x| x == &f[i])
                && q_scale.is_none_or(|v| q[i] == Some(v))
                && r_scale.is_none_or(|v| r[i] == Some(v))
                && want_runs.is_none_or(|n| runs[i] == Some(n as i64));
            if !keep {
                continue;
            }
            let (Some(p), Some(l), Some(h)) = (rate[i], lo[i], hi[i]) else {
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
            out.push(CaseResult {
                kind: "rejection_rate".into(),
                name: format!(
                    "rejection_rate[{} N={} α={} {}]",
                    names[i],
                    runs[i].unwrap_or(0),
                    fmt_g(alpha[i]),
                    test[i]
                ),
                pass,
                detail: format!(
                    "rejected in {} of {} replications: rate {} [{}, {}] ({what} {bounds})",
                    rejections[i].unwrap_or(0),
                    reps[i].unwrap_or(0),
                    fmt(Some(p)),
                    fmt(Some(l)),
                    fmt(Some(h)),
                ),
            });
        }
        settle(a, "rejection_rate", &mut out, before);
    }
    Ok(out)
}

/// The readable report.
pub fn render(experiment: &str, cases: &[CaseResult]) -> String {
    let failed = cases.iter().filter(|c| !c.pass).count();
    let mut s = format!(
        "kfmc check {experiment}: {} cases, {} passed, {failed} failed\n",
        cases.len(),
        cases.len() - failed
    );
    let w = cases
        .iter()
        .map(|c| c.name.chars().count())
        .max()
        .unwrap_or(10);
    for c in cases {
        let _ = writeln!(
            s,
            "  {}  {:<w$}  {}",
            if c.pass { "PASS" } else { "FAIL" },
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

/// JUnit XML: one `<testcase>` per case, failures with their numbers.
pub fn junit(experiment: &str, cases: &[CaseResult], seconds: f64) -> String {
    let failed = cases.iter().filter(|c| !c.pass).count();
    let mut s = String::from("<?xml version=\"1.0\" encoding=\"UTF-8\"?>\n");
    let _ = writeln!(
        s,
        "<testsuites name=\"kfmc check\" tests=\"{}\" failures=\"{failed}\" time=\"{seconds:.3}\">",
        cases.len()
    );
    let _ = writeln!(
        s,
        "  <testsuite name=\"{}\" tests=\"{}\" failures=\"{failed}\" errors=\"0\" time=\"{seconds:.3}\">",
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
            let _ = writeln!(
                s,
                ">\n      <failure message=\"{}\">{}</failure>\n    </testcase>",
                xml_escape(&c.detail),
                xml_escape(&c.detail)
            );
        }
    }
    s.push_str("  </testsuite>\n</testsuites>\n");
    s
}
