//! `kfmc tune`: the methods that tune a filter's noise covariances.
//!
//! * `consistency` (this file, the default): searches a filter's Q scale (and R scale, when
//!   asked) for consistency or for minimum RMSE, on a grid.
//! * `ml` ([`ml`]): the maximum-likelihood estimate of named elements of Q and R from the
//!   innovations alone ([`likelihood`]), with intervals from the observed information
//!   ([`estimate`]), for linear systems.
//! * `truth` ([`truth`]): named elements of Q and R from a simulated study whose truth is
//!   known, by identifying conditions ([`conditions`]: E[e_i²/P_ii] = 1, E[ν_j²/S_jj] = 1, or
//!   the least MSE) on common random numbers, with sandwich intervals, for linear systems.
//!
//! `ml` and `truth` share the search and the identifiability report ([`estimate`]) and what
//! they write ([`tables`]).
//!
//! The `consistency` search: each stage is an ordinary study whose filter variants are the
//! candidate scales, so every candidate sees the same truths and measurements (paired
//! comparison) and the stage's tables are kept for inspection. Stage 1 is a coarse log grid
//! (half-decades from 10⁻³ to 10³: 13 points, or 13 × 13 with the R scale); stage 2 refines
//! around the best point (±½ decade: 11 points, or 7 × 7),
//! separately for each truth-noise scale, because each scale has its own best tuning (the
//! seeds' noise cases are four different truths).
//!
//! Objectives, averaged over the spec's scenarios and noise scales:
//! * `consistency`: |ln(Ā_NEES/n)| + |ln(Ā_NIS/p)|, the run-and-time averages after burn-in
//!   (zero for a perfectly calibrated filter);
//! * `rmse`: Σ_states RMSE_state / min over the candidates of RMSE_state, so every state
//!   counts equally whatever its units.
//!
//! The two-scalar search has two equations: with more unknowns it is flat along a set of
//! solutions (only the overall balance of Q against R is fixed), which is why `ml` exists.

pub mod conditions;
pub mod estimate;
pub mod likelihood;
pub mod ml;
pub mod tables;
pub mod truth;

use std::collections::BTreeMap;
use std::path::PathBuf;

use crate::error::{KfmcError, OutputError};
use crate::experiment::plan::ConsistencyPlan;
use crate::experiment::{FilterPlan, Plan};
use crate::output::folder::{FinishedFolder, FinishedTable, StudyFolder};
use crate::output::manifest::StudyKind;
use crate::output::table::read;
use crate::output::{TableWriter, Value, schema};
use crate::runner::RunObserver;
use crate::study::{ExecOptions, run};

/// What to optimise.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Objective {
    /// ANEES closest to n and ANIS closest to p.
    Consistency,
    /// Smallest RMSE over all states (each normalised by its best value).
    Rmse,
}

/// Tuning options.
#[derive(Clone, Debug, PartialEq)]
pub struct TuneOptions {
    /// The objective.
    pub objective: Objective,
    /// Also search the R scale.
    pub tune_r: bool,
    /// The filter label (default: the first filter with a covariance).
    pub filter: Option<String>,
    /// Write into a non-empty folder that is not a kfmc study.
    pub force: bool,
    /// Worker threads.
    pub threads: usize,
}

/// One evaluated candidate in one cell.
#[derive(Clone, Debug, PartialEq)]
pub struct TunePoint {
    /// `coarse` or `refine`.
    pub stage: &'static str,
    /// Scenario.
    pub scenario: String,
    /// Truth-noise multiplier.
    pub noise_scale: f64,
    /// Q multiplier.
    pub q_scale: f64,
    /// R multiplier.
    pub r_scale: f64,
    /// Run-and-time average NEES.
    pub anees: Option<f64>,
    /// Run-and-time average NIS.
    pub anis: Option<f64>,
    /// Mean RMSE over runs per state.
    pub rmse: Vec<f64>,
    /// The cell's objective (lower is better).
    pub objective: f64,
}

/// The search's result.
#[derive(Clone, Debug, PartialEq)]
pub struct TuneReport {
    /// The tuned filter's label.
    pub filter: String,
    /// Every evaluated point.
    pub points: Vec<TunePoint>,
    /// The best (q_scale, r_scale) over all cells, and its mean objective.
    pub best: (f64, f64, f64),
    /// Per noise scale: its best (noise_scale, q_scale, r_scale, mean objective over scenarios).
    pub per_noise_scale: Vec<(f64, f64, f64, f64)>,
    /// Per (scenario, noise scale): its own best (q_scale, r_scale, objective).
    pub per_cell: Vec<(String, f64, f64, f64, f64)>,
    /// Where tuning.parquet went.
    pub table: PathBuf,
}

/// A candidate's consistency averaged over the cells it was evaluated in.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CandidateAverages {
    /// The mean of the cells' ANEES (`None` where no cell has one).
    pub anees: Option<f64>,
    /// The mean of the cells' ANIS.
    pub anis: Option<f64>,
}

impl TuneReport {
    /// The averages of candidate (`q_scale`, `r_scale`) over the cells it was evaluated in,
    /// or over the cells of one truth-noise scale.
    pub fn averages(
        &self,
        q_scale: f64,
        r_scale: f64,
        noise_scale: Option<f64>,
    ) -> CandidateAverages {
        let points: Vec<&TunePoint> = self
            .points
            .iter()
            .filter(|p| p.q_scale == q_scale && p.r_scale == r_scale)
            .filter(|p| noise_scale.is_none_or(|s| p.noise_scale == s))
            .collect();
        let mean = |value: fn(&TunePoint) -> Option<f64>| {
            let v: Vec<f64> = points.iter().filter_map(|p| value(p)).collect();
            (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
        };
        CandidateAverages {
            anees: mean(|p| p.anees),
            anis: mean(|p| p.anis),
        }
    }
}

fn log_grid(center: f64, half_decades: f64, points: usize) -> Vec<f64> {
    (0..points)
        .map(|i| {
            let t = if points > 1 {
                i as f64 / (points - 1) as f64
            } else {
                0.5
            };
            let v = center * 10f64.powf(half_decades * (2.0 * t - 1.0));
            // Round to 6 significant digits so the tables show readable scales.
            let mag = 10f64.powi(5 - v.log10().floor() as i32);
            (v * mag).round() / mag
        })
        .collect()
}

/// Runs one stage of the search into its folder under `staging`, and returns its points and
/// the folder's name.
/// The folder of the stage `name` of a search over `plan` (a refine stage's plan has one
/// noise scale).
fn stage_folder(plan: &Plan, name: &str) -> String {
    match plan.noise_scales.as_slice() {
        [one] if name == "refine" => format!("tune_{name}_noise_{one}"),
        _ => format!("tune_{name}"),
    }
}

/// The folders of every stage a search over `plan` writes: the coarse grid, and a refine
/// stage per noise scale.
fn stage_names(plan: &Plan) -> Vec<String> {
    let mut names = vec![stage_folder(plan, "coarse")];
    // As stage_folder names the refine stage of each scale's one-scale plan.
    names.extend(
        plan.noise_scales
            .iter()
            .map(|scale| format!("tune_refine_noise_{scale}")),
    );
    names
}

fn stage(
    plan: &Plan,
    staging: &std::path::Path,
    base: &FilterPlan,
    grid: &[(f64, f64)],
    name: &'static str,
    opts: &TuneOptions,
    observer: &dyn RunObserver,
) -> Result<(Vec<TunePoint>, String), KfmcError> {
    let mut p = plan.clone();
    let folder = stage_folder(plan, name);
    p.output = staging.join(&folder);
    p.trace_runs = 0;
    p.assertions.clear();
    p.rmse_thresholds = None;
    p.consistency = Some(ConsistencyPlan {
        alpha: plan.alpha,
        whiteness_lags: 0,
        whiteness_burn_in: 0,
        subsets: Vec::new(),
    });
    p.filters = grid
        .iter()
        .map(|&(q, r)| FilterPlan {
            q_scale: q,
            r_scale: r,
            ..base.clone()
        })
        .collect();
    run(
        &p,
        &ExecOptions {
            threads: opts.threads,
            force: false,
            shard: None,
            checkpoints: None,
        },
        observer,
    )?;

    // Read the stage back from its tables: one code path for studies and tuning.
    let err = |path: &std::path::Path, e| OutputError::Polars {
        action: "unexpected columns in",
        path: path.to_path_buf(),
        source: e,
    };
    let mut points: BTreeMap<(String, u64, u64, u64), TunePoint> = BTreeMap::new();
    let key =
        |s: &str, n: f64, q: f64, r: f64| (s.to_string(), n.to_bits(), q.to_bits(), r.to_bits());
    let spath = p.output.join("summary.parquet");
    let s = read(&spath)?;
    let col_s = |c: &str| {
        s.column(c)
            .and_then(|c| c.str().cloned())
            .map_err(|e| err(&spath, e))
    };
    let col_f = |c: &str| {
        s.column(c)
            .and_then(|c| c.f64().cloned())
            .map_err(|e| err(&spath, e))
    };
    let (sc, noise, q, r, state, mean) = (
        col_s("scenario")?,
        col_f("noise_scale")?,
        col_f("q_scale")?,
        col_f("r_scale")?,
        col_s("state")?,
        col_f("rmse_mean")?,
    );
    let states = p.quantity_names();
    for i in 0..s.height() {
        let (scn, n, qq, rr) = (
            sc.get(i).unwrap_or(""),
            noise.get(i).unwrap_or(f64::NAN),
            q.get(i).unwrap_or(f64::NAN),
            r.get(i).unwrap_or(f64::NAN),
        );
        let pt = points
            .entry(key(scn, n, qq, rr))
            .or_insert_with(|| TunePoint {
                stage: name,
                scenario: scn.to_string(),
                noise_scale: n,
                q_scale: qq,
                r_scale: rr,
                anees: None,
                anis: None,
                rmse: vec![f64::NAN; states.len()],
                objective: f64::NAN,
            });
        if let Some(si) = states.iter().position(|x| Some(*x) == state.get(i)) {
            pt.rmse[si] = mean.get(i).unwrap_or(f64::NAN);
        }
    }
    let cpath = p.output.join("consistency.parquet");
    let c = read(&cpath)?;
    let ccol_s = |n: &str| {
        c.column(n)
            .and_then(|c| c.str().cloned())
            .map_err(|e| err(&cpath, e))
    };
    let ccol_f = |n: &str| {
        c.column(n)
            .and_then(|c| c.f64().cloned())
            .map_err(|e| err(&cpath, e))
    };
    let (sc, noise, q, r, test, stat) = (
        ccol_s("scenario")?,
        ccol_f("noise_scale")?,
        ccol_f("q_scale")?,
        ccol_f("r_scale")?,
        ccol_s("test")?,
        ccol_f("statistic")?,
    );
    for i in 0..c.height() {
        let k = key(
            sc.get(i).unwrap_or(""),
            noise.get(i).unwrap_or(f64::NAN),
            q.get(i).unwrap_or(f64::NAN),
            r.get(i).unwrap_or(f64::NAN),
        );
        if let Some(pt) = points.get_mut(&k) {
            match test.get(i) {
                Some("nees_time_average") => pt.anees = stat.get(i),
                Some("nis_time_average") => pt.anis = stat.get(i),
                _ => {}
            }
        }
    }
    Ok((points.into_values().collect(), folder))
}

/// The search's stage folders while it runs: inside the tune folder (so they move into place
/// by a rename), hidden, and removed when the search does not commit.
struct Staging(PathBuf);

impl Drop for Staging {
    fn drop(&mut self) {
        // Empty once committed; whatever an error or an interruption left otherwise.
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// Scores every point with the objective (the RMSE objective needs all points of a cell).
fn score(points: &mut [TunePoint], objective: Objective, n: f64, p: f64) {
    match objective {
        Objective::Consistency => {
            for pt in points.iter_mut() {
                pt.objective = match (pt.anees, pt.anis) {
                    (Some(a), Some(b)) if a > 0.0 && b > 0.0 => {
                        (a / n).ln().abs() + (b / p).ln().abs()
                    }
                    _ => f64::INFINITY,
                };
            }
        }
        Objective::Rmse => {
            let mut best: BTreeMap<(String, u64), Vec<f64>> = BTreeMap::new();
            for pt in points.iter() {
                let b = best
                    .entry((pt.scenario.clone(), pt.noise_scale.to_bits()))
                    .or_insert_with(|| vec![f64::INFINITY; pt.rmse.len()]);
                for (bi, v) in b.iter_mut().zip(&pt.rmse) {
                    *bi = bi.min(*v);
                }
            }
            for pt in points.iter_mut() {
                let b = &best[&(pt.scenario.clone(), pt.noise_scale.to_bits())];
                pt.objective = pt.rmse.iter().zip(b).map(|(v, b)| v / b).sum();
            }
        }
    }
}

/// The (q, r) with the lowest objective averaged over cells (those passing `keep`).
fn best_overall(points: &[TunePoint], keep: impl Fn(&TunePoint) -> bool) -> (f64, f64, f64) {
    let mut by: BTreeMap<(u64, u64), (f64, usize)> = BTreeMap::new();
    for pt in points.iter().filter(|p| keep(p)) {
        let e = by
            .entry((pt.q_scale.to_bits(), pt.r_scale.to_bits()))
            .or_insert((0.0, 0));
        e.0 += pt.objective;
        e.1 += 1;
    }
    by.into_iter()
        .map(|((q, r), (s, c))| (f64::from_bits(q), f64::from_bits(r), s / c as f64))
        .min_by(|a, b| a.2.total_cmp(&b.2))
        .unwrap_or((1.0, 1.0, f64::INFINITY))
}

/// A spec error of the `filters` key.
fn filters_error(plan: &Plan, message: String) -> KfmcError {
    KfmcError::Spec(crate::error::SpecErrors(vec![crate::error::SpecError {
        file: plan.spec_path.clone(),
        key_path: "filters".into(),
        message,
    }]))
}

/// The filter to tune: the one labelled `opts.filter`, else the first with a covariance and
/// a Q scale.
fn tuned_filter(plan: &Plan, opts: &TuneOptions) -> Result<FilterPlan, KfmcError> {
    // kfmc does not run an external filter (its estimates come from a file), so it has
    // nothing to tune there.
    if let Some(l) = &opts.filter
        && plan.filters.iter().any(|f| f.external && f.label == *l)
    {
        return Err(filters_error(
            plan,
            format!(
                "filter `{l}` is external (kind = \"external\"): kfmc does not run it, so it cannot tune it"
            ),
        ));
    }
    plan.filters
        .iter()
        .filter(|f| !f.external)
        .find(|f| {
            let info = &plan.system.filters()[f.entry];
            info.has_covariance
                && info.q_scale
                && opts.filter.as_ref().is_none_or(|l| *l == f.label)
        })
        .cloned()
        .ok_or_else(|| {
            filters_error(
                plan,
                match &opts.filter {
                    Some(l) => {
                        format!("no filter with a covariance and a q_scale labelled `{l}` to tune")
                    }
                    None => {
                        "no filter with a covariance and a q_scale (e.g. kind = \"ekf\") to tune"
                            .into()
                    }
                },
            )
        })
}

/// Stage 1's candidates: half-decades from 10⁻³ to 10³ for Q (and R with `tune_r`).
fn coarse_grid(tune_r: bool) -> Vec<(f64, f64)> {
    if tune_r {
        let g = log_grid(1.0, 3.0, 13);
        g.iter()
            .flat_map(|&q| g.iter().map(move |&r| (q, r)))
            .collect()
    } else {
        log_grid(1.0, 3.0, 13)
            .into_iter()
            .map(|q| (q, 1.0))
            .collect()
    }
}

/// Stage 2's candidates: ±½ decade around (q0, r0).
fn refine_grid(tune_r: bool, q0: f64, r0: f64) -> Vec<(f64, f64)> {
    if tune_r {
        let (gq, gr) = (log_grid(q0, 0.5, 7), log_grid(r0, 0.5, 7));
        gq.iter()
            .flat_map(|&q| gr.iter().map(move |&r| (q, r)))
            .collect()
    } else {
        log_grid(q0, 0.5, 11)
            .into_iter()
            .map(|q| (q, 1.0))
            .collect()
    }
}

/// Per (scenario, noise scale): its own best (q_scale, r_scale, objective).
fn best_per_cell(points: &[TunePoint]) -> Vec<(String, f64, f64, f64, f64)> {
    let mut per_cell: BTreeMap<(String, u64), (f64, f64, f64)> = BTreeMap::new();
    for pt in points {
        let e = per_cell
            .entry((pt.scenario.clone(), pt.noise_scale.to_bits()))
            .or_insert((f64::NAN, f64::NAN, f64::INFINITY));
        if pt.objective < e.2 {
            *e = (pt.q_scale, pt.r_scale, pt.objective);
        }
    }
    per_cell
        .into_iter()
        .map(|((s, n), (q, r, o))| (s, f64::from_bits(n), q, r, o))
        .collect()
}

/// Writes every evaluated point into `tuning.parquet` (not yet committed).
fn tuning_table(
    plan: &Plan,
    filter: &str,
    points: &[TunePoint],
) -> Result<FinishedTable, KfmcError> {
    let states = plan.quantity_names();
    let mut w = TableWriter::create(&plan.output, "tuning", schema::tuning(&states))?;
    for pt in points {
        let mut row = vec![
            Value::Str(pt.stage),
            Value::Str(&pt.scenario),
            Value::F64(Some(pt.noise_scale)),
            Value::Str(filter),
            Value::F64(Some(pt.q_scale)),
            Value::F64(Some(pt.r_scale)),
            Value::F64(pt.anees),
            Value::F64(pt.anis),
        ];
        row.extend(pt.rmse.iter().map(|v| Value::F64(Some(*v))));
        row.push(Value::F64(Some(pt.objective).filter(|o| o.is_finite())));
        w.push(&row)?;
    }
    Ok(w.finish()?)
}

/// Moves the tuning table, the coarse stage's summary and the stage folders into the tune
/// folder in one commit.
fn commit(
    plan: &Plan,
    folder: &StudyFolder,
    staging: &Staging,
    stages: Vec<String>,
    tuning: FinishedTable,
) -> Result<(), KfmcError> {
    // The coarse stage's summary beside tuning.parquet makes the folder plottable as it is
    // (`kfmc plot DIR` draws the tuning curves and the coarse grid's RMSE); the folder's own
    // manifest, written last, commits both.
    let coarse = staging.0.join("tune_coarse");
    let mut manifest = crate::output::folder::verify(&coarse)?;
    manifest.kind = Some(StudyKind::Tune);
    let summary_tmp = copy_beside(
        &coarse.join("summary.parquet"),
        &plan.output.join("summary.parquet"),
    )?;
    let summary_rows = manifest
        .tables
        .iter()
        .find(|t| t.name == "summary")
        .map_or(0, |t| t.rows);
    manifest.tables.clear();
    if crate::runner::interrupted() {
        return Err(OutputError::Interrupted.into());
    }
    // Every stage the earlier search listed goes with it (a refine stage per noise scale it
    // had), not only those this search replaces.
    folder.commit_with_folders(
        vec![
            tuning,
            FinishedTable {
                name: "summary".into(),
                tmp: summary_tmp,
                rows: summary_rows,
            },
        ],
        stages
            .into_iter()
            .map(|name| FinishedFolder {
                tmp: staging.0.join(&name),
                name,
            })
            .collect(),
        manifest,
    )?;
    Ok(())
}

/// Copies `from` to a temporary file beside `to` (never through a symbolic link, never over
/// an existing file); returns the temporary path, removed with the table if not committed.
fn copy_beside(from: &std::path::Path, to: &std::path::Path) -> Result<PathBuf, KfmcError> {
    let (tmp, mut file) =
        crate::output::atomic::create_temp_beside(to).map_err(|source| OutputError::Io {
            action: "cannot create a temporary file beside",
            path: to.to_path_buf(),
            source,
        })?;
    let copied = crate::output::atomic::open_regular(from)
        .and_then(|mut src| std::io::copy(&mut src, &mut file));
    if let Err(source) = copied {
        let _ = std::fs::remove_file(&tmp);
        return Err(OutputError::Io {
            action: "cannot copy the coarse stage's summary to",
            path: tmp,
            source,
        }
        .into());
    }
    Ok(tmp)
}

/// Runs the search and writes `tuning.parquet` into the plan's output folder.
pub fn tune(
    plan: &Plan,
    opts: &TuneOptions,
    observer: &dyn RunObserver,
) -> Result<TuneReport, KfmcError> {
    let base = tuned_filter(plan, opts)?;
    // Locked for the whole search. The stages are written aside and move into place with the
    // tuning table in one commit: an interrupted search leaves the earlier one whole.
    let folder = StudyFolder::open_with(
        &plan.output,
        StudyKind::Tune,
        opts.force,
        &crate::study::inputs(plan),
    )?;
    folder.refuse_unlisted(&stage_names(plan))?;
    let staging = Staging(
        plan.output
            .join(crate::output::atomic::temp_name("tune-stages")),
    );
    let mut stages = Vec::new();
    let (n, p) = (
        plan.layout().quantities.len() as f64,
        plan.layout().measurements.len() as f64,
    );

    let coarse = coarse_grid(opts.tune_r);
    let (mut points, name) = stage(plan, &staging.0, &base, &coarse, "coarse", opts, observer)?;
    stages.push(name);
    score(&mut points, opts.objective, n, p);

    for &scale in &plan.noise_scales {
        let (q0, r0, _) = best_overall(&points, |pt| pt.noise_scale == scale);
        let refine = refine_grid(opts.tune_r, q0, r0);
        let mut sub = plan.clone();
        sub.noise_scales = vec![scale];
        let (mut fine, name) = stage(&sub, &staging.0, &base, &refine, "refine", opts, observer)?;
        points.append(&mut fine);
        stages.push(name);
    }
    // Re-score together: the RMSE objective normalises by the best of all candidates.
    score(&mut points, opts.objective, n, p);
    // Refined candidates exist for one noise scale each; only the coarse grid was run in
    // every cell, so it alone can say what is best over all of them.
    let single = plan.noise_scales.len() == 1;
    let best = best_overall(&points, |pt| single || pt.stage == "coarse");
    let per_noise_scale = plan
        .noise_scales
        .iter()
        .map(|&s| {
            let (q, r, o) = best_overall(&points, |pt| pt.noise_scale == s);
            (s, q, r, o)
        })
        .collect();
    let per_cell = best_per_cell(&points);

    let tuning = tuning_table(plan, &base.label, &points)?;
    commit(plan, &folder, &staging, stages, tuning)?;
    Ok(TuneReport {
        filter: base.label.clone(),
        points,
        best,
        per_noise_scale,
        per_cell,
        table: plan.output.join("tuning.parquet"),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn log_grid_is_symmetric_in_decades() {
        let g = log_grid(1.0, 3.0, 13);
        assert_eq!(g.len(), 13);
        assert_eq!(g[0], 0.001);
        assert_eq!(g[6], 1.0);
        assert_eq!(g[12], 1000.0);
        let g = log_grid(2.0, 0.5, 11);
        assert!((g[5] - 2.0).abs() < 1e-12);
        assert!((g[0] - 2.0 / 10f64.sqrt()).abs() < 1e-5);
    }
}
