//! Validation: raw [`Spec`] → typed [`Plan`], reporting *every* problem with its key path.
//!
//! The generic part of a spec (runs, seeds, the noise sweep, filter labels and their Q/R scale
//! axes, consistency, check) is validated here; the system that `model.kind` names validates
//! the rest ([`crate::system::System::configure`]) into the same [`Checker`].

mod check;
mod consistency;
mod divergence;
mod filters;
mod model;
mod names;
mod noise;
mod sizes;
mod world;

use std::path::{Path, PathBuf};
use std::sync::Arc;

use super::spec::Spec;

use crate::error::{SpecError, SpecErrors};
use crate::sim::seed::hash_str;
use crate::system::checker::Checker;
pub(crate) use crate::system::settings::{ConsistencyPlan, FilterPlan, RunSettings, ScenarioPlan};
use crate::system::{Layout, Registry, SystemPlan, SystemSpec};

pub use check::{Assertion, Selection};
pub use filters::{EXTERNAL_KIND, expand_range};
pub use names::name_problem;

use check::{Targets, check_asserts, check_table};
use consistency::consistency_table;
use divergence::{never_crossed, rmse_thresholds};
use filters::{filter_tables, filter_variants};
use model::{initial_estimate_table, model_table};
use names::{experiment_name, figure_name_clashes, filter_labels, scenario_names};
use noise::noise_table;
use sizes::check_sizes;
use world::world_canonical;

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
    /// `[tune]`: `kfmc tune`'s method and elements, when the spec has the table.
    pub tune: Option<crate::experiment::tune_spec::TunePlan>,
    /// The binary that loaded the plan (its registry's [`crate::system::Program`]): its name
    /// and version go into the manifest beside kfmc's.
    pub program: crate::system::Program,
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

pub(crate) use crate::system::limits;

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
    let tune =
        crate::experiment::tune_spec::validate(&mut c, spec.tune.as_deref(), configured.as_deref());

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
            lanes: crate::runner::lanes::LanesMode::env_or_auto(),
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
        tune,
        program: registry.program(),
    })
}

/// What "is not …" says of a value that must be positive.
const POSITIVE: &str = "a positive number";

#[cfg(test)]
mod tests;
