//! External filters' estimates attached to a plan before its study runs, with the world
//! stamp that ties them to the spec's runs.

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
