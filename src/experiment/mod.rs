//! The experiment role: TOML spec → validated [`Plan`].
//!
//! Two phases, as cargo-nextest does it: [`spec`] holds serde types that mirror the file
//! (unknown keys are errors), [`plan`] validates them into typed values, reporting every
//! problem at once with the file and the key path (`filters[1].q_std: …`).

pub mod plan;
pub mod spec;
pub mod tune_spec;

use std::path::Path;

pub(crate) use crate::system::checker::{self, Checker};
pub(crate) use crate::system::settings::{FilterPlan, InitialMode};
pub use plan::{Overrides, Plan, PlanSize};

use crate::error::{SpecError, SpecErrors};
use crate::system::Registry;

/// Reads, parses and validates a spec file against the built-in systems.
pub fn load(path: &Path) -> Result<Plan, SpecErrors> {
    load_with(path, &crate::systems::builtin())
}

/// Parses and validates spec text against the built-in systems; `path` names it in errors.
pub fn parse(text: &str, path: &Path) -> Result<Plan, SpecErrors> {
    parse_with(text, path, &crate::systems::builtin())
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
    let file = crate::output::atomic::open_input(path)
        .map_err(|e| one(format!("cannot read the spec: {e}")))?;
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
///
/// Every problem is reported in one pass. The spec's structure is read first: each key of
/// the wrong type and each unknown key is reported and set aside, and reading goes on. When
/// the only such problems were unknown keys (typos), which change nothing, the spec is then
/// validated as usual and its problems are added; a value of the wrong type stops there,
/// since validating what stands in for it would report its consequences as new problems. A
/// TOML syntax error stops at once (nothing else can be read).
pub fn parse_with(text: &str, path: &Path, registry: &Registry) -> Result<Plan, SpecErrors> {
    let de = toml::de::Deserializer::parse(text).map_err(|e| {
        SpecErrors(vec![SpecError {
            file: path.to_path_buf(),
            key_path: String::new(),
            message: with_line(text, e),
        }])
    })?;
    let first = match serde_path_to_error::deserialize::<_, spec::Spec>(de) {
        Ok(spec) => return plan::validate(spec, path, text, registry),
        Err(e) => e,
    };
    // The first problem as the text's own parser saw it (with its column), then every other.
    let inner = checker::format_path(first.path());
    let message = with_line(text, first.into_inner());
    let document: toml::Table = text.parse().map_err(|e: toml::de::Error| {
        SpecErrors(vec![SpecError {
            file: path.to_path_buf(),
            key_path: String::new(),
            message: with_line(text, e),
        }])
    })?;
    let mut c = Checker::new(path, text);
    let parsed =
        c.parse_all::<spec::Spec>("", toml::Value::Table(document), Some((inner, message)));
    match parsed.value {
        Some(spec) if parsed.sound => plan::validate_into(c, spec, registry),
        _ => Err(SpecErrors(c.into_errors())),
    }
}

/// The TOML error's message with its line and column (1-based; the column counts characters).
/// A syntax error stops everything else, so the position is all the help there is.
fn with_line(text: &str, e: toml::de::Error) -> String {
    let msg = checker::with_suggestion(e.message().trim());
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
