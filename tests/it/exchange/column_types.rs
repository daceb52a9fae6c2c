//! The estimates reader takes the column types the format documents and no other: the keys
//! their own (strings, integers, numbers), the values float64 or float32. A decimal or map
//! column (which polars cannot hold) and a bool, integer or string value column (which a
//! conversion would score: `True` as 1.0) are refused naming the file and the column, exit 1,
//! before a row is read: never a panic, never a score. The decimal and map files are made by
//! `tests/fixtures/estimates_types/make.py` (pyarrow), as polars here cannot write them.

use std::path::{Path, PathBuf};

use crate::common::{kfmc, ok, read, repo, run_cli};
use polars::prelude::*;

/// A linear quadrotor with its position sensor and one outside filter `ext`: the estimates
/// format of the fixture files.
const SPEC: &str = r#"
name = "column_types"
master_seed = 7
runs = 3
[model]
kind = "linear_quadrotor"
sensor = "positions"
[[scenarios]]
name = "hover"
x0 = [1.0, 0.0, 1.0, 0.0, 1.0, 0.0]
duration_s = 1.0
[noise]
scales = [1.0]
[[filters]]
label = "ext"
kind = "external"
"#;

const QUANTITIES: [&str; 6] = ["x", "xdot", "y", "ydot", "z", "zdot"];

/// The spec simulated: (its folder, the simulation).
fn simulated() -> (tempfile::TempDir, PathBuf) {
    let d = tempfile::tempdir().unwrap();
    let spec = d.path().join("spec.toml");
    std::fs::write(&spec, SPEC).unwrap();
    let sim = d.path().join("sim");
    ok(kfmc()
        .args(["simulate", "-q", "--out"])
        .arg(&sim)
        .arg(&spec));
    (d, sim)
}

/// Sound estimates of every run: the truth as the estimate, P = I.
fn estimates(sim: &Path) -> DataFrame {
    let truth = read(&sim.join("truth.parquet"));
    let n = truth.height();
    let mut cols: Vec<Column> = ["scenario", "noise_scale", "run", "step"]
        .iter()
        .map(|k| truth.column(k).unwrap().clone())
        .collect();
    cols.push(Column::new("filter".into(), vec!["ext"; n]));
    for q in QUANTITIES {
        let c = truth.column(&format!("truth_{q}")).unwrap().clone();
        cols.push(c.with_name(format!("est_{q}").into()));
    }
    for (i, a) in QUANTITIES.iter().enumerate() {
        for b in &QUANTITIES[..=i] {
            let v = if a == b { 1.0 } else { 0.0 };
            cols.push(Column::new(format!("P_{a}_{b}").into(), vec![v; n]));
        }
    }
    DataFrame::new(n, cols).unwrap()
}

fn write(df: &DataFrame, path: &Path) {
    let mut df = df.clone();
    ParquetWriter::new(std::fs::File::create(path).unwrap())
        .finish(&mut df)
        .unwrap();
}

/// `kfmc score` of `file`: (exit code, stderr).
fn score(sim: &Path, file: &Path, out: &Path) -> (i32, String) {
    let (code, _, err) = run_cli(&[
        "score",
        sim.to_str().unwrap(),
        "--estimates",
        file.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "-q",
    ]);
    (code, err)
}

#[test]
fn decimal_and_map_columns_are_refused_naming_file_and_column_not_a_panic() {
    let (d, sim) = simulated();
    let fixtures = repo().join("tests/fixtures/estimates_types");
    for (file, column, type_name) in [
        ("decimal_value.parquet", "est_x", "decimal(10, 3)"),
        // Parquet's map is read as Arrow's list of key-value structs.
        ("map_value.parquet", "P_y_y", "list"),
        ("decimal_key.parquet", "noise_scale", "decimal(10, 3)"),
        ("map_key.parquet", "run", "list"),
    ] {
        let out = d.path().join(file);
        let (code, err) = score(&sim, &fixtures.join(file), &out);
        assert_eq!(code, 1, "{file}: {err}");
        assert!(
            !err.contains("panicked")
                && err.contains(file)
                && err.contains(&format!("column `{column}` holds {type_name} values")),
            "{file}: {err}"
        );
        assert!(!out.exists(), "{file}: nothing is written");
    }
}

#[test]
fn bool_int_and_string_value_columns_are_refused_naming_the_column() {
    let (d, sim) = simulated();
    let good = estimates(&sim);
    let n = good.height();
    let with = |name: &str, c: Column| -> DataFrame {
        let mut df = good.clone();
        df.with_column(c.with_name(name.into())).unwrap();
        df
    };
    for (column, df, type_name) in [
        (
            "est_x",
            with("est_x", Column::new("".into(), vec![true; n])),
            "bool",
        ),
        (
            "P_x_x",
            with("P_x_x", Column::new("".into(), vec![1i64; n])),
            "int64",
        ),
        (
            "est_zdot",
            with("est_zdot", Column::new("".into(), vec!["0.0"; n])),
            "string",
        ),
    ] {
        let file = d.path().join(format!("{column}.parquet"));
        write(&df, &file);
        let (code, err) = score(&sim, &file, &d.path().join(format!("out_{column}")));
        assert_eq!(code, 1, "{column}: {err}");
        assert!(
            err.contains(&format!("{column}.parquet"))
                && err.contains(&format!("column `{column}` holds {type_name} values"))
                && err.contains("float64 or float32"),
            "{err}"
        );
    }
    // The keys keep their types, and float32 values are read exactly: an integer noise
    // scale, a uint32 run and float32 covariances score as the float64 file does.
    let reference = d.path().join("good.parquet");
    write(&good, &reference);
    let (code, err) = score(&sim, &reference, &d.path().join("out_good"));
    assert_eq!(code, 0, "{err}");
    let mut keyed = with("noise_scale", Column::new("".into(), vec![1i64; n]));
    let run = keyed
        .column("run")
        .unwrap()
        .cast(&DataType::UInt32)
        .unwrap();
    keyed.with_column(run).unwrap();
    for (i, a) in QUANTITIES.iter().enumerate() {
        for b in &QUANTITIES[..=i] {
            let name = format!("P_{a}_{b}");
            let c = keyed
                .column(&name)
                .unwrap()
                .cast(&DataType::Float32)
                .unwrap();
            keyed.with_column(c).unwrap();
        }
    }
    let file = d.path().join("keyed.parquet");
    write(&keyed, &file);
    let (code, err) = score(&sim, &file, &d.path().join("out_keyed"));
    assert_eq!(code, 0, "{err}");
    assert_eq!(
        read(&d.path().join("out_good/runs.parquet")),
        read(&d.path().join("out_keyed/runs.parquet"))
    );
}

/// A table handed over in memory (the route of Python's tables) is checked the same way.
#[test]
fn a_bool_value_column_in_memory_is_refused_naming_the_column() {
    let (_d, sim) = simulated();
    let mut df = estimates(&sim);
    let n = df.height();
    df.with_column(Column::new("est_y".into(), vec![false; n]))
        .unwrap();
    let registry = kfmc::systems::builtin();
    let mut plan = kfmc::simulate::scoring_plan(&sim, None, &registry).unwrap();
    let source = kfmc::score::EstimatesSource::Stream(kfmc::score::TableStream {
        name: "<estimates 0>".into(),
        batches: Box::new(vec![Ok(df)].into_iter()),
        metadata: Vec::new(),
    });
    let e =
        kfmc::check::attach_estimates_from(&mut plan, [Ok(source)], kfmc::check::Unstamped::Warn)
            .unwrap_err()
            .to_string();
    assert!(
        e.contains("<estimates 0>") && e.contains("column `est_y` holds bool values"),
        "{e}"
    );
}
