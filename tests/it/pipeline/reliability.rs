//! Faults a CI pipeline or a shared cluster produces: two writers in one folder, kills at any
//! moment, Ctrl-C, corrupt or missing tables and manifests, foreign folders, absurd plans, a
//! closed stdout pipe. After each, the folder holds either a complete study or one the readers
//! refuse by name — never a mix that looks complete.

use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use crate::common::{kfmc, repo};

fn output(cmd: &mut Command) -> (i32, String, String) {
    let o = cmd.output().expect("kfmc runs");
    (
        o.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&o.stdout).into_owned(),
        String::from_utf8_lossy(&o.stderr).into_owned(),
    )
}

/// A study that takes a second or two on the CI machine.
fn slow_run(out: &Path, seed: u64) -> Command {
    let mut c = kfmc();
    c.args([
        "run",
        repo()
            .join("experiments/planar_robustness.toml")
            .to_str()
            .unwrap(),
        "--runs",
        "6",
        "--quiet",
        "--threads",
        "2",
        "--seed",
        &seed.to_string(),
        "--out",
        out.to_str().unwrap(),
    ]);
    c
}

fn quick_run(out: &Path, seed: u64) -> Command {
    let mut c = kfmc();
    c.args([
        "run",
        repo()
            .join("experiments/planar_seed_study.toml")
            .to_str()
            .unwrap(),
        "--runs",
        "3",
        "--quiet",
        "--seed",
        &seed.to_string(),
        "--out",
        out.to_str().unwrap(),
    ]);
    c
}

/// The master seed the manifest records, and whether every reader accepts the folder and
/// its runs table agrees with the manifest (the `seed` column is derived from the master
/// seed, so a table of another study would disagree).
fn readers_accept(dir: &Path) -> Option<u64> {
    match check_readers(dir) {
        Ok(seed) => Some(seed),
        Err(why) => {
            eprintln!("refused: {why}");
            None
        }
    }
}

fn check_readers(dir: &Path) -> Result<u64, String> {
    let (code, _, err) = output(kfmc().args(["summary", dir.to_str().unwrap()]));
    if code != 0 {
        return Err(format!("summary: {err}"));
    }
    let m = kfmc::output::folder::verify(dir).map_err(|e| e.to_string())?;
    let runs = kfmc::output::table::read(&dir.join("runs.parquet")).map_err(|e| e.to_string())?;
    let col = |n: &str| runs.column(n).map_err(|e| e.to_string());
    let seed = col("seed")?
        .u64()
        .map_err(|e| e.to_string())?
        .get(0)
        .ok_or("no rows")?;
    let scenario = col("scenario")?
        .str()
        .map_err(|e| e.to_string())?
        .get(0)
        .ok_or("no rows")?
        .to_string();
    let run = col("run")?
        .i64()
        .map_err(|e| e.to_string())?
        .get(0)
        .ok_or("no rows")? as u64;
    assert_eq!(
        seed,
        kfmc::sim::seed::run_seed(m.master_seed, &scenario, run),
        "runs.parquet belongs to another study than manifest.toml"
    );
    Ok(m.master_seed)
}

fn wait_with_timeout(child: &mut Child, limit: Duration) -> Option<i32> {
    let start = Instant::now();
    loop {
        if let Some(status) = child.try_wait().unwrap() {
            return status.code();
        }
        if start.elapsed() > limit {
            let _ = child.kill();
            return None;
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

#[test]
fn a_second_writer_is_refused_while_the_first_completes() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("d");
    let mut a = slow_run(&out, 11).spawn().unwrap();
    // Wait until A holds the lock.
    let lock = out.join(".kfmc.lock");
    let start = Instant::now();
    while !lock.exists() && start.elapsed() < Duration::from_secs(30) {
        std::thread::sleep(Duration::from_millis(10));
    }
    let (code, _, err) = output(&mut slow_run(&out, 12));
    assert_eq!(code, 1, "{err}");
    assert!(err.contains("being written by another kfmc"), "{err}");
    assert_eq!(wait_with_timeout(&mut a, Duration::from_secs(300)), Some(0));
    assert_eq!(readers_accept(&out), Some(11));
    assert!(!lock.exists(), "the lock is released");
}

#[test]
fn sigkill_at_twenty_moments_leaves_the_old_study_or_the_new_one() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("d");
    assert_eq!(output(&mut quick_run(&out, 1)).0, 0);
    assert_eq!(readers_accept(&out), Some(1));
    // Time one uninterrupted run, then kill replacement runs at spread-out moments of it.
    let t = Instant::now();
    assert_eq!(output(&mut slow_run(&out, 2)).0, 0);
    let full = t.elapsed();
    assert_eq!(readers_accept(&out), Some(2));
    let (mut old_kept, mut new_done, mut refused) = (0, 0, 0);
    let mut current = 2;
    for i in 0..20u64 {
        let seed = 100 + i;
        let mut child = slow_run(&out, seed).spawn().unwrap();
        // Moments from 2 % to 120 % of a full run (the last few let it finish).
        let at = full.mul_f64(0.02 + 1.18 * i as f64 / 19.0);
        std::thread::sleep(at);
        let _ = child.kill();
        let _ = child.wait();
        match readers_accept(&out) {
            Some(s) if s == current => old_kept += 1,
            Some(s) if s == seed => {
                new_done += 1;
                current = seed;
            }
            Some(s) => panic!("moment {i}: a study of seed {s} appeared"),
            None => {
                // Killed inside the commit's renames: the manifest is the one in the middle of
                // the commit, so every reader refuses.
                refused += 1;
                let (code, _, err) = output(kfmc().args(["summary", out.to_str().unwrap()]));
                assert_eq!(code, 1, "moment {i}: {err}");
                assert!(err.contains("committed a study here"), "moment {i}: {err}");
            }
        }
    }
    eprintln!(
        "20 SIGKILLs: old study intact {old_kept}, new study complete {new_done}, refused (killed mid-commit) {refused}"
    );
    assert_eq!(old_kept + new_done + refused, 20);
    // The next run takes the stale lock over and removes the orphaned partial files.
    assert_eq!(output(&mut quick_run(&out, 7)).0, 0);
    assert_eq!(readers_accept(&out), Some(7));
    let partial = std::fs::read_dir(&out)
        .unwrap()
        .filter(|e| {
            let n = e.as_ref().unwrap().file_name();
            n.to_string_lossy().ends_with(".partial")
        })
        .count();
    assert_eq!(partial, 0);
}

#[test]
fn sigint_stops_cleanly_and_keeps_the_old_study() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("d");
    assert_eq!(output(&mut quick_run(&out, 3)).0, 0);
    let child = slow_run(&out, 4).stderr(Stdio::piped()).spawn().unwrap();
    std::thread::sleep(Duration::from_millis(300));
    let pid = child.id().to_string();
    assert!(
        Command::new("kill")
            .args(["-INT", &pid])
            .status()
            .unwrap()
            .success()
    );
    let o = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    if o.status.code() == Some(0) {
        // The run finished before the signal arrived (a very fast machine): still complete.
        assert_eq!(readers_accept(&out), Some(4));
        return;
    }
    assert_eq!(o.status.code(), Some(130), "{err}");
    assert!(err.contains("interrupted"), "{err}");
    assert_eq!(readers_accept(&out), Some(3));
    for e in std::fs::read_dir(&out).unwrap() {
        let n = e.unwrap().file_name().to_string_lossy().into_owned();
        assert!(
            !n.ends_with(".partial") && n != ".kfmc.lock",
            "{n} left behind"
        );
    }
}

#[test]
fn readers_refuse_corrupt_missing_and_foreign_tables_naming_the_file() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("d");
    assert_eq!(output(&mut quick_run(&out, 5)).0, 0);
    let dir = out.to_str().unwrap();
    let readers: [&[&str]; 3] = [&["summary", dir], &["plot", dir], &["report", dir]];
    let refused = |needle: &str| {
        for args in readers {
            let (code, _, err) = output(kfmc().args(args));
            assert_eq!(code, 1, "{args:?}: {err}");
            assert!(
                err.contains(needle),
                "{args:?}: missing `{needle}` in {err}"
            );
        }
    };
    // A corrupted table.
    let runs = out.join("runs.parquet");
    let good = std::fs::read(&runs).unwrap();
    let mut bad = good.clone();
    let mid = bad.len() / 2;
    bad[mid] ^= 0xff;
    std::fs::write(&runs, &bad).unwrap();
    refused("runs.parquet does not match manifest.toml");
    // A missing table.
    std::fs::remove_file(&runs).unwrap();
    refused("runs.parquet listed in manifest.toml but missing");
    std::fs::write(&runs, &good).unwrap();
    // A table no manifest lists (left by another study).
    std::fs::write(out.join("divergence.parquet"), &good).unwrap();
    refused("divergence.parquet present but not listed");
    std::fs::remove_file(out.join("divergence.parquet")).unwrap();
    // A garbage manifest, then none.
    let manifest = out.join("manifest.toml");
    std::fs::write(&manifest, "this is = not [a manifest").unwrap();
    refused("manifest.toml");
    std::fs::remove_file(&manifest).unwrap();
    refused("no manifest.toml");
}

#[test]
fn a_foreign_folder_is_refused_unless_forced_and_dot_dot_names_are_rejected() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("d");
    std::fs::create_dir_all(&out).unwrap();
    std::fs::write(out.join("notes.txt"), "mine").unwrap();
    let (code, _, err) = output(&mut quick_run(&out, 1));
    assert_eq!(code, 1);
    assert!(
        err.contains("is not a kfmc result folder") && err.contains("--force"),
        "{err}"
    );
    // A file with a table's name that no manifest lists is the user's: refused by name,
    // forced or not, and never written over.
    std::fs::write(out.join("traces.parquet"), "not kfmc's").unwrap();
    for force in [false, true] {
        let mut c = quick_run(&out, 1);
        if force {
            c.arg("--force");
        }
        let (code, _, err) = output(&mut c);
        assert_eq!(code, 1, "{err}");
        assert!(
            err.contains("traces.parquet has the name of a kfmc table")
                && err.contains("even with --force"),
            "{err}"
        );
        assert_eq!(
            std::fs::read_to_string(out.join("traces.parquet")).unwrap(),
            "not kfmc's",
            "nothing was touched"
        );
    }
    std::fs::remove_file(out.join("traces.parquet")).unwrap();
    let (code, _, err) = output(quick_run(&out, 1).arg("--force"));
    assert_eq!(code, 0, "{err}");
    assert_eq!(
        std::fs::read_to_string(out.join("notes.txt")).unwrap(),
        "mine"
    );

    let spec = tmp.path().join("dots.toml");
    std::fs::write(
        &spec,
        "name = \"..\"\n[model]\nkind = \"planar_quadrotor\"\n[[scenarios]]\nname = \"basic\"\n[[filters]]\nlabel = \"e\"\nkind = \"ekf\"\n",
    )
    .unwrap();
    let (code, _, err) = output(kfmc().args(["validate", spec.to_str().unwrap()]));
    assert_eq!(code, 2);
    assert!(
        err.contains("name: must be non-empty, not `.` or `..`"),
        "{err}"
    );
}

#[test]
fn absurd_plans_are_refused_before_anything_runs() {
    let tmp = tempfile::tempdir().unwrap();
    let spec = |extra: &str, scenario: &str| {
        let p = tmp.path().join("s.toml");
        std::fs::write(
            &p,
            format!("{extra}\n[model]\nkind = \"planar_quadrotor\"\n[[scenarios]]\nname = \"basic\"\n{scenario}\n[[filters]]\nlabel = \"e\"\nkind = \"ekf\"\n"),
        )
        .unwrap();
        p
    };
    let cases: [(&str, &str, &[&str]); 4] = [
        (
            "runs = 9223372036854775807",
            "",
            &["runs:", "at most 1000000000"],
        ),
        (
            "",
            "duration_s = 1e9",
            &["scenarios[0].duration_s", "at most 10000000"],
        ),
        // Runs no longer cost memory (per-run values spill to scratch files, the consistency
        // tests fold their sums), but steps per run do: every unit in flight holds them.
        (
            "runs = 100",
            "duration_s = 100000.0",
            &["(plan)", "memory", "--allow-large"],
        ),
        (
            "[noise]\nscales = { start = 0.0, stop = 1e9, step = 1.0 }",
            "",
            &["noise.scales", "more than 100000"],
        ),
    ];
    for (extra, scenario, needles) in cases {
        let p = spec(extra, scenario);
        for cmd in ["validate", "run"] {
            let start = Instant::now();
            let (code, _, err) = output(kfmc().args([cmd, p.to_str().unwrap()]));
            assert_eq!(code, 2, "{cmd} {extra} {scenario}: {err}");
            assert!(
                !err.contains("panicked") && !err.contains("memory allocation"),
                "{err}"
            );
            for n in needles {
                assert!(err.contains(n), "missing `{n}` in {err}");
            }
            assert!(start.elapsed() < Duration::from_secs(20), "refused at once");
        }
    }
    // A device is no spec file; a regular file past the cap is read no further than it.
    let (code, _, err) = output(kfmc().args(["validate", "/dev/zero"]));
    assert_eq!(code, 2);
    assert!(err.contains("it is a device, not a regular file"), "{err}");
    let huge = tmp.path().join("huge.toml");
    std::fs::File::create(&huge)
        .unwrap()
        .set_len(2 << 20)
        .unwrap();
    let (code, _, err) = output(kfmc().arg("validate").arg(&huge));
    assert_eq!(code, 2);
    assert!(err.contains("larger than 1048576 bytes"), "{err}");
    let (code, _, err) = output(&mut {
        let mut c = quick_run(&tmp.path().join("t"), 1);
        c.args(["--threads", "100000"]);
        c
    });
    assert_eq!(code, 0, "{err}");
}

#[test]
fn a_closed_stdout_pipe_is_not_a_panic() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("d");
    assert_eq!(output(&mut quick_run(&out, 1)).0, 0);
    for args in [vec!["summary", out.to_str().unwrap()], vec!["list"]] {
        let mut child = kfmc()
            .args(&args)
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        // Read one byte and hang up, as `| head -c1` does.
        use std::io::Read;
        let mut one = [0u8; 1];
        child.stdout.take().unwrap().read_exact(&mut one).unwrap();
        let o = child.wait_with_output().unwrap();
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!err.contains("panicked"), "{args:?}: {err}");
        assert_eq!(o.status.code(), Some(0), "{args:?}: {err}");
    }
}

/// A spec with one outside filter, small enough to simulate at once.
const EXTERNAL_SPEC: &str = r#"
name = "inputs"
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
[consistency]
alpha = 0.05
[[check.assert]]
kind = "consistent"
filter = "ext"
"#;

/// Runs kfmc with `args` for at most 20 s: (exit code, stderr), or a failure naming the hang.
fn limited(args: &[&str]) -> (i32, String) {
    let mut child = kfmc()
        .args(args)
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let code = wait_with_timeout(&mut child, Duration::from_secs(20));
    let mut err = String::new();
    std::io::Read::read_to_string(&mut child.stderr.take().unwrap(), &mut err).unwrap();
    (
        code.unwrap_or_else(|| panic!("kfmc {args:?} hangs: {err}")),
        err,
    )
}

/// A FIFO (which blocks whoever opens it until a writer comes), a device or a folder given
/// where kfmc reads a file is refused before it is opened, naming it: a spec, estimates, a
/// study's table.
#[test]
fn inputs_that_are_not_regular_files_are_refused_at_once() {
    let tmp = tempfile::tempdir().unwrap();
    let fifo = tmp.path().join("fifo.parquet");
    assert!(
        Command::new("mkfifo")
            .arg(&fifo)
            .status()
            .unwrap()
            .success()
    );
    let f = fifo.to_str().unwrap();
    let spec = tmp.path().join("s.toml");
    std::fs::write(&spec, EXTERNAL_SPEC).unwrap();
    let s = spec.to_str().unwrap();
    let sim = tmp.path().join("sim");
    let (code, err) = limited(&["simulate", s, "-q", "--out", sim.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    let sim = sim.to_str().unwrap();
    let out = tmp.path().join("out");
    let o = out.to_str().unwrap();
    let folder = tmp.path().to_str().unwrap();
    for (args, code, named, what) in [
        (vec!["validate", f], 2, f, "a FIFO"),
        (
            vec!["score", sim, "--estimates", f, "--out", o],
            1,
            f,
            "a FIFO",
        ),
        (
            vec!["check", s, "--estimates", f, "--out", o],
            1,
            f,
            "a FIFO",
        ),
        (
            vec!["score", sim, "--estimates", "/dev/zero", "--out", o],
            1,
            "/dev/zero",
            "a device",
        ),
        (
            vec!["score", sim, "--estimates", folder, "--out", o],
            1,
            folder,
            "a folder",
        ),
    ] {
        let (got, err) = limited(&args);
        assert_eq!(got, code, "{args:?}: {err}");
        assert!(
            err.contains(named)
                && err.contains(&format!("it is {what}"))
                && err.contains("not a regular file"),
            "{args:?}: {err}"
        );
    }
    assert!(!out.exists(), "nothing was written");
    // A study's table replaced by a FIFO.
    let study = tmp.path().join("study");
    assert_eq!(output(&mut quick_run(&study, 3)).0, 0);
    let summary = study.join("summary.parquet");
    std::fs::remove_file(&summary).unwrap();
    assert!(
        Command::new("mkfifo")
            .arg(&summary)
            .status()
            .unwrap()
            .success()
    );
    let (code, err) = limited(&["summary", study.to_str().unwrap()]);
    assert_eq!(code, 1, "{err}");
    assert!(
        err.contains("summary.parquet") && err.contains("is a FIFO (named pipe)"),
        "{err}"
    );
}

/// Outside a study (here: designing a sequential gate of 100 looks with futility bounds,
/// which takes many seconds) the first SIGTERM or SIGINT ends kfmc at once, exit 130, with a
/// word on stderr: no wait is deaf to it.
#[test]
fn the_first_signal_ends_a_long_wait_outside_a_study_at_once() {
    let tmp = tempfile::tempdir().unwrap();
    let spec = tmp.path().join("s.toml");
    std::fs::write(
        &spec,
        EXTERNAL_SPEC.replace("runs = 3", "runs = 1000").replace(
            "label = \"ext\"\nkind = \"external\"",
            "label = \"ext\"\nkind = \"ekf\"",
        ),
    )
    .unwrap();
    for signal in ["-TERM", "-INT"] {
        let out = tmp.path().join(format!("o{signal}"));
        let mut child = kfmc()
            .args(["check", spec.to_str().unwrap(), "-q", "--out"])
            .arg(&out)
            .args(["--sequential", "--looks", "100", "--futility", "0.2"])
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        std::thread::sleep(Duration::from_millis(1000));
        assert!(
            child.try_wait().unwrap().is_none(),
            "the design ended within a second"
        );
        let sent = Instant::now();
        assert!(
            Command::new("kill")
                .args([signal, &child.id().to_string()])
                .status()
                .unwrap()
                .success()
        );
        let code = wait_with_timeout(&mut child, Duration::from_secs(5));
        let mut err = String::new();
        std::io::Read::read_to_string(&mut child.stderr.take().unwrap(), &mut err).unwrap();
        assert_eq!(
            code,
            Some(130),
            "{signal}: {err} after {:?}",
            sent.elapsed()
        );
        assert!(err.contains("interrupted"), "{err}");
        assert!(!out.exists(), "nothing was written");
    }
}
