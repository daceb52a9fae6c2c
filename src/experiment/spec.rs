//! Raw spec types mirroring the TOML file exactly (`deny_unknown_fields`). Code past
//! [`super::plan`] never sees these; validation turns them into a typed [`super::Plan`].

use serde::Deserialize;
use serde::de::{self, Deserializer, MapAccess, SeqAccess, Visitor};
use std::fmt;

pub(crate) use crate::system::spec_values::{OneOrMany, TableOf};

/// The whole experiment spec.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Spec {
    /// Experiment name (used in the manifest and default output folder).
    pub name: Option<String>,
    /// Free text for humans.
    pub description: Option<String>,
    /// Master seed from which every random stream is derived.
    pub master_seed: Option<u64>,
    /// Monte Carlo runs per cell.
    pub runs: Option<u64>,
    /// Output folder (relative paths are relative to the working directory).
    pub output: Option<String>,
    /// Number of runs per (scenario, noise scale) whose full trajectories are written.
    pub trace_runs: Option<u64>,
    /// The system (`kind`) and its own keys, which the system validates.
    pub model: toml::Table,
    /// Scenarios (at least one); `name` is generic, every other key belongs to the system.
    #[serde(default)]
    pub scenarios: Vec<toml::Table>,
    /// Filters (at least one).
    #[serde(default)]
    pub filters: Vec<FilterSpec>,
    /// The truth-noise sweep.
    pub noise: Option<TableOf<NoiseSpec>>,
    /// How the initial estimate is formed.
    pub initial_estimate: Option<TableOf<InitialEstimateSpec>>,
    /// Divergence thresholds.
    pub divergence: Option<TableOf<DivergenceSpec>>,
    /// Consistency tests (NEES/NIS χ², whiteness, bias) and their significance level.
    pub consistency: Option<TableOf<ConsistencySpec>>,
    /// Assertions for `kfmc check`.
    pub check: Option<TableOf<CheckSpec>>,
    /// `kfmc tune`'s method and tuned elements.
    pub tune: Option<TableOf<super::tune_spec::TuneSpec>>,
}

/// `[check]`
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CheckSpec {
    /// Replications of the whole study for the `rejection_rate` assertions (`kfmc check`
    /// then runs `kfmc power`; `--replications` overrides).
    pub replications: Option<usize>,
    /// The fraction of a cell's declared runs that may fail numerically before its cases are
    /// incomplete rather than judged (default 0: every declared run must complete).
    pub max_failed_runs: Option<f64>,
    /// Judge the consistency verdicts with a group-sequential gate: each cell stops at the
    /// first look that settles every verdict in it (default false).
    pub sequential: Option<bool>,
    /// The gate's looks: a count of even looks (default 10) or the run counts of the looks,
    /// increasing and ending at the study's runs.
    pub looks: Option<OneOrMany>,
    /// How the gate spends α over its looks: `obrien_fleming` (default; also spelled
    /// `obrien-fleming`, as the command's flag) or `pocock`.
    pub spending: Option<String>,
    /// Stop a consistent filter early: non-binding futility bounds spending β (also spelled
    /// `futility`, as the command's flag and the Python keyword).
    #[serde(alias = "futility")]
    pub futility_beta: Option<f64>,
    /// The exponent ρ of the futility bounds' β-spending β·t^ρ (default 2; 1 stops a
    /// consistent filter earlier).
    pub futility_rho: Option<f64>,
    /// The assertions (`[[check.assert]]`).
    #[serde(default, rename = "assert")]
    pub asserts: Vec<TableOf<AssertSpec>>,
}

/// `[[check.assert]]`
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AssertSpec {
    /// `consistent`, `white`, `unbiased`, `test_passes`, `rmse_below`, `no_worse_than` or
    /// `rejection_rate`.
    pub kind: String,
    /// Only this filter label (default: every filter).
    pub filter: Option<String>,
    /// Only this scenario (default: every scenario).
    pub scenario: Option<String>,
    /// The state (`rmse_below`; `unbiased` and `no_worse_than` default to every state).
    pub state: Option<String>,
    /// The bound (`rmse_below`: on the mean RMSE over runs; `rejection_rate`: the largest
    /// rate allowed).
    pub max: Option<f64>,
    /// The smallest rejection rate allowed (`rejection_rate`).
    pub min: Option<f64>,
    /// Only the filter variants with this Q multiplier.
    pub q_scale: Option<f64>,
    /// Only the filter variants with this R multiplier.
    pub r_scale: Option<f64>,
    /// The reference filter's label (`no_worse_than`).
    pub reference: Option<String>,
    /// The relative RMSE excess tolerated against the reference (`no_worse_than`; 0.1 = 10 %).
    pub margin: Option<f64>,
    /// Only the test at this run count (`rejection_rate`; the study's, or a subset's).
    pub runs: Option<usize>,
    /// What `min`/`max` bound (`rejection_rate`): `estimate` (default, the rate) or
    /// `interval` (the whole Clopper–Pearson 95 % interval must lie within the bounds).
    pub bound: Option<String>,
    /// A test name of consistency.parquet (`test_passes`).
    pub test: Option<String>,
    /// `pass` (default) or `fail`: a negative control, whose every case must fail, so a
    /// pipeline proves its gate catches a deliberately mistuned filter.
    pub expect: Option<String>,
}

/// `[consistency]`
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ConsistencySpec {
    /// Significance level α of every test (default 0.05).
    pub alpha: Option<f64>,
    /// Innovation-whiteness lags 1..=L (default 5).
    pub whiteness_lags: Option<u64>,
    /// Steps 1..=B left out of the whiteness sums (default 0).
    pub whiteness_burn_in: Option<u64>,
    /// The same tests again on the first `runs` runs at their own α (`[[consistency.subsets]]`).
    #[serde(default)]
    pub subsets: Vec<TableOf<ConsistencySubsetSpec>>,
    /// Also write every run's NEES and NIS at every step (`run_steps.parquet`; default false).
    pub per_step_runs: Option<bool>,
}

/// `[[consistency.subsets]]`: runs are seeded by their index, so the first N runs of a study
/// are exactly the runs an N-run study would make; one study can hold several (N, α) tests.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ConsistencySubsetSpec {
    /// N: the first N runs of every cell.
    pub runs: u64,
    /// α for this subset.
    pub alpha: f64,
}

/// `[[filters]]`: the generic keys; every other key goes to the filter kind's own parser.
#[derive(Debug, Deserialize)]
pub struct FilterSpec {
    /// Label in the tables' `filter` column.
    pub label: String,
    /// The filter kind (`kfmc list` shows each system's).
    pub kind: String,
    /// Multipliers of the assumed Q (a number, a list or a range): a sweep axis.
    pub q_scale: Option<Scales>,
    /// Multipliers of the assumed R: a sweep axis.
    pub r_scale: Option<Scales>,
    /// The kind's own keys.
    #[serde(flatten)]
    pub keys: toml::Table,
}

/// `[noise]`
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NoiseSpec {
    /// Truth-noise multipliers: a list or `{ start, stop, step }`.
    pub scales: Option<Scales>,
    /// `nominal` (filters keep their Q/R) or `matched` (filters' Q/R scale with the truth).
    pub filter_noise: Option<String>,
    /// `common` (a run sees the same standard normals at every multiplier) or `fresh`
    /// (every run and multiplier its own, as robustness.m draws them).
    pub draws: Option<String>,
}

/// `[initial_estimate]`
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct InitialEstimateSpec {
    /// `truth` (the seeds), `sampled` (x̂_0 ~ N(x_0, P_0)) or `batch_ls` (least squares on the
    /// run's measurements).
    pub mode: Option<String>,
    /// Standard deviations of P_0's diagonal (P_0 = I in the seeds).
    pub p0_std: Option<OneOrMany>,
}

/// `[divergence]`
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DivergenceSpec {
    /// RMSE threshold per state.
    pub rmse_thresholds: Option<OneOrMany>,
    /// A run that never crosses: `null` (censored, the default) or `largest_scale` (the largest
    /// multiplier tried, as robustness.m records it).
    pub never_crossed: Option<String>,
}

/// A list of noise scales or an arithmetic range.
#[derive(Debug, Clone, PartialEq)]
pub enum Scales {
    /// Explicit values.
    List(Vec<f64>),
    /// `start, start+step, …, ≤ stop`.
    Range {
        /// First value.
        start: f64,
        /// Last value (included when the grid reaches it).
        stop: f64,
        /// Increment.
        step: f64,
    },
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RangeSpec {
    start: f64,
    stop: f64,
    step: f64,
}

struct ScalesVisitor;

impl<'de> Visitor<'de> for ScalesVisitor {
    type Value = Scales;
    fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
        f.write_str("a number, a list of numbers or a table { start, stop, step }")
    }
    fn visit_f64<E: de::Error>(self, v: f64) -> Result<Scales, E> {
        Ok(Scales::List(vec![v]))
    }
    fn visit_i64<E: de::Error>(self, v: i64) -> Result<Scales, E> {
        Ok(Scales::List(vec![v as f64]))
    }
    fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Scales, A::Error> {
        let mut v = Vec::new();
        while let Some(x) = seq.next_element::<f64>()? {
            v.push(x);
        }
        Ok(Scales::List(v))
    }
    fn visit_map<A: MapAccess<'de>>(self, map: A) -> Result<Scales, A::Error> {
        let r = RangeSpec::deserialize(de::value::MapAccessDeserializer::new(map))?;
        Ok(Scales::Range {
            start: r.start,
            stop: r.stop,
            step: r.step,
        })
    }
}

impl<'de> Deserialize<'de> for Scales {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        d.deserialize_any(ScalesVisitor)
    }
}
