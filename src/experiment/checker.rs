//! [`Checker`]: collects every validation problem of a spec with its file and key path.
//!
//! Validation reports all problems at once (as cargo-nextest does for its config) instead of
//! stopping at the first; systems use the same checker for their own tables, so a user's
//! system gets the same `filters[1].gain: …` messages, with line numbers, as the built-ins.

use std::path::{Path, PathBuf};

use serde::de::DeserializeOwned;

use super::spec::OneOrMany;
use crate::error::SpecError;

/// Collects validation errors with the file name attached.
#[derive(Debug)]
pub struct Checker {
    file: PathBuf,
    text: String,
    errors: Vec<SpecError>,
}

impl Checker {
    /// A checker for the spec `file` whose text is `text` (used to find line numbers).
    pub fn new(file: &Path, text: &str) -> Self {
        Checker {
            file: file.to_path_buf(),
            text: text.to_string(),
            errors: Vec::new(),
        }
    }

    /// The spec file.
    pub fn file(&self) -> &Path {
        &self.file
    }

    /// Records a problem at `key` (a key path such as `filters[1].q_std`).
    pub fn err(&mut self, key: impl Into<String>, msg: impl Into<String>) {
        self.errors.push(SpecError {
            file: self.file.clone(),
            key_path: key.into(),
            message: msg.into(),
        });
    }

    /// Whether no problem has been recorded.
    pub fn is_clean(&self) -> bool {
        self.errors.is_empty()
    }

    /// Number of problems recorded so far (to tell whether a section added any).
    pub fn error_count(&self) -> usize {
        self.errors.len()
    }

    /// The problems, in the order found.
    pub fn into_errors(self) -> Vec<SpecError> {
        self.errors
    }

    /// Deserializes `table` (the table at key path `prefix`) into `T`. A type with
    /// `#[serde(deny_unknown_fields)]` rejects unknown keys; the error names the full key path
    /// and the line in the spec.
    pub fn parse<T: DeserializeOwned>(&mut self, prefix: &str, table: &toml::Table) -> Option<T> {
        let value = toml::Value::Table(table.clone());
        match serde_path_to_error::deserialize::<_, T>(value) {
            Ok(v) => Some(v),
            Err(e) => {
                let inner = e.path().to_string();
                let key = match (prefix.is_empty(), inner.as_str()) {
                    (_, "." | "") => prefix.to_string(),
                    (true, p) => p.to_string(),
                    (false, p) if p.starts_with('[') => format!("{prefix}{p}"),
                    (false, p) => format!("{prefix}.{p}"),
                };
                let msg = e.into_inner().message().trim().to_string();
                let msg = match line_of(&self.text, &key) {
                    Some(line) => format!("{msg} (line {line})"),
                    None => msg,
                };
                self.err(key, msg);
                None
            }
        }
    }

    /// Reports every key of `keys` (name, present) that is set although `prefix`'s kind does
    /// not use it: a silently ignored key would be a silent mistake in the study.
    pub fn reject_present(&mut self, prefix: &str, keys: &[(&str, bool)], message: &str) {
        for (k, present) in keys {
            if *present {
                self.err(format!("{prefix}.{k}"), message);
            }
        }
    }

    /// Expands a scalar-or-list to `n` components, checking each with `ok`.
    pub fn vector(
        &mut self,
        key: &str,
        v: Option<&OneOrMany>,
        n: usize,
        default: &[f64],
        ok: fn(f64) -> bool,
        what: &str,
    ) -> Vec<f64> {
        let out = match v {
            None => default.to_vec(),
            Some(OneOrMany::One(x)) => vec![*x; n],
            Some(OneOrMany::Many(xs)) if xs.len() == n => xs.clone(),
            Some(OneOrMany::Many(xs)) => {
                self.err(key, format!("expected 1 or {n} values, got {}", xs.len()));
                return default.to_vec();
            }
        };
        for (i, x) in out.iter().enumerate() {
            if !ok(*x) {
                let k = if matches!(v, Some(OneOrMany::Many(_))) {
                    format!("{key}[{i}]")
                } else {
                    key.to_string()
                };
                self.err(k, format!("{x} is not {what}"));
                break;
            }
        }
        out
    }

    /// The transitions K = round(duration / Δt) of a scenario at key path `key` (reported at
    /// `key.duration_s`): at least one sample, at most [`super::plan::limits::MAX_STEPS`].
    /// Systems call this before expanding a scenario, so an absurd duration is an error,
    /// never an allocation failure.
    pub fn scenario_steps(&mut self, key: &str, duration_s: f64, dt_s: f64) -> Option<usize> {
        let max = super::plan::limits::MAX_STEPS;
        if !positive(duration_s) || !positive(dt_s) || duration_s < dt_s {
            self.err(
                format!("{key}.duration_s"),
                format!("{duration_s} is shorter than one sample"),
            );
            return None;
        }
        let steps = (duration_s / dt_s).round();
        if steps > max as f64 {
            self.err(
                format!("{key}.duration_s"),
                format!("{duration_s} s is {steps} steps of {dt_s} s; at most {max} per run"),
            );
            return None;
        }
        Some(steps as usize)
    }

    /// A string option with a default, which must be one of `allowed`.
    pub fn choice<'a>(
        &mut self,
        key: &str,
        v: Option<&'a str>,
        default: &'a str,
        allowed: &[&str],
    ) -> &'a str {
        let s = v.unwrap_or(default);
        if !allowed.contains(&s) {
            self.err(
                key,
                format!(
                    "unknown value `{s}`; expected one of: {}",
                    allowed.join(", ")
                ),
            );
        }
        s
    }
}

/// Whether `x` is a finite positive number.
pub fn positive(x: f64) -> bool {
    x.is_finite() && x > 0.0
}

/// Whether `x` is a finite non-negative number.
pub fn non_negative(x: f64) -> bool {
    x.is_finite() && x >= 0.0
}

/// The 1-based line of the value at `key_path` (`filters[1].q_std`, `model.dt_s`) in a TOML
/// document, or of the deepest enclosing key that exists.
pub fn line_of(text: &str, key_path: &str) -> Option<usize> {
    let doc = toml::de::DeTable::parse(text).ok()?;
    let mut span: Option<std::ops::Range<usize>> = None;
    let mut table = Some(doc.get_ref());
    let mut value: Option<&toml::de::DeValue<'_>> = None;
    for part in key_path.split('.') {
        let (name, indices) = match part.find('[') {
            Some(i) => (&part[..i], &part[i..]),
            None => (part, ""),
        };
        let entry = table?.iter().find(|(k, _)| k.get_ref() == name)?;
        span = Some(entry.0.span());
        let mut v = entry.1;
        for idx in indices
            .split(['[', ']'])
            .filter(|s| !s.is_empty())
            .filter_map(|s| s.parse::<usize>().ok())
        {
            match v.get_ref().get(idx) {
                Some(next) => {
                    v = next;
                    span = Some(v.span());
                }
                None => break,
            }
        }
        value = Some(v.get_ref());
        table = value.and_then(|v| v.as_table());
    }
    let _ = value;
    let start = span?.start.min(text.len());
    Some(text[..start].matches('\n').count() + 1)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn line_of_finds_nested_keys_and_array_entries() {
        let text = "runs = 3\n[model]\nkind = \"x\"\ndt_s = 0.1\n[[filters]]\nlabel = \"a\"\n[[filters]]\nlabel = \"b\"\nq_std = 2\n";
        assert_eq!(line_of(text, "runs"), Some(1));
        assert_eq!(line_of(text, "model.dt_s"), Some(4));
        assert_eq!(line_of(text, "filters[1].q_std"), Some(9));
        assert_eq!(line_of(text, "filters[0].label"), Some(6));
        assert_eq!(line_of(text, "nothing"), None);
    }
}
