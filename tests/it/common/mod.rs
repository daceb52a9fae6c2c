//! Helpers shared by the integration tests.
#![allow(dead_code)]

use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// A CSV with a header row and numeric or string cells.
pub struct Csv {
    pub header: Vec<String>,
    pub rows: Vec<Vec<String>>,
}

impl Csv {
    pub fn read(path: &Path) -> Csv {
        let text =
            std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        let mut lines = text.lines();
        let header = lines
            .next()
            .expect("header")
            .split(',')
            .map(str::to_string)
            .collect();
        let rows = lines
            .filter(|l| !l.is_empty())
            .map(|l| l.split(',').map(str::to_string).collect())
            .collect();
        Csv { header, rows }
    }
    pub fn col(&self, name: &str) -> usize {
        self.header
            .iter()
            .position(|h| h == name)
            .unwrap_or_else(|| panic!("no column {name}"))
    }
    pub fn f(&self, row: usize, name: &str) -> f64 {
        self.rows[row][self.col(name)].parse().expect("a number")
    }
    pub fn index(&self) -> HashMap<String, usize> {
        self.header
            .iter()
            .enumerate()
            .map(|(i, h)| (h.clone(), i))
            .collect()
    }
}

pub fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

pub fn kfmc() -> std::process::Command {
    std::process::Command::new(env!("CARGO_BIN_EXE_kfmc"))
}

/// Runs kfmc with `args`: (exit code, stdout, stderr).
pub fn run_cli(args: &[&str]) -> (i32, String, String) {
    let o = kfmc().args(args).output().unwrap();
    (
        o.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&o.stdout).into_owned(),
        String::from_utf8_lossy(&o.stderr).into_owned(),
    )
}

/// Every Parquet table in `dir`, by name, with its bytes: what byte-identity compares.
pub fn table_bytes(dir: &Path) -> Vec<(String, Vec<u8>)> {
    let mut v: Vec<(String, Vec<u8>)> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "parquet"))
        .map(|p| {
            (
                p.file_name().unwrap().to_string_lossy().into_owned(),
                std::fs::read(&p).unwrap(),
            )
        })
        .collect();
    v.sort();
    v
}

/// Writes a spec into a fresh temporary folder and returns (folder, spec path).
pub fn spec_in_tempdir(text: &str) -> (tempfile::TempDir, PathBuf) {
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("spec.toml");
    std::fs::write(&path, text).expect("write spec");
    (dir, path)
}

/// A small planar spec: `runs` runs, the given scales and extra TOML appended.
pub fn small_spec(out: &Path, runs: usize, scales: &str, filters: &str) -> String {
    format!(
        r#"
name = "small"
master_seed = 11
runs = {runs}
output = "{out}"
[model]
kind = "planar_quadrotor"
[[scenarios]]
name = "basic"
duration_s = 2.0
[[scenarios]]
name = "roll"
duration_s = 2.0
{filters}
[noise]
scales = {scales}
[divergence]
rmse_thresholds = [0.05, 0.05, 0.01, 0.05, 0.01, 0.01]
"#,
        out = out.display()
    )
}

pub const EKF_AND_MEAN: &str = r#"
[[filters]]
label = "ekf"
kind = "ekf"
[[filters]]
label = "running_mean"
kind = "running_mean"
"#;

/// A Parquet table, read whole.
pub fn read(path: &Path) -> polars::prelude::DataFrame {
    use polars::prelude::SerReader;
    polars::prelude::ParquetReader::new(std::fs::File::open(path).unwrap())
        .finish()
        .unwrap()
}

/// Runs `cmd`, asserting it succeeds (its stderr in the message).
pub fn ok(cmd: &mut std::process::Command) -> std::process::Output {
    let o = cmd.output().unwrap();
    assert!(
        o.status.success(),
        "{:?} failed: {}",
        cmd,
        String::from_utf8_lossy(&o.stderr)
    );
    o
}

/// The `kfmc.*` file metadata of a Parquet file (its world stamp), sorted by key.
pub fn stamp_of(path: &Path) -> Vec<(String, String)> {
    use polars::prelude::SerReader;
    let mut r = polars::prelude::ParquetReader::new(std::fs::File::open(path).unwrap());
    let meta = r.get_metadata().unwrap().clone();
    let mut stamp: Vec<(String, String)> = meta
        .key_value_metadata()
        .iter()
        .flatten()
        .filter(|kv| kv.key.starts_with("kfmc."))
        .map(|kv| (kv.key.clone(), kv.value.clone().unwrap_or_default()))
        .collect();
    stamp.sort();
    stamp
}

/// Writes `df` to `path` with the file metadata `meta` (a stamp, as an outside writer that
/// stamps its files would).
pub fn write_with(df: &polars::prelude::DataFrame, path: &Path, meta: &[(String, String)]) {
    let mut df = df.clone();
    polars::prelude::ParquetWriter::new(std::fs::File::create(path).unwrap())
        .with_key_value_metadata(Some(
            polars::io::parquet::write::KeyValueMetadata::from_static(meta.to_vec()),
        ))
        .finish(&mut df)
        .unwrap();
}

/// A column of `df` as floats (a float32 column widened), null as `None`.
pub fn f64s(df: &polars::prelude::DataFrame, name: &str) -> Vec<Option<f64>> {
    df.column(name)
        .unwrap_or_else(|e| panic!("column {name}: {e}"))
        .cast(&polars::prelude::DataType::Float64)
        .unwrap_or_else(|e| panic!("column {name}: {e}"))
        .f64()
        .expect("cast to float64")
        .iter()
        .collect()
}

/// A column of `df` as floats, null as NaN.
pub fn f64s_or_nan(df: &polars::prelude::DataFrame, name: &str) -> Vec<f64> {
    f64s(df, name)
        .into_iter()
        .map(|v| v.unwrap_or(f64::NAN))
        .collect()
}

/// An integer column of `df`; a null panics, naming the column.
pub fn i64s(df: &polars::prelude::DataFrame, name: &str) -> Vec<i64> {
    df.column(name)
        .unwrap_or_else(|e| panic!("column {name}: {e}"))
        .i64()
        .unwrap_or_else(|e| panic!("column {name}: {e}"))
        .iter()
        .map(|v| v.unwrap_or_else(|| panic!("column {name}: null")))
        .collect()
}

/// A string column of `df`, null as the empty string.
pub fn strs(df: &polars::prelude::DataFrame, name: &str) -> Vec<String> {
    df.column(name)
        .unwrap_or_else(|e| panic!("column {name}: {e}"))
        .str()
        .unwrap_or_else(|e| panic!("column {name}: {e}"))
        .iter()
        .map(|s| s.unwrap_or("").to_string())
        .collect()
}

/// A boolean column of `df`, null as `None`.
pub fn bools(df: &polars::prelude::DataFrame, name: &str) -> Vec<Option<bool>> {
    df.column(name)
        .unwrap_or_else(|e| panic!("column {name}: {e}"))
        .bool()
        .unwrap_or_else(|e| panic!("column {name}: {e}"))
        .iter()
        .collect()
}

/// Six cells (two planar scenarios × three noise scales, two filters, the EKF at two Q
/// scales) with every journaled table: runs, steps, summary, traces and consistency, and
/// divergence points rebuilt across the cells. The study that resume and shards cut apart
/// and put back together.
pub fn six_cell_planar(name: &str, runs: usize) -> String {
    format!(
        r#"
name = "{name}"
master_seed = 9
runs = {runs}
trace_runs = 1
[model]
kind = "planar_quadrotor"
[[scenarios]]
name = "basic"
duration_s = 2.0
[[scenarios]]
name = "roll"
duration_s = 2.0
[[filters]]
label = "ekf"
kind = "ekf"
q_scale = [1.0, 4.0]
[[filters]]
label = "running_mean"
kind = "running_mean"
[noise]
scales = [0.5, 1.0, 20.0]
[divergence]
rmse_thresholds = [0.05, 0.05, 0.02, 0.05, 0.02, 0.05]
[initial_estimate]
mode = "sampled"
p0_std = 0.01
[consistency]
alpha = 0.05
"#
    )
}
