//! `kfmc report`: one self-contained HTML file that reads as a study — the consistency
//! verdicts and the headline RMSE first, then every figure (inline SVG) by scenario with a
//! table of contents, the divergence tables, and provenance with the spec folded away — with
//! no external resource, so it can be mailed or attached to a CI run.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use polars::prelude::DataType;

use super::{Table, Tables, plotted_scales, render, short};
use crate::error::PlotError;
use crate::metrics::consistency::verdict_band;

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
pub fn inline_svg(svg: &str) -> String {
    let s = match svg.find("<svg") {
        Some(i) => &svg[i..],
        None => svg,
    };
    s.replace(" xmlns=\"http://www.w3.org/2000/svg\"", "")
        .replace("xmlns=\"http://www.w3.org/2000/svg\"", "")
}

/// Any table as an HTML table, every cell escaped.
pub fn html_table(t: &Table) -> Result<String, PlotError> {
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

/// Decimals that show 3 significant digits of a column whose typical magnitude is `typical`:
/// one column, one number of decimals, so values line up and compare at a glance.
fn decimals_for(typical: f64) -> usize {
    if !(typical.is_finite() && typical > 0.0) {
        return 3;
    }
    (2 - typical.log10().floor() as i32).clamp(0, 6) as usize
}

/// A number with fixed decimals; scientific beyond what fixed decimals can show; "—" for null.
fn fixed(v: Option<f64>, decimals: usize) -> String {
    match v {
        None => "—".into(),
        Some(x) if !x.is_finite() => format!("{x}"),
        Some(x) if x != 0.0 && (x.abs() >= 1e6 || x.abs() < 10f64.powi(-(decimals as i32))) => {
            format!("{x:.2e}")
        }
        Some(x) => format!("{x:.decimals$}"),
    }
}

/// `YYYY-MM-DD HH:MM:SS UTC` of a Unix time (proleptic Gregorian, H. Hinnant's
/// days-to-civil), so the report needs no date library.
pub fn utc(unix_s: u64) -> String {
    let days = (unix_s / 86_400) as i64;
    let rem = unix_s % 86_400;
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let m = if mp < 10 { mp + 3 } else { mp - 9 };
    let y = yoe + era * 400 + i64::from(m <= 2);
    format!(
        "{y:04}-{m:02}-{d:02} {:02}:{:02}:{:02} UTC",
        rem / 3600,
        rem % 3600 / 60,
        rem % 60
    )
}

/// The headline RMSE: one row per (scenario, noise scale, filter variant), one column per
/// quantity with its unit, "mean" over runs and p5–p95 below it in smaller type; each column
/// with one number of decimals.
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
    let many = t.noise_scales.len() > 12;
    let decimals: Vec<usize> = t
        .states
        .iter()
        .map(|st| {
            // The column's smallest mean sets its decimals, so the best filter's value keeps
            // three significant digits and every row of the column lines up.
            decimals_for(
                (0..s.height())
                    .filter(|&i| state[i] == *st)
                    .filter_map(|i| mean[i])
                    .filter(|v| *v > 0.0)
                    .fold(f64::INFINITY, f64::min),
            )
        })
        .collect();
    let mut rows: Vec<(String, f64, String)> = Vec::new();
    let mut cells: std::collections::BTreeMap<(usize, usize), String> = Default::default();
    for i in 0..s.height() {
        let Some(nz) = noise[i] else { continue };
        if many && !shown.contains(&nz) {
            continue;
        }
        let Some(si) = t.states.iter().position(|x| *x == state[i]) else {
            continue;
        };
        let key = (scen[i].clone(), nz, filt[i].clone());
        let ri = match rows.iter().position(|r| *r == key) {
            Some(p) => p,
            None => {
                rows.push(key);
                rows.len() - 1
            }
        };
        let d = decimals[si];
        cells.insert(
            (ri, si),
            format!(
                "{}<small>{}–{}</small>",
                escape(&fixed(mean[i], d)),
                escape(&fixed(p05[i], d)),
                escape(&fixed(p95[i], d))
            ),
        );
    }
    // Scenario order, then noise, then filter colour order.
    let pos = |v: &[String], x: &str| v.iter().position(|y| y == x);
    let mut order: Vec<usize> = (0..rows.len()).collect();
    order.sort_by(|&a, &b| {
        let (ra, rb) = (&rows[a], &rows[b]);
        pos(&t.scenarios, &ra.0)
            .cmp(&pos(&t.scenarios, &rb.0))
            .then(ra.1.total_cmp(&rb.1))
            .then(pos(&t.filters, &ra.2).cmp(&pos(&t.filters, &rb.2)))
    });
    let mut h = String::new();
    if many {
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
    h.push_str("<div class=\"scroll\"><table class=\"rmse\">\n<thead><tr><th>scenario</th><th>noise ×</th><th>filter</th>");
    for st in &t.states {
        let _ = write!(
            h,
            "<th>{}{}</th>",
            escape(st),
            match t.unit(st) {
                "" => String::new(),
                u => format!(" <span class=\"unit\">[{}]</span>", escape(u)),
            }
        );
    }
    h.push_str("</tr></thead>\n<tbody>\n");
    for ri in order {
        let (sc, nz, f) = &rows[ri];
        let _ = write!(
            h,
            "<tr><td>{}</td><td>{}</td><td>{}</td>",
            escape(sc),
            escape(&short(*nz)),
            escape(f)
        );
        for si in 0..t.states.len() {
            let _ = write!(
                h,
                "<td>{}</td>",
                cells.get(&(ri, si)).map_or("—", |c| c.as_str())
            );
        }
        h.push_str("</tr>\n");
    }
    h.push_str("</tbody>\n</table></div>\n");
    Ok(h)
}

/// The consistency tests the verdict table gives a column, with their headings.
const VERDICT_COLUMNS: [(&str, &str); 4] = [
    ("nees_time_average", "NEES time average"),
    ("nis_time_average", "NIS time average"),
    ("nees_run_average_t", "NEES run averages (t)"),
    ("innovation_whiteness", "innovation whiteness"),
];

/// A row of the verdict table: (scenario, noise scale's bits, filter variant).
type VerdictKey = (String, u64, String);

/// The CSS class of a cell: pass, fail, or not judged.
fn class(ok: Option<bool>) -> &'static str {
    match ok {
        Some(true) => "pass",
        Some(false) => "fail",
        None => "na",
    }
}

/// The columns of consistency.parquet that the verdict table shows.
struct Verdicts {
    rows: usize,
    scen: Vec<String>,
    filt: Vec<String>,
    test: Vec<String>,
    noise: Vec<Option<f64>>,
    stat: Vec<Option<f64>>,
    lo: Vec<Option<f64>>,
    hi: Vec<Option<f64>>,
    p: Vec<Option<f64>>,
    dof: Vec<Option<f64>>,
    alpha: Vec<Option<f64>>,
    pass: Vec<Option<bool>>,
    direction: Vec<String>,
}

impl Verdicts {
    fn read(c: &Table) -> Result<Verdicts, PlotError> {
        let (scen, filt, test) = (c.strs("scenario")?, c.strs("filter")?, c.strs("test")?);
        let noise = c.f64s("noise_scale")?;
        let (stat, lo, hi, p) = (
            c.f64s("statistic")?,
            c.f64s("lower")?,
            c.f64s("upper")?,
            c.f64s("p_value")?,
        );
        let (dof, alpha) = (c.f64s("dof")?, c.f64s("alpha")?);
        let pass: Vec<Option<bool>> =
            c.df.column("pass")
                .ok()
                .and_then(|col| col.bool().ok().map(|b| b.iter().collect()))
                .unwrap_or_else(|| vec![None; c.height()]);
        let direction = if c.has("direction") {
            c.strs("direction")?
        } else {
            vec![String::new(); c.height()]
        };
        Ok(Verdicts {
            rows: c.height(),
            scen,
            filt,
            test,
            noise,
            stat,
            lo,
            hi,
            p,
            dof,
            alpha,
            pass,
            direction,
        })
    }

    fn in_row(&self, i: usize, k: &VerdictKey) -> bool {
        self.scen[i] == k.0
            && self.noise[i].unwrap_or(f64::NAN).to_bits() == k.1
            && self.filt[i] == k.2
    }

    /// The table's rows, in order of first appearance.
    fn keys(&self) -> Vec<VerdictKey> {
        let mut keys: Vec<VerdictKey> = Vec::new();
        for i in 0..self.rows {
            let k = (
                self.scen[i].clone(),
                self.noise[i].unwrap_or(f64::NAN).to_bits(),
                self.filt[i].clone(),
            );
            if !keys.contains(&k) {
                keys.push(k);
            }
        }
        keys
    }

    /// The row of test `name` in table row `k`.
    fn find(&self, k: &VerdictKey, name: &str) -> Option<usize> {
        (0..self.rows).find(|&i| self.in_row(i, k) && self.test[i] == name)
    }

    /// The verdict cell: consistent or not (with the direction), and its p-value.
    fn verdict_cell(&self, k: &VerdictKey) -> String {
        let Some(i) = self.find(k, "verdict") else {
            return "<td class=\"na\">—</td>".into();
        };
        let word = match self.pass[i] {
            Some(true) => "consistent".to_string(),
            Some(false) if !self.direction[i].is_empty() => {
                format!("inconsistent ({})", self.direction[i])
            }
            Some(false) => "inconsistent".to_string(),
            None => "—".to_string(),
        };
        format!(
            "<td class=\"{}\"><b>{}</b><small>p = {}</small></td>",
            class(self.pass[i]),
            escape(&word),
            escape(&num(self.p[i]))
        )
    }

    /// The cell of test `name`: its statistic against its acceptance band.
    fn test_cell(&self, k: &VerdictKey, name: &str) -> String {
        let Some(i) = self.find(k, name) else {
            return "<td class=\"na\">—</td>".into();
        };
        // The verdict's components (the NEES time average, or the run-average t-test standing
        // in for it, and the NIS time average) are drawn with the α/2 band and the α/2
        // decision the verdict uses; the other columns are their own tests at α.
        let component = self.find(k, "verdict").is_some()
            && match name {
                "nees_time_average" | "nis_time_average" => true,
                "nees_run_average_t" => self.find(k, "nees_time_average").is_none(),
                _ => false,
            };
        let half = component
            .then(|| {
                let a = self.alpha[i]?;
                let band = verdict_band(name, self.lo[i], self.hi[i], self.dof[i], a)?;
                Some((band, self.p[i].map(|p| p > a / 2.0)))
            })
            .flatten();
        let (l, u, ok) = match half {
            Some((band, ok)) => (Some(band.lo), Some(band.hi), ok),
            None => (self.lo[i], self.hi[i], self.pass[i]),
        };
        let inside = match ok {
            Some(true) => "∈",
            _ => "∉",
        };
        // Statistic and band with one number of decimals: 4 significant digits of the band's
        // larger end.
        let scale = u.or(l).or(self.stat[i]).unwrap_or(1.0).abs();
        let d = (decimals_for(scale) + 1).min(6);
        format!(
            "<td class=\"{}\">{}<small>{} [{}, {}]</small></td>",
            class(ok),
            escape(&fixed(self.stat[i], d)),
            inside,
            escape(&fixed(l, d)),
            escape(&fixed(u, d))
        )
    }

    /// The bias tests' cell: how many of them pass.
    fn bias_cell(&self, k: &VerdictKey) -> String {
        let bias: Vec<usize> = (0..self.rows)
            .filter(|&i| self.in_row(i, k) && self.test[i].starts_with("bias_"))
            .collect();
        if bias.is_empty() {
            return "<td class=\"na\">—</td>".into();
        }
        let ok = bias.iter().filter(|&&i| self.pass[i] == Some(true)).count();
        format!(
            "<td class=\"{}\">{ok} of {}</td>",
            class(Some(ok == bias.len())),
            bias.len()
        )
    }
}

/// The consistency verdicts: one row per (scenario, noise scale, filter variant), the verdict
/// first (pass/fail in colour, with its direction and p-value), then each calibrated test's
/// statistic against its acceptance band, and the bias tests as a count.
fn verdict_table(c: &Table) -> Result<String, PlotError> {
    let v = Verdicts::read(c)?;
    let mut h = String::from(
        "<div class=\"scroll\"><table class=\"verdicts\" id=\"verdict-table\">\n<thead><tr><th>scenario</th><th>noise ×</th><th>filter</th><th>verdict</th>",
    );
    for (_, title) in VERDICT_COLUMNS {
        let _ = write!(h, "<th>{}</th>", escape(title));
    }
    h.push_str("<th>bias tests passed</th></tr></thead>\n<tbody>\n");
    for k in &v.keys() {
        let _ = write!(
            h,
            "<tr><td>{}</td><td>{}</td><td>{}</td>",
            escape(&k.0),
            escape(&short(f64::from_bits(k.1))),
            escape(&k.2)
        );
        h.push_str(&v.verdict_cell(k));
        for (name, _) in VERDICT_COLUMNS {
            h.push_str(&v.test_cell(k, name));
        }
        h.push_str(&v.bias_cell(k));
        h.push_str("</tr>\n");
    }
    h.push_str("</tbody>\n</table></div>\n");
    Ok(h)
}

/// Per-block ANEES over the traced runs: time average and the fraction of steps inside the
/// per-step band, per (scenario, filter variant) × block.
fn block_table(t: &Tables) -> Result<Option<String>, PlotError> {
    let bl = super::blocks::blocks(t);
    let cells = super::blocks::block_cells(t, &bl)?;
    if cells.is_empty() {
        return Ok(None);
    }
    let alpha = super::blocks::alpha(t);
    let mut h = String::from(
        "<div class=\"scroll\"><table class=\"blocks\">\n<thead><tr><th>scenario</th><th>filter</th>",
    );
    for b in &bl {
        let _ = write!(
            h,
            "<th>{} ({}) <span class=\"unit\">consistent: {}</span></th>",
            escape(&b.name),
            escape(&b.quantities.join(", ")),
            b.quantities.len()
        );
    }
    h.push_str("</tr></thead>\n<tbody>\n");
    for c in &cells {
        let _ = write!(
            h,
            "<tr><td>{}</td><td>{}</td>",
            escape(&c.scenario),
            escape(&c.filter)
        );
        for (bi, b) in bl.iter().enumerate() {
            let (mean, inside) = c.time_average(bi, b.quantities.len(), alpha);
            let _ = write!(
                h,
                "<td>{}<small>{:.0} % of steps in band</small></td>",
                escape(&fixed(Some(mean), decimals_for(mean.abs()).min(2))),
                inside * 100.0
            );
        }
        h.push_str("</tr>\n");
    }
    h.push_str("</tbody>\n</table></div>\n");
    Ok(Some(h))
}

/// The command that reproduces the study from its spec, as the manifest records it.
pub fn reproduce_command(t: &Tables) -> Option<String> {
    let m = t.manifest.as_ref()?;
    let cmd = if t.tuning.is_some() {
        "tune"
    } else if m.exchange.is_some() {
        "simulate"
    } else if t.dir.join("power.parquet").exists() {
        "power"
    } else {
        "run"
    };
    let mut c = format!(
        "{} {cmd} {} --seed {} --runs {} --out {}",
        m.program(),
        m.spec_path,
        m.master_seed,
        m.runs_per_cell,
        t.dir.display()
    );
    if let Some(s) = &m.shard {
        let _ = write!(c, " --shard {}/{}", s.index + 1, s.count);
    }
    Some(c)
}

/// The report's style sheet.
pub const STYLE: &str = "\
*{box-sizing:border-box}\
body{font-family:'DejaVu Sans',Verdana,sans-serif;max-width:1320px;margin:0 auto;padding:0 1.2rem 3rem;color:#1f2328;line-height:1.45;font-size:16px}\
h1{font-size:1.7rem;margin:1.2rem 0 .3rem}h2{font-size:1.35rem;margin-top:2.2rem;border-bottom:1px solid #d0d7de;padding-bottom:.2rem}h3{font-size:1.1rem;margin-top:1.6rem}\
p.lead{font-size:1.05rem;color:#444;margin-top:0}\
nav.toc{background:#f6f8fa;border:1px solid #d0d7de;border-radius:6px;padding:.6rem 1rem;margin:1rem 0}\
nav.toc ol{margin:.2rem 0;padding-left:1.4rem}nav.toc li{margin:.1rem 0}nav.toc ol ol{font-size:.92em}\
a{color:#0969da}\
.scroll{overflow-x:auto;max-width:100%}\
table{border-collapse:collapse;font-size:.88rem;margin:.8rem 0;font-variant-numeric:tabular-nums}\
th,td{border:1px solid #d0d7de;padding:.3em .6em;text-align:right;white-space:nowrap;vertical-align:top}\
th{background:#f6f8fa;font-weight:600}td:first-child,th:first-child,td:nth-child(3),th:nth-child(3){text-align:left}\
td small{display:block;color:#57606a;font-size:.8em}\
th .unit{font-weight:400;color:#57606a}\
table.verdicts td:nth-child(4),table.verdicts th:nth-child(4){text-align:left}\
td.pass{background:#dafbe1;color:#116329}td.fail{background:#ffebe9;color:#a40e26}td.na{color:#8c959f}\
table.kv th{text-align:left}table.kv td{text-align:left;white-space:normal}\
pre,code{font-family:'DejaVu Sans Mono',Consolas,monospace;font-size:.86rem}\
pre{background:#f6f8fa;padding:.8rem;overflow-x:auto;border-radius:6px}\
details{margin:1rem 0}summary{cursor:pointer;font-weight:600}\
figure{margin:1.4rem 0;break-inside:avoid;page-break-inside:avoid}\
figure svg{display:block;width:100%;height:auto}\
figcaption{font-size:.9rem;color:#57606a;margin-top:.3rem}\
@media (max-width:760px){body{padding:0 .6rem 2rem;font-size:15px}\
figure{overflow-x:auto;max-width:100%!important}figure svg{width:980px;max-width:none}h1{font-size:1.35rem}}\
@media print{body{max-width:none;padding:0;font-size:11pt}nav.toc{break-after:page}\
a{color:inherit;text-decoration:none}.scroll{overflow:visible}\
figure svg{width:100%;max-width:100%}h2{break-after:avoid}h3{break-after:avoid}\
td.pass,td.fail{-webkit-print-color-adjust:exact;print-color-adjust:exact}}";

/// An id safe in a URL fragment, unique per index.
fn anchor(prefix: &str, i: usize) -> String {
    format!("{prefix}-{i}")
}

/// The report's figures grouped by scenario, in order of first appearance.
fn by_scenario(figs: &[super::Figure]) -> Vec<(String, Vec<&super::Figure>)> {
    let mut out: Vec<(String, Vec<&super::Figure>)> = Vec::new();
    for f in figs {
        match out.iter_mut().find(|(s, _)| *s == f.scenario) {
            Some((_, v)) => v.push(f),
            None => out.push((f.scenario.clone(), vec![f])),
        }
    }
    out
}

/// The question the study asks: its description and its size.
fn lead(t: &Tables) -> String {
    let spec: Option<toml::Table> = t.manifest.as_ref().and_then(|m| m.spec.parse().ok());
    let description = spec
        .as_ref()
        .and_then(|s| s.get("description")?.as_str().map(str::to_string));
    let mut lead = String::new();
    if let Some(d) = &description {
        let _ = write!(lead, "{}. ", escape(d.trim_end_matches('.')));
    }
    if let Some(m) = &t.manifest {
        let _ = write!(
            lead,
            "System <code>{}</code>; {} scenario{} × {} noise scale{} × {} filter variant{}, {} runs per cell.",
            escape(&m.system),
            t.scenarios.len(),
            if t.scenarios.len() == 1 { "" } else { "s" },
            t.noise_scales.len(),
            if t.noise_scales.len() == 1 { "" } else { "s" },
            t.filters.len(),
            if t.filters.len() == 1 { "" } else { "s" },
            m.runs_per_cell
        );
    }
    lead
}

/// The table of contents: the sections the report has, and the figures' scenarios.
fn contents(t: &Tables, has_blocks: bool, by_scenario: &[(String, Vec<&super::Figure>)]) -> String {
    let mut h = String::from("<nav class=\"toc\"><b>Contents</b>\n<ol>\n");
    if t.consistency.is_some() {
        h.push_str("<li><a href=\"#verdicts\">Consistency verdicts</a></li>\n");
    }
    h.push_str("<li><a href=\"#rmse\">RMSE</a></li>\n");
    if has_blocks {
        h.push_str("<li><a href=\"#blocks\">ANEES per block</a></li>\n");
    }
    if !by_scenario.is_empty() {
        h.push_str("<li><a href=\"#figures\">Figures</a>\n<ol>\n");
        for (i, (s, v)) in by_scenario.iter().enumerate() {
            let _ = writeln!(
                h,
                "<li><a href=\"#{}\">{}</a> ({} figure{})</li>",
                anchor("scenario", i),
                escape(s),
                v.len(),
                if v.len() == 1 { "" } else { "s" }
            );
        }
        h.push_str("</ol></li>\n");
    }
    if t.divergence.is_some() {
        h.push_str("<li><a href=\"#divergence\">Divergence points</a></li>\n");
    }
    h.push_str("<li><a href=\"#provenance\">Provenance and spec</a></li>\n</ol>\n</nav>\n");
    h
}

/// The answer: the consistency verdicts, the RMSE and the per-block ANEES.
fn answer(h: &mut String, t: &Tables, blocks: Option<&str>) -> Result<(), PlotError> {
    if let Some(c) = &t.consistency {
        h.push_str("<h2 id=\"verdicts\">Consistency verdicts</h2>\n<p>A filter is consistent when the NEES and the NIS time averages both lie in their χ² bands at α/2 each (Bonferroni: the verdict’s p = 2·min(p<sub>NEES</sub>, p<sub>NIS</sub>) exceeds α; see kfmc’s book, “What the verdict means”). The NEES and NIS cells (and the NEES run-average t-test where it stands in for a NEES test) show the statistic in those α/2 bands; the whiteness cell and a t-test that is not part of the verdict show their own test at α. Green passes, red fails.</p>\n");
        h.push_str(&verdict_table(c)?);
        let _ = writeln!(
            h,
            "<details><summary>Every test row of consistency.parquet</summary>\n{}</details>",
            html_table(c)?
        );
    }
    h.push_str("<h2 id=\"rmse\">RMSE over runs</h2>\n<p>Mean over runs, with the 5th–95th percentile over runs below it.</p>\n");
    h.push_str(&rmse_table(t)?);
    if let Some(b) = blocks {
        h.push_str("<h2 id=\"blocks\">ANEES per block</h2>\n<p>NEES of each block of quantities, averaged over the traced runs (at the nominal noise scale) and over steps ≥ 1, and the share of steps whose ANEES lies in the per-step χ² band. A block size near the average is consistent; descriptive only (steps are correlated and few runs are traced).</p>\n");
        h.push_str(b);
    }
    Ok(())
}

/// Every figure as inline SVG, under a heading per scenario.
fn figures(h: &mut String, by_scenario: &[(String, Vec<&super::Figure>)]) -> Result<(), PlotError> {
    if by_scenario.is_empty() {
        return Ok(());
    }
    h.push_str("<h2 id=\"figures\">Figures</h2>\n");
    for (i, (s, v)) in by_scenario.iter().enumerate() {
        let _ = writeln!(h, "<h3 id=\"{}\">{}</h3>", anchor("scenario", i), escape(s));
        for f in v {
            let svg = render::to_svg_string(f)?;
            // Never wider than drawn: scaled up, a one-panel figure would fill a screen.
            let _ = writeln!(
                h,
                "<figure id=\"fig-{}\" style=\"max-width:{}px\">\n{}\n<figcaption>{} <code>{}</code></figcaption>\n</figure>",
                escape(&f.name),
                render::size(f).0,
                inline_svg(&svg),
                escape(&f.title),
                escape(&f.name)
            );
        }
    }
    Ok(())
}

/// Where the numbers come from: the folder, the command that reproduces it, the manifest's
/// facts and the spec.
fn provenance(h: &mut String, t: &Tables) {
    h.push_str("<h2 id=\"provenance\">Provenance</h2>\n");
    let _ = writeln!(
        h,
        "<p>Result folder <code>{}</code>. Every number and figure above is read from its Parquet tables.</p>",
        escape(&t.dir.display().to_string())
    );
    let Some(m) = &t.manifest else {
        h.push_str("<p>manifest.toml is missing or unreadable.</p>\n");
        return;
    };
    if let Some(c) = reproduce_command(t) {
        let _ = writeln!(
            h,
            "<p>Reproduce the tables bit for bit (any thread count), then this report:</p>\n<pre>{}\n{} report {}</pre>",
            escape(&c),
            escape(m.program()),
            escape(&t.dir.display().to_string())
        );
    }
    let tables = m
        .tables
        .iter()
        .map(|e| format!("{} ({} rows)", e.name, e.rows))
        .collect::<Vec<_>>()
        .join(", ");
    let program = match (&m.program, &m.program_version) {
        (Some(name), Some(version)) => format!("{name} {version}"),
        (Some(name), None) => name.clone(),
        _ => "kfmc".to_string(),
    };
    let rows: [(&str, String); 14] = [
        ("program", program),
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
        ("started", utc(m.started_unix_s)),
        (
            "wall time",
            format!("{:.2} s ({:.0} runs/s)", m.wall_s, m.runs_per_s),
        ),
        ("tables", tables),
    ];
    h.push_str("<table class=\"kv\">\n<tbody>\n");
    for (k, v) in rows {
        let _ = writeln!(h, "<tr><th>{}</th><td>{}</td></tr>", escape(k), escape(&v));
    }
    h.push_str("</tbody>\n</table>\n");
    let _ = writeln!(
        h,
        "<details><summary>Spec ({})</summary>\n<pre>{}</pre>\n</details>",
        escape(&m.spec_path),
        escape(&m.spec)
    );
}

/// The whole report as HTML text: the question and the answer first (verdicts, headline RMSE),
/// then the figures by scenario, the divergence tables, and provenance with the spec folded.
pub fn render_html(t: &Tables) -> Result<String, PlotError> {
    let name = t
        .manifest
        .as_ref()
        .map_or_else(|| t.dir.display().to_string(), |m| m.experiment.clone());
    let figs = super::all_figures(t, &[])?;
    let blocks = block_table(t)?;
    let by_scenario = by_scenario(&figs);

    let mut h = String::new();
    let _ = write!(
        h,
        "<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n<meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">\n<title>kfmc report: {n}</title>\n<style>{STYLE}</style>\n</head>\n<body>\n<h1>kfmc report: {n}</h1>\n",
        n = escape(&name)
    );
    let _ = writeln!(h, "<p class=\"lead\">{}</p>", lead(t));
    h.push_str(&contents(t, blocks.is_some(), &by_scenario));
    answer(&mut h, t, blocks.as_deref())?;
    figures(&mut h, &by_scenario)?;
    if let Some(d) = &t.divergence {
        h.push_str("<h2 id=\"divergence\">Divergence points</h2>\n<p>The first truth-noise multiplier whose RMSE exceeds the state's threshold: for the mean over runs (<code>mc_divergence_scale</code>) and as quantiles over runs (— = not reached within the sweep).</p>\n");
        let _ = writeln!(h, "<div class=\"scroll\">{}</div>", html_table(d)?);
    }
    provenance(&mut h, t);
    h.push_str("</body>\n</html>\n");
    Ok(h)
}

/// Writes the report of `dir` to `out` (default `<dir>/report.html`); returns the path.
pub fn write_report(dir: &Path, out: Option<&Path>) -> Result<PathBuf, PlotError> {
    write_html(dir, out, || render_html(&Tables::load(dir)?))
}

/// Writes the report that `render` draws from the folder `dir` to `out` (default
/// `<dir>/report.html`), by the rules every report follows: inside the folder under its lock
/// and listed in its manifest before it is written, outside it only over a file that is a
/// kfmc report.
pub(crate) fn write_html(
    dir: &Path,
    out: Option<&Path>,
    render: impl Fn() -> Result<String, PlotError>,
) -> Result<PathBuf, PlotError> {
    use crate::output::folder;
    let path = out.map_or_else(|| dir.join("report.html"), Path::to_path_buf);
    match folder::relative_inside(dir, &path).filter(|_| dir.is_dir()) {
        // The study's own report: drawn under its lock, listed in its manifest before it is
        // written.
        Some(rel) => {
            let held = folder::StudyFolder::lock(dir)?;
            let html = render()?;
            held.claim_files(&[rel], &is_kfmc_report)?;
            folder::write_atomic(&path, html.as_bytes()).map_err(|source| PlotError::Io {
                action: "cannot write the report",
                path: path.clone(),
                source,
            })?;
        }
        None => {
            let html = render()?;
            folder::write_file(&path, html.as_bytes(), &is_kfmc_report)?;
        }
    }
    Ok(path)
}

/// Whether the file at `path` is a report kfmc wrote (its title says so), which a report may
/// replace where no manifest lists it.
fn is_kfmc_report(path: &Path) -> bool {
    use std::io::Read;
    let mut head = Vec::new();
    crate::output::atomic::open_regular(path)
        .and_then(|f| f.take(4096).read_to_end(&mut head))
        .is_ok()
        && head.starts_with(b"<!DOCTYPE html>")
        && String::from_utf8_lossy(&head).contains("<title>kfmc report: ")
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
    fn utc_times_are_civil_dates() {
        assert_eq!(utc(0), "1970-01-01 00:00:00 UTC");
        // 2000-02-29 (a leap day of a century divisible by 400) 12:34:56.
        assert_eq!(utc(951_827_696), "2000-02-29 12:34:56 UTC");
        assert_eq!(utc(1_796_118_600), "2026-12-01 09:50:00 UTC");
    }

    #[test]
    fn one_column_one_number_of_decimals() {
        assert_eq!(decimals_for(0.253), 3);
        assert_eq!(decimals_for(0.0052), 5);
        assert_eq!(decimals_for(12.5), 1);
        assert_eq!(fixed(Some(0.1), 3), "0.100");
        assert_eq!(fixed(Some(2e-9), 3), "2.00e-9");
    }

    #[test]
    fn inline_svg_drops_the_prolog_and_namespace() {
        let s = inline_svg(
            "<?xml version=\"1.0\"?>\n<svg width=\"1\" xmlns=\"http://www.w3.org/2000/svg\"></svg>",
        );
        assert_eq!(s, "<svg width=\"1\"></svg>");
    }
}
