//! Figures and the HTML report, drawn from the written tables: the expected files exist and
//! are not blank, each figure shows exactly the table values it came from, and the report is
//! self-contained.

mod common;

use std::path::Path;

use common::{EKF_AND_MEAN, kfmc, repo, small_spec, spec_in_tempdir};
use kfmc::plot::{Figure, FigureKind, Mark, Tables};
use polars::prelude::*;

/// Runs a small study (40 runs: past the quantile sketch's exact phase, three noise scales,
/// divergence thresholds, one traced run) and returns (tempdir, result folder).
fn study() -> (tempfile::TempDir, std::path::PathBuf) {
    let (dir, _) = spec_in_tempdir("");
    let out = dir.path().join("res");
    let spec = dir.path().join("s.toml");
    std::fs::write(&spec, small_spec(&out, 40, "[0.5, 1.0, 2.0]", EKF_AND_MEAN)).unwrap();
    let o = kfmc()
        .args([
            "run",
            spec.to_str().unwrap(),
            "--quiet",
            "--trace-runs",
            "1",
        ])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    (dir, out)
}

fn df(dir: &Path, table: &str) -> DataFrame {
    let f = std::fs::File::open(dir.join(format!("{table}.parquet"))).unwrap();
    ParquetReader::new(f).finish().unwrap()
}

fn f64s(df: &DataFrame, c: &str) -> Vec<Option<f64>> {
    df.column(c)
        .unwrap()
        .cast(&DataType::Float64)
        .unwrap()
        .f64()
        .unwrap()
        .iter()
        .collect()
}

fn strs(df: &DataFrame, c: &str) -> Vec<String> {
    df.column(c)
        .unwrap()
        .str()
        .unwrap()
        .iter()
        .map(|s| s.unwrap_or("").to_string())
        .collect()
}

/// The points of the line labelled `label` in the panel titled `panel`.
fn line(fig: &Figure, panel: &str, label: &str) -> Vec<(f64, f64)> {
    let p = fig
        .panels
        .iter()
        .find(|p| p.title == panel)
        .unwrap_or_else(|| panic!("{}: no panel {panel}", fig.name));
    p.marks
        .iter()
        .find_map(|m| match m {
            Mark::Line {
                label: Some(l),
                points,
                ..
            } if l == label => Some(points.clone()),
            _ => None,
        })
        .unwrap_or_else(|| panic!("{}/{panel}: no line {label}", fig.name))
}

fn fig(figs: &[Figure], name: &str) -> Figure {
    figs.iter()
        .find(|f| f.name == name)
        .unwrap_or_else(|| {
            panic!(
                "no figure {name} in {:?}",
                figs.iter().map(|f| &f.name).collect::<Vec<_>>()
            )
        })
        .clone()
}

/// Rows of `df` where the string/float keys match, in table order.
fn rows(df: &DataFrame, scen: &str, noise: Option<f64>, filter: &str) -> Vec<usize> {
    let (s, f) = (strs(df, "scenario"), strs(df, "filter"));
    let n = df
        .column("noise_scale")
        .is_ok()
        .then(|| f64s(df, "noise_scale"));
    (0..df.height())
        .filter(|&i| {
            s[i] == scen
                && f[i] == filter
                && noise.is_none_or(|x| n.as_ref().is_some_and(|n| n[i] == Some(x)))
        })
        .collect()
}

#[test]
fn every_figure_kind_is_drawn_and_not_blank() {
    let (_tmp, res) = study();
    let o = kfmc()
        .args(["plot", res.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let figdir = res.join("figures");
    let expected = [
        "trajectory_basic",
        "trajectory_roll",
        "states_basic",
        "states_roll",
        "errors_basic_ns0.5",
        "errors_basic_ns1",
        "errors_roll_ns2",
        "rmse_cases_basic_ekf",
        "rmse_cases_roll_running_mean",
        "rmse_growth_basic",
        "rmse_growth_roll",
        "consistency_basic_ns1",
        "consistency_roll_ns2",
        "divergence_hist_basic",
        "divergence_hist_roll",
    ];
    for name in expected {
        let path = figdir.join(format!("{name}.png"));
        let bytes = std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        assert!(bytes.len() > 10_000, "{name}: only {} bytes", bytes.len());
        let decoder = png::Decoder::new(std::io::Cursor::new(bytes));
        let mut reader = decoder.read_info().unwrap();
        let mut buf = vec![0; reader.output_buffer_size()];
        let info = reader.next_frame(&mut buf).unwrap();
        let px = &buf[..info.buffer_size()];
        let ch = info.color_type.samples();
        let non_white = px
            .chunks(ch)
            .filter(|p| p[..3].iter().any(|&c| c < 200))
            .count();
        let coloured = px
            .chunks(ch)
            .filter(|p| p[0].abs_diff(p[2]) > 60 || p[1].abs_diff(p[2]) > 60)
            .count();
        let total = px.len() / ch;
        assert!(
            non_white * 100 > total,
            "{name}: {non_white} of {total} pixels drawn"
        );
        assert!(coloured > 200, "{name}: only {coloured} coloured pixels");
    }
    // No tuning.parquet, so no tuning figure; every file is one of the expected kinds.
    let files: Vec<String> = std::fs::read_dir(&figdir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    assert!(!files.iter().any(|f| f.starts_with("tuning")), "{files:?}");
    assert_eq!(files.len(), 2 + 2 + 6 + 4 + 2 + 6 + 2, "{files:?}");

    // --only and --format select.
    let svg_dir = res.join("svg");
    let o = kfmc()
        .args([
            "plot",
            res.to_str().unwrap(),
            "--out",
            svg_dir.to_str().unwrap(),
            "--format",
            "svg",
            "--only",
            "rmse_growth",
            "trajectory",
        ])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let mut svgs: Vec<String> = std::fs::read_dir(&svg_dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    svgs.sort();
    assert_eq!(
        svgs,
        [
            "rmse_growth_basic.svg",
            "rmse_growth_roll.svg",
            "trajectory_basic.svg",
            "trajectory_roll.svg"
        ]
    );
    let text = std::fs::read_to_string(svg_dir.join("rmse_growth_basic.svg")).unwrap();
    assert!(text.contains("RMSE of thetadot") && text.contains("<polyline"));
}

#[test]
fn figures_show_the_table_values() {
    let (_tmp, res) = study();
    let t = Tables::load(&res).unwrap();
    assert_eq!(t.filters, ["ekf", "running_mean"]);

    // rmse_growth: the mean line is summary.rmse_mean, by noise scale.
    let s = df(&res, "summary");
    let g = fig(
        &FigureKind::RmseGrowth.series(&t).unwrap(),
        "rmse_growth_roll",
    );
    for (filter, state) in [("ekf", "x"), ("running_mean", "theta")] {
        let st = strs(&s, "state");
        let want: Vec<(f64, f64)> = rows(&s, "roll", None, filter)
            .into_iter()
            .filter(|&i| st[i] == state)
            .map(|i| {
                (
                    f64s(&s, "noise_scale")[i].unwrap(),
                    f64s(&s, "rmse_mean")[i].unwrap(),
                )
            })
            .collect();
        assert_eq!(want.len(), 3);
        assert_eq!(
            line(
                &g,
                &format!("RMSE of {state}"),
                &format!("{filter} mean, p5–p95")
            ),
            want
        );
    }
    assert!(
        g.panels[0].log_y && !g.panels[2].log_y,
        "log y for x and xdot only"
    );

    // errors: the median line is steps.abs_err_p50_<s> against t.
    let st = df(&res, "steps");
    let e = fig(&FigureKind::Errors.series(&t).unwrap(), "errors_basic_ns1");
    let r = rows(&st, "basic", Some(1.0), "ekf");
    // The quantiles live on a grid of at most ~200 steps (metrics::ABS_ERR_MAX_POINTS):
    // 201 samples here → every 2nd step, null in between.
    let want: Vec<(f64, f64)> = r
        .iter()
        .filter_map(|&i| Some((f64s(&st, "t")[i]?, f64s(&st, "abs_err_p50_theta")[i]?)))
        .collect();
    assert_eq!(want.len(), r.len().div_ceil(2), "quantile grid");
    assert_eq!(line(&e, "|e| of theta", "ekf median, p5–p95"), want);
    // p05 ≤ p50 ≤ p95 wherever defined, and |e| ≥ 0.
    for s in ["x", "theta"] {
        let (lo, mid, hi) = (
            f64s(&st, &format!("abs_err_p05_{s}")),
            f64s(&st, &format!("abs_err_p50_{s}")),
            f64s(&st, &format!("abs_err_p95_{s}")),
        );
        for i in 0..st.height() {
            let (Some(a), Some(b), Some(c)) = (lo[i], mid[i], hi[i]) else {
                assert!(lo[i].is_none() && mid[i].is_none() && hi[i].is_none());
                continue;
            };
            assert!(0.0 <= a && a <= b && b <= c, "row {i}: {a} {b} {c}");
        }
    }

    // consistency: ANEES of the EKF, and no running-mean curve (it has no covariance).
    let c = fig(
        &FigureKind::Consistency.series(&t).unwrap(),
        "consistency_roll_ns2",
    );
    let r = rows(&st, "roll", Some(2.0), "ekf");
    let (tt, anees) = (f64s(&st, "t"), f64s(&st, "anees"));
    let want: Vec<(f64, f64)> = r
        .iter()
        .filter_map(|&i| Some((tt[i]?, anees[i]?)))
        .collect();
    assert_eq!(line(&c, "ANEES", "ekf"), want);
    assert!(
        !c.panels[0]
            .marks
            .iter()
            .any(|m| matches!(m, Mark::Line { label: Some(l), .. } if l == "running_mean"))
    );

    // states: the EKF estimate of y is traces.est_y of the first traced run.
    let tr = df(&res, "traces");
    let sfig = fig(&FigureKind::States.series(&t).unwrap(), "states_basic");
    let r = rows(&tr, "basic", Some(0.5), "ekf");
    let (tt, est) = (f64s(&tr, "t"), f64s(&tr, "est_y"));
    let want: Vec<(f64, f64)> = r
        .iter()
        .map(|&i| (tt[i].unwrap(), est[i].unwrap()))
        .collect();
    assert_eq!(line(&sfig, "y", "ekf"), want);
    // The running mean has no variance, hence one band (the EKF's) per panel.
    let bands = sfig.panels[0]
        .marks
        .iter()
        .filter(|m| matches!(m, Mark::Band { .. }))
        .count();
    assert_eq!(bands, 1);

    // divergence_hist: the bars count every run that crossed; the legend the others.
    let dr = df(&res, "divergence_runs");
    let h = fig(
        &FigureKind::DivergenceHist.series(&t).unwrap(),
        "divergence_hist_roll",
    );
    let (dst, dsc) = (strs(&dr, "state"), f64s(&dr, "divergence_scale"));
    for (pi, state) in t.states.iter().enumerate() {
        for f in ["ekf", "running_mean"] {
            let r: Vec<usize> = rows(&dr, "roll", None, f)
                .into_iter()
                .filter(|&i| dst[i] == *state)
                .collect();
            let crossed = r.iter().filter(|&&i| dsc[i].is_some()).count();
            let (label, total) = h.panels[pi]
                .marks
                .iter()
                .find_map(|m| match m {
                    Mark::Bars {
                        label: Some(l),
                        bars,
                        ..
                    } if l.starts_with(&format!("{f} (")) => {
                        Some((l.clone(), bars.iter().map(|b| b.y).sum::<f64>()))
                    }
                    _ => None,
                })
                .unwrap();
            assert_eq!(total, crossed as f64, "{state}/{f}");
            assert!(
                label.contains(&format!(
                    "{} of {} runs never diverged",
                    r.len() - crossed,
                    r.len()
                )),
                "{label}"
            );
        }
    }
}

#[test]
fn the_report_is_self_contained() {
    let (_tmp, res) = study();
    let o = kfmc()
        .args(["report", res.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let html = std::fs::read_to_string(res.join("report.html")).unwrap();
    for tag in ["html", "head", "body", "table", "figure"] {
        let open = html.matches(&format!("<{tag}")).count();
        let close = html.matches(&format!("</{tag}>")).count();
        assert!(
            open > 0 && open == close,
            "<{tag}>: {open} opened, {close} closed"
        );
    }
    for tag in ["html", "head", "body"] {
        assert_eq!(html.matches(&format!("<{tag}")).count(), 1, "{tag}");
    }
    let t = Tables::load(&res).unwrap();
    let n_figs: usize = FigureKind::ALL
        .iter()
        .map(|k| k.series(&t).unwrap().len())
        .sum();
    assert_eq!(n_figs, 24);
    assert_eq!(html.matches("<svg").count(), n_figs);
    assert_eq!(html.matches("</svg>").count(), n_figs);
    for bad in ["http://", "https://", "src=\"", "<link", "<script", "url("] {
        assert!(!html.contains(bad), "the report contains {bad}");
    }
    // Spec, provenance, RMSE and divergence sections, with escaped text.
    assert!(html.contains("rmse_thresholds"));
    assert!(html.contains("master seed"));
    assert!(html.contains("<h2>Divergence points</h2>"));
    assert!(html.contains("RMSE over runs"));
    assert!(
        !html.contains("<h2>Consistency verdicts</h2>"),
        "no consistency.parquet"
    );
}

#[test]
fn a_folder_without_tables_is_a_clear_error() {
    let tmp = tempfile::tempdir().unwrap();
    for cmd in ["plot", "report"] {
        let o = kfmc()
            .args([cmd, tmp.path().to_str().unwrap()])
            .output()
            .unwrap();
        assert_eq!(o.status.code(), Some(1), "{cmd}");
        let err = String::from_utf8_lossy(&o.stderr);
        // Readers check the folder's commit record before any table.
        assert!(
            err.contains("not a complete kfmc result folder") && err.contains("manifest.toml"),
            "{cmd}: {err}"
        );
    }
}

#[test]
fn filter_variants_sharing_a_label_are_separate_series_in_every_figure() {
    // linear_q_scaling: one label `kf` with eight q_scale values.
    let tmp = tempfile::tempdir().unwrap();
    let res = tmp.path().join("q");
    let o = kfmc()
        .args([
            "run",
            repo()
                .join("experiments/linear_q_scaling.toml")
                .to_str()
                .unwrap(),
            "--runs",
            "8",
            "--trace-runs",
            "1",
            "--quiet",
            "--out",
        ])
        .arg(&res)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let t = Tables::load(&res).unwrap();
    let want: Vec<String> = [0.1, 0.5, 1.0, 2.0, 10.0, 100.0, 2500.0, 5000.0]
        .iter()
        .map(|q| format!("kf Q×{q}"))
        .collect();
    let mut seen = std::collections::BTreeSet::new();
    for kind in FigureKind::ALL {
        for fig in kind.series(&t).unwrap() {
            for panel in &fig.panels {
                // Within a panel, no two lines or bands share a label: each variant is its
                // own series (one legend entry, one colour), never one line joined across.
                let mut labels: Vec<&str> = panel
                    .marks
                    .iter()
                    .filter_map(|m| match m {
                        Mark::Line { label: Some(l), .. } | Mark::Band { label: Some(l), .. } => {
                            Some(l.as_str())
                        }
                        _ => None,
                    })
                    .collect();
                let n = labels.len();
                labels.sort();
                labels.dedup();
                assert_eq!(
                    labels.len(),
                    n,
                    "{}: {} repeats a series label",
                    fig.name,
                    panel.title
                );
                for l in labels {
                    if l.starts_with("kf") {
                        seen.insert(l.to_string());
                    }
                }
            }
        }
    }
    for w in &want {
        assert!(
            seen.iter().any(|s| s.starts_with(w.as_str())),
            "no series labelled `{w}`; seen {seen:?}"
        );
    }
}
