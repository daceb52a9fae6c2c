//! Sharded studies: `run --shard i/n` in separate processes and `merge` give tables
//! byte-identical to one process, for any n (more parts than cells included); a part of
//! another study or a missing part is refused at merge time, naming it.

use crate::common::run_cli as run;
use crate::common::table_bytes as tables;

/// The six-cell planar study, 12 runs a cell.
fn spec_text() -> String {
    crate::common::six_cell_planar("sharded", 12)
}

#[test]
fn merged_parts_are_byte_identical_to_one_process_for_any_part_count() {
    let tmp = tempfile::tempdir().unwrap();
    let spec = tmp.path().join("s.toml");
    std::fs::write(&spec, spec_text()).unwrap();
    let spec = spec.to_str().unwrap();
    let single = tmp.path().join("single");
    let (code, _, err) = run(&["run", spec, "-q", "--out", single.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    let want = tables(&single);
    let names: Vec<&str> = want.iter().map(|(n, _)| n.as_str()).collect();
    assert_eq!(
        names,
        [
            "consistency.parquet",
            "divergence.parquet",
            "divergence_runs.parquet",
            "runs.parquet",
            "steps.parquet",
            "summary.parquet",
            "traces.parquet"
        ]
    );
    // The credibility columns (per-block ANEES, NCI) are part of what is compared: the
    // identity below covers them only if they hold values.
    for table in ["consistency.parquet", "steps.parquet"] {
        let df = crate::common::read(&single.join(table));
        for c in [
            "block_anees_position",
            "block_anees_rad_s",
            "nci",
            "inclination",
        ] {
            let col = df.column(c).unwrap_or_else(|_| panic!("{table} has {c}"));
            assert!(col.null_count() < col.len(), "{table}: {c} is all null");
        }
    }
    // The divergence points are rebuilt by the merge from every part's runs and summary: the
    // comparison below means something only if runs cross first at every noise scale (a
    // rebuild that lost or mixed up a scale's rows would then change them).
    let crossings = crossing_counts(&single);
    let scales: Vec<Option<f64>> = crossings.iter().map(|c| c.0).collect();
    assert_eq!(scales, [Some(0.5), Some(1.0), Some(20.0)], "{crossings:?}");
    // 2 scenarios × 3 noise scales = 6 cells: 7 parts leave one empty.
    for n in [1usize, 2, 3, 7] {
        let out = tmp.path().join(format!("n{n}"));
        let o = out.to_str().unwrap();
        // Out of order, as a scheduler may run them.
        for i in (0..n).rev() {
            let (code, _, err) = run(&[
                "run",
                spec,
                "-q",
                "--out",
                o,
                "--shard",
                &format!("{i}/{n}"),
            ]);
            assert_eq!(code, 0, "part {i}/{n}: {err}");
        }
        let (code, stdout, _) = run(&["status", o]);
        assert_eq!(code, 0);
        assert!(
            stdout.contains(&format!("{n} of {n} parts complete")),
            "{stdout}"
        );
        let (code, _, err) = run(&["merge", o]);
        assert_eq!(code, 0, "merge n = {n}: {err}");
        let got = tables(&out);
        assert_eq!(got.len(), want.len(), "n = {n}");
        for ((name, a), (_, b)) in want.iter().zip(&got) {
            assert!(a == b, "n = {n}: {name} differs from the single process");
        }
        // The merged folder is a study every reader accepts.
        assert_eq!(run(&["summary", o]).0, 0);
    }
}

/// How many (run, state) rows of `divergence_runs` cross first at each noise scale (`None`:
/// never crossed), sorted by scale.
fn crossing_counts(dir: &std::path::Path) -> Vec<(Option<f64>, usize)> {
    let df = kfmc::output::table::read(&dir.join("divergence_runs.parquet")).unwrap();
    let mut counts: Vec<(Option<f64>, usize)> = Vec::new();
    let scale = df.column("divergence_scale").unwrap().f64().unwrap();
    for v in (0..scale.len()).map(|i| scale.get(i)) {
        match counts.iter_mut().find(|(s, _)| *s == v) {
            Some((_, n)) => *n += 1,
            None => counts.push((v, 1)),
        }
    }
    counts.sort_by(|a, b| a.0.partial_cmp(&b.0).unwrap());
    counts
}

#[test]
fn parts_of_another_study_or_a_missing_part_are_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let spec = tmp.path().join("s.toml");
    std::fs::write(&spec, spec_text()).unwrap();
    let spec = spec.to_str().unwrap();
    let out = tmp.path().join("d");
    let o = out.to_str().unwrap();
    assert_eq!(run(&["run", spec, "-q", "--out", o, "--shard", "0/3"]).0, 0);
    assert_eq!(run(&["run", spec, "-q", "--out", o, "--shard", "2/3"]).0, 0);
    let (code, stdout, _) = run(&["status", o]);
    assert_eq!(code, 0);
    assert!(
        stdout.contains("2 of 3 parts complete") && stdout.contains("part     1 of 3: missing"),
        "{stdout}"
    );
    let (code, _, err) = run(&["merge", o]);
    assert_eq!(code, 1);
    assert!(err.contains("missing part 1 of 3"), "{err}");
    // Part 1 with another master seed.
    assert_eq!(
        run(&[
            "run", spec, "-q", "--out", o, "--shard", "1/3", "--seed", "10"
        ])
        .0,
        0
    );
    let (code, _, err) = run(&["merge", o]);
    assert_eq!(code, 1);
    assert!(
        err.contains("part-00001-of-00003") && err.contains("master seed"),
        "{err}"
    );
    // A bad shard argument is a usage error.
    let (code, _, err) = run(&["run", spec, "-q", "--out", o, "--shard", "3/3"]);
    assert_eq!(code, 2, "{err}");
}

#[test]
fn the_shard_comes_from_slurm_or_kubernetes_environments() {
    use kfmc::merge::shard_from;
    use kfmc::study::Shard;
    let env = |vars: &'static [(&'static str, &'static str)]| {
        move |k: &str| {
            vars.iter()
                .find(|(n, _)| *n == k)
                .map(|(_, v)| v.to_string())
        }
    };
    let s = |index, count| Ok(Some(Shard { index, count }));
    assert_eq!(shard_from(Some("2/5"), None, &env(&[])), s(2, 5));
    assert_eq!(
        shard_from(
            None,
            None,
            &env(&[
                ("SLURM_ARRAY_TASK_ID", "3"),
                ("SLURM_ARRAY_TASK_COUNT", "4")
            ])
        ),
        s(3, 4)
    );
    // An array 10-16:2 has tasks 10, 12, 14, 16.
    assert_eq!(
        shard_from(
            None,
            None,
            &env(&[
                ("SLURM_ARRAY_TASK_ID", "14"),
                ("SLURM_ARRAY_TASK_COUNT", "4"),
                ("SLURM_ARRAY_TASK_MIN", "10"),
                ("SLURM_ARRAY_TASK_STEP", "2")
            ])
        ),
        s(2, 4)
    );
    assert_eq!(
        shard_from(None, Some(8), &env(&[("JOB_COMPLETION_INDEX", "7")])),
        s(7, 8)
    );
    assert!(shard_from(None, None, &env(&[("JOB_COMPLETION_INDEX", "7")])).is_err());
    assert!(shard_from(Some("4/4"), None, &env(&[])).is_err());
    assert_eq!(shard_from(None, None, &env(&[])), Ok(None));
}

#[test]
fn slurm_scripts_run_every_part_and_merge_after_the_array() {
    let tmp = tempfile::tempdir().unwrap();
    let spec = tmp.path().join("s.toml");
    std::fs::write(&spec, spec_text()).unwrap();
    let out = tmp.path().join("d");
    let (code, _, err) = run(&[
        "slurm",
        spec.to_str().unwrap(),
        "--shards",
        "4",
        "--partition",
        "batch",
        "--time",
        "01:00:00",
        "--cpus",
        "8",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{err}");
    let read = |f: &str| std::fs::read_to_string(out.join("slurm").join(f)).unwrap();
    let array = read("array.sbatch");
    for needle in [
        "#SBATCH --array=0-3",
        "#SBATCH --partition=batch",
        "#SBATCH --time=01:00:00",
        "#SBATCH --cpus-per-task=8",
        "--shards 4",
        " run ",
    ] {
        assert!(array.contains(needle), "missing `{needle}` in\n{array}");
    }
    assert!(read("merge.sbatch").contains(" merge "));
    assert!(read("submit.sh").contains("--dependency=afterok:$array"));
}

/// A part written by another kfmc is refused, as a resume refuses another version's
/// checkpoint: its rows may be computed differently.
#[test]
fn a_part_of_another_kfmc_version_is_refused() {
    let tmp = tempfile::tempdir().unwrap();
    let spec = tmp.path().join("s.toml");
    std::fs::write(&spec, spec_text()).unwrap();
    let spec = spec.to_str().unwrap();
    let out = tmp.path().join("d");
    let o = out.to_str().unwrap();
    for i in 0..2 {
        let shard = format!("{i}/2");
        assert_eq!(
            run(&["run", spec, "-q", "--out", o, "--shard", &shard]).0,
            0
        );
    }
    let manifest = out.join("parts/part-00001-of-00002/manifest.toml");
    let text = std::fs::read_to_string(&manifest).unwrap();
    let ours = format!("kfmc_version = \"{}\"", env!("CARGO_PKG_VERSION"));
    assert!(text.contains(&ours), "{text}");
    std::fs::write(&manifest, text.replace(&ours, "kfmc_version = \"0.0.1\"")).unwrap();
    let (code, _, err) = run(&["merge", o]);
    assert_eq!(code, 1, "{err}");
    assert!(
        err.contains("part-00001-of-00002")
            && err.contains(&format!(
                "written by kfmc 0.0.1 (this is {})",
                env!("CARGO_PKG_VERSION")
            )),
        "{err}"
    );
    assert!(!out.join("manifest.toml").exists(), "nothing is committed");
}
