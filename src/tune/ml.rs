//! `kfmc tune --method ml`: the maximum-likelihood estimate of named elements of Q and R from
//! the innovations alone (no truth), for linear systems, with 95 % intervals from the observed
//! information; writes `tuned.parquet`, `tune_trace.parquet` and `tuned.toml`.
//!
//! The data are the runs of the spec's own simulation (built in memory from its master seed:
//! the very measurements `kfmc simulate` writes) or a `measurements.parquet` in the layout
//! `kfmc simulate` writes (one run or many). The model (F, G, H, the untuned elements of Q
//! and R, and the prior) is the spec's.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::{Instant, SystemTime, UNIX_EPOCH};

use nalgebra::{DMatrix, DVector};

use super::estimate::{Estimate, SearchSettings, TraceRow, estimate};
use super::likelihood::{LinearModel, Parameter, Problem, Series};
pub use super::tables::TUNED_TOML;
use super::tables::{Timing, commit, tuned_toml};
use crate::error::{KfmcError, OutputError, SpecError, SpecErrors};
use crate::experiment::tune_spec::{NoiseMatrix, TuneElement, TuneMethod, parse_elements};
use crate::experiment::{InitialMode, Plan};
use crate::output::folder::StudyFolder;
use crate::output::manifest::StudyKind;
use crate::runner::RunObserver;
use crate::trial::Unit;

/// The fewest scalar measurements per tuned element: below it the likelihood's curvature,
/// and so the intervals, rest on too few innovations to mean anything.
pub const MIN_MEASUREMENTS_PER_ELEMENT: usize = 10;

/// What `kfmc tune --method ml` is given besides the plan.
#[derive(Clone, Debug, PartialEq)]
pub struct MlOptions {
    /// The elements (`--elements`), winning over `tune.elements`.
    pub elements: Option<Vec<String>>,
    /// A `measurements.parquet` to tune from instead of the spec's simulation.
    pub measurements: Option<PathBuf>,
    /// The search's settings.
    pub search: SearchSettings,
    /// Write into a non-empty folder that is not a kfmc study.
    pub force: bool,
    /// Worker threads (0 = all cores).
    pub threads: usize,
}

/// The result of an ML tuning.
#[derive(Clone, Debug, PartialEq)]
pub struct MlReport {
    /// The tuned elements, in the order of the tables.
    pub elements: Vec<TuneElement>,
    /// Each element's spec value (the start of the search).
    pub spec_values: Vec<f64>,
    /// The estimate and its intervals.
    pub estimate: Estimate,
    /// Q at the estimate (every other element at the spec's value).
    pub q: DMatrix<f64>,
    /// R at the estimate.
    pub r: DMatrix<f64>,
    /// Runs the likelihood summed over.
    pub runs: usize,
    /// Scalar measurements in them.
    pub measurements: usize,
    /// Where the data came from (`the spec's simulation …` or the file).
    pub data: String,
    /// The folder written.
    pub output: PathBuf,
}

pub(crate) fn spec_error(plan: &Plan, key_path: &str, message: String) -> KfmcError {
    KfmcError::Spec(SpecErrors(vec![SpecError {
        file: plan.spec_path.clone(),
        key_path: key_path.into(),
        message,
    }]))
}

/// The elements to tune by `method`: `flag` (the command line) when given, else
/// `tune.elements`.
pub fn elements_of(
    plan: &Plan,
    flag: Option<&[String]>,
    method: TuneMethod,
) -> Result<Vec<TuneElement>, KfmcError> {
    let layout = plan.layout();
    let (states, meas) = (layout.quantity_names(), layout.measurement_names());
    if let Some(list) = flag {
        let (found, problems) = parse_elements(list, &states, &meas);
        if let Some((i, m)) = problems.into_iter().next() {
            return Err(spec_error(plan, &format!("--elements[{i}]"), m));
        }
        if found.is_empty() {
            return Err(spec_error(
                plan,
                "--elements",
                "needs at least one element, e.g. q[px,px]".into(),
            ));
        }
        return Ok(found);
    }
    match plan.tune.as_ref().map(|t| &t.elements) {
        Some(e) if !e.is_empty() => Ok(e.clone()),
        _ => Err(spec_error(
            plan,
            "tune.elements",
            format!(
                "the {} method needs the elements to tune: `[tune] elements = [\"q[px,px]\", …]` in the spec or --elements",
                method.name()
            ),
        )),
    }
}

/// The model of a linear system as `method` tunes it: F, G, H and the truth's Q and R at
/// noise scale 1, with the elements' spec values checked (a log-parameter needs a positive
/// start).
pub fn linear_model(
    plan: &Plan,
    elements: &[TuneElement],
    method: TuneMethod,
) -> Result<LinearModel, KfmcError> {
    let fm = plan.system.filter_model().ok_or_else(|| {
        spec_error(
            plan,
            "model.kind",
            format!(
                "the {} system's world is not one model with additive noise: the {} method tunes linear systems",
                plan.kind,
                method.name()
            ),
        )
    })?;
    let (f, g, h) = fm.model.linear().ok_or_else(|| {
        spec_error(
            plan,
            "model.kind",
            format!(
                "the {} model is not linear: the {} method is built for linear-Gaussian systems{}",
                plan.kind,
                method.name(),
                match method {
                    TuneMethod::Ml => " (the EKF's quasi-likelihood is not built yet)",
                    _ => " (EKF support is not built yet)",
                }
            ),
        )
    })?;
    let dm =
        |m: &crate::model::exposed::DynMatrix| DMatrix::from_row_slice(m.rows, m.cols, &m.data);
    let model = LinearModel {
        f: dm(&f),
        g: dm(&g),
        h: dm(&h),
        q: dm(&fm.process_noise),
        r: dm(&fm.measurement_noise),
    };
    for (i, e) in elements.iter().enumerate() {
        let v = match e.matrix {
            NoiseMatrix::Q => model.q[(e.row, e.col)],
            NoiseMatrix::R => model.r[(e.row, e.col)],
        };
        if !(v > 0.0 && v.is_finite()) {
            return Err(spec_error(
                plan,
                &format!("tune.elements[{i}]"),
                format!(
                    "{} is {v} in the spec: a tuned element starts from its spec value, which must be positive",
                    e.name
                ),
            ));
        }
    }
    Ok(model)
}

/// The spec's own runs, simulated in memory: the measurements, inputs and priors `kfmc
/// simulate` writes, in its unit order (scenario, noise scale, run).
pub fn simulated_series(
    plan: &Plan,
    threads: usize,
    observer: &dyn RunObserver,
) -> Result<Vec<Series>, KfmcError> {
    Ok(simulated_runs(plan, threads, observer)?
        .into_iter()
        .map(|(s, _)| s)
        .collect())
}

/// [`simulated_series`] with each run's true quantities x_0..x_K (`n` per step, row by row):
/// the study engine's trial simulates every run once, from the seeds `kfmc run` uses, so
/// every candidate a search evaluates sees the same runs (common random numbers).
pub fn simulated_runs(
    plan: &Plan,
    threads: usize,
    observer: &dyn RunObserver,
) -> Result<Vec<(Series, Vec<f64>)>, KfmcError> {
    let mut world_only = plan.clone();
    world_only.filters.clear();
    world_only.trace_runs = plan.runs;
    world_only.consistency = None;
    world_only.rmse_thresholds = None;
    world_only.export_estimates = false;
    let trial = world_only.trial();
    let (n_scales, n_runs) = (plan.noise_scales.len(), plan.runs);
    let units = plan.scenarios.len() * n_scales * n_runs;
    let n = plan.layout().quantities.len();
    let p = plan.layout().measurements.len();
    let mut out = Vec::with_capacity(units);
    crate::runner::execute::<_, KfmcError>(
        units,
        threads,
        |i| {
            trial.run(&Unit {
                scenario: i / (n_scales * n_runs),
                scale: i / n_runs % n_scales,
                run: i % n_runs,
            })
        },
        observer,
        |r| {
            let tr = r.trace.ok_or_else(|| OutputError::Format {
                path: plan.spec_path.clone(),
                message: format!("the {} system gave no trajectories to tune on", plan.kind),
            })?;
            let (x0, p0) = tr.initial.ok_or_else(|| OutputError::Format {
                path: plan.spec_path.clone(),
                message: format!("the {} system gave no prior to start from", plan.kind),
            })?;
            let mut z = tr.z;
            // No sensor reports at step 0 (measurements.parquet has nulls there): the run
            // starts from its prior.
            for v in z.iter_mut().take(p) {
                *v = f64::NAN;
            }
            out.push((
                Series {
                    x0: DVector::from_vec(x0),
                    p0: from_lower_triangle(&p0, n),
                    u: tr.u,
                    z,
                },
                tr.truth,
            ));
            Ok(())
        },
    )?;
    Ok(out)
}

/// The full symmetric matrix of a lower triangle stored row by row ((0,0), (1,0), (1,1), …).
fn from_lower_triangle(tri: &[f64], n: usize) -> DMatrix<f64> {
    let mut m = DMatrix::zeros(n, n);
    let mut k = 0;
    for i in 0..n {
        for j in 0..=i {
            m[(i, j)] = tri[k];
            m[(j, i)] = tri[k];
            k += 1;
        }
    }
    m
}

/// The runs of a `measurements.parquet` in `kfmc simulate`'s layout: grouped by (scenario,
/// noise scale, run), each with its steps 0..K once. The prior of a run is its row of
/// `initial.parquet` beside the file when there is one, else the spec's: the scenario's x_0
/// (by name, or the spec's only scenario) and P_0 = diag(p0_std²).
pub fn file_series(plan: &Plan, path: &Path) -> Result<Vec<Series>, KfmcError> {
    let bad = |message: String| -> KfmcError {
        OutputError::Format {
            path: path.to_path_buf(),
            message,
        }
        .into()
    };
    let df = crate::output::table::read(path)?;
    let layout = plan.layout();
    let (meas, inputs, states) = (
        layout.measurement_names(),
        layout.input_names(),
        layout.quantity_names(),
    );
    let (p, nu, n) = (meas.len(), inputs.len(), states.len());
    let f64_col = |name: &str| -> Result<Vec<Option<f64>>, KfmcError> {
        let c = df.column(name).map_err(|_| {
            bad(format!(
                "has no column `{name}`; the {} model's measurements.parquet has scenario, noise_scale, run, step, {} and {}",
                plan.kind,
                meas.iter().map(|m| format!("z_{m}")).collect::<Vec<_>>().join(", "),
                if inputs.is_empty() { "no inputs".to_string() } else {
                    inputs.iter().map(|u| format!("u_{u}")).collect::<Vec<_>>().join(", ")
                }
            ))
        })?;
        let c = c
            .cast(&polars::prelude::DataType::Float64)
            .map_err(|_| bad(format!("column `{name}` is not numeric")))?;
        let c = c
            .f64()
            .map_err(|_| bad(format!("column `{name}` is not numeric")))?;
        Ok((0..c.len()).map(|i| c.get(i)).collect())
    };
    let extra: Vec<String> = df
        .get_column_names()
        .iter()
        .map(|c| c.to_string())
        .filter(|c| {
            (c.starts_with("z_") && !meas.iter().any(|m| format!("z_{m}") == *c))
                || (c.starts_with("u_") && !inputs.iter().any(|u| format!("u_{u}") == *c))
        })
        .collect();
    if !extra.is_empty() {
        return Err(bad(format!(
            "has columns the {} model does not have: {} (its measurements: {}; inputs: {})",
            plan.kind,
            extra.join(", "),
            meas.join(", "),
            inputs.join(", ")
        )));
    }
    let scenario = text_column(&df, "scenario").map_err(bad)?;
    let noise = f64_col("noise_scale")?;
    let run = f64_col("run")?;
    let step = f64_col("step")?;
    let z: Vec<Vec<Option<f64>>> = meas
        .iter()
        .map(|m| f64_col(&format!("z_{m}")))
        .collect::<Result<_, _>>()?;
    let u: Vec<Vec<Option<f64>>> = inputs
        .iter()
        .map(|m| f64_col(&format!("u_{m}")))
        .collect::<Result<_, _>>()?;
    type Key = (String, u64, i64);
    let mut groups: BTreeMap<Key, Vec<(i64, usize)>> = BTreeMap::new();
    for row in 0..df.height() {
        let (Some(s), Some(ns), Some(r), Some(k)) =
            (&scenario[row], noise[row], run[row], step[row])
        else {
            return Err(bad(format!(
                "row {row} has a null scenario, noise_scale, run or step"
            )));
        };
        groups
            .entry((s.clone(), ns.to_bits(), r as i64))
            .or_default()
            .push((k as i64, row));
    }
    let scales: std::collections::BTreeSet<u64> = groups.keys().map(|k| k.1).collect();
    if scales.len() > 1 {
        return Err(bad(format!(
            "holds {} noise scales ({}); the ml method estimates one world's Q and R: keep the rows of one noise_scale",
            scales.len(),
            scales
                .iter()
                .map(|b| f64::from_bits(*b).to_string())
                .collect::<Vec<_>>()
                .join(", ")
        )));
    }
    let priors = read_priors(plan, &path.with_file_name("initial.parquet"), n)?;
    let fm = plan.system.filter_model();
    let mut out = Vec::with_capacity(groups.len());
    for ((s, ns, r), mut rows) in groups {
        rows.sort();
        if rows.iter().enumerate().any(|(i, (k, _))| *k != i as i64) {
            return Err(bad(format!(
                "run {r} of scenario `{s}` does not have each step 0..K once (steps {}…)",
                rows.iter()
                    .take(5)
                    .map(|(k, _)| k.to_string())
                    .collect::<Vec<_>>()
                    .join(", ")
            )));
        }
        let mut zs = Vec::with_capacity(rows.len() * p);
        let mut us = Vec::with_capacity(rows.len() * nu);
        for &(k, row) in &rows {
            for col in &z {
                // Row 0 is the prior's: its z is null and never read.
                zs.push(if k == 0 {
                    f64::NAN
                } else {
                    col[row].unwrap_or(f64::NAN)
                });
            }
            for (j, col) in u.iter().enumerate() {
                us.push(col[row].ok_or_else(|| {
                    bad(format!(
                        "u_{} is null at step {k} of run {r} of scenario `{s}`",
                        inputs[j]
                    ))
                })?);
            }
        }
        let (x0, p0) = match priors.get(&(s.clone(), ns, r)) {
            Some(prior) => prior.clone(),
            None => {
                let fm = fm.as_ref().ok_or_else(|| {
                    bad("has no initial.parquet beside it, and the system gives no prior".into())
                })?;
                let start = match fm.initial_states.as_slice() {
                    [one] => one,
                    all => all.iter().find(|x| x.scenario == s).ok_or_else(|| {
                        bad(format!(
                            "scenario `{s}` is not one of the spec's ({}), and no initial.parquet beside the file gives its prior",
                            all.iter().map(|x| x.scenario.as_str()).collect::<Vec<_>>().join(", ")
                        ))
                    })?,
                };
                let c = &fm.initial_covariance;
                (
                    DVector::from_column_slice(&start.x0),
                    DMatrix::from_row_slice(c.rows, c.cols, &c.data),
                )
            }
        };
        out.push(Series {
            x0,
            p0,
            u: us,
            z: zs,
        });
    }
    if out.is_empty() {
        return Err(bad("has no rows".into()));
    }
    Ok(out)
}

/// A text column's values, or what is wrong with it.
fn text_column(df: &polars::prelude::DataFrame, name: &str) -> Result<Vec<Option<String>>, String> {
    let c = df
        .column(name)
        .map_err(|_| format!("has no column `{name}`"))?
        .str()
        .map_err(|_| format!("column `{name}` is not text"))?;
    Ok((0..c.len()).map(|i| c.get(i).map(str::to_string)).collect())
}

type Priors = BTreeMap<(String, u64, i64), (DVector<f64>, DMatrix<f64>)>;

/// The priors of `initial.parquet` (as `kfmc simulate` writes it), when the file exists.
fn read_priors(plan: &Plan, path: &Path, n: usize) -> Result<Priors, KfmcError> {
    let mut out = BTreeMap::new();
    if !path.is_file() {
        return Ok(out);
    }
    let bad = |message: String| -> KfmcError {
        OutputError::Format {
            path: path.to_path_buf(),
            message,
        }
        .into()
    };
    let df = crate::output::table::read(path)?;
    let states = plan.layout().quantity_names();
    let col = |name: &str| -> Result<Vec<Option<f64>>, KfmcError> {
        let c = df
            .column(name)
            .map_err(|_| {
                bad(format!(
                    "has no column `{name}` (the prior of the spec's model)"
                ))
            })?
            .cast(&polars::prelude::DataType::Float64)
            .map_err(|_| bad(format!("column `{name}` is not numeric")))?;
        let c = c
            .f64()
            .map_err(|_| bad(format!("column `{name}` is not numeric")))?;
        Ok((0..c.len()).map(|i| c.get(i)).collect())
    };
    let scenario = text_column(&df, "scenario").map_err(bad)?;
    let (noise, run) = (col("noise_scale")?, col("run")?);
    let est: Vec<Vec<Option<f64>>> = states
        .iter()
        .map(|s| col(&format!("est_{s}")))
        .collect::<Result<_, _>>()?;
    let mut tri = Vec::new();
    for (i, a) in states.iter().enumerate() {
        for b in &states[..=i] {
            tri.push(col(&format!("P_{a}_{b}"))?);
        }
    }
    for row in 0..df.height() {
        let missing = || bad(format!("row {row} has a null value"));
        let key = (
            scenario[row].clone().ok_or_else(missing)?,
            noise[row].ok_or_else(missing)?.to_bits(),
            run[row].ok_or_else(missing)? as i64,
        );
        let x0: Vec<f64> = est
            .iter()
            .map(|c| c[row].ok_or_else(missing))
            .collect::<Result<_, _>>()?;
        let p0: Vec<f64> = tri
            .iter()
            .map(|c| c[row].ok_or_else(missing))
            .collect::<Result<_, _>>()?;
        out.insert(key, (DVector::from_vec(x0), from_lower_triangle(&p0, n)));
    }
    Ok(out)
}

/// The parameters of the elements (diagonal elements: θ = ln of the element).
pub fn parameters(elements: &[TuneElement]) -> Vec<Parameter> {
    elements
        .iter()
        .map(|e| Parameter {
            matrix: e.matrix,
            index: e.row,
        })
        .collect()
}

/// Runs `f` on a pool of `threads` threads (0 = all cores), so the likelihood's runs and the
/// observed information's scores share it.
pub fn on_pool<T: Send>(threads: usize, f: impl FnOnce() -> T + Send) -> Result<T, KfmcError> {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .map_err(|source| KfmcError::ThreadPool { threads, source })?;
    Ok(pool.install(f))
}

/// What the search runs on: the elements, the model and the runs' data.
#[derive(Clone, Debug, PartialEq)]
pub struct Prepared {
    /// The tuned elements.
    pub elements: Vec<TuneElement>,
    /// Their parameters (θ = ln of each element).
    pub params: Vec<Parameter>,
    /// The model with the spec's Q and R.
    pub model: LinearModel,
    /// The runs.
    pub series: Vec<Series>,
    /// Where the data came from.
    pub data: String,
    /// Scalar measurements in the runs.
    pub measurements: usize,
    /// The spec file, for messages.
    pub spec_path: PathBuf,
}

impl Prepared {
    /// The likelihood of the data in the tuned parameters.
    pub fn problem(&self) -> Problem<'_> {
        Problem {
            model: &self.model,
            series: &self.series,
            params: &self.params,
        }
    }

    /// Maximises the likelihood on `threads` threads (0 = all cores); the result does not
    /// depend on the threads.
    pub fn search(
        &self,
        settings: &SearchSettings,
        threads: usize,
        on_iteration: &(dyn Fn(&TraceRow) + Sync),
    ) -> Result<Estimate, KfmcError> {
        let problem = self.problem();
        on_pool(threads, || estimate(&problem, settings, on_iteration))?.map_err(|e| {
            KfmcError::Spec(SpecErrors(vec![SpecError {
                file: self.spec_path.clone(),
                key_path: "tune.elements".into(),
                message: format!("the likelihood search on {} failed: {}", self.data, e.0),
            }]))
        })
    }
}

/// Reads the elements, the model and the data of an ML tuning, with every check that does
/// not need the search: the data's runs are simulated here when no file is given.
pub fn prepare(
    plan: &Plan,
    opts: &MlOptions,
    observer: &dyn RunObserver,
) -> Result<Prepared, KfmcError> {
    let elements = elements_of(plan, opts.elements.as_deref(), TuneMethod::Ml)?;
    let model = linear_model(plan, &elements, TuneMethod::Ml)?;
    let (series, data) = match &opts.measurements {
        Some(path) => (
            file_series(plan, path)?,
            format!("measurements of {}", path.display()),
        ),
        None => {
            if plan.initial == InitialMode::BatchLs {
                return Err(spec_error(
                    plan,
                    "initial_estimate.mode",
                    "is batch_ls: its prior is made of the measurements the likelihood scores; the ml method needs a prior from the spec (mode = \"sampled\" or \"truth\")".into(),
                ));
            }
            if plan.noise_scales.len() > 1 {
                return Err(spec_error(
                    plan,
                    "noise.scales",
                    format!(
                        "lists {} truth-noise scales: the ml method estimates one world's Q and R; give one scale",
                        plan.noise_scales.len()
                    ),
                ));
            }
            (
                simulated_series(plan, opts.threads, observer)?,
                format!(
                    "the spec's simulation: {} runs per scenario, master seed {}",
                    plan.runs, plan.master_seed
                ),
            )
        }
    };
    let p = model.h.nrows();
    let measurements: usize = series.iter().map(|s| s.measurements(p)).sum();
    let needed = MIN_MEASUREMENTS_PER_ELEMENT * elements.len();
    if measurements < needed {
        let key = if opts.elements.is_some() {
            "--elements"
        } else {
            "tune.elements"
        };
        return Err(spec_error(
            plan,
            key,
            format!(
                "{} elements need at least {needed} scalar measurements ({MIN_MEASUREMENTS_PER_ELEMENT} per element); {data} has {measurements}",
                elements.len()
            ),
        ));
    }
    Ok(Prepared {
        params: parameters(&elements),
        elements,
        model,
        series,
        data,
        measurements,
        spec_path: plan.spec_path.clone(),
    })
}

/// Tunes the elements of the plan by maximum likelihood and writes the study folder.
pub fn tune_ml(
    plan: &Plan,
    opts: &MlOptions,
    observer: &dyn RunObserver,
    on_iteration: &(dyn Fn(&TraceRow) + Sync),
) -> Result<MlReport, KfmcError> {
    let started = Instant::now();
    let started_unix_s = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_secs());
    let mut inputs = crate::study::inputs(plan);
    inputs.extend(opts.measurements.iter().cloned());
    let prepared = prepare(plan, opts, observer)?;
    // Locked before the search, so a second writer is refused before the work.
    let folder = StudyFolder::open_with(&plan.output, StudyKind::Tune, opts.force, &inputs)?;
    let problem = prepared.problem();
    let spec_values: Vec<f64> = problem.start().iter().map(|t| t.exp()).collect();
    let est = prepared.search(&opts.search, opts.threads, on_iteration)?;
    let (q, r) = problem.covariances(&est.theta);
    let Prepared {
        elements,
        model,
        series,
        data,
        measurements,
        ..
    } = &prepared;
    let text = tuned_toml(
        plan,
        TuneMethod::Ml,
        &format!("−ln L = {}", est.objective),
        elements,
        &est,
        model,
        &q,
        &r,
        data,
    );
    commit(
        plan,
        &folder,
        TuneMethod::Ml,
        elements,
        &est,
        Timing {
            started,
            started_unix_s,
            threads: opts.threads,
            force: opts.force,
        },
        &text,
    )?;
    Ok(MlReport {
        elements: elements.clone(),
        spec_values,
        estimate: est,
        q,
        r,
        runs: series.len(),
        measurements: *measurements,
        data: data.clone(),
        output: plan.output.clone(),
    })
}
