//! `kfmc tune --method truth`: named diagonal elements of a filter's Q and R from a simulated
//! study whose truth is known, by identifying conditions solved in the least-squares sense
//! ([`super::conditions`]), with 95 % intervals from the M-estimator sandwich over the runs;
//! writes `tuned.parquet`, `tune_trace.parquet` and `tuned.toml` as `ml` does.
//!
//! The runs are the spec's own, simulated once in memory by the study engine's trial from the
//! master seed (the very runs `kfmc run` scores), and every candidate (Q, R) is filtered over
//! those same runs: common random numbers, no table per candidate. The filter is the linear
//! Kalman filter of the spec's F, G, H (what kfmc's filters run on a linear model), with the
//! candidate's Q and R in place of the spec's: the study engine's filters take Q and R from the
//! model with one multiplier each, so an element-wise candidate runs in this module's loop.

use std::path::PathBuf;
use std::time::{Instant, SystemTime, UNIX_EPOCH};

use nalgebra::DMatrix;

use super::conditions::{Conditions, TruthObjective, TruthRun, sandwich};
use super::estimate::{
    Estimate, FlatDirection, MIN_INFO, Minimum, SearchSettings, TraceRow, intervals, minimise,
};
use super::likelihood::{LinearModel, Parameter};
use super::ml::{elements_of, linear_model, on_pool, parameters, simulated_runs, spec_error};
use super::tables::{Timing, commit, tuned_toml};
use crate::error::{KfmcError, SpecError, SpecErrors};
use crate::experiment::tune_spec::{NoiseMatrix, TuneElement, TuneMethod};
use crate::experiment::{InitialMode, Plan};
use crate::output::folder::StudyFolder;
use crate::output::manifest::StudyKind;
use crate::runner::RunObserver;

/// What `kfmc tune --method truth` is given besides the plan.
#[derive(Clone, Debug, PartialEq)]
pub struct TruthOptions {
    /// The elements (`--elements`), winning over `tune.elements`.
    pub elements: Option<Vec<String>>,
    /// The conditions (`--objective consistency|mse`).
    pub objective: TruthObjective,
    /// The search's settings.
    pub search: SearchSettings,
    /// Write into a non-empty folder that is not a kfmc study.
    pub force: bool,
    /// Worker threads (0 = all cores).
    pub threads: usize,
}

/// What the search runs on: the elements, the model and the simulated runs.
#[derive(Clone, Debug, PartialEq)]
pub struct TruthPrepared {
    /// The tuned elements.
    pub elements: Vec<TuneElement>,
    /// Their parameters (θ = ln of each element).
    pub params: Vec<Parameter>,
    /// The model with the spec's Q and R (the truth's, at noise scale 1).
    pub model: LinearModel,
    /// The runs with their truth.
    pub runs: Vec<TruthRun>,
    /// The conditions.
    pub objective: TruthObjective,
    /// Where the runs came from.
    pub data: String,
    /// The spec file, for messages.
    pub spec_path: PathBuf,
}

/// The result of a truth tuning.
#[derive(Clone, Debug, PartialEq)]
pub struct TruthReport {
    /// The tuned elements, in the order of the tables.
    pub elements: Vec<TuneElement>,
    /// Each element's spec value (the start of the search).
    pub spec_values: Vec<f64>,
    /// The estimate, its intervals and its identifiability.
    pub estimate: Estimate,
    /// The conditions' mean ḡ at the estimate (one per element; 0 at an exact root).
    pub residuals: Vec<f64>,
    /// What the identifiability report adds in words (e.g. the scale `mse` cannot fix).
    pub notes: Vec<String>,
    /// Q at the estimate (every other element at the spec's value).
    pub q: DMatrix<f64>,
    /// R at the estimate.
    pub r: DMatrix<f64>,
    /// Runs the conditions averaged over.
    pub runs: usize,
    /// Where the runs came from.
    pub data: String,
    /// The folder written.
    pub output: PathBuf,
}

/// Reads the elements and the model of a truth tuning and simulates its runs, with every
/// check that does not need the search.
pub fn prepare(
    plan: &Plan,
    opts: &TruthOptions,
    observer: &dyn RunObserver,
) -> Result<TruthPrepared, KfmcError> {
    let method = TuneMethod::Truth;
    let elements = elements_of(plan, opts.elements.as_deref(), method)?;
    let model = linear_model(plan, &elements, method)?;
    if plan.initial != InitialMode::Sampled {
        return Err(spec_error(
            plan,
            "initial_estimate.mode",
            "the truth method's conditions E[e²/P] = 1 hold at every step only when the prior is the distribution of x_0 given x̂_0: set mode = \"sampled\" (with p0_std)".into(),
        ));
    }
    if plan.noise_scales.len() > 1 {
        return Err(spec_error(
            plan,
            "noise.scales",
            format!(
                "lists {} truth-noise scales: the truth method estimates one world's Q and R; give one scale",
                plan.noise_scales.len()
            ),
        ));
    }
    let units = plan.scenarios.len() * plan.runs;
    let needed = elements.len() + 2;
    if units < needed {
        return Err(spec_error(
            plan,
            "runs",
            format!(
                "{} runs for {} elements: the sandwich intervals need the covariance of the conditions across at least {needed} runs (elements + 2)",
                units,
                elements.len()
            ),
        ));
    }
    let runs: Vec<TruthRun> = simulated_runs(plan, opts.threads, observer)?
        .into_iter()
        .map(|(series, truth)| TruthRun { series, truth })
        .collect();
    let p = model.h.nrows();
    for e in elements.iter().filter(|e| e.matrix == NoiseMatrix::R) {
        if runs.iter().any(|r| {
            !r.series
                .z
                .chunks(p)
                .skip(1)
                .any(|step| step[e.row].is_finite())
        }) {
            return Err(spec_error(
                plan,
                "tune.elements",
                format!(
                    "{}: its measurement component never reports in some run, so its condition E[ν²/S] = 1 has no data",
                    e.name
                ),
            ));
        }
    }
    Ok(TruthPrepared {
        params: parameters(&elements),
        elements,
        model,
        data: format!(
            "the spec's simulation: {} runs per scenario, master seed {}",
            plan.runs, plan.master_seed
        ),
        runs,
        objective: opts.objective,
        spec_path: plan.spec_path.clone(),
    })
}

impl TruthPrepared {
    /// The conditions of the runs (`None` when the spec's values make no valid filter).
    pub fn conditions(&self) -> Option<Conditions<'_>> {
        Conditions::new(&self.model, &self.runs, &self.params, self.objective)
    }

    fn failed(&self, message: String) -> KfmcError {
        KfmcError::Spec(SpecErrors(vec![SpecError {
            file: self.spec_path.clone(),
            key_path: "tune.elements".into(),
            message: format!("the truth search on {} failed: {message}", self.data),
        }]))
    }

    /// Solves the conditions on `threads` threads (0 = all cores) and forms the sandwich
    /// intervals and the identifiability report; the result does not depend on the threads.
    pub fn search(
        &self,
        settings: &SearchSettings,
        threads: usize,
        on_iteration: &(dyn Fn(&TraceRow) + Sync),
    ) -> Result<(Estimate, Vec<f64>, Vec<String>), KfmcError> {
        let conditions = self.conditions().ok_or_else(|| {
            self.failed(
                "the spec's values make an innovation covariance S not positive definite".into(),
            )
        })?;
        on_pool(threads, || self.solve(&conditions, settings, on_iteration))?
    }

    fn solve(
        &self,
        conditions: &Conditions<'_>,
        settings: &SearchSettings,
        on_iteration: &(dyn Fn(&TraceRow) + Sync),
    ) -> Result<(Estimate, Vec<f64>, Vec<String>), KfmcError> {
        let Minimum {
            theta,
            objective,
            best_start,
            converged,
            at_bound,
            trace,
        } = minimise(conditions, settings, on_iteration).map_err(|e| self.failed(e.0))?;
        let near = "the conditions cannot be evaluated at the estimate";
        let per_run = conditions
            .per_run(&theta)
            .ok_or_else(|| self.failed(near.into()))?;
        let j = conditions
            .jacobian(&theta)
            .ok_or_else(|| self.failed(near.into()))?;
        let jtj = j.transpose() * &j;
        let (_, mut identifiable, mut flat) = intervals(&jtj);
        let mut notes = Vec::new();
        if self.objective == TruthObjective::Mse {
            notes.push(
                "the mse objective cannot fix an absolute scale of Q and R: the gain depends on them only through their ratios, so only the untuned elements (and P₀'s transient) set the scale"
                    .to_string(),
            );
            if self.scale_is_free() {
                let m = theta.len();
                let unit = 1.0 / (m as f64).sqrt();
                let along = DMatrix::from_element(m, 1, unit);
                let info = (along.transpose() * &jtj * &along)[(0, 0)];
                identifiable.iter_mut().for_each(|b| *b = false);
                flat.push(FlatDirection {
                    eigenvalue: info,
                    largest: nalgebra::SymmetricEigen::new(jtj.clone()).eigenvalues.max(),
                    components: vec![unit; m],
                });
                notes.push(
                    "every non-zero element of Q and R is tuned: their common scale is not identified by the MSE, and no element gets an interval; fix one element (leave it out of the list) or use --objective consistency"
                        .to_string(),
                );
            }
        }
        let cov = sandwich(&per_run, &j, MIN_INFO);
        let se_log = (0..theta.len())
            .map(|i| identifiable[i].then(|| cov[(i, i)].max(0.0).sqrt()))
            .collect();
        let residuals = conditions.mean(&theta).map_or_else(
            || vec![f64::NAN; theta.len()],
            |g| g.iter().copied().collect(),
        );
        Ok((
            Estimate {
                theta,
                objective,
                best_start,
                converged,
                observed: jtj,
                se_log,
                identifiable,
                at_bound,
                flat,
                trace,
            },
            residuals,
            notes,
        ))
    }

    /// Whether every non-zero element of Q and R is tuned: then scaling all of them together
    /// leaves the gain, and so the MSE, unchanged (up to P₀'s transient).
    fn scale_is_free(&self) -> bool {
        let tuned = |m: NoiseMatrix, i: usize, j: usize| {
            i == j && self.elements.iter().any(|e| e.matrix == m && e.row == i)
        };
        let fixed_nonzero = |mat: &DMatrix<f64>, m: NoiseMatrix| {
            (0..mat.nrows())
                .any(|i| (0..mat.ncols()).any(|j| mat[(i, j)] != 0.0 && !tuned(m, i, j)))
        };
        !fixed_nonzero(&self.model.q, NoiseMatrix::Q)
            && !fixed_nonzero(&self.model.r, NoiseMatrix::R)
    }
}

/// Tunes the elements of the plan against its simulated truth and writes the study folder.
pub fn tune_truth(
    plan: &Plan,
    opts: &TruthOptions,
    observer: &dyn RunObserver,
    on_iteration: &(dyn Fn(&TraceRow) + Sync),
) -> Result<TruthReport, KfmcError> {
    let started = Instant::now();
    let started_unix_s = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_secs());
    let inputs = crate::study::inputs(plan);
    let prepared = prepare(plan, opts, observer)?;
    // Locked before the search, so a second writer is refused before the work.
    let folder = StudyFolder::open_with(&plan.output, StudyKind::Tune, opts.force, &inputs)?;
    let (est, residuals, notes) = prepared.search(&opts.search, opts.threads, on_iteration)?;
    let conditions = prepared
        .conditions()
        .ok_or_else(|| prepared.failed("the spec's values make no valid filter".into()))?;
    let spec_values: Vec<f64> = super::estimate::Objective::start(&conditions)
        .iter()
        .map(|t| t.exp())
        .collect();
    let (q, r) = conditions.covariances(&est.theta);
    let objective = match opts.objective {
        TruthObjective::Consistency => {
            format!("½|ḡ|² of the consistency conditions = {:e}", est.objective)
        }
        TruthObjective::Mse => format!("mean normalised MSE = {}", est.objective),
    };
    let text = tuned_toml(
        plan,
        TuneMethod::Truth,
        &objective,
        &prepared.elements,
        &est,
        &prepared.model,
        &q,
        &r,
        &prepared.data,
    );
    commit(
        plan,
        &folder,
        TuneMethod::Truth,
        &prepared.elements,
        &est,
        Timing {
            started,
            started_unix_s,
            threads: opts.threads,
            force: opts.force,
        },
        &text,
    )?;
    Ok(TruthReport {
        elements: prepared.elements.clone(),
        spec_values,
        estimate: est,
        residuals,
        notes,
        q,
        r,
        runs: prepared.runs.len(),
        data: prepared.data.clone(),
        output: plan.output.clone(),
    })
}
