//! `kfmc tune`: the `consistency` method searches a filter's Q scale (and R scale with
//! --tune-r) for consistency or minimum RMSE on a coarse log grid, then a refinement, and
//! writes tuning.parquet; the `ml` method estimates named elements of Q and R by maximum
//! likelihood of the innovations, with intervals, and writes tuned.parquet; the `truth` method
//! estimates them from a simulated study's truth by identifying conditions, with sandwich
//! intervals, and writes the same tables.

use super::*;

/// The arguments of `kfmc tune`.
#[derive(Debug, clap::Args)]
pub struct Tune {
    /// The spec and the shared overrides.
    #[command(flatten)]
    pub study: StudyArgs,
    /// What to optimise: `consistency` or `rmse` for the consistency method, `consistency`
    /// (E[e²/P] = 1, E[ν²/S] = 1 per element) or `mse` (the estimation MSE against truth) for
    /// the truth method.
    #[arg(long, value_enum, default_value_t = ObjectiveArg::Consistency)]
    pub objective: ObjectiveArg,
    /// Also search the R scale (2-D grid).
    #[arg(long)]
    pub tune_r: bool,
    /// The filter label to tune (default: the first EKF).
    #[arg(long)]
    pub filter: Option<String>,
    /// The method (default: `tune.method` of the spec, else `consistency`).
    #[arg(long, value_enum)]
    pub method: Option<crate::experiment::tune_spec::TuneMethod>,
    /// The elements the `ml` and `truth` methods estimate, e.g. `--elements 'q[px,px]' 'r[zx,zx]'`
    /// (default: `tune.elements` of the spec).
    #[arg(long, num_args = 1..)]
    pub elements: Vec<String>,
    /// Tune (`ml`) from this `measurements.parquet` (the layout `kfmc simulate` writes)
    /// instead of the spec's simulation; an `initial.parquet` beside it gives the priors.
    #[arg(long, value_name = "FILE")]
    pub measurements: Option<std::path::PathBuf>,
}

/// `--objective`: the union of what the methods optimise.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum ObjectiveArg {
    /// Consistency (every method that has an objective).
    Consistency,
    /// The sum of normalised RMSEs (the consistency method).
    Rmse,
    /// The estimation MSE against truth (the truth method).
    Mse,
}

impl Tune {
    /// Runs the command.
    pub(super) fn execute(self, registry: &Registry) -> anyhow::Result<()> {
        let Self {
            study,
            objective,
            tune_r,
            filter,
            method,
            elements,
            measurements,
        } = self;
        let plan = study.plan(registry, None)?;
        let method = method
            .or_else(|| plan.tune.as_ref().and_then(|t| t.method))
            .unwrap_or(crate::experiment::tune_spec::TuneMethod::Consistency);
        if method == crate::experiment::tune_spec::TuneMethod::Ml {
            let opts = crate::tune::ml::MlOptions {
                elements: (!elements.is_empty()).then_some(elements),
                measurements,
                search: Default::default(),
                force: study.force,
                threads: study.threads(study.quiet),
            };
            if objective != ObjectiveArg::Consistency {
                anyhow::bail!(
                    "--objective belongs to the consistency and truth methods; the ml method maximises the likelihood"
                );
            }
            return execute_ml(&plan, &study.spec, study.quiet, &opts);
        }
        if method == crate::experiment::tune_spec::TuneMethod::Truth {
            if measurements.is_some() {
                anyhow::bail!(
                    "--measurements belongs to the ml method; the truth method tunes on the spec's simulated runs, whose truth it needs"
                );
            }
            let objective = match objective {
                ObjectiveArg::Consistency => crate::tune::conditions::TruthObjective::Consistency,
                ObjectiveArg::Mse => crate::tune::conditions::TruthObjective::Mse,
                ObjectiveArg::Rmse => anyhow::bail!(
                    "--objective rmse belongs to the consistency method; the truth method takes consistency or mse"
                ),
            };
            let opts = crate::tune::truth::TruthOptions {
                elements: (!elements.is_empty()).then_some(elements),
                objective,
                search: Default::default(),
                force: study.force,
                threads: study.threads(study.quiet),
            };
            return execute_truth(&plan, &study.spec, study.quiet, &opts);
        }
        if !elements.is_empty() || measurements.is_some() {
            anyhow::bail!(
                "--elements and --measurements belong to the ml method (--method ml); the consistency method tunes a Q scale and an R scale"
            );
        }
        let objective = match objective {
            ObjectiveArg::Consistency => crate::tune::Objective::Consistency,
            ObjectiveArg::Rmse => crate::tune::Objective::Rmse,
            ObjectiveArg::Mse => anyhow::bail!(
                "--objective mse belongs to the truth method (--method truth); the consistency method takes consistency or rmse"
            ),
        };
        let threads = study.threads(study.quiet);
        let StudyArgs {
            spec, quiet, force, ..
        } = study;
        let observer = ProgressObserver::new(!quiet);
        let opts = crate::tune::TuneOptions {
            objective,
            tune_r,
            filter,
            threads,
            force,
        };
        let report = crate::tune::tune(&plan, &opts, &observer)
            .map_err(anyhow::Error::from)
            .map_err(|e| e.context(format!("tuning {}", spec.display())))?;
        let (q, r, obj) = report.best;
        let fmt = |v: Option<f64>| v.map_or("—".into(), |x| format!("{x:.4}"));
        outln!(
            "{} tune {}: filter {}, objective {:?}, {} candidates evaluated → {}",
            plan.program.name,
            plan.name,
            report.filter,
            objective,
            report.points.len(),
            report.table.display()
        );
        let best = report.averages(q, r, None);
        outln!(
            "best q_scale = {q}, r_scale = {r}: objective {obj:.4}, ANEES {} (n = {}), ANIS {} (p = {})",
            fmt(best.anees),
            plan.layout().quantities.len(),
            fmt(best.anis),
            plan.layout().measurements.len()
        );
        if report.per_noise_scale.len() > 1 {
            outln!("best per truth-noise scale (over the scenarios):");
            for &(s, q, r, o) in &report.per_noise_scale {
                let at = report.averages(q, r, Some(s));
                outln!(
                    "  noise_scale {s:<6} q_scale {q:<10} r_scale {r:<10} objective {o:.4}  ANEES {}  ANIS {}",
                    fmt(at.anees),
                    fmt(at.anis)
                );
            }
        }
        Ok(())
    }
}

/// `kfmc tune --method ml`: runs the estimate and prints each element with its interval and
/// every direction the data do not identify.
fn execute_ml(
    plan: &crate::experiment::Plan,
    spec: &std::path::Path,
    quiet: bool,
    opts: &crate::tune::ml::MlOptions,
) -> anyhow::Result<()> {
    let observer = ProgressObserver::new(!quiet);
    let spinner = progress::IterationProgress::new(!quiet);
    let report = crate::tune::ml::tune_ml(plan, opts, &observer, &|row| {
        spinner.show(row.start, row.iteration, row.objective)
    });
    spinner.finish();
    let report = report
        .map_err(anyhow::Error::from)
        .map_err(|e| e.context(format!("tuning {}", spec.display())))?;
    let est = &report.estimate;
    let iterations = est.best_start_iterations();
    outln!(
        "{} tune {} (ml): {} elements from {} runs, {} scalar measurements ({})",
        plan.program.name,
        plan.name,
        report.elements.len(),
        report.runs,
        report.measurements,
        report.data
    );
    outln!(
        "−ln L = {:.6} after {iterations} iterations from the start at ×{} of the spec's values{} → {}",
        est.objective,
        opts.search.starts[est.best_start],
        if est.converged {
            ""
        } else {
            " (not converged)"
        },
        report.output.join("tuned.parquet").display()
    );
    print_elements(&report.elements, &report.spec_values, est);
    outln!(
        "the tuned Q and R, ready to paste: {}",
        report.output.join(crate::tune::ml::TUNED_TOML).display()
    );
    Ok(())
}

/// Each element against its spec value with its interval, and every direction the data do
/// not identify (`ml` and `truth`).
fn print_elements(
    elements: &[crate::experiment::tune_spec::TuneElement],
    spec_values: &[f64],
    est: &crate::tune::estimate::Estimate,
) {
    outln!(
        "  {:<24} {:>13} {:>13} {:>13}  95 % interval",
        "element",
        "spec",
        "estimate",
        "std_error"
    );
    for (i, e) in elements.iter().enumerate() {
        let (v, se, ci) = est.natural(i);
        let ci = ci.map_or("not identified".to_string(), |(lo, hi)| {
            format!("[{lo:.6e}, {hi:.6e}]")
        });
        let bound = if est.at_bound[i] {
            "  (at a bound of the search)"
        } else {
            ""
        };
        outln!(
            "  {:<24} {:>13.6e} {:>13.6e} {:>13} {ci}{bound}",
            e.name,
            spec_values[i],
            v,
            se.map_or("—".to_string(), |s| format!("{s:.6e}"))
        );
    }
    for d in &est.flat {
        let terms: Vec<String> = d
            .components
            .iter()
            .zip(elements)
            .filter(|(c, _)| c.abs() >= crate::tune::estimate::DIRECTION_SHARE)
            .map(|(c, e)| format!("{c:+.3}·ln {}", e.name))
            .collect();
        outln!(
            "not identified: the direction {} (information {:.3e}, {:.1e} of the largest {:.3e})",
            terms.join(" "),
            d.eigenvalue,
            d.eigenvalue / d.largest,
            d.largest
        );
    }
}

/// `kfmc tune --method truth`: solves the conditions and prints each element with its
/// sandwich interval, the conditions' residuals and the identifiability report.
fn execute_truth(
    plan: &crate::experiment::Plan,
    spec: &std::path::Path,
    quiet: bool,
    opts: &crate::tune::truth::TruthOptions,
) -> anyhow::Result<()> {
    let observer = ProgressObserver::new(!quiet);
    let spinner = progress::IterationProgress::new(!quiet);
    let report = crate::tune::truth::tune_truth(plan, opts, &observer, &|row| {
        spinner.show(row.start, row.iteration, row.objective)
    });
    spinner.finish();
    let report = report
        .map_err(anyhow::Error::from)
        .map_err(|e| e.context(format!("tuning {}", spec.display())))?;
    let est = &report.estimate;
    let iterations = est.best_start_iterations();
    outln!(
        "{} tune {} (truth, objective {}): {} elements from {} runs ({})",
        plan.program.name,
        plan.name,
        opts.objective.name(),
        report.elements.len(),
        report.runs,
        report.data
    );
    outln!(
        "objective {:.6e} after {iterations} iterations from the start at ×{} of the spec's values{} → {}",
        est.objective,
        opts.search.starts[est.best_start],
        if est.converged {
            ""
        } else {
            " (not converged)"
        },
        report.output.join("tuned.parquet").display()
    );
    print_elements(&report.elements, &report.spec_values, est);
    let residuals: Vec<String> = report
        .elements
        .iter()
        .zip(&report.residuals)
        .map(|(e, g)| format!("{} {g:+.2e}", e.name))
        .collect();
    outln!(
        "conditions at the estimate (0 at an exact root): {}",
        residuals.join(", ")
    );
    for note in &report.notes {
        outln!("note: {note}");
    }
    outln!(
        "the tuned Q and R, ready to paste: {}",
        report.output.join(crate::tune::ml::TUNED_TOML).display()
    );
    Ok(())
}
