//! Validation: raw [`Spec`] → typed [`Plan`], reporting *every* problem with its key path.
//!
//! The generic part of a spec (runs, seeds, the noise sweep, filter labels and their Q/R scale
//! axes, consistency, check) is validated here; the system that `model.kind` names validates
//! the rest ([`crate::system::System::configure`]) into the same [`Checker`].

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use super::spec::{AssertSpec, OneOrMany, Scales, Spec};

use crate::error::{SpecError, SpecErrors};
use crate::sim::seed::hash_str;
use crate::system::checker::{Checker, non_negative, positive};
pub use crate::system::settings::{
    ConsistencyPlan, DeclaredScales, Draws, FilterNoiseMode, FilterPlan, InitialMode, RunSettings,
    ScenarioPlan,
};
use crate::system::{FilterTable, InitialSpec, Layout, Registry, System, SystemPlan, SystemSpec};

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

/// A validated, expanded experiment: the [`RunSettings`] a system's trial runs with, the
/// configured system, and what only the commands need (the spec, the output folder, the
/// assertions). It dereferences to its settings, so `plan.runs` reads `plan.settings.runs`.
#[derive(Clone, Debug)]
pub struct Plan {
    /// Experiment name.
    pub name: String,
    /// Description.
    pub description: Option<String>,
    /// The spec file.
    pub spec_path: PathBuf,
    /// The spec text, recorded in the manifest.
    pub spec_text: String,
    /// FNV-1a 64 hash of the spec text (hex).
    pub spec_hash: String,
    /// The canonical text of everything but the master seed that determines each run's
    /// truth, measurements and prior ([`Plan::world_stamp`] hashes it with the seed).
    pub world: String,
    /// `model.kind`: the system.
    pub kind: String,
    /// The configured system (world, filters, evaluated quantities).
    pub system: Arc<dyn SystemPlan>,
    /// What the system's trial needs: cells, filter variants, seeds, what each run records.
    pub settings: RunSettings,
    /// Output folder.
    pub output: PathBuf,
    /// Significance level of the per-step ANEES/ANIS bands in steps.parquet.
    pub alpha: f64,
    /// `kfmc check` assertions.
    pub assertions: Vec<Assertion>,
    /// `check.replications`: the replications of the `rejection_rate` assertions.
    pub check_replications: Option<usize>,
    /// `check.max_failed_runs`: the fraction of a cell's declared runs that may fail
    /// numerically before `kfmc check` calls its cases incomplete (default 0).
    pub check_max_failed_runs: f64,
    /// `check.sequential` and its keys: the gate `kfmc check` judges the verdicts with.
    pub check_sequential: Option<crate::sequential::GateSettings>,
    /// The gate this study runs under: each cell stops at the first look that settles
    /// every verdict in it. Set by `kfmc check` from [`Plan::check_sequential`] (for the
    /// study's run count); `kfmc run` leaves it `None` and runs every declared run.
    pub sequential: Option<crate::sequential::Gate>,
    /// `consistency.per_step_runs`: also write `run_steps.parquet`, every run's NEES and NIS
    /// at every step, for users who draw their own figures.
    pub per_step_runs: bool,
    /// Whether a run that never crosses its divergence threshold records the largest
    /// multiplier (`divergence.never_crossed = "largest_scale"`) instead of null.
    pub never_crossed_largest: bool,
}

impl std::ops::Deref for Plan {
    type Target = RunSettings;
    fn deref(&self) -> &RunSettings {
        &self.settings
    }
}

impl std::ops::DerefMut for Plan {
    fn deref_mut(&mut self) -> &mut RunSettings {
        &mut self.settings
    }
}

pub use crate::system::limits;

/// Command-line overrides of spec values.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Overrides {
    /// `--runs`
    pub runs: Option<usize>,
    /// `--seed`
    pub master_seed: Option<u64>,
    /// `--out`
    pub output: Option<PathBuf>,
    /// `--trace-runs`
    pub trace_runs: Option<usize>,
}

/// The size of a plan.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PlanSize {
    /// (scenario, noise scale) pairs.
    pub cells: usize,
    /// Simulated truths: cells × runs.
    pub runs: usize,
    /// Filter runs: runs × filters.
    pub filter_runs: usize,
    /// Filter steps in total.
    pub filter_steps: u64,
}

impl Plan {
    /// The executor of this plan's runs: the system's trial for its settings.
    pub fn trial(&self) -> Box<dyn crate::trial::Trial + '_> {
        self.system.trial(&self.settings)
    }

    /// `kfmc describe`'s analysis: the system's, or its layout alone when it offers none.
    pub fn describe(&self) -> crate::analysis::Description {
        let mut d = self.system.describe(&self.settings).unwrap_or_else(|| {
            let mut d = crate::system::describe::header(self.layout());
            d.notes.push(format!(
                "model.kind = \"{}\" offers no linearised analysis (its world is not one Model); \
                 the layout above is all kfmc describe can show",
                self.kind
            ));
            d
        });
        d.kind = self.kind.clone();
        d.experiment = self.name.clone();
        d.filter_model = self.system.filter_model().map(|m| m.record(self.layout()));
        d
    }

    /// What reading a recorded truth table for this study needs
    /// ([`crate::exchange::recorded`]): the scenarios, noise scales and runs it declares, and
    /// a `truth_<q>` column per quantity (`world_<w>` columns, as `kfmc simulate` writes them,
    /// are read past).
    pub fn truth_keys(&self) -> crate::exchange::recorded::RecordedKeys {
        let layout = self.layout();
        crate::exchange::recorded::RecordedKeys {
            table: "truth".into(),
            scenarios: (self.scenarios.iter())
                .map(|s| (s.name.clone(), s.steps))
                .collect(),
            noise_scales: self.noise_scales.clone(),
            runs: self.runs,
            groups: vec![crate::exchange::recorded::ValueGroup::truth(
                &layout.quantity_names(),
            )],
            ignored_prefixes: vec!["world_".into()],
        }
    }

    /// What reading estimates for this study needs: its keys and its world.
    pub fn study_keys(&self) -> crate::score::StudyKeys<'_> {
        let layout = self.layout();
        crate::score::StudyKeys {
            experiment: &self.name,
            world_stamp: self.world_stamp(),
            master_seed: self.master_seed,
            quantities: layout.quantity_names(),
            measurements: layout.measurement_names(),
            rotations: layout.rotations(),
            scenarios: self
                .scenarios
                .iter()
                .map(|s| (s.name.as_str(), s.steps))
                .collect(),
            noise_scales: &self.noise_scales,
            runs: self.runs,
            filters: self
                .filters
                .iter()
                .map(|f| crate::score::StudyFilter {
                    label: f.label.as_str(),
                    external: f.external,
                    multipliers: f.multipliers(),
                    q_column: f.external && f.declared.q_scale,
                    r_column: f.external && f.declared.r_scale,
                })
                .collect(),
        }
    }

    /// The columns of an estimates file for this plan (`kfmc schema estimates`): those of
    /// [`crate::score::estimate_columns_with`], with `q_scale` and `r_scale` after `filter`
    /// when an external filter declares variants on that axis or the export keys kfmc's own
    /// variants by it ([`Plan::export_variant_keys`]).
    pub fn estimate_schema(&self) -> Vec<crate::output::schema::ColumnDef> {
        let l = self.layout();
        let cols = crate::score::estimate_columns_with(
            &l.quantity_names(),
            &l.measurement_names(),
            &l.rotations(),
        );
        let keys = self.export_variant_keys();
        let axes = [0, 1].map(|axis| {
            self.filters
                .iter()
                .any(|f| f.external && [f.declared.q_scale, f.declared.r_scale][axis])
                || keys.iter().any(|k| k[axis].is_some())
        });
        crate::output::schema::with_variant_columns(cols, axes)
    }

    /// Per filter variant, what `kfmc run --export-estimates` writes in the estimates'
    /// `q_scale` and `r_scale` columns. A label of kfmc's with several variants names each
    /// row's variant on every axis where one of its variants is not 1: the axes its entry
    /// lists when declared `kind = "external"` with the same variants, and so the columns the
    /// reader then requires, and keys as this study did. A label with one variant names none
    /// (its rows are read as an external filter's without variants), nor does an external
    /// filter (its rows are scored, not exported).
    pub fn export_variant_keys(&self) -> Vec<[Option<f64>; 2]> {
        let axis_of = |f: &FilterPlan, axis: usize| [f.q_scale, f.r_scale][axis];
        self.filters
            .iter()
            .map(|f| {
                let same: Vec<&FilterPlan> =
                    self.filters.iter().filter(|g| g.label == f.label).collect();
                if f.external || same.len() < 2 {
                    return [None, None];
                }
                [0, 1].map(|axis| {
                    same.iter()
                        .any(|g| axis_of(g, axis) != 1.0)
                        .then_some(axis_of(f, axis))
                })
            })
            .collect()
    }

    /// The variants the estimates' `q_scale` (or `r_scale`, as `axis` names) column names,
    /// as `kfmc schema estimates` notes them: `` `mine` q_scale = 0.5, 1, 2 `` for each
    /// external label declaring variants on that axis and each label of kfmc's whose export
    /// keys them ([`Plan::export_variant_keys`]).
    pub fn external_variants_text(&self, axis: &str) -> Vec<String> {
        let a = usize::from(axis != "q_scale");
        let keys = self.export_variant_keys();
        let mut out: Vec<(String, Vec<f64>)> = Vec::new();
        for (f, key) in self.filters.iter().zip(&keys) {
            let declared = if f.external {
                [f.declared.q_scale, f.declared.r_scale][a]
            } else {
                key[a].is_some()
            };
            if !declared {
                continue;
            }
            let v = [f.q_scale, f.r_scale][a];
            match out.iter_mut().find(|(l, _)| *l == f.label) {
                Some((_, vs)) if !vs.contains(&v) => vs.push(v),
                Some(_) => {}
                None => out.push((f.label.clone(), vec![v])),
            }
        }
        out.into_iter()
            .map(|(l, vs)| {
                let vs: Vec<String> = vs.iter().map(|v| v.to_string()).collect();
                format!("`{l}` {axis} = {}", vs.join(", "))
            })
            .collect()
    }

    /// The stamp an estimates file made from this plan's runs carries
    /// ([`crate::score::stamp_metadata`]).
    pub fn stamp_metadata(&self) -> Vec<(String, String)> {
        crate::score::stamp_metadata(&self.world_stamp(), self.master_seed)
    }

    /// The file-level metadata kfmc writes into its table `name` of a study of this plan: the
    /// stamp on `estimates`, nothing on the others (their bytes do not depend on the world's
    /// description).
    pub fn table_metadata(&self, name: &str) -> Vec<(String, String)> {
        if name == "estimates" {
            self.stamp_metadata()
        } else {
            Vec::new()
        }
    }

    /// The system's names and Δt.
    pub fn layout(&self) -> &Layout {
        self.system.layout()
    }

    /// Sample time Δt (s).
    pub fn dt_s(&self) -> f64 {
        self.layout().dt_s
    }

    /// The evaluated quantities' names.
    pub fn quantity_names(&self) -> Vec<&str> {
        self.layout().quantity_names()
    }

    /// Keeps only the scenarios for which `keep(name)` holds (a smaller study of the same
    /// runs: seeds depend on the scenario's name, not its position).
    pub fn retain_scenarios(&mut self, keep: impl Fn(&str) -> bool) {
        self.scenarios.retain(|s| keep(&s.name));
    }

    /// Counts cells, runs and steps.
    pub fn size(&self) -> PlanSize {
        // Saturating: an absurd plan is refused by `check_limits`, never shown wrapped.
        let cells = self.scenarios.len().saturating_mul(self.noise_scales.len());
        let runs = cells.saturating_mul(self.runs);
        let steps: u64 = self
            .scenarios
            .iter()
            .map(|s| s.steps as u64)
            .fold(0u64, u64::saturating_add)
            .saturating_mul(
                (self.noise_scales.len() as u64)
                    .saturating_mul(self.runs as u64)
                    .saturating_mul(self.filters.len() as u64),
            );
        PlanSize {
            cells,
            runs,
            filter_runs: runs.saturating_mul(self.filters.len()),
            filter_steps: steps,
        }
    }

    /// Applies command-line overrides (they win over the spec).
    pub fn apply(&mut self, o: &Overrides) -> Result<(), SpecErrors> {
        let mut errs = Vec::new();
        if let Some(r) = o.runs {
            if r == 0 {
                errs.push(self.err("--runs", "must be at least 1"));
            } else if r as u64 > limits::MAX_RUNS {
                errs.push(self.err(
                    "--runs",
                    format!("{r} runs per cell; at most {}", limits::MAX_RUNS),
                ));
            }
            self.runs = r;
            // A subset of N ≥ the study's runs evaluates all of them: if the whole cell or an
            // earlier subset already evaluates those runs at that α, its rows would repeat
            // (two rows with one key, which every reader refuses).
            if let Some(c) = &self.settings.consistency {
                let mut seen = vec![(r, c.alpha)];
                for (i, &(n, alpha)) in c.subsets.iter().enumerate() {
                    let effective = (n.min(r), alpha);
                    if seen.contains(&effective) {
                        errs.push(self.err(
                            "--runs",
                            format!(
                                "with {r} runs per cell, consistency.subsets[{i}] ({n} runs at α = {alpha}) would repeat the evaluation of the first {} runs at that α; pass --runs above {n} or remove the subset",
                                effective.0
                            ),
                        ));
                    }
                    seen.push(effective);
                }
            }
        }
        if let Some(s) = o.master_seed {
            self.master_seed = s;
        }
        if let Some(p) = &o.output {
            self.output = p.clone();
        }
        if let Some(t) = o.trace_runs {
            self.trace_runs = t;
        }
        if self.trace_runs > self.runs {
            errs.push(self.err(
                "trace_runs",
                format!(
                    "{} traced runs but only {} runs",
                    self.trace_runs, self.runs
                ),
            ));
        }
        if errs.is_empty() {
            Ok(())
        } else {
            Err(SpecErrors(errs))
        }
    }

    /// The stamp of the simulated world: FNV-1a 64 (hex) of [`Plan::world`] and the master
    /// seed. Run i of two plans with one stamp has the same truth, measurements and prior,
    /// whatever their filters, run counts, comments or key order; an estimates file carries
    /// it as `kfmc.world_stamp` ([`Plan::stamp_metadata`]).
    pub fn world_stamp(&self) -> String {
        // A recorded world is its truth table: the table's content hash stands in.
        if let Some(truth) = &self.settings.truth {
            return truth.content_hash();
        }
        format!(
            "{:016x}",
            hash_str(&format!(
                "{}master_seed = {}\n",
                self.world, self.master_seed
            ))
        )
    }

    /// An error of this plan's spec at `key`.
    pub(crate) fn err(&self, key: &str, msg: impl Into<String>) -> SpecError {
        SpecError {
            file: self.spec_path.clone(),
            key_path: key.to_string(),
            message: msg.into(),
        }
    }
}

/// Expands `start, start+step, … ≤ stop`; values are rounded to 12 significant digits so a
/// grid like 0.2, 0.4, 0.6 prints as written rather than as 0.6000000000000001.
pub fn expand_range(start: f64, stop: f64, step: f64) -> Vec<f64> {
    let n = ((stop - start) / step + 1e-9).floor() as usize + 1;
    (0..n)
        .map(|i| {
            let v = start + i as f64 * step;
            if v == 0.0 || !v.is_finite() {
                return v;
            }
            // log10 of a subnormal is about −324, so the exponent stays far from overflow.
            let mag = 10f64.powi(11 - v.abs().log10().floor() as i32);
            let r = (v * mag).round() / mag;
            if r.is_finite() { r } else { v }
        })
        .collect()
}

/// Why a scenario name or filter label cannot be used, if it cannot. They are parts of
/// figure file names (`rmse_cases_<scenario>_<filter>.png`) and table keys, so only
/// `[A-Za-z0-9_.-]` is allowed: the name is then its own file-name part, with no path
/// separator, no `..`, nothing a file system changes, and no two names that map to one file.
pub fn name_problem(name: &str) -> Option<String> {
    let max = limits::MAX_NAME_CHARS;
    if name.is_empty() {
        return Some("must not be empty".into());
    }
    if let Some(bad) = name
        .chars()
        .find(|c| !(c.is_ascii_alphanumeric() || matches!(c, '_' | '.' | '-')))
    {
        return Some(format!(
            "`{}` contains {bad:?}; use only letters A-Z a-z, digits, `_`, `.` and `-` (names become file names)",
            name.escape_debug()
        ));
    }
    if name.starts_with('.') {
        return Some(format!(
            "`{name}` starts with `.`; names become file names, which would be hidden or `..`"
        ));
    }
    let n = name.chars().count();
    (n > max).then(|| format!("{n} characters; at most {max} (names become file names)"))
}

/// Expands a list or range of multipliers, checking each is `ok`; `None` gives `default`.
fn scale_list(
    c: &mut Checker,
    key: &str,
    v: Option<&Scales>,
    default: f64,
    ok: fn(f64) -> bool,
    what: &str,
) -> Vec<f64> {
    let mut out = match v {
        None => vec![default],
        Some(Scales::List(v)) => v.clone(),
        Some(Scales::Range { start, stop, step }) => {
            if !(positive(*step) && non_negative(*start) && stop.is_finite() && stop >= start) {
                c.err(key, "a range needs 0 ≤ start ≤ stop and step > 0");
                vec![default]
            } else if (stop - start) / step >= limits::MAX_SCALES as f64 {
                c.err(key, format!("more than {} values", limits::MAX_SCALES));
                vec![default]
            } else {
                expand_range(*start, *stop, *step)
            }
        }
    };
    if out.is_empty() {
        c.err(key, "at least one value is required");
    }
    if out.len() > limits::MAX_SCALES {
        c.err(
            key,
            format!("{} values; at most {}", out.len(), limits::MAX_SCALES),
        );
        out.truncate(1);
    }
    if let Some(bad) = out.iter().find(|x| !ok(**x)) {
        c.err(key, format!("{bad} is not {what}"));
    }
    out.sort_by(f64::total_cmp);
    if out.windows(2).any(|w| w[0] == w[1]) {
        c.err(key, "duplicate values");
    }
    out
}

/// Reports (scenario, filter) pairs whose figure `rmse_cases_<scenario>_<filter>` would be the
/// same file as another pair's: `a` with `b_c` and `a_b` with `c`. Names are only
/// `[A-Za-z0-9_.-]`, so `_` inside a name is the one way two pairs can meet.
fn figure_name_clashes(
    c: &mut Checker,
    spec: &Spec,
    names: &BTreeSet<String>,
    labels: &BTreeSet<String>,
) {
    let mut reported = BTreeSet::new();
    for long in names {
        for (at, _) in long.match_indices('_') {
            let (short, rest) = (&long[..at], &long[at + 1..]);
            if !names.contains(short) {
                continue;
            }
            // With long = short_rest: short_f1 and long_f2 are one string iff f1 = rest_f2.
            let prefix = format!("{rest}_");
            for f1 in labels.range(prefix.clone()..) {
                let Some(f2) = f1.strip_prefix(&prefix) else {
                    break;
                };
                if !labels.contains(f2) || !reported.insert(f1.clone()) {
                    continue;
                }
                let i = spec
                    .filters
                    .iter()
                    .position(|f| &f.label == f1)
                    .unwrap_or(0);
                c.err(
                    format!("filters[{i}].label"),
                    format!(
                        "scenario `{short}` with filter `{f1}` and scenario `{long}` with filter `{f2}` would share the figure rmse_cases_{short}_{f1}; rename one"
                    ),
                );
            }
        }
    }
}

/// Validates a parsed spec into a plan; `registry` supplies the system `model.kind` names.
pub fn validate(
    spec: Spec,
    path: &Path,
    text: &str,
    registry: &Registry,
) -> Result<Plan, SpecErrors> {
    validate_into(Checker::new(path, text), spec, registry)
}

/// [`validate`] into `c`, which may already hold problems found while reading the spec (they
/// come first and make the result an error, as any problem found here does).
///
/// One function per table of the spec, in the order of the messages; each reports into `c`
/// and returns what later tables need, so every independent problem is reported at once.
pub(crate) fn validate_into(
    mut c: Checker,
    mut spec: Spec,
    registry: &Registry,
) -> Result<Plan, SpecErrors> {
    let path = c.file().to_path_buf();
    let (kind, model, system) = model_table(&mut c, &spec, registry);
    if spec.scenarios.is_empty()
        && let Some(name) = system.and_then(|s| s.default_scenario())
    {
        let mut table = toml::Table::new();
        table.insert("name".into(), toml::Value::String(name.into()));
        spec.scenarios.push(table);
    }
    let presentation_keys: Vec<String> = system
        .map(|s| {
            s.presentation_keys()
                .iter()
                .map(|k| k.to_string())
                .collect()
        })
        .unwrap_or_default();
    let names = scenario_names(&mut c, &spec);
    let labels = filter_labels(&mut c, &spec);
    figure_name_clashes(&mut c, &spec, &names, &labels);
    let (system_index, filter_tables) = filter_tables(&mut c, &spec);
    let initial = initial_estimate_table(&mut c, &spec);
    let configured = system.and_then(|s| {
        let parts = SystemSpec {
            file: &path,
            model: &model,
            scenarios: &spec.scenarios,
            filters: &filter_tables,
            initial: &initial,
        };
        s.configure(&parts, &mut c)
    });
    let filters = filter_variants(&mut c, &spec, &system_index, configured.as_deref());
    let noise = noise_table(&mut c, &spec);
    let never_crossed_largest = never_crossed(&mut c, &spec);
    let states: Vec<String> = configured
        .as_ref()
        .map(|s| {
            let quantities = &s.layout().quantities;
            quantities.iter().map(|q| q.name.clone()).collect()
        })
        .unwrap_or_default();
    let rmse_thresholds = rmse_thresholds(&mut c, &spec, configured.is_some(), states.len());
    let runs = spec.runs.unwrap_or(100);
    // The shortest scenario bounds the whiteness burn-in.
    let shortest = configured.as_deref().and_then(|s| {
        s.scenarios()
            .iter()
            .min_by_key(|s| s.steps)
            .map(|s| (s.steps, s.name.clone()))
    });
    let consistency = consistency_table(&mut c, &spec, runs, shortest);
    let targets = Targets {
        spec: &spec,
        names: &names,
        labels: &labels,
        states: &states,
        system: configured.as_deref(),
        system_index: &system_index,
        variants: &filters,
        whiteness_lags: consistency.whiteness_lags,
    };
    let assertions = check_asserts(&mut c, &targets);
    let check = check_table(&mut c, &spec, runs as usize, consistency.alpha);
    check_sizes(&mut c, &spec, runs, filters.len(), configured.as_deref());
    let name = experiment_name(&mut c, &spec, &path);

    let system = match configured {
        Some(s) if c.is_clean() => s,
        _ => {
            // A system that refuses a spec without saying why would otherwise make an error
            // with no problem in it ("invalid spec (0 problems)").
            if c.is_clean() {
                c.err(
                    "model.kind",
                    format!("the {kind} system refused the spec without naming a problem (a bug in the system)"),
                );
            }
            return Err(SpecErrors(c.into_errors()));
        }
    };
    let text = c.text().to_string();
    // Keys that only say how results are shown do not make another world.
    let mut world_model = spec.model.clone();
    for key in &presentation_keys {
        world_model.remove(key);
    }
    let world = world_canonical(
        &kind,
        &world_model,
        &spec.scenarios,
        initial.mode,
        initial.p0_std.as_ref(),
        &noise.scales,
        noise.draws,
    );
    let output = spec
        .output
        .as_ref()
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from("results").join(&name));
    Ok(Plan {
        name,
        description: spec.description,
        spec_path: path,
        spec_hash: format!("{:016x}", hash_str(&text)),
        spec_text: text,
        world,
        kind,
        settings: RunSettings {
            scenarios: system
                .scenarios()
                .iter()
                .enumerate()
                .map(|(index, s)| ScenarioPlan {
                    name: s.name.clone(),
                    steps: s.steps,
                    index,
                })
                .collect(),
            filters,
            noise_scales: noise.scales,
            filter_noise: noise.filter_noise,
            initial: initial.mode,
            runs: runs as usize,
            master_seed: spec.master_seed.unwrap_or(0),
            draws: noise.draws,
            trace_runs: spec.trace_runs.unwrap_or(0) as usize,
            rmse_thresholds,
            consistency: consistency.plan,
            export_estimates: false,
            export_precision: crate::score::EstimatePrecision::F64,
            estimates: None,
            truth: None,
        },
        system,
        output,
        alpha: consistency.alpha,
        assertions,
        check_replications: check.replications,
        check_max_failed_runs: check.max_failed_runs,
        check_sequential: check.sequential,
        sequential: None,
        per_step_runs: spec
            .consistency
            .as_deref()
            .and_then(|c| c.per_step_runs)
            .unwrap_or(false),
        never_crossed_largest,
    })
}

/// `[model]`: the system `kind` names (`None` when it names none, which is reported), and the
/// rest of the table, which is the system's.
fn model_table<'r>(
    c: &mut Checker,
    spec: &Spec,
    registry: &'r Registry,
) -> (String, toml::Table, Option<&'r dyn System>) {
    let mut model = spec.model.clone();
    // `None` when kind is absent or not a string, which is reported here.
    let given = match model.remove("kind") {
        Some(toml::Value::String(k)) => Some(k),
        Some(other) => {
            c.err(
                "model.kind",
                format!("expected a string, got {}", other.type_str()),
            );
            None
        }
        None => {
            c.err("model.kind", "missing; `kfmc list` shows the systems");
            None
        }
    };
    let system = given.as_deref().and_then(|k| registry.get(k));
    if let Some(k) = &given
        && system.is_none()
    {
        c.err(
            "model.kind",
            format!(
                "unknown model `{k}`; expected one of: {}",
                registry.kinds().join(", ")
            ),
        );
    }
    (given.unwrap_or_default(), model, system)
}

/// `[[scenarios]]` names: present, usable as file names, unique (also ignoring case). The
/// rest of each table is the system's.
fn scenario_names(c: &mut Checker, spec: &Spec) -> BTreeSet<String> {
    if spec.scenarios.is_empty() {
        c.err("scenarios", "at least one [[scenarios]] entry is required");
    }
    let mut names = BTreeSet::new();
    let mut folded = BTreeSet::new();
    for (i, s) in spec.scenarios.iter().enumerate() {
        let key = format!("scenarios[{i}].name");
        match s.get("name") {
            Some(toml::Value::String(n)) => {
                if let Some(msg) = name_problem(n) {
                    c.err(key, msg);
                } else if !names.insert(n.clone()) {
                    c.err(key, format!("duplicate scenario name `{n}`"));
                } else if !folded.insert(n.to_ascii_lowercase()) {
                    c.err(
                        key,
                        format!("`{n}` differs from another scenario name only by case; their figures would be one file on case-insensitive file systems"),
                    );
                }
            }
            Some(_) => c.err(key, "expected a string"),
            None => c.err(key, "missing"),
        }
    }
    names
}

/// `[[filters]]` labels: usable as file names, unique (also ignoring case).
fn filter_labels(c: &mut Checker, spec: &Spec) -> BTreeSet<String> {
    if spec.filters.is_empty() {
        c.err("filters", "at least one [[filters]] entry is required");
    }
    let mut labels = BTreeSet::new();
    let mut folded = BTreeSet::new();
    for (i, f) in spec.filters.iter().enumerate() {
        let key = format!("filters[{i}].label");
        if let Some(msg) = name_problem(&f.label) {
            c.err(key, msg);
        } else if !labels.insert(f.label.clone()) {
            c.err(key, format!("duplicate filter label `{}`", f.label));
        } else if !folded.insert(f.label.to_ascii_lowercase()) {
            c.err(
                key,
                format!("`{}` differs from another filter label only by case; their figures would be one file on case-insensitive file systems", f.label),
            );
        }
    }
    labels
}

/// The `[[filters]]` entries the system validates. External filters are kfmc's, not the
/// system's: the system sees the others only, and `system_index[i]` is spec entry i's
/// position among them.
fn filter_tables(c: &mut Checker, spec: &Spec) -> (Vec<Option<usize>>, Vec<FilterTable>) {
    let mut system_index = Vec::with_capacity(spec.filters.len());
    let mut tables: Vec<FilterTable> = Vec::new();
    for (i, f) in spec.filters.iter().enumerate() {
        if f.kind == EXTERNAL_KIND {
            system_index.push(None);
            for k in f.keys.keys() {
                c.err(
                    format!("filters[{i}].{}", super::checker::path_key(k)),
                    "an external filter has no keys besides label, kind and its variants q_scale, r_scale (its settings are its own)",
                );
            }
        } else {
            system_index.push(Some(tables.len()));
            tables.push(FilterTable {
                key: format!("filters[{i}]"),
                label: f.label.clone(),
                kind: f.kind.clone(),
                keys: f.keys.clone(),
            });
        }
    }
    (system_index, tables)
}

/// `[initial_estimate]`: the mode is generic, P0 and any initialiser are the system's.
fn initial_estimate_table(c: &mut Checker, spec: &Spec) -> InitialSpec {
    let ie = spec.initial_estimate.as_deref();
    let mode = c.choice(
        "initial_estimate.mode",
        ie.and_then(|i| i.mode.as_deref()),
        "truth",
        &["truth", "sampled", "batch_ls"],
    );
    InitialSpec {
        mode: match mode {
            "sampled" => InitialMode::Sampled,
            "batch_ls" => InitialMode::BatchLs,
            _ => InitialMode::Truth,
        },
        present: ie.is_some(),
        p0_std: ie.and_then(|i| i.p0_std.clone()),
    }
}

/// The filter variants: each (q_scale, r_scale) pair of an entry, with the same label; the
/// scales are key columns of every table.
fn filter_variants(
    c: &mut Checker,
    spec: &Spec,
    system_index: &[Option<usize>],
    system: Option<&dyn SystemPlan>,
) -> Vec<FilterPlan> {
    let mut filters = Vec::new();
    for (i, f) in spec.filters.iter().enumerate() {
        let key = format!("filters[{i}]");
        let declared = DeclaredScales {
            q_scale: f.q_scale.is_some(),
            r_scale: f.r_scale.is_some(),
        };
        let q_key = format!("{key}.q_scale");
        let r_key = format!("{key}.r_scale");
        let Some(entry) = system_index[i] else {
            // An external filter's variants: the multipliers it applied to its own assumed
            // Q and R, named by its estimates' `q_scale`/`r_scale` columns.
            let q_scales = scale_list(c, &q_key, f.q_scale.as_ref(), 1.0, positive, POSITIVE);
            let r_scales = scale_list(c, &r_key, f.r_scale.as_ref(), 1.0, positive, POSITIVE);
            for &q_scale in &q_scales {
                for &r_scale in &r_scales {
                    filters.push(FilterPlan {
                        label: f.label.clone(),
                        kind: f.kind.clone(),
                        entry: usize::MAX,
                        external: true,
                        q_scale,
                        r_scale,
                        declared,
                    });
                }
            }
            continue;
        };
        if let Some(info) = system.and_then(|s| s.filters().get(entry)) {
            let msg = format!("not used by a {} filter", info.kind);
            c.reject_present(
                &key,
                &[
                    ("q_scale", f.q_scale.is_some() && !info.q_scale),
                    ("r_scale", f.r_scale.is_some() && !info.r_scale),
                ],
                &msg,
            );
        }
        let q_scales = scale_list(c, &q_key, f.q_scale.as_ref(), 1.0, positive, POSITIVE);
        let r_scales = scale_list(c, &r_key, f.r_scale.as_ref(), 1.0, positive, POSITIVE);
        for &q_scale in &q_scales {
            for &r_scale in &r_scales {
                filters.push(FilterPlan {
                    label: f.label.clone(),
                    kind: f.kind.clone(),
                    entry,
                    external: false,
                    q_scale,
                    r_scale,
                    declared,
                });
            }
        }
    }
    filters
}

/// What "is not …" says of a value that must be positive.
const POSITIVE: &str = "a positive number";

/// `[noise]` as validated.
struct Noise {
    scales: Vec<f64>,
    filter_noise: FilterNoiseMode,
    draws: Draws,
}

/// `[noise]`: the sweep of truth-noise multipliers, the filters' noise mode, the draws.
fn noise_table(c: &mut Checker, spec: &Spec) -> Noise {
    let noise = spec.noise.as_deref();
    let scales = scale_list(
        c,
        "noise.scales",
        noise.and_then(|n| n.scales.as_ref()),
        1.0,
        non_negative,
        "a non-negative number",
    );
    let filter_noise = c.choice(
        "noise.filter_noise",
        noise.and_then(|n| n.filter_noise.as_deref()),
        "nominal",
        &["nominal", "matched"],
    );
    let draws = c.choice(
        "noise.draws",
        noise.and_then(|n| n.draws.as_deref()),
        "common",
        &["common", "fresh"],
    );
    Noise {
        scales,
        filter_noise: if filter_noise == "matched" {
            FilterNoiseMode::Matched
        } else {
            FilterNoiseMode::Nominal
        },
        draws: if draws == "fresh" {
            Draws::Fresh
        } else {
            Draws::Common
        },
    }
}

/// `divergence.never_crossed`: whether a run that never crosses records the largest scale.
fn never_crossed(c: &mut Checker, spec: &Spec) -> bool {
    c.choice(
        "divergence.never_crossed",
        spec.divergence
            .as_deref()
            .and_then(|d| d.never_crossed.as_deref()),
        "null",
        &["null", "largest_scale"],
    ) == "largest_scale"
}

/// `divergence.rmse_thresholds`, one per evaluated quantity (`nq` of them).
fn rmse_thresholds(c: &mut Checker, spec: &Spec, configured: bool, nq: usize) -> Option<Vec<f64>> {
    let t = spec.divergence.as_deref()?.rmse_thresholds.as_ref()?;
    // Without a configured system the dimension is unknown; the values can still be
    // checked, so a second run of validate does not bring up a new error.
    let n = match (configured, t) {
        (false, super::spec::OneOrMany::Many(v)) => v.len(),
        (false, _) => 1,
        _ => nq,
    };
    Some(c.vector(
        "divergence.rmse_thresholds",
        Some(t),
        n,
        &vec![f64::INFINITY; n],
        positive,
        POSITIVE,
    ))
}

/// `[consistency]` as validated (also when the table is absent, for the steps' bands).
struct Consistency {
    alpha: f64,
    whiteness_lags: usize,
    /// The consistency tests, when the spec has the table.
    plan: Option<ConsistencyPlan>,
}

/// `[consistency]`: α, the whiteness lags and burn-in, and the subsets evaluated on the first
/// runs. `shortest`: the (steps, name) of the shortest scenario, when the system is known.
fn consistency_table(
    c: &mut Checker,
    spec: &Spec,
    runs: u64,
    shortest: Option<(usize, String)>,
) -> Consistency {
    let cs = spec.consistency.as_deref();
    let alpha = cs.and_then(|c| c.alpha).unwrap_or(0.05);
    if !(alpha > 0.0 && alpha < 1.0) {
        c.err("consistency.alpha", format!("{alpha} is not in (0, 1)"));
    }
    let whiteness_lags = cs
        .and_then(|c| c.whiteness_lags)
        .unwrap_or(ConsistencyPlan::DEFAULT_WHITENESS_LAGS as u64);
    if whiteness_lags > limits::MAX_WHITENESS_LAGS {
        c.err(
            "consistency.whiteness_lags",
            format!(
                "{whiteness_lags} lags; at most {}",
                limits::MAX_WHITENESS_LAGS
            ),
        );
    }
    let whiteness_burn_in = cs.and_then(|c| c.whiteness_burn_in).unwrap_or(0);
    if whiteness_burn_in > 0 && whiteness_lags == 0 {
        c.err(
            "consistency.whiteness_burn_in",
            "drops steps from a whiteness test that whiteness_lags = 0 does not compute",
        );
    }
    // Without a burn-in, lags beyond the run are the lags' business, not this key's.
    if let Some((steps, name)) = shortest
        && whiteness_burn_in > 0
        && whiteness_burn_in.saturating_add(whiteness_lags) >= steps as u64
    {
        c.err(
            "consistency.whiteness_burn_in",
            format!(
                "{whiteness_burn_in} steps dropped and {whiteness_lags} lags leave no lag pair in scenario {name:?} ({steps} steps)"
            ),
        );
    }
    let mut subsets = Vec::new();
    for (i, sub) in cs.iter().flat_map(|c| c.subsets.iter()).enumerate() {
        let key = format!("consistency.subsets[{i}]");
        if sub.runs < 2 || sub.runs > runs {
            c.err(
                format!("{key}.runs"),
                format!("{} is not in 2..={runs} (the study's runs)", sub.runs),
            );
        }
        if !(sub.alpha > 0.0 && sub.alpha < 1.0) {
            c.err(
                format!("{key}.alpha"),
                format!("{} is not in (0, 1)", sub.alpha),
            );
        }
        if subsets.contains(&(sub.runs as usize, sub.alpha))
            || (sub.runs == runs && sub.alpha == alpha)
        {
            c.err(key, "duplicates another (runs, alpha) evaluation");
        }
        subsets.push((sub.runs as usize, sub.alpha));
    }
    Consistency {
        alpha,
        whiteness_lags: whiteness_lags as usize,
        plan: cs.map(|_| ConsistencyPlan {
            alpha,
            whiteness_lags: whiteness_lags as usize,
            whiteness_burn_in: whiteness_burn_in as usize,
            subsets,
        }),
    }
}

/// What `[[check.assert]]` entries may name: the spec's scenarios, filters and states.
struct Targets<'a> {
    spec: &'a Spec,
    names: &'a BTreeSet<String>,
    labels: &'a BTreeSet<String>,
    states: &'a [String],
    /// The configured system; `None` when it was refused (checks that need it are skipped).
    system: Option<&'a dyn SystemPlan>,
    system_index: &'a [Option<usize>],
    /// The filter variants (label × q_scale × r_scale).
    variants: &'a [FilterPlan],
    /// `consistency.whiteness_lags` (its default without the table).
    whiteness_lags: usize,
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
fn check_asserts(c: &mut Checker, t: &Targets) -> Vec<Assertion> {
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
                format!("unknown value `{other}`; expected one of: consistent, white, unbiased, test_passes, rmse_below, no_worse_than, rejection_rate"),
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
struct CheckTable {
    replications: Option<usize>,
    max_failed_runs: f64,
    sequential: Option<crate::sequential::GateSettings>,
}

/// `[check]`'s own keys (a study of `runs` runs per cell, tests at level `alpha`).
fn check_table(c: &mut Checker, spec: &Spec, runs: usize, alpha: f64) -> CheckTable {
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
    t: &super::spec::CheckSpec,
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
        None | Some("obrien_fleming") => {}
        Some("pocock") => settings.spending = Spending::Pocock,
        Some(other) => c.err(
            "check.spending",
            format!(
                "`{other}` is not a spending function: expected \"obrien_fleming\" or \"pocock\""
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

/// The top level's counts within [`limits`]: runs, scenarios, filter variants, steps, and
/// `trace_runs` ≤ `runs`.
fn check_sizes(
    c: &mut Checker,
    spec: &Spec,
    runs: u64,
    variants: usize,
    system: Option<&dyn SystemPlan>,
) {
    if runs == 0 {
        c.err("runs", "must be at least 1");
    } else if runs > limits::MAX_RUNS {
        c.err(
            "runs",
            format!("{runs} runs per cell; at most {}", limits::MAX_RUNS),
        );
    }
    if spec.scenarios.len() > limits::MAX_ENTRIES {
        c.err(
            "scenarios",
            format!(
                "{} scenarios; at most {}",
                spec.scenarios.len(),
                limits::MAX_ENTRIES
            ),
        );
    }
    if variants > limits::MAX_ENTRIES {
        c.err(
            "filters",
            format!(
                "{variants} filter variants (entries × q_scale × r_scale values); at most {}",
                limits::MAX_ENTRIES
            ),
        );
    }
    for (i, sc) in system.iter().flat_map(|s| s.scenarios().iter()).enumerate() {
        if sc.steps as u64 > limits::MAX_STEPS {
            c.err(
                format!("scenarios[{i}]"),
                format!(
                    "{} steps (duration / Δt); at most {} per run",
                    sc.steps,
                    limits::MAX_STEPS
                ),
            );
        }
    }
    let trace_runs = spec.trace_runs.unwrap_or(0);
    if trace_runs > runs {
        c.err(
            "trace_runs",
            format!("{trace_runs} traced runs but only {runs} runs"),
        );
    }
}

/// `name`, or the file's name without it: a folder name of its own.
fn experiment_name(c: &mut Checker, spec: &Spec, path: &Path) -> String {
    let name = spec.name.clone().unwrap_or_else(|| {
        path.file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_else(|| "experiment".into())
    });
    if name.is_empty() || name == "." || name == ".." || name.contains(['/', '\\']) {
        // Without a `name` key the file's own name stands in: say so, at the file.
        let (key, what) = if spec.name.is_some() {
            ("name", String::new())
        } else {
            (
                "",
                format!("the experiment name (from the file name, `{name}`) "),
            )
        };
        c.err(
            key,
            format!(
                "{what}must be non-empty, not `.` or `..`, and contain no path separators; set name"
            ),
        );
    }
    name
}

/// The canonical text of a world (all of [`Plan::world`]): the system, its model table, the
/// scenarios (sorted, as a run's streams depend on its scenario's name, not its position),
/// the prior's settings, the noise multipliers and how their draws relate. Tables are written
/// with sorted keys and numbers by their bits, so neither comments, key order, formatting nor
/// `1` against `1.0` change it. Filters, run counts and the judging settings are left out:
/// they do not change what run i's world is.
fn world_canonical(
    kind: &str,
    model: &toml::Table,
    scenarios: &[toml::Table],
    initial: InitialMode,
    p0_std: Option<&super::spec::OneOrMany>,
    noise_scales: &[f64],
    draws: Draws,
) -> String {
    let mut model = model.clone();
    model.remove("kind");
    let mut scen: Vec<String> = scenarios
        .iter()
        .map(|s| canonical_value(&toml::Value::Table(s.clone())))
        .collect();
    scen.sort();
    let p0 = match p0_std {
        None => "default".to_string(),
        Some(super::spec::OneOrMany::One(v)) => canonical_f64(*v),
        Some(super::spec::OneOrMany::Many(v)) => {
            let items: Vec<String> = v.iter().map(|x| canonical_f64(*x)).collect();
            format!("[{}]", items.join(","))
        }
    };
    let scales: Vec<String> = noise_scales.iter().map(|x| canonical_f64(*x)).collect();
    format!(
        "kfmc world 1\nkind = {kind:?}\nmodel = {}\nscenarios = [{}]\ninitial = {initial:?}\np0_std = {p0}\nnoise_scales = [{}]\ndraws = {draws:?}\n",
        canonical_value(&toml::Value::Table(model)),
        scen.join(","),
        scales.join(","),
    )
}

/// A number by its bits (−0 as 0), so every spelling of one value gives one text.
fn canonical_f64(v: f64) -> String {
    let v = if v == 0.0 { 0.0 } else { v };
    format!("f{:016x}", v.to_bits())
}

/// A TOML value in one spelling: tables with sorted keys, integers that are exact floats as
/// those floats (a model parameter written `1` means `1.0`).
fn canonical_value(v: &toml::Value) -> String {
    match v {
        toml::Value::String(s) => format!("{s:?}"),
        toml::Value::Integer(i) => {
            let f = *i as f64;
            if f as i64 == *i && f.abs() < 9_007_199_254_740_992.0 {
                canonical_f64(f)
            } else {
                format!("i{i}")
            }
        }
        toml::Value::Float(f) => canonical_f64(*f),
        toml::Value::Boolean(b) => b.to_string(),
        toml::Value::Datetime(d) => format!("d{d}"),
        toml::Value::Array(a) => {
            let items: Vec<String> = a.iter().map(canonical_value).collect();
            format!("[{}]", items.join(","))
        }
        toml::Value::Table(t) => {
            let mut items: Vec<(&String, String)> =
                t.iter().map(|(k, v)| (k, canonical_value(v))).collect();
            items.sort_by(|a, b| a.0.cmp(b.0));
            let items: Vec<String> = items
                .into_iter()
                .map(|(k, v)| format!("{k:?}={v}"))
                .collect();
            format!("{{{}}}", items.join(","))
        }
    }
}

/// The `kind` of a `[[filters]]` entry whose estimates come from outside kfmc.
pub const EXTERNAL_KIND: &str = "external";

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn range_matches_the_seed_sweep() {
        let v = expand_range(0.2, 50.0, 0.2);
        assert_eq!(v.len(), 250);
        assert_eq!(v[0], 0.2);
        assert_eq!(v[2], 0.6);
        assert_eq!(*v.last().unwrap(), 50.0);
    }

    const WORLD: &str = r#"
name = "stamp"
master_seed = 7
runs = 12
[model]
kind = "linear_quadrotor"
sensor = "positions"
[[scenarios]]
name = "hover"
x0 = [1.0, 0.0, 1.0, 0.0, 1.0, 0.0]
duration_s = 5.0
[[scenarios]]
name = "drift"
x0 = [0.0, 0.5, 0.0, -0.5, 2.0, 0.0]
duration_s = 3.0
[noise]
scales = [1.0, 3.0]
[[filters]]
label = "kf"
kind = "ekf"
[initial_estimate]
mode = "sampled"
p0_std = 1.0
"#;

    fn stamp(text: &str) -> String {
        crate::experiment::parse(text, Path::new("stamp.toml"))
            .expect("a valid spec")
            .world_stamp()
    }

    #[test]
    fn the_world_stamp_ignores_what_does_not_change_the_world() {
        let base = stamp(WORLD);
        // Comments, layout, key order and number spelling.
        let reformatted = WORLD
            .replace("[model]\n", "# the truth\n[model]   # here\n")
            .replace(
                "kind = \"linear_quadrotor\"\nsensor = \"positions\"",
                "sensor = 'positions'\nkind    =   \"linear_quadrotor\"",
            )
            .replace("duration_s = 5.0", "duration_s = 5");
        assert_ne!(reformatted, WORLD);
        assert_eq!(stamp(&reformatted), base);
        // The filters, the run count, the name and the judging settings.
        let filters = WORLD
            .replace("kind = \"ekf\"", "kind = \"external\"")
            .replace("runs = 12", "runs = 3\ntrace_runs = 1")
            .replace("name = \"stamp\"", "name = \"other\"")
            + "[[filters]]\nlabel = \"sqrt\"\nkind = \"sqrt\"\n[consistency]\nalpha = 0.01\n";
        assert_eq!(stamp(&filters), base);
        // Scenario order: a run's streams follow its scenario's name.
        let (head, rest) = WORLD.split_once("[[scenarios]]").unwrap();
        let (hover, rest) = rest.split_once("[[scenarios]]").unwrap();
        let (drift, tail) = rest.split_once("[noise]").unwrap();
        let swapped = format!("{head}[[scenarios]]{drift}[[scenarios]]{hover}[noise]{tail}");
        assert_eq!(stamp(&swapped), base);
    }

    #[test]
    fn the_world_stamp_follows_what_changes_the_world() {
        let base = stamp(WORLD);
        for (from, to) in [
            ("master_seed = 7", "master_seed = 8"),
            ("scales = [1.0, 3.0]", "scales = [1.0, 2.0]"),
            (
                "scales = [1.0, 3.0]",
                "scales = [1.0, 3.0]\ndraws = \"fresh\"",
            ),
            ("duration_s = 5.0", "duration_s = 4.0"),
            ("x0 = [1.0, 0.0,", "x0 = [1.5, 0.0,"),
            ("name = \"drift\"", "name = \"drift2\""),
            ("p0_std = 1.0", "p0_std = 2.0"),
            ("mode = \"sampled\"", "mode = \"truth\""),
            (
                "sensor = \"positions\"",
                "sensor = \"positions\"\nmeasurement_noise_std = 0.2",
            ),
        ] {
            let changed = WORLD.replace(from, to);
            assert_ne!(changed, WORLD, "{from}");
            assert_ne!(stamp(&changed), base, "{from} → {to} kept the stamp");
        }
        // The seed override (`--seed`) changes it as the spec's key does.
        let mut plan = crate::experiment::parse(WORLD, Path::new("stamp.toml")).unwrap();
        plan.master_seed = 8;
        assert_eq!(
            plan.world_stamp(),
            stamp(&WORLD.replace("master_seed = 7", "master_seed = 8"))
        );
    }
}
