//! `kfmc check`: evaluates a spec's `[check]` assertions against the tables a study wrote,
//! and renders them as a readable table and as JUnit XML for CI systems.

mod estimates;
mod judge;
mod paired;
mod power;
mod report;
mod tables;

use std::path::Path;

use crate::error::KfmcError;
use crate::experiment::Plan;

pub use estimates::{
    Unstamped, attach_estimates, attach_estimates_from, attach_estimates_with_tables, attach_truth,
    missing_runs_text, recorded_plan, stamp_estimates,
};
pub use judge::evaluate;
pub use paired::{PairedExcess, paired_excess_test};
pub use power::evaluate_power;
pub use report::{junit, render, tally};

/// What the verdict of a filter without innovations says, in the check's report and in
/// Python's `Study.verdict()`: the NIS half of the verdict has no data.
pub const NO_INNOVATIONS: &str = "not judged: no innovations";

/// One evaluated test case (an assertion applied to one cell the spec declares).
#[derive(Clone, Debug, PartialEq)]
pub struct CaseResult {
    /// The assertion kind (`consistent`, `rmse_below`, …).
    pub kind: String,
    /// The case name, e.g. `consistent[basic noise=1 ekf q=1 r=1]` (an external filter,
    /// which carries no multipliers, by its label alone: `consistent[basic noise=1 mine]`).
    pub name: String,
    /// Whether it holds: judged on every run the spec declares, and the assertion holds.
    pub pass: bool,
    /// Whether it could not be judged on the runs the spec declares (runs missing, too many
    /// numerical failures, a test that could not be computed): never a pass, and reported
    /// apart from a failure (`kfmc check` exits 4 when nothing failed but something is
    /// incomplete).
    pub incomplete: bool,
    /// The numbers behind the outcome.
    pub detail: String,
}

impl CaseResult {
    /// A case judged on its data: it holds or it fails.
    fn judged(kind: &str, name: String, pass: bool, detail: String) -> Self {
        CaseResult {
            kind: kind.into(),
            name,
            pass,
            incomplete: false,
            detail,
        }
    }
    /// A case that could not be judged on the runs the spec declares.
    fn incomplete(kind: &str, name: String, why: String) -> Self {
        CaseResult {
            kind: kind.into(),
            name,
            pass: false,
            incomplete: true,
            detail: format!("incomplete: {why}"),
        }
    }
}

/// The gate's exit code when an assertion failed.
pub const EXIT_CHECK_FAILED: u8 = 3;
/// The gate's exit code when no assertion failed but a case could not be judged on the runs
/// the spec declares (incomplete).
pub const EXIT_CHECK_INCOMPLETE: u8 = 4;

/// What `kfmc check` found: the evaluated cases of one spec, as the CLI prints them and the
/// Python module returns them.
#[derive(Clone, Debug, PartialEq)]
pub struct CheckOutcome {
    /// The binary that ran the check (`kfmc` or a plugin crate's): the report's header and
    /// the JUnit suite name it.
    pub program: String,
    /// The experiment's name.
    pub experiment: String,
    /// Every evaluated case, in the order the report lists them.
    pub cases: Vec<CaseResult>,
    /// Wall-clock seconds of the studies behind the cases.
    pub wall_s: f64,
}

impl CheckOutcome {
    /// Failed and incomplete cases ([`tally`]).
    pub fn tally(&self) -> (usize, usize) {
        tally(&self.cases)
    }
    /// The readable report ([`render`]).
    pub fn render(&self) -> String {
        render(&self.program, &self.experiment, &self.cases)
    }
    /// The JUnit XML ([`junit`]).
    pub fn junit(&self) -> String {
        junit(&self.program, &self.experiment, &self.cases, self.wall_s)
    }
    /// The gate's exit code: 0 all hold, 3 one failed (a judged failure outranks a case that
    /// could not be judged), 4 none failed but one is incomplete.
    pub fn exit_code(&self) -> u8 {
        match self.tally() {
            (0, 0) => 0,
            (0, _) => EXIT_CHECK_INCOMPLETE,
            _ => EXIT_CHECK_FAILED,
        }
    }
}

/// Why [`run`] stopped: an invalid request (reported as it is), or a failure of one stage,
/// which the CLI prefixes with `context` (`running SPEC`, `evaluating the assertions`).
#[derive(Debug, thiserror::Error)]
pub enum RunError {
    /// The spec or the request is invalid (no assertion, no replications, over a limit).
    #[error(transparent)]
    Invalid(KfmcError),
    /// A stage failed.
    #[error("{context}")]
    Stage {
        /// What was being done.
        context: String,
        /// The cause (boxed: a `Result` carrying it stays small).
        #[source]
        source: Box<KfmcError>,
    },
}

impl RunError {
    /// The library error underneath, whatever the stage.
    pub fn error(&self) -> &KfmcError {
        match self {
            RunError::Invalid(e) => e,
            RunError::Stage { source, .. } => source,
        }
    }
}

/// Runs `kfmc check`'s studies for `plan` (loaded from `spec`, overrides applied, external
/// filters' estimates attached) and evaluates its `[check]` assertions: the study itself for
/// the per-cell assertions, `replications` (or `check.replications`) replications of it for
/// the rejection-rate ones. Each study gets its own observer from `observer`. Printing and
/// exit codes are the caller's ([`CheckOutcome`]).
pub fn run<O: crate::runner::RunObserver>(
    mut plan: Plan,
    spec: &Path,
    replications: Option<usize>,
    allow_large: bool,
    exec: &crate::study::ExecOptions,
    observer: impl Fn() -> O,
) -> Result<CheckOutcome, RunError> {
    use crate::error::{SpecError, SpecErrors};
    if plan.assertions.is_empty() {
        return Err(RunError::Invalid(KfmcError::Spec(SpecErrors(vec![
            SpecError {
                file: spec.to_path_buf(),
                key_path: "check.assert".into(),
                message: "kfmc check needs at least one [[check.assert]]".into(),
            },
        ]))));
    }
    // Consistency assertions need the tests even when the spec did not ask for them.
    let alpha = plan.alpha;
    plan.consistency
        .get_or_insert(crate::experiment::plan::ConsistencyPlan::at_level(alpha));
    plan.sequential = plan
        .check_gate()
        .map_err(|e| RunError::Invalid(KfmcError::Spec(e)))?;
    let needs_power = plan.assertions.iter().any(|a| a.needs_replications());
    let replications = replications.or(plan.check_replications);
    if let Some(r) = replications.filter(|_| needs_power) {
        crate::study::check_replications(&plan, r, allow_large)
            .map_err(|e| RunError::Invalid(e.into()))?;
    }
    if needs_power && replications.is_none_or(|r| r == 0) {
        return Err(RunError::Invalid(KfmcError::Spec(SpecErrors(vec![
            SpecError {
                file: spec.to_path_buf(),
                key_path: "check.replications".into(),
                message: "a rejection_rate assertion is judged over replications of the whole study: set check.replications ≥ 1 or pass --replications R".into(),
            },
        ]))));
    }
    let stage = |context: String| {
        move |source: KfmcError| RunError::Stage {
            context,
            source: Box::new(source),
        }
    };
    let mut cases = Vec::new();
    let mut wall_s = 0.0;
    if plan.assertions.iter().any(|a| !a.needs_replications()) {
        // Judged while still held: the tables read back are this study's.
        let (report, _held) = crate::study::run_locked(&plan, exec, &observer())
            .map_err(stage(format!("running {}", spec.display())))?;
        wall_s += report.wall_s;
        cases.extend(
            evaluate(&plan, &report.output)
                .map_err(KfmcError::from)
                .map_err(stage("evaluating the assertions".into()))?,
        );
    }
    if let Some(r) = replications.filter(|_| needs_power) {
        let out = plan.output.join("power");
        let mut power_plan = plan.clone();
        power_plan.output = out.clone();
        // Rejection rates are those of the fixed-N tests the assertions name.
        power_plan.sequential = None;
        let report = crate::power::power(&power_plan, r, plan.master_seed, &out, exec, &observer())
            .map_err(stage(format!(
                "running {} replications of {}",
                r,
                spec.display()
            )))?;
        wall_s += report.wall_s;
        cases.extend(
            evaluate_power(&plan, &report.output)
                .map_err(KfmcError::from)
                .map_err(stage("evaluating the rejection-rate assertions".into()))?,
        );
    }
    Ok(CheckOutcome {
        program: plan.program.name.to_string(),
        experiment: plan.name.clone(),
        cases,
        wall_s,
    })
}

#[cfg(test)]
mod tests;
