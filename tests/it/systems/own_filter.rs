//! The "bring your own filter" example (examples/own_filter) as a user would run it: its
//! binary's commands on its two specs, key-path errors in the user's own table, and what its
//! filters must satisfy.
//!
//! The binary is the example, which `cargo test --release` builds before it runs the tests;
//! `cargo test --release --test it systems::own_filter::` alone does not build examples, so build it first
//! (`cargo build --release --example own_filter`).

use crate::common::{f64s, strs};
use std::path::{Path, PathBuf};
use std::process::Command;

use polars::prelude::*;

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// target/<profile>/examples/own_filter: the test runs from target/<profile>/deps.
fn example_binary() -> PathBuf {
    let exe = std::env::current_exe().expect("the test's own path");
    let profile_dir = exe
        .parent()
        .and_then(Path::parent)
        .expect("the test binary lives in target/<profile>/deps");
    let bin = profile_dir
        .join("examples")
        .join(format!("own_filter{}", std::env::consts::EXE_SUFFIX));
    assert!(
        bin.exists(),
        "{} is missing: run `cargo build --release --example own_filter` (or the whole `cargo test --release`, which builds examples)",
        bin.display()
    );
    bin
}

fn spec(name: &str) -> PathBuf {
    repo()
        .join("examples/own_filter")
        .join(format!("{name}.toml"))
}

/// (exit code, stdout, stderr) of the example binary.
fn own_filter(args: &[&str]) -> (i32, String, String) {
    let o = Command::new(example_binary())
        .args(args)
        .output()
        .expect("the example runs");
    (
        o.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&o.stdout).into_owned(),
        String::from_utf8_lossy(&o.stderr).into_owned(),
    )
}

fn path_str(p: &Path) -> &str {
    p.to_str().expect("a UTF-8 path")
}

#[test]
fn the_users_binary_has_its_own_name_and_version() {
    let (code, out, err) = own_filter(&["--version"]);
    assert_eq!(code, 0, "{err}");
    assert_eq!(
        out.trim(),
        format!("own_filter 0.1.0 (kfmc {})", env!("CARGO_PKG_VERSION"))
    );
    let (code, out, err) = own_filter(&["--help"]);
    assert_eq!(code, 0, "{err}");
    assert!(out.contains("Usage: own_filter <COMMAND>"), "{out}");
    // A usage error names the user's binary too, and exits 2 as kfmc's does.
    let (code, _, err) = own_filter(&["no-such-command"]);
    assert_eq!(code, 2);
    assert!(err.contains("Usage: own_filter"), "{err}");
}

/// The subcommands a `--help` lists (the lines under `Commands:`), `help` left out.
fn subcommands(help: &str) -> Vec<String> {
    help.lines()
        .skip_while(|l| !l.starts_with("Commands:"))
        .skip(1)
        .take_while(|l| l.starts_with("  "))
        .filter_map(|l| l.split_whitespace().next())
        .filter(|c| *c != "help")
        .map(str::to_string)
        .collect()
}

#[test]
fn kfmc_appears_nowhere_in_the_users_help() {
    // Every help page, down to `ulog nis`: only the metadata key `kfmc.world_stamp` (a name
    // in the files, not the program) may remain.
    let mut pages = vec![Vec::<String>::new()];
    let mut seen = 0;
    while let Some(path) = pages.pop() {
        let mut args: Vec<&str> = path.iter().map(String::as_str).collect();
        args.push("--help");
        let (code, out, err) = own_filter(&args);
        assert_eq!(code, 0, "{args:?}: {err}");
        seen += 1;
        let rest = out.replace("kfmc.world_stamp", "");
        assert!(
            !rest.contains("kfmc"),
            "{args:?} names kfmc:\n{}",
            rest.lines()
                .filter(|l| l.contains("kfmc"))
                .collect::<Vec<_>>()
                .join("\n")
        );
        assert!(out.contains("own_filter"), "{args:?}: {out}");
        for sub in subcommands(&out) {
            let mut p = path.clone();
            p.push(sub);
            pages.push(p);
        }
    }
    // The top page, its 18 commands and ulog's three.
    assert!(seen >= 22, "{seen} help pages");
}

#[test]
fn the_users_binary_names_itself_in_the_manifest_the_report_and_the_check() {
    let s = spec("cv_range_bearing");
    let dir = tempfile::tempdir().expect("tempdir");
    let out_dir = dir.path().join("study");
    let (code, out, err) = own_filter(&[
        "check",
        path_str(&s),
        "--runs",
        "20",
        "--out",
        path_str(&out_dir),
    ]);
    assert!(code == 0 || code == 3, "{out}\n{err}");
    assert!(
        out.lines()
            .any(|l| l.starts_with("own_filter check own_filter_cv_range_bearing: ")),
        "{out}"
    );
    // The manifest: the binary beside kfmc's library version (what merge and resume compare).
    let manifest: kfmc::toml::Table = std::fs::read_to_string(out_dir.join("manifest.toml"))
        .unwrap()
        .parse()
        .unwrap();
    let get = |k: &str| {
        manifest
            .get(k)
            .and_then(|v| v.as_str())
            .unwrap_or("")
            .to_string()
    };
    assert_eq!(get("program"), "own_filter");
    assert_eq!(get("program_version"), "0.1.0");
    assert_eq!(get("kfmc_version"), env!("CARGO_PKG_VERSION"));

    // The report's "reproduce" line runs the user's binary, and running it gives the same
    // tables byte for byte.
    let (code, _, err) = own_filter(&["report", path_str(&out_dir)]);
    assert_eq!(code, 0, "{err}");
    let html = std::fs::read_to_string(out_dir.join("report.html")).unwrap();
    let line = html
        .lines()
        .find_map(|l| {
            l.strip_prefix("<pre>")
                .filter(|l| l.starts_with("own_filter run "))
        })
        .unwrap_or_else(|| panic!("no reproduce line naming own_filter in the report"))
        .to_string();
    assert!(html.contains(&format!("own_filter report {}", path_str(&out_dir))));
    assert!(html.contains("<th>program</th><td>own_filter 0.1.0</td>"));
    let before = std::fs::read(out_dir.join("runs.parquet")).unwrap();
    let words: Vec<&str> = line.split_whitespace().skip(1).collect();
    assert!(words.contains(&"--runs") && words.contains(&"20"), "{line}");
    let again = dir.path().join("again");
    let mut args = words.clone();
    let at = args.iter().position(|w| *w == "--out").unwrap();
    args[at + 1] = path_str(&again);
    args.push("-q");
    let (code, _, err) = own_filter(&args);
    assert_eq!(code, 0, "{line}: {err}");
    assert_eq!(std::fs::read(again.join("runs.parquet")).unwrap(), before);
}

#[test]
fn every_example_spec_validates_runs_and_passes_its_checks() {
    for name in ["cv_range_bearing", "planar_user_filter", "turning_target"] {
        let s = spec(name);
        let (code, out, err) = own_filter(&["validate", path_str(&s)]);
        assert_eq!(code, 0, "validate {name}: {err}");
        assert!(out.contains("cells"), "{name}: {out}");

        let dir = tempfile::tempdir().expect("tempdir");
        let (code, _, err) =
            own_filter(&["run", path_str(&s), "--out", path_str(dir.path()), "-q"]);
        assert_eq!(code, 0, "run {name}: {err}");
        assert!(dir.path().join("runs.parquet").exists(), "{name}");

        let dir = tempfile::tempdir().expect("tempdir");
        let (code, out, err) =
            own_filter(&["check", path_str(&s), "--out", path_str(dir.path()), "-q"]);
        assert_eq!(code, 0, "check {name}:\n{out}\n{err}");
        assert!(out.contains("0 failed"), "{name}: {out}");
    }
}

#[test]
fn list_shows_the_user_system_and_filters() {
    let (code, out, err) = own_filter(&["list"]);
    assert_eq!(code, 0, "{err}");
    for needle in [
        "cv_range_bearing",
        "user_ekf",
        "user_filter",
        "planar_quadrotor",
    ] {
        assert!(out.contains(needle), "`{needle}` not listed:\n{out}");
    }
}

#[test]
fn a_bad_key_in_the_user_model_table_names_its_path_and_line() {
    let text = std::fs::read_to_string(spec("cv_range_bearing")).expect("spec");
    let bad = text.replacen("accel_psd =", "accel_pds =", 1);
    assert_ne!(bad, text, "the spec sets accel_psd");
    let line = bad
        .lines()
        .position(|l| l.starts_with("accel_pds"))
        .expect("the replaced line")
        + 1;
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("bad.toml");
    std::fs::write(&path, bad).expect("write spec");
    let (code, _, err) = own_filter(&["validate", path_str(&path)]);
    assert_eq!(code, 2, "{err}");
    assert!(err.contains("model.accel_pds"), "{err}");
    assert!(err.contains("unknown field"), "{err}");
    assert!(err.contains(&format!("line {line}")), "{err}");
}

fn rows_of(df: &DataFrame, filter: &str) -> DataFrame {
    let mask = df
        .column("filter")
        .expect("filter")
        .str()
        .expect("str")
        .equal(filter);
    df.filter(&mask).expect("filter rows")
}

#[test]
fn the_user_ekf_equals_kfmcs_ekf_to_round_off_and_is_consistent() {
    let dir = tempfile::tempdir().expect("tempdir");
    let (code, out, err) = own_filter(&[
        "check",
        path_str(&spec("cv_range_bearing")),
        "--out",
        path_str(dir.path()),
        "-q",
    ]);
    assert_eq!(code, 0, "{out}\n{err}");

    // Paired runs: the same truth, measurements and x̂0 for both filters, in the same order.
    let runs = kfmc::output::table::read(&dir.path().join("runs.parquet")).expect("runs");
    let (user, ekf) = (rows_of(&runs, "user_ekf"), rows_of(&runs, "kfmc_ekf"));
    assert_eq!(user.height(), 200);
    assert_eq!(user.height(), ekf.height());
    assert_eq!(strs(&user, "scenario"), strs(&ekf, "scenario"));
    assert_eq!(strs(&user, "status"), vec!["ok".to_string(); 200]);
    let mut worst: f64 = 0.0;
    for s in ["px", "vx", "py", "vy"] {
        let col = format!("rmse_{s}");
        for (a, b) in f64s(&user, &col).iter().zip(f64s(&ekf, &col)) {
            let (a, b) = (a.expect("finite"), b.expect("finite"));
            worst = worst.max((a - b).abs() / b);
        }
    }
    // Joseph form and S⁻¹ against kfmc's standard form and Cholesky solve: measured 1.3e-13.
    assert!(worst < 1e-10, "largest relative RMSE difference {worst:e}");

    let cons =
        kfmc::output::table::read(&dir.path().join("consistency.parquet")).expect("consistency");
    let user = rows_of(&cons, "user_ekf");
    let tests = strs(&user, "test");
    let pass: Vec<Option<bool>> = user
        .column("pass")
        .expect("pass")
        .bool()
        .expect("bool")
        .iter()
        .collect();
    for wanted in ["verdict", "nees_time_average"] {
        let rows: Vec<usize> = (0..tests.len()).filter(|&i| tests[i] == wanted).collect();
        assert_eq!(rows.len(), 2, "{wanted}: one row per scenario");
        assert!(rows.iter().all(|&i| pass[i] == Some(true)), "{wanted}");
    }
}

#[test]
fn a_mistuned_user_ekf_fails_the_check_with_exit_3() {
    let text = std::fs::read_to_string(spec("cv_range_bearing")).expect("spec");
    // Q/100: the filter trusts its motion model far too much, so it is optimistic.
    let bad = text.replace("q_scale = 1.0", "q_scale = 0.01");
    assert_ne!(bad, text, "the spec states q_scale = 1.0");
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("mistuned.toml");
    std::fs::write(&path, bad).expect("write spec");
    let out_dir = dir.path().join("out");
    let (code, out, err) =
        own_filter(&["check", path_str(&path), "--out", path_str(&out_dir), "-q"]);
    assert_eq!(code, 3, "{out}\n{err}");
    assert!(
        out.lines().any(|l| l.contains("FAIL")
            && l.contains("consistent[")
            && l.contains("user_ekf")
            && l.contains("optimistic")),
        "{out}"
    );
}

/// A user's P1 filter kind on the IMU sensor set is named as what it is, not given the
/// running mean's reason (which is about reading y, θ, θ̇ directly).
#[test]
fn a_user_kind_on_the_other_sensor_set_is_named_as_the_user_kind() {
    let text = std::fs::read_to_string(spec("planar_user_filter")).expect("spec");
    let imu = text.replacen("sensor = \"p1\"", "sensor = \"imu\"", 1);
    assert_ne!(imu, text, "the spec sets sensor = \"p1\"");
    let dir = tempfile::tempdir().expect("tempdir");
    let path = dir.path().join("imu.toml");
    std::fs::write(&path, imu).expect("write spec");
    let (code, _, err) = own_filter(&["validate", path_str(&path)]);
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("filter kind `user_filter` is registered for model.sensor = \"p1\" only"),
        "{err}"
    );
    assert!(!err.contains("reads y, θ, θ̇"), "{err}");
}

#[test]
fn validate_lists_each_filter_label_once() {
    let (code, out, err) = own_filter(&["validate", path_str(&spec("turning_target"))]);
    assert_eq!(code, 0, "{err}");
    let line = out
        .lines()
        .find_map(|l| l.trim().strip_prefix("filters: "))
        .unwrap_or_else(|| panic!("no filters line: {out}"));
    // ekf runs at q_scale 1 and 100: one label with two variants, not two labels.
    assert_eq!(
        line,
        "ekf (ekf, 2 variants), ukf (ukf), user_ekf (user_ekf)"
    );
}

#[test]
fn a_mistyped_kind_tag_gets_the_closest_one() {
    let text = std::fs::read_to_string(spec("turning_target")).expect("spec");
    let dir = tempfile::tempdir().expect("tempdir");
    let cases = [
        (
            "kind = \"user_ekf\"",
            "kind = \"user_ekff\"",
            "filters[2].kind",
            "user_ekf",
        ),
        (
            "kind = \"turning_target\"",
            "kind = \"turning_targte\"",
            "model.kind",
            "turning_target",
        ),
    ];
    for (from, to, key, best) in cases {
        let typo = text.replacen(from, to, 1);
        assert_ne!(typo, text, "{from}");
        let path = dir.path().join("typo.toml");
        std::fs::write(&path, typo).expect("write spec");
        let (code, _, err) = own_filter(&["validate", path_str(&path)]);
        assert_eq!(code, 2, "{err}");
        let line = err
            .lines()
            .find(|l| l.contains(&format!(": {key}: ")))
            .unwrap_or_else(|| panic!("no error at {key}: {err}"));
        assert!(
            line.contains(&format!("; did you mean `{best}`?")),
            "{line}"
        );
    }
    // A word close to no tag gets the list alone.
    let far = text.replacen("kind = \"user_ekf\"", "kind = \"particle\"", 1);
    let path = dir.path().join("far.toml");
    std::fs::write(&path, far).expect("write spec");
    let (code, _, err) = own_filter(&["validate", path_str(&path)]);
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("unknown value `particle`; expected one of: "),
        "{err}"
    );
    assert!(!err.contains("did you mean"), "{err}");
}
