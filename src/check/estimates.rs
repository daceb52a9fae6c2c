//! External filters' estimates attached to a plan before its study runs, with the world
//! stamp that ties them to the spec's runs.

use std::path::Path;

use polars::prelude::{ParquetCompression, ParquetReader, ParquetWriter, SerReader};

use crate::error::{KfmcError, OutputError};
use crate::experiment::Plan;

/// What a command does with an estimates file that carries no world stamp.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Unstamped {
    /// Read it, with a warning on stderr (`kfmc score`, `kfmc check --allow-unstamped`).
    Warn,
    /// Refuse it (`kfmc check`: a CI gate passes only on data tied to its spec's runs).
    Refuse,
}

/// Reads the external filters' estimates into `plan`; files without a world stamp are
/// warned about or refused, as `unstamped` says.
pub fn attach_estimates(
    plan: &mut Plan,
    files: &[std::path::PathBuf],
    unstamped: Unstamped,
) -> Result<(), KfmcError> {
    attach_estimates_with_tables(plan, files, &[], unstamped)
}

/// [`attach_estimates`] with tables already in memory besides the files
/// ([`crate::score::InMemoryTable`]: their stamp is looked for in their metadata, and one
/// without is unstamped as a file without is).
pub fn attach_estimates_with_tables(
    plan: &mut Plan,
    files: &[std::path::PathBuf],
    tables: &[crate::score::InMemoryTable],
    unstamped: Unstamped,
) -> Result<(), KfmcError> {
    let sources = (files
        .iter()
        .cloned()
        .map(crate::score::EstimatesSource::File))
    .chain(
        tables
            .iter()
            .cloned()
            .map(crate::score::EstimatesSource::Table),
    )
    .map(Ok);
    attach_estimates_from(plan, sources, unstamped)
}

/// [`attach_estimates_with_tables`] from sources taken one at a time
/// ([`crate::score::EstimateSet::load_from`]): a producer's tables are read and dropped as
/// they come.
pub fn attach_estimates_from(
    plan: &mut Plan,
    sources: impl IntoIterator<Item = Result<crate::score::EstimatesSource, crate::error::OutputError>>,
    unstamped: Unstamped,
) -> Result<(), KfmcError> {
    let set = crate::score::EstimateSet::load_from(&plan.study_keys(), sources)?;
    if let Some(truth) = &plan.truth {
        refuse_runs_without_truth(plan, truth, &set)?;
    }
    let stamp = format!(
        "{} = {}, {} = {}",
        crate::score::STAMP_KEY,
        plan.world_stamp(),
        crate::score::SEED_KEY,
        plan.master_seed
    );
    for path in set.unstamped() {
        match unstamped {
            Unstamped::Warn => eprintln!(
                "warning: {} carries no world stamp: nothing ties its rows to this study's runs (estimates of another simulation would be judged as data). A writer stamps its file with the metadata {stamp} (`kfmc schema estimates SPEC` shows them)",
                path.display()
            ),
            Unstamped::Refuse => {
                return Err(OutputError::Format {
                    path: path.clone(),
                    message: format!(
                        "carries no world stamp; kfmc check judges only estimates tied to the spec's runs: stamp the file with the metadata {stamp}, or pass --allow-unstamped{}",
                        if set.is_table(path) {
                            " (in Python: allow_unstamped=True; a kfmc.Estimates made on the simulation, or a pyarrow Table read from a stamped file, carries the stamp)"
                        } else {
                            ""
                        }
                    ),
                }
                .into());
            }
        }
    }
    for m in set.missing_runs() {
        eprintln!("warning: {}", missing_runs_text(plan, &m));
    }
    plan.estimates = Some(std::sync::Arc::new(set));
    Ok(())
}

/// Reads a user's truth table into a recorded plan (`kfmc score --truth`, `kfmc check
/// --truth`): `files` and then the tables in memory `frames` (name, rows), checked against
/// the spec ([`crate::exchange::recorded`]). Its content hash becomes the plan's world stamp,
/// so attach it before the estimates. A run the table leaves out is missing (a warning says
/// how many), as is a run an outside filter's estimates leave out.
pub fn attach_truth(
    plan: &mut Plan,
    files: &[std::path::PathBuf],
    frames: &[(String, polars::prelude::DataFrame)],
) -> Result<(), KfmcError> {
    let name = files
        .first()
        .cloned()
        .or_else(|| frames.first().map(|(n, _)| n.into()))
        .unwrap_or_else(|| "--truth".into());
    if !plan.system.recorded() {
        return Err(OutputError::Mismatch {
            path: name,
            why: format!(
                "is a truth table, but the spec {} simulates its own truth (model.kind = \"{}\"); a truth table is judged with a spec of model.kind = \"{}\", and a kfmc simulation with `kfmc score SIM_DIR --estimates …`",
                plan.spec_path.display(),
                plan.kind,
                crate::systems::recorded::KIND,
            ),
        }
        .into());
    }
    let table = crate::exchange::recorded::RecordedTable::read(plan.truth_keys(), files, frames)?;
    let missing = table.missing_runs();
    if let Some(&(cell, run)) = missing.first() {
        let scales = plan.noise_scales.len();
        eprintln!(
            "warning: {}: the truth leaves {} of the spec's {} runs out (first: scenario {}, noise scale {}, run {run}); they are missing, and a `kfmc check` case judged on the declared runs is incomplete without them",
            name.display(),
            missing.len(),
            plan.runs * plan.scenarios.len() * scales,
            plan.scenarios[cell / scales].name,
            plan.noise_scales[cell % scales]
        );
    }
    plan.settings.truth = Some(std::sync::Arc::new(table));
    Ok(())
}

/// The plan that judges a user's truth table `truth` with the recorded spec `spec` (`kfmc
/// score --truth`): the spec parsed, its output `out` (default the spec's `output`), and the
/// truth attached ([`attach_truth`]). The estimates are the caller's.
pub fn recorded_plan(
    spec: &Path,
    truth: &Path,
    out: Option<std::path::PathBuf>,
    registry: &crate::system::Registry,
) -> Result<Plan, KfmcError> {
    let mut plan = crate::experiment::load_with(spec, registry)?;
    if let Some(out) = out {
        plan.output = out;
    }
    attach_truth(&mut plan, &[truth.to_path_buf()], &[])?;
    Ok(plan)
}

/// Stamps estimates files with `plan`'s world ([`Plan::stamp_metadata`]: for a recorded plan
/// with its truth attached, the truth's content hash), in place and atomically: the rows and
/// the file's other metadata are kept, the two stamp keys set (`kfmc stamp`). A file is read
/// whole, so this is for files that fit in memory.
pub fn stamp_estimates(plan: &Plan, files: &[std::path::PathBuf]) -> Result<(), KfmcError> {
    let stamp = plan.stamp_metadata();
    for path in files {
        let polars = |action, source| OutputError::Polars {
            action,
            path: path.clone(),
            source,
        };
        let open = || {
            crate::output::atomic::open_input(path).map_err(|source| OutputError::Io {
                action: "cannot open",
                path: path.clone(),
                source,
            })
        };
        if !crate::output::table::starts_as_parquet(&open()?) {
            return Err(OutputError::Format {
                path: path.clone(),
                message: "estimates must be Parquet (got a CSV?): the file does not begin with Parquet's `PAR1` marker".into(),
            }
            .into());
        }
        let mut reader = ParquetReader::new(open()?);
        let meta = reader
            .get_metadata()
            .map_err(|e| polars("cannot read", e))?
            .clone();
        let mut pairs: Vec<(String, String)> = meta
            .key_value_metadata()
            .iter()
            .flatten()
            .filter(|kv| !stamp.iter().any(|(k, _)| *k == kv.key))
            .map(|kv| (kv.key.clone(), kv.value.clone().unwrap_or_default()))
            .collect();
        pairs.extend(stamp.iter().cloned());
        let mut df = ParquetReader::new(open()?)
            .finish()
            .map_err(|e| polars("cannot read", e))?;
        let mut bytes = Vec::new();
        ParquetWriter::new(&mut bytes)
            .with_compression(ParquetCompression::Zstd(None))
            .with_key_value_metadata(Some(
                polars::io::parquet::write::KeyValueMetadata::from_static(pairs),
            ))
            .finish(&mut df)
            .map_err(|e| polars("cannot write", e))?;
        crate::output::atomic::write_atomic(path, &bytes).map_err(|source| OutputError::Io {
            action: "cannot write",
            path: path.clone(),
            source,
        })?;
    }
    Ok(())
}

/// Refuses estimates of a run the truth leaves out: nothing to judge them against.
fn refuse_runs_without_truth(
    plan: &Plan,
    truth: &crate::exchange::recorded::RecordedTable,
    set: &crate::score::EstimateSet,
) -> Result<(), KfmcError> {
    let scales = plan.noise_scales.len();
    for (cell, run) in truth.missing_runs() {
        if let Some((label, path)) = set.gives_run(cell, run) {
            return Err(OutputError::Format {
                path,
                message: format!(
                    "filter {label} gives estimates for scenario {}, noise scale {}, run {run}, which the truth table leaves out: nothing to judge them against",
                    plan.scenarios[cell / scales].name,
                    plan.noise_scales[cell % scales]
                ),
            }
            .into());
        }
    }
    Ok(())
}

/// What `kfmc score` and `kfmc check` say of an external filter's missing runs.
pub fn missing_runs_text(plan: &Plan, m: &crate::score::MissingRuns) -> String {
    let first = m
        .first
        .map(|(cell, run)| {
            let scales = plan.noise_scales.len();
            format!(
                "; first: scenario {}, noise scale {}, run {run}",
                plan.scenarios[cell / scales].name,
                plan.noise_scales[cell % scales]
            )
        })
        .unwrap_or_default();
    format!(
        "the estimates of {} leave {} of its {} runs out{first}: they are missing (status `missing` in runs.parquet), not failures; no statistic counts them, and a `kfmc check` case judged on the declared runs is incomplete without them",
        m.filter, m.runs, m.of
    )
}
