//! `kfmc check` assertions that select a filter variant by its multipliers, and the paired
//! `no_worse_than` comparison of a filter against a reference on the same runs.

use crate::common::{repo, run_cli as run, spec_in_tempdir};

/// The bundled CI gate spec with its filters and assertions replaced.
fn gate_spec(filters_and_asserts: &str, runs: usize) -> String {
    let text = std::fs::read_to_string(repo().join("experiments/ci_consistency.toml")).unwrap();
    let head = &text[..text.find("[[filters]]").unwrap()];
    let middle_start = text.find("[noise]").unwrap();
    let middle_end = text.find("# `kfmc check").unwrap();
    let head = head.replace("runs = 100", &format!("runs = {runs}"));
    format!(
        "{head}{}\n{filters_and_asserts}",
        &text[middle_start..middle_end]
    )
}

#[test]
fn an_assertion_selects_a_filter_variant_by_q_scale() {
    let tmp = tempfile::tempdir().unwrap();
    let text = gate_spec(
        r#"
[[filters]]
label = "ekf"
kind = "ekf"
q_scale = [1.0, 4.0]

[[check.assert]]
kind = "consistent"
filter = "ekf"
q_scale = 1.0

[[check.assert]]
kind = "consistent"
q_scale = 4.0
expect = "fail"

[[check.assert]]
kind = "rmse_below"
state = "y"
max = 0.01
q_scale = 1.0
r_scale = 1.0
"#,
        100,
    );
    let (_d, spec) = spec_in_tempdir(&text);
    let out = tmp.path().join("o");
    let (code, stdout, err) = run(&[
        "check",
        spec.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--quiet",
    ]);
    assert_eq!(code, 0, "{stdout}{err}");
    // Two scenarios × one selected variant per assertion, never the other variant.
    assert!(stdout.contains("6 cases, 6 passed, 0 failed"), "{stdout}");
    assert_eq!(stdout.matches("PASS  consistent[").count(), 2, "{stdout}");
    assert!(
        stdout.contains("PASS  consistent[basic noise=1 ekf q=1 r=1]")
            && stdout.contains("PASS  negative_control:consistent[roll noise=1 ekf q=4 r=1]")
            && stdout.contains("PASS  rmse_below[basic noise=1 ekf q=1 r=1 y]"),
        "{stdout}"
    );
    assert!(
        !stdout.contains("rmse_below[basic noise=1 ekf q=4"),
        "{stdout}"
    );

    // A value no variant has is a spec error at its key path, before anything runs.
    let bad = text.replacen(
        "filter = \"ekf\"\nq_scale = 1.0\n",
        "filter = \"ekf\"\nq_scale = 0.9\n",
        1,
    );
    let (_d, spec) = spec_in_tempdir(&bad);
    let (code, _, err) = run(&["check", spec.to_str().unwrap(), "--quiet"]);
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("check.assert[0].q_scale")
            && err.contains(
                "filter `ekf` has no variant with q_scale = 0.9; its variants have q_scale = 1, 4"
            ),
        "{err}"
    );
}

#[test]
fn no_worse_than_fails_a_worse_filter_and_passes_an_equal_one_on_the_same_runs() {
    let tmp = tempfile::tempdir().unwrap();
    let text = gate_spec(
        r#"
[[filters]]
label = "ekf"
kind = "ekf"

[[filters]]
label = "ekf_copy"
kind = "ekf"

[[filters]]
label = "ekf_wide_q"
kind = "ekf"
q_scale = 100.0

[[check.assert]]
kind = "no_worse_than"
filter = "ekf_copy"
reference = "ekf"
margin = 0.0

[[check.assert]]
kind = "no_worse_than"
filter = "ekf_wide_q"
reference = "ekf"
state = "y"
margin = 0.1
expect = "fail"
"#,
        40,
    );
    let (_d, spec) = spec_in_tempdir(&text);
    let out = tmp.path().join("o");
    let junit = tmp.path().join("junit.xml");
    let (code, stdout, err) = run(&[
        "check",
        spec.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--junit",
        junit.to_str().unwrap(),
        "--quiet",
    ]);
    assert_eq!(code, 0, "{stdout}{err}");
    // The copy: six states × two scenarios, each run's RMSE equal to the reference's, so
    // every difference is 0 and nothing is significantly worse.
    assert_eq!(
        stdout
            .matches("PASS  no_worse_than[basic noise=1 ekf_copy q=1 r=1 vs ekf ")
            .count(),
        6,
        "{stdout}"
    );
    assert!(stdout.contains("(+0.0 %, margin 0 %)"), "{stdout}");
    // Q × 100 follows the measurement noise: its altitude RMSE is far above 1.1 × the tuned
    // filter's, run by run, so the negative control holds.
    let line = stdout
        .lines()
        .find(|l| {
            l.contains(
                "negative_control:no_worse_than[basic noise=1 ekf_wide_q q=100 r=1 vs ekf y]",
            )
        })
        .unwrap_or_else(|| panic!("{stdout}"));
    assert!(line.trim_start().starts_with("PASS"), "{line}");
    assert!(line.contains("expected to fail, and it failed"), "{line}");
    let xml = std::fs::read_to_string(&junit).unwrap();
    assert!(xml.contains("tests=\"14\" failures=\"0\""), "{xml}");

    // Without the negative control the worse filter fails the gate (exit 3).
    let (_d, spec) = spec_in_tempdir(&text.replace("expect = \"fail\"\n", ""));
    let (code, stdout, _) = run(&[
        "check",
        spec.to_str().unwrap(),
        "--out",
        tmp.path().join("fail").to_str().unwrap(),
        "--quiet",
    ]);
    assert_eq!(code, 3, "{stdout}");
    assert!(
        stdout.contains("FAIL  no_worse_than[roll noise=1 ekf_wide_q q=100 r=1 vs ekf y]"),
        "{stdout}"
    );

    // The reference must be one filter variant, the margin stated, and the filter another.
    for (edit, key, says) in [
        (
            "reference = \"ekf\"\nmargin = 0.0",
            "check.assert[0].margin",
            "missing",
        ),
        (
            "reference = \"nope\"\nmargin = 0.0",
            "check.assert[0].reference",
            "no filter labelled `nope`",
        ),
        (
            "reference = \"ekf\"\nmargin = -0.1",
            "check.assert[0].margin",
            "not a relative excess",
        ),
    ] {
        let t = text.replacen("reference = \"ekf\"\nmargin = 0.0", edit, 1);
        let t = if key.ends_with("margin") && says == "missing" {
            t.replacen(
                "reference = \"ekf\"\nmargin = 0.0",
                "reference = \"ekf\"",
                1,
            )
        } else {
            t
        };
        let (_d, spec) = spec_in_tempdir(&t);
        let (code, _, err) = run(&["validate", spec.to_str().unwrap()]);
        assert_eq!(code, 2, "{edit}: {err}");
        assert!(err.contains(key) && err.contains(says), "{edit}: {err}");
    }
    let t = text
        .replace("q_scale = 100.0", "q_scale = [1.0, 100.0]")
        .replacen(
            "filter = \"ekf_copy\"\nreference = \"ekf\"",
            "filter = \"ekf_copy\"\nreference = \"ekf_wide_q\"",
            1,
        );
    let (_d, spec) = spec_in_tempdir(&t);
    let (code, _, err) = run(&["validate", spec.to_str().unwrap()]);
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("check.assert[0].reference") && err.contains("`ekf_wide_q` has 2 variants"),
        "{err}"
    );
}
