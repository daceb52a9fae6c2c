//! [`Checker`]: collects every validation problem of a spec with its file and key path.
//!
//! Validation reports all problems at once (as cargo-nextest does for its config) instead of
//! stopping at the first; systems use the same checker for their own tables, so a user's
//! system gets the same `filters[1].gain: …` messages, with line numbers, as the built-ins.

use std::path::{Path, PathBuf};

use serde::de::DeserializeOwned;

use super::spec_values::OneOrMany;
use crate::error::SpecError;

/// Collects validation errors with the file name attached.
#[derive(Debug)]
pub struct Checker {
    file: PathBuf,
    text: String,
    errors: Vec<SpecError>,
    /// Samples (K + 1) of the scenarios counted by [`Checker::scenario_steps`] so far.
    samples: u64,
}

impl Checker {
    /// A checker for the spec `file` whose text is `text` (used to find line numbers).
    pub fn new(file: &Path, text: &str) -> Self {
        Checker {
            file: file.to_path_buf(),
            text: text.to_string(),
            errors: Vec::new(),
            samples: 0,
        }
    }

    /// The spec file.
    pub fn file(&self) -> &Path {
        &self.file
    }

    /// The spec text.
    pub fn text(&self) -> &str {
        &self.text
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
    /// and the line in the spec, and an unknown key gets the closest allowed one as a
    /// suggestion.
    ///
    /// Every problem of the table is reported, not only the first: after a problem the
    /// offending key is set aside and the table is read again, so a typo in one key does not
    /// hide a bad value in another. When every problem was an unknown key the result is the
    /// table without them (an unknown key changes nothing, and each was reported), so the
    /// caller goes on to validate the values; otherwise `None`, since checks on a value that
    /// stands in for an unusable one would report its consequences as new problems.
    pub fn parse<T: DeserializeOwned>(&mut self, prefix: &str, table: &toml::Table) -> Option<T> {
        let parsed = self.parse_all(prefix, toml::Value::Table(table.clone()), None);
        parsed.value.filter(|_| parsed.sound)
    }

    /// [`Checker::parse`] of `value` at `prefix`, with the first problem already found by
    /// the caller (`first`: its key path inside `value` and its message, which then is
    /// reported as given: the spec's top level reads the text itself, whose errors carry a
    /// column too).
    pub(crate) fn parse_all<T: DeserializeOwned>(
        &mut self,
        prefix: &str,
        mut value: toml::Value,
        mut first: Option<(String, String)>,
    ) -> Parsed<T> {
        // Key paths (inside `value`) set aside after their problem was reported.
        let mut removed: Vec<String> = Vec::new();
        let mut sound = true;
        loop {
            let (inner, msg) = match first.take() {
                Some(found) => found,
                None => match serde_path_to_error::deserialize::<_, T>(value.clone()) {
                    Ok(v) => {
                        return Parsed {
                            value: Some(v),
                            sound,
                        };
                    }
                    Err(e) => {
                        let inner = format_path(e.path());
                        let msg = with_suggestion(e.into_inner().message().trim());
                        let msg = match line_of(&self.text, &join_key(prefix, &inner)) {
                            Some(line) => format!("{msg} (line {line})"),
                            None => msg,
                        };
                        (inner, msg)
                    }
                },
            };
            // A key set aside because its value was unusable now reads as missing: that
            // problem was reported already. The table holding it cannot be read without it,
            // so it is set aside whole and the rest is read on.
            if let Some(field) = missing_field(&msg)
                && removed
                    .iter()
                    .any(|r| *r == join_key(&inner, &path_key(field)))
            {
                sound = false;
                if remove_key(&mut value, &inner).is_none() {
                    return Parsed { value: None, sound };
                }
                continue;
            }
            let unknown = msg.starts_with("unknown field");
            self.err(join_key(prefix, &inner), msg);
            match remove_key(&mut value, &inner) {
                Some(()) => {
                    sound &= unknown;
                    removed.push(inner);
                }
                None => {
                    return Parsed {
                        value: None,
                        sound: false,
                    };
                }
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
    ///
    /// `None` gives `default` unchecked: the key is not in the file, so an error here would
    /// name a key the user never wrote; a caller whose default comes from elsewhere in the
    /// spec checks it and reports it at a key that exists. After an error the result is
    /// `default`, so a value derived from this one never repeats the error elsewhere.
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
            None => return default.to_vec(),
            Some(OneOrMany::One(x)) => vec![*x; n],
            Some(OneOrMany::Many(xs)) if xs.len() == n => xs.clone(),
            Some(OneOrMany::Many(xs)) => {
                let got = match xs.len() {
                    0 => "an empty list".to_string(),
                    1 => "a list of 1".to_string(),
                    k => format!("a list of {k}"),
                };
                let msg = self.with_line(
                    key,
                    format!("expected a number or a list of {n} numbers, got {got}"),
                );
                self.err(key, msg);
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
                let msg = self.with_line(&k, format!("{x} is not {what}"));
                self.err(k, msg);
                return default.to_vec();
            }
        }
        out
    }

    /// Checks one number read at `key` with `ok`, recording "`x` is not `what`"; returns
    /// whether it passed.
    pub fn number(&mut self, key: &str, x: f64, ok: fn(f64) -> bool, what: &str) -> bool {
        let pass = ok(x);
        if !pass {
            let msg = self.with_line(key, format!("{x} is not {what}"));
            self.err(key, msg);
        }
        pass
    }

    /// `msg` with the line of the value at `key` when the spec holds that very key (a
    /// default's problem has no line of its own).
    fn with_line(&self, key: &str, msg: String) -> String {
        match key_span(&self.text, key, true) {
            Some(span) => {
                let start = span.start.min(self.text.len());
                let line = self.text[..start].matches('\n').count() + 1;
                format!("{msg} (line {line})")
            }
            None => msg,
        }
    }

    /// Whether the spec text holds a value at `key_path` (`scenarios[0].duration_s`), so a
    /// problem with a default can be reported at a key the user wrote.
    pub fn has(&self, key_path: &str) -> bool {
        key_span(&self.text, key_path, true).is_some()
    }

    /// Reports each of `foreign` present in `table` (at `prefix`) with `message` and returns
    /// the table without them: a key of another system then says so, instead of the generic
    /// "unknown field" of the table's own parser.
    pub fn reject_foreign(
        &mut self,
        prefix: &str,
        table: &toml::Table,
        foreign: &[&str],
        message: &str,
    ) -> toml::Table {
        let mut rest = table.clone();
        for k in foreign {
            if rest.remove(*k).is_some() {
                self.err(format!("{prefix}.{k}"), message);
            }
        }
        rest
    }

    /// The transitions K = round(duration / Δt) of a scenario at key path `key` (reported at
    /// `key.duration_s`): at least one sample, at most [`super::limits::MAX_STEPS`], and
    /// with the scenarios counted before it at most
    /// [`super::limits::MAX_TOTAL_SAMPLES`] samples, as systems expand them in memory.
    /// Systems call this before expanding a scenario, so an absurd duration is an error,
    /// never an allocation failure.
    ///
    /// When the scenario has no `duration_s` of its own, `duration_s` is its default and a
    /// problem is reported at `key` (the scenario), saying so.
    pub fn scenario_steps(&mut self, key: &str, duration_s: f64, dt_s: f64) -> Option<usize> {
        let max = super::limits::MAX_STEPS;
        let own = format!("{key}.duration_s");
        let (at, what) = if self.has(&own) {
            (own, format!("{duration_s}"))
        } else {
            (
                key.to_string(),
                format!("the default duration_s = {duration_s}"),
            )
        };
        if !positive(duration_s) {
            self.err(at, format!("{what} is not a positive number of seconds"));
            return None;
        }
        if !positive(dt_s) {
            // Δt is the model's; its own key reports it.
            return None;
        }
        if duration_s < dt_s {
            self.err(
                at,
                format!("{what} s is shorter than one sample (model Δt = {dt_s} s)"),
            );
            return None;
        }
        let steps = (duration_s / dt_s).round();
        if steps > max as f64 {
            self.err(
                at,
                format!("{what} s is {steps} steps of {dt_s} s; at most {max} per run"),
            );
            return None;
        }
        let total = super::limits::MAX_TOTAL_SAMPLES;
        self.samples += steps as u64 + 1;
        if self.samples > total {
            self.err(
                at,
                format!(
                    "the scenarios up to this one hold {} samples (K + 1 each); at most {total} in one spec, as they are expanded in memory to validate it",
                    self.samples
                ),
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
            self.err(key, unknown_value("value", s, allowed.iter().copied()));
        }
        s
    }
}

/// What [`Checker::parse_all`] read.
#[derive(Debug)]
pub(crate) struct Parsed<T> {
    /// The value, without the keys whose problems were reported; `None` when unreadable.
    pub value: Option<T>,
    /// Whether the value can be validated further without reporting consequences of the
    /// problems already reported: true when every key set aside was an unknown one.
    pub sound: bool,
}

/// `inner` below `prefix` as one key path.
fn join_key(prefix: &str, inner: &str) -> String {
    match (prefix.is_empty(), inner) {
        (_, "") => prefix.to_string(),
        (true, p) => p.to_string(),
        (false, p) if p.starts_with('[') => format!("{prefix}{p}"),
        (false, p) => format!("{prefix}.{p}"),
    }
}

/// The field of serde's "missing field `x`".
fn missing_field(msg: &str) -> Option<&str> {
    msg.strip_prefix("missing field `")?.split('`').next()
}

/// Removes the key that `inner` ends in (for `scales[1]`, the whole `scales`) from the table
/// holding it; `None` when `inner` names no key (the value itself).
fn remove_key(value: &mut toml::Value, inner: &str) -> Option<()> {
    if inner.is_empty() {
        return None;
    }
    let parts = key_path_parts(inner)?;
    let (last, up) = parts.split_last()?;
    let mut v = value;
    for (key, indices) in up {
        v = v
            .as_table_mut()?
            .iter_mut()
            .find(|(k, _)| path_key(k) == *key)?
            .1;
        for &i in indices {
            v = v.as_array_mut()?.get_mut(i)?;
        }
    }
    let table = v.as_table_mut()?;
    let name = table.keys().find(|k| path_key(k) == last.0)?.clone();
    table.remove(&name).map(|_| ())
}

/// Serde's "unknown field `runz`, expected one of `runs`, …" with the closest allowed key
/// added ("did you mean `runs`?") when one is close enough to be a typo of it.
pub fn with_suggestion(msg: &str) -> String {
    let Some(rest) = msg.strip_prefix("unknown field `") else {
        return msg.to_string();
    };
    let Some((unknown, allowed)) = rest.split_once('`') else {
        return msg.to_string();
    };
    // The allowed keys are the back-quoted words after the unknown one.
    let candidates = allowed.split('`').skip(1).step_by(2);
    match did_you_mean(unknown, candidates) {
        Some(best) => format!("{msg}; did you mean `{best}`?"),
        None => msg.to_string(),
    }
}

/// "unknown {what} `word`; expected one of: a, b, c", with "; did you mean `b`?" when one of
/// `known` is close enough to be a typo of `word` ([`did_you_mean`]): the message of a tag
/// (`model.kind`, a filter's `kind`, a choice) that names nothing known.
pub fn unknown_value<'a>(
    what: &str,
    word: &str,
    known: impl Iterator<Item = &'a str> + Clone,
) -> String {
    let list: Vec<&str> = known.clone().collect();
    let mut msg = format!(
        "unknown {what} `{word}`; expected one of: {}",
        list.join(", ")
    );
    if let Some(best) = did_you_mean(word, known) {
        msg.push_str(&format!("; did you mean `{best}`?"));
    }
    msg
}

/// The candidate closest to `word` by edit distance, if within a third of its length (at
/// least 1): `runz` → `runs`, `master_sead` → `master_seed`; nothing for an unrelated word.
pub fn did_you_mean<'a>(word: &str, candidates: impl Iterator<Item = &'a str>) -> Option<&'a str> {
    let limit = (word.chars().count() / 3).max(1);
    candidates
        .map(|c| (edit_distance(word, c), c))
        .filter(|(d, _)| *d <= limit)
        .min_by_key(|(d, _)| *d)
        .map(|(_, c)| c)
}

/// Edit distance over characters: insertions, deletions, substitutions and swaps of two
/// neighbours (`q_sdt` is one step from `q_std`), each costing 1.
fn edit_distance(a: &str, b: &str) -> usize {
    let (a, b): (Vec<char>, Vec<char>) = (a.chars().collect(), b.chars().collect());
    let mut d = vec![vec![0usize; b.len() + 1]; a.len() + 1];
    for (i, row) in d.iter_mut().enumerate() {
        row[0] = i;
    }
    for (j, cell) in d[0].iter_mut().enumerate() {
        *cell = j;
    }
    for i in 1..=a.len() {
        for j in 1..=b.len() {
            let cost = usize::from(a[i - 1] != b[j - 1]);
            let mut best = (d[i - 1][j] + 1)
                .min(d[i][j - 1] + 1)
                .min(d[i - 1][j - 1] + cost);
            if i > 1 && j > 1 && a[i - 1] == b[j - 2] && a[i - 2] == b[j - 1] {
                best = best.min(d[i - 2][j - 2] + 1);
            }
            d[i][j] = best;
        }
    }
    d[a.len()][b.len()]
}

/// A key as it stands in a key path: bare when TOML would write it bare (`q_std`), quoted
/// otherwise (`"r_std[θ"`), so a hostile key cannot pass for a path with an index.
pub fn path_key(key: &str) -> String {
    let bare = !key.is_empty()
        && key
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-');
    if bare {
        key.to_string()
    } else {
        format!("\"{}\"", key.escape_debug())
    }
}

/// The key path of a deserialization error (`filters[0].q_std`). The path stops before a
/// segment serde cannot name, so it is always the value's own key or an enclosing one.
pub fn format_path(path: &serde_path_to_error::Path) -> String {
    use serde_path_to_error::Segment;
    let mut out = String::new();
    for seg in path.iter() {
        match seg {
            Segment::Seq { index } => out.push_str(&format!("[{index}]")),
            Segment::Map { key } | Segment::Enum { variant: key } => {
                if !out.is_empty() {
                    out.push('.');
                }
                out.push_str(&path_key(key));
            }
            Segment::Unknown => break,
        }
    }
    out
}

/// Splits a key path into its keys (as [`path_key`] writes them) and each key's array
/// indices: `filters[1].q_std` → `[("filters", [1]), ("q_std", [])]`. `None` when the path
/// is not one kfmc writes.
pub fn key_path_parts(path: &str) -> Option<Vec<(String, Vec<usize>)>> {
    let mut parts = Vec::new();
    let mut chars = path.chars().peekable();
    loop {
        let mut key = String::new();
        if chars.peek() == Some(&'"') {
            key.push(chars.next()?);
            loop {
                let c = chars.next()?;
                key.push(c);
                match c {
                    '\\' => key.push(chars.next()?),
                    '"' => break,
                    _ => {}
                }
            }
        } else {
            while let Some(&c) = chars.peek() {
                if c == '.' || c == '[' {
                    break;
                }
                key.push(c);
                chars.next();
            }
        }
        if key.is_empty() {
            return None;
        }
        let mut indices = Vec::new();
        while chars.peek() == Some(&'[') {
            chars.next();
            let mut digits = String::new();
            loop {
                match chars.next()? {
                    ']' => break,
                    c => digits.push(c),
                }
            }
            indices.push(digits.parse().ok()?);
        }
        parts.push((key, indices));
        match chars.next() {
            None => return Some(parts),
            Some('.') => {}
            Some(_) => return None,
        }
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
    let start = key_span(text, key_path, false)?.start.min(text.len());
    Some(text[..start].matches('\n').count() + 1)
}

/// The span of the value at `key_path` in a TOML document. `exact`: only when every part of
/// the path exists; otherwise the deepest enclosing key that does.
fn key_span(text: &str, key_path: &str, exact: bool) -> Option<std::ops::Range<usize>> {
    let doc = toml::de::DeTable::parse(text).ok()?;
    let mut span: Option<std::ops::Range<usize>> = None;
    let mut table = Some(doc.get_ref());
    for (name, indices) in key_path_parts(key_path)? {
        let found = table.and_then(|t| t.iter().find(|(k, _)| path_key(k.get_ref()) == name));
        let Some(entry) = found else {
            return if exact { None } else { span };
        };
        span = Some(entry.0.span());
        let mut v = entry.1;
        for idx in indices {
            match v.get_ref().get(idx) {
                Some(next) => {
                    v = next;
                    span = Some(v.span());
                }
                None if exact => return None,
                None => return span,
            }
        }
        table = v.get_ref().as_table();
    }
    span
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

    #[test]
    fn odd_keys_are_quoted_in_key_paths() {
        assert_eq!(path_key("q_std"), "q_std");
        assert_eq!(path_key("r_std[θ"), "\"r_std[θ\"");
        let parts = key_path_parts("filters[0].\"r_std[θ\".x[2][3]").unwrap();
        assert_eq!(
            parts,
            [
                ("filters".to_string(), vec![0]),
                ("\"r_std[θ\"".to_string(), vec![]),
                ("x".to_string(), vec![2, 3]),
            ]
        );
        let text = "[[filters]]\n\"r_std[θ\" = 1\n";
        let c = Checker::new(Path::new("t.toml"), text);
        assert!(c.has("filters[0].\"r_std[θ\""));
        assert!(!c.has("filters[0].r_std"));
    }

    /// A value refused by `number` or `vector` names its line, as a parse error does; a
    /// default (not in the file) has no line to name.
    #[test]
    fn value_errors_carry_the_line_of_the_value() {
        let text = "runs = 3\n[model]\nkind = \"x\"\ndt_s = -0.1\n[[filters]]\nlabel = \"a\"\nq_std = [1.0, -2.0]\n";
        let mut c = Checker::new(Path::new("t.toml"), text);
        assert!(!c.number("model.dt_s", -0.1, |x| x > 0.0, "a positive number"));
        assert!(!c.number("model.mass_kg", -1.0, |x| x > 0.0, "a positive number"));
        let q = OneOrMany::Many(vec![1.0, -2.0]);
        c.vector(
            "filters[0].q_std",
            Some(&q),
            2,
            &[1.0, 1.0],
            |x| x >= 0.0,
            "≥ 0",
        );
        c.vector(
            "filters[0].q_std",
            Some(&q),
            3,
            &[1.0; 3],
            |x| x >= 0.0,
            "≥ 0",
        );
        let e: Vec<String> = c.into_errors().iter().map(|e| e.to_string()).collect();
        assert_eq!(
            e[0],
            "t.toml: model.dt_s: -0.1 is not a positive number (line 4)"
        );
        assert_eq!(e[1], "t.toml: model.mass_kg: -1 is not a positive number");
        assert_eq!(e[2], "t.toml: filters[0].q_std[1]: -2 is not ≥ 0 (line 7)");
        assert_eq!(
            e[3],
            "t.toml: filters[0].q_std: expected a number or a list of 3 numbers, got a list of 2 (line 7)"
        );
    }

    #[derive(Debug, serde::Deserialize)]
    #[serde(deny_unknown_fields)]
    #[allow(dead_code)]
    struct Keys {
        runs: Option<u64>,
        alpha: Option<f64>,
        scales: Option<Vec<f64>>,
        label: String,
    }

    /// Three independent mistakes in one table are three problems, each at its own key; the
    /// rest of the table is still read.
    #[test]
    fn parse_reports_every_problem_of_a_table() {
        let text = "[t]\nlabel = \"a\"\nrunz = 3\nalpha = \"x\"\nscales = [1.0, \"y\"]\n";
        let doc: toml::Table = text.parse().unwrap();
        let mut c = Checker::new(Path::new("t.toml"), text);
        // Values stood in for by defaults are not handed on to be validated.
        assert!(c.parse::<Keys>("t", doc["t"].as_table().unwrap()).is_none());
        let e: Vec<String> = c.into_errors().iter().map(|e| e.to_string()).collect();
        assert_eq!(e.len(), 3, "{e:#?}");
        assert!(
            e.iter()
                .any(|m| m.starts_with("t.toml: t.runz: unknown field `runz`")
                    && m.contains("did you mean `runs`?")
                    && m.ends_with("(line 3)")),
            "{e:#?}"
        );
        assert!(
            e.iter()
                .any(|m| m.starts_with("t.toml: t.alpha: invalid type: string \"x\"")),
            "{e:#?}"
        );
        assert!(
            e.iter()
                .any(|m| m.starts_with("t.toml: t.scales[1]: invalid type")),
            "{e:#?}"
        );

        // Unknown keys alone change nothing: the rest of the table is handed on.
        let text = "[t]\nlabel = \"a\"\nrunz = 3\nalhpa = 0.1\nalpha = 0.2\n";
        let doc: toml::Table = text.parse().unwrap();
        let mut c = Checker::new(Path::new("t.toml"), text);
        let keys: Keys = c.parse("t", doc["t"].as_table().unwrap()).unwrap();
        assert_eq!((keys.label.as_str(), keys.alpha), ("a", Some(0.2)));
        let e: Vec<String> = c.into_errors().iter().map(|e| e.key_path.clone()).collect();
        assert_eq!(e.len(), 2, "{e:#?}");
        assert!(e.contains(&"t.runz".to_string()) && e.contains(&"t.alhpa".to_string()));
    }

    /// A required key whose value was unusable is one problem, not also a missing key.
    #[test]
    fn an_unusable_required_key_is_reported_once() {
        let text = "[t]\nlabel = 5\n";
        let doc: toml::Table = text.parse().unwrap();
        let mut c = Checker::new(Path::new("t.toml"), text);
        assert!(c.parse::<Keys>("t", doc["t"].as_table().unwrap()).is_none());
        let e = c.into_errors();
        assert_eq!(e.len(), 1, "{e:#?}");
        assert_eq!(e[0].key_path, "t.label");
    }

    #[test]
    fn suggestions_are_close_keys_only() {
        let keys = ["name", "runs", "master_seed", "trace_runs"];
        assert_eq!(did_you_mean("runz", keys.into_iter()), Some("runs"));
        assert_eq!(
            did_you_mean("master_sead", keys.into_iter()),
            Some("master_seed")
        );
        assert_eq!(
            did_you_mean("trace_run", keys.into_iter()),
            Some("trace_runs")
        );
        assert_eq!(did_you_mean("colour", keys.into_iter()), None);
        assert_eq!(edit_distance("kitten", "sitting"), 3);
        assert_eq!(edit_distance("q_sdt", "q_std"), 1);
        assert_eq!(
            with_suggestion("unknown field `q_sdt`, expected `q_std` or `r_std`"),
            "unknown field `q_sdt`, expected `q_std` or `r_std`; did you mean `q_std`?"
        );
        assert_eq!(
            with_suggestion("invalid type: string"),
            "invalid type: string"
        );
    }

    #[test]
    fn has_needs_every_part_of_the_path() {
        let text = "[model]\ndt_s = 0.1\n[[scenarios]]\nname = \"a\"\n";
        let c = Checker::new(Path::new("t.toml"), text);
        assert!(c.has("model.dt_s") && c.has("scenarios[0].name") && c.has("scenarios[0]"));
        assert!(!c.has("model.mass_kg") && !c.has("scenarios[1]") && !c.has("scenarios[0].x0"));
    }
}
