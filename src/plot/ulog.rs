//! The figures and the report of a `kfmc ulog nis` folder (a log is a study like any other):
//! per log and aid source, each axis's NIS over time with the per-sample χ²₁ band at 95 %,
//! its mean 1 and the rejection gate γ², drawn from `ulog_samples.parquet`; the report leads
//! with the verdicts of `ulog_summary.parquet`.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::Path;

use statrs::distribution::{ChiSquared, ContinuousCDF};

use super::report::{STYLE, escape, html_table, inline_svg};
use super::{Figure, FigureKind, Ink, Mark, Panel, Table, render};
use crate::error::PlotError;

/// Points drawn per panel at most: a long flight is thinned by a stride.
pub const MAX_POINTS: usize = 1500;

/// One figure per log × instance selection × source: a panel per axis.
pub fn nis_series(dir: &Path) -> Result<Vec<Figure>, PlotError> {
    let path = dir.join("ulog_samples.parquet");
    let t = Table::read_optional(path.clone())?.ok_or(PlotError::MissingTable {
        path,
        why: "the NIS figures need it; is this a folder written by `kfmc ulog nis`?".into(),
    })?;
    let (log, source) = (t.strs("log")?, t.strs("source")?);
    let (axis, time, nis, gate, included) = (
        t.f64s("axis")?,
        t.f64s("t_sample")?,
        t.f64s("nis")?,
        t.f64s("gate")?,
        t.f64s("included")?,
    );
    // (log, source) → axis → points of the included samples.
    type Points = BTreeMap<usize, Vec<(f64, f64)>>;
    let mut groups: BTreeMap<(String, String), (Points, Option<f64>)> = BTreeMap::new();
    for i in 0..t.height() {
        if included[i] != Some(1.0) {
            continue;
        }
        let (Some(a), Some(x), Some(y)) = (axis[i], time[i], nis[i]) else {
            continue;
        };
        let g = groups
            .entry((log[i].clone(), source[i].clone()))
            .or_default();
        g.0.entry(a as usize).or_default().push((x, y.max(1e-6)));
        if g.1.is_none() {
            g.1 = gate[i];
        }
    }
    let chi = ChiSquared::new(1.0).map_err(|e| PlotError::Columns {
        path: dir.join("ulog_samples.parquet"),
        message: e.to_string(),
    })?;
    let (lo, hi) = (chi.inverse_cdf(0.025), chi.inverse_cdf(0.975));
    let mut figs = Vec::new();
    for ((log, source), (axes, gate)) in groups {
        let mut panels = Vec::new();
        for (a, pts) in axes {
            let stride = pts.len().div_ceil(MAX_POINTS).max(1);
            let shown: Vec<(f64, f64)> = pts.iter().step_by(stride).copied().collect();
            let (t0, t1) = (
                pts.first().map_or(0.0, |p| p.0),
                pts.last().map_or(1.0, |p| p.0),
            );
            let mut marks = vec![
                Mark::Band {
                    label: Some("χ²₁ 95 % band".into()),
                    ink: Ink::Reference,
                    points: vec![(t0, lo, hi), (t1, lo, hi)],
                },
                Mark::Scatter {
                    label: Some(if stride > 1 {
                        format!("NIS (every {stride}th sample)")
                    } else {
                        "NIS".into()
                    }),
                    ink: Ink::Palette(0),
                    points: shown,
                },
                Mark::HLine {
                    label: Some("E[NIS] = 1".into()),
                    ink: Ink::Reference,
                    y: 1.0,
                },
            ];
            if let Some(g) = gate {
                marks.push(Mark::HLine {
                    label: Some(format!("gate γ² = {}", g * g)),
                    ink: Ink::Palette(3),
                    y: g * g,
                });
            }
            panels.push(Panel {
                title: format!("{source}[{a}]"),
                x_label: "time since the log's start (s)".into(),
                y_label: "NIS = ν²/S".into(),
                log_y: true,
                marks,
                ..Panel::default()
            });
        }
        figs.push(Figure {
            kind: FigureKind::UlogNis,
            name: format!("ulog_nis_{}_{}", super::file_part(&log), source),
            scenario: log.clone(),
            title: format!("{log}: {source} NIS over time"),
            panels,
        });
    }
    super::unique_names(&mut figs);
    Ok(figs)
}

/// The NIS figures of a `ulog nis` folder (refusing any other kind asked for by name).
pub fn figures(dir: &Path, only: &[FigureKind]) -> Result<Vec<Figure>, PlotError> {
    if only.iter().any(|k| *k != FigureKind::UlogNis) {
        return Err(PlotError::NoFigures {
            path: dir.to_path_buf(),
            lacking: only
                .iter()
                .filter(|k| **k != FigureKind::UlogNis)
                .map(|k| k.name())
                .collect::<Vec<_>>()
                .join(", "),
            available: FigureKind::UlogNis.name().into(),
        });
    }
    nis_series(dir)
}

/// The report of a `ulog nis` folder as HTML: the verdicts, the per-axis rows, the figures.
pub fn render_html(dir: &Path) -> Result<String, PlotError> {
    let manifest = crate::output::folder::verify(dir)?;
    let path = dir.join("ulog_summary.parquet");
    let summary = Table::read_optional(path.clone())?.ok_or(PlotError::MissingTable {
        path,
        why: "the report needs it".into(),
    })?;
    let figs = nis_series(dir)?;
    let mut h = String::new();
    let _ = write!(
        h,
        "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n<title>kfmc report: {n}</title>\n<style>{STYLE}</style>\n</head>\n<body>\n<h1>kfmc report: {n}</h1>\n",
        n = escape(&manifest.experiment)
    );
    h.push_str("<p class=\"lead\">NIS = ν²/S of each aid source and axis of PX4's EKF, judged per log by batch means: the mean over the judged samples against 1 with a t reference on the batches (effective sample size from the series' own correlation); each test at α/k, Bonferroni over the k tests of a log. A series too short for 10 batches of ≥ 10 autocorrelation times is incomplete. See kfmc's book, “Real logs and your own runs”.</p>\n");
    let (test, verdict, log, detail, stat) = (
        summary.strs("test")?,
        summary.strs("verdict")?,
        summary.strs("log")?,
        summary.strs("detail")?,
        summary.f64s("statistic")?,
    );
    h.push_str("<h2 id=\"verdicts\">Verdicts per log</h2>\n<table>\n<thead><tr><th>log</th><th>verdict</th><th>Bonferroni p</th><th>why</th></tr></thead>\n<tbody>\n");
    for i in (0..summary.height()).filter(|&i| test[i] == crate::ulog::TEST_VERDICT) {
        let _ = writeln!(
            h,
            "<tr><td>{}</td><td class=\"{}\">{}</td><td>{}</td><td>{}</td></tr>",
            escape(&log[i]),
            if verdict[i] == "pass" { "pass" } else { "fail" },
            escape(&verdict[i]),
            stat[i].map_or("—".into(), |p| format!("{p:.4}")),
            escape(&detail[i])
        );
    }
    h.push_str("</tbody>\n</table>\n");
    let _ = writeln!(
        h,
        "<details><summary>Every row of ulog_summary.parquet</summary>\n<div class=\"scroll\">{}</div></details>",
        html_table(&summary)?
    );
    if !figs.is_empty() {
        h.push_str("<h2 id=\"figures\">NIS over time</h2>\n");
    }
    for f in &figs {
        let svg = render::to_svg_string(f)?;
        let _ = writeln!(
            h,
            "<figure style=\"max-width:{}px\">\n{}\n<figcaption>{} <code>{}</code></figcaption>\n</figure>",
            render::size(f).0,
            inline_svg(&svg),
            escape(&f.title),
            escape(&f.name)
        );
    }
    let _ = writeln!(
        h,
        "<h2 id=\"provenance\">Provenance</h2>\n<p>Result folder <code>{}</code>, written by kfmc {} in {:.2} s. Every number and figure above is read from its Parquet tables.</p>\n<pre>{}</pre>\n</body>\n</html>",
        escape(&dir.display().to_string()),
        escape(&manifest.kfmc_version),
        manifest.wall_s,
        escape(&manifest.spec)
    );
    Ok(h)
}
