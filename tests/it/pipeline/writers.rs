//! Writers of a folder: at most one at a time, each replaces only its own kind of result,
//! and a stop leaves the earlier study whole.
//!
//! * Concurrent pairs of every writing command (run, score, merge, power, tune, simulate,
//!   describe --out) into one folder: every pair ends with one complete, verified study (or
//!   file) and, for the writer that lost the race, a clean refusal (exit 1 naming the holder's
//!   pid, host and start time); never two writers at once, never an exit 0 over a broken
//!   folder. The pairs run one after another over the same folder, so all but the first
//!   replace an existing result. `KFMC_WRITER_PAIRS` sets the pairs per command (default 14);
//!   `KFMC_WRITERS_BIN` runs them against another kfmc binary (e.g. an older build).
//! * `score SIM --out SIM`, `run --out SIM`, `power --out RUNDIR` are refused without
//!   `--force`, saying what the folder holds, and the folder is left as it was.
//! * `merge` stopped by SIGINT or SIGTERM exits 130 and leaves the parts intact, no
//!   manifest; `tune` stopped over an earlier tune folder leaves that search whole.
//! * Shards: a simulation part is never written over a run's part; `status` counts only the
//!   parts of one study; `merge --force` exists where merge advises it.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use kfmc::output::folder::verify;
use kfmc::output::manifest::{Manifest, StudyKind};

const SPEC: &str = r#"
name = "writers"
master_seed = 7
runs = 4
[model]
kind = "linear_quadrotor"
sensor = "positions"
[[scenarios]]
name = "hover"
x0 = [1.0, 0.0, 1.0, 0.0, 1.0, 0.0]
duration_s = 1.0
[noise]
scales = [1.0, 3.0]
[[filters]]
label = "kf"
kind = "KIND"
[initial_estimate]
mode = "sampled"
p0_std = 1.0
[consistency]
alpha = 0.05
[divergence]
rmse_thresholds = [0.5, 0.5, 0.5, 0.5, 0.5, 0.5]
"#;

fn kfmc() -> Command {
    match std::env::var_os("KFMC_WRITERS_BIN") {
        Some(bin) => Command::new(bin),
        None => crate::common::kfmc(),
    }
}

fn output(cmd: &mut Command) -> (i32, String, String) {
    let o = cmd.output().expect("kfmc runs");
    (
        o.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&o.stdout).into_owned(),
        String::from_utf8_lossy(&o.stderr).into_owned(),
    )
}

fn ok(cmd: &mut Command) {
    let (code, _, err) = output(cmd);
    assert_eq!(code, 0, "{cmd:?}: {err}");
}

/// A temporary folder with the spec (`run.toml`, filter `kf` an EKF), the same spec with
/// `kf` external (`ext.toml`), kfmc's own estimates of `kf` (`kf.parquet`) and the
/// simulation of `ext.toml` (`sim/`).
struct World {
    _tmp: tempfile::TempDir,
    dir: PathBuf,
}

impl World {
    fn new() -> World {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().to_path_buf();
        std::fs::write(dir.join("run.toml"), SPEC.replace("KIND", "ekf")).unwrap();
        std::fs::write(dir.join("ext.toml"), SPEC.replace("KIND", "external")).unwrap();
        ok(kfmc()
            .args(["run", "-q", "--export-estimates", "--out"])
            .arg(dir.join("exported"))
            .arg(dir.join("run.toml")));
        std::fs::copy(
            dir.join("exported/estimates.parquet"),
            dir.join("kf.parquet"),
        )
        .unwrap();
        ok(kfmc()
            .args(["simulate", "-q", "--out"])
            .arg(dir.join("sim"))
            .arg(dir.join("ext.toml")));
        World { _tmp: tmp, dir }
    }
    fn p(&self, name: &str) -> PathBuf {
        self.dir.join(name)
    }
    fn s(&self, name: &str) -> String {
        self.p(name).to_str().unwrap().to_string()
    }
}

/// The command line of one writer into `out` (`seed` tells the two writers of a pair apart
/// where the command takes one).
fn writer(w: &World, command: &str, out: &Path, seed: u64) -> Command {
    let mut c = kfmc();
    let out_s = out.to_str().unwrap().to_string();
    let seed_s = seed.to_string();
    match command {
        "run" => c.args([
            "run",
            "-q",
            "--seed",
            &seed_s,
            "--out",
            &out_s,
            &w.s("run.toml"),
        ]),
        "simulate" => c.args([
            "simulate",
            "-q",
            "--seed",
            &seed_s,
            "--out",
            &out_s,
            &w.s("ext.toml"),
        ]),
        "score" => c.args([
            "score",
            "-q",
            &w.s("sim"),
            "--out",
            &out_s,
            "--estimates",
            &w.s("kf.parquet"),
        ]),
        "power" => c.args([
            "power",
            "-q",
            "--replications",
            "2",
            "--seed",
            &seed_s,
            "--out",
            &out_s,
            &w.s("run.toml"),
        ]),
        "tune" => c.args([
            "tune",
            "-q",
            "--runs",
            "2",
            "--seed",
            &seed_s,
            "--out",
            &out_s,
            &w.s("run.toml"),
        ]),
        "merge" => c.args(["merge", &out_s]),
        "describe" => c.args([
            "describe",
            &w.s("run.toml"),
            "--out",
            out.join("describe.toml").to_str().unwrap(),
        ]),
        other => panic!("no writer {other}"),
    };
    c.stdout(Stdio::null()).stderr(Stdio::piped());
    c
}

/// What a finished writer left: `Some(kind)` of a verified study, or the description's
/// check for `describe`.
fn check_folder(command: &str, out: &Path) -> Result<(), String> {
    if command == "describe" {
        let text = std::fs::read_to_string(out.join("describe.toml")).map_err(|e| e.to_string())?;
        return text
            .parse::<toml::Table>()
            .map(|_| ())
            .map_err(|e| format!("describe.toml does not parse: {e}"));
    }
    let m: Manifest = verify(out).map_err(|e| e.to_string())?;
    let want = match command {
        "run" | "merge" => StudyKind::Run,
        "simulate" => StudyKind::Simulate,
        "score" => StudyKind::Score,
        "power" => StudyKind::Power,
        "tune" => StudyKind::Tune,
        _ => unreachable!(),
    };
    if m.kind() != want {
        return Err(format!("holds a {:?} study, not {want:?}", m.kind()));
    }
    if command == "tune" {
        // The search's stages belong to the committed search.
        let coarse = verify(&out.join("tune_coarse")).map_err(|e| e.to_string())?;
        if coarse.master_seed != m.master_seed {
            return Err(format!(
                "tune_coarse is of seed {}, the search of seed {}",
                coarse.master_seed, m.master_seed
            ));
        }
    }
    for e in std::fs::read_dir(out).unwrap() {
        let n = e.unwrap().file_name().to_string_lossy().into_owned();
        if n.ends_with(".partial") || n == ".kfmc.lock" {
            return Err(format!("{n} left behind"));
        }
    }
    Ok(())
}

fn wait(mut child: Child) -> (i32, String) {
    use std::io::Read;
    let mut err = String::new();
    if let Some(mut e) = child.stderr.take() {
        let _ = e.read_to_string(&mut err);
    }
    let status = child.wait().unwrap();
    (status.code().unwrap_or(-1), err)
}

/// Runs `pairs` concurrent pairs of `command` into one folder and checks every outcome.
fn concurrent_pairs(command: &str) {
    let pairs: usize = std::env::var("KFMC_WRITER_PAIRS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(14);
    let w = World::new();
    let out = if command == "merge" {
        // Parts to merge, over and over.
        let out = w.p("sharded");
        for i in 0..2 {
            ok(kfmc()
                .args(["run", "-q", "--shard", &format!("{i}/2"), "--out"])
                .arg(&out)
                .arg(w.p("run.toml")));
        }
        out
    } else {
        w.p("out")
    };
    let (mut one_refused, mut both_ok, mut broken, mut bad) = (0, 0, 0, Vec::new());
    let started = Instant::now();
    for pair in 0..pairs {
        let a = writer(&w, command, &out, 100 + 2 * pair as u64)
            .spawn()
            .unwrap();
        let b = writer(&w, command, &out, 101 + 2 * pair as u64)
            .spawn()
            .unwrap();
        let (ra, rb) = (wait(a), wait(b));
        let mut problems = Vec::new();
        for (code, err) in [&ra, &rb] {
            match code {
                0 => {}
                1 if err.contains("being written by another kfmc (")
                    && (err.contains("on host") || err.contains("just taken the lock")) => {}
                _ => problems.push(format!("exit {code}: {}", err.trim())),
            }
        }
        match (ra.0, rb.0) {
            (0, 0) => both_ok += 1,
            (0, _) | (_, 0) => one_refused += 1,
            _ => problems.push("no writer succeeded".into()),
        }
        if let Err(e) = check_folder(command, &out) {
            broken += 1;
            problems.push(format!("folder after the pair: {e}"));
        }
        if !problems.is_empty() {
            bad.push(format!("pair {pair}: {}", problems.join("; ")));
        }
    }
    eprintln!(
        "{command}: {pairs} pairs in {:.1} s: one writer refused {one_refused}, both succeeded one after the other {both_ok}; wrong {} (of which the folder left broken {broken})",
        started.elapsed().as_secs_f64(),
        bad.len()
    );
    assert!(bad.is_empty(), "{command}:\n{}", bad.join("\n"));
}

#[test]
fn concurrent_runs() {
    concurrent_pairs("run");
}
#[test]
fn concurrent_scores() {
    concurrent_pairs("score");
}
#[test]
fn concurrent_merges() {
    concurrent_pairs("merge");
}
#[test]
fn concurrent_powers() {
    concurrent_pairs("power");
}
#[test]
fn concurrent_tunes() {
    concurrent_pairs("tune");
}
#[test]
fn concurrent_simulates() {
    concurrent_pairs("simulate");
}
#[test]
fn concurrent_describes() {
    concurrent_pairs("describe");
}

/// Every table file of a folder with its bytes.
fn snapshot(dir: &Path) -> Vec<(String, Vec<u8>)> {
    let mut v: Vec<(String, Vec<u8>)> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.is_file())
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

#[test]
fn a_writer_replaces_only_its_own_kind_of_folder_unless_forced() {
    let w = World::new();
    let (sim, run) = (w.s("sim"), w.p("exported"));
    let sim_before = snapshot(&w.p("sim"));
    let run_before = snapshot(&run);

    let refused = |args: &[&str], holds: &str| {
        let (code, _, err) = output(kfmc().args(args));
        assert_eq!(code, 1, "{args:?}: {err}");
        assert!(err.contains(holds), "{args:?}: {err}");
        assert!(err.contains("--force"), "{args:?}: {err}");
    };
    let kf = w.s("kf.parquet");
    refused(
        &["score", "-q", &sim, "--out", &sim, "--estimates", &kf],
        "holds a `kfmc simulate` world (the truth, measurements and initial tables",
    );
    refused(
        &["run", "-q", "--out", &sim, &w.s("run.toml")],
        "holds a `kfmc simulate` world",
    );
    let run_s = run.to_str().unwrap();
    refused(
        &[
            "power",
            "-q",
            "--replications",
            "1",
            "--out",
            run_s,
            &w.s("run.toml"),
        ],
        "holds the tables of a `kfmc run` (or `kfmc check`) study",
    );
    // Each refusal came before anything was touched.
    assert!(
        snapshot(&w.p("sim")) == sim_before,
        "the simulation changed"
    );
    assert!(snapshot(&run) == run_before, "the run changed");
    verify(&w.p("sim")).unwrap();
    verify(&run).unwrap();

    // The same kind replaces its own folder without being asked.
    ok(kfmc().args(["run", "-q", "--seed", "3", "--out", run_s, &w.s("run.toml")]));
    assert_eq!(verify(&run).unwrap().master_seed, 3);
    // --force replaces another kind.
    ok(kfmc().args(["run", "-q", "--force", "--out", &sim, &w.s("run.toml")]));
    assert_eq!(verify(&w.p("sim")).unwrap().kind(), StudyKind::Run);
}

#[test]
fn a_manifest_without_a_kind_is_read_and_its_kind_told() {
    let w = World::new();
    for (dir, want) in [("sim", StudyKind::Simulate), ("exported", StudyKind::Run)] {
        let path = w.p(dir).join("manifest.toml");
        let text = std::fs::read_to_string(&path).unwrap();
        let kept: String = text
            .lines()
            .filter(|l| !l.starts_with("kind = "))
            .map(|l| format!("{l}\n"))
            .collect();
        assert_ne!(kept, text, "{dir}: the manifest records its kind");
        std::fs::write(&path, kept).unwrap();
        let m = Manifest::read(&w.p(dir)).unwrap();
        assert_eq!(m.kind, None);
        assert_eq!(m.kind(), want, "{dir}");
    }
}

/// Starts `args`, waits until it holds `dir` (its lock file exists) and `ready` holds, sends
/// `signal`, and returns its exit code and stderr.
fn stop_when(args: &[String], dir: &Path, ready: impl Fn() -> bool, signal: &str) -> (i32, String) {
    let child = kfmc()
        .args(args)
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let start = Instant::now();
    while !(dir.join(".kfmc.lock").exists() && ready())
        && start.elapsed() < Duration::from_secs(120)
    {
        std::thread::sleep(Duration::from_millis(2));
    }
    assert!(
        Command::new("kill")
            .args([signal, &child.id().to_string()])
            .status()
            .unwrap()
            .success()
    );
    wait(child)
}

#[test]
fn an_interrupted_merge_exits_130_and_leaves_the_parts_intact() {
    let tmp = tempfile::tempdir().unwrap();
    // Parts large enough that merging them takes a while (a million trace rows).
    let spec = tmp.path().join("big.toml");
    std::fs::write(
        &spec,
        SPEC.replace("KIND", "ekf")
            .replace("runs = 4", "runs = 40\ntrace_runs = 40")
            .replace("duration_s = 1.0", "duration_s = 60.0"),
    )
    .unwrap();
    let out = tmp.path().join("sharded");
    for i in 0..2 {
        ok(kfmc()
            .args(["run", "-q", "--shard", &format!("{i}/2"), "--out"])
            .arg(&out)
            .arg(&spec));
    }
    let parts: Vec<PathBuf> = ["part-00000-of-00002", "part-00001-of-00002"]
        .iter()
        .map(|p| out.join("parts").join(p))
        .collect();
    let before: Vec<_> = parts.iter().map(|p| snapshot(p)).collect();
    for signal in ["-INT", "-TERM"] {
        let args = vec!["merge".to_string(), out.to_str().unwrap().to_string()];
        // Stopped once it has begun writing a merged table.
        let ready = || {
            std::fs::read_dir(&out).unwrap().any(|e| {
                e.unwrap()
                    .file_name()
                    .to_string_lossy()
                    .ends_with(".parquet.partial")
            })
        };
        let (code, err) = stop_when(&args, &out, ready, signal);
        assert_eq!(code, 130, "{signal}: {err}");
        assert!(err.contains("interrupted"), "{err}");
        assert!(!out.join("manifest.toml").exists(), "{signal}: committed");
        for e in std::fs::read_dir(&out).unwrap() {
            let n = e.unwrap().file_name().to_string_lossy().into_owned();
            assert!(
                !n.ends_with(".partial") && n != ".kfmc.lock" && !n.ends_with(".parquet"),
                "{signal}: {n} left behind"
            );
        }
        for (p, b) in parts.iter().zip(&before) {
            verify(p).unwrap();
            assert!(snapshot(p) == *b, "{signal}: {} changed", p.display());
        }
    }
    // The parts still merge.
    ok(kfmc().arg("merge").arg(&out));
    verify(&out).unwrap();
}

/// The staging folders of tuning searches in `out` (kfmc's temporary names for them).
fn staging(out: &Path) -> Vec<PathBuf> {
    std::fs::read_dir(out)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| {
            let n = p.file_name().unwrap().to_string_lossy();
            n.starts_with(".kfmc-") && n.ends_with(".tune-stages.partial")
        })
        .collect()
}

#[test]
fn an_interrupted_tune_leaves_the_earlier_search_whole() {
    let w = World::new();
    let out = w.p("tuned");
    let tune = |seed: &str| -> Vec<String> {
        [
            "tune",
            "-q",
            "--seed",
            seed,
            "--out",
            out.to_str().unwrap(),
            &w.s("run.toml"),
        ]
        .iter()
        .map(|s| s.to_string())
        .collect()
    };
    let (code, _, err) = output(kfmc().args(tune("1")));
    assert_eq!(code, 0, "{err}");
    check_folder("tune", &out).unwrap();
    let before = snapshot(&out);
    let coarse_before = snapshot(&out.join("tune_coarse"));
    // Stopped once the new search's coarse stage is committed (wherever it is written), so
    // that a stage of the new search exists when the stop arrives.
    let new_coarse = || {
        staging(&out)
            .into_iter()
            .map(|s| s.join("tune_coarse"))
            .chain([out.join("tune_coarse")])
            .any(|d| Manifest::read(&d).is_ok_and(|m| m.master_seed == 2))
    };
    let (code, err) = stop_when(&tune("2"), &out, new_coarse, "-INT");
    assert_eq!(code, 130, "{err}");
    assert!(err.contains("interrupted"), "{err}");
    check_folder("tune", &out).unwrap();
    assert_eq!(verify(&out).unwrap().master_seed, 1);
    assert!(
        snapshot(&out) == before,
        "the earlier search's tables changed"
    );
    assert!(
        snapshot(&out.join("tune_coarse")) == coarse_before,
        "the earlier search's coarse stage changed"
    );
    assert!(staging(&out).is_empty(), "{:?}", staging(&out));
    // Uninterrupted, the new search replaces the old one whole.
    let (code, _, err) = output(kfmc().args(tune("2")));
    assert_eq!(code, 0, "{err}");
    check_folder("tune", &out).unwrap();
    assert_eq!(verify(&out).unwrap().master_seed, 2);
}

#[test]
fn shards_of_another_study_are_refused_and_not_counted() {
    let w = World::new();
    let out = w.p("sharded");
    let o = out.to_str().unwrap();
    for i in 0..3 {
        ok(kfmc().args([
            "run",
            "-q",
            "--shard",
            &format!("{i}/3"),
            "--out",
            o,
            &w.s("run.toml"),
        ]));
    }
    let part1 = out.join("parts/part-00001-of-00003");
    let part1_before = snapshot(&part1);

    // A simulation part over the run's part: refused, the run's part untouched.
    let sim_part = [
        "simulate",
        "-q",
        "--shard",
        "1/3",
        "--out",
        o,
        &w.s("ext.toml"),
    ];
    let (code, _, err) = output(kfmc().args(sim_part));
    assert_eq!(code, 1, "{err}");
    assert!(err.contains("holds the tables of a `kfmc run`"), "{err}");
    assert!(snapshot(&part1) == part1_before);

    // Forced, it is written; then status does not count it and merge refuses it by name.
    let mut forced = sim_part.to_vec();
    forced.insert(2, "--force");
    ok(kfmc().args(&forced));
    let (code, status, err) = output(kfmc().args(["status", o]));
    assert_eq!(code, 0, "{err}");
    assert!(status.contains("2 of 3 parts complete"), "{status}");
    assert!(status.contains("part     1 of 3: missing"), "{status}");
    assert!(
        status.contains("of another study") && status.contains("a `kfmc simulate` part 1 of 3"),
        "{status}"
    );
    let (code, _, err) = output(kfmc().args(["merge", o]));
    assert_eq!(code, 1, "{err}");
    assert!(err.contains("part-00001-of-00003"), "{err}");
    assert!(err.contains("kind is `kfmc simulate`"), "{err}");
    assert!(!err.contains("cannot open"), "{err}");
    ok(kfmc().args([
        "run",
        "-q",
        "--force",
        "--shard",
        "1/3",
        "--out",
        o,
        &w.s("run.toml"),
    ]));

    // A part of a split into 2 beside the three of 3: "3 of 3", the other listed apart.
    ok(kfmc().args(["run", "-q", "--shard", "0/2", "--out", o, &w.s("run.toml")]));
    let (code, status, err) = output(kfmc().args(["status", o]));
    assert_eq!(code, 0, "{err}");
    assert!(status.contains("3 of 3 parts complete"), "{status}");
    assert!(!status.contains("of 2 parts complete"), "{status}");
    assert!(status.contains("part-00000-of-00002"), "{status}");
    let (code, _, err) = output(kfmc().args(["merge", o]));
    assert_eq!(code, 1, "{err}");
    assert!(err.contains("part count"), "{err}");
    std::fs::remove_dir_all(out.join("parts/part-00000-of-00002")).unwrap();

    // A stray file: merge advises --force, and takes it.
    std::fs::write(out.join("notes.txt"), "mine").unwrap();
    let (code, _, err) = output(kfmc().args(["merge", o]));
    assert_eq!(code, 1, "{err}");
    assert!(err.contains("--force"), "{err}");
    ok(kfmc().args(["merge", "--force", o]));
    let m = verify(&out).unwrap();
    assert_eq!(m.kind(), StudyKind::Run);
    assert_eq!(
        std::fs::read_to_string(out.join("notes.txt")).unwrap(),
        "mine"
    );
}
