//! Fuzzing what users hand in besides the spec text: every command's flags, estimates tables
//! for `score` and `check`, shard parts for `merge`, checkpoint journals and indexes for
//! `--resume`, and manifests and tables for `summary`, `plot` and `report`.
//!
//! Each input is a seeded mutation of a real command line or of a real file that kfmc wrote
//! for a small study, run through the `kfmc` binary with a time limit. The properties:
//! * never a panic (exit 101 or "panicked at"), a death by signal, or a hang past the limit;
//! * every refusal says why (a non-empty message on stderr);
//! * the gate never passes on damaged estimates: `check` does not exit 0 when rows were
//!   removed or a value was made non-finite;
//! * a damaged part or checkpoint is refused or gives exactly the tables of an undamaged
//!   study: a merge or a resume never commits other values.
//!
//! The command lines come from the CLI's own definition (clap's `CommandFactory`), so every
//! flag a command gains is fuzzed without editing this file.
//!
//! `cargo test --release --test it fuzz::input_fuzz::` runs a short pass of each target and replays the
//! inputs kept in `tests/fuzz_corpus/inputs/` (one per line: the target, then the mutation).
//! A longer run: `KFMC_FUZZ_INPUTS=2000 cargo test --release --test it fuzz::input_fuzz:: -- --nocapture`
//! (inputs per target; `KFMC_FUZZ_SEED` picks another stream). A failing input is printed in
//! the corpus format, ready to be added to the corpus.

use std::ffi::OsString;
use std::path::{Path, PathBuf};
use std::process::Stdio;
use std::time::{Duration, Instant};

use crate::common::{kfmc, read, stamp_of, table_bytes};
use clap::CommandFactory;
use polars::prelude::*;
use rand::{RngExt, SeedableRng};
use rand_pcg::Pcg64;

/// Inputs per target in a plain `cargo test` run.
const DEFAULT_INPUTS: usize = 60;
/// A command on these small studies takes well under a second; ten is a hang.
const LIMIT: Duration = Duration::from_secs(20);

fn inputs() -> usize {
    std::env::var("KFMC_FUZZ_INPUTS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(DEFAULT_INPUTS)
}

fn rng(target: &str) -> Pcg64 {
    let seed: u64 = std::env::var("KFMC_FUZZ_SEED")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(0x6b666d63);
    let salt = target
        .bytes()
        .fold(0u64, |h, b| h.wrapping_mul(31).wrapping_add(b as u64));
    Pcg64::seed_from_u64(seed ^ salt)
}

/// A linear-quadrotor study small enough to run in a fraction of a second, with every table
/// the commands read: consistency (so `check` judges), traces (so `plot` draws), and two
/// scenarios (so the two parts differ). One noise scale: at a larger one the nominal filter
/// is rightly optimistic, and the undamaged gate must pass.
const SPEC: &str = r#"
name = "fuzzed"
master_seed = 7
runs = 8
trace_runs = 1
[model]
kind = "linear_quadrotor"
sensor = "positions"
[[scenarios]]
name = "hover"
x0 = [1.0, 0.0, 1.0, 0.0, 1.0, 0.0]
duration_s = 2.0
[[scenarios]]
name = "drift"
x0 = [0.0, 0.5, 0.0, -0.5, 2.0, 0.0]
duration_s = 1.5
[noise]
scales = [1.0]
[[filters]]
label = "kf"
kind = "KIND"
[initial_estimate]
mode = "sampled"
p0_std = 1.0
[consistency]
alpha = 0.01
[divergence]
rmse_thresholds = [0.5, 0.5, 0.5, 0.5, 0.5, 0.5]
[[check.assert]]
kind = "consistent"
filter = "kf"
"#;

/// The files every target starts from, written once per test.
struct Fixture {
    _tmp: tempfile::TempDir,
    root: PathBuf,
}

impl Fixture {
    fn new() -> Self {
        let tmp = tempfile::tempdir().unwrap();
        let root = tmp.path().to_path_buf();
        std::fs::write(root.join("run.toml"), SPEC.replace("KIND", "ekf")).unwrap();
        std::fs::write(root.join("ext.toml"), SPEC.replace("KIND", "external")).unwrap();
        let f = Fixture { _tmp: tmp, root };
        f.ok(&[
            "run",
            "run.toml",
            "-q",
            "--export-estimates",
            "--out",
            "study",
        ]);
        f.ok(&["simulate", "ext.toml", "-q", "--out", "sim"]);
        std::fs::copy(
            f.root.join("study/estimates.parquet"),
            f.root.join("estimates.parquet"),
        )
        .unwrap();
        std::fs::write(
            f.root.join("estimates.csv"),
            "scenario,run,step\nhover,0,0\n",
        )
        .unwrap();
        f
    }

    fn ok(&self, args: &[&str]) {
        let o = kfmc().current_dir(&self.root).args(args).output().unwrap();
        assert!(
            o.status.success(),
            "kfmc {args:?}: {}",
            String::from_utf8_lossy(&o.stderr)
        );
    }

    /// A fresh copy of the fixture for one input, so that no input sees another's writes.
    fn copy(&self) -> tempfile::TempDir {
        let dir = tempfile::tempdir().unwrap();
        copy_tree(&self.root, dir.path());
        dir
    }
}

fn copy_tree(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        let dest = to.join(e.file_name());
        if e.file_type().unwrap().is_dir() {
            copy_tree(&e.path(), &dest);
        } else {
            std::fs::copy(e.path(), dest).unwrap();
        }
    }
}

/// How a command ended.
struct Outcome {
    code: Option<i32>,
    timed_out: bool,
    stderr: String,
}

thread_local! {
    /// Exit codes seen by this test (each test runs on a thread of its own), for the summary
    /// line that `report` prints.
    static CODES: std::cell::RefCell<std::collections::BTreeMap<String, usize>> =
        const { std::cell::RefCell::new(std::collections::BTreeMap::new()) };
}

/// Runs kfmc in `cwd`, killing it after [`LIMIT`].
fn run_limited(cwd: &Path, args: &[OsString]) -> Outcome {
    let mut child = kfmc()
        .current_dir(cwd)
        .args(args)
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut stderr = child.stderr.take().unwrap();
    let reader = std::thread::spawn(move || {
        let mut s = String::new();
        let _ = std::io::Read::read_to_string(&mut stderr, &mut s);
        s
    });
    let start = Instant::now();
    let (status, timed_out) = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break (s, false);
        }
        if start.elapsed() > LIMIT {
            let _ = child.kill();
            break (child.wait().unwrap(), true);
        }
        std::thread::sleep(Duration::from_millis(2));
    };
    let key = match (timed_out, status.code()) {
        (true, _) => "timeout".to_string(),
        (false, Some(c)) => format!("exit {c}"),
        (false, None) => "signal".to_string(),
    };
    CODES.with(|c| *c.borrow_mut().entry(key).or_default() += 1);
    Outcome {
        code: status.code(),
        timed_out,
        stderr: reader.join().unwrap(),
    }
}

/// The properties every input must keep; `Err` describes the violation.
fn clean(o: &Outcome) -> Result<(), String> {
    if o.timed_out {
        return Err(format!("still running after {LIMIT:?}"));
    }
    match o.code {
        None => Err("killed by a signal".into()),
        Some(101) => Err(format!("panicked:\n{}", o.stderr)),
        _ if o.stderr.contains("panicked at") => Err(format!("panicked:\n{}", o.stderr)),
        // A verdict (a failed or an incomplete `check`) is a report, which `--quiet` silences,
        // not an error.
        Some(0 | 3 | 4) => Ok(()),
        Some(c) if o.stderr.trim().is_empty() => Err(format!("exit {c} without a message")),
        Some(_) => Ok(()),
    }
}

// ---------------------------------------------------------------------------------------
// Command lines.

/// Values tried for flags: numbers at and beyond every edge, text with separators, newlines
/// and shell tricks, and the fixture's paths (right and wrong kinds).
const VALUES: &[&str] = &[
    "0",
    "1",
    "2",
    "-1",
    "7",
    "0.5",
    "1e308",
    "1e400",
    "-1e308",
    "NaN",
    "inf",
    "-inf",
    "1000000000000",
    "18446744073709551615",
    "18446744073709551616",
    "0/0",
    "1/0",
    "0/1",
    "1/2",
    "2/2",
    "3/2",
    "0/1000000000000",
    "-1/2",
    "1/-2",
    "",
    " ",
    "a\nb",
    "x;rm -rf y",
    "$(id)",
    "ünïcødé",
    "..",
    "out",
    "study",
    "sim",
    "run.toml",
    "ext.toml",
    "estimates.parquet",
    "estimates.csv",
    "missing/nowhere",
    "/dev/null",
];

/// A subcommand as clap defines it: its name, positional arguments and flags.
struct CommandShape {
    name: String,
    positionals: Vec<Vec<String>>,
    flags: Vec<(String, bool, Vec<String>)>,
}

fn shapes() -> Vec<CommandShape> {
    kfmc::cli::Cli::command()
        .get_subcommands()
        .map(|sub| {
            let mut positionals = Vec::new();
            let mut flags = Vec::new();
            for a in sub.get_arguments() {
                let possible: Vec<String> = a
                    .get_possible_values()
                    .iter()
                    .map(|v| v.get_name().to_string())
                    .collect();
                if a.is_positional() {
                    positionals.push(possible);
                } else if let Some(long) = a.get_long() {
                    let takes_value = a.get_action().takes_values();
                    flags.push((format!("--{long}"), takes_value, possible));
                }
            }
            CommandShape {
                name: sub.get_name().to_string(),
                positionals,
                flags,
            }
        })
        .collect()
}

fn pick<'a, T>(rng: &mut Pcg64, items: &'a [T]) -> &'a T {
    &items[rng.random_range(0..items.len())]
}

/// A value for an argument: one of its possible values (or, rarely, something else).
fn value(rng: &mut Pcg64, possible: &[String]) -> String {
    if !possible.is_empty() && rng.random_bool(0.8) {
        pick(rng, possible).clone()
    } else {
        pick(rng, VALUES).to_string()
    }
}

/// A command line: a subcommand, its positionals, a few flags with values, and usually an
/// output folder of its own (so that the input does not write over the fixture's folders
/// every time; sometimes it does, on purpose).
fn command_line(rng: &mut Pcg64, shapes: &[CommandShape]) -> Vec<String> {
    let shape = pick(rng, shapes);
    let mut args = vec![shape.name.clone()];
    for possible in &shape.positionals {
        if rng.random_bool(0.95) {
            args.push(value(rng, possible));
        }
    }
    for _ in 0..rng.random_range(0..5) {
        if shape.flags.is_empty() {
            break;
        }
        let (flag, takes_value, possible) = pick(rng, &shape.flags);
        args.push(flag.clone());
        if *takes_value {
            args.push(value(rng, possible));
        }
    }
    if rng.random_bool(0.05) {
        args.push("--no-such-flag".into());
    }
    if shape.flags.iter().any(|(f, _, _)| f == "--out") && rng.random_bool(0.8) {
        args.push("--out".into());
        args.push("fuzz-out".into());
    }
    if shape.flags.iter().any(|(f, _, _)| f == "--quiet") {
        args.push("--quiet".into());
    }
    args
}

fn check_command_line(fixture: &Fixture, args: &[String]) -> Result<(), String> {
    let dir = fixture.copy();
    let os: Vec<OsString> = args.iter().map(OsString::from).collect();
    clean(&run_limited(dir.path(), &os))
}

// ---------------------------------------------------------------------------------------
// File mutations.

/// One change to a file. Structured changes act on a Parquet table's values; byte changes on
/// any file.
#[derive(Clone, Debug)]
enum Mutation {
    /// Cell (column index, row) set to a value (`nan`, `inf`, a number).
    Set(usize, usize, String),
    /// Rows [start, start + len) removed.
    DropRows(usize, usize),
    /// Row duplicated in place.
    Duplicate(usize),
    /// Two rows swapped.
    Swap(usize, usize),
    /// Column removed.
    DropColumn(usize),
    /// Column renamed.
    Rename(usize, String),
    /// Column cast to another type (`str`, `i32`, `f32`, `bool`).
    Cast(usize, String),
    /// Bit `bit` of byte `offset` flipped.
    Flip(usize, u8),
    /// File cut to `len` bytes.
    Truncate(usize),
    /// `len` bytes from `offset` overwritten with `byte`.
    Overwrite(usize, usize, u8),
    /// The file removed.
    Delete,
    /// A text file's line `i` removed (manifests, indexes).
    DropLine(usize),
    /// A text file's number at occurrence `i` replaced.
    Number(usize, String),
}

impl Mutation {
    fn to_corpus(&self) -> String {
        match self {
            Mutation::Set(c, r, v) => format!("set {c} {r} {v}"),
            Mutation::DropRows(s, n) => format!("drop_rows {s} {n}"),
            Mutation::Duplicate(r) => format!("duplicate {r}"),
            Mutation::Swap(a, b) => format!("swap {a} {b}"),
            Mutation::DropColumn(c) => format!("drop_column {c}"),
            Mutation::Rename(c, n) => format!("rename {c} {n}"),
            Mutation::Cast(c, t) => format!("cast {c} {t}"),
            Mutation::Flip(o, b) => format!("flip {o} {b}"),
            Mutation::Truncate(n) => format!("truncate {n}"),
            Mutation::Overwrite(o, n, b) => format!("overwrite {o} {n} {b}"),
            Mutation::Delete => "delete".into(),
            Mutation::DropLine(i) => format!("drop_line {i}"),
            Mutation::Number(i, v) => format!("number {i} {v}"),
        }
    }

    fn from_corpus(text: &str) -> Mutation {
        let w: Vec<&str> = text.split_whitespace().collect();
        let n = |i: usize| -> usize { w[i].parse().unwrap() };
        match w[0] {
            "set" => Mutation::Set(n(1), n(2), w[3].into()),
            "drop_rows" => Mutation::DropRows(n(1), n(2)),
            "duplicate" => Mutation::Duplicate(n(1)),
            "swap" => Mutation::Swap(n(1), n(2)),
            "drop_column" => Mutation::DropColumn(n(1)),
            "rename" => Mutation::Rename(n(1), w[2].into()),
            "cast" => Mutation::Cast(n(1), w[2].into()),
            "flip" => Mutation::Flip(n(1), w[2].parse().unwrap()),
            "truncate" => Mutation::Truncate(n(1)),
            "overwrite" => Mutation::Overwrite(n(1), n(2), w[3].parse().unwrap()),
            "delete" => Mutation::Delete,
            "drop_line" => Mutation::DropLine(n(1)),
            "number" => Mutation::Number(n(1), w[2].into()),
            other => panic!("unknown mutation {other}"),
        }
    }

    /// Whether a gate judging these estimates lost data the spec declares: rows removed, or a
    /// value made non-finite. A `check` that exits 0 after one of these passed on damage.
    fn damages_estimates(&self, df: &DataFrame) -> bool {
        match self {
            Mutation::DropRows(_, n) => *n > 0,
            Mutation::Set(c, _, v) => {
                let numeric = df.columns()[*c].dtype().is_float();
                numeric && v.parse::<f64>().is_ok_and(|x| !x.is_finite())
            }
            _ => false,
        }
    }

    /// Applies a structured change to `df` (a no-op for byte and text changes).
    fn apply_to_table(&self, df: &mut DataFrame) -> PolarsResult<()> {
        let height = df.height();
        match self {
            Mutation::Set(c, r, v) => {
                let col = df.columns()[*c].clone();
                let r = (*r).min(height.saturating_sub(1));
                let flags: Vec<bool> = (0..height).map(|i| i == r).collect();
                let mask = BooleanChunked::from_slice("mask".into(), &flags);
                let name = col.name().clone();
                let changed = match col.dtype() {
                    DataType::Float64 => {
                        let x: f64 = v.parse().unwrap_or(f64::NAN);
                        let f = col.f64()?;
                        let other = Float64Chunked::full(name.clone(), x, height);
                        f.zip_with(&mask, &other)?.into_series()
                    }
                    DataType::Int64 | DataType::UInt64 | DataType::Int32 | DataType::UInt32 => {
                        let x: i64 = v.parse::<f64>().map_or(-1, |x| x as i64);
                        let c64 = col.cast(&DataType::Int64)?;
                        let other = Int64Chunked::full(name.clone(), x, height);
                        c64.i64()?.zip_with(&mask, &other)?.into_series()
                    }
                    _ => {
                        let s = col.cast(&DataType::String)?;
                        let other = StringChunked::full(name.clone(), v, height);
                        s.str()?.zip_with(&mask, &other)?.into_series()
                    }
                };
                df.replace(name.as_str(), changed.into_column())?;
            }
            Mutation::DropRows(s, n) => {
                let s = (*s).min(height);
                let flags: Vec<bool> = (0..height).map(|i| i < s || i >= s + n).collect();
                *df = df.filter(&BooleanChunked::from_slice("keep".into(), &flags))?;
            }
            Mutation::Duplicate(r) => {
                let r = (*r).min(height.saturating_sub(1));
                let idx: Vec<IdxSize> = (0..height)
                    .flat_map(|i| if i == r { vec![i, i] } else { vec![i] })
                    .map(|i| i as IdxSize)
                    .collect();
                *df = df.take(&IdxCa::from_vec("idx".into(), idx))?;
            }
            Mutation::Swap(a, b) => {
                let last = height.saturating_sub(1);
                let (a, b) = ((*a).min(last), (*b).min(last));
                let idx: Vec<IdxSize> = (0..height)
                    .map(|i| {
                        if i == a {
                            b
                        } else if i == b {
                            a
                        } else {
                            i
                        }
                    })
                    .map(|i| i as IdxSize)
                    .collect();
                *df = df.take(&IdxCa::from_vec("idx".into(), idx))?;
            }
            Mutation::DropColumn(c) => {
                let name = df.columns()[*c].name().clone();
                *df = df.drop(name.as_str())?;
            }
            Mutation::Rename(c, new) => {
                let name = df.columns()[*c].name().clone();
                df.rename(name.as_str(), new.as_str().into())?;
            }
            Mutation::Cast(c, to) => {
                let col = df.columns()[*c].clone();
                let dtype = match to.as_str() {
                    "str" => DataType::String,
                    "i32" => DataType::Int32,
                    "f32" => DataType::Float32,
                    _ => DataType::Boolean,
                };
                let cast = col.cast(&dtype)?;
                df.replace(col.name().as_str(), cast)?;
            }
            _ => {}
        }
        Ok(())
    }

    /// Applies a byte or text change to the file at `path` (a no-op for structured changes).
    fn apply_to_file(&self, path: &Path) {
        match self {
            Mutation::Flip(o, b) => {
                let mut bytes = std::fs::read(path).unwrap();
                if !bytes.is_empty() {
                    let o = o % bytes.len();
                    bytes[o] ^= 1 << (b % 8);
                }
                std::fs::write(path, bytes).unwrap();
            }
            Mutation::Truncate(n) => {
                let bytes = std::fs::read(path).unwrap();
                std::fs::write(path, &bytes[..(*n).min(bytes.len())]).unwrap();
            }
            Mutation::Overwrite(o, n, b) => {
                let mut bytes = std::fs::read(path).unwrap();
                let len = bytes.len();
                for x in bytes.iter_mut().skip(o % len.max(1)).take(*n) {
                    *x = *b;
                }
                std::fs::write(path, bytes).unwrap();
            }
            Mutation::Delete => {
                let _ = std::fs::remove_file(path);
            }
            Mutation::DropLine(i) => {
                let text = String::from_utf8_lossy(&std::fs::read(path).unwrap()).into_owned();
                let lines: Vec<&str> = text.lines().collect();
                let i = i % lines.len().max(1);
                let kept: Vec<&str> = lines
                    .iter()
                    .enumerate()
                    .filter(|(j, _)| *j != i)
                    .map(|(_, l)| *l)
                    .collect();
                std::fs::write(path, kept.join("\n") + "\n").unwrap();
            }
            Mutation::Number(i, v) => {
                let text = String::from_utf8_lossy(&std::fs::read(path).unwrap()).into_owned();
                std::fs::write(path, replace_number(&text, *i, v)).unwrap();
            }
            _ => {}
        }
    }

    fn is_structured(&self) -> bool {
        matches!(
            self,
            Mutation::Set(..)
                | Mutation::DropRows(..)
                | Mutation::Duplicate(..)
                | Mutation::Swap(..)
                | Mutation::DropColumn(..)
                | Mutation::Rename(..)
                | Mutation::Cast(..)
        )
    }
}

/// `text` with its `i`-th run of digits (mod the count) replaced by `v`.
fn replace_number(text: &str, i: usize, v: &str) -> String {
    let bytes = text.as_bytes();
    let mut runs = Vec::new();
    let mut j = 0;
    while j < bytes.len() {
        if bytes[j].is_ascii_digit() {
            let start = j;
            while j < bytes.len() && bytes[j].is_ascii_digit() {
                j += 1;
            }
            runs.push((start, j));
        } else {
            j += 1;
        }
    }
    if runs.is_empty() {
        return text.to_string();
    }
    let (s, e) = runs[i % runs.len()];
    format!("{}{}{}", &text[..s], v, &text[e..])
}

const NUMBERS: &[&str] = &[
    "nan",
    "inf",
    "-inf",
    "0",
    "-1",
    "1e308",
    "-1e-300",
    "3",
    "1000000000000",
];

/// A structured change for a table of `width` columns and `height` rows.
fn structured(rng: &mut Pcg64, width: usize, height: usize) -> Mutation {
    let c = rng.random_range(0..width);
    let r = rng.random_range(0..height.max(1));
    match rng.random_range(0..7) {
        0 | 1 => Mutation::Set(c, r, pick(rng, NUMBERS).to_string()),
        2 => Mutation::DropRows(r, rng.random_range(1..=(height / 4).max(1))),
        3 => Mutation::Duplicate(r),
        4 => Mutation::Swap(r, rng.random_range(0..height.max(1))),
        5 => match rng.random_range(0..3) {
            0 => Mutation::DropColumn(c),
            1 => Mutation::Rename(
                c,
                pick(rng, &["run", "step", "x", "P_0_0", "zz"]).to_string(),
            ),
            _ => Mutation::Cast(c, pick(rng, &["str", "i32", "f32", "bool"]).to_string()),
        },
        _ => Mutation::DropRows(0, height),
    }
}

/// A byte or text change for a file of `len` bytes.
fn bytewise(rng: &mut Pcg64, len: usize, text: bool) -> Mutation {
    let o = rng.random_range(0..len.max(1));
    match rng.random_range(0..if text { 7 } else { 5 }) {
        0 | 1 => Mutation::Flip(o, rng.random_range(0..8)),
        2 => Mutation::Truncate(o),
        3 => Mutation::Overwrite(o, rng.random_range(1..64), rng.random()),
        4 => Mutation::Delete,
        5 => Mutation::DropLine(rng.random_range(0..1000)),
        _ => Mutation::Number(rng.random_range(0..1000), pick(rng, NUMBERS).to_string()),
    }
}

/// Every file under `dir` (relative paths, sorted), `filter` choosing which.
fn files_under(dir: &Path, filter: &dyn Fn(&Path) -> bool) -> Vec<PathBuf> {
    fn walk(root: &Path, dir: &Path, out: &mut Vec<PathBuf>) {
        for e in std::fs::read_dir(dir).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                walk(root, &p, out);
            } else {
                out.push(p.strip_prefix(root).unwrap().to_path_buf());
            }
        }
    }
    let mut out = Vec::new();
    walk(dir, dir, &mut out);
    out.retain(|p| filter(p));
    out.sort();
    out
}

/// Writes `df` with the stamp `meta`, as a writer outside kfmc that stamps its files would:
/// the damage is then in the values, not in a missing stamp that `check` refuses first.
fn write_parquet(df: &mut DataFrame, path: &Path, meta: &[(String, String)]) {
    ParquetWriter::new(std::fs::File::create(path).unwrap())
        .with_key_value_metadata(Some(
            polars::io::parquet::write::KeyValueMetadata::from_static(meta.to_vec()),
        ))
        .finish(df)
        .unwrap();
}

fn os(args: &[&str]) -> Vec<OsString> {
    args.iter().map(OsString::from).collect()
}

/// Estimates for `score` and `check`: the property above, plus the gate rule.
fn check_estimates(fixture: &Fixture, m: &Mutation) -> Result<(), String> {
    let dir = fixture.copy();
    let path = dir.path().join("estimates.parquet");
    let mut df = read(&path);
    let stamp = stamp_of(&path);
    let damaged = m.damages_estimates(&df);
    if m.is_structured() {
        if m.apply_to_table(&mut df).is_err() {
            return Ok(()); // the change does not apply to this column's type
        }
        write_parquet(&mut df, &path, &stamp);
    } else {
        m.apply_to_file(&path);
    }
    let score = run_limited(
        dir.path(),
        &os(&[
            "score",
            "sim",
            "--estimates",
            "estimates.parquet",
            "--out",
            "scored",
            "-q",
        ]),
    );
    clean(&score).map_err(|e| format!("score: {e}"))?;
    let check = run_limited(
        dir.path(),
        &os(&[
            "check",
            "ext.toml",
            "--estimates",
            "estimates.parquet",
            "--out",
            "checked",
            "-q",
        ]),
    );
    clean(&check).map_err(|e| format!("check: {e}"))?;
    if damaged && check.code == Some(0) {
        return Err("check passed on estimates with rows removed or a non-finite value".into());
    }
    Ok(())
}

/// A random change to one estimates table.
fn estimates_mutation(rng: &mut Pcg64, fixture: &Fixture) -> Mutation {
    let path = fixture.root.join("estimates.parquet");
    if rng.random_bool(0.75) {
        let df = read(&path);
        structured(rng, df.width(), df.height())
    } else {
        bytewise(rng, std::fs::metadata(&path).unwrap().len() as usize, false)
    }
}

// ---------------------------------------------------------------------------------------
// Targets.

fn report(target: &str, failures: &[(String, String)], tried: usize) {
    let codes: Vec<String> = CODES.with(|c| {
        c.borrow()
            .iter()
            .map(|(k, n)| format!("{k}: {n}"))
            .collect()
    });
    eprintln!(
        "{target}: {tried} inputs; commands ended {}",
        codes.join(", ")
    );
    for (input, why) in failures {
        eprintln!("FAILING INPUT\t{target}\t{input}\n  {why}");
    }
    assert!(
        failures.is_empty(),
        "{target}: {} of {tried} inputs broke a property (see the FAILING INPUT lines)",
        failures.len()
    );
}

/// Corpus lines of one target: (file, mutation or command line).
fn corpus(target: &str) -> Vec<String> {
    let dir = crate::common::repo().join("tests/fuzz_corpus/inputs");
    let Ok(text) = std::fs::read_to_string(dir.join(format!("{target}.txt"))) else {
        return Vec::new();
    };
    text.lines()
        .filter(|l| !l.trim().is_empty() && !l.starts_with('#'))
        .map(str::to_string)
        .collect()
}

#[test]
fn command_lines_never_panic_hang_or_fail_silently() {
    let fixture = Fixture::new();
    let shapes = shapes();
    assert!(shapes.len() >= 15, "the CLI's commands");
    let mut rng = rng("flags");
    let mut failures = Vec::new();
    let mut lines: Vec<Vec<String>> = corpus("flags")
        .iter()
        .map(|l| l.split('\t').map(str::to_string).collect())
        .collect();
    let replayed = lines.len();
    for _ in 0..inputs() * 3 {
        lines.push(command_line(&mut rng, &shapes));
    }
    for args in &lines {
        if let Err(why) = check_command_line(&fixture, args) {
            failures.push((args.join("\t"), why));
        }
    }
    eprintln!(
        "flags: {} command lines ({replayed} from the corpus)",
        lines.len()
    );
    report("flags", &failures, lines.len());
}

#[test]
fn damaged_estimates_are_refused_or_judged_never_passed() {
    let fixture = Fixture::new();
    // The undamaged estimates pass the gate: what the mutations below must never keep.
    let dir = fixture.copy();
    let o = run_limited(
        dir.path(),
        &os(&[
            "check",
            "ext.toml",
            "--estimates",
            "estimates.parquet",
            "--out",
            "c",
            "-q",
        ]),
    );
    assert_eq!(o.code, Some(0), "the undamaged gate: {}", o.stderr);

    let mut rng = rng("estimates");
    let mut inputs_: Vec<Mutation> = corpus("estimates")
        .iter()
        .map(|l| Mutation::from_corpus(l))
        .collect();
    for _ in 0..inputs() {
        inputs_.push(estimates_mutation(&mut rng, &fixture));
    }
    let mut failures = Vec::new();
    for m in &inputs_ {
        if let Err(why) = check_estimates(&fixture, m) {
            failures.push((m.to_corpus(), why));
        }
    }
    report("estimates", &failures, inputs_.len());
}

/// A study run in two shards, each part's files fuzzed before `merge`: the merged tables are
/// the one-process tables or the merge is refused.
#[test]
fn damaged_parts_are_refused_or_merge_to_the_same_tables() {
    let fixture = Fixture::new();
    for i in 0..2 {
        fixture.ok(&[
            "run",
            "run.toml",
            "-q",
            "--shard",
            &format!("{i}/2"),
            "--out",
            "sharded",
        ]);
    }
    let want = table_bytes(&fixture.root.join("study"))
        .into_iter()
        .filter(|(n, _)| n != "estimates.parquet")
        .collect::<Vec<_>>();
    let files = files_under(&fixture.root.join("sharded"), &|_| true);
    assert!(files.len() >= 4, "two parts with their tables: {files:?}");
    // Undamaged, the parts merge to the one-process tables: what every input is held to.
    let dir = fixture.copy();
    let o = run_limited(dir.path(), &os(&["merge", "sharded"]));
    assert_eq!(o.code, Some(0), "the undamaged merge: {}", o.stderr);
    let got = table_bytes(&dir.path().join("sharded"));
    for (name, bytes) in &want {
        assert!(
            got.iter().any(|(n, b)| n == name && b == bytes),
            "the undamaged merge's {name}"
        );
    }
    let mut rng = rng("parts");
    let mut cases: Vec<(PathBuf, Mutation)> = corpus("parts")
        .iter()
        .map(|l| {
            let (f, m) = l.split_once('\t').unwrap();
            (PathBuf::from(f), Mutation::from_corpus(m))
        })
        .collect();
    for _ in 0..inputs() {
        let f = pick(&mut rng, &files).clone();
        let len = std::fs::metadata(fixture.root.join("sharded").join(&f))
            .unwrap()
            .len() as usize;
        let text = f.extension().is_some_and(|e| e == "toml");
        cases.push((f, bytewise(&mut rng, len, text)));
    }
    let mut failures = Vec::new();
    for (f, m) in &cases {
        let dir = fixture.copy();
        m.apply_to_file(&dir.path().join("sharded").join(f));
        let o = run_limited(dir.path(), &os(&["merge", "sharded"]));
        let verdict = clean(&o).and_then(|()| {
            if o.code == Some(0) {
                let got: Vec<_> = table_bytes(&dir.path().join("sharded"));
                for (name, bytes) in &want {
                    if got.iter().find(|(n, _)| n == name).map(|(_, b)| b) != Some(bytes) {
                        return Err(format!("merge exited 0 with {name} unlike one process's"));
                    }
                }
            }
            Ok(())
        });
        if let Err(why) = verdict {
            failures.push((format!("{}\t{}", f.display(), m.to_corpus()), why));
        }
    }
    report("parts", &failures, cases.len());
}

/// A checkpoint of an interrupted run, its journal and index fuzzed before `--resume`: the
/// resumed tables are the uninterrupted run's or the resume is refused.
#[test]
fn damaged_checkpoints_are_refused_or_resume_to_the_same_tables() {
    let fixture = Fixture::new();
    let want = table_bytes(&fixture.root.join("study"))
        .into_iter()
        .filter(|(n, _)| n != "estimates.parquet")
        .collect::<Vec<_>>();
    // Interrupted after its first checkpointed cell (one thread, a checkpoint per cell).
    let out = fixture.root.join("interrupted");
    let mut child = kfmc()
        .current_dir(&fixture.root)
        .args([
            "run",
            "run.toml",
            "-q",
            "--threads",
            "1",
            "--checkpoint-every",
            "0",
        ])
        .args(["--out", "interrupted"])
        .spawn()
        .unwrap();
    let deadline = Instant::now() + Duration::from_secs(60);
    let index = out.join(".checkpoint/index.toml");
    while !index.exists() && child.try_wait().unwrap().is_none() && Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(1));
    }
    let _ = child.kill();
    let _ = child.wait();
    if !index.exists() {
        // The run finished before a checkpoint could be seen: nothing to fuzz on this machine.
        eprintln!("no checkpoint caught; the run ended first");
        return;
    }
    let files = files_under(&out.join(".checkpoint"), &|_| true);
    // Undamaged, the checkpoint resumes to the whole run's tables.
    let dir = fixture.copy();
    let o = run_limited(
        dir.path(),
        &os(&["run", "run.toml", "-q", "--resume", "--out", "interrupted"]),
    );
    assert_eq!(o.code, Some(0), "the undamaged resume: {}", o.stderr);
    let got = table_bytes(&dir.path().join("interrupted"));
    for (name, bytes) in &want {
        assert!(
            got.iter().any(|(n, b)| n == name && b == bytes),
            "the undamaged resume's {name}"
        );
    }
    let mut rng = rng("checkpoint");
    let mut cases: Vec<(PathBuf, Mutation)> = corpus("checkpoint")
        .iter()
        .map(|l| {
            let (f, m) = l.split_once('\t').unwrap();
            (PathBuf::from(f), Mutation::from_corpus(m))
        })
        .collect();
    for _ in 0..inputs() {
        let f = pick(&mut rng, &files).clone();
        let len = std::fs::metadata(out.join(".checkpoint").join(&f))
            .unwrap()
            .len() as usize;
        let text = f.extension().is_some_and(|e| e == "toml");
        cases.push((f, bytewise(&mut rng, len, text)));
    }
    let mut failures = Vec::new();
    for (f, m) in &cases {
        let dir = fixture.copy();
        let target = dir.path().join("interrupted/.checkpoint").join(f);
        if !target.exists() {
            continue; // a corpus line for a file this machine's checkpoint does not have
        }
        m.apply_to_file(&target);
        let o = run_limited(
            dir.path(),
            &os(&["run", "run.toml", "-q", "--resume", "--out", "interrupted"]),
        );
        let verdict = clean(&o).and_then(|()| {
            if o.code == Some(0) {
                let got = table_bytes(&dir.path().join("interrupted"));
                for (name, bytes) in &want {
                    if got.iter().find(|(n, _)| n == name).map(|(_, b)| b) != Some(bytes) {
                        return Err(format!("resume exited 0 with {name} unlike a whole run's"));
                    }
                }
            }
            Ok(())
        });
        if let Err(why) = verdict {
            failures.push((format!("{}\t{}", f.display(), m.to_corpus()), why));
        }
    }
    report("checkpoint", &failures, cases.len());
}

/// A committed study, its manifest or a table fuzzed before `summary`, `plot` and `report`.
#[test]
fn damaged_study_folders_are_refused_or_read_never_panic() {
    let fixture = Fixture::new();
    let study = fixture.root.join("study");
    let files = files_under(&study, &|p| {
        p.extension().is_some_and(|e| e == "toml" || e == "parquet")
    });
    let mut rng = rng("manifest");
    let mut cases: Vec<(PathBuf, Mutation)> = corpus("manifest")
        .iter()
        .map(|l| {
            let (f, m) = l.split_once('\t').unwrap();
            (PathBuf::from(f), Mutation::from_corpus(m))
        })
        .collect();
    for _ in 0..inputs() {
        // The manifest most of the time: it is what a reader trusts first.
        let f = if rng.random_bool(0.6) {
            PathBuf::from("manifest.toml")
        } else {
            pick(&mut rng, &files).clone()
        };
        let len = std::fs::metadata(study.join(&f)).unwrap().len() as usize;
        let text = f.extension().is_some_and(|e| e == "toml");
        cases.push((f, bytewise(&mut rng, len, text)));
    }
    let mut failures = Vec::new();
    for (i, (f, m)) in cases.iter().enumerate() {
        let dir = fixture.copy();
        m.apply_to_file(&dir.path().join("study").join(f));
        // One reader per input, in turn, so that each sees the damage first.
        let args = match i % 3 {
            0 => os(&["summary", "study"]),
            1 => os(&["plot", "study", "--format", "svg", "--out", "figs"]),
            _ => os(&["report", "study", "--out", "r.html"]),
        };
        if let Err(why) = clean(&run_limited(dir.path(), &args)) {
            failures.push((format!("{}\t{}", f.display(), m.to_corpus()), why));
        }
    }
    report("manifest", &failures, cases.len());
}

#[test]
fn corpus_lines_parse() {
    for target in ["estimates", "parts", "checkpoint", "manifest"] {
        for line in corpus(target) {
            let m = line.rsplit('\t').next().unwrap();
            let _ = Mutation::from_corpus(m);
        }
    }
    // Command-line corpus entries name a subcommand the CLI has.
    let names: Vec<String> = shapes().into_iter().map(|s| s.name).collect();
    for line in corpus("flags") {
        let sub = line.split('\t').next().unwrap();
        assert!(names.iter().any(|n| n == sub), "corpus names {sub}");
    }
}
