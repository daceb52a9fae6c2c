//! Smaller estimates files: float32 value columns and the compact covariance forms.
//!
//! * float32 columns are read as f64 exactly: a file whose values are float32-representable
//!   scores to the same tables, byte for byte, whether its columns are float64 or float32.
//! * The Cholesky factor `L_<i>_<j>` and the variances with correlations `var_<q>` +
//!   `corr_<qi>_<qj>`, in f64, score as the lower triangle `P_` to round-off (1e-12
//!   relative); with the covariance, innovation, S and A in float32 and the estimates in
//!   f64 (what `kfmc.Estimates(..., float32=True)` writes), within the tolerances stated in
//!   `docs/src/guide/external.md` (NEES 1e-6 relative, p-values 1e-5 absolute), and with the same
//!   verdicts and run statuses.
//! * A file mixing covariance forms is refused naming a column of each; a correlation outside
//!   [−1, 1] or a negative variance makes that run a numerical failure naming the column.

use std::path::Path;

use super::exchange::{Study, score, study};
use crate::common::{f64s, read};
use kfmc::linalg::Matrix;
use polars::prelude::*;

/// The key columns, and the boolean `failed` that marks a failed run: no value column.
const KEYS: [&str; 6] = ["scenario", "noise_scale", "run", "step", "filter", "failed"];

/// The tables `kfmc score` writes that depend on the estimates.
const TABLES: [&str; 6] = [
    "runs",
    "steps",
    "summary",
    "consistency",
    "divergence",
    "divergence_runs",
];

fn quantities(df: &DataFrame) -> Vec<String> {
    df.get_column_names()
        .iter()
        .filter_map(|c| c.strip_prefix("est_").map(str::to_string))
        .collect()
}

/// Each row's covariance from the `P_` columns.
fn covariances(df: &DataFrame) -> Vec<Matrix<6, 6>> {
    let q = quantities(df);
    assert_eq!(q.len(), 6);
    let mut p = vec![Matrix::<6, 6>::zeros(); df.height()];
    for i in 0..6 {
        for j in 0..=i {
            for (r, v) in f64s(df, &format!("P_{}_{}", q[i], q[j])).iter().enumerate() {
                p[r][(i, j)] = v.unwrap();
                p[r][(j, i)] = v.unwrap();
            }
        }
    }
    p
}

/// `good` with its `P_` columns replaced by the covariance in `form` ("L" or "corr"), and,
/// if `f32`, every value column but the estimates stored as float32.
fn compact(good: &DataFrame, form: &str, f32: bool) -> DataFrame {
    let q = quantities(good);
    let p = covariances(good);
    let mut cols: Vec<Column> = Vec::new();
    for name in good.get_column_names() {
        if !name.starts_with("P_") {
            cols.push(good.column(name).unwrap().clone());
        }
    }
    for i in 0..6 {
        for j in 0..=i {
            let (name, values): (String, Vec<f64>) = match form {
                "L" => (
                    format!("L_{i}_{j}"),
                    p.iter()
                        .map(|m| m.cholesky().expect("P is positive definite").l()[(i, j)])
                        .collect(),
                ),
                "corr" if i == j => (
                    format!("var_{}", q[i]),
                    p.iter().map(|m| m[(i, i)]).collect(),
                ),
                "corr" => (
                    format!("corr_{}_{}", q[i], q[j]),
                    p.iter()
                        .map(|m| m[(i, j)] / (m[(i, i)] * m[(j, j)]).sqrt())
                        .collect(),
                ),
                other => panic!("no form {other}"),
            };
            cols.push(Column::new(name.into(), values));
        }
    }
    let mut df = DataFrame::new(good.height(), cols).unwrap();
    if f32 {
        df = to_f32(&df, |c| !c.starts_with("est_"));
    }
    df
}

/// `df` with the value columns `which` selects stored as float32.
fn to_f32(df: &DataFrame, which: impl Fn(&str) -> bool) -> DataFrame {
    let cols: Vec<Column> = df
        .columns()
        .iter()
        .map(|c| {
            if !KEYS.contains(&c.name().as_str()) && which(c.name()) {
                c.cast(&DataType::Float32).unwrap()
            } else {
                c.clone()
            }
        })
        .collect();
    DataFrame::new(df.height(), cols).unwrap()
}

fn scored(s: &Study, df: &DataFrame, name: &str) -> std::path::PathBuf {
    let path = s.dir.join(format!("{name}.parquet"));
    s.write(df, &path);
    let o = score(s, &[&path], name);
    assert!(
        o.status.success(),
        "{name}: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    s.dir.join(name)
}

/// The largest difference between two folders' tables: (any float column's largest
/// difference relative to the column's largest magnitude, which stays meaningful for
/// statistics near zero; the largest absolute difference of a p-value); every other column
/// must be equal, and so must the non-finite values.
fn largest_difference(a: &Path, b: &Path) -> (f64, f64) {
    let (mut rel, mut p_abs) = (0.0f64, 0.0f64);
    for t in TABLES {
        let (x, y) = (
            read(&a.join(format!("{t}.parquet"))),
            read(&b.join(format!("{t}.parquet"))),
        );
        assert_eq!(x.shape(), y.shape(), "{t}");
        for c in x.columns() {
            let d = y.column(c.name()).unwrap();
            if c.dtype() != &DataType::Float64 {
                assert!(c.equals_missing(d), "{t}.{} differs", c.name());
                continue;
            }
            let (u, v) = (c.f64().unwrap(), d.f64().unwrap());
            let scale = u
                .iter()
                .flatten()
                .filter(|u| u.is_finite())
                .fold(0.0f64, |m, u| m.max(u.abs()));
            for (u, v) in u.iter().zip(v.iter()) {
                match (u, v) {
                    (Some(u), Some(v)) if u.is_finite() && v.is_finite() => {
                        let diff = (u - v).abs();
                        if c.name().as_str() == "p_value" {
                            p_abs = p_abs.max(diff);
                        } else if diff > 0.0 {
                            rel = rel.max(diff / scale);
                        }
                    }
                    (Some(u), Some(v)) => {
                        assert!(
                            u.to_bits() == v.to_bits() || (u.is_nan() && v.is_nan()),
                            "{t}.{}: {u} vs {v}",
                            c.name()
                        )
                    }
                    (None, None) => {}
                    other => panic!("{t}.{}: {other:?}", c.name()),
                }
            }
        }
    }
    (rel, p_abs)
}

fn same_tables(a: &Path, b: &Path) -> bool {
    TABLES.iter().all(|t| {
        read(&a.join(format!("{t}.parquet"))).equals_missing(&read(&b.join(format!("{t}.parquet"))))
    })
}

#[test]
fn float32_columns_are_read_as_float64_exactly() {
    let s = study();
    let good = read(&s.dir.join("kf.parquet"));
    // Every value rounded to a float32 value, kept in float64 columns…
    let rounded = to_f32(&good, |_| true);
    let rounded64 = DataFrame::new(
        rounded.height(),
        rounded
            .columns()
            .iter()
            .map(|c| {
                if c.dtype() == &DataType::Float32 {
                    c.cast(&DataType::Float64).unwrap()
                } else {
                    c.clone()
                }
            })
            .collect(),
    )
    .unwrap();
    let a = scored(&s, &rounded64, "rounded_f64");
    // … and the same values in float32 columns.
    let b = scored(&s, &rounded, "rounded_f32");
    assert!(
        same_tables(&a, &b),
        "float32 columns score other tables than the same values in float64"
    );
    // The rounding is not nothing: the original file scores differently.
    let full = scored(&s, &good, "full");
    assert!(
        !same_tables(&full, &a),
        "rounding to float32 changed no table"
    );
    // A key stays a key: a float32 noise_scale of 1.0 and 3.0 is that value exactly.
    let keys32 = DataFrame::new(
        rounded.height(),
        rounded
            .columns()
            .iter()
            .map(|c| {
                if c.name().as_str() == "noise_scale" {
                    c.cast(&DataType::Float32).unwrap()
                } else {
                    c.clone()
                }
            })
            .collect(),
    )
    .unwrap();
    let c = scored(&s, &keys32, "keys_f32");
    assert!(same_tables(&a, &c));
}

#[test]
fn compact_covariance_forms_score_as_the_lower_triangle() {
    let s = study();
    let good = read(&s.dir.join("kf.parquet"));
    let full = scored(&s, &good, "full");
    for form in ["L", "corr"] {
        let f64_form = scored(&s, &compact(&good, form, false), &format!("{form}_f64"));
        let (rel, p) = largest_difference(&full, &f64_form);
        assert!(
            rel < 1e-12 && p < 1e-12,
            "{form} in f64: {rel:e} relative, p-values {p:e}"
        );
        let f32_form = scored(&s, &compact(&good, form, true), &format!("{form}_f32"));
        let (rel, p) = largest_difference(&full, &f32_form);
        eprintln!("{form} with float32 values: {rel:e} relative, p-values {p:e}");
        assert!(
            rel < 1e-6 && p < 1e-5,
            "{form} with float32 values: {rel:e} relative, p-values {p:e}"
        );
        // The estimates are the file's own: the RMSE is the full file's, bit for bit.
        let (a, b) = (
            read(&full.join("runs.parquet")),
            read(&f32_form.join("runs.parquet")),
        );
        for c in a.get_column_names() {
            if c.starts_with("rmse_") || *c == "status" {
                assert!(
                    a.column(c).unwrap().equals_missing(b.column(c).unwrap()),
                    "{c}"
                );
            }
        }
    }
    // The covariance in float32 as the lower triangle, estimates in f64: also within the
    // tolerance on this well-conditioned L1 run.
    let p32 = scored(&s, &to_f32(&good, |c| !c.starts_with("est_")), "lower_f32");
    let (rel, p) = largest_difference(&full, &p32);
    eprintln!("P_ with float32 values: {rel:e} relative, p-values {p:e}");
    assert!(rel < 1e-6 && p < 1e-5, "{rel:e} {p:e}");
}

#[test]
fn mixed_forms_are_refused_naming_both_columns_and_bad_correlations_fail_the_run() {
    let s = study();
    let good = read(&s.dir.join("kf.parquet"));
    let l = compact(&good, "L", false);
    let corr = compact(&good, "corr", false);
    let mut p_and_var = good.clone();
    p_and_var
        .with_column(corr.column("var_x").unwrap().clone())
        .unwrap();
    let mut l_and_corr = l.clone();
    l_and_corr
        .with_column(corr.column("corr_xdot_x").unwrap().clone())
        .unwrap();
    let cases = [
        ("p_and_var", p_and_var, "both `P_x_x` and `var_x`"),
        ("l_and_corr", l_and_corr, "both `L_0_0` and `corr_xdot_x`"),
        (
            "corr_without_var",
            corr.drop("var_y").unwrap(),
            "missing column `var_y`",
        ),
    ];
    for (name, df, expect) in cases {
        let path = s.dir.join(format!("{name}.parquet"));
        s.write(&df, &path);
        let o = score(&s, &[&path], name);
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(1), "{name}: {err}");
        assert!(err.contains(expect), "{name}: expected `{expect}` in {err}");
    }

    // A correlation beyond 1 at run 3, step 5 and a negative variance at run 4, step 2 of
    // the first cell: those runs fail there, naming the column; the others score.
    let at = |i: usize, r: i64, k: i64| {
        good.column("scenario").unwrap().str().unwrap().get(i) == Some("hover")
            && good.column("noise_scale").unwrap().f64().unwrap().get(i) == Some(1.0)
            && good.column("run").unwrap().i64().unwrap().get(i) == Some(r)
            && good.column("step").unwrap().i64().unwrap().get(i) == Some(k)
    };
    let edit = |df: &mut DataFrame, col: &str, r: i64, k: i64, v: f64| {
        let vals: Vec<Option<f64>> = f64s(df, col)
            .into_iter()
            .enumerate()
            .map(|(i, x)| if at(i, r, k) { Some(v) } else { x })
            .collect();
        df.with_column(Column::new(col.into(), vals)).unwrap();
    };
    let mut bad = corr.clone();
    edit(&mut bad, "corr_xdot_x", 3, 5, 1.5);
    edit(&mut bad, "var_y", 4, 2, -0.25);
    let folder = scored(&s, &bad, "bad_corr");
    let runs = read(&folder.join("runs.parquet"));
    let status = |r: i64| {
        let m = runs.column("filter").unwrap().str().unwrap().equal("kf")
            & runs
                .column("scenario")
                .unwrap()
                .str()
                .unwrap()
                .equal("hover")
            & runs
                .column("noise_scale")
                .unwrap()
                .f64()
                .unwrap()
                .equal(1.0)
            & runs.column("run").unwrap().i64().unwrap().equal(r);
        let row = runs.filter(&m).unwrap();
        (
            row.column("status_step").unwrap().i64().unwrap().get(0),
            row.column("status_detail")
                .unwrap()
                .str()
                .unwrap()
                .get(0)
                .map(str::to_string),
        )
    };
    assert_eq!(
        status(3),
        (
            Some(5),
            Some("estimates: corr_xdot_x = 1.5 is outside [-1, 1]".into())
        )
    );
    assert_eq!(
        status(4),
        (Some(2), Some("estimates: var_y = -0.25 is negative".into()))
    );
    assert_eq!(status(5).0, None, "run 5 is untouched");
}

#[test]
fn schema_lists_the_covariance_forms_before_the_stamp() {
    let tmp = tempfile::tempdir().unwrap();
    let spec = tmp.path().join("l1.toml");
    std::fs::write(
        &spec,
        "name = \"forms\"\nruns = 2\n[model]\nkind = \"linear_quadrotor\"\nsensor = \"positions\"\n[[scenarios]]\nname = \"hover\"\nx0 = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0]\nduration_s = 1.0\n[[filters]]\nlabel = \"mine\"\nkind = \"external\"\n",
    )
    .unwrap();
    let o = crate::common::kfmc()
        .args(["schema", "estimates"])
        .arg(&spec)
        .output()
        .unwrap();
    assert!(o.status.success());
    let text = String::from_utf8_lossy(&o.stdout);
    let cholesky = text
        .find("L_<i>_<j> (0-based, i >= j): a lower Cholesky factor, P = L L^T: L_0_0, L_1_0, …, L_5_5")
        .unwrap_or_else(|| panic!("{text}"));
    assert!(
        text.contains("P_ij = corr_ij sqrt(var_i var_j): var_x, corr_xdot_x, …, var_zdot"),
        "{text}"
    );
    assert!(text.contains("value columns may be float32"), "{text}");
    // The stamp stays after them: a writer reads it off the end.
    assert!(text.find("file metadata (the stamp").unwrap() > cholesky);
}

#[test]
fn a_float32_export_is_the_f64_export_rounded_and_scores_to_the_same_verdicts() {
    let s = study();
    let run_spec = s.dir.join("run.toml");
    let export = |out: &str, precision: Option<&str>| {
        let mut c = crate::common::kfmc();
        c.args(["run", "-q", "--export-estimates", "--out"])
            .arg(s.dir.join(out))
            .arg(&run_spec);
        if let Some(p) = precision {
            c.args(["--export-estimates-precision", p]);
        }
        let o = c.output().unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        s.dir.join(out).join("estimates.parquet")
    };
    // f64 is the default, byte for byte.
    let f64_path = export("run64", Some("f64"));
    assert!(
        std::fs::read(&f64_path).unwrap()
            == std::fs::read(s.dir.join("run/estimates.parquet")).unwrap(),
        "--export-estimates-precision f64 changed the export"
    );
    let f32_path = export("run32", Some("f32"));
    let (all64, all32) = (read(&f64_path), read(&f32_path));
    // The estimates stay float64; the covariance, innovation, S and A are float32, and are
    // the f64 export's values rounded to nearest.
    for c in all32.columns() {
        let name = c.name().as_str();
        let want = if KEYS.contains(&name) {
            all64.column(name).unwrap().dtype().clone()
        } else if name.starts_with("est_") || name.starts_with("quat_") {
            DataType::Float64
        } else {
            DataType::Float32
        };
        assert_eq!(c.dtype(), &want, "{name}");
    }
    assert!(
        to_f32(&all64, |c| !c.starts_with("est_")).equals_missing(&all32),
        "the f32 export is not the f64 export rounded"
    );
    // Scored as the external `kf`: the same verdicts, statuses and RMSE, the statistics
    // within the book's float32 tolerance.
    let keep = |df: &DataFrame| {
        let kf = df.column("filter").unwrap().str().unwrap().equal("kf");
        df.filter(&kf).unwrap()
    };
    let full = scored(&s, &keep(&all64), "export64");
    let rounded = scored(&s, &keep(&all32), "export32");
    let (rel, p) = largest_difference(&full, &rounded);
    eprintln!("float32 export: {rel:e} relative, p-values {p:e}");
    assert!(rel > 0.0, "rounding to float32 changed no statistic");
    assert!(rel < 1e-6 && p < 1e-5, "{rel:e} relative, p-values {p:e}");
    let (a, b) = (
        read(&full.join("consistency.parquet")),
        read(&rounded.join("consistency.parquet")),
    );
    for c in ["test", "pass", "direction"] {
        assert!(
            a.column(c).unwrap().equals_missing(b.column(c).unwrap()),
            "{c}"
        );
    }
    let (a, b) = (
        read(&full.join("runs.parquet")),
        read(&rounded.join("runs.parquet")),
    );
    for c in a.get_column_names() {
        if c.starts_with("rmse_") || *c == "status" {
            assert!(
                a.column(c).unwrap().equals_missing(b.column(c).unwrap()),
                "{c}"
            );
        }
    }
    // Without --export-estimates the precision is refused (it would set nothing).
    let o = crate::common::kfmc()
        .args(["run", "-q", "--export-estimates-precision", "f32", "--out"])
        .arg(s.dir.join("none"))
        .arg(&run_spec)
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(2));
}
