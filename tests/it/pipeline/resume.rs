//! Resuming an interrupted `kfmc run` from its checkpoint: killed (SIGKILL) or interrupted
//! (SIGINT) at several moments, the resumed study's tables are byte-identical to an
//! uninterrupted run's, whatever the thread count; only the cells after the checkpoint are
//! recomputed; a checkpoint of a changed study, or a damaged one, is refused with a message
//! that says what to do.

use std::path::{Path, PathBuf};
use std::process::{Child, Command};
use std::time::{Duration, Instant};

use crate::common::kfmc;
use crate::common::run_cli as run;
use crate::common::table_bytes as tables;

/// Six cells (two scenarios × three noise scales) with every journaled table: runs, steps,
/// summary, traces and consistency, and divergence points rebuilt across the cells.
fn spec_text() -> String {
    crate::common::six_cell_planar("resumable", 150)
}

const CELLS: u64 = 6;

/// Cells the checkpoint in `out` vouches for (0 without one).
fn checkpointed(out: &Path) -> u64 {
    let Ok(text) = std::fs::read_to_string(out.join(".checkpoint/index.toml")) else {
        return 0;
    };
    let index: toml::Table = text.parse().unwrap();
    index["cells_done"].as_integer().unwrap() as u64
}

struct Study {
    _tmp: tempfile::TempDir,
    spec: PathBuf,
    root: PathBuf,
}

impl Study {
    fn new() -> Self {
        let tmp = tempfile::tempdir().unwrap();
        let spec = tmp.path().join("s.toml");
        std::fs::write(&spec, spec_text()).unwrap();
        let root = tmp.path().to_path_buf();
        Study {
            _tmp: tmp,
            spec,
            root,
        }
    }

    fn spec(&self) -> &str {
        self.spec.to_str().unwrap()
    }

    fn out(&self, name: &str) -> PathBuf {
        self.root.join(name)
    }

    /// A run on one thread that checkpoints after every cell, in the background.
    fn start(&self, out: &Path, extra: &[&str]) -> Child {
        kfmc()
            .args([
                "run",
                self.spec(),
                "-q",
                "--threads",
                "1",
                "--checkpoint-every",
                "0",
            ])
            .args(extra)
            .arg("--out")
            .arg(out)
            .spawn()
            .unwrap()
    }
}

/// SIGKILLs `child` once the checkpoint in `out` holds at least `cells` cells (or the run
/// ended).
fn kill_after_checkpoint(child: &mut Child, out: &Path, cells: u64) {
    let deadline = Instant::now() + Duration::from_secs(120);
    while checkpointed(out) < cells && child.try_wait().unwrap().is_none() {
        assert!(Instant::now() < deadline, "no checkpoint of {cells} cells");
        std::thread::sleep(Duration::from_millis(5));
    }
    let _ = child.kill();
    let _ = child.wait();
}

fn signal(child: &Child, name: &str) {
    let ok = Command::new("kill")
        .args([format!("-{name}"), child.id().to_string()])
        .status()
        .unwrap()
        .success();
    assert!(ok, "kill -{name}");
}

#[test]
fn a_study_killed_at_several_moments_resumes_to_the_uninterrupted_tables() {
    let s = Study::new();
    let single = s.out("single");
    let (code, _, err) = run(&["run", s.spec(), "-q", "--out", single.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    let want = tables(&single);
    assert_eq!(
        want.len(),
        7,
        "runs, steps, summary, traces, consistency, divergence ×2"
    );
    assert!(
        !single.join(".checkpoint").exists(),
        "a committed study keeps no checkpoint"
    );

    let mut resumed_somewhere = false;
    // SIGKILL right away (before any checkpoint) and after 1, 3 and 5 checkpointed cells.
    for at in [0u64, 1, 3, 5] {
        let out = s.out(&format!("killed{at}"));
        let mut child = s.start(&out, &[]);
        kill_after_checkpoint(&mut child, &out, at);
        let kept = checkpointed(&out);
        // Resumed on two threads: the thread count changes nothing.
        let (code, stdout, err) = run(&[
            "run",
            s.spec(),
            "--resume",
            "--threads",
            "2",
            "--out",
            out.to_str().unwrap(),
        ]);
        assert_eq!(code, 0, "{err}");
        let runs_now: u64 = stdout
            .lines()
            .find_map(|l| {
                l.split_once(" runs in ")
                    .map(|(n, _)| n.trim().parse().unwrap())
            })
            .unwrap_or_else(|| panic!("no run count in {stdout}"));
        if kept > 0 && kept < CELLS {
            resumed_somewhere = true;
            assert!(
                stdout.contains(&format!("{kept} cells continued from the checkpoint")),
                "{stdout}"
            );
        }
        // Only the cells after the checkpoint are recomputed.
        assert_eq!(runs_now, (CELLS - kept) * 150, "{stdout}");
        eprintln!(
            "SIGKILL after {at}+ checkpointed cells: {kept} kept, {runs_now} runs recomputed"
        );
        assert_eq!(
            tables(&out),
            want,
            "resumed after SIGKILL with {kept} cells kept"
        );
        assert!(!out.join(".checkpoint").exists());
    }
    assert!(
        resumed_somewhere,
        "no kill landed between the first and the last cell"
    );

    // A resume killed in its turn: the next resume continues from the later checkpoint.
    let out = s.out("twice");
    let mut child = s.start(&out, &[]);
    kill_after_checkpoint(&mut child, &out, 1);
    let first = checkpointed(&out);
    let mut child = s.start(&out, &["--resume"]);
    kill_after_checkpoint(&mut child, &out, first + 2);
    eprintln!(
        "killed twice: {first} cells kept, then {} after the killed resume",
        checkpointed(&out)
    );
    let (code, _, err) = run(&[
        "run",
        s.spec(),
        "-q",
        "--resume",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{err}");
    assert_eq!(tables(&out), want, "resumed after two kills");
}

#[test]
fn sigint_checkpoints_the_complete_cells_and_the_resume_is_identical() {
    let s = Study::new();
    let single = s.out("single");
    let started = Instant::now();
    let mut child = kfmc()
        .args([
            "run",
            s.spec(),
            "-q",
            "--threads",
            "1",
            "--no-checkpoint",
            "--out",
        ])
        .arg(&single)
        .spawn()
        .unwrap();
    assert!(child.wait().unwrap().success());
    let whole = started.elapsed();
    let want = tables(&single);

    // Without time-based checkpoints (one hour apart) the checkpoint SIGINT writes is all a
    // resume has. The signal must land between the first and the last cell: try a few
    // moments of the uninterrupted run's duration.
    let mut landed = false;
    for (k, fraction) in [0.5, 0.35, 0.7, 0.2, 0.85].into_iter().enumerate() {
        let out = s.out(&format!("interrupted{k}"));
        let mut child = kfmc()
            .args([
                "run",
                s.spec(),
                "-q",
                "--threads",
                "1",
                "--checkpoint-every",
                "3600",
                "--out",
            ])
            .arg(&out)
            .stderr(std::process::Stdio::piped())
            .spawn()
            .unwrap();
        std::thread::sleep(whole.mul_f64(fraction));
        signal(&child, "INT");
        let status = child.wait().unwrap();
        let mut err = String::new();
        std::io::Read::read_to_string(child.stderr.as_mut().unwrap(), &mut err).unwrap();
        let kept = checkpointed(&out);
        match status.code() {
            Some(130) if kept > 0 => {
                landed = true;
                assert!(
                    err.contains(&format!("keeps {kept} of 6 cells"))
                        && err.contains("kfmc run SPEC --resume"),
                    "{err}"
                );
                assert!(!out.join("runs.parquet").exists(), "nothing committed");
            }
            // Before the first cell was complete: nothing to keep.
            Some(130) => assert!(err.contains("interrupted"), "{err}"),
            // Killed by the signal's default action, before kfmc installed its handler.
            None => {}
            // After the last: the study committed.
            code => assert_eq!(code, Some(0), "{err}"),
        }
        let (code, _, err) = run(&[
            "run",
            s.spec(),
            "-q",
            "--resume",
            "--out",
            out.to_str().unwrap(),
        ]);
        assert_eq!(code, 0, "{err}");
        assert_eq!(
            tables(&out),
            want,
            "resumed after SIGINT with {kept} cells kept"
        );
        if landed {
            break;
        }
    }
    assert!(
        landed,
        "no SIGINT landed between the first and the last cell"
    );
}

#[test]
fn a_checkpoint_is_neither_overwritten_silently_nor_continued_for_another_study() {
    let s = Study::new();
    let out = s.out("o");
    let o = out.to_str().unwrap();
    let mut child = s.start(&out, &[]);
    kill_after_checkpoint(&mut child, &out, 2);
    let kept = checkpointed(&out);
    assert!((2..CELLS).contains(&kept), "the run ended before the kill");
    let (code, stdout, err) = run(&["status", o]);
    assert_eq!(code, 0, "{err}");
    assert!(
        stdout.contains(&format!(
            "an interrupted run, {kept} of 6 cells checkpointed"
        )),
        "{stdout}"
    );

    // A plain run would throw the checkpoint away: refused, saying how to go on.
    let (code, _, err) = run(&["run", s.spec(), "-q", "--out", o]);
    assert_eq!(code, 1, "{err}");
    assert!(
        err.contains("checkpoint of an interrupted run of this study")
            && err.contains("--resume")
            && err.contains("--restart"),
        "{err}"
    );
    // A resume with another run count, seed or spec is refused, naming what changed.
    for (args, why) in [
        (
            vec!["--runs", "151"],
            "the runs per cell changed (150 → 151)",
        ),
        (vec!["--seed", "10"], "the master seed changed (9 → 10)"),
        (vec!["--trace-runs", "2"], "--trace-runs changed (1 → 2)"),
    ] {
        let mut a = vec!["run", s.spec(), "-q", "--resume", "--out", o];
        a.extend(args);
        let (code, _, err) = run(&a);
        assert_eq!(code, 1, "{err}");
        assert!(err.contains(why), "{err}");
    }
    let edited = s.root.join("edited.toml");
    std::fs::write(
        &edited,
        spec_text().replace("master_seed = 9", "master_seed = 9 # edited"),
    )
    .unwrap();
    let (code, _, err) = run(&[
        "run",
        edited.to_str().unwrap(),
        "-q",
        "--resume",
        "--out",
        o,
    ]);
    assert_eq!(code, 1, "{err}");
    assert!(
        err.contains("the spec changed since the checkpoint"),
        "{err}"
    );
    assert_eq!(
        checkpointed(&out),
        kept,
        "a refused resume keeps the checkpoint"
    );

    // A journal that lost bytes the index vouches for is damaged: refused.
    let damaged = s.out("damaged");
    copy_dir(&out, &damaged);
    let journal = damaged.join(".checkpoint/runs.journal");
    let len = std::fs::metadata(&journal).unwrap().len();
    std::fs::OpenOptions::new()
        .write(true)
        .open(&journal)
        .unwrap()
        .set_len(len / 2)
        .unwrap();
    let (code, _, err) = run(&[
        "run",
        s.spec(),
        "-q",
        "--resume",
        "--out",
        damaged.to_str().unwrap(),
    ]);
    assert_eq!(code, 1, "{err}");
    assert!(
        err.contains("damaged checkpoint journal") && err.contains("--restart"),
        "{err}"
    );

    // --restart discards it; the result is the uninterrupted study's.
    let single = s.out("single");
    assert_eq!(
        run(&["run", s.spec(), "-q", "--out", single.to_str().unwrap()]).0,
        0
    );
    let (code, stdout, err) = run(&["run", s.spec(), "--restart", "--out", o]);
    assert_eq!(code, 0, "{err}");
    assert!(
        !stdout.contains("continued from the checkpoint"),
        "{stdout}"
    );
    assert_eq!(tables(&out), tables(&single));
    // --no-checkpoint writes none.
    let plain = s.out("plain");
    let mut child = kfmc()
        .args([
            "run",
            s.spec(),
            "-q",
            "--threads",
            "1",
            "--no-checkpoint",
            "--out",
        ])
        .arg(&plain)
        .spawn()
        .unwrap();
    assert!(child.wait().unwrap().success());
    assert!(!plain.join(".checkpoint").exists());
    assert_eq!(tables(&plain), tables(&single));
}

#[test]
fn a_killed_shard_resumes_to_the_part_it_would_have_written() {
    let s = Study::new();
    let whole = s.out("whole");
    for i in 0..2 {
        let shard = format!("{i}/2");
        assert_eq!(
            run(&[
                "run",
                s.spec(),
                "-q",
                "--shard",
                &shard,
                "--out",
                whole.to_str().unwrap()
            ])
            .0,
            0
        );
    }
    let part = |root: &Path| root.join("parts/part-00001-of-00002");
    let out = s.out("killed");
    let mut child = s.start(&out, &["--shard", "1/2"]);
    kill_after_checkpoint(&mut child, &part(&out), 1);
    let kept = checkpointed(&part(&out));
    let (_, stdout, _) = run(&["status", out.to_str().unwrap()]);
    if kept > 0 {
        assert!(
            stdout.contains("running or interrupted")
                && stdout.contains(&format!("{kept} of 3 cells checkpointed")),
            "{stdout}"
        );
    }
    let (code, _, err) = run(&[
        "run",
        s.spec(),
        "-q",
        "--shard",
        "1/2",
        "--resume",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{err}");
    assert_eq!(tables(&part(&out)), tables(&part(&whole)));
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        let target = to.join(e.file_name());
        if e.file_type().unwrap().is_dir() {
            copy_dir(&e.path(), &target);
        } else {
            std::fs::copy(e.path(), target).unwrap();
        }
    }
}

/// The `[[tables]]` entries of the checkpoint index in `out`: (name, bytes).
fn journaled(out: &Path) -> Vec<(String, u64)> {
    let text = std::fs::read_to_string(out.join(".checkpoint/index.toml")).unwrap();
    let index: toml::Table = text.parse().unwrap();
    index["tables"]
        .as_array()
        .unwrap()
        .iter()
        .map(|t| {
            (
                t["name"].as_str().unwrap().to_string(),
                t["bytes"].as_integer().unwrap() as u64,
            )
        })
        .collect()
}

/// Resumes the study in `out`; it must be refused (exit 1) with the advice to restart, and
/// commit nothing.
fn assert_resume_refused(s: &Study, out: &Path, what: &str) {
    let (code, _, err) = run(&[
        "run",
        s.spec(),
        "-q",
        "--resume",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert_eq!(code, 1, "{what}: {err}");
    assert!(
        err.contains("damaged checkpoint") && err.contains("--restart"),
        "{what}: {err}"
    );
    assert!(
        !out.join("manifest.toml").exists() && tables(out).is_empty(),
        "{what}: something was committed"
    );
}

/// One flipped bit in any journal, or an index whose `cells_done` was edited up, down or
/// out of range, is refused with the advice to restart and nothing committed: a resume
/// never builds tables from rows or cells its checkpoint does not vouch for.
#[test]
fn a_flipped_bit_or_an_edited_index_is_refused_and_nothing_is_committed() {
    let s = Study::new();
    let out = s.out("o");
    let mut child = s.start(&out, &[]);
    kill_after_checkpoint(&mut child, &out, 3);
    let kept = checkpointed(&out);
    assert!((3..CELLS).contains(&kept), "the run ended before the kill");
    let journals = journaled(&out);
    assert_eq!(journals.len(), 5, "{journals:?}");

    for (name, bytes) in &journals {
        for (k, at) in [bytes / 4, bytes / 2, 3 * bytes / 4]
            .into_iter()
            .enumerate()
        {
            let copy = s.out(&format!("flip-{name}-{k}"));
            copy_dir(&out, &copy);
            let path = copy.join(format!(".checkpoint/{name}.journal"));
            let mut b = std::fs::read(&path).unwrap();
            b[at as usize] ^= 0x10;
            std::fs::write(&path, b).unwrap();
            assert_resume_refused(&s, &copy, &format!("bit 4 of byte {at} of {name}.journal"));
        }
    }

    let index_text = std::fs::read_to_string(out.join(".checkpoint/index.toml")).unwrap();
    let line = format!("cells_done = {kept}\n");
    assert!(index_text.contains(&line), "{index_text}");
    for edited in [kept - 1, kept + 1, CELLS, 100, i64::MAX as u64] {
        let copy = s.out(&format!("cells-{edited}"));
        copy_dir(&out, &copy);
        std::fs::write(
            copy.join(".checkpoint/index.toml"),
            index_text.replace(&line, &format!("cells_done = {edited}\n")),
        )
        .unwrap();
        assert_resume_refused(&s, &copy, &format!("cells_done = {edited}"));
    }

    // The untouched checkpoint still resumes to the uninterrupted tables.
    let single = s.out("single");
    assert_eq!(
        run(&["run", s.spec(), "-q", "--out", single.to_str().unwrap()]).0,
        0
    );
    let (code, _, err) = run(&[
        "run",
        s.spec(),
        "-q",
        "--resume",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{err}");
    assert_eq!(tables(&out), tables(&single));
}

/// A checkpoint of the earlier journal format (bare rows, no checksums) is refused with the
/// advice to restart, not misread.
#[test]
fn a_checkpoint_of_the_earlier_format_is_refused_with_the_restart_advice() {
    let s = Study::new();
    let out = s.out("o");
    let mut child = s.start(&out, &[]);
    kill_after_checkpoint(&mut child, &out, 2);
    let path = out.join(".checkpoint/index.toml");
    let text = std::fs::read_to_string(&path).unwrap();
    assert!(text.contains("journal_format = 3"), "{text}");
    std::fs::write(
        &path,
        text.replace("journal_format = 3", "journal_format = 1"),
    )
    .unwrap();
    let (code, _, err) = run(&[
        "run",
        s.spec(),
        "-q",
        "--resume",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert_eq!(code, 1, "{err}");
    assert!(
        err.contains("format 1") && err.contains("--restart"),
        "{err}"
    );
    assert!(!out.join("manifest.toml").exists());
}

/// An index that is empty or not a checkpoint index vouches for nothing: `--resume` is
/// refused advising `--restart`, and `--restart` and a plain run start over to the
/// uninterrupted tables, leaving no checkpoint.
#[test]
fn an_empty_or_garbage_index_is_started_over_by_restart_and_a_plain_run() {
    let s = Study::new();
    let out = s.out("o");
    let mut child = s.start(&out, &[]);
    kill_after_checkpoint(&mut child, &out, 1);
    assert!(checkpointed(&out) >= 1, "the run ended before the kill");
    let single = s.out("single");
    assert_eq!(
        run(&["run", s.spec(), "-q", "--out", single.to_str().unwrap()]).0,
        0
    );
    for (k, garbage) in ["", "\u{0}\u{1} not toml [[[", "cells_done = 3\n"]
        .into_iter()
        .enumerate()
    {
        for mode in ["--resume", "--restart", "plain"] {
            let copy = s.out(&format!("garbage{k}{mode}"));
            copy_dir(&out, &copy);
            std::fs::write(copy.join(".checkpoint/index.toml"), garbage).unwrap();
            let c = copy.to_str().unwrap();
            let mut args = vec!["run", s.spec(), "-q", "--out", c];
            if mode != "plain" {
                args.push(mode);
            }
            let (code, _, err) = run(&args);
            if mode == "--resume" {
                assert_eq!(code, 1, "{garbage:?} {mode}: {err}");
                assert!(
                    err.contains("not a kfmc checkpoint index") && err.contains("--restart"),
                    "{err}"
                );
                assert!(!copy.join("manifest.toml").exists());
                // What it advises works.
                let (code, _, err) = run(&["run", s.spec(), "-q", "--restart", "--out", c]);
                assert_eq!(code, 0, "{garbage:?} then --restart: {err}");
            } else {
                assert_eq!(code, 0, "{garbage:?} {mode}: {err}");
            }
            assert_eq!(tables(&copy), tables(&single), "{garbage:?} {mode}");
            assert!(!copy.join(".checkpoint").exists(), "{garbage:?} {mode}");
        }
    }
}

/// A checkpoint index edited to another master seed, resumed with that seed, would splice
/// one seed's cells into the other's study: refused, whether the edit left the index's world
/// stamp (the index contradicts the plan) or changed it too (the journals still name the
/// study that wrote them), and nothing is committed.
#[test]
fn an_index_edited_to_another_seed_is_refused_on_resume() {
    let s = Study::new();
    let out = s.out("o");
    let mut child = s.start(&out, &[]);
    kill_after_checkpoint(&mut child, &out, 2);
    assert!(
        (2..CELLS).contains(&checkpointed(&out)),
        "the run ended before the kill"
    );
    let text = std::fs::read_to_string(out.join(".checkpoint/index.toml")).unwrap();
    let stamp = |seed: u64| {
        let registry = kfmc::systems::builtin();
        let mut plan = kfmc::experiment::load_with(&s.spec, &registry).unwrap();
        plan.apply(&kfmc::experiment::Overrides {
            master_seed: Some(seed),
            ..Default::default()
        })
        .unwrap();
        plan.world_stamp()
    };
    let (nine, ten) = (stamp(9), stamp(10));
    assert!(text.contains("master_seed = 9\n"), "{text}");
    assert!(
        text.contains(&format!("world_stamp = \"{nine}\"")),
        "{text}"
    );
    let seed_only = text.replace("master_seed = 9\n", "master_seed = 10\n");
    let both = seed_only.replace(&nine, &ten);
    for (k, (edited, why)) in [
        (seed_only, "the simulated world changed"),
        (both, "holds another study's cells"),
    ]
    .into_iter()
    .enumerate()
    {
        let copy = s.out(&format!("edited{k}"));
        copy_dir(&out, &copy);
        std::fs::write(copy.join(".checkpoint/index.toml"), &edited).unwrap();
        let (code, _, err) = run(&[
            "run",
            s.spec(),
            "-q",
            "--seed",
            "10",
            "--resume",
            "--out",
            copy.to_str().unwrap(),
        ]);
        assert_eq!(code, 1, "{err}");
        assert!(err.contains(why) && err.contains("--restart"), "{err}");
        assert!(
            !copy.join("manifest.toml").exists() && tables(&copy).is_empty(),
            "something was committed"
        );
    }
}
