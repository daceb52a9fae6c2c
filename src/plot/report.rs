//! `kfmc report`: one self-contained HTML file — spec, provenance, tables and every figure
//! (inline SVG) — with no external resource, so it can be mailed or attached to a CI run.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use polars::prelude::DataType;

use super::{FigureKind, Table, Tables, plotted_scales, render, short};
use crate::error::PlotError;

/// Escapes text for HTML element content and attribute values.
pub fn escape(s: &str) -> String {
    let mut o = String::with_capacity(s.len());
    for c in s.chars() {
        match c {
            '&' => o.push_str("&amp;"),
            '<' => o.push_str("&lt;"),
            '>' => o.push_str("&gt;"),
            '"' => o.push_str("&quot;"),
            '\'' => o.push_str("&#39;"),
            c => o.push(c),
        }
    }
    o
}

/// A number in 4 significant digits; "—" for null.
fn num(v: Option<f64>) -> String {
    match v {
        None => "—".into(),
        Some(x) if x != 0.0 && (x.abs() >= 1e5 || x.abs() < 1e-3) => format!("{x:.3e}"),
        Some(x) => format!("{}", (x * 1e4).round() / 1e4),
    }
}

/// An SVG from plotters, ready to sit inside HTML: no XML prolog and no namespace URL (inline
/// SVG in HTML5 needs neither, and the report must not name any URL).
fn inline_svg(svg: &str) -> String {
    let s = match svg.find("<svg") {
        Some(i) => &svg[i..],
        None => svg,
    };
    s.replace(" xmlns=\"http://www.w3.org/2000/svg\"", "")
        .replace("xmlns=\"http://www.w3.org/2000/svg\"", "")
}

/// Any table as an HTML table, every cell escaped.
fn html_table(t: &Table) -> Result<String, PlotError> {
    let names = t.names();
    let mut cols: Vec<Vec<String>> = Vec::new();
    for n in &names {
        let dt = t.df.column(n).map(|c| c.dtype().clone()).ok();
        cols.push(match dt {
            Some(DataType::String) => t.strs(n)?,
            Some(DataType::Boolean) => {
                t.df.column(n)
                    .ok()
                    .and_then(|c| {
                        c.bool().ok().map(|b| {
                            b.iter()
                                .map(|v| v.map_or("—".to_string(), |v| v.to_string()))
                                .collect()
                        })
                    })
                    .unwrap_or_default()
            }
            _ => t.f64s(n)?.into_iter().map(num).collect(),
        });
    }
    let mut h = String::from("<table>\n<thead><tr>");
    for n in &names {
        let _ = write!(h, "<th>{}</th>", escape(n));
    }
    h.push_str("</tr></thead>\n<tbody>\n");
    for r in 0..t.height() {
        h.push_str("<tr>");
        for c in &cols {
            let _ = write!(
                h,
                "<td>{}</td>",
                escape(c.get(r).map_or("", |s| s.as_str()))
            );
        }
        h.push_str("</tr>\n");
    }
    h.push_str("</tbody>\n</table>\n");
    Ok(h)
}

/// RMSE per (scenario, noise scale, filter) × state: "mean (p5–p95)".
fn rmse_table(t: &Tables) -> Result<String, PlotError> {
    let s = &t.summary;
    let (scen, filt, state) = (s.strs("scenario")?, s.strs("filter")?, s.strs("state")?);
    let (noise, mean, p05, p95) = (
        s.f64s("noise_scale")?,
        s.f64s("rmse_mean")?,
        s.f64s("rmse_p05")?,
        s.f64s("rmse_p95")?,
    );
    let shown = plotted_scales(&t.noise_scales);
    let mut rows: Vec<(String, f64, String)> = Vec::new();
    let mut cells: Vec<(usize, String, String)> = Vec::new();
    for i in 0..s.height() {
        let Some(nz) = noise[i] else { continue };
        if t.noise_scales.len() > 12 && !shown.contains(&nz) {
            continue;
        }
        let key = (scen[i].clone(), nz, filt[i].clone());
        let ri = match rows.iter().position(|r| *r == key) {
            Some(p) => p,
            None => {
                rows.push(key);
                rows.len() - 1
            }
        };
        let text = format!("{} ({}–{})", num(mean[i]), num(p05[i]), num(p95[i]));
        cells.push((ri, state[i].clone(), text));
    }
    let mut h = String::new();
    if t.noise_scales.len() > 12 {
        let _ = writeln!(
            h,
            "<p>{} noise scales; the table shows {}. summary.parquet has them all.</p>",
            t.noise_scales.len(),
            escape(
                &shown
                    .iter()
                    .map(|v| short(*v))
                    .collect::<Vec<_>>()
                    .join(", ")
            )
        );
    }
    h.push_str("<table>\n<thead><tr><th>scenario</th><th>noise scale</th><th>filter</th>");
    for st in &t.states {
        let _ = write!(h, "<th>rmse_{}</th>", escape(st));
    }
    h.push_str("</tr></thead>\n<tbody>\n");
    for (ri, (sc, nz, f)) in rows.iter().enumerate() {
        let _ = write!(
            h,
            "<tr><td>{}</td><td>{}</td><td>{}</td>",
            escape(sc),
            escape(&short(*nz)),
            escape(f)
        );
        for st in &t.states {
            let c = cells
                .iter()
                .find(|(r, s, _)| *r == ri && s == st)
                .map_or("—", |c| c.2.as_str());
            let _ = write!(h, "<td>{}</td>", escape(c));
        }
        h.push_str("</tr>\n");
    }
    h.push_str("</tbody>\n</table>\n");
    Ok(h)
}

const STYLE: &str = "body{font-family:sans-serif;max-width:1200px;margin:2em auto;padding:0 1em;color:#222}\
table{border-collapse:collapse;font-size:0.85em;margin:1em 0}\
th,td{border:1px solid #ccc;padding:0.2em 0.5em;text-align:right}\
th{background:#f3f3f3}td:first-child,th:first-child{text-align:left}\
pre{background:#f6f6f6;padding:1em;overflow-x:auto}\
figure{margin:1.5em 0}svg{max-width:100%;height:auto}figcaption{font-size:0.85em;color:#555}";

/// The whole report as HTML text.
pub fn render_html(t: &Tables) -> Result<String, PlotError> {
    let name = t
        .manifest
        .as_ref()
        .map_or_else(|| t.dir.display().to_string(), |m| m.experiment.clone());
    let mut h = String::new();
    let _ = write!(
        h,
        "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n<title>kfmc report: {n}</title>\n<style>{STYLE}</style>\n</head>\n<body>\n<h1>kfmc report: {n}</h1>\n",
        n = escape(&name)
    );
    let _ = writeln!(
        h,
        "<p>Result folder <code>{}</code>. Every number and figure below is read from its Parquet tables.</p>",
        escape(&t.dir.display().to_string())
    );

    h.push_str("<h2>Provenance</h2>\n");
    match &t.manifest {
        Some(m) => {
            let started = m.started_unix_s.to_string();
            let tables = m
                .tables
                .iter()
                .map(|e| format!("{} ({} rows)", e.name, e.rows))
                .collect::<Vec<_>>()
                .join(", ");
            let rows: [(&str, String); 13] = [
                ("kfmc version", m.kfmc_version.clone()),
                ("experiment", m.experiment.clone()),
                ("spec file", m.spec_path.clone()),
                ("spec hash (FNV-1a 64)", m.spec_hash.clone()),
                ("master seed", m.master_seed.to_string()),
                ("runs per cell", m.runs_per_cell.to_string()),
                ("cells", m.cells.to_string()),
                (
                    "runs / filter runs",
                    format!("{} / {}", m.runs, m.filter_runs),
                ),
                ("filter steps", m.filter_steps.to_string()),
                ("threads", m.threads.to_string()),
                ("started (Unix time, s)", started),
                (
                    "wall time",
                    format!("{:.2} s ({:.0} runs/s)", m.wall_s, m.runs_per_s),
                ),
                ("tables", tables),
            ];
            h.push_str("<table>\n<tbody>\n");
            for (k, v) in rows {
                let _ = writeln!(h, "<tr><th>{}</th><td>{}</td></tr>", escape(k), escape(&v));
            }
            h.push_str("</tbody>\n</table>\n");
            let _ = writeln!(h, "<h2>Spec</h2>\n<pre>{}</pre>", escape(&m.spec));
        }
        None => h.push_str("<p>manifest.toml is missing or unreadable.</p>\n"),
    }

    h.push_str("<h2>RMSE over runs: mean (p5–p95)</h2>\n");
    h.push_str(&rmse_table(t)?);

    if let Some(c) = &t.consistency {
        h.push_str("<h2>Consistency verdicts</h2>\n");
        h.push_str(&html_table(c)?);
    }
    if let Some(d) = &t.divergence {
        h.push_str("<h2>Divergence points</h2>\n<p>The first truth-noise multiplier whose RMSE exceeds the state's threshold: for the mean over runs (<code>mc_divergence_scale</code>) and as quantiles over runs (— = not reached within the sweep).</p>\n");
        h.push_str(&html_table(d)?);
    }

    h.push_str("<h2>Figures</h2>\n");
    for kind in FigureKind::ALL {
        let figs = kind.series(t)?;
        if figs.is_empty() {
            continue;
        }
        let _ = writeln!(h, "<h3>{}</h3>", escape(kind.name()));
        for f in figs {
            let svg = render::to_svg_string(&f)?;
            let _ = writeln!(
                h,
                "<figure>\n{}\n<figcaption>{} ({})</figcaption>\n</figure>",
                inline_svg(&svg),
                escape(&f.title),
                escape(&f.name)
            );
        }
    }
    h.push_str("</body>\n</html>\n");
    Ok(h)
}

/// Writes the report of `dir` to `out` (default `<dir>/report.html`); returns the path.
pub fn write_report(dir: &Path, out: Option<&Path>) -> Result<PathBuf, PlotError> {
    let t = Tables::load(dir)?;
    let html = render_html(&t)?;
    let path = out.map_or_else(|| dir.join("report.html"), Path::to_path_buf);
    crate::output::folder::write_atomic(&path, html.as_bytes()).map_err(|source| {
        PlotError::Io {
            action: "cannot write the report",
            path: path.clone(),
            source,
        }
    })?;
    Ok(path)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn escaping_covers_markup_and_quotes() {
        assert_eq!(
            escape("<a href=\"x\">&'</a>"),
            "&lt;a href=&quot;x&quot;&gt;&amp;&#39;&lt;/a&gt;"
        );
    }

    #[test]
    fn inline_svg_drops_the_prolog_and_namespace() {
        let s = inline_svg(
            "<?xml version=\"1.0\"?>\n<svg width=\"1\" xmlns=\"http://www.w3.org/2000/svg\"></svg>",
        );
        assert_eq!(s, "<svg width=\"1\"></svg>");
    }
}
