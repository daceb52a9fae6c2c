//! The experiment role: TOML spec → validated [`Plan`].
//!
//! Two phases, as cargo-nextest does it: [`spec`] holds serde types that mirror the file
//! (unknown keys are errors), [`plan`] validates them into typed values, reporting every
//! problem at once with the file and the key path (`filters[1].q_std: …`).

pub mod checker;
pub mod plan;
pub mod spec;

use std::path::Path;

pub use checker::{Checker, non_negative, positive};
pub use plan::{FilterNoiseMode, FilterPlan, InitialMode, Overrides, Plan, PlanSize, ScenarioPlan};

use crate::error::{SpecError, SpecErrors};
use crate::system::Registry;

/// Reads, parses and validates a spec file against the built-in systems.
pub fn load(path: &Path) -> Result<Plan, SpecErrors> {
    load_with(path, &Registry::builtin())
}

/// Parses and validates spec text against the built-in systems; `path` names it in errors.
pub fn parse(text: &str, path: &Path) -> Result<Plan, SpecErrors> {
    parse_with(text, path, &Registry::builtin())
}

/// Reads, parses and validates a spec file; `registry` supplies the systems.
pub fn load_with(path: &Path, registry: &Registry) -> Result<Plan, SpecErrors> {
    use std::io::Read;
    let one = |message: String| {
        SpecErrors(vec![SpecError {
            file: path.to_path_buf(),
            key_path: String::new(),
            message,
        }])
    };
    let file = std::fs::File::open(path).map_err(|e| one(format!("cannot read the spec: {e}")))?;
    // Read at most one byte past the cap, so `/dev/zero` or a huge file is refused, not read.
    let mut bytes = Vec::new();
    file.take(plan::limits::MAX_SPEC_BYTES + 1)
        .read_to_end(&mut bytes)
        .map_err(|e| one(format!("cannot read the spec: {e}")))?;
    if bytes.len() as u64 > plan::limits::MAX_SPEC_BYTES {
        return Err(one(format!(
            "larger than {} bytes; a spec is a small TOML file",
            plan::limits::MAX_SPEC_BYTES
        )));
    }
    let text = String::from_utf8(bytes).map_err(|e| one(format!("not UTF-8 text: {e}")))?;
    parse_with(&text, path, registry)
}

/// Parses and validates spec text; `path` names it in errors, `registry` supplies the systems.
pub fn parse_with(text: &str, path: &Path, registry: &Registry) -> Result<Plan, SpecErrors> {
    let one = |key_path: String, message: String| {
        SpecErrors(vec![SpecError {
            file: path.to_path_buf(),
            key_path,
            message,
        }])
    };
    let de =
        toml::de::Deserializer::parse(text).map_err(|e| one(String::new(), with_line(text, e)))?;
    let spec: spec::Spec = serde_path_to_error::deserialize(de).map_err(|e| {
        let path = checker::format_path(e.path());
        one(path, with_line(text, e.into_inner()))
    })?;
    plan::validate(spec, path, text, registry)
}

/// The TOML error's message with its line and column (1-based; the column counts characters).
/// A syntax error stops everything else, so the position is all the help there is.
fn with_line(text: &str, e: toml::de::Error) -> String {
    let msg = e.message().trim().to_string();
    match e.span() {
        Some(span) => {
            let mut at = span.start.min(text.len());
            while !text.is_char_boundary(at) {
                at -= 1;
            }
            let before = &text[..at];
            let line = before.matches('\n').count() + 1;
            let column = before.rsplit('\n').next().map_or(0, |l| l.chars().count()) + 1;
            format!("{msg} (line {line}, column {column})")
        }
        None => msg,
    }
}
