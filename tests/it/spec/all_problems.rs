//! Validation reports every problem of a spec in one pass: a typo in one key does not hide
//! the others, an unknown key gets the closest allowed one, and one problem still prints as
//! it always did.

use std::path::Path;

use crate::common::{run_cli, spec_in_tempdir};

/// Four independent mistakes: a misspelt top-level key, a misspelt key in `[noise]`, a
/// filter's Q of the wrong length (the system's check) and an α outside (0, 1).
const FOUR_MISTAKES: &str = r#"name = "four"
runz = 5
[model]
kind = "planar_quadrotor"
[[scenarios]]
name = "basic"
duration_s = 2.0
[[filters]]
label = "ekf"
kind = "ekf"
q_std = [0.1]
[noise]
scales = [1.0]
filter_noize = "matched"
[consistency]
alpha = 2.0
"#;

#[test]
fn four_independent_mistakes_are_four_problems_in_one_run() {
    let errors = kfmc::experiment::parse(FOUR_MISTAKES, Path::new("four.toml"))
        .expect_err("the spec has four mistakes")
        .0;
    let message = |key: &str| {
        let found = errors
            .iter()
            .filter(|e| e.key_path == key)
            .collect::<Vec<_>>();
        assert_eq!(found.len(), 1, "{key}: {errors:#?}");
        found[0].message.clone()
    };
    assert_eq!(errors.len(), 4, "{errors:#?}");
    assert!(message("runz").contains("did you mean `runs`?"));
    assert!(message("noise.filter_noize").contains("did you mean `filter_noise`?"));
    assert!(message("filters[0].q_std").contains("expected a number or a list of 6 numbers"));
    assert!(message("consistency.alpha").contains("2 is not in (0, 1)"));
    let keys: Vec<&str> = errors.iter().map(|e| e.key_path.as_str()).collect();

    // The command line prints them one per line under their count, and exits 2.
    let (_dir, path) = spec_in_tempdir(FOUR_MISTAKES);
    let (code, _, err) = run_cli(&["validate", path.to_str().unwrap()]);
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("invalid spec (4 problems)"), "{err}");
    for key in keys {
        let line = format!("{}: {key}: ", path.display());
        assert!(
            err.lines().any(|l| l.trim_start().starts_with(&line)),
            "{key}: {err}"
        );
    }
}

#[test]
fn a_misspelt_key_gets_the_allowed_key_it_is_closest_to() {
    let text = "runz = 5\n[model]\nkind = \"planar_quadrotor\"\n[[scenarios]]\nname = \"basic\"\n[[filters]]\nlabel = \"ekf\"\nkind = \"ekf\"\n";
    let errors = kfmc::experiment::parse(text, Path::new("typo.toml"))
        .expect_err("runz is no key")
        .0;
    assert_eq!(errors.len(), 1, "{errors:#?}");
    let shown = errors[0].to_string();
    assert!(
        shown.starts_with("typo.toml: runz: unknown field `runz`, expected one of `name`"),
        "{shown}"
    );
    assert!(shown.contains("; did you mean `runs`? (line 1"), "{shown}");
    // A key of a system's own table gets the same help (the systems use the same checker).
    let text = text.replace("runz = 5\n", "").replace(
        "kind = \"planar_quadrotor\"",
        "kind = \"planar_quadrotor\"\nmas_kg = 1.0",
    );
    let errors = kfmc::experiment::parse(&text, Path::new("typo.toml"))
        .expect_err("mas_kg is no key")
        .0;
    assert_eq!(errors.len(), 1, "{errors:#?}");
    assert_eq!(errors[0].key_path, "model.mas_kg");
    assert!(
        errors[0].message.contains("did you mean `mass_kg`?"),
        "{errors:#?}"
    );
}

/// A value of the wrong type is reported once, and what depends on it is not validated on a
/// guess: `label = 5` is one problem (not also "missing field `label`"), and the unknown key
/// elsewhere is still reported beside it.
#[test]
fn a_problem_others_depend_on_is_reported_alone() {
    let text = "[model]\nkind = \"planar_quadrotor\"\n[[scenarios]]\nname = \"basic\"\n[[filters]]\nlabel = 5\nkind = \"ekf\"\n[noise]\nscalez = [1.0]\n";
    let errors = kfmc::experiment::parse(text, Path::new("label.toml"))
        .expect_err("a label is a string")
        .0;
    let mut keys: Vec<&str> = errors.iter().map(|e| e.key_path.as_str()).collect();
    keys.sort();
    assert_eq!(keys, ["filters[0].label", "noise.scalez"], "{errors:#?}");
}

/// The drone validates its own filter entries; an external entry before them is not passed
/// to it, yet a problem must still be named at the entry's place in the spec's list.
#[test]
fn a_drone_filter_problem_is_named_at_its_place_in_the_spec_after_an_external_filter() {
    let text = r#"name = "drone_keys"
initial_estimate.mode = "sampled"
[model]
kind = "drone"
[[scenarios]]
name = "linear"
[[filters]]
label = "mine"
kind = "external"
[[filters]]
label = "ekf9"
kind = "ekf9"
baro_drfit = true
[[filters]]
label = "nine"
kind = "nine"
"#;
    let errors = kfmc::experiment::parse(text, Path::new("drone_keys.toml"))
        .expect_err("a misspelt key and an unknown kind")
        .0;
    let keys: Vec<&str> = errors.iter().map(|e| e.key_path.as_str()).collect();
    assert_eq!(
        keys,
        ["filters[1].baro_drfit", "filters[2].kind"],
        "{errors:#?}"
    );
}

/// The same for a check made after every entry is configured (the running mean's window
/// against the scenarios' length), which names entries through the shared mechanism.
#[test]
fn a_scenario_check_names_the_entry_at_its_place_in_the_spec_after_an_external_filter() {
    let text = r#"name = "window_keys"
[model]
kind = "planar_quadrotor"
[[scenarios]]
name = "basic"
duration_s = 0.5
[[filters]]
label = "mine"
kind = "external"
[[filters]]
label = "mean"
kind = "running_mean"
window = 1000
"#;
    let errors = kfmc::experiment::parse(text, Path::new("window_keys.toml"))
        .expect_err("the window never fills")
        .0;
    let keys: Vec<&str> = errors.iter().map(|e| e.key_path.as_str()).collect();
    assert_eq!(keys, ["filters[1].window"], "{errors:#?}");
}
