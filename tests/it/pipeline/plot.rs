//! Figures and the HTML report, drawn from the written tables: the expected files exist and
//! are not blank, each figure shows exactly the table values it came from, and the report is
//! self-contained.

use std::path::Path;

use crate::common::{EKF_AND_MEAN, f64s, kfmc, repo, small_spec, spec_in_tempdir, strs};
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

/// The points of the line labelled `label` in the panel titled `panel`.
fn line(fig: &Figure, panel: &str, label: &str) -> Vec<(f64, f64)> {
    let p = fig
        .panels
        .iter()
        .find(|p| p.title == panel || p.title.starts_with(&format!("{panel} (")))
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

    // consistency: ANEES of the EKF from step 1 on (step 0 is the prior), and no
    // running-mean curve (it has no covariance).
    let c = fig(
        &FigureKind::Consistency.series(&t).unwrap(),
        "consistency_roll_ns2",
    );
    let r = rows(&st, "roll", Some(2.0), "ekf");
    let (tt, anees, step) = (f64s(&st, "t"), f64s(&st, "anees"), f64s(&st, "step"));
    let want: Vec<(f64, f64)> = r
        .iter()
        .filter(|&&i| step[i] != Some(0.0))
        .filter_map(|&i| Some((tt[i]?, anees[i]?)))
        .collect();
    assert_eq!(want.len(), r.len() - 1);
    assert_eq!(line(&c, "ANEES", "ekf"), want);
    assert!(
        !c.panels[0]
            .marks
            .iter()
            .any(|m| matches!(m, Mark::Line { label: Some(l), .. } if l == "running_mean"))
    );

    // states: the EKF's error of y is traces.truth_y − est_y of the first traced run at the
    // nominal noise scale ×1 (the sweep is 0.5, 1, 2), and its band is ±3·sqrt(var_y)
    // around 0.
    let tr = df(&res, "traces");
    let sfig = fig(&FigureKind::States.series(&t).unwrap(), "states_basic");
    assert!(
        sfig.title.contains("run 0, noise ×1)") && sfig.title.starts_with("basic: "),
        "{}",
        sfig.title
    );
    let r = rows(&tr, "basic", Some(1.0), "ekf");
    let (tt, truth, est, var) = (
        f64s(&tr, "t"),
        f64s(&tr, "truth_y"),
        f64s(&tr, "est_y"),
        f64s(&tr, "var_y"),
    );
    let (runs, steps) = (f64s(&tr, "run"), f64s(&tr, "step"));
    // From step 1: step 0 is the prior.
    let r: Vec<usize> = r
        .into_iter()
        .filter(|&i| runs[i] == Some(0.0) && steps[i] != Some(0.0))
        .collect();
    let want: Vec<(f64, f64)> = r
        .iter()
        .map(|&i| (tt[i].unwrap(), truth[i].unwrap() - est[i].unwrap()))
        .collect();
    assert_eq!(line(&sfig, "y", "ekf"), want);
    let y_panel = sfig.panels.iter().find(|p| p.title == "y").unwrap();
    let band = y_panel
        .marks
        .iter()
        .find_map(|m| match m {
            Mark::Band { points, .. } => Some(points.clone()),
            _ => None,
        })
        .unwrap();
    let sd = var[r[5]].unwrap().sqrt();
    assert_eq!(band[5], (tt[r[5]].unwrap(), -3.0 * sd, 3.0 * sd));
    // The running mean has no variance, hence one band (the EKF's) per panel.
    let bands = sfig.panels[0]
        .marks
        .iter()
        .filter(|m| matches!(m, Mark::Band { .. }))
        .count();
    assert_eq!(bands, 1);
    // The trajectory shows the same cell, and says so.
    let traj = fig(
        &FigureKind::Trajectory.series(&t).unwrap(),
        "trajectory_roll",
    );
    assert!(traj.title.ends_with("(run 0, noise ×1)"), "{}", traj.title);
    let r = rows(&tr, "roll", Some(1.0), "ekf");
    let (tx, ty) = (f64s(&tr, "truth_x"), f64s(&tr, "truth_y"));
    let want: Vec<(f64, f64)> = r
        .iter()
        .filter(|&&i| runs[i] == Some(0.0))
        .map(|&i| (tx[i].unwrap(), ty[i].unwrap()))
        .collect();
    assert_eq!(line(&traj, "x–y plane", "truth"), want);

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
    assert!(html.contains("RMSE over runs"));
    assert!(
        !html.contains("id=\"verdicts\""),
        "no consistency.parquet, no verdict section"
    );
    // A study's order: the answer (RMSE) first, then the figures by scenario, the divergence
    // table, provenance; the spec folded away; a contents list linking every scenario.
    let at = |needle: &str| {
        html.find(needle)
            .unwrap_or_else(|| panic!("the report lacks {needle}"))
    };
    assert!(at("<h2 id=\"rmse\">") < at("<h2 id=\"figures\">"));
    assert!(at("<h2 id=\"figures\">") < at("<h2 id=\"divergence\">"));
    assert!(at("<h2 id=\"divergence\">") < at("<h2 id=\"provenance\">"));
    assert!(at("<details><summary>Spec") > at("<h2 id=\"provenance\">"));
    for (i, s) in ["basic", "roll"].iter().enumerate() {
        assert!(html.contains(&format!("<a href=\"#scenario-{i}\">{s}</a>")));
        assert!(html.contains(&format!("<h3 id=\"scenario-{i}\">{s}</h3>")));
    }
    // Human-readable start time and the command that reproduces the tables.
    assert!(html.contains(" UTC</td>"));
    assert!(html.contains("kfmc run ") && html.contains(" --seed 11 --runs 40 --out "));
    // RMSE headers carry units; a column has one number of decimals.
    assert!(html.contains("<th>x <span class=\"unit\">[m]</span></th>"));
    assert!(html.contains("<meta name=\"viewport\"") && html.contains("@media print"));
}

#[test]
fn the_report_of_a_consistency_study_opens_with_the_verdicts() {
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
            "6",
            "--quiet",
            "--out",
        ])
        .arg(&res)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let o = kfmc()
        .args(["report", res.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let html = std::fs::read_to_string(res.join("report.html")).unwrap();
    let verdicts = html.find("<h2 id=\"verdicts\">").expect("verdict section");
    assert!(verdicts < html.find("<h2 id=\"rmse\">").unwrap());
    assert!(verdicts < html.find("<h2 id=\"figures\">").unwrap());
    // One verdict row per variant, each coloured by the consistency table's own pass flag.
    let c = df(&res, "consistency");
    let (test, filt) = (strs(&c, "test"), f64s(&c, "q_scale"));
    let pass: Vec<Option<bool>> = c.column("pass").unwrap().bool().unwrap().iter().collect();
    let table = &html[html.find("id=\"verdict-table\"").unwrap()..];
    let table = &table[..table.find("</table>").unwrap()];
    let body_rows: Vec<&str> = table.split("<tr>").skip(2).collect();
    let verdict_rows: Vec<usize> = (0..c.height()).filter(|&i| test[i] == "verdict").collect();
    assert_eq!(body_rows.len(), verdict_rows.len());
    assert_eq!(verdict_rows.len(), 8);
    for (row, &i) in body_rows.iter().zip(&verdict_rows) {
        let q = filt[i].unwrap();
        assert!(row.contains(&format!("<td>kf Q×{q}</td>")), "{row}");
        let class = if pass[i] == Some(true) {
            "pass"
        } else {
            "fail"
        };
        assert!(
            row.contains(&format!("<td class=\"{class}\"><b>")),
            "q {q}: {row}"
        );
    }
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

/// linear_q_scaling (one label `kf`, eight `q_scale` values) with two noise scales and RMSE
/// thresholds, so that every per-cell figure kind has something to draw.
fn q_scaling_spec(out: &Path) -> String {
    let base = std::fs::read_to_string(repo().join("experiments/linear_q_scaling.toml")).unwrap();
    let base = base
        .lines()
        .filter(|l| !l.starts_with("output") && !l.starts_with("runs"))
        .collect::<Vec<_>>()
        .join("\n");
    let base = base.replace("duration_s = 40.0", "duration_s = 4.0");
    format!(
        "output = \"{}\"\nruns = 8\ntrace_runs = 1\n{base}\n[noise]\nscales = [1.0, 2.0]\n[divergence]\nrmse_thresholds = [0.5, 0.5, 0.5, 0.5, 0.5, 0.5]\n",
        out.display()
    )
}

/// Labels of the filter series (lines, bands, bars) of a panel.
fn series_labels(panel: &kfmc::plot::Panel) -> Vec<String> {
    panel
        .marks
        .iter()
        .filter_map(|m| match m {
            Mark::Line { label: Some(l), .. }
            | Mark::Band { label: Some(l), .. }
            | Mark::Bars { label: Some(l), .. } => Some(l.clone()),
            _ => None,
        })
        .collect()
}

#[test]
fn filter_variants_sharing_a_label_are_separate_series_in_every_figure() {
    let tmp = tempfile::tempdir().unwrap();
    let res = tmp.path().join("q");
    let spec = tmp.path().join("q.toml");
    std::fs::write(&spec, q_scaling_spec(&res)).unwrap();
    let o = kfmc()
        .args(["run", spec.to_str().unwrap(), "--quiet"])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    // The tuning figure comes from `kfmc tune` on the same spec (one search per noise scale).
    let tuned = tmp.path().join("tuned");
    let o = kfmc()
        .args([
            "tune",
            spec.to_str().unwrap(),
            "--quiet",
            "--runs",
            "4",
            "--out",
        ])
        .arg(&tuned)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));

    let qs = [0.1, 0.5, 1.0, 2.0, 10.0, 100.0, 2500.0, 5000.0];
    let want: Vec<String> = qs.iter().map(|q| format!("kf Q×{q}")).collect();
    let t = Tables::load(&res).unwrap();
    assert_eq!(t.filters, want, "one variant per q_scale, in spec order");
    let figs = kfmc::plot::all_figures(&t, &[]).unwrap();
    let mut kinds = std::collections::BTreeSet::new();
    for fig in &figs {
        kinds.insert(fig.kind);
        // Every figure renders (to pixels, as `kfmc plot` would write it).
        let (px, w, h) = kfmc::plot::render::to_rgb(fig).unwrap();
        assert_eq!(px.len(), (w * h * 3) as usize);
        for panel in &fig.panels {
            let labels = series_labels(panel);
            // No two series of a panel share a label: each variant is its own series (one
            // legend entry, one colour), never one line joined across variants.
            let mut unique = labels.clone();
            unique.sort();
            unique.dedup();
            assert_eq!(unique.len(), labels.len(), "{}: {}", fig.name, panel.title);
            // And every variant has its series, with its own label, in every panel that draws
            // filters (the ANIS panel: all eight, the ANEES panel: all eight, …).
            for w in &want {
                let n = labels
                    .iter()
                    .filter(|l| *l == w || l.starts_with(&format!("{w} ")))
                    .count();
                assert!(
                    n >= 1,
                    "{} / {}: no series for `{w}` in {labels:?}",
                    fig.name,
                    panel.title
                );
            }
            // Distinct variants, distinct colours.
            let mut inks: Vec<String> = panel
                .marks
                .iter()
                .filter_map(|m| match m {
                    Mark::Line {
                        label: Some(l),
                        ink,
                        ..
                    } if l.starts_with("kf Q×") => Some(format!("{ink:?}")),
                    _ => None,
                })
                .collect();
            let n = inks.len();
            inks.sort();
            inks.dedup();
            assert_eq!(inks.len(), n, "{}: {}", fig.name, panel.title);
        }
    }
    // L1's positions x, y, z (z up) make a route, not a plane alone.
    for k in [
        FigureKind::Route,
        FigureKind::States,
        FigureKind::Errors,
        FigureKind::RmseCases,
        FigureKind::RmseGrowth,
        FigureKind::Consistency,
        FigureKind::DivergenceHist,
        FigureKind::BlockConsistency,
    ] {
        assert!(kinds.contains(&k), "no {k:?} figure");
    }
    // rmse_cases: one file for the label, eight bar series side by side in each noise case.
    let cases = fig(&figs, "rmse_cases_hover_kf");
    let bars: Vec<(f64, f64)> = cases.panels[0]
        .marks
        .iter()
        .filter_map(|m| match m {
            Mark::Bars { bars, .. } => Some((bars[0].x0, bars[0].x1)),
            _ => None,
        })
        .collect();
    assert_eq!(bars.len(), 8);
    assert!(
        bars.windows(2).all(|w| w[0].1 <= w[1].0),
        "bars overlap: {bars:?}"
    );
    // rmse_growth: each variant's line is its own summary rows, by noise scale.
    let s = df(&res, "summary");
    let (st, q, mean, nz) = (
        strs(&s, "state"),
        f64s(&s, "q_scale"),
        f64s(&s, "rmse_mean"),
        f64s(&s, "noise_scale"),
    );
    let g = fig(&figs, "rmse_growth_hover");
    for (qv, label) in qs.iter().zip(&want) {
        let rows: Vec<(f64, f64)> = (0..s.height())
            .filter(|&i| st[i] == "x" && q[i] == Some(*qv))
            .map(|i| (nz[i].unwrap(), mean[i].unwrap()))
            .collect();
        assert_eq!(rows.len(), 2);
        assert_eq!(
            line(&g, "RMSE of x", &format!("{label} mean, p5–p95")),
            rows
        );
    }

    // Tuning: one curve per noise scale (each its own search), none joined across them.
    let tt = Tables::load(&tuned).unwrap();
    let tf = kfmc::plot::all_figures(&tt, &[FigureKind::Tuning]).unwrap();
    let tuning = fig(&tf, "tuning_hover");
    kfmc::plot::render::to_rgb(&tuning).unwrap();
    let curves: Vec<&Vec<(f64, f64)>> = tuning.panels[0]
        .marks
        .iter()
        .filter_map(|m| match m {
            Mark::Line {
                label: Some(l),
                points,
                ..
            } if l.starts_with("kf") => Some(points),
            _ => None,
        })
        .collect();
    assert_eq!(
        series_labels(&tuning.panels[0]).len(),
        2,
        "kf at noise ×1 and ×2"
    );
    assert_eq!(curves.len(), 2);
    for c in curves {
        assert!(c.windows(2).all(|w| w[0].0 < w[1].0), "a sawtooth: {c:?}");
    }
    // ANEES from 0.001× to 1000× Q spans decades: a log axis.
    assert!(tuning.panels[0].log_y, "{}", tuning.panels[0].title);
}

#[test]
fn figure_files_never_collide() {
    // The spec checker refuses names whose figures would meet (tests/bad_specs); folders
    // merged or written by other tools can still hold them, so the plot names every figure
    // uniquely, also ignoring case (macOS and Windows folders), from the figure's own title.
    let figure = |name: &str, title: &str| Figure {
        kind: FigureKind::Trajectory,
        name: name.into(),
        scenario: title.split(':').next().unwrap().into(),
        title: title.into(),
        panels: Vec::new(),
    };
    let make = || {
        vec![
            figure("trajectory_x_y", "x/y: trajectory"),
            figure("trajectory_x_y", "x_y: trajectory"),
            figure("trajectory_X_y", "X_y: trajectory"),
            figure("trajectory_z", "z: trajectory"),
        ]
    };
    let mut figs = make();
    kfmc::plot::unique_names(&mut figs);
    let mut names: Vec<String> = figs.iter().map(|f| f.name.to_lowercase()).collect();
    names.sort();
    names.dedup();
    assert_eq!(names.len(), 4, "{figs:?}");
    assert_eq!(
        figs[3].name, "trajectory_z",
        "names without a clash stay as they are"
    );
    assert!(
        figs[..3]
            .iter()
            .all(|f| f.name.len() == "trajectory_x_y".len() + 9)
    );
    // A figure's name depends on its own title, not on its position among the others.
    let mut reversed = make();
    reversed.reverse();
    kfmc::plot::unique_names(&mut reversed);
    reversed.reverse();
    assert_eq!(
        figs.iter().map(|f| &f.name).collect::<Vec<_>>(),
        reversed.iter().map(|f| &f.name).collect::<Vec<_>>()
    );
    // Identical titles too: a running number.
    let mut same = vec![figure("a", "t: x"), figure("a", "t: x")];
    kfmc::plot::unique_names(&mut same);
    assert_ne!(same[0].name, same[1].name);
}

/// The 3×3 inverse by the adjugate: independent of the Cholesky solve in `plot::blocks`.
fn inv3(m: [[f64; 3]; 3]) -> [[f64; 3]; 3] {
    let c =
        |r0: usize, r1: usize, c0: usize, c1: usize| m[r0][c0] * m[r1][c1] - m[r0][c1] * m[r1][c0];
    let adj = [
        [c(1, 2, 1, 2), -c(0, 2, 1, 2), c(0, 1, 1, 2)],
        [-c(1, 2, 0, 2), c(0, 2, 0, 2), -c(0, 1, 0, 2)],
        [c(1, 2, 0, 1), -c(0, 2, 0, 1), c(0, 1, 0, 1)],
    ];
    let det = m[0][0] * adj[0][0] + m[0][1] * adj[1][0] + m[0][2] * adj[2][0];
    adj.map(|r| r.map(|v| v / det))
}

#[test]
fn block_anees_is_the_traced_runs_mean_of_the_block_nees() {
    let tmp = tempfile::tempdir().unwrap();
    let res = drone_maneuver_study(tmp.path(), 3, 3);
    let t = Tables::load(&res).unwrap();
    let bl = kfmc::plot::blocks::blocks(&t);
    let names: Vec<(&str, Vec<String>)> = bl
        .iter()
        .map(|b| (b.name.as_str(), b.quantities.clone()))
        .collect();
    let q = |v: &[&str]| v.iter().map(|s| s.to_string()).collect::<Vec<_>>();
    assert_eq!(
        names,
        [
            ("position", q(&["px", "py", "pz"])),
            ("velocity", q(&["vx", "vy", "vz"])),
            ("attitude", q(&["roll", "pitch", "yaw"])),
        ]
    );
    let cells = kfmc::plot::blocks::block_cells(&t, &bl).unwrap();
    assert_eq!(cells.len(), 1);

    // Independently, from the trace columns: per step ≥ 1, the mean over the 3 runs of
    // eᵀP⁻¹e, the attitude's e the rotation error log(R̂ᵀR) in degrees (the drone's default),
    // here from the matrix formula (angle and axis from the trace and the antisymmetric part).
    let tr = df(&res, "traces");
    let (step, time) = (f64s(&tr, "step"), f64s(&tr, "t"));
    let order = ["px", "py", "pz", "vx", "vy", "vz", "roll", "pitch", "yaw"];
    for (bi, b) in bl.iter().enumerate() {
        let mut by_step: std::collections::BTreeMap<i64, (f64, f64, usize)> = Default::default();
        let e: Vec<Vec<Option<f64>>> = b
            .quantities
            .iter()
            .map(|s| {
                let (x, xh) = (
                    f64s(&tr, &format!("truth_{s}")),
                    f64s(&tr, &format!("est_{s}")),
                );
                x.iter()
                    .zip(&xh)
                    .map(|(a, b)| Some((*a)? - (*b)?))
                    .collect()
            })
            .collect();
        let p_col = |a: &str, c: &str| {
            let (ia, ic) = (
                order.iter().position(|x| *x == a).unwrap(),
                order.iter().position(|x| *x == c).unwrap(),
            );
            let (hi, lo) = if ia >= ic { (a, c) } else { (c, a) };
            f64s(&tr, &format!("P_{hi}_{lo}"))
        };
        let p: Vec<Vec<Vec<Option<f64>>>> = b
            .quantities
            .iter()
            .map(|a| b.quantities.iter().map(|c| p_col(a, c)).collect())
            .collect();
        for r in 0..tr.height() {
            let k = step[r].unwrap();
            if k < 1.0 {
                continue;
            }
            let mut ev = [0.0; 3];
            for (j, col) in e.iter().enumerate() {
                ev[j] = col[r].unwrap();
            }
            if b.name == "attitude" {
                let angles = |pre: &str| -> [f64; 3] {
                    std::array::from_fn(|j| {
                        f64s(&tr, &format!("{pre}_{}", b.quantities[j]))[r]
                            .unwrap()
                            .to_radians()
                    })
                };
                ev = rotation_error_deg(
                    &euler_matrix(angles("est")),
                    &euler_matrix(angles("truth")),
                );
            }
            let m: [[f64; 3]; 3] =
                std::array::from_fn(|i| std::array::from_fn(|j| p[i][j][r].unwrap()));
            let mi = inv3(m);
            let nees: f64 = (0..3)
                .map(|i| (0..3).map(|j| ev[i] * mi[i][j] * ev[j]).sum::<f64>())
                .sum();
            let s = by_step
                .entry(k as i64)
                .or_insert((time[r].unwrap(), 0.0, 0));
            s.1 += nees;
            s.2 += 1;
        }
        let got = &cells[0].series[bi];
        assert_eq!(got.len(), by_step.len(), "{}", b.name);
        for (g, (_, w)) in got.iter().zip(&by_step) {
            assert_eq!((g.0, g.2), (w.0, w.2), "{}", b.name);
            let want = w.1 / w.2 as f64;
            assert!(
                (g.1 - want).abs() <= 1e-9 * want.abs().max(1.0),
                "{} at t = {}: {} against {want}",
                b.name,
                g.0,
                g.1
            );
        }
    }
    // The figure draws these series, one panel per block.
    let figs = FigureKind::BlockConsistency.series(&t).unwrap();
    assert_eq!(figs.len(), 1);
    assert_eq!(figs[0].panels.len(), 3);
    // The route: the GPS fixes of the first traced run, as many as its non-null z_gps_px.
    let route = FigureKind::Route.series(&t).unwrap();
    assert_eq!(route.len(), 1, "the drone's route figure");
    let run = f64s(&tr, "run");
    let first = run.iter().flatten().copied().fold(f64::INFINITY, f64::min);
    let gps = f64s(&tr, "z_gps_px");
    let want = (0..tr.height())
        .filter(|&i| run[i] == Some(first) && gps[i].is_some())
        .count();
    let fixes = route[0].panels[0]
        .marks
        .iter()
        .find_map(|m| match m {
            Mark::Scatter { points, .. } => Some(points.len()),
            _ => None,
        })
        .unwrap();
    assert_eq!(fixes, want);
    assert_eq!(want, 31, "10 Hz over 3 s, from t = 0");
}

/// R_z(ψ) R_y(θ) R_x(φ) for (φ, θ, ψ) in radians, multiplied out.
fn euler_matrix(e: [f64; 3]) -> [[f64; 3]; 3] {
    let rx = |a: f64| {
        [
            [1.0, 0.0, 0.0],
            [0.0, a.cos(), -a.sin()],
            [0.0, a.sin(), a.cos()],
        ]
    };
    let ry = |a: f64| {
        [
            [a.cos(), 0.0, a.sin()],
            [0.0, 1.0, 0.0],
            [-a.sin(), 0.0, a.cos()],
        ]
    };
    let rz = |a: f64| {
        [
            [a.cos(), -a.sin(), 0.0],
            [a.sin(), a.cos(), 0.0],
            [0.0, 0.0, 1.0],
        ]
    };
    let mul = |a: [[f64; 3]; 3], b: [[f64; 3]; 3]| -> [[f64; 3]; 3] {
        std::array::from_fn(|i| std::array::from_fn(|j| (0..3).map(|k| a[i][k] * b[k][j]).sum()))
    };
    mul(rz(e[2]), mul(ry(e[1]), rx(e[0])))
}

/// log(R̂ᵀR) in degrees for rotations well below 180° apart: the angle from the trace and
/// the antisymmetric part (sin and cos of the angle), the axis from the latter.
fn rotation_error_deg(est: &[[f64; 3]; 3], truth: &[[f64; 3]; 3]) -> [f64; 3] {
    let d: [[f64; 3]; 3] = std::array::from_fn(|i| {
        std::array::from_fn(|j| (0..3).map(|k| est[k][i] * truth[k][j]).sum())
    });
    let w = [d[2][1] - d[1][2], d[0][2] - d[2][0], d[1][0] - d[0][1]];
    let s = (w[0] * w[0] + w[1] * w[1] + w[2] * w[2]).sqrt() / 2.0;
    let angle = s.atan2((d[0][0] + d[1][1] + d[2][2] - 1.0) / 2.0);
    let k = if s < 1e-12 { 0.5 } else { angle / (2.0 * s) };
    w.map(|x| (x * k).to_degrees())
}

/// The folder's manifest as an older kfmc wrote it: without position roles or fixes.
fn strip_roles(res: &Path) {
    let path = res.join("manifest.toml");
    let mut m: toml::Table = std::fs::read_to_string(&path).unwrap().parse().unwrap();
    for q in m["quantities"].as_array_mut().unwrap() {
        let q = q.as_table_mut().unwrap();
        q.remove("position");
        q.remove("fixes");
    }
    std::fs::write(&path, toml::to_string(&m).unwrap()).unwrap();
}

/// The quantities of a folder's manifest: (name, position role, `sensor:component` fixes).
fn roles(res: &Path) -> Vec<(String, Option<String>, Vec<String>)> {
    let text = std::fs::read_to_string(res.join("manifest.toml")).unwrap();
    let m: toml::Table = text.parse().unwrap();
    m["quantities"]
        .as_array()
        .unwrap()
        .iter()
        .map(|q| {
            let s = |v: &toml::Value, k: &str| v.get(k).and_then(|x| x.as_str()).map(String::from);
            let fixes = q
                .get("fixes")
                .and_then(|f| f.as_array())
                .map(|f| {
                    f.iter()
                        .map(|e| {
                            format!("{}:{}", s(e, "sensor").unwrap(), s(e, "component").unwrap())
                        })
                        .collect()
                })
                .unwrap_or_default();
            (s(q, "name").unwrap(), s(q, "position"), fixes)
        })
        .collect()
}

/// The scatter marks (label, points) of a panel.
fn scatters(panel: &kfmc::plot::Panel) -> Vec<(String, Vec<(f64, f64)>)> {
    panel
        .marks
        .iter()
        .filter_map(|m| match m {
            Mark::Scatter {
                label: Some(l),
                points,
                ..
            } => Some((l.clone(), points.clone())),
            _ => None,
        })
        .collect()
}

#[test]
fn a_linear_system_with_declared_positions_gets_a_trajectory_with_its_fixes() {
    let tmp = tempfile::tempdir().unwrap();
    let res = tmp.path().join("cv");
    let spec = tmp.path().join("cv.toml");
    // linear_cv_target: states px, vx, py, vy with `positions = ["px", "py"]`, px and py
    // measured directly at 1 Hz (a sensor group), vx and vy at every step.
    let base = std::fs::read_to_string(repo().join("experiments/linear_cv_target.toml")).unwrap();
    assert!(base.contains("positions = [\"px\", \"py\"]"));
    let base: String = base
        .lines()
        .filter(|l| !l.starts_with("output") && !l.starts_with("runs"))
        .collect::<Vec<_>>()
        .join("\n");
    std::fs::write(
        &spec,
        format!(
            "output = \"{}\"\nruns = 2\ntrace_runs = 1\n{base}\n",
            res.display()
        ),
    )
    .unwrap();
    let o = kfmc()
        .args(["run", spec.to_str().unwrap(), "--quiet"])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    // The manifest records the roles and the fixes found in H.
    let m = roles(&res);
    let role = |q: &str| {
        let e = m.iter().find(|e| e.0 == q).unwrap();
        (e.1.clone(), e.2.clone())
    };
    assert_eq!(role("px"), (Some("x".into()), vec!["px/py:px".to_string()]));
    assert_eq!(role("py"), (Some("y".into()), vec!["px/py:py".to_string()]));
    assert_eq!(role("vx"), (None, vec![]));

    let t = Tables::load(&res).unwrap();
    let figs = kfmc::plot::all_figures(&t, &[FigureKind::Trajectory, FigureKind::Route]).unwrap();
    assert_eq!(
        figs.iter().map(|f| f.name.as_str()).collect::<Vec<_>>(),
        ["trajectory_turn"],
        "a plane without a vertical axis: a trajectory, no route"
    );
    let traj = &figs[0];
    let p = &traj.panels[0];
    assert_eq!(
        (p.title.as_str(), p.x_label.as_str(), p.y_label.as_str()),
        ("px–py plane", "px [m]", "py [m]")
    );
    let tr = df(&res, "traces");
    let r = rows(&tr, "turn", Some(1.0), "kf");
    let (tx, ty, zx, zy) = (
        f64s(&tr, "truth_px"),
        f64s(&tr, "truth_py"),
        f64s(&tr, "z_px"),
        f64s(&tr, "z_py"),
    );
    let want: Vec<(f64, f64)> = r
        .iter()
        .map(|&i| (tx[i].unwrap(), ty[i].unwrap()))
        .collect();
    assert_eq!(line(traj, "px–py plane", "truth"), want);
    let fixes: Vec<(f64, f64)> = r.iter().filter_map(|&i| Some((zx[i]?, zy[i]?))).collect();
    assert_eq!(fixes.len(), 61, "1 Hz over 60 s, from t = 0");
    assert_eq!(scatters(p), vec![("px/py fixes".to_string(), fixes)]);

    // Without roles (a folder of an older kfmc) the names px, py make no trajectory, as then.
    strip_roles(&res);
    let t = Tables::load(&res).unwrap();
    assert!(
        kfmc::plot::all_figures(&t, &[FigureKind::Trajectory, FigureKind::Route])
            .unwrap()
            .is_empty()
    );
}

#[test]
fn the_drone_route_finds_its_fixes_by_role_and_an_old_manifest_by_name() {
    let tmp = tempfile::tempdir().unwrap();
    let res = drone_maneuver_study(tmp.path(), 2, 1);
    let route = |res: &Path| {
        let t = Tables::load(res).unwrap();
        let figs =
            kfmc::plot::all_figures(&t, &[FigureKind::Trajectory, FigureKind::Route]).unwrap();
        assert_eq!(figs.len(), 1, "the route only: a vertical axis");
        assert_eq!(figs[0].kind, FigureKind::Route);
        figs[0].clone()
    };
    let by_role = route(&res);
    let tr = df(&res, "traces");
    let (gn, ge) = (f64s(&tr, "z_gps_px"), f64s(&tr, "z_gps_py"));
    let want: Vec<(f64, f64)> = (0..tr.height())
        .filter_map(|i| Some((ge[i]?, gn[i]?)))
        .collect();
    assert_eq!(want.len(), 31, "10 Hz over 3 s, from t = 0");
    assert_eq!(
        scatters(&by_role.panels[0]),
        vec![("gps fixes".to_string(), want.clone())]
    );
    // The fixes come from the roles the manifest records: renaming the sensor there renames
    // the legend, whatever the columns are called.
    let text = std::fs::read_to_string(res.join("manifest.toml")).unwrap();
    assert!(text.contains("position = \"north\""), "{text}");
    assert_eq!(text.matches("sensor = \"gps\"").count(), 3);
    std::fs::write(
        res.join("manifest.toml"),
        text.replace("sensor = \"gps\"", "sensor = \"receiver\""),
    )
    .unwrap();
    assert_eq!(
        scatters(&route(&res).panels[0]),
        vec![("receiver fixes".to_string(), want)]
    );
    // A manifest without roles (an older kfmc's) draws the route as then, by the names px,
    // py, pz and the sensor named gps: the same figure as by roles.
    strip_roles(&res);
    assert_eq!(route(&res), by_role);
}

#[test]
fn an_old_manifest_without_roles_plots_as_before() {
    let (_tmp, res) = study();
    let declared: Vec<(String, Option<String>)> =
        roles(&res).into_iter().map(|(n, p, _)| (n, p)).collect();
    assert_eq!(
        declared[..3],
        [
            ("x".to_string(), Some("x".to_string())),
            ("xdot".to_string(), None),
            ("y".to_string(), Some("y".to_string())),
        ],
        "the planar x, y are declared positions"
    );
    let t = Tables::load(&res).unwrap();
    let new = kfmc::plot::all_figures(&t, &[]).unwrap();
    strip_roles(&res);
    assert!(roles(&res).iter().all(|r| r.1.is_none()));
    let t = Tables::load(&res).unwrap();
    let old = kfmc::plot::all_figures(&t, &[]).unwrap();
    // The planar roles give exactly the figures the names x, y gave.
    assert_eq!(old, new);
    assert!(old.iter().any(|f| f.name == "trajectory_roll"));
}

#[test]
fn the_divergence_histogram_puts_each_run_at_its_grid_multiplier() {
    let (dir, _) = spec_in_tempdir("");
    let out = dir.path().join("res");
    let spec = dir.path().join("s.toml");
    // A non-uniform grid: equal-width bins over [min, max] would not sit on its points.
    let grid = [0.5, 1.0, 2.0, 3.0, 7.0, 20.0];
    let text = small_spec(&out, 20, "[0.5, 1.0, 2.0, 3.0, 7.0, 20.0]", EKF_AND_MEAN).replace(
        "rmse_thresholds = [0.05, 0.05, 0.01, 0.05, 0.01, 0.01]",
        "rmse_thresholds = [0.05, 0.05, 0.05, 0.05, 0.05, 0.05]",
    );
    std::fs::write(&spec, text).unwrap();
    let o = kfmc()
        .args(["run", spec.to_str().unwrap(), "--quiet"])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let t = Tables::load(&out).unwrap();
    let dr = df(&out, "divergence_runs");
    let (sc, fl, st, ds) = (
        strs(&dr, "scenario"),
        strs(&dr, "filter"),
        strs(&dr, "state"),
        f64s(&dr, "divergence_scale"),
    );
    let figs = FigureKind::DivergenceHist.series(&t).unwrap();
    let mut seen_at_7 = 0;
    for f in &figs {
        for (pi, state) in t.states.iter().enumerate() {
            let p = &f.panels[pi];
            let cats = p.x_categories.clone().expect("a categorical axis");
            // One slot per multiplier at which a run crossed, labelled with it, in order.
            let mut at: Vec<f64> = (0..dr.height())
                .filter(|&i| sc[i] == f.scenario && st[i] == *state)
                .filter_map(|i| ds[i])
                .collect();
            at.sort_by(f64::total_cmp);
            at.dedup();
            assert!(at.iter().all(|v| grid.contains(v)));
            let labels: Vec<String> = at.iter().map(|v| format!("{v}")).collect();
            assert_eq!(cats, labels, "{}/{state}", f.name);
            for (j, filter) in ["ekf", "running_mean"].iter().enumerate() {
                let bars = p
                    .marks
                    .iter()
                    .filter_map(|m| match m {
                        Mark::Bars { bars, .. } => Some(bars.clone()),
                        _ => None,
                    })
                    .nth(j)
                    .unwrap();
                for (b, v) in at.iter().enumerate() {
                    let n = (0..dr.height())
                        .filter(|&i| {
                            sc[i] == f.scenario
                                && st[i] == *state
                                && fl[i] == *filter
                                && ds[i] == Some(*v)
                        })
                        .count();
                    if *v == 7.0 {
                        seen_at_7 += n;
                    }
                    // The bar inside the slot of its multiplier counts exactly those runs.
                    let bar = &bars[b];
                    assert!(bar.x0 >= b as f64 - 0.5 && bar.x1 <= b as f64 + 0.5);
                    assert_eq!(bar.y, n as f64, "{}/{state}/{filter} at ×{v}", f.name);
                }
            }
        }
    }
    assert!(seen_at_7 > 0, "some run crossed at ×7");
}

/// Runs `runs` drone runs (the first `trace_runs` traced) of 3 s on the maneuver route with
/// ekf9 under `dir`; returns the result folder.
fn drone_maneuver_study(dir: &Path, runs: usize, trace_runs: usize) -> std::path::PathBuf {
    let res = dir.join("d");
    let spec = dir.join("d.toml");
    std::fs::write(
        &spec,
        format!(
            "name = \"d\"\nmaster_seed = 3\nruns = {runs}\ntrace_runs = {trace_runs}\noutput = \"{}\"\n[model]\nkind = \"drone\"\nimu_output = \"specific_force\"\n[[scenarios]]\nname = \"maneuver\"\nduration_s = 3.0\n[[filters]]\nlabel = \"ekf9\"\nkind = \"ekf9\"\n[initial_estimate]\nmode = \"sampled\"\n",
            res.display()
        ),
    )
    .unwrap();
    let o = kfmc()
        .args(["run", spec.to_str().unwrap(), "--quiet"])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    res
}
