//! `[check]` and its `[[check.assert]]` entries: the assertions `kfmc check` judges, and the
//! sequential gate it judges them with.

use std::collections::BTreeSet;

use super::Plan;
use crate::error::{SpecError, SpecErrors};
use crate::experiment::spec::{AssertSpec, OneOrMany, Spec};
use crate::system::SystemPlan;
use crate::system::checker::{Checker, positive};
use crate::system::settings::FilterPlan;

/// Which cells an assertion covers: each key given narrows it, none covers every cell.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Selection {
    /// Only the filter with this label.
    pub filter: Option<String>,
    /// Only this scenario.
    pub scenario: Option<String>,
    /// Only the filter variants with this Q multiplier (external filters have none).
    pub q_scale: Option<f64>,
    /// Only the filter variants with this R multiplier (external filters have none).
    pub r_scale: Option<f64>,
}

impl Selection {
    /// Whether the selection covers a cell of `scenario` and filter `label` with the
    /// multipliers `q`, `r` (`None` for an external filter, as in the tables).
    pub fn covers(&self, scenario: &str, label: &str, q: Option<f64>, r: Option<f64>) -> bool {
        self.scenario.as_deref().is_none_or(|s| s == scenario)
            && self.filter.as_deref().is_none_or(|f| f == label)
            && self.q_scale.is_none_or(|v| q == Some(v))
            && self.r_scale.is_none_or(|v| r == Some(v))
    }

    /// [`Selection::covers`] for a planned filter variant.
    pub fn covers_variant(&self, scenario: &str, f: &FilterPlan) -> bool {
        let (q, r) = f.multipliers().unzip();
        self.covers(scenario, &f.label, q, r)
    }
}

/// One validated `[[check.assert]]`.
#[derive(Clone, Debug, PartialEq)]
pub enum Assertion {
    /// The consistency test(s) named must pass (`consistent` → `verdict`,
    /// `white` → `innovation_whiteness`, `unbiased` → `bias_<state>`, `test_passes` → any).
    TestPasses {
        /// The `kind` as written, for reports.
        kind: String,
        /// Test names in consistency.parquet.
        tests: Vec<String>,
        /// The cells judged.
        select: Selection,
        /// A negative control (`expect = "fail"`): every case must fail.
        expect_fail: bool,
    },
    /// A test's rejection rate over `kfmc power` replications stays within bounds (a
    /// false-alarm rate below, a power above).
    RejectionRate {
        /// The test name in power.parquet (default `verdict`).
        test: String,
        /// The cells judged.
        select: Selection,
        /// Run-count filter.
        runs: Option<usize>,
        /// Smallest rate allowed.
        min: Option<f64>,
        /// Largest rate allowed.
        max: Option<f64>,
        /// Whether the whole Clopper–Pearson interval must lie within the bounds.
        interval: bool,
        /// A negative control (`expect = "fail"`): every case must fail.
        expect_fail: bool,
    },
    /// The mean RMSE over runs of a state stays below a bound.
    RmseBelow {
        /// The cells judged.
        select: Selection,
        /// The state.
        state: String,
        /// The bound.
        max: f64,
        /// A negative control (`expect = "fail"`): every case must fail.
        expect_fail: bool,
    },
    /// A filter is no worse than a reference filter on the same runs: per state, a paired
    /// one-sided t-test over runs of rmse − (1 + margin)·rmse_reference fails the case when
    /// the filter's mean RMSE is significantly above (1 + margin) × the reference's.
    NoWorseThan {
        /// The cells judged (the reference's own variant is never judged against itself).
        select: Selection,
        /// The reference filter's label (one variant).
        reference: String,
        /// The states compared (one, or every state).
        states: Vec<String>,
        /// The relative RMSE excess tolerated (0.1: 10 %).
        margin: f64,
        /// A negative control (`expect = "fail"`): every case must fail.
        expect_fail: bool,
    },
}

impl Assertion {
    /// Whether the assertion is a negative control (`expect = "fail"`).
    pub fn expect_fail(&self) -> bool {
        match self {
            Assertion::TestPasses { expect_fail, .. }
            | Assertion::RejectionRate { expect_fail, .. }
            | Assertion::RmseBelow { expect_fail, .. }
            | Assertion::NoWorseThan { expect_fail, .. } => *expect_fail,
        }
    }
    /// The cells the assertion covers.
    pub fn selection(&self) -> &Selection {
        match self {
            Assertion::TestPasses { select, .. }
            | Assertion::RejectionRate { select, .. }
            | Assertion::RmseBelow { select, .. }
            | Assertion::NoWorseThan { select, .. } => select,
        }
    }
    /// Whether the assertion is judged on `kfmc power`'s replications, not on one study.
    pub fn needs_replications(&self) -> bool {
        matches!(self, Assertion::RejectionRate { .. })
    }
}
/// What `[[check.assert]]` entries may name: the spec's scenarios, filters and states.
pub(super) struct Targets<'a> {
    pub(super) spec: &'a Spec,
    pub(super) names: &'a BTreeSet<String>,
    pub(super) labels: &'a BTreeSet<String>,
    pub(super) states: &'a [String],
    /// The configured system; `None` when it was refused (checks that need it are skipped).
    pub(super) system: Option<&'a dyn SystemPlan>,
    pub(super) system_index: &'a [Option<usize>],
    /// The filter variants (label × q_scale × r_scale).
    pub(super) variants: &'a [FilterPlan],
    /// `consistency.whiteness_lags` (its default without the table).
    pub(super) whiteness_lags: usize,
}

impl Targets<'_> {
    /// (carries a covariance, kind) of the filter labelled `label`; `None` for an external
    /// filter, whose columns are only known when its file is read.
    fn covariance(&self, label: &str) -> Option<(bool, String)> {
        let i = self.spec.filters.iter().position(|f| f.label == label)?;
        let info = self.system?.filters().get(self.system_index[i]?)?;
        Some((info.has_covariance, info.kind.clone()))
    }

    /// The consistency tests this system's filters can produce; `test = "…"` must be one.
    fn test_names(&self) -> Vec<String> {
        let states: Vec<&str> = self.states.iter().map(String::as_str).collect();
        crate::metrics::consistency::test_names(&states)
    }
}

/// `[[check.assert]]`: each entry's targets, then its kind's own keys.
pub(super) fn check_asserts(c: &mut Checker, t: &Targets) -> Vec<Assertion> {
    let test_names = t.test_names();
    let asserts = t.spec.check.iter().flat_map(|c| c.asserts.iter());
    let mut assertions = Vec::new();
    for (i, a) in asserts.enumerate() {
        let key = format!("check.assert[{i}]");
        assert_targets(c, t, &key, a);
        assertions.extend(assertion(c, t, &test_names, &key, a));
    }
    assertions
}

/// The filter, scenario and state an assertion names exist, and a consistency assertion's
/// filter carries a covariance.
fn assert_targets(c: &mut Checker, t: &Targets, key: &str, a: &AssertSpec) {
    if let Some(f) = &a.filter
        && !t.labels.contains(f)
    {
        c.err(format!("{key}.filter"), format!("no filter labelled `{f}`"));
    }
    // A consistency test needs a covariance; without one, `kfmc check` would only find
    // no matching rows after the whole study ran.
    let is_test = matches!(
        a.kind.as_str(),
        "consistent" | "white" | "unbiased" | "test_passes" | "rejection_rate"
    );
    if is_test {
        match &a.filter {
            Some(f) => {
                if let Some((false, kind)) = t.covariance(f) {
                    c.err(
                        format!("{key}.filter"),
                        format!("`{f}` is a {kind} filter, which carries no covariance and so has no consistency tests"),
                    );
                }
            }
            None if t.system.is_some()
                && !t.spec.filters.is_empty()
                && t.spec
                    .filters
                    .iter()
                    .all(|f| t.covariance(&f.label).is_some_and(|(cov, _)| !cov)) =>
            {
                c.err(
                    format!("{key}.kind"),
                    "no filter of this spec carries a covariance, so there are no consistency tests to assert",
                );
            }
            None => {}
        }
    }
    let whiteness = a.kind == "white"
        || (a.kind == "test_passes" && a.test.as_deref() == Some("innovation_whiteness"));
    if whiteness && t.spec.consistency.is_some() && t.whiteness_lags == 0 {
        c.err(
            key,
            "asserts innovation whiteness, but consistency.whiteness_lags = 0 computes no whiteness test; set whiteness_lags ≥ 1",
        );
    }
    if let Some(sc) = &a.scenario
        && !t.names.contains(sc)
    {
        c.err(
            format!("{key}.scenario"),
            format!("no scenario named `{sc}`"),
        );
    }
    if let Some(st) = &a.state
        && t.system.is_some()
        && !t.states.contains(st)
    {
        c.err(
            format!("{key}.state"),
            format!("unknown state `{st}`; states: {}", t.states.join(", ")),
        );
    }
    variant_selection(c, t, key, a);
}

/// `q_scale` / `r_scale` of an assertion must select a variant of the filters it covers, so a
/// typo is a spec error instead of a case that matches nothing after the whole study ran.
fn variant_selection(c: &mut Checker, t: &Targets, key: &str, a: &AssertSpec) {
    let named = |f: &&FilterPlan| a.filter.as_ref().is_none_or(|l| *l == f.label);
    let of_filter: Vec<&FilterPlan> = t.variants.iter().filter(named).collect();
    for (name, want, get) in [
        (
            "q_scale",
            a.q_scale,
            (|f: &FilterPlan| f.q_scale) as fn(&FilterPlan) -> f64,
        ),
        ("r_scale", a.r_scale, |f: &FilterPlan| f.r_scale),
    ] {
        let Some(v) = want else { continue };
        let keyed = |f: &&&FilterPlan| f.multipliers().is_some();
        if of_filter.is_empty() || of_filter.iter().filter(keyed).any(|f| get(f) == v) {
            continue;
        }
        let mut have: Vec<f64> = of_filter.iter().filter(keyed).map(|f| get(f)).collect();
        have.sort_by(f64::total_cmp);
        have.dedup();
        let have: Vec<String> = have.iter().map(|x| format!("{x}")).collect();
        let message = match (&a.filter, have.is_empty()) {
            (Some(l), true) => format!(
                "filter `{l}` is external and declares no variants (no q_scale or r_scale), so no variant of it has {name} = {v}"
            ),
            (Some(l), false) => format!(
                "filter `{l}` has no variant with {name} = {v}; its variants have {name} = {}",
                have.join(", ")
            ),
            (None, true) => {
                format!(
                    "no filter variant has {name} = {v} (every filter is external without declared variants)"
                )
            }
            (None, false) => format!(
                "no filter variant has {name} = {v}; the variants have {name} = {}",
                have.join(", ")
            ),
        };
        c.err(format!("{key}.{name}"), message);
    }
}

/// One assertion of its kind, with the keys its kind does not use reported.
fn assertion(
    c: &mut Checker,
    t: &Targets,
    test_names: &[String],
    key: &str,
    a: &AssertSpec,
) -> Option<Assertion> {
    let unused_msg = format!("not used by kind = \"{}\"", a.kind);
    let unused = |c: &mut Checker, keys: &[(&str, bool)]| c.reject_present(key, keys, &unused_msg);
    if a.kind != "rejection_rate" {
        unused(
            c,
            &[
                ("min", a.min.is_some()),
                ("runs", a.runs.is_some()),
                ("bound", a.bound.is_some()),
            ],
        );
    }
    if a.kind != "no_worse_than" {
        unused(
            c,
            &[
                ("reference", a.reference.is_some()),
                ("margin", a.margin.is_some()),
            ],
        );
    }
    let expect_fail = c.choice(
        &format!("{key}.expect"),
        a.expect.as_deref(),
        "pass",
        &["pass", "fail"],
    ) == "fail";
    let select = Selection {
        filter: a.filter.clone(),
        scenario: a.scenario.clone(),
        q_scale: a.q_scale,
        r_scale: a.r_scale,
    };
    let tests = |names: Vec<String>| Assertion::TestPasses {
        kind: a.kind.clone(),
        tests: names,
        select: select.clone(),
        expect_fail,
    };
    match a.kind.as_str() {
        "consistent" | "white" => {
            let present = [
                ("state", a.state.is_some()),
                ("max", a.max.is_some()),
                ("test", a.test.is_some()),
            ];
            unused(c, &present);
            let test = if a.kind == "white" {
                "innovation_whiteness"
            } else {
                "verdict"
            };
            Some(tests(vec![test.to_string()]))
        }
        "unbiased" => {
            unused(c, &[("max", a.max.is_some()), ("test", a.test.is_some())]);
            let which: Vec<String> = match &a.state {
                Some(s) => vec![format!("bias_{s}")],
                None => t.states.iter().map(|s| format!("bias_{s}")).collect(),
            };
            Some(tests(which))
        }
        "test_passes" => {
            unused(c, &[("state", a.state.is_some()), ("max", a.max.is_some())]);
            match &a.test {
                Some(test) if t.system.is_some() && !test_names.contains(test) => {
                    unknown_test(c, key, test, test_names);
                    None
                }
                Some(test) => Some(tests(vec![test.clone()])),
                None => {
                    c.err(
                        format!("{key}.test"),
                        "missing: kind = \"test_passes\" needs a test name of consistency.parquet",
                    );
                    None
                }
            }
        }
        "rejection_rate" => rejection_rate(c, t, test_names, key, a, select, expect_fail),
        "rmse_below" => {
            unused(c, &[("test", a.test.is_some())]);
            match (&a.state, a.max) {
                (Some(state), Some(max)) if positive(max) => Some(Assertion::RmseBelow {
                    select,
                    state: state.clone(),
                    max,
                    expect_fail,
                }),
                _ => {
                    c.err(
                        key,
                        "kind = \"rmse_below\" needs state and a finite max > 0",
                    );
                    None
                }
            }
        }
        "no_worse_than" => {
            unused(c, &[("test", a.test.is_some()), ("max", a.max.is_some())]);
            no_worse_than(c, t, key, a, select, expect_fail)
        }
        other => {
            c.err(
                format!("{key}.kind"),
                crate::system::checker::unknown_value(
                    "value",
                    other,
                    [
                        "consistent",
                        "white",
                        "unbiased",
                        "test_passes",
                        "rmse_below",
                        "no_worse_than",
                        "rejection_rate",
                    ]
                    .into_iter(),
                ),
            );
            None
        }
    }
}

/// `kind = "no_worse_than"`: a reference of one variant, other than the filter judged, and a
/// finite margin ≥ 0.
fn no_worse_than(
    c: &mut Checker,
    t: &Targets,
    key: &str,
    a: &AssertSpec,
    select: Selection,
    expect_fail: bool,
) -> Option<Assertion> {
    let reference = match &a.reference {
        None => {
            c.err(
                format!("{key}.reference"),
                "missing: kind = \"no_worse_than\" needs the label of the reference filter",
            );
            None
        }
        Some(r) if !t.labels.contains(r) => {
            c.err(
                format!("{key}.reference"),
                format!("no filter labelled `{r}`"),
            );
            None
        }
        Some(r) => {
            let variants = t.variants.iter().filter(|f| f.label == *r).count();
            if variants > 1 {
                c.err(
                    format!("{key}.reference"),
                    format!("`{r}` has {variants} variants (q_scale × r_scale values); a reference is one filter: give the reference variant its own label"),
                );
            }
            if a.filter.as_ref() == Some(r) {
                c.err(
                    format!("{key}.filter"),
                    format!("`{r}` is the reference itself; name the filter judged against it"),
                );
            }
            (variants == 1 && a.filter.as_ref() != Some(r)).then(|| r.clone())
        }
    };
    let margin = match a.margin {
        Some(m) if m.is_finite() && m >= 0.0 => Some(m),
        Some(m) => {
            c.err(
                format!("{key}.margin"),
                format!("{m} is not a relative excess ≥ 0 (0.1 tolerates a mean RMSE 10 % above the reference's)"),
            );
            None
        }
        None => {
            c.err(
                format!("{key}.margin"),
                "missing: the relative RMSE excess tolerated (0 for none, 0.1 for 10 %)",
            );
            None
        }
    };
    let states = match &a.state {
        Some(s) => vec![s.clone()],
        None => t.states.to_vec(),
    };
    Some(Assertion::NoWorseThan {
        select,
        reference: reference?,
        states,
        margin: margin?,
        expect_fail,
    })
}

/// Reports `test` at `key.test` as none of the system's tests.
fn unknown_test(c: &mut Checker, key: &str, test: &str, test_names: &[String]) {
    c.err(
        format!("{key}.test"),
        format!(
            "unknown test `{test}`; the tests of this system: {}",
            test_names.join(", ")
        ),
    );
}

/// `kind = "rejection_rate"`: a test's rejection rate over replications, bounded by `min` (a
/// power) or `max` (a false-alarm rate), as an estimate or by its interval.
fn rejection_rate(
    c: &mut Checker,
    t: &Targets,
    test_names: &[String],
    key: &str,
    a: &AssertSpec,
    select: Selection,
    expect_fail: bool,
) -> Option<Assertion> {
    let unused_msg = format!("not used by kind = \"{}\"", a.kind);
    c.reject_present(key, &[("state", a.state.is_some())], &unused_msg);
    let test = a.test.clone().unwrap_or_else(|| "verdict".into());
    if t.system.is_some() && !test_names.contains(&test) {
        unknown_test(c, key, &test, test_names);
    }
    let rate = |c: &mut Checker, name: &str, v: Option<f64>| match v {
        Some(x) if !(0.0..=1.0).contains(&x) => {
            c.err(
                format!("{key}.{name}"),
                format!("{x} is not a rate in [0, 1]"),
            );
            None
        }
        v => v,
    };
    let (min, max) = (rate(c, "min", a.min), rate(c, "max", a.max));
    let interval = c.choice(
        &format!("{key}.bound"),
        a.bound.as_deref(),
        "estimate",
        &["estimate", "interval"],
    ) == "interval";
    if a.min.is_none() && a.max.is_none() {
        c.err(
            key,
            "kind = \"rejection_rate\" needs min (a power) or max (a false-alarm rate)",
        );
    }
    (a.min.is_some() || a.max.is_some()).then_some(Assertion::RejectionRate {
        test,
        select,
        runs: a.runs,
        min,
        max,
        interval,
        expect_fail,
    })
}

/// `[check]`'s own keys.
pub(super) struct CheckTable {
    pub(super) replications: Option<usize>,
    pub(super) max_failed_runs: f64,
    pub(super) sequential: Option<crate::sequential::GateSettings>,
}

/// `[check]`'s own keys (a study of `runs` runs per cell, tests at level `alpha`).
pub(super) fn check_table(c: &mut Checker, spec: &Spec, runs: usize, alpha: f64) -> CheckTable {
    let check = spec.check.as_deref();
    let replications = check.and_then(|t| t.replications);
    if replications == Some(0) {
        c.err("check.replications", "must be at least 1");
    }
    let max_failed_runs = check.and_then(|t| t.max_failed_runs).unwrap_or(0.0);
    if !(0.0..=1.0).contains(&max_failed_runs) {
        c.err(
            "check.max_failed_runs",
            format!("{max_failed_runs} is not a fraction in [0, 1]"),
        );
    }
    let sequential = check.and_then(|t| check_sequential(c, spec, t, runs, alpha));
    CheckTable {
        replications,
        max_failed_runs,
        sequential,
    }
}

/// `check.sequential` with `check.looks`, `check.spending` and `check.futility_beta`: the
/// gate's settings when it is on (the keys are refused without it), validated by building the
/// gate for the spec's runs.
fn check_sequential(
    c: &mut Checker,
    spec: &Spec,
    t: &crate::experiment::spec::CheckSpec,
    runs: usize,
    alpha: f64,
) -> Option<crate::sequential::GateSettings> {
    use crate::sequential::{GateSettings, Looks, Spending};
    if t.sequential != Some(true) {
        let given = [
            ("looks", t.looks.is_some()),
            ("spending", t.spending.is_some()),
            ("futility_beta", t.futility_beta.is_some()),
            ("futility_rho", t.futility_rho.is_some()),
        ];
        c.reject_present(
            "check",
            &given,
            "is a setting of the sequential gate: set check.sequential = true to use it",
        );
        return None;
    }
    let mut settings = GateSettings::default();
    let whole = |x: f64| (x.fract() == 0.0 && (1.0..1e9).contains(&x)).then_some(x as usize);
    match &t.looks {
        None => {}
        Some(OneOrMany::One(n)) => match whole(*n) {
            Some(n) => settings.looks = Looks::Count(n),
            None => c.err("check.looks", format!("{n} is not a count of looks ≥ 1")),
        },
        Some(OneOrMany::Many(v)) => match v.iter().map(|&x| whole(x)).collect::<Option<Vec<_>>>() {
            Some(counts) => settings.looks = Looks::RunCounts(counts),
            None => c.err("check.looks", format!("{v:?} are not whole run counts")),
        },
    }
    match t.spending.as_deref() {
        // The flag's spelling is accepted too: one value, whichever side it was copied from.
        None | Some("obrien_fleming" | "obrien-fleming") => {}
        Some("pocock") => settings.spending = Spending::Pocock,
        Some(other) => c.err(
            "check.spending",
            format!(
                "`{other}` is not a spending function: expected \"obrien_fleming\" (or \"obrien-fleming\") or \"pocock\""
            ),
        ),
    }
    settings.futility_beta = t.futility_beta;
    if let Some(rho) = t.futility_rho {
        if t.futility_beta.is_none() {
            c.err(
                "check.futility_rho",
                "shapes the futility bounds: set check.futility_beta too",
            );
        }
        settings.futility_rho = rho;
    }
    if spec
        .consistency
        .as_deref()
        .is_some_and(|cs| !cs.subsets.is_empty())
    {
        c.err("check.sequential", "cannot be combined with [[consistency.subsets]]: a sequential gate judges each cell at its own looks");
    }
    if spec
        .divergence
        .as_deref()
        .is_some_and(|d| d.rmse_thresholds.is_some())
    {
        c.err("check.sequential", "cannot be combined with divergence.rmse_thresholds: the divergence tables follow every run across the noise scales, and a sequential gate stops each cell at its own look");
    }
    if let Err(e) = settings.gate(runs, alpha) {
        c.err(gate_error_key(&e), e.to_string());
    }
    Some(settings)
}

/// The `[check]` key a gate's error is about.
fn gate_error_key(e: &crate::sequential::GateError) -> &'static str {
    use crate::sequential::GateError;
    match e {
        GateError::Looks(_) => "check.looks",
        GateError::Futility(_) => "check.futility_beta",
        GateError::FutilityRho(_) => "check.futility_rho",
        GateError::Design(_) => "check.sequential",
    }
}

impl Plan {
    /// Whether filter `f` carries a covariance, so has consistency tests and a verdict: an
    /// outside filter's estimates do, and a built-in kind says whether it does.
    pub fn has_covariance(&self, f: &FilterPlan) -> bool {
        f.external
            || self
                .system
                .filters()
                .get(f.entry)
                .is_none_or(|i| i.has_covariance)
    }

    /// The sequential gate of `check.sequential` for this plan's runs per cell and
    /// consistency α (`None` without it); an error names the `[check]` key, as validation
    /// does (a `--runs` override can make the spec's looks invalid).
    pub fn check_gate(&self) -> Result<Option<crate::sequential::Gate>, SpecErrors> {
        let Some(settings) = &self.check_sequential else {
            return Ok(None);
        };
        let alpha = self.consistency.as_ref().map_or(self.alpha, |c| c.alpha);
        settings.gate(self.runs, alpha).map(Some).map_err(|e| {
            SpecErrors(vec![SpecError {
                file: self.spec_path.clone(),
                key_path: gate_error_key(&e).into(),
                message: format!("{e} (with {} runs per cell)", self.runs),
            }])
        })
    }
}
