//! A full disk (a 2 MiB tmpfs) for `run`, `plot` and `report`: each fails with exit code 1 and
//! the OS error, and no file is left under a real name that is not complete — the old study
//! stays readable, figures and the report are either whole or absent.
//!
//! Mounting needs root (CI runs as root); elsewhere the test says that it skipped.

use std::path::{Path, PathBuf};

use crate::common::{kfmc, repo};

struct Tmpfs {
    dir: tempfile::TempDir,
}

impl Tmpfs {
    fn mount(size: &str) -> Option<Self> {
        let dir = tempfile::tempdir().ok()?;
        let ok = std::process::Command::new("mount")
            .args(["-t", "tmpfs", "-o", &format!("size={size}"), "tmpfs"])
            .arg(dir.path())
            .stderr(std::process::Stdio::null())
            .status()
            .is_ok_and(|s| s.success());
        ok.then_some(Tmpfs { dir })
    }
    fn path(&self) -> PathBuf {
        self.dir.path().to_path_buf()
    }
}

impl Drop for Tmpfs {
    fn drop(&mut self) {
        let _ = std::process::Command::new("umount")
            .arg(self.dir.path())
            .status();
    }
}

fn run(args: &[&str]) -> (i32, String) {
    let o = kfmc().args(args).output().unwrap();
    (
        o.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&o.stderr).into_owned(),
    )
}

/// Fills the file system of `dir` until fewer than `leave` bytes are free.
fn fill(dir: &Path, leave: u64) {
    use std::io::Write;
    let mut f = std::fs::File::create(dir.join("filler")).unwrap();
    let block = vec![0u8; 4096];
    let mut written = 0u64;
    // tmpfs is 2 MiB here: write until the next block would leave less than `leave`.
    while written + 4096 + leave <= 2 * 1024 * 1024 && f.write_all(&block).is_ok() {
        written += 4096;
    }
    let _ = f.flush();
    while f.write_all(&block[..512]).is_ok() && free_bytes(dir) > leave {}
}

fn free_bytes(dir: &Path) -> u64 {
    let o = std::process::Command::new("df")
        .args(["-B1", "--output=avail"])
        .arg(dir)
        .output()
        .unwrap();
    String::from_utf8_lossy(&o.stdout)
        .lines()
        .nth(1)
        .and_then(|l| l.trim().parse().ok())
        .unwrap_or(0)
}

fn is_complete_png(path: &Path) -> bool {
    let b = std::fs::read(path).unwrap();
    b.starts_with(b"\x89PNG") && b.ends_with(&[0xae, 0x42, 0x60, 0x82])
}

#[test]
fn a_full_disk_leaves_nothing_half_written() {
    let Some(fs) = Tmpfs::mount("2m") else {
        eprintln!(
            "SKIPPED: cannot mount a tmpfs here (needs root); the disk-full test did not run"
        );
        return;
    };
    let out = fs.path().join("study");
    let spec = repo().join("experiments/planar_seed_study.toml");
    let spec = spec.to_str().unwrap();
    let o = out.to_str().unwrap();

    // A small study that fits (without its checkpoint, which takes about as much again as
    // the tables uncompressed).
    let (code, err) = run(&[
        "run",
        spec,
        "--runs",
        "2",
        "--trace-runs",
        "0",
        "--no-checkpoint",
        "-q",
        "--out",
        o,
    ]);
    assert_eq!(code, 0, "{err}");
    // A larger one into the same folder does not fit: refused at the OS error, old study kept.
    let (code, err) = run(&[
        "run",
        spec,
        "--runs",
        "400",
        "--trace-runs",
        "1",
        "-q",
        "--out",
        o,
    ]);
    assert_eq!(code, 1, "{err}");
    assert!(
        err.contains("No space left") || err.contains("space"),
        "{err}"
    );
    let (code, err) = run(&["summary", o]);
    assert_eq!(code, 0, "the old study is intact: {err}");
    let leftovers: Vec<String> = std::fs::read_dir(&out)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.ends_with(".partial") || n == ".kfmc.lock")
        .collect();
    assert!(leftovers.is_empty(), "{leftovers:?}");
    assert!(
        !out.join(".checkpoint").exists(),
        "journals that no checkpoint index vouches for are removed"
    );

    // Figures and the report with almost no space left.
    fill(&fs.path(), 48 * 1024);
    let (code, err) = run(&["plot", o]);
    assert_eq!(code, 1, "{err}");
    for e in std::fs::read_dir(out.join("figures")).into_iter().flatten() {
        let p = e.unwrap().path();
        let name = p.file_name().unwrap().to_string_lossy().into_owned();
        assert!(!name.ends_with(".partial.png"), "{name} left behind");
        if name.ends_with(".png") {
            assert!(is_complete_png(&p), "{name} is truncated");
        }
    }
    fill(&fs.path(), 0);
    let (code, err) = run(&["report", o]);
    assert_eq!(code, 1, "{err}");
    let report = out.join("report.html");
    assert!(
        !report.exists()
            || std::fs::read_to_string(&report)
                .unwrap()
                .trim_end()
                .ends_with("</html>"),
        "a truncated report"
    );
    assert!(!out.join(".report.html.partial").exists());
}

/// The entries of `dir` that a failed command must not leave: partial files, a lock, or a
/// manifest (which would claim the folder is a complete study).
fn leftovers(dir: &Path) -> Vec<String> {
    std::fs::read_dir(dir)
        .into_iter()
        .flatten()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.ends_with(".partial") || n == ".kfmc.lock" || n == "manifest.toml")
        .collect()
}

#[test]
fn simulate_and_score_on_a_full_disk_leave_nothing_half_written() {
    let Some(fs) = Tmpfs::mount("2m") else {
        eprintln!(
            "SKIPPED: cannot mount a tmpfs here (needs root); the disk-full test of simulate and score did not run"
        );
        return;
    };
    let work = tempfile::tempdir().unwrap();
    let spec = |kind: &str| {
        let p = work.path().join(format!("{kind}.toml"));
        std::fs::write(
            &p,
            format!(
                "name = \"full\"\nmaster_seed = 3\nruns = 4\n[model]\nkind = \"linear_quadrotor\"\nsensor = \"positions\"\n[[scenarios]]\nname = \"hover\"\nx0 = [1.0, 0.0, 1.0, 0.0, 1.0, 0.0]\nduration_s = 5.0\n[[filters]]\nlabel = \"kf\"\nkind = \"{kind}\"\n[initial_estimate]\nmode = \"sampled\"\np0_std = 1.0\n"
            ),
        )
        .unwrap();
        p.to_string_lossy().into_owned()
    };
    let (run_spec, ext_spec) = (spec("ekf"), spec("external"));
    // Estimates made on a disk with room.
    let est_dir = work.path().join("run");
    let (code, err) = run(&[
        "run",
        &run_spec,
        "-q",
        "--export-estimates",
        "--out",
        est_dir.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{err}");
    let estimates = est_dir.join("estimates.parquet");

    // A simulation too large for the disk fails with the OS error and leaves no table.
    let big = fs.path().join("big");
    let (code, err) = run(&[
        "simulate",
        &ext_spec,
        "-q",
        "--runs",
        "3000",
        "--out",
        big.to_str().unwrap(),
    ]);
    assert_eq!(code, 1, "{err}");
    assert!(err.contains("space"), "{err}");
    assert!(leftovers(&big).is_empty(), "{:?}", leftovers(&big));
    let _ = std::fs::remove_dir_all(&big);

    // One that fits, then a score with the disk full.
    let sim = fs.path().join("sim");
    let (code, err) = run(&["simulate", &ext_spec, "-q", "--out", sim.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    fill(&fs.path(), 0);
    let scored = fs.path().join("scored");
    let (code, err) = run(&[
        "score",
        sim.to_str().unwrap(),
        "-q",
        "--out",
        scored.to_str().unwrap(),
        "--estimates",
        estimates.to_str().unwrap(),
    ]);
    assert_eq!(code, 1, "{err}");
    assert!(leftovers(&scored).is_empty(), "{:?}", leftovers(&scored));
    // The simulation itself is still a complete, verifiable folder.
    std::fs::remove_file(fs.path().join("filler")).unwrap();
    let (code, err) = run(&[
        "score",
        sim.to_str().unwrap(),
        "-q",
        "--out",
        scored.to_str().unwrap(),
        "--estimates",
        estimates.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{err}");
}
