//! `kfmc summary DIR`: the RMSE table (and divergence points) in the terminal, read from the
//! written Parquet tables.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::Path;

use polars::prelude::*;

use crate::error::OutputError;
use crate::metrics::consistency::verdict_band;
use crate::output::table::read;

fn fmt_err(path: &Path, e: PolarsError) -> OutputError {
    OutputError::Polars {
        action: "unexpected columns in",
        path: path.to_path_buf(),
        source: e,
    }
}

fn strs(df: &DataFrame, name: &str, path: &Path) -> Result<Vec<String>, OutputError> {
    let c = df.column(name).map_err(|e| fmt_err(path, e))?;
    Ok(c.str()
        .map_err(|e| fmt_err(path, e))?
        .iter()
        .map(|s| s.unwrap_or("").to_string())
        .collect())
}

fn f64s(df: &DataFrame, name: &str, path: &Path) -> Result<Vec<Option<f64>>, OutputError> {
    let c = df.column(name).map_err(|e| fmt_err(path, e))?;
    Ok(c.f64().map_err(|e| fmt_err(path, e))?.iter().collect())
}

/// A number in 4 significant digits, or "—" for null.
fn num(v: Option<f64>) -> String {
    match v {
        None => "—".into(),
        Some(x) if x != 0.0 && (x.abs() >= 1e4 || x.abs() < 1e-3) => format!("{x:.3e}"),
        Some(x) => format!("{:.4}", x),
    }
}

/// Whether a row at truth-noise multiplier `nz` is hidden by `--noise-scale`.
fn hidden(noise_scale: Option<f64>, nz: f64) -> bool {
    noise_scale.is_some_and(|s| (s - nz).abs() > 1e-12 * s.abs().max(1.0))
}

/// Why a verified folder without summary.parquet has no summary: what kind of folder it is.
fn not_a_study(dir: &Path, manifest: &crate::output::manifest::Manifest) -> OutputError {
    let holds: Vec<&str> = manifest.tables.iter().map(|t| t.name.as_str()).collect();
    let kind = if manifest.exchange.is_some() {
        "a simulation (`kfmc simulate`)"
    } else if holds == ["power"] {
        "a power study (`kfmc power`)"
    } else {
        "a result folder without an RMSE summary"
    };
    OutputError::Mismatch {
        path: dir.to_path_buf(),
        why: format!(
            "is {kind} holding {}, not a study with summary.parquet: `kfmc summary` reads the folders of `kfmc run`, `score` and `check`",
            holds.join(", ")
        ),
    }
}

/// The RMSE table's content: rows (scenario, noise scale, filter variant) in table order, the
/// states in order of first appearance, and the "mean ± std" text of each (row, state).
struct RmseTable {
    states: Vec<String>,
    rows: Vec<(String, f64, String)>,
    cells: BTreeMap<(usize, String), String>,
}

impl RmseTable {
    /// Reads summary.parquet; also returns every row's noise scale (for the error that none
    /// matches `noise_scale`).
    fn read(
        path: &Path,
        noise_scale: Option<f64>,
    ) -> Result<(RmseTable, Vec<Option<f64>>), OutputError> {
        let df = read(path)?;
        let scen = strs(&df, "scenario", path)?;
        let filt = strs(&df, "filter", path)?;
        let state = strs(&df, "state", path)?;
        let noise = f64s(&df, "noise_scale", path)?;
        // Filter variants of one label differ in their Q/R multipliers: show them in the label.
        let q = f64s(&df, "q_scale", path)?;
        let r = f64s(&df, "r_scale", path)?;
        let filt: Vec<String> = filt
            .iter()
            .enumerate()
            .map(|(i, f)| match (q[i], r[i]) {
                (Some(q), Some(r)) if q != 1.0 || r != 1.0 => format!("{f} q×{q} r×{r}"),
                _ => f.clone(),
            })
            .collect();
        let mean = f64s(&df, "rmse_mean", path)?;
        let std = f64s(&df, "rmse_std", path)?;

        let mut t = RmseTable {
            states: Vec::new(),
            rows: Vec::new(),
            cells: BTreeMap::new(),
        };
        for i in 0..df.height() {
            let nz = noise[i].unwrap_or(f64::NAN);
            if hidden(noise_scale, nz) {
                continue;
            }
            if !t.states.contains(&state[i]) {
                t.states.push(state[i].clone());
            }
            let key = (scen[i].clone(), nz, filt[i].clone());
            let idx = match t.rows.iter().position(|r| *r == key) {
                Some(p) => p,
                None => {
                    t.rows.push(key);
                    t.rows.len() - 1
                }
            };
            let text = match std[i] {
                Some(s) => format!("{} ± {}", num(mean[i]), num(Some(s))),
                None => num(mean[i]),
            };
            t.cells.insert((idx, state[i].clone()), text);
        }
        Ok((t, noise))
    }

    /// Widths of the scenario and filter columns (the divergence section lines up with them).
    fn key_widths(&self) -> (usize, usize) {
        let sw = self
            .rows
            .iter()
            .map(|r| r.0.len())
            .max()
            .unwrap_or(8)
            .max(8);
        let fw = self
            .rows
            .iter()
            .map(|r| r.2.len())
            .max()
            .unwrap_or(6)
            .max(6);
        (sw, fw)
    }

    fn render(&self, out: &mut String) {
        let (states, rows, cells) = (&self.states, &self.rows, &self.cells);
        let widths: Vec<usize> = states
            .iter()
            .map(|s| {
                (0..rows.len())
                    .filter_map(|r| cells.get(&(r, s.clone())).map(|c| c.chars().count()))
                    .chain([s.len() + 5])
                    .max()
                    .unwrap_or(8)
            })
            .collect();
        let (sw, fw) = self.key_widths();
        let _ = write!(
            out,
            "RMSE (mean ± std over runs)\n{:<sw$}  {:>11}  {:<fw$}",
            "scenario", "noise_scale", "filter"
        );
        for (s, w) in states.iter().zip(&widths) {
            let _ = write!(out, "  {:>w$}", format!("rmse_{s}"));
        }
        out.push('\n');
        for (ri, (s, nz, f)) in rows.iter().enumerate() {
            let _ = write!(out, "{s:<sw$}  {:>11}  {f:<fw$}", format!("{nz}"));
            for (st, w) in states.iter().zip(&widths) {
                let c = cells
                    .get(&(ri, st.clone()))
                    .cloned()
                    .unwrap_or_else(|| "—".into());
                let _ = write!(out, "  {c:>w$}");
            }
            out.push('\n');
        }
    }
}

/// Renders the summary of a result folder as text.
pub fn render(dir: &Path, noise_scale: Option<f64>) -> Result<String, OutputError> {
    let manifest = crate::output::folder::verify(dir)?;
    if !manifest.tables.iter().any(|t| t.name == "summary") {
        return Err(not_a_study(dir, &manifest));
    }
    let path = dir.join("summary.parquet");
    let (rmse, noise) = RmseTable::read(&path, noise_scale)?;
    let mut out = String::new();
    if rmse.rows.is_empty()
        && let Some(wanted) = noise_scale
    {
        let mut scales: Vec<f64> = noise.iter().flatten().copied().collect();
        scales.sort_by(f64::total_cmp);
        scales.dedup();
        let scales: Vec<String> = scales.iter().map(|s| s.to_string()).collect();
        return Err(OutputError::Mismatch {
            path,
            why: format!(
                "has no rows at noise scale {wanted} (it has {})",
                scales.join(", ")
            ),
        });
    }
    if rmse.rows.is_empty() {
        out.push_str("no rows match\n");
        return Ok(out);
    }
    rmse.render(&mut out);

    let cpath = dir.join("consistency.parquet");
    if cpath.exists() {
        out.push_str(&consistency_section(&cpath, noise_scale)?);
    }

    let spath = dir.join("sensors.parquet");
    if spath.exists() {
        out.push_str(&sensors_section(&spath, noise_scale)?);
    }

    let dpath = dir.join("divergence.parquet");
    if dpath.exists() {
        out.push_str(&divergence_section(&dpath, rmse.key_widths())?);
    }
    Ok(out)
}

/// The divergence points, one line per (scenario, filter, state), its scenario and filter
/// columns `(sw, fw)` wide.
fn divergence_section(path: &Path, (sw, fw): (usize, usize)) -> Result<String, OutputError> {
    let d = read(path)?;
    let scen = strs(&d, "scenario", path)?;
    let filt = strs(&d, "filter", path)?;
    let state = strs(&d, "state", path)?;
    let thr = f64s(&d, "threshold", path)?;
    let mc = f64s(&d, "mc_divergence_scale", path)?;
    let p50 = f64s(&d, "run_divergence_p50", path)?;
    let mut out = format!(
        "\nDivergence: first noise scale whose RMSE exceeds the threshold (— = none up to the largest scale)\n{:<sw$}  {:<fw$}  {:<9}  {:>9}  {:>11}  {:>15}\n",
        "scenario", "filter", "state", "threshold", "mc_mean", "run_median"
    );
    for i in 0..d.height() {
        let _ = writeln!(
            out,
            "{:<sw$}  {:<fw$}  {:<9}  {:>9}  {:>11}  {:>15}",
            scen[i],
            filt[i],
            state[i],
            num(thr[i]),
            num(mc[i]),
            num(p50[i])
        );
    }
    Ok(out)
}

/// The world's own sensor metrics (e.g. each raw sensor's RMSE against the truth), one line
/// per cell × metric.
fn sensors_section(path: &Path, noise_scale: Option<f64>) -> Result<String, OutputError> {
    let df = read(path)?;
    let scen = strs(&df, "scenario", path)?;
    let metric = strs(&df, "metric", path)?;
    let noise = f64s(&df, "noise_scale", path)?;
    let (mean, p05, p95) = (
        f64s(&df, "mean", path)?,
        f64s(&df, "p05", path)?,
        f64s(&df, "p95", path)?,
    );
    let sw = scen.iter().map(|s| s.len()).max().unwrap_or(8).max(8);
    let mw = metric.iter().map(|s| s.len()).max().unwrap_or(6).max(6);
    let mut out = format!(
        "\nSensors (the world's metrics: mean [p5, p95] over runs)\n{:<sw$}  {:>11}  {:<mw$}  {:>10}  {:>21}\n",
        "scenario", "noise_scale", "metric", "mean", "[p5, p95]"
    );
    for i in 0..df.height() {
        let nz = noise[i].unwrap_or(f64::NAN);
        if hidden(noise_scale, nz) {
            continue;
        }
        let _ = writeln!(
            out,
            "{:<sw$}  {:>11}  {:<mw$}  {:>10}  {:>21}",
            scen[i],
            format!("{nz}"),
            metric[i],
            num(mean[i]),
            format!("[{}, {}]", num(p05[i]), num(p95[i]))
        );
    }
    Ok(out)
}

/// A consistency line's key: scenario, noise scale, filter variant, runs, α.
type ConsistencyKey = [String; 5];

/// The columns of consistency.parquet the summary shows.
struct Consistency {
    rows: usize,
    scen: Vec<String>,
    filt: Vec<String>,
    test: Vec<String>,
    dirn: Vec<String>,
    noise: Vec<Option<f64>>,
    q: Vec<Option<f64>>,
    r: Vec<Option<f64>>,
    stat: Vec<Option<f64>>,
    lo: Vec<Option<f64>>,
    hi: Vec<Option<f64>>,
    alpha: Vec<Option<f64>>,
    dof: Vec<Option<f64>>,
    p_value: Vec<Option<f64>>,
    pass: Vec<Option<bool>>,
    runs: Vec<Option<i64>>,
}

impl Consistency {
    fn read(path: &Path) -> Result<Consistency, OutputError> {
        let df = read(path)?;
        let scen = strs(&df, "scenario", path)?;
        let filt = strs(&df, "filter", path)?;
        let test = strs(&df, "test", path)?;
        let dirn = strs(&df, "direction", path)?;
        let noise = f64s(&df, "noise_scale", path)?;
        let (q, r) = (f64s(&df, "q_scale", path)?, f64s(&df, "r_scale", path)?);
        let (stat, lo, hi) = (
            f64s(&df, "statistic", path)?,
            f64s(&df, "lower", path)?,
            f64s(&df, "upper", path)?,
        );
        let alpha = f64s(&df, "alpha", path)?;
        let (dof, p_value) = (f64s(&df, "dof", path)?, f64s(&df, "p_value", path)?);
        let pass: Vec<Option<bool>> = df
            .column("pass")
            .and_then(|c| c.bool().cloned())
            .map_err(|e| fmt_err(path, e))?
            .iter()
            .collect();
        let runs: Vec<Option<i64>> = df
            .column("runs")
            .and_then(|c| c.i64().cloned())
            .map_err(|e| fmt_err(path, e))?
            .iter()
            .collect();
        Ok(Consistency {
            rows: df.height(),
            scen,
            filt,
            test,
            dirn,
            noise,
            q,
            r,
            stat,
            lo,
            hi,
            alpha,
            dof,
            p_value,
            pass,
            runs,
        })
    }

    fn key_of(&self, i: usize) -> ConsistencyKey {
        let g = |v: Option<f64>| v.map_or("—".to_string(), |x| format!("{x}"));
        let label = match (self.q[i], self.r[i]) {
            (Some(q), Some(r)) if q != 1.0 || r != 1.0 => format!("{} q×{q} r×{r}", self.filt[i]),
            _ => self.filt[i].clone(),
        };
        [
            self.scen[i].clone(),
            g(self.noise[i]),
            label,
            self.runs[i].map_or("—".into(), |n| n.to_string()),
            g(self.alpha[i]),
        ]
    }

    /// The text of row `i`'s verdict.
    fn verdict(&self, i: usize) -> String {
        match self.pass[i] {
            Some(true) => "pass".into(),
            _ if self.dirn[i].is_empty() => "FAIL".into(),
            _ => format!("FAIL ({})", self.dirn[i]),
        }
    }

    /// The text of row `i`'s statistic in its band; in the verdict's α/2 band when the test is
    /// one of the verdict's components (`in_verdict`).
    fn in_band(&self, i: usize, in_verdict: bool) -> String {
        let (stat, lo, hi, alpha) = (self.stat[i], self.lo[i], self.hi[i], self.alpha[i]);
        let band = in_verdict
            .then(|| verdict_band(&self.test[i], lo, hi, self.dof[i], alpha?))
            .flatten();
        match band {
            // The verdict's decision (p > α/2), with the band it is equivalent to.
            Some(b) => {
                let out = self.p_value[i].is_none_or(|p| p <= alpha.unwrap_or(0.0) / 2.0);
                format!(
                    "{} [{}, {}]{}",
                    num(stat),
                    num(Some(b.lo)),
                    num(Some(b.hi)),
                    if out { " outside" } else { "" }
                )
            }
            None => format!(
                "{} [{}, {}]{}",
                num(stat),
                num(lo),
                num(hi),
                if self.pass[i] == Some(false) {
                    " outside"
                } else {
                    ""
                }
            ),
        }
    }

    /// The lines' keys in table order, each with its [ANEES, ANIS, x0 NEES, verdict] texts.
    fn lines(&self, noise_scale: Option<f64>) -> (Vec<ConsistencyKey>, Vec<[String; 4]>) {
        // Keys with a verdict: their ANEES and ANIS are shown in the α/2 bands it judges by.
        let judged: Vec<ConsistencyKey> = (0..self.rows)
            .filter(|&i| self.test[i] == "verdict")
            .map(|i| self.key_of(i))
            .collect();
        let mut keys: Vec<ConsistencyKey> = Vec::new();
        let mut cols: Vec<[String; 4]> = Vec::new();
        for i in 0..self.rows {
            if hidden(noise_scale, self.noise[i].unwrap_or(f64::NAN)) {
                continue;
            }
            let slot = match self.test[i].as_str() {
                "nees_time_average" => 0,
                "nis_time_average" => 1,
                "initial_nees" => 2,
                "verdict" => 3,
                _ => continue,
            };
            let key = self.key_of(i);
            let in_verdict = slot < 2 && judged.contains(&key);
            let idx = match keys.iter().position(|k| *k == key) {
                Some(p) => p,
                None => {
                    keys.push(key);
                    cols.push(Default::default());
                    keys.len() - 1
                }
            };
            cols[idx][slot] = if slot == 3 {
                self.verdict(i)
            } else {
                self.in_band(i, in_verdict)
            };
        }
        (keys, cols)
    }
}

/// One line per cell × filter × (runs, α): the time-averaged NEES and NIS with their bands,
/// the initial-estimate NEES when there is one, and the verdict.
fn consistency_section(path: &Path, noise_scale: Option<f64>) -> Result<String, OutputError> {
    let (keys, cols) = Consistency::read(path)?.lines(noise_scale);
    let mut out = String::new();
    if keys.is_empty() {
        return Ok(out);
    }
    let has_x0 = cols.iter().any(|c| !c[2].is_empty());
    let heads = ["scenario", "noise_scale", "filter", "runs", "alpha"];
    let col_heads = ["ANEES [band]", "ANIS [band]", "x0 NEES [band]", "verdict"];
    let shown: Vec<usize> = (0..4).filter(|&c| c != 2 || has_x0).collect();
    let kw: Vec<usize> = (0..5)
        .map(|j| {
            keys.iter()
                .map(|k| k[j].chars().count())
                .chain([heads[j].len()])
                .max()
                .unwrap_or(4)
        })
        .collect();
    let cw: Vec<usize> = (0..4)
        .map(|j| {
            cols.iter()
                .map(|c| c[j].chars().count().max(1))
                .chain([col_heads[j].chars().count()])
                .max()
                .unwrap_or(4)
        })
        .collect();
    out.push_str(
        "\nConsistency (run-and-time averages; ANEES and ANIS in the χ² bands at α/2 the verdict judges by (at α in a cell without a verdict): it passes when both lie inside, i.e. its Bonferroni p = 2·min(p_NEES, p_NIS) exceeds α; x0 NEES at α)\n",
    );
    let mut line = String::new();
    for j in 0..5 {
        let _ = write!(line, "{:<w$}  ", heads[j], w = kw[j]);
    }
    for &j in &shown {
        let _ = write!(line, "{:<w$}  ", col_heads[j], w = cw[j]);
    }
    out.push_str(line.trim_end());
    out.push('\n');
    for (k, c) in keys.iter().zip(&cols) {
        let mut line = String::new();
        for j in 0..5 {
            let _ = write!(line, "{:<w$}  ", k[j], w = kw[j]);
        }
        for &j in &shown {
            let text = if c[j].is_empty() {
                "—"
            } else {
                c[j].as_str()
            };
            let _ = write!(line, "{:<w$}  ", text, w = cw[j]);
        }
        out.push_str(line.trim_end());
        out.push('\n');
    }
    Ok(out)
}

/// The arguments of `kfmc summary`.
#[derive(Debug, clap::Args)]
pub struct Summary {
    /// A folder written by `kfmc run`.
    pub dir: std::path::PathBuf,
    /// Only this truth-noise multiplier.
    #[arg(long)]
    pub noise_scale: Option<f64>,
}

impl Summary {
    /// Runs the command.
    pub(super) fn execute(self) -> anyhow::Result<()> {
        let Self { dir, noise_scale } = self;
        if let Some(x) = noise_scale.filter(|x| !x.is_finite() || *x <= 0.0) {
            return Err(super::UsageError {
                flag: "--noise-scale".into(),
                message: format!("{x} is not a truth-noise multiplier (a finite number > 0)"),
            }
            .into());
        }
        let text = render(&dir, noise_scale)
            .map_err(crate::error::KfmcError::from)
            .map_err(|e| {
                anyhow::Error::from(e).context(format!("reading results in {}", dir.display()))
            })?;
        super::emit(&text);
        Ok(())
    }
}
