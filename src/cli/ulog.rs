//! `kfmc ulog`: PX4 flight logs. `inspect` says what a log holds for a NIS verdict; `nis`
//! judges the innovations of one log or a folder of logs, with `kfmc check`'s exit codes
//! (0 pass, 3 a test failed, 4 incomplete and none failed, 2 usage, 1 error).

use super::*;
use crate::ulog::{InstanceSelection, NisError, NisOptions};

/// The arguments of `kfmc ulog`.
#[derive(Debug, clap::Args)]
pub struct Ulog {
    /// What to do with the logs.
    #[command(subcommand)]
    pub command: UlogCommand,
}

/// `kfmc ulog`'s commands.
#[derive(Debug, Subcommand)]
pub enum UlogCommand {
    /// Print what a log holds for a NIS verdict: firmware, EKF instances and the primary over
    /// time, aid sources with their rates, how many innovations pair with a variance,
    /// EKF2_LOG_VERBOSE and the gates, and what cannot be judged and why.
    Inspect(Inspect),
    /// Judge the NIS of every aid source and axis of a log (or every .ulg under a folder)
    /// with a calibrated batch-means verdict; write ulog_samples.parquet and
    /// ulog_summary.parquet. Exit 0 when all pass, 3 when one fails (or regressed against
    /// --baseline), 4 when none fails but one is incomplete.
    Nis(Nis),
    /// Write flight logs of a simulated filter with a known S (ULog, as PX4 writes them):
    /// the test set (consistent, over-confident, over-conservative, correlated, a reset,
    /// non-stationary, a primary switch, the innovations topics, a low gate, an hour), or
    /// --count consistent ten-minute flights.
    Simulate(SimulateLogs),
}

/// The arguments of `kfmc ulog simulate`.
#[derive(Debug, clap::Args)]
pub struct SimulateLogs {
    /// The folder the logs are written into (created if needed).
    pub dir: PathBuf,
    /// Write this many consistent flights (`flight_000.ulg`, …) instead of the test set.
    #[arg(long, value_parser = clap::builder::RangedU64ValueParser::<u64>::new().range(1..=10_000))]
    pub count: Option<u64>,
}

/// The arguments of `kfmc ulog inspect`.
#[derive(Debug, clap::Args)]
pub struct Inspect {
    /// The log (.ulg).
    pub log: PathBuf,
}

/// The arguments of `kfmc ulog nis`.
#[derive(Debug, clap::Args)]
pub struct Nis {
    /// A log (.ulg) or a folder: every .ulg under it is judged.
    pub path: PathBuf,
    /// The EKF instances judged: `primary` (the primary's innovations, split where it
    /// changes), `all` (each instance on its own) or an instance number.
    #[arg(long, default_value = "primary", value_parser = instance)]
    pub instance: InstanceSelection,
    /// Only these aid sources (e.g. gnss_vel baro_hgt); default: every source.
    #[arg(long, num_args = 1..)]
    pub sensors: Vec<String>,
    /// The family-wise significance level of each log's verdict (Bonferroni over its tests).
    #[arg(long, default_value_t = 0.05, value_parser = alpha)]
    pub alpha: f64,
    /// Seconds left out after an EKF instance starts and after each of its resets.
    #[arg(long, default_value_t = crate::ulog::DEFAULT_HOLDOFF_S, value_parser = seconds)]
    pub holdoff: f64,
    /// Judge samples on the ground too (default: only in the air).
    #[arg(long)]
    pub include_ground: bool,
    /// Output folder.
    #[arg(long, default_value = "results/ulog")]
    pub out: PathBuf,
    /// A stored ulog_summary.parquet: a verdict that got worse or a mean NIS that grew beyond
    /// --tolerance is a failed case (exit 3).
    #[arg(long)]
    pub baseline: Option<PathBuf>,
    /// The relative growth of a mean NIS the regression gate tolerates.
    #[arg(long, default_value_t = crate::ulog::DEFAULT_TOLERANCE, requires = "baseline", value_parser = tolerance)]
    pub tolerance: f64,
    /// Also write the cases as JUnit XML to this file.
    #[arg(long)]
    pub junit: Option<PathBuf>,
    /// No progress bar.
    #[arg(long, short)]
    pub quiet: bool,
    /// Write into a non-empty folder that is not a kfmc result folder, or replace a folder
    /// that holds another command's result.
    #[arg(long)]
    pub force: bool,
}

/// A bar over logs, drawn only when `visible` and stderr is a terminal.
fn log_bar(visible: bool) -> Option<indicatif::ProgressBar> {
    use std::io::IsTerminal;
    if !visible || !std::io::stderr().is_terminal() {
        return None;
    }
    let bar = indicatif::ProgressBar::new(0);
    bar.set_style(
        indicatif::ProgressStyle::with_template(
            "{elapsed_precise} [{wide_bar:.cyan/blue}] {human_pos}/{human_len} logs  ETA {eta}",
        )
        .expect("the template is valid")
        .progress_chars("=> "),
    );
    Some(bar)
}

fn instance(text: &str) -> Result<InstanceSelection, String> {
    text.parse()
}

fn alpha(text: &str) -> Result<f64, String> {
    match text.trim().parse::<f64>() {
        Ok(a) if a > 0.0 && a < 1.0 && !a.is_nan() => Ok(a),
        _ => Err(format!("`{text}` is not a level in (0, 1)")),
    }
}

fn tolerance(text: &str) -> Result<f64, String> {
    match text.trim().parse::<f64>() {
        Ok(t) if t >= 0.0 && t.is_finite() => Ok(t),
        _ => Err(format!(
            "`{text}` is not a relative tolerance ≥ 0 (0.2 = 20 %)"
        )),
    }
}

impl Ulog {
    /// Runs the command.
    pub(super) fn execute(self) -> anyhow::Result<()> {
        match self.command {
            UlogCommand::Inspect(i) => {
                let (text, _) = crate::ulog::inspect::inspect(&i.log)
                    .map_err(|e| anyhow::Error::from(e).context("inspecting a ULog file"))?;
                emit(&text);
                Ok(())
            }
            UlogCommand::Nis(n) => n.execute(),
            UlogCommand::Simulate(s) => {
                use crate::ulog::simulate::{Flight, write};
                let flights = match s.count {
                    None => Flight::presets(),
                    Some(n) => (0..n)
                        .map(|i| Flight::consistent(&format!("flight_{i:03}"), 1000 + i))
                        .collect(),
                };
                std::fs::create_dir_all(&s.dir).map_err(|e| {
                    anyhow::Error::from(e).context(format!("creating {}", s.dir.display()))
                })?;
                for f in &flights {
                    let p = write(f, &s.dir).map_err(|e| {
                        anyhow::Error::from(e).context(format!(
                            "writing {} into {}",
                            f.name,
                            s.dir.display()
                        ))
                    })?;
                    outln!("{}", p.display());
                }
                Ok(())
            }
        }
    }
}

impl Nis {
    fn execute(self) -> anyhow::Result<()> {
        let opts = NisOptions {
            instance: self.instance,
            sensors: self.sensors,
            alpha: self.alpha,
            holdoff_s: self.holdoff,
            include_ground: self.include_ground,
            baseline: self.baseline,
            tolerance: self.tolerance,
            out: self.out,
            force: self.force,
        };
        let bar = log_bar(!self.quiet);
        let outcome = crate::ulog::nis(&self.path, &opts, |i, n| {
            if let Some(b) = &bar {
                b.set_length(n as u64);
                b.set_position(i as u64);
            }
        });
        if let Some(b) = bar {
            b.finish_and_clear();
        }
        let outcome = outcome.map_err(|e| {
            let context = format!("judging {}", self.path.display());
            match e {
                NisError::Usage { flag, message } => anyhow::Error::from(UsageError {
                    flag: flag.into(),
                    message,
                }),
                NisError::Output(o) => anyhow::Error::from(KfmcError::Output(o)).context(context),
                other => anyhow::Error::from(other).context(context),
            }
        })?;
        emit(&outcome.render());
        if !self.quiet {
            outln!(
                "{} log{} judged in {:.2} s; tables in {}:",
                outcome.logs,
                if outcome.logs == 1 { "" } else { "s" },
                outcome.seconds,
                opts.out.display()
            );
            print_tables(&outcome.tables);
        }
        if let Some(path) = self.junit {
            crate::output::folder::write_atomic(&path, outcome.junit().as_bytes()).map_err(
                |e| anyhow::Error::from(e).context(format!("writing {}", path.display())),
            )?;
        }
        let (failed, incomplete) = outcome.tally();
        if failed + incomplete > 0 {
            return Err(CheckFailed {
                failed,
                incomplete,
                total: outcome.cases.len(),
            }
            .into());
        }
        Ok(())
    }
}
