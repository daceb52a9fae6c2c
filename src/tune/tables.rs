//! What every element-wise tuning method writes: `tuned.parquet` (one row per element, with
//! its interval and whether it is identified), `tune_trace.parquet` (every iteration of every
//! start) and `tuned.toml` (the tuned Q and R, ready to paste), committed together.

use std::time::Instant;

use nalgebra::DMatrix;

use super::estimate::{Estimate, TraceRow};
use super::likelihood::LinearModel;
use crate::error::{KfmcError, OutputError};
use crate::experiment::Plan;
use crate::experiment::tune_spec::{TuneElement, TuneMethod};
use crate::output::folder::{FinishedTable, StudyFolder};
use crate::output::manifest::StudyKind;
use crate::output::{TableWriter, Value, schema};
use crate::study::ExecOptions;

/// The file of the tuned filter's covariances.
pub const TUNED_TOML: &str = "tuned.toml";

/// When and how a tuning ran, for its manifest.
#[derive(Clone, Copy, Debug)]
pub struct Timing {
    /// When it started.
    pub started: Instant,
    /// The same, in seconds since the epoch.
    pub started_unix_s: u64,
    /// Worker threads asked for.
    pub threads: usize,
    /// `--force`.
    pub force: bool,
}

/// Writes `tuned.parquet` and `tune_trace.parquet` of `est` into the locked `folder` with
/// the manifest, then `tuned.toml` (`toml_text`).
pub fn commit(
    plan: &Plan,
    folder: &StudyFolder,
    method: TuneMethod,
    elements: &[TuneElement],
    est: &Estimate,
    timing: Timing,
    toml_text: &str,
) -> Result<(), KfmcError> {
    let tuned = tuned_table(plan, method, elements, est)?;
    let trace = trace_table(plan, elements, &est.trace)?;
    let mut manifest = crate::study::manifest_for(
        plan,
        &ExecOptions {
            threads: timing.threads,
            force: timing.force,
            shard: None,
            checkpoints: None,
        },
        timing.started_unix_s,
        timing.started.elapsed().as_secs_f64(),
        0..plan.scenarios.len() * plan.noise_scales.len(),
    );
    manifest.kind = Some(StudyKind::Tune);
    if crate::runner::interrupted() {
        return Err(OutputError::Interrupted.into());
    }
    folder.commit(vec![tuned, trace], manifest)?;
    let toml_path = plan.output.join(TUNED_TOML);
    folder.claim_files(&[TUNED_TOML.to_string()], &|_| false)?;
    crate::output::atomic::write_atomic(&toml_path, toml_text.as_bytes()).map_err(|source| {
        OutputError::Io {
            action: "cannot write",
            path: toml_path.clone(),
            source,
        }
    })?;
    Ok(())
}

/// `tuned.parquet`: one row per element.
fn tuned_table(
    plan: &Plan,
    method: TuneMethod,
    elements: &[TuneElement],
    est: &Estimate,
) -> Result<FinishedTable, KfmcError> {
    let mut w = TableWriter::create(&plan.output, "tuned", schema::tuned())?;
    for (i, e) in elements.iter().enumerate() {
        let (v, se, ci) = est.natural(i);
        w.push(&[
            Value::Str(&e.name),
            Value::F64(Some(v)),
            Value::F64(se),
            Value::F64(ci.map(|c| c.0)),
            Value::F64(ci.map(|c| c.1)),
            Value::Str(method.name()),
            Value::Bool(Some(est.identifiable[i])),
        ])?;
    }
    Ok(w.finish()?)
}

/// `tune_trace.parquet`: every iteration of every start.
fn trace_table(
    plan: &Plan,
    elements: &[TuneElement],
    trace: &[TraceRow],
) -> Result<FinishedTable, KfmcError> {
    let names: Vec<&str> = elements.iter().map(|e| e.name.as_str()).collect();
    let mut w = TableWriter::create(&plan.output, "tune_trace", schema::tune_trace(&names))?;
    for row in trace {
        let mut values = vec![
            Value::I64(Some(row.start as i64)),
            Value::I64(Some(row.iteration as i64)),
            Value::F64(Some(row.objective)),
        ];
        values.extend(row.parameters.iter().map(|v| Value::F64(Some(*v))));
        w.push(&values)?;
    }
    Ok(w.finish()?)
}

/// `tuned.toml`: the model's F, G, H with the tuned Q and R, in the discrete form of a
/// `kind = "linear"` spec (filters take the model's Q and R; they have no keys of their own).
/// `objective` says what the search reached (e.g. `−ln L = …`).
#[allow(clippy::too_many_arguments)]
pub fn tuned_toml(
    plan: &Plan,
    method: TuneMethod,
    objective: &str,
    elements: &[TuneElement],
    est: &Estimate,
    model: &LinearModel,
    q: &DMatrix<f64>,
    r: &DMatrix<f64>,
    data: &str,
) -> String {
    let rows = |m: &DMatrix<f64>| {
        toml::Value::Array(
            (0..m.nrows())
                .map(|i| {
                    toml::Value::Array(
                        (0..m.ncols())
                            .map(|j| toml::Value::Float(m[(i, j)]))
                            .collect(),
                    )
                })
                .collect(),
        )
    };
    let mut table = toml::Table::new();
    table.insert("f".into(), rows(&model.f));
    if model.g.ncols() > 0 {
        table.insert("g".into(), rows(&model.g));
    }
    table.insert("h".into(), rows(&model.h));
    table.insert("q".into(), rows(q));
    table.insert("r".into(), rows(r));
    let mut doc = toml::Table::new();
    doc.insert("model".into(), toml::Value::Table(table));
    let mut head = format!(
        "# kfmc tune --method {} of {} ({}): {objective}\n",
        method.name(),
        plan.spec_path.display(),
        data,
    );
    head.push_str("# Tuned elements (estimate, 95 % interval):\n");
    for (i, e) in elements.iter().enumerate() {
        let (v, _, ci) = est.natural(i);
        head.push_str(&match ci {
            Some((lo, hi)) => format!("#   {} = {v} [{lo}, {hi}]\n", e.name),
            None => format!("#   {} = {v} (not identified: no interval)\n", e.name),
        });
    }
    head.push_str(
        "# kfmc's filters assume the model's Q and R (a filter has no Q or R keys of its own), so\n\
         # these are [model] keys of a kind = \"linear\" spec in its discrete form: f, g, h, q\n\
         # and r replace a, b, c, gamma and q_tilde when the spec gives the continuous form.\n",
    );
    head + &toml::to_string(&doc).unwrap_or_default()
}
