//! The `kfmc` binary: commands, exit codes, error messages with key paths, clean output.

use crate::common::{EKF_AND_MEAN, kfmc, repo, small_spec, spec_in_tempdir};

fn output(args: &[&str]) -> (i32, String, String) {
    let o = kfmc().args(args).output().expect("kfmc runs");
    (
        o.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&o.stdout).into_owned(),
        String::from_utf8_lossy(&o.stderr).into_owned(),
    )
}

#[test]
fn every_command_has_help() {
    for cmd in [
        vec!["--help"],
        vec!["run", "--help"],
        vec!["validate", "--help"],
        vec!["summary", "--help"],
        vec!["list", "--help"],
    ] {
        let (code, out, _) = output(&cmd);
        assert_eq!(code, 0, "{cmd:?}");
        assert!(out.contains("Usage:"), "{cmd:?}: {out}");
    }
    let (_, out, _) = output(&["--help"]);
    assert!(out.contains("Exit codes"));
}

#[test]
fn bundled_specs_validate() {
    for spec in [
        "planar_seed_study",
        "planar_noise_cases",
        "planar_robustness",
        "planar_imu",
    ] {
        let path = repo().join(format!("experiments/{spec}.toml"));
        let (code, out, err) = output(&["validate", path.to_str().unwrap()]);
        assert_eq!(code, 0, "{spec}: {err}");
        assert!(out.contains("cells"), "{spec}: {out}");
    }
    let (_, out, _) = output(&[
        "validate",
        repo()
            .join("experiments/planar_robustness.toml")
            .to_str()
            .unwrap(),
    ]);
    assert!(out.contains("1000 cells × 100 runs = 100000 runs"), "{out}");
}

#[test]
fn bad_specs_exit_2_naming_the_file_and_key_path() {
    let cases: [(&str, &[&str]); 5] = [
        (
            "[model]\nkind = \"planar_quadrotor\"\n[[scenarios]]\nname = \"basic\"\n[[filters]]\nlabel = \"ekf\"\nkind = \"ekf\"\nq_sdt = 0.1\n",
            &["filters[0].q_sdt", "unknown field"],
        ),
        (
            "[model]\nkind = \"planar_quadrotor\"\nsensor = \"imu\"\n[[scenarios]]\nname = \"basic\"\n[[filters]]\nlabel = \"rm\"\nkind = \"running_mean\"\n",
            &["filters[0].kind", "sensor"],
        ),
        (
            "[model]\nkind = \"planar_quadrotor\"\n[[scenarios]]\nname = \"basic\"\n[[filters]]\nlabel = \"ekf\"\nkind = \"ekf\"\nr_std = [0.01, 0.0, 0.01]\n",
            &["filters[0].r_std[1]", "positive"],
        ),
        (
            "runs = -3\n[model]\nkind = \"planar_quadrotor\"\n",
            &["runs", "line 1"],
        ),
        (
            "[model]\nkind = \"planar_quadrotor\"\n[[scenarios]]\nname = \"basic\"\n[[filters]]\nlabel = \"ekf\"\nkind = \"particle\"\n[noise]\nscales = [1.0, 1.0]\n",
            &[
                "filters[0].kind",
                "unknown value `particle`",
                "noise.scales",
                "duplicate",
            ],
        ),
    ];
    for (text, needles) in cases {
        let (_dir, spec) = spec_in_tempdir(text);
        for cmd in ["validate", "run"] {
            let (code, out, err) = output(&[cmd, spec.to_str().unwrap()]);
            assert_eq!(code, 2, "{cmd} {text}: {err}");
            assert!(out.is_empty());
            assert!(err.contains("spec.toml"), "{err}");
            assert!(!err.contains("panicked"), "{err}");
            for n in needles {
                assert!(err.contains(n), "missing `{n}` in: {err}");
            }
        }
    }
    let (code, _, err) = output(&["run", "/nonexistent/spec.toml"]);
    assert_eq!(code, 2);
    assert!(
        err.contains("/nonexistent/spec.toml") && err.contains("cannot read"),
        "{err}"
    );
}

#[test]
fn run_writes_the_tables_and_summary_reads_them() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("res");
    let (_d, spec) = spec_in_tempdir(&small_spec(&out, 5, "[1.0, 2.0]", EKF_AND_MEAN));
    let (code, stdout, stderr) = output(&[
        "run",
        spec.to_str().unwrap(),
        "--trace-runs",
        "1",
        "--threads",
        "2",
    ]);
    assert_eq!(code, 0, "{stderr}");
    // Not a terminal: no progress bar, no escape codes.
    assert!(
        !stderr.contains('\u{1b}') && stderr.is_empty(),
        "{stderr:?}"
    );
    assert!(stdout.contains("20 runs"), "{stdout}");
    for t in [
        "runs",
        "steps",
        "summary",
        "divergence",
        "divergence_runs",
        "traces",
    ] {
        assert!(out.join(format!("{t}.parquet")).exists(), "{t}");
    }
    let manifest = std::fs::read_to_string(out.join("manifest.toml")).unwrap();
    for key in [
        "spec_hash",
        "kfmc_version",
        "master_seed = 11",
        "runs = 20",
        "wall_s",
        "[[tables]]",
    ] {
        assert!(manifest.contains(key), "manifest lacks {key}");
    }
    assert!(std::fs::read_dir(&out).unwrap().all(|e| {
        !e.unwrap()
            .file_name()
            .to_string_lossy()
            .ends_with(".partial")
    }));

    let (code, s, err) = output(&["summary", out.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    for needle in [
        "rmse_thetadot",
        "running_mean",
        "basic",
        "roll",
        "Divergence",
    ] {
        assert!(s.contains(needle), "summary lacks {needle}:\n{s}");
    }
    let (_, s2, _) = output(&["summary", out.to_str().unwrap(), "--noise-scale", "2"]);
    assert!(s2.lines().count() < s.lines().count());

    // --quiet prints nothing at all.
    let (code, stdout, stderr) = output(&["run", spec.to_str().unwrap(), "--quiet", "--runs", "2"]);
    assert_eq!(code, 0);
    assert!(stdout.is_empty() && stderr.is_empty());
    // A second run without tracing removes the earlier traces table: one folder, one study.
    assert!(!out.join("traces.parquet").exists());
}

#[test]
fn summary_of_a_missing_folder_exits_1() {
    let (code, _, err) = output(&["summary", "/nonexistent/results"]);
    assert_eq!(code, 1);
    assert!(err.contains("/nonexistent/results"), "{err}");
}

#[test]
fn unwritable_output_exits_1_and_leaves_nothing_half_written() {
    let tmp = tempfile::tempdir().unwrap();
    let blocker = tmp.path().join("file");
    std::fs::write(&blocker, "not a folder").unwrap();
    let (_d, spec) = spec_in_tempdir(&small_spec(&blocker.join("out"), 2, "[1.0]", EKF_AND_MEAN));
    let (code, _, err) = output(&["run", spec.to_str().unwrap()]);
    assert_eq!(code, 1, "{err}");
    assert!(err.contains("cannot create the output folder"), "{err}");
}

#[test]
fn list_names_the_models_scenarios_and_filters() {
    let (code, out, _) = output(&["list"]);
    assert_eq!(code, 0);
    for n in [
        "planar_quadrotor",
        "p1",
        "imu",
        "basic",
        "horizontal",
        "roll",
        "fall",
        "ekf",
        "running_mean",
        "open_loop",
        "ukf",
        "ckf",
        "pole_placement",
        "batch_ls",
    ] {
        assert!(out.contains(n), "list lacks {n}");
    }
}

#[test]
fn check_passes_on_the_tuned_spec_and_fails_with_exit_3_when_q_is_mistuned() {
    let tmp = tempfile::tempdir().unwrap();
    let spec = repo().join("experiments/ci_consistency.toml");
    let junit = tmp.path().join("junit.xml");
    let out = tmp.path().join("ok");
    let (code, stdout, err) = output(&[
        "check",
        spec.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--junit",
        junit.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{stdout}{err}");
    assert!(stdout.contains("6 cases, 6 passed, 0 failed"), "{stdout}");
    let xml = std::fs::read_to_string(&junit).unwrap();
    assert!(
        xml.contains("<testsuites") && xml.contains("tests=\"6\" failures=\"0\""),
        "{xml}"
    );
    assert_eq!(xml.matches("<testcase ").count(), 6);
    // The summary prints the verdicts next to the RMSE table.
    let (code, summary, _) = output(&["summary", out.to_str().unwrap()]);
    assert_eq!(code, 0);
    assert!(
        summary.contains("Consistency (") && summary.contains("basic     1            ekf"),
        "{summary}"
    );
    assert_eq!(summary.matches("  pass").count(), 2, "{summary}");

    let text = std::fs::read_to_string(&spec)
        .unwrap()
        .replace("q_scale = 1.0 ", "q_scale = 2.0 ");
    let (_d, bad) = spec_in_tempdir(&text);
    let (code, stdout, _) = output(&[
        "check",
        bad.to_str().unwrap(),
        "--out",
        tmp.path().join("bad").to_str().unwrap(),
        "--junit",
        junit.to_str().unwrap(),
        "--quiet",
    ]);
    assert_eq!(code, 3, "{stdout}");
    assert!(
        stdout.contains("FAIL  consistent[basic noise=1 ekf q=2 r=1]"),
        "{stdout}"
    );
    assert!(
        stdout.contains("pessimistic"),
        "Q too large makes P too large: {stdout}"
    );
    let xml = std::fs::read_to_string(&junit).unwrap();
    assert_eq!(xml.matches("<failure ").count(), 4, "{xml}");
}

#[test]
fn check_refuses_zero_replications_as_power_does() {
    // `power --replications 0` is refused (exit 2); so is `check --replications 0`, whether or
    // not the spec has a rejection_rate assertion.
    let tmp = tempfile::tempdir().unwrap();
    let spec = repo().join("experiments/ci_consistency.toml");
    for cmd in ["check", "power"] {
        let (code, _, err) = output(&[
            cmd,
            spec.to_str().unwrap(),
            "--replications",
            "0",
            "--quiet",
            "--out",
            tmp.path().join(cmd).to_str().unwrap(),
        ]);
        assert_eq!(code, 2, "{cmd}: {err}");
        assert!(err.contains("--replications"), "{cmd}: {err}");
        assert!(!tmp.path().join(cmd).exists(), "{cmd} ran");
    }
}

#[test]
fn check_without_assertions_or_with_a_bad_one_is_an_invalid_spec() {
    let tmp = tempfile::tempdir().unwrap();
    let (_d, spec) = spec_in_tempdir(&small_spec(&tmp.path().join("o"), 2, "[1.0]", EKF_AND_MEAN));
    let (code, _, err) = output(&["check", spec.to_str().unwrap()]);
    assert_eq!(code, 2);
    assert!(err.contains("check.assert"), "{err}");
    let text = small_spec(&tmp.path().join("o"), 2, "[1.0]", EKF_AND_MEAN)
        + "[[check.assert]]\nkind = \"rmse_below\"\nfilter = \"ukf\"\nstate = \"q\"\nmax = 1\n";
    let (_d2, spec) = spec_in_tempdir(&text);
    let (code, _, err) = output(&["check", spec.to_str().unwrap()]);
    assert_eq!(code, 2);
    assert!(
        err.contains("check.assert[0].filter") && err.contains("check.assert[0].state"),
        "{err}"
    );
}

#[test]
fn tune_finds_q_scale_near_1_for_a_matched_ekf_and_writes_tuning_parquet() {
    let tmp = tempfile::tempdir().unwrap();
    let spec = repo().join("experiments/ci_consistency.toml");
    let out = tmp.path().join("tune");
    let (code, stdout, err) = output(&[
        "tune",
        spec.to_str().unwrap(),
        "--runs",
        "30",
        "--out",
        out.to_str().unwrap(),
        "--quiet",
    ]);
    assert_eq!(code, 0, "{err}");
    let best: f64 = stdout
        .split("best q_scale = ")
        .nth(1)
        .and_then(|s| s.split(',').next())
        .and_then(|s| s.trim().parse().ok())
        .unwrap_or_else(|| panic!("no best q_scale in: {stdout}"));
    // The coarse grid has half-decade steps and the refinement ±½ decade in 11 points.
    assert!((0.6..=1.6).contains(&best), "best q_scale {best}: {stdout}");
    let df = kfmc::output::table::read(&out.join("tuning.parquet")).unwrap();
    for c in [
        "stage",
        "scenario",
        "q_scale",
        "r_scale",
        "anees",
        "anis",
        "rmse_x",
        "objective",
    ] {
        assert!(df.column(c).is_ok(), "tuning.parquet lacks {c}");
    }
    assert_eq!(df.height(), 2 * (13 + 11));
    // The stages' own studies are kept beside it.
    assert!(out.join("tune_coarse/consistency.parquet").exists());
    // Filter variants stay apart in the summary.
    let (code, summary, _) = output(&["summary", out.join("tune_coarse").to_str().unwrap()]);
    assert_eq!(code, 0);
    assert!(
        summary.contains("ekf q×0.001 r×1") && summary.contains("ekf q×1000 r×1"),
        "{summary}"
    );
    // The folder plots as it is: tuning curves per scenario.
    let (code, _, err) = output(&["plot", out.to_str().unwrap(), "--only", "tuning"]);
    assert_eq!(code, 0, "{err}");
    for s in ["basic", "roll"] {
        let f = out.join(format!("figures/tuning_{s}.png"));
        assert!(
            std::fs::metadata(&f)
                .map(|m| m.len() > 10_000)
                .unwrap_or(false),
            "{}",
            f.display()
        );
    }
}

/// Asserts a clean refusal: exit `want`, no panic, the stderr holding every needle.
fn refused(args: &[&str], want: i32, needles: &[&str]) -> String {
    let (code, _, err) = output(args);
    assert_eq!(code, want, "{args:?}: {err}");
    assert!(!err.contains("panicked"), "{args:?}: {err}");
    for n in needles {
        assert!(err.contains(n), "{args:?}: `{n}` not in {err}");
    }
    err
}

const EXTERNAL_ONLY: &str = r#"
[[filters]]
label = "theirs"
kind = "external"
"#;

/// Flag values that used to panic (exit 101) or start unbounded work are usage errors (exit
/// 2), refused before anything is written.
#[test]
fn panicking_and_unbounded_flag_values_are_usage_errors() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("res");
    let (_d, spec) = spec_in_tempdir(&small_spec(&out, 2, "[1.0]", EKF_AND_MEAN));
    let s = spec.to_str().unwrap();
    refused(
        &["run", s, "-q", "--checkpoint-every", "1e308"],
        2,
        &["--checkpoint-every", "longer than kfmc can wait"],
    );
    // The filter-step limit holds for the whole command, not one replication.
    let err = refused(
        &["power", s, "-q", "--replications", "1000000000000"],
        2,
        &["--replications", "filter steps", "--allow-large"],
    );
    assert!(err.contains("1000000000000 replications"), "{err}");
    // Shard counts are bounded, and a bad --shard is a usage error, not an invalid spec.
    for shard in ["0/1000000000000", "0/100001", "3/2", "x/2"] {
        let err = refused(&["run", s, "-q", "--shard", shard], 2, &["invalid --shard"]);
        assert!(!err.contains("invalid spec"), "{err}");
    }
    refused(
        &["run", s, "-q", "--shard", "0/100001"],
        2,
        &["at most 100000"],
    );
    assert!(!out.exists(), "a refused command wrote {}", out.display());
    // describe --no-write --out: the two contradict each other.
    let file = tmp.path().join("d.toml");
    refused(
        &["describe", s, "--no-write", "--out", file.to_str().unwrap()],
        2,
        &["--no-write", "--out"],
    );
    assert!(!file.exists());
    // summary --noise-scale must be a multiplier (1e400 parses as ∞).
    for x in ["NaN", "inf", "1e400", "0"] {
        refused(
            &["summary", out.to_str().unwrap(), "--noise-scale", x],
            2,
            &["invalid --noise-scale"],
        );
    }
}

/// `kfmc tune` on a spec whose filters are external used to index past the system's filter
/// kinds (exit 101): now it says why there is nothing to tune.
#[test]
fn tune_refuses_an_external_filter_with_a_reason() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("res");
    let (_d, spec) = spec_in_tempdir(&small_spec(&out, 2, "[1.0]", EXTERNAL_ONLY));
    let s = spec.to_str().unwrap();
    refused(&["tune", s, "-q"], 2, &["no filter with a covariance"]);
    let both = format!("{EKF_AND_MEAN}{EXTERNAL_ONLY}");
    let (_d2, spec2) = spec_in_tempdir(&small_spec(&out, 2, "[1.0]", &both));
    refused(
        &["tune", spec2.to_str().unwrap(), "-q", "--filter", "theirs"],
        2,
        &["filter `theirs` is external"],
    );
    assert!(!out.exists());
}

/// Every value that goes into a Slurm script is checked (none can add a line or a
/// directive), the counts are bounded, and a spec whose array tasks would all fail (an
/// external filter) is refused with the reason: exit 2, and no script is written.
#[test]
fn slurm_refuses_values_that_would_break_or_inject_into_its_scripts() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("res");
    let (_d, spec) = spec_in_tempdir(&small_spec(&out, 2, "[1.0]", EKF_AND_MEAN));
    let s = spec.to_str().unwrap();
    let o = out.to_str().unwrap();
    let base = ["slurm", s, "--out", o];
    for (extra, needle) in [
        (vec!["--shards", "0"], "--shards"),
        (vec!["--shards", "1000000000000"], "--shards"),
        (vec!["--shards", "100001"], "--shards"),
        (vec!["--shards", "2", "--cpus", "0"], "--cpus"),
        (
            vec!["--shards", "2", "--partition", "batch\n#SBATCH --uid=0"],
            "invalid --partition",
        ),
        (
            vec!["--shards", "2", "--partition", "a b"],
            "invalid --partition",
        ),
        (
            vec!["--shards", "2", "--partition", ""],
            "invalid --partition",
        ),
        (
            vec!["--shards", "2", "--time", "01:00:00\nrm -rf ~"],
            "invalid --time",
        ),
        (vec!["--shards", "2", "--time", "1:00;x"], "invalid --time"),
    ] {
        let mut args: Vec<&str> = base.to_vec();
        args.extend(extra);
        refused(&args, 2, &[needle]);
    }
    assert!(!out.join("slurm").exists(), "a refused slurm wrote scripts");
    // An output folder sbatch would split or expand in `#SBATCH --output=`.
    let odd = tmp.path().join("a b%j");
    refused(
        &["slurm", s, "--shards", "2", "--out", odd.to_str().unwrap()],
        2,
        &["invalid --out"],
    );
    let (_d2, ext) = spec_in_tempdir(&small_spec(&out, 2, "[1.0]", EXTERNAL_ONLY));
    refused(
        &["slurm", ext.to_str().unwrap(), "--shards", "2", "--out", o],
        2,
        &["filter `theirs` is external", "kfmc simulate --shard"],
    );
    assert!(!out.join("slurm").exists());
    // Still accepted: Slurm's own forms.
    let (code, _, err) = output(&[
        "slurm",
        s,
        "--shards",
        "100000",
        "--partition",
        "gpu,batch",
        "--time",
        "2-00:00:00",
        "--out",
        o,
    ]);
    assert_eq!(code, 0, "{err}");
    let array = std::fs::read_to_string(out.join("slurm/array.sbatch")).unwrap();
    assert!(array.contains("#SBATCH --array=0-99999\n"), "{array}");
    assert!(array.contains("#SBATCH --partition=gpu,batch\n"), "{array}");
}

/// `summary` names what a simulation or power folder holds instead of a raw "cannot open";
/// a noise scale the folder lacks is an error listing the ones it has; `plot --only` with a
/// kind the tables cannot give says so (exit 1) instead of drawing nothing and exiting 0.
#[test]
fn summary_and_plot_say_what_a_folder_lacks() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("res");
    let (_d, spec) = spec_in_tempdir(&small_spec(&out, 2, "[1.0, 2.0]", EKF_AND_MEAN));
    let s = spec.to_str().unwrap();
    let sim = tmp.path().join("sim");
    let pow = tmp.path().join("pow");
    for args in [
        vec!["run", s, "-q"],
        vec!["simulate", s, "-q", "--out", sim.to_str().unwrap()],
        vec!["power", s, "-q", "-R", "1", "--out", pow.to_str().unwrap()],
    ] {
        let (code, _, err) = output(&args);
        assert_eq!(code, 0, "{args:?}: {err}");
    }
    refused(
        &["summary", sim.to_str().unwrap()],
        1,
        &["is a simulation (`kfmc simulate`)", "truth"],
    );
    refused(
        &["summary", pow.to_str().unwrap()],
        1,
        &["is a power study (`kfmc power`)"],
    );
    refused(
        &["summary", out.to_str().unwrap(), "--noise-scale", "3"],
        1,
        &["no rows at noise scale 3 (it has 1, 2)"],
    );
    let (code, text, err) = output(&["summary", out.to_str().unwrap(), "--noise-scale", "2"]);
    assert_eq!(code, 0, "{err}");
    assert!(text.contains("rmse_"), "{text}");
    let figs = tmp.path().join("figs");
    refused(
        &[
            "plot",
            out.to_str().unwrap(),
            "--out",
            figs.to_str().unwrap(),
            "--only",
            "tuning",
            "states",
        ],
        1,
        &["no data for the figures tuning", "asked for with --only"],
    );
    assert!(!figs.exists(), "a refused plot drew figures");
}

/// A `--runs` at or below a `[[consistency.subsets]]` run count would evaluate the subset
/// on the whole study, writing consistency rows with the same key twice (which every reader
/// then refuses): the override is refused naming the subset.
#[test]
fn runs_override_below_a_subset_is_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let spec = crate::common::repo().join("experiments/linear_power.toml");
    let (code, _, err) = crate::common::run_cli(&[
        "run",
        spec.to_str().unwrap(),
        "--runs",
        "20",
        "--out",
        tmp.path().join("o").to_str().unwrap(),
        "--quiet",
    ]);
    assert_eq!(code, 2, "{err}");
    assert!(
        err.contains("--runs") && err.contains("consistency.subsets[0] (50 runs at α = 0.05)"),
        "{err}"
    );
    assert!(!tmp.path().join("o/consistency.parquet").exists());
}
