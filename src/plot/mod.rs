//! The plot role: figures drawn from the written Parquet tables, never from in-memory run
//! state, so a study run on a cluster can be plotted (and reported) on a laptop.
//!
//! Every figure kind has a pure function `*_series(&Tables) -> Vec<Figure>` that turns table
//! rows into a [`Figure`]: panels of lines, bands, bars and reference marks, with every number
//! taken from a table column. [`render`] only draws such a description, so the tests can check
//! what a figure shows against the Parquet values without looking at pixels.
//!
//! Colours follow the filter label, in order of first appearance in `summary.parquet`, so a
//! filter has the same colour in every figure of a folder.

pub mod blocks;
pub mod divergence;
pub mod errors;
pub mod render;
pub mod report;
pub mod rmse;
pub mod trajectory;
pub mod ulog;

use std::path::{Path, PathBuf};

use polars::prelude::*;

use crate::error::PlotError;
use crate::output::manifest::Manifest;

/// A figure family; each draws the figures the folder's tables support.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash, clap::ValueEnum)]
pub enum FigureKind {
    /// The plane of the position roles (x against y) of the first traced run at the nominal
    /// noise scale (traces.parquet; systems with a planar position).
    Trajectory,
    /// Each quantity's estimate error over time with the ±3σ band around 0, in the first
    /// traced run at the nominal noise scale (traces.parquet).
    States,
    /// |e| over time: median and p5–p95 band across runs (steps.parquet).
    Errors,
    /// RMSE per noise scale as bars with p5–p95 whiskers (summary.parquet).
    #[value(name = "rmse_cases")]
    RmseCases,
    /// RMSE against the noise multiplier, with divergence thresholds (summary, divergence).
    #[value(name = "rmse_growth")]
    RmseGrowth,
    /// ANEES and ANIS over time with their χ² band (steps.parquet).
    Consistency,
    /// Per-run divergence multipliers (divergence_runs.parquet).
    #[value(name = "divergence_hist")]
    DivergenceHist,
    /// ANEES/ANIS and RMSE against the filter's Q scale (tuning.parquet).
    Tuning,
    /// The position route as projections: the plane and the altitude against time, with the
    /// truth, every estimate and the position fixes (traces.parquet; systems whose position
    /// roles include a vertical axis, the drone's north–east–down, L1's x, y, z).
    Route,
    /// ANEES per block of quantities sharing a unit (position, velocity, attitude), from the
    /// traced runs' covariances (traces.parquet `P_<qi>_<qj>`).
    #[value(name = "block_consistency")]
    BlockConsistency,
    /// NIS over time per aid source with its χ² band and the gate (`ulog nis` folders,
    /// ulog_samples.parquet).
    #[value(name = "ulog_nis")]
    UlogNis,
}

impl FigureKind {
    /// Every kind, in drawing order.
    pub const ALL: [FigureKind; 11] = [
        FigureKind::Trajectory,
        FigureKind::States,
        FigureKind::Errors,
        FigureKind::RmseCases,
        FigureKind::RmseGrowth,
        FigureKind::Consistency,
        FigureKind::DivergenceHist,
        FigureKind::Tuning,
        FigureKind::Route,
        FigureKind::BlockConsistency,
        FigureKind::UlogNis,
    ];

    /// The file-name prefix and CLI name.
    pub fn name(self) -> &'static str {
        match self {
            FigureKind::Trajectory => "trajectory",
            FigureKind::States => "states",
            FigureKind::Errors => "errors",
            FigureKind::RmseCases => "rmse_cases",
            FigureKind::RmseGrowth => "rmse_growth",
            FigureKind::Consistency => "consistency",
            FigureKind::DivergenceHist => "divergence_hist",
            FigureKind::Tuning => "tuning",
            FigureKind::Route => "route",
            FigureKind::BlockConsistency => "block_consistency",
            FigureKind::UlogNis => "ulog_nis",
        }
    }

    /// The figures of this kind the tables support (none when a table is absent).
    pub fn series(self, t: &Tables) -> Result<Vec<Figure>, PlotError> {
        match self {
            FigureKind::Trajectory => trajectory::trajectory_series(t),
            FigureKind::States => trajectory::states_series(t),
            FigureKind::Errors => errors::errors_series(t),
            FigureKind::RmseCases => rmse::rmse_cases_series(t),
            FigureKind::RmseGrowth => rmse::rmse_growth_series(t),
            FigureKind::Consistency => errors::consistency_series(t),
            FigureKind::DivergenceHist => divergence::divergence_hist_series(t),
            FigureKind::Tuning => rmse::tuning_series(t),
            FigureKind::Route => trajectory::route_series(t),
            FigureKind::BlockConsistency => blocks::block_consistency_series(t),
            // A study's tables have no flight logs; a `ulog nis` folder is drawn by `ulog`.
            FigureKind::UlogNis => Ok(Vec::new()),
        }
    }
}

/// Image format of the figure files.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, clap::ValueEnum)]
pub enum Format {
    /// PNG bitmap.
    #[default]
    Png,
    /// SVG vector graphics.
    Svg,
}

impl Format {
    /// The file extension.
    pub fn ext(self) -> &'static str {
        match self {
            Format::Png => "png",
            Format::Svg => "svg",
        }
    }
}

/// What a mark is coloured after.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Ink {
    /// The filter with this index in [`Tables::filters`].
    Filter(usize),
    /// The true state.
    Truth,
    /// Reference values (thresholds, χ² means).
    Reference,
    /// The i-th colour of the palette, for series that are not filters (noise scales).
    Palette(usize),
}

/// One bar of a bar chart: `[x0, x1]` wide, `y` high, optional whisker.
#[derive(Clone, Debug, PartialEq)]
pub struct Bar {
    /// Left edge.
    pub x0: f64,
    /// Right edge.
    pub x1: f64,
    /// Height.
    pub y: f64,
    /// Whisker (low, high), e.g. p5–p95.
    pub whisker: Option<(f64, f64)>,
}

/// One drawn element of a panel.
#[derive(Clone, Debug, PartialEq)]
pub enum Mark {
    /// A polyline.
    Line {
        /// Legend entry.
        label: Option<String>,
        /// Colour.
        ink: Ink,
        /// Dashed (reference curves).
        dashed: bool,
        /// (x, y) in drawing order.
        points: Vec<(f64, f64)>,
    },
    /// A shaded band between two curves.
    Band {
        /// Legend entry.
        label: Option<String>,
        /// Colour (drawn translucent).
        ink: Ink,
        /// (x, low, high).
        points: Vec<(f64, f64, f64)>,
    },
    /// A horizontal line across the panel.
    HLine {
        /// Legend entry.
        label: Option<String>,
        /// Colour.
        ink: Ink,
        /// Height.
        y: f64,
    },
    /// Marked points without a connecting line (measurement fixes).
    Scatter {
        /// Legend entry.
        label: Option<String>,
        /// Colour.
        ink: Ink,
        /// The points.
        points: Vec<(f64, f64)>,
    },
    /// A marked point.
    Point {
        /// Legend entry.
        label: Option<String>,
        /// Colour.
        ink: Ink,
        /// Position.
        x: f64,
        /// Position.
        y: f64,
        /// Text written beside it (its value), since the legend entry is shared by panels.
        text: Option<String>,
    },
    /// Bars.
    Bars {
        /// Legend entry.
        label: Option<String>,
        /// Colour.
        ink: Ink,
        /// The bars.
        bars: Vec<Bar>,
    },
}

/// One chart of a figure.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Panel {
    /// Caption.
    pub title: String,
    /// x-axis label with its unit.
    pub x_label: String,
    /// y-axis label with its unit.
    pub y_label: String,
    /// Logarithmic y axis.
    pub log_y: bool,
    /// Logarithmic x axis.
    pub log_x: bool,
    /// Category names at x = 0, 1, … (bar charts); `None` for a numeric axis.
    pub x_categories: Option<Vec<String>>,
    /// The y axis counts things: integer ticks only.
    pub integer_y: bool,
    /// x and y in the same unit (a map): one metre is as long on both axes.
    pub equal_aspect: bool,
    /// What is drawn, in order.
    pub marks: Vec<Mark>,
}

/// One figure file: a title and a grid of panels.
#[derive(Clone, Debug, PartialEq)]
pub struct Figure {
    /// Its kind.
    pub kind: FigureKind,
    /// File stem, e.g. `states_roll`.
    pub name: String,
    /// The scenario it shows (the report groups figures by it).
    pub scenario: String,
    /// Title above the panels.
    pub title: String,
    /// The panels, row-major.
    pub panels: Vec<Panel>,
}

/// The unit of a state or measurement name (`x` → `m`).
/// The unit of a column name that the manifest does not describe (the measurement components
/// of the built-in systems, and folders written before quantities had units).
pub fn fallback_unit(name: &str) -> &'static str {
    match name {
        "x" | "y" => "m",
        "xdot" | "ydot" => "m/s",
        "theta" => "rad",
        "thetadot" => "rad/s",
        "xddot" | "yddot" => "m/s²",
        _ => "",
    }
}

impl Tables {
    /// The unit of a quantity, as its system declared it (the manifest), or the fallback.
    pub fn unit<'a>(&'a self, name: &str) -> &'a str {
        self.manifest
            .as_ref()
            .and_then(|m| m.quantities.iter().find(|q| q.name == name))
            .map_or_else(|| fallback_unit(name), |q| q.unit.as_str())
    }

    /// `name [unit]`, or the bare name without a unit.
    pub fn with_unit(&self, name: &str) -> String {
        match self.unit(name) {
            "" => name.to_string(),
            u => format!("{name} [{u}]"),
        }
    }
}

/// A name safe in a file name (scenario and filter labels are free text in the spec). Not
/// injective (`x/y` and `x_y` both give `x_y`): [`all_figures`] makes the final names unique.
pub fn file_part(s: &str) -> String {
    s.chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' || c == '.' {
                c
            } else {
                '_'
            }
        })
        .collect()
}

/// Makes figure names unique, also ignoring case (macOS and Windows folders do): readable
/// names stay as they are, and every figure of a clash gets a suffix from its title, which
/// holds the raw scenario and filter text (`x/y` and `x_y` differ there), so a name does not
/// depend on which other figures a folder has. Titles that clash too get a running number.
pub fn unique_names(figs: &mut [Figure]) {
    use std::collections::BTreeMap;
    let mut count: BTreeMap<String, usize> = BTreeMap::new();
    for f in figs.iter() {
        *count.entry(f.name.to_lowercase()).or_default() += 1;
    }
    for f in figs.iter_mut() {
        if count[&f.name.to_lowercase()] > 1 {
            f.name = format!(
                "{}_{:08x}",
                f.name,
                crate::hash::fnv1a64(f.title.as_bytes()) as u32
            );
        }
    }
    let mut seen: BTreeMap<String, usize> = BTreeMap::new();
    for f in figs.iter_mut() {
        let n = seen.entry(f.name.to_lowercase()).or_default();
        *n += 1;
        if *n > 1 {
            f.name = format!("{}_{}", f.name, n);
        }
    }
}

/// Every figure of the given kinds (all when `only` is empty), with unique file names: what
/// `kfmc plot` draws and the report shows, in drawing order.
pub fn all_figures(t: &Tables, only: &[FigureKind]) -> Result<Vec<Figure>, PlotError> {
    let mut figs = Vec::new();
    for kind in FigureKind::ALL {
        if only.is_empty() || only.contains(&kind) {
            figs.extend(kind.series(t)?);
        }
    }
    unique_names(&mut figs);
    Ok(figs)
}

/// A number for titles and file names: `1`, `0.2`, `12.5`.
pub fn short(x: f64) -> String {
    let s = format!("{x}");
    if s.len() > 8 { format!("{x:.4}") } else { s }
}

/// A table of the result folder, with typed column access that names the file on error.
#[derive(Clone, Debug)]
pub struct Table {
    /// Where it was read from.
    pub path: PathBuf,
    /// Its rows (possibly a subset, see [`Table::read_where`]).
    pub df: DataFrame,
}

impl Table {
    /// Reads the whole table, or `None` when the file does not exist.
    pub fn read_optional(path: PathBuf) -> Result<Option<Table>, PlotError> {
        if !path.exists() {
            return Ok(None);
        }
        let df = crate::output::table::read(&path)?;
        Ok(Some(Table { path, df }))
    }

    /// Reads only the rows whose `noise_scale` passes `keep`, one column at a time, so a
    /// per-step table of a 250-scale sweep never sits in memory whole.
    pub fn read_where(
        path: PathBuf,
        keep: &dyn Fn(f64) -> bool,
    ) -> Result<Option<Table>, PlotError> {
        if !path.exists() {
            return Ok(None);
        }
        let polars_err = |source| crate::error::OutputError::Polars {
            action: "cannot read",
            path: path.clone(),
            source,
        };
        let open = || {
            crate::output::atomic::open_input(&path).map_err(|source| {
                crate::error::OutputError::Io {
                    action: "cannot open",
                    path: path.clone(),
                    source,
                }
            })
        };
        let names: Vec<String> = ParquetReader::new(open()?)
            .schema()
            .map_err(polars_err)?
            .iter_names()
            .map(|n| n.to_string())
            .collect();
        let read_col = |name: &str| {
            ParquetReader::new(open()?)
                .with_columns(Some(vec![name.to_string()]))
                .finish()
                .map_err(polars_err)
        };
        let key = Table {
            path: path.clone(),
            df: read_col("noise_scale")?,
        };
        let keep_rows: Vec<bool> = key
            .f64s("noise_scale")?
            .into_iter()
            .map(|v| v.is_some_and(keep))
            .collect();
        let height = keep_rows.iter().filter(|b| **b).count();
        let mask = BooleanChunked::from_slice("keep".into(), &keep_rows);
        let mut cols = Vec::with_capacity(names.len());
        for n in &names {
            let df = read_col(n)?.filter(&mask).map_err(polars_err)?;
            cols.extend(df.columns().iter().cloned());
        }
        let df = DataFrame::new(height, cols).map_err(polars_err)?;
        crate::output::table::unique_keys(&df, &path)?;
        Ok(Some(Table { path, df }))
    }

    fn column(&self, name: &str) -> Result<&Column, PlotError> {
        self.df.column(name).map_err(|_| PlotError::Columns {
            path: self.path.clone(),
            message: format!("no column `{name}`"),
        })
    }

    /// Whether the table has a column.
    pub fn has(&self, name: &str) -> bool {
        self.df.column(name).is_ok()
    }

    /// A numeric column as floats (integers are converted), nulls as `None`.
    pub fn f64s(&self, name: &str) -> Result<Vec<Option<f64>>, PlotError> {
        let c = self
            .column(name)?
            .cast(&DataType::Float64)
            .map_err(|e| PlotError::Columns {
                path: self.path.clone(),
                message: format!("column `{name}` is not numeric: {e}"),
            })?;
        Ok(c.f64()
            .map_err(|e| PlotError::Columns {
                path: self.path.clone(),
                message: format!("column `{name}`: {e}"),
            })?
            .iter()
            .collect())
    }

    /// A string column, nulls as "".
    ///
    /// The `filter` column comes back as the *variant*: a label with several Q/R scales in
    /// the table (or a scale other than 1) is keyed and labelled per scale, `kf Q×2`,
    /// `kf Q×2 R×0.5`, so every figure draws each variant as its own series. (The tuning
    /// table keeps the bare label: its scales are the figure's axis.)
    pub fn strs(&self, name: &str) -> Result<Vec<String>, PlotError> {
        if name == "filter"
            && self.has("q_scale")
            && self.has("r_scale")
            && !self.path.ends_with("tuning.parquet")
        {
            return self.variant_labels();
        }
        self.raw_strs(name)
    }

    fn variant_labels(&self) -> Result<Vec<String>, PlotError> {
        let labels = self.raw_strs("filter")?;
        let (q, r) = (self.f64s("q_scale")?, self.f64s("r_scale")?);
        let mut scales: std::collections::BTreeMap<&str, (Vec<u64>, Vec<u64>)> = Default::default();
        for (i, l) in labels.iter().enumerate() {
            let e = scales.entry(l.as_str()).or_default();
            for (v, set) in [(q[i], &mut e.0), (r[i], &mut e.1)] {
                let bits = v.unwrap_or(1.0).to_bits();
                if !set.contains(&bits) {
                    set.push(bits);
                }
            }
        }
        let one = 1.0f64.to_bits();
        Ok(labels
            .iter()
            .enumerate()
            .map(|(i, l)| {
                let (qs, rs) = &scales[l.as_str()];
                let mut out = l.clone();
                if qs.len() > 1 || qs[0] != one {
                    out.push_str(&format!(" Q×{}", short(q[i].unwrap_or(1.0))));
                }
                if rs.len() > 1 || rs[0] != one {
                    out.push_str(&format!(" R×{}", short(r[i].unwrap_or(1.0))));
                }
                out
            })
            .collect())
    }

    fn raw_strs(&self, name: &str) -> Result<Vec<String>, PlotError> {
        let c = self.column(name)?;
        Ok(c.str()
            .map_err(|e| PlotError::Columns {
                path: self.path.clone(),
                message: format!("column `{name}` is not text: {e}"),
            })?
            .iter()
            .map(|s| s.unwrap_or("").to_string())
            .collect())
    }

    /// Column names.
    pub fn names(&self) -> Vec<String> {
        self.df
            .get_column_names()
            .iter()
            .map(|n| n.to_string())
            .collect()
    }

    /// Rows.
    pub fn height(&self) -> usize {
        self.df.height()
    }
}

/// Distinct values in order of first appearance.
pub fn first_appearance(v: &[String]) -> Vec<String> {
    let mut out: Vec<String> = Vec::new();
    for s in v {
        if !out.contains(s) {
            out.push(s.clone());
        }
    }
    out
}

/// The noise scales whose per-step figures are drawn: all of them up to four, otherwise the
/// smallest, 1 (the nominal noise) when present, and the largest — a 250-point sweep would
/// otherwise produce a thousand near-identical files.
pub fn plotted_scales(all: &[f64]) -> Vec<f64> {
    if all.len() <= 4 {
        return all.to_vec();
    }
    let mut v = vec![all[0]];
    if all.contains(&1.0) && all[0] != 1.0 {
        v.push(1.0);
    }
    v.push(all[all.len() - 1]);
    v.dedup();
    v
}

/// The nominal noise scale of a study's scales: 1 when the study has it, otherwise the scale
/// nearest 1 on a log scale (of two as near, the smaller; positive scales before 0). The
/// figures of single traced runs show this cell, whatever the sweep's first scale is.
pub fn nominal_scale(all: &[f64]) -> Option<f64> {
    let distance = |s: f64| {
        if s > 0.0 { s.ln().abs() } else { f64::INFINITY }
    };
    all.iter()
        .copied()
        .filter(|s| !s.is_nan())
        .min_by(|a, b| distance(*a).total_cmp(&distance(*b)).then(a.total_cmp(b)))
}

/// The tables of one result folder, loaded once for every figure kind.
#[derive(Clone, Debug)]
pub struct Tables {
    /// The folder.
    pub dir: PathBuf,
    /// `summary.parquet` (required).
    pub summary: Table,
    /// `steps.parquet`, restricted to [`plotted_scales`].
    pub steps: Option<Table>,
    /// `traces.parquet`, restricted to the nominal noise scale ([`nominal_scale`]).
    pub traces: Option<Table>,
    /// `divergence.parquet`.
    pub divergence: Option<Table>,
    /// `divergence_runs.parquet`.
    pub divergence_runs: Option<Table>,
    /// `tuning.parquet`.
    pub tuning: Option<Table>,
    /// `consistency.parquet`.
    pub consistency: Option<Table>,
    /// `manifest.toml`, when readable.
    pub manifest: Option<Manifest>,
    /// Filter variants (label with its Q/R scales, see [`Table::strs`]) in order of first
    /// appearance in the summary: the colour order.
    pub filters: Vec<String>,
    /// The spec's label of each entry of `filters` (`kf` for `kf Q×2`).
    pub filter_labels: Vec<String>,
    /// Scenarios in order of first appearance in the summary.
    pub scenarios: Vec<String>,
    /// State names in order of first appearance in the summary.
    pub states: Vec<String>,
    /// Distinct noise scales, ascending.
    pub noise_scales: Vec<f64>,
    /// Measurement components (the ANIS reference), when the folder says.
    pub n_meas: Option<usize>,
}

impl Tables {
    /// Loads the tables of `dir`. `summary.parquet` must exist; the others are optional.
    pub fn load(dir: &Path) -> Result<Tables, PlotError> {
        let verified = crate::output::folder::verify(dir)?;
        let spath = dir.join("summary.parquet");
        let summary = Table::read_optional(spath.clone())?.ok_or(PlotError::MissingTable {
            path: spath,
            why: "every figure and the report need it; is this a folder written by `kfmc run`?"
                .into(),
        })?;
        let variants = summary.strs("filter")?;
        let filters = first_appearance(&variants);
        let raw = summary.raw_strs("filter")?;
        let filter_labels = filters
            .iter()
            .map(|f| {
                let i = variants.iter().position(|v| v == f).unwrap_or(0);
                raw.get(i).cloned().unwrap_or_default()
            })
            .collect();
        let scenarios = first_appearance(&summary.strs("scenario")?);
        let states = first_appearance(&summary.strs("state")?);
        let mut noise_scales: Vec<f64> =
            summary.f64s("noise_scale")?.into_iter().flatten().collect();
        noise_scales.sort_by(f64::total_cmp);
        noise_scales.dedup();
        let plotted = plotted_scales(&noise_scales);
        let nominal = nominal_scale(&noise_scales);
        let steps = Table::read_where(dir.join("steps.parquet"), &|s| plotted.contains(&s))?;
        let traces = Table::read_where(dir.join("traces.parquet"), &|s| Some(s) == nominal)?;
        let manifest = Some(verified);
        let n_meas = traces
            .as_ref()
            .map(|t| t.names().iter().filter(|n| n.starts_with("z_")).count())
            .filter(|&n| n > 0)
            .or_else(|| {
                // No traces: the manifest names the measurement components.
                let m = manifest.as_ref()?;
                (!m.measurements.is_empty()).then_some(m.measurements.len())
            });
        Ok(Tables {
            dir: dir.to_path_buf(),
            summary,
            steps,
            traces,
            divergence: Table::read_optional(dir.join("divergence.parquet"))?,
            divergence_runs: Table::read_optional(dir.join("divergence_runs.parquet"))?,
            tuning: Table::read_optional(dir.join("tuning.parquet"))?,
            consistency: Table::read_optional(dir.join("consistency.parquet"))?,
            manifest,
            filters,
            filter_labels,
            scenarios,
            states,
            noise_scales,
            n_meas,
        })
    }

    /// The spec's label of a filter variant.
    pub fn label_of<'a>(&'a self, variant: &'a str) -> &'a str {
        self.filters
            .iter()
            .position(|f| f == variant)
            .map_or(variant, |i| self.filter_labels[i].as_str())
    }

    /// The colour index of a filter label.
    pub fn ink(&self, filter: &str) -> Ink {
        Ink::Filter(
            self.filters
                .iter()
                .position(|f| f == filter)
                .unwrap_or(self.filters.len()),
        )
    }
}

/// Options of [`plot_all`].
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PlotOptions {
    /// Output folder; default `<dir>/figures`.
    pub out: Option<PathBuf>,
    /// Image format.
    pub format: Format,
    /// Only these kinds; empty = all.
    pub only: Vec<FigureKind>,
}

/// Writes the HTML report of `dir` (a study's, or a `kfmc ulog nis` folder's) to `out`
/// (default `<dir>/report.html`); returns the path.
pub fn write_report(dir: &Path, out: Option<&Path>) -> Result<PathBuf, PlotError> {
    if crate::output::folder::verify(dir)?.kind() == crate::output::manifest::StudyKind::Ulog {
        return report::write_html(dir, out, || ulog::render_html(dir));
    }
    report::write_report(dir, out)
}

/// Draws every figure the tables of `dir` support; returns the files written.
pub fn plot_all(dir: &Path, opts: &PlotOptions) -> Result<Vec<PathBuf>, PlotError> {
    let out = opts.out.clone().unwrap_or_else(|| dir.join("figures"));
    // Figures inside the result folder are the study's: drawn under its lock from the tables
    // it holds, and listed in its manifest before they are written. A folder named outside
    // it is written as named.
    let inside = crate::output::folder::relative_inside(dir, &out);
    let held = match &inside {
        Some(_) if dir.is_dir() => Some(crate::output::folder::StudyFolder::lock(dir)?),
        _ => None,
    };
    let ulog_folder =
        crate::output::folder::verify(dir)?.kind() == crate::output::manifest::StudyKind::Ulog;
    let figures = if ulog_folder {
        ulog::figures(dir, &opts.only)?
    } else {
        study_figures(dir, &opts.only)?
    };
    if let (Some(held), Some(rel)) = (&held, &inside) {
        let files: Vec<String> = figures
            .iter()
            .map(|fig| {
                let name = format!("{}.{}", fig.name, opts.format.ext());
                if rel.is_empty() {
                    name
                } else {
                    format!("{rel}/{name}")
                }
            })
            .collect();
        held.claim_files(&files, &|_| false)?;
    }
    std::fs::create_dir_all(&out).map_err(|source| PlotError::Io {
        action: "cannot create the figure folder",
        path: out.clone(),
        source,
    })?;
    let mut written = Vec::new();
    for fig in figures {
        let path = out.join(format!("{}.{}", fig.name, opts.format.ext()));
        render::to_file(&fig, &path, opts.format)?;
        written.push(path);
    }
    Ok(written)
}

/// The figures of a study folder's tables; a kind asked for by name that the data cannot
/// give is an error, not an empty success.
fn study_figures(dir: &Path, only: &[FigureKind]) -> Result<Vec<Figure>, PlotError> {
    let tables = Tables::load(dir)?;
    let figures = all_figures(&tables, only)?;
    let lacking: Vec<&str> = only
        .iter()
        .filter(|k| !figures.iter().any(|f| f.kind == **k))
        .map(|k| k.name())
        .collect();
    if !lacking.is_empty() {
        let mut available: Vec<&str> = all_figures(&tables, &[])?
            .iter()
            .map(|f| f.kind.name())
            .collect();
        available.dedup();
        return Err(PlotError::NoFigures {
            path: dir.to_path_buf(),
            lacking: lacking.join(", "),
            available: if available.is_empty() {
                "none".into()
            } else {
                available.join(", ")
            },
        });
    }
    Ok(figures)
}

#[cfg(test)]
mod tests {
    use super::nominal_scale;

    #[test]
    fn the_nominal_scale_is_1_or_the_nearest_on_a_log_scale() {
        assert_eq!(nominal_scale(&[0.5, 1.0, 2.0, 7.0]), Some(1.0));
        // ln 3 = 1.10 is nearer 0 than ln 0.25 = −1.39; 0 is never nearest.
        assert_eq!(nominal_scale(&[0.0, 0.25, 3.0, 10.0]), Some(3.0));
        // Equally near on a log scale: the smaller.
        assert_eq!(nominal_scale(&[0.5, 2.0]), Some(0.5));
        assert_eq!(nominal_scale(&[0.0]), Some(0.0));
        assert_eq!(nominal_scale(&[]), None);
    }
}
