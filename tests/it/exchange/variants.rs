//! Variants of an outside filter: an external entry that lists `q_scale` (or `r_scale`) is one
//! label with several tunings, one simulation serves them all, and each is scored as its own
//! series keyed by its multipliers, as kfmc's own variants are.
//!
//! * Scored from one file whose `q_scale` column names each row's variant, the three series
//!   equal, row for row and value for value, three separately labelled external filters
//!   scored from the same rows (relabelled); only the key columns differ.
//! * A file without the `q_scale` column, a row naming an undeclared variant and a declared
//!   variant without rows are refused naming the file, the column and the label; `check`
//!   never passes on them.

use std::fs;
use std::path::{Path, PathBuf};

use crate::common::{kfmc, ok, read, stamp_of, write_with};
use polars::prelude::*;

const BASE: &str = r#"
name = "variants"
master_seed = 11
runs = 8
[model]
kind = "linear_quadrotor"
sensor = "positions"
[[scenarios]]
name = "hover"
x0 = [1.0, 0.0, 1.0, 0.0, 1.0, 0.0]
duration_s = 4.0
[[scenarios]]
name = "drift"
x0 = [0.0, 0.5, 0.0, -0.5, 2.0, 0.0]
duration_s = 3.0
[noise]
scales = [1.0, 2.0]
[[filters]]
label = "kf"
kind = "ekf"
FILTERS
[initial_estimate]
mode = "sampled"
p0_std = 1.0
[consistency]
alpha = 0.05
[divergence]
rmse_thresholds = [0.5, 0.5, 0.5, 0.5, 0.5, 0.5]
"#;

/// The three tunings: (q_scale, the label a separately labelled filter gets).
const TUNINGS: [(f64, &str); 3] = [(0.5, "mine_a"), (1.0, "mine_b"), (2.0, "mine_c")];

struct Setup {
    _tmp: tempfile::TempDir,
    dir: PathBuf,
    /// The spec with one external `mine` declaring q_scale = [0.5, 1, 2].
    variants_spec: PathBuf,
    /// The exported rows with `filter` = "mine" and a `q_scale` column.
    rows: DataFrame,
    stamp: Vec<(String, String)>,
}

fn spec(dir: &Path, name: &str, filters: &str) -> PathBuf {
    let p = dir.join(name);
    fs::write(&p, BASE.replace("FILTERS", filters)).unwrap();
    p
}

/// kfmc's KF at the three Q scales, exported under three labels: the rows of the outside
/// filter's three tunings.
fn setup() -> Setup {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().to_path_buf();
    let own: String = TUNINGS
        .iter()
        .map(|(q, l)| format!("[[filters]]\nlabel = \"{l}\"\nkind = \"ekf\"\nq_scale = {q}\n"))
        .collect();
    let run_spec = spec(&dir, "run.toml", &own);
    ok(kfmc()
        .args(["run", "-q", "--export-estimates", "--out"])
        .arg(dir.join("run"))
        .arg(&run_spec));
    let exported = dir.join("run/estimates.parquet");
    let stamp = stamp_of(&exported);
    let all = read(&exported);
    let labels = all.column("filter").unwrap().str().unwrap().clone();
    let mine = labels
        .iter()
        .map(|l| l.is_some_and(|l| l.starts_with("mine_")));
    let mine: BooleanChunked = mine.collect();
    let mut rows = all.filter(&mine).unwrap();
    let labels = rows.column("filter").unwrap().str().unwrap().clone();
    let q: Float64Chunked = labels
        .iter()
        .map(|l| TUNINGS.iter().find(|(_, t)| Some(*t) == l).map(|(q, _)| *q))
        .collect();
    rows.with_column(q.into_series().with_name("q_scale".into()).into())
        .unwrap();
    rows.with_column(Series::new("filter".into(), vec!["mine"; rows.height()]).into())
        .unwrap();
    let variants_spec = spec(
        &dir,
        "variants.toml",
        "[[filters]]\nlabel = \"mine\"\nkind = \"external\"\nq_scale = [0.5, 1, 2]\n",
    );
    ok(kfmc()
        .args(["simulate", "-q", "--out"])
        .arg(dir.join("sim"))
        .arg(&variants_spec));
    Setup {
        _tmp: tmp,
        dir,
        variants_spec,
        rows,
        stamp,
    }
}

fn score(sim: &Path, out: &Path, files: &[&Path]) -> std::process::Output {
    kfmc()
        .args(["score", "-q"])
        .arg(sim)
        .arg("--out")
        .arg(out)
        .arg("--estimates")
        .args(files)
        .output()
        .unwrap()
}

#[test]
fn declared_variants_score_as_separately_labelled_filters_value_for_value() {
    let s = setup();
    let file = s.dir.join("variants.parquet");
    write_with(&s.rows, &file, &s.stamp);
    let o = score(&s.dir.join("sim"), &s.dir.join("score"), &[&file]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));

    // The same rows under three labels, scored from a simulation of the spec that declares
    // them (the same world: its tables are byte-identical).
    let separate: String = TUNINGS
        .iter()
        .map(|(_, l)| format!("[[filters]]\nlabel = \"{l}\"\nkind = \"external\"\n"))
        .collect();
    let separate_spec = spec(&s.dir, "separate.toml", &separate);
    ok(kfmc()
        .args(["simulate", "-q", "--out"])
        .arg(s.dir.join("sim_separate"))
        .arg(&separate_spec));
    for t in ["truth", "measurements", "initial"] {
        let a = fs::read(s.dir.join(format!("sim/{t}.parquet"))).unwrap();
        let b = fs::read(s.dir.join(format!("sim_separate/{t}.parquet"))).unwrap();
        assert!(a == b, "{t}.parquet differs between the two simulations");
    }
    let q = s.rows.column("q_scale").unwrap().f64().unwrap().clone();
    let relabelled: StringChunked = q
        .iter()
        .map(|q| TUNINGS.iter().find(|(v, _)| Some(*v) == q).map(|(_, l)| *l))
        .collect();
    let mut separate_rows = s.rows.drop("q_scale").unwrap();
    separate_rows
        .with_column(relabelled.into_series().with_name("filter".into()).into())
        .unwrap();
    let separate_file = s.dir.join("separate.parquet");
    write_with(&separate_rows, &separate_file, &s.stamp);
    let o = score(
        &s.dir.join("sim_separate"),
        &s.dir.join("score_separate"),
        &[&separate_file],
    );
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));

    for t in [
        "runs",
        "steps",
        "summary",
        "consistency",
        "divergence",
        "divergence_runs",
    ] {
        let a = read(&s.dir.join(format!("score/{t}.parquet")));
        let b = read(&s.dir.join(format!("score_separate/{t}.parquet")));
        assert_eq!(a.height(), b.height(), "{t}: row counts");
        let (fa, fb) = (
            a.column("filter").unwrap().str().unwrap().clone(),
            b.column("filter").unwrap().str().unwrap().clone(),
        );
        let (qa, ra) = (
            a.column("q_scale").unwrap().f64().unwrap().clone(),
            a.column("r_scale").unwrap().f64().unwrap().clone(),
        );
        let (qb, rb) = (
            b.column("q_scale").unwrap().f64().unwrap().clone(),
            b.column("r_scale").unwrap().f64().unwrap().clone(),
        );
        let mut series = std::collections::BTreeSet::new();
        for i in 0..a.height() {
            match fa.get(i) {
                // A variant: keyed by its multipliers, as kfmc's own variants are; the
                // separately labelled filter carries none.
                Some("mine") => {
                    let q = qa.get(i).expect("a variant's q_scale");
                    let label = TUNINGS.iter().find(|(v, _)| *v == q).unwrap().1;
                    assert_eq!(fb.get(i), Some(label), "{t} row {i}");
                    assert_eq!(ra.get(i), Some(1.0), "{t} row {i}: r_scale");
                    assert_eq!((qb.get(i), rb.get(i)), (None, None), "{t} row {i}");
                    series.insert(q.to_bits());
                }
                other => {
                    assert_eq!(other, fb.get(i), "{t} row {i}");
                    assert_eq!((qa.get(i), ra.get(i)), (qb.get(i), rb.get(i)));
                }
            }
        }
        assert_eq!(series.len(), 3, "{t}: three series of `mine`");
        let keys = ["filter", "q_scale", "r_scale"];
        assert!(
            a.drop_many(keys).equals_missing(&b.drop_many(keys)),
            "{t}.parquet: the variants' values differ from the separately labelled filters'"
        );
    }

    // The manifest and `kfmc schema estimates` tell the outside program what to write.
    let manifest = fs::read_to_string(s.dir.join("sim/manifest.toml")).unwrap();
    assert!(
        manifest
            .contains("[[exchange.external_filters]]\nlabel = \"mine\"\nq_scale = [0.5, 1.0, 2.0]"),
        "{manifest}"
    );
    let o = ok(kfmc().args(["schema", "estimates"]).arg(&s.variants_spec));
    let text = String::from_utf8_lossy(&o.stdout);
    let line = text
        .lines()
        .find(|l| l.starts_with("q_scale "))
        .unwrap_or_else(|| panic!("no q_scale column in\n{text}"));
    assert!(line.contains("`mine` q_scale = 0.5, 1, 2"), "{line}");
    assert!(!text.lines().any(|l| l.starts_with("r_scale ")), "{text}");
}

/// `kfmc score` and `kfmc check` of `rows`: (score's exit code and stderr, check's).
fn judged(s: &Setup, name: &str, rows: &DataFrame) -> ((i32, String), (i32, String)) {
    let file = s.dir.join(format!("{name}.parquet"));
    write_with(rows, &file, &s.stamp);
    let o = score(
        &s.dir.join("sim"),
        &s.dir.join(format!("score_{name}")),
        &[&file],
    );
    let check_spec = s.dir.join(format!("check_{name}.toml"));
    fs::write(
        &check_spec,
        fs::read_to_string(&s.variants_spec).unwrap()
            + "[[check.assert]]\nkind = \"rmse_below\"\nfilter = \"mine\"\nstate = \"x\"\nmax = 100.0\n",
    )
    .unwrap();
    let c = kfmc()
        .args(["check", "-q"])
        .arg(&check_spec)
        .arg("--out")
        .arg(s.dir.join(format!("check_{name}")))
        .arg("--estimates")
        .arg(&file)
        .output()
        .unwrap();
    let code = |o: &std::process::Output| o.status.code().unwrap_or(-1);
    (
        (code(&o), String::from_utf8_lossy(&o.stderr).into_owned()),
        (code(&c), String::from_utf8_lossy(&c.stderr).into_owned()),
    )
}

#[test]
fn a_missing_column_an_undeclared_variant_and_a_variant_without_rows_are_refused() {
    let s = setup();
    let q = || s.rows.column("q_scale").unwrap().f64().unwrap().clone();

    // The file as it should be passes the gate: the refusals below are the variants'.
    let (score_ok, check_ok) = judged(&s, "good", &s.rows);
    assert_eq!(score_ok.0, 0, "{}", score_ok.1);
    assert_eq!(check_ok.0, 0, "{}", check_ok.1);

    let no_column = s.rows.drop("q_scale").unwrap();
    let mut undeclared = s.rows.clone();
    let three: Float64Chunked = q()
        .iter()
        .map(|v| v.map(|v| if v == 2.0 { 3.0 } else { v }))
        .collect();
    undeclared
        .with_column(three.into_series().with_name("q_scale".into()).into())
        .unwrap();
    let keep: BooleanChunked = q().iter().map(|v| v != Some(2.0)).collect();
    let without_2 = s.rows.filter(&keep).unwrap();
    let mut null_q = s.rows.clone();
    let nulls: Float64Chunked = q()
        .iter()
        .enumerate()
        .map(|(i, v)| if i == 0 { None } else { v })
        .collect();
    null_q
        .with_column(nulls.into_series().with_name("q_scale".into()).into())
        .unwrap();
    for (name, rows, expect) in [
        (
            "no_column",
            &no_column,
            &[
                "no_column.parquet",
                "missing column `q_scale`",
                "filter `mine` declares q_scale variants (q_scale = 0.5, 1, 2)",
            ][..],
        ),
        (
            "undeclared",
            &undeclared,
            &[
                "undeclared.parquet",
                "column `q_scale`: 3 is not a variant of filter `mine`",
                "q_scale = 0.5, 1, 2",
            ][..],
        ),
        (
            "without_2",
            &without_2,
            &[
                "without_2.parquet",
                "no rows for the external filter `mine` (q_scale = 2)",
            ][..],
        ),
        (
            "null_q",
            &null_q,
            &[
                "null_q.parquet",
                "column `q_scale`: null at",
                "filter = \"mine\"",
            ][..],
        ),
    ] {
        let ((score_code, score_err), (check_code, check_err)) = judged(&s, name, rows);
        assert_eq!(score_code, 1, "{name}: score: {score_err}");
        assert_ne!(check_code, 0, "{name}: check passed: {check_err}");
        for e in expect {
            assert!(score_err.contains(e), "{name}: `{e}` not in {score_err}");
            assert!(check_err.contains(e), "{name}: `{e}` not in {check_err}");
        }
    }

    // A label without variants refuses a row that names one.
    let plain = spec(
        &s.dir,
        "plain.toml",
        "[[filters]]\nlabel = \"mine\"\nkind = \"external\"\n",
    );
    let file = s.dir.join("plain.parquet");
    write_with(&without_2, &file, &s.stamp);
    let o = kfmc()
        .args(["check", "-q"])
        .arg(&plain)
        .arg("--out")
        .arg(s.dir.join("check_plain"))
        .arg("--estimates")
        .arg(&file)
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(
        err.contains("column `q_scale`: 0.5 at")
            && err.contains("filter `mine` declares no q_scale variants"),
        "{err}"
    );
}

#[test]
fn an_external_filters_variants_are_validated_and_selected_like_kfmcs_own() {
    let tmp = tempfile::tempdir().unwrap();
    let validate = |name: &str, filters: &str| {
        let p = spec(tmp.path(), name, filters);
        let o = kfmc().arg("validate").arg(&p).output().unwrap();
        (
            o.status.code(),
            String::from_utf8_lossy(&o.stderr).into_owned(),
        )
    };
    let mine = "[[filters]]\nlabel = \"mine\"\nkind = \"external\"\nq_scale = [0.5, 1, 2]\n";
    let (code, err) = validate("ok.toml", mine);
    assert_eq!(code, Some(0), "{err}");
    let (code, err) = validate(
        "bad.toml",
        "[[filters]]\nlabel = \"mine\"\nkind = \"external\"\nr_scale = [1, -2]\n",
    );
    assert_ne!(code, Some(0));
    assert!(
        err.contains("filters[1].r_scale") && err.contains("-2 is not a positive number"),
        "{err}"
    );
    // An assertion selects a declared variant; an undeclared one is a spec error.
    let (code, err) = validate(
        "select.toml",
        &format!("{mine}[[check.assert]]\nkind = \"consistent\"\nfilter = \"mine\"\nq_scale = 2\n"),
    );
    assert_eq!(code, Some(0), "{err}");
    let (code, err) = validate(
        "select_bad.toml",
        &format!("{mine}[[check.assert]]\nkind = \"consistent\"\nfilter = \"mine\"\nq_scale = 3\n"),
    );
    assert_ne!(code, Some(0));
    assert!(
        err.contains("check.assert[0].q_scale") && err.contains("filter `mine` has no variant with q_scale = 3; its variants have q_scale = 0.5, 1, 2"),
        "{err}"
    );
}
