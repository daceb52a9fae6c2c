//! `kfmc check` under a sequential gate (`check.sequential`): each cell stops at the look
//! that settles its verdicts, the runs it made are the fixed study's first runs, each look's
//! p-value is the fixed study's verdict on that many runs, and the same spec gives the same
//! tables on any thread count.

use crate::common::{
    bools, f64s, i64s, read, repo, run_cli as run, spec_in_tempdir, strs, table_bytes,
};
use polars::prelude::*;

/// The bundled CI gate spec with `runs`, its filters and the `[check]` section replaced.
fn gate_spec(runs: usize, filters: &str, check: &str) -> String {
    let text = std::fs::read_to_string(repo().join("experiments/ci_consistency.toml")).unwrap();
    let head = &text[..text.find("[[filters]]").unwrap()];
    let middle = &text[text.find("[noise]").unwrap()..text.find("# `kfmc check").unwrap()];
    let head = head.replace("runs = 100", &format!("runs = {runs}"));
    format!("{head}{filters}\n{middle}\n{check}")
}

const MISTUNED: &str = "[[filters]]\nlabel = \"ekf\"\nkind = \"ekf\"\nq_scale = 4.0\n";
const TUNED: &str = "[[filters]]\nlabel = \"ekf\"\nkind = \"ekf\"\n";
const ASSERT: &str = "[[check.assert]]\nkind = \"consistent\"\nfilter = \"ekf\"\n";

fn check(spec: &std::path::Path, out: &std::path::Path, extra: &[&str]) -> (i32, String) {
    let mut args = vec![
        "check",
        spec.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--quiet",
        "--force",
    ];
    args.extend(extra);
    let (code, stdout, err) = run(&args);
    (code, format!("{stdout}{err}"))
}

#[test]
fn a_mistuned_filter_is_stopped_early_on_the_fixed_studys_first_runs() {
    let tmp = tempfile::tempdir().unwrap();
    let text = gate_spec(
        200,
        MISTUNED,
        &format!("[check]\nsequential = true\n\n{ASSERT}"),
    );
    let (_d, spec) = spec_in_tempdir(&text);
    let (a, b) = (tmp.path().join("t1"), tmp.path().join("t2"));
    let (code, text_a) = check(&spec, &a, &["--threads", "1"]);
    assert_eq!(code, 3, "the Q×4 filter is inconsistent: {text_a}");
    assert!(
        text_a.contains("FAIL  consistent[basic noise=1 ekf q=4 r=1]")
            && text_a.contains("sequential gate: inconsistent after"),
        "{text_a}"
    );
    // Any thread count: the same looks, the same tables, byte for byte.
    let (code, _) = check(&spec, &b, &["--threads", "2"]);
    assert_eq!(code, 3);
    assert_eq!(table_bytes(&a), table_bytes(&b));

    // Each scenario stopped at a look before the last, rejecting, and holds exactly the
    // runs of that look.
    let seq = read(&a.join("sequential.parquet"));
    let looks: Vec<i64> = (1..=10).map(|k| 20 * k).collect();
    let runs_df = read(&a.join("runs.parquet"));
    let (scenario, decision, look_runs) = (
        strs(&seq, "scenario"),
        strs(&seq, "decision"),
        i64s(&seq, "runs"),
    );
    for name in ["basic", "roll"] {
        let rows: Vec<usize> = (0..seq.height()).filter(|&i| scenario[i] == name).collect();
        let last = *rows.last().unwrap();
        assert_eq!(decision[last], "reject", "{seq}");
        assert!(
            rows[..rows.len() - 1]
                .iter()
                .all(|&i| decision[i] == "continue"),
            "{seq}"
        );
        assert_eq!(
            rows.iter().map(|&i| look_runs[i]).collect::<Vec<_>>(),
            looks[..rows.len()].to_vec()
        );
        assert!(rows.len() < 10, "stopped before the last look: {seq}");
        let made = strs(&runs_df, "scenario")
            .iter()
            .filter(|s| *s == name)
            .count();
        assert_eq!(made as i64, look_runs[last]);
    }

    // The runs made are the fixed study's first runs, value for value.
    let fixed_text = gate_spec(
        200,
        MISTUNED,
        &format!(
            "{}\n{ASSERT}",
            (1..10)
                .map(|k| format!("[[consistency.subsets]]\nruns = {}\nalpha = 0.05\n", 20 * k))
                .collect::<String>()
        ),
    );
    let (_d2, fixed_spec) = spec_in_tempdir(&fixed_text);
    let fixed = tmp.path().join("fixed");
    let (code, _, err) = run(&[
        "run",
        fixed_spec.to_str().unwrap(),
        "--out",
        fixed.to_str().unwrap(),
        "--quiet",
    ]);
    assert_eq!(code, 0, "{err}");
    let fixed_runs = read(&fixed.join("runs.parquet"));
    let key = |df: &DataFrame| -> Vec<(String, i64)> {
        strs(df, "scenario")
            .into_iter()
            .zip(i64s(df, "run"))
            .collect()
    };
    let fixed_index: std::collections::HashMap<(String, i64), usize> = key(&fixed_runs)
        .into_iter()
        .enumerate()
        .map(|(i, k)| (k, i))
        .collect();
    for col in ["seed", "rmse_x", "rmse_theta", "nees_mean", "nis_mean"] {
        let (s, f) = (
            runs_df.column(col).unwrap(),
            fixed_runs.column(col).unwrap(),
        );
        for (i, k) in key(&runs_df).into_iter().enumerate() {
            let j = fixed_index[&k];
            assert_eq!(
                s.get(i).unwrap(),
                f.get(j).unwrap(),
                "{col} of run {k:?} differs from the fixed study's"
            );
        }
    }

    // Each look's p-value is the fixed study's verdict on that look's first runs, bit for
    // bit (the subsets of the fixed study evaluate exactly those runs).
    let cons = read(&fixed.join("consistency.parquet"));
    let (c_scenario, c_test, c_runs, c_p) = (
        strs(&cons, "scenario"),
        strs(&cons, "test"),
        i64s(&cons, "runs"),
        f64s(&cons, "p_value"),
    );
    let seq_p = f64s(&seq, "p_value");
    for i in 0..seq.height() {
        let j = (0..cons.height())
            .find(|&j| {
                c_scenario[j] == scenario[i] && c_test[j] == "verdict" && c_runs[j] == look_runs[i]
            })
            .expect("the fixed study has the verdict at every look's runs");
        assert_eq!(
            seq_p[i].map(f64::to_bits),
            c_p[j].map(f64::to_bits),
            "look at {} runs of {}",
            look_runs[i],
            scenario[i]
        );
    }

    // The gate's boundaries are the design's: an O'Brien–Fleming gate of ten even looks at
    // α = 0.05 (each test two-sided at α/2), with the decision the look's row states.
    let gate = kfmc::sequential::GateSettings::default()
        .gate(200, 0.05)
        .unwrap();
    let (reject_p, z) = (f64s(&seq, "reject_p"), f64s(&seq, "efficacy_z"));
    for i in 0..seq.height() {
        let k = (look_runs[i] / 20 - 1) as usize;
        assert_eq!(z[i], Some(gate.design.efficacy[k]));
        assert_eq!(reject_p[i], Some(gate.p_boundaries(k).0));
        let rejects = seq_p[i].unwrap() <= reject_p[i].unwrap();
        assert_eq!(rejects, decision[i] == "reject", "row {i}: {seq}");
    }
}

#[test]
fn a_consistent_filter_stops_early_with_futility_and_passes() {
    let tmp = tempfile::tempdir().unwrap();
    let text = gate_spec(
        200,
        TUNED,
        &format!("[check]\nsequential = true\nfutility_beta = 0.2\n\n{ASSERT}"),
    );
    let (_d, spec) = spec_in_tempdir(&text);
    let out = tmp.path().join("o");
    let (code, text) = check(&spec, &out, &[]);
    assert_eq!(code, 0, "{text}");
    assert!(
        text.contains("PASS  consistent[basic noise=1 ekf q=1 r=1]")
            && text.contains("sequential gate: consistent after"),
        "{text}"
    );
    let seq = read(&out.join("sequential.parquet"));
    let decisions = strs(&seq, "decision");
    assert!(decisions.iter().all(|d| d == "continue" || d == "accept"));
    assert_eq!(decisions.iter().filter(|d| *d == "accept").count(), 2);
    // The consistency table carries the decision after the verdict of the runs made.
    let cons = read(&out.join("consistency.parquet"));
    let (test, pass, runs) = (
        strs(&cons, "test"),
        bools(&cons, "pass"),
        i64s(&cons, "runs"),
    );
    let rows: Vec<usize> = (0..cons.height())
        .filter(|&i| test[i] == "sequential")
        .collect();
    assert_eq!(rows.len(), 2);
    for &i in &rows {
        assert_eq!(test[i - 1], "verdict");
        assert_eq!(pass[i], Some(true));
        assert_eq!(runs[i], runs[i - 1], "the verdict row is of the runs made");
        // This seed's cells settle at looks 6 and 8 of 10 (the rate over replications is
        // `kfmc power --sequential`'s to measure).
        assert!(runs[i] < 200, "stopped before the last look: {cons}");
    }
    let manifest = std::fs::read_to_string(out.join("manifest.toml")).unwrap();
    assert!(
        manifest.contains("[sequential]") && manifest.contains("futility_beta = 0.2"),
        "{manifest}"
    );
}

#[test]
fn the_gates_settings_are_checked_at_their_key_paths() {
    let cases = [
        (
            "[check]\nlooks = 5\n",
            "check.looks",
            "set check.sequential = true",
        ),
        (
            "[check]\nsequential = true\nlooks = [50, 100]\n",
            "check.looks",
            "end at the study's 200 runs",
        ),
        (
            "[check]\nsequential = true\nspending = \"linear\"\n",
            "check.spending",
            "is not a spending function",
        ),
        (
            "[check]\nsequential = true\nfutility_beta = 1.5\n",
            "check.futility_beta",
            "",
        ),
        (
            "[check]\nsequential = true\nfutility_rho = 1.0\n",
            "check.futility_rho",
            "set check.futility_beta too",
        ),
        (
            "[[consistency.subsets]]\nruns = 50\nalpha = 0.05\n[check]\nsequential = true\n",
            "check.sequential",
            "cannot be combined with [[consistency.subsets]]",
        ),
    ];
    for (check_table, key, message) in cases {
        let text = gate_spec(200, TUNED, &format!("{check_table}\n{ASSERT}"));
        let (_d, spec) = spec_in_tempdir(&text);
        let (code, _, err) = run(&["validate", spec.to_str().unwrap()]);
        assert_eq!(code, 2, "{check_table}: {err}");
        assert!(err.contains(key) && err.contains(message), "{err}");
    }
    // A flag of the gate without the gate is a usage error.
    let text = gate_spec(200, TUNED, ASSERT);
    let (_d, spec) = spec_in_tempdir(&text);
    let (code, _, err) = run(&["check", spec.to_str().unwrap(), "--looks", "5"]);
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("--looks") && err.contains("--sequential"),
        "{err}"
    );
}

/// A count of looks, or a list of run counts, beyond `MAX_LOOKS` is refused before the gate
/// expands or designs anything: as the spec's key, `check --looks` and `power --looks`, each
/// with the same message, within seconds and without memory to speak of.
#[test]
fn more_looks_than_the_limit_are_refused_at_once_everywhere() {
    use kfmc::sequential::MAX_LOOKS;
    let too_many = format!(
        "{} looks are more than a gate may take (at most {MAX_LOOKS})",
        1_000_000_000_000u64
    );
    let runs = 1_000_000;
    let list: Vec<String> = (1..=MAX_LOOKS + 1)
        .map(|k| (k * runs / (MAX_LOOKS + 1)).to_string())
        .collect();
    let list_too_long = format!("{} looks are more than a gate may take", MAX_LOOKS + 1);
    let started = std::time::Instant::now();
    // The spec's key: a count below its own cap of 10⁹, and a list.
    for (looks, message) in [
        (
            "999999999".to_string(),
            "999999999 looks are more than a gate may take".to_string(),
        ),
        (format!("[{}]", list.join(", ")), list_too_long.clone()),
    ] {
        let text = gate_spec(
            runs,
            TUNED,
            &format!("[check]\nsequential = true\nlooks = {looks}\n\n{ASSERT}"),
        );
        let (_d, spec) = spec_in_tempdir(&text);
        let (code, _, err) = run(&["validate", spec.to_str().unwrap()]);
        assert_eq!(code, 2, "{err}");
        assert!(
            err.contains("check.looks") && err.contains(&message),
            "{err}"
        );
    }
    // The flags of check and power.
    let text = gate_spec(runs, TUNED, ASSERT);
    let (_d, spec) = spec_in_tempdir(&text);
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("o");
    for command in ["check", "power"] {
        for (looks, message) in [
            ("1000000000000", too_many.as_str()),
            (&list.join(",")[..], list_too_long.as_str()),
        ] {
            let mut args = vec![
                command,
                spec.to_str().unwrap(),
                "--out",
                out.to_str().unwrap(),
                "--quiet",
                "--sequential",
                "--looks",
                looks,
            ];
            if command == "power" {
                args.extend(["-R", "2"]);
            }
            let (code, _, err) = run(&args);
            assert_eq!(code, 2, "{command} --looks {looks}: {err}");
            // `check` judges its flags with the spec's `[check]` keys, `power` as flags.
            let key = if command == "check" {
                "check.looks"
            } else {
                "--looks"
            };
            assert!(
                err.contains(key) && err.contains(message),
                "{command}: {err}"
            );
        }
    }
    assert!(!out.exists(), "nothing was written");
    assert!(
        started.elapsed() < std::time::Duration::from_secs(60),
        "{:?}",
        started.elapsed()
    );
}

/// The spec's spellings (`obrien_fleming`, `futility_beta`) and the flags' (`obrien-fleming`,
/// `--futility`) are each accepted on the other side, and name the same gate: the same
/// tables byte for byte.
#[test]
fn either_spelling_of_spending_and_futility_is_the_same_gate() {
    let tmp = tempfile::tempdir().unwrap();
    let spec_of = |check: &str| gate_spec(40, TUNED, &format!("[check]\n{check}\n{ASSERT}"));
    let canonical =
        spec_of("sequential = true\nspending = \"obrien_fleming\"\nfutility_beta = 0.2");
    let flagged = spec_of("sequential = true\nspending = \"obrien-fleming\"\nfutility = 0.2");
    let bare = spec_of("");
    let (_d1, canonical) = spec_in_tempdir(&canonical);
    let (_d2, flagged) = spec_in_tempdir(&flagged);
    let (_d3, bare) = spec_in_tempdir(&bare);
    let outs: Vec<_> = (0..4).map(|i| tmp.path().join(format!("t{i}"))).collect();
    let (a, _) = check(&canonical, &outs[0], &[]);
    let (b, text) = check(&flagged, &outs[1], &[]);
    assert_eq!(a, b, "{text}");
    assert_eq!(table_bytes(&outs[0]), table_bytes(&outs[1]));
    for (i, spending, futility) in [
        (2, "obrien_fleming", "--futility-beta"),
        (3, "obrien-fleming", "--futility"),
    ] {
        let flags = ["--sequential", "--spending", spending, futility, "0.2"];
        let (code, text) = check(&bare, &outs[i], &flags);
        assert_eq!(code, a, "{flags:?}: {text}");
        assert_eq!(table_bytes(&outs[0]), table_bytes(&outs[i]), "{flags:?}");
    }
}
