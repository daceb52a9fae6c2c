//! The names a study's files carry: `[[scenarios]]` names, `[[filters]]` labels, the
//! experiment's `name`, and the figure names they make together.

use std::collections::BTreeSet;
use std::path::Path;

use crate::experiment::spec::Spec;
use crate::system::checker::Checker;
use crate::system::limits;

/// Why a scenario name or filter label cannot be used, if it cannot. They are parts of
/// figure file names (`rmse_cases_<scenario>_<filter>.png`) and table keys, so only
/// `[A-Za-z0-9_.-]` is allowed: the name is then its own file-name part, with no path
/// separator, no `..`, nothing a file system changes, and no two names that map to one file.
pub fn name_problem(name: &str) -> Option<String> {
    let max = limits::MAX_NAME_CHARS;
    if name.is_empty() {
        return Some("must not be empty".into());
    }
    if let Some(bad) = name
        .chars()
        .find(|c| !(c.is_ascii_alphanumeric() || matches!(c, '_' | '.' | '-')))
    {
        return Some(format!(
            "`{}` contains {bad:?}; use only letters A-Z a-z, digits, `_`, `.` and `-` (names become file names)",
            name.escape_debug()
        ));
    }
    if name.starts_with('.') {
        return Some(format!(
            "`{name}` starts with `.`; names become file names, which would be hidden or `..`"
        ));
    }
    let n = name.chars().count();
    (n > max).then(|| format!("{n} characters; at most {max} (names become file names)"))
}
/// Reports (scenario, filter) pairs whose figure `rmse_cases_<scenario>_<filter>` would be the
/// same file as another pair's: `a` with `b_c` and `a_b` with `c`. Names are only
/// `[A-Za-z0-9_.-]`, so `_` inside a name is the one way two pairs can meet.
pub(super) fn figure_name_clashes(
    c: &mut Checker,
    spec: &Spec,
    names: &BTreeSet<String>,
    labels: &BTreeSet<String>,
) {
    let mut reported = BTreeSet::new();
    for long in names {
        for (at, _) in long.match_indices('_') {
            let (short, rest) = (&long[..at], &long[at + 1..]);
            if !names.contains(short) {
                continue;
            }
            // With long = short_rest: short_f1 and long_f2 are one string iff f1 = rest_f2.
            let prefix = format!("{rest}_");
            for f1 in labels.range(prefix.clone()..) {
                let Some(f2) = f1.strip_prefix(&prefix) else {
                    break;
                };
                if !labels.contains(f2) || !reported.insert(f1.clone()) {
                    continue;
                }
                let i = spec
                    .filters
                    .iter()
                    .position(|f| &f.label == f1)
                    .unwrap_or(0);
                c.err(
                    format!("filters[{i}].label"),
                    format!(
                        "scenario `{short}` with filter `{f1}` and scenario `{long}` with filter `{f2}` would share the figure rmse_cases_{short}_{f1}; rename one"
                    ),
                );
            }
        }
    }
}
/// `[[scenarios]]` names: present, usable as file names, unique (also ignoring case). The
/// rest of each table is the system's.
pub(super) fn scenario_names(c: &mut Checker, spec: &Spec) -> BTreeSet<String> {
    if spec.scenarios.is_empty() {
        c.err("scenarios", "at least one [[scenarios]] entry is required");
    }
    let mut names = BTreeSet::new();
    let mut folded = BTreeSet::new();
    for (i, s) in spec.scenarios.iter().enumerate() {
        let key = format!("scenarios[{i}].name");
        match s.get("name") {
            Some(toml::Value::String(n)) => {
                if let Some(msg) = name_problem(n) {
                    c.err(key, msg);
                } else if !names.insert(n.clone()) {
                    c.err(key, format!("duplicate scenario name `{n}`"));
                } else if !folded.insert(n.to_ascii_lowercase()) {
                    c.err(
                        key,
                        format!("`{n}` differs from another scenario name only by case; their figures would be one file on case-insensitive file systems"),
                    );
                }
            }
            Some(_) => c.err(key, "expected a string"),
            None => c.err(key, "missing"),
        }
    }
    names
}

/// `[[filters]]` labels: usable as file names, unique (also ignoring case).
pub(super) fn filter_labels(c: &mut Checker, spec: &Spec) -> BTreeSet<String> {
    if spec.filters.is_empty() {
        c.err("filters", "at least one [[filters]] entry is required");
    }
    let mut labels = BTreeSet::new();
    let mut folded = BTreeSet::new();
    for (i, f) in spec.filters.iter().enumerate() {
        let key = format!("filters[{i}].label");
        if let Some(msg) = name_problem(&f.label) {
            c.err(key, msg);
        } else if !labels.insert(f.label.clone()) {
            c.err(key, format!("duplicate filter label `{}`", f.label));
        } else if !folded.insert(f.label.to_ascii_lowercase()) {
            c.err(
                key,
                format!("`{}` differs from another filter label only by case; their figures would be one file on case-insensitive file systems", f.label),
            );
        }
    }
    labels
}
/// `name`, or the file's name without it: a folder name of its own.
pub(super) fn experiment_name(c: &mut Checker, spec: &Spec, path: &Path) -> String {
    let name = spec.name.clone().unwrap_or_else(|| {
        path.file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_else(|| "experiment".into())
    });
    if name.is_empty() || name == "." || name == ".." || name.contains(['/', '\\']) {
        // Without a `name` key the file's own name stands in: say so, at the file.
        let (key, what) = if spec.name.is_some() {
            ("name", String::new())
        } else {
            (
                "",
                format!("the experiment name (from the file name, `{name}`) "),
            )
        };
        c.err(
            key,
            format!(
                "{what}must be non-empty, not `.` or `..`, and contain no path separators; set name"
            ),
        );
    }
    name
}
