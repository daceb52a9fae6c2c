//! Memory independent of the runs per cell: a cell with more runs than a spill keeps in
//! memory still gets exact across-run statistics (checked against sorting the runs table),
//! leaves no scratch file behind; `validate`'s estimate bounds the tables on disk; plans the
//! estimate or the limits refuse are refused naming the key.

mod common;

use std::path::Path;

use common::{kfmc, read};

fn run(args: &[&str]) -> (i32, String, String) {
    let o = kfmc().args(args).output().unwrap();
    (
        o.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&o.stdout).into_owned(),
        String::from_utf8_lossy(&o.stderr).into_owned(),
    )
}

/// Two filters on the linear quadrotor, 3 steps a run: cheap enough for 70,000 runs.
fn spec(out: &Path, runs: usize) -> String {
    format!(
        r#"
name = "many_runs"
master_seed = 5
runs = {runs}
output = "{}"
[model]
kind = "linear_quadrotor"
sensor = "positions"
[[scenarios]]
name = "hover"
x0 = [1.0, 0.0, 1.0, 0.0, 1.0, 0.0]
duration_s = 0.3
[[filters]]
label = "kf"
kind = "ekf"
[[filters]]
label = "open"
kind = "open_loop"
"#,
        out.display()
    )
}

/// numpy's type-7 quantile of sorted values, as kfmc documents it.
fn quantile(sorted: &[f64], q: f64) -> f64 {
    let h = (sorted.len() - 1) as f64 * q;
    let (lo, hi) = (h.floor() as usize, h.ceil() as usize);
    sorted[lo] + (h - lo as f64) * (sorted[hi] - sorted[lo])
}

#[test]
fn a_spilled_cell_summary_is_exactly_the_sorted_runs_table() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("out");
    let path = tmp.path().join("s.toml");
    // More runs than a spill keeps in memory (65,536), so the scratch path is taken.
    let runs = kfmc::spill::SPILL_ROWS + 4_464;
    std::fs::write(&path, spec(&out, runs)).unwrap();
    let (code, _, err) = run(&["run", path.to_str().unwrap(), "--quiet"]);
    assert_eq!(code, 0, "{err}");
    let leftovers: Vec<String> = std::fs::read_dir(&out)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with('.'))
        .collect();
    assert!(leftovers.is_empty(), "left behind: {leftovers:?}");

    let runs_df = read(&out.join("runs.parquet"));
    let summary = read(&out.join("summary.parquet"));
    let filters = runs_df.column("filter").unwrap().str().unwrap().clone();
    let mut checked = 0;
    for i in 0..summary.height() {
        let f = summary
            .column("filter")
            .unwrap()
            .str()
            .unwrap()
            .get(i)
            .unwrap();
        let state = summary
            .column("state")
            .unwrap()
            .str()
            .unwrap()
            .get(i)
            .unwrap();
        let col = runs_df
            .column(&format!("rmse_{state}"))
            .unwrap()
            .f64()
            .unwrap()
            .clone();
        // In run order, as the study adds them.
        let v: Vec<f64> = (0..runs_df.height())
            .filter(|&r| filters.get(r) == Some(f))
            .filter_map(|r| col.get(r))
            .collect();
        assert_eq!(v.len(), runs, "{f} {state}: every run completed");
        let n = v.len() as f64;
        let mean = v.iter().sum::<f64>() / n;
        let std = (v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0)).sqrt();
        let mut s = v.clone();
        s.sort_by(f64::total_cmp);
        let got = |c: &str| summary.column(c).unwrap().f64().unwrap().get(i).unwrap();
        let n_runs = summary
            .column("runs")
            .unwrap()
            .i64()
            .unwrap()
            .get(i)
            .unwrap();
        assert_eq!(n_runs as usize, runs);
        for (c, want) in [
            ("rmse_mean", mean),
            ("rmse_std", std),
            ("rmse_p05", quantile(&s, 0.05)),
            ("rmse_p50", quantile(&s, 0.50)),
            ("rmse_p95", quantile(&s, 0.95)),
        ] {
            assert_eq!(got(c).to_bits(), want.to_bits(), "{f} {state} {c}");
        }
        checked += 1;
    }
    assert_eq!(checked, 2 * 6, "two filters × six states");
}

/// The estimate is an upper bound on the tables as written (compressed Parquet), and not
/// a wild one: within a factor of 40 of what a modest plan wrote.
#[test]
fn the_estimate_bounds_the_tables_on_disk() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("out");
    let path = tmp.path().join("s.toml");
    let text = spec(&out, 2_000).replace("duration_s = 0.3", "duration_s = 20.0")
        + "trace_runs = 3\n[noise]\nscales = [1.0, 2.0]\n";
    // `trace_runs` belongs to the top level: move it above the first table.
    let text = text.replace("trace_runs = 3\n", "").replacen(
        "runs = 2000\n",
        "runs = 2000\ntrace_runs = 3\n",
        1,
    );
    std::fs::write(&path, &text).unwrap();
    let plan = kfmc::experiment::load(&path).unwrap();
    let estimate = plan.resources();
    let (code, stdout, err) = run(&["validate", path.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    assert!(stdout.contains("estimated peak memory"), "{stdout}");
    assert!(stdout.contains("scratch up to 0.0 B"), "{stdout}");
    let (code, _, err) = run(&["run", path.to_str().unwrap(), "--quiet"]);
    assert_eq!(code, 0, "{err}");
    let on_disk: u64 = std::fs::read_dir(&out)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "parquet"))
        .map(|p| std::fs::metadata(p).unwrap().len())
        .sum();
    let ratio = estimate.disk_bytes as f64 / on_disk as f64;
    assert!(
        (1.0..=40.0).contains(&ratio),
        "estimate {} B, on disk {on_disk} B (ratio {ratio:.2})",
        estimate.disk_bytes
    );
}

#[test]
fn plans_beyond_the_limits_are_refused_naming_the_key() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("out");
    let cases: [(String, &[&str]); 3] = [
        // Beyond the runs limit: refused at once, no allocation attempted.
        (
            spec(&out, 1_000_000_000_000),
            &["runs:", "at most 1000000000"],
        ),
        // Runs alone no longer cost memory, but tables and scratch files cost disk.
        (
            spec(&out, 1_000_000_000),
            &["(plan)", "of tables", "of scratch files", "--allow-large"],
        ),
        // The consistency tests keep per-run sums: their memory is estimated and refused.
        (
            spec(&out, 100_000_000) + "[consistency]\nalpha = 0.05\n",
            &["(plan)", "of memory", "--allow-large"],
        ),
    ];
    for (text, needles) in cases {
        let path = tmp.path().join("big.toml");
        std::fs::write(&path, &text).unwrap();
        for cmd in ["validate", "run"] {
            let (code, _, err) = run(&[cmd, path.to_str().unwrap()]);
            assert_eq!(code, 2, "{cmd}: {err}");
            assert!(err.contains("big.toml"), "names the file: {err}");
            for n in needles {
                assert!(err.contains(n), "{cmd}: missing `{n}` in {err}");
            }
        }
        assert!(!out.exists(), "nothing was started");
    }
}
