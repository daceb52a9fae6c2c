//! Draws a [`Figure`] with plotters, to PNG or SVG, with the bundled DejaVu Sans so that text
//! renders on a machine without any font package (plotters' `ab_glyph` backend reads only
//! fonts registered at runtime).

use std::path::Path;
use std::sync::OnceLock;

use plotters::coord::Shift;
use plotters::coord::ranged1d::{DefaultFormatting, KeyPointHint};
use plotters::prelude::*;
use plotters::style::FontStyle;

use super::{Bar, Figure, Format, Ink, Mark, Panel};
use crate::error::PlotError;

/// DejaVu Sans (Bitstream Vera licence, `assets/fonts/DejaVuSans.LICENSE`).
static FONT: &[u8] = include_bytes!("../../assets/fonts/DejaVuSans.ttf");

/// Registers the bundled font as plotters' `sans-serif` once per process.
fn ensure_font() -> Result<(), PlotError> {
    static DONE: OnceLock<bool> = OnceLock::new();
    let ok = *DONE.get_or_init(|| {
        plotters::style::register_font("sans-serif", FontStyle::Normal, FONT).is_ok()
    });
    if ok {
        Ok(())
    } else {
        Err(PlotError::Draw {
            path: "assets/fonts/DejaVuSans.ttf".into(),
            message: "the bundled font is not a valid TrueType font".into(),
        })
    }
}

/// Tableau 10: distinguishable, and readable by most colour-blind viewers.
const PALETTE: [(u8, u8, u8); 10] = [
    (31, 119, 180),
    (255, 127, 14),
    (44, 160, 44),
    (214, 39, 40),
    (148, 103, 189),
    (140, 86, 75),
    (227, 119, 194),
    (188, 189, 34),
    (23, 190, 207),
    (127, 127, 127),
];

fn color(ink: Ink) -> RGBColor {
    match ink {
        Ink::Filter(i) | Ink::Palette(i) => {
            let (r, g, b) = PALETTE[i % PALETTE.len()];
            RGBColor(r, g, b)
        }
        Ink::Truth => RGBColor(0, 0, 0),
        Ink::Reference => RGBColor(90, 90, 90),
    }
}

/// (columns, rows) of the panel grid: at most three columns, so that a figure keeps its
/// text readable when the report scales it to a 1280 px window.
fn grid(n: usize) -> (usize, usize) {
    match n {
        0 | 1 => (1, 1),
        2 => (2, 1),
        4 => (2, 2),
        n => (3, n.div_ceil(3)),
    }
}

/// The most category labels an x axis writes; beyond, every k-th category is labelled.
const MAX_CATEGORY_LABELS: usize = 12;

/// Font sizes (px). The legend and tick text stay at 13–14 px so that a figure scaled to 75 %
/// in the report still reads at about 10 px.
const TITLE_PX: u32 = 22;
const CAPTION_PX: u32 = 17;
const TICK_PX: u32 = 13;
const AXIS_PX: u32 = 14;
const LEGEND_PX: u32 = 14;
/// Rough advance of one DejaVu Sans character at [`LEGEND_PX`], for sizing the legend.
const LEGEND_CHAR_PX: u32 = 8;
const LEGEND_ROW_PX: u32 = 22;

/// How a legend entry is drawn.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Swatch {
    Line { dashed: bool },
    Area,
    Dot,
    Bar,
}

/// One legend entry of a figure.
#[derive(Clone, Debug, PartialEq)]
struct Entry {
    label: String,
    ink: Ink,
    swatch: Swatch,
}

/// The figure's legend: every labelled mark of every panel, once per label, in order of first
/// appearance. One legend per figure, beside the panels and never on the data.
fn legend(fig: &Figure) -> Vec<Entry> {
    let mut out: Vec<Entry> = Vec::new();
    for p in &fig.panels {
        for m in &p.marks {
            let (label, ink, swatch) = match m {
                Mark::Line {
                    label, ink, dashed, ..
                } => (label, *ink, Swatch::Line { dashed: *dashed }),
                Mark::Band { label, ink, .. } => (label, *ink, Swatch::Area),
                Mark::HLine { label, ink, .. } => (label, *ink, Swatch::Line { dashed: true }),
                Mark::Point { label, ink, .. } | Mark::Scatter { label, ink, .. } => {
                    (label, *ink, Swatch::Dot)
                }
                Mark::Bars { label, ink, .. } => (label, *ink, Swatch::Bar),
            };
            if let Some(l) = label
                && !out.iter().any(|e| e.label == *l)
            {
                out.push(Entry {
                    label: l.clone(),
                    ink,
                    swatch,
                });
            }
        }
    }
    out
}

/// Pixel layout of a figure.
struct Layout {
    cols: usize,
    rows: usize,
    panel_w: u32,
    panel_h: u32,
    legend_w: u32,
    title_h: u32,
}

fn layout(fig: &Figure) -> Layout {
    let (cols, rows) = grid(fig.panels.len());
    let single = fig.panels.len() <= 1;
    let entries = legend(fig);
    let longest = entries
        .iter()
        .map(|e| e.label.chars().count() as u32)
        .max()
        .unwrap_or(0);
    let legend_w = if entries.is_empty() {
        0
    } else {
        (48 + LEGEND_CHAR_PX * longest).clamp(140, 380)
    };
    let (panel_w, panel_h) = if single { (720, 520) } else { (450, 340) };
    let title_h = 40;
    // A long legend lengthens the figure rather than running off its bottom.
    let needed = entries.len() as u32 * LEGEND_ROW_PX + 20;
    let panel_h = panel_h.max(needed.div_ceil(rows as u32));
    Layout {
        cols,
        rows,
        panel_w,
        panel_h,
        legend_w,
        title_h,
    }
}

/// Pixel size of a figure.
pub fn size(fig: &Figure) -> (u32, u32) {
    let l = layout(fig);
    (
        l.cols as u32 * l.panel_w + l.legend_w,
        l.rows as u32 * l.panel_h + l.title_h,
    )
}

/// Draws `fig` into a file of the given format, atomically: the image is made in memory and
/// written by [`crate::output::folder::write_atomic`] (temporary file beside it, fsync,
/// rename), so a full disk or a kill never leaves a truncated figure under its real name.
pub fn to_file(fig: &Figure, path: &Path, format: Format) -> Result<(), PlotError> {
    let bytes = match format {
        Format::Png => to_png(fig)?,
        Format::Svg => to_svg_string(fig)?.into_bytes(),
    };
    crate::output::folder::write_atomic(path, &bytes).map_err(|source| PlotError::Io {
        action: "cannot write the figure",
        path: path.to_path_buf(),
        source,
    })
}

/// Draws `fig` as PNG bytes.
pub fn to_png(fig: &Figure) -> Result<Vec<u8>, PlotError> {
    let (buf, w, h) = to_rgb(fig)?;
    let err = |e: png::EncodingError| PlotError::Draw {
        path: format!("<png of {}>", fig.name).into(),
        message: e.to_string(),
    };
    let mut out = Vec::new();
    {
        let mut enc = png::Encoder::new(&mut out, w, h);
        enc.set_color(png::ColorType::Rgb);
        enc.set_depth(png::BitDepth::Eight);
        let mut writer = enc.write_header().map_err(err)?;
        writer.write_image_data(&buf).map_err(err)?;
    }
    Ok(out)
}

/// Draws `fig` as SVG text (for the HTML report).
pub fn to_svg_string(fig: &Figure) -> Result<String, PlotError> {
    ensure_font()?;
    let mut s = String::new();
    {
        let root = SVGBackend::with_string(&mut s, size(fig)).into_drawing_area();
        let err = |message: String| PlotError::Draw {
            path: format!("<svg of {}>", fig.name).into(),
            message,
        };
        draw(&root, fig).map_err(err)?;
        root.present().map_err(|e| err(e.to_string()))?;
    }
    Ok(s)
}

/// Draws `fig` into a raw RGB buffer; returns (pixels, width, height). For checks that a
/// figure is not blank without decoding a file.
pub fn to_rgb(fig: &Figure) -> Result<(Vec<u8>, u32, u32), PlotError> {
    ensure_font()?;
    let (w, h) = size(fig);
    let mut buf = vec![0u8; (w * h * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut buf, (w, h)).into_drawing_area();
        let err = |message: String| PlotError::Draw {
            path: format!("<bitmap of {}>", fig.name).into(),
            message,
        };
        draw(&root, fig).map_err(err)?;
        root.present().map_err(|e| err(e.to_string()))?;
    }
    Ok((buf, w, h))
}

fn draw<DB: DrawingBackend>(root: &DrawingArea<DB, Shift>, fig: &Figure) -> Result<(), String> {
    root.fill(&WHITE).map_err(|e| e.to_string())?;
    let l = layout(fig);
    let body = root
        .titled(&fig.title, ("sans-serif", TITLE_PX))
        .map_err(|e| e.to_string())?;
    let plots_w = l.cols as u32 * l.panel_w;
    let (plots, legend_area) = body.split_horizontally(plots_w);
    for (area, panel) in plots.split_evenly((l.rows, l.cols)).iter().zip(&fig.panels) {
        draw_panel(area, panel)?;
    }
    if l.legend_w > 0 {
        draw_legend(&legend_area, &legend(fig))?;
    }
    Ok(())
}

fn draw_legend<DB: DrawingBackend>(
    area: &DrawingArea<DB, Shift>,
    entries: &[Entry],
) -> Result<(), String> {
    let e = |e: DrawingAreaErrorKind<DB::ErrorType>| e.to_string();
    let font = ("sans-serif", LEGEND_PX).into_font().color(&BLACK);
    for (i, en) in entries.iter().enumerate() {
        let y = 30 + i as i32 * LEGEND_ROW_PX as i32;
        let c = color(en.ink);
        match en.swatch {
            Swatch::Line { dashed: false } => area
                .draw(&PathElement::new(vec![(8, y), (36, y)], c.stroke_width(3)))
                .map_err(e)?,
            Swatch::Line { dashed: true } => {
                for x in [8, 20, 32] {
                    area.draw(&PathElement::new(
                        vec![(x, y), (x + 6, y)],
                        c.stroke_width(2),
                    ))
                    .map_err(e)?;
                }
            }
            Swatch::Area => area
                .draw(&Rectangle::new(
                    [(8, y - 7), (36, y + 7)],
                    c.mix(0.3).filled(),
                ))
                .map_err(e)?,
            Swatch::Bar => area
                .draw(&Rectangle::new(
                    [(12, y - 8), (32, y + 8)],
                    c.mix(0.85).filled(),
                ))
                .map_err(e)?,
            Swatch::Dot => area.draw(&Circle::new((22, y), 5, c.filled())).map_err(e)?,
        }
        area.draw(&Text::new(
            en.label.clone(),
            (44, y - LEGEND_PX as i32 / 2 - 1),
            font.clone(),
        ))
        .map_err(e)?;
    }
    Ok(())
}

/// Axis range of some values, padded so that curves do not touch the frame.
fn range(values: impl Iterator<Item = f64>, pad: f64) -> (f64, f64) {
    let (lo, hi) = values
        .filter(|v| v.is_finite())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| {
            (a.min(v), b.max(v))
        });
    if !lo.is_finite() {
        return (0.0, 1.0);
    }
    if hi - lo <= f64::EPSILON * lo.abs().max(1.0) {
        let d = (lo.abs() * 0.1).max(0.5);
        return (lo - d, hi + d);
    }
    let d = (hi - lo) * pad;
    (lo - d, hi + d)
}

/// A 1-2-5 step giving about `target` intervals over `span`.
fn nice_step(span: f64, target: f64) -> f64 {
    let raw = span / target;
    let mag = 10f64.powf(raw.log10().floor());
    let f = raw / mag;
    let m = if f < 1.5 {
        1.0
    } else if f < 3.5 {
        2.0
    } else if f < 7.5 {
        5.0
    } else {
        10.0
    };
    m * mag
}

/// Ticks of a linear axis over [lo, hi]: multiples of a 1-2-5 step (of at least 1 for counts),
/// and the decimals that show that step.
pub fn linear_ticks(lo: f64, hi: f64, integer: bool) -> (Vec<f64>, usize) {
    let mut step = nice_step(hi - lo, 5.0);
    if integer {
        step = step.max(1.0);
    }
    let first = (lo / step).ceil() as i64;
    let last = (hi / step).floor() as i64;
    // Each tick is i·step, so zero is exactly 0 and no tick reads 8.7e-19.
    let ticks = (first..=last).map(|i| i as f64 * step).collect();
    let decimals = if step >= 1.0 {
        0
    } else {
        (-step.log10().floor()) as usize
    };
    (ticks, decimals)
}

/// Ticks of a log axis, as log10 values over [lo, hi] (log10 units): powers of ten, with 2
/// and 5 between them when the axis spans less than about two decades, and every k-th power
/// when it spans many.
pub fn log_ticks(lo: f64, hi: f64) -> Vec<f64> {
    let inside = |v: &f64| *v >= lo - 1e-9 && *v <= hi + 1e-9;
    let (d0, d1) = (lo.floor() as i32, hi.ceil() as i32);
    let decades: Vec<f64> = (d0..=d1).map(f64::from).filter(inside).collect();
    if decades.len() > 7 {
        let k = decades.len().div_ceil(6);
        return decades
            .into_iter()
            .filter(|d| (*d as i32).rem_euclid(k as i32) == 0)
            .collect();
    }
    if decades.len() >= 3 {
        return decades;
    }
    for mantissas in [
        &[1.0, 2.0, 5.0][..],
        &[1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0],
    ] {
        let v: Vec<f64> = (d0..=d1)
            .flat_map(|d| mantissas.iter().map(move |m| (m * 10f64.powi(d)).log10()))
            .filter(inside)
            .collect();
        if v.len() >= 3 {
            return v;
        }
    }
    linear_ticks(lo, hi, false).0
}

/// A tick label: up to 4 significant digits, scientific notation for extremes.
fn tick(v: f64) -> String {
    if v == 0.0 {
        return "0".into();
    }
    let a = v.abs();
    if !(1e-3..1e5).contains(&a) {
        return format!("{v:.1e}").replace(".0e", "e");
    }
    let s = format!(
        "{:.*}",
        (3 - a.log10().floor() as i32).clamp(0, 6) as usize,
        v
    );
    if s.contains('.') {
        s.trim_end_matches('0').trim_end_matches('.').to_string()
    } else {
        s
    }
}

/// A linear tick label with a fixed number of decimals ("-0" shown as "0").
fn fixed(v: f64, decimals: usize) -> String {
    if v.abs() >= 1e5 || (v != 0.0 && v.abs() < 1e-4) {
        return tick(v);
    }
    let s = format!("{v:.decimals$}");
    if s.trim_start_matches('-')
        .chars()
        .all(|c| c == '0' || c == '.')
    {
        "0".into()
    } else {
        s
    }
}

/// A linear axis whose tick positions are given (plotters' own picks give 0.03162 on log
/// axes and 0.5 on count axes). Log axes use it in log10 units.
#[derive(Clone, Debug)]
struct Ticked {
    lo: f64,
    hi: f64,
    keys: Vec<f64>,
}

impl Ranged for Ticked {
    type FormatOption = DefaultFormatting;
    type ValueType = f64;

    fn map(&self, v: &f64, limit: (i32, i32)) -> i32 {
        if self.hi == self.lo {
            return (limit.0 + limit.1) / 2;
        }
        let f = (v - self.lo) / (self.hi - self.lo);
        let px = limit.0 as f64 + f * (limit.1 - limit.0) as f64;
        // Far-off points (clipped anyway) must not overflow the pixel type.
        px.clamp(-1e6, 1e6).round() as i32
    }

    fn key_points<H: KeyPointHint>(&self, hint: H) -> Vec<f64> {
        if hint.weight().allow_light_points() {
            Vec::new()
        } else {
            self.keys.clone()
        }
    }

    fn range(&self) -> std::ops::Range<f64> {
        self.lo..self.hi
    }
}

/// Key points and labels of one axis.
struct Axis {
    lo: f64,
    hi: f64,
    keys: Vec<f64>,
    decimals: usize,
    log: bool,
}

impl Axis {
    fn new(lo: f64, hi: f64, log: bool, integer: bool) -> Axis {
        if log {
            Axis {
                lo,
                hi,
                keys: log_ticks(lo, hi),
                decimals: 0,
                log,
            }
        } else {
            let (keys, decimals) = linear_ticks(lo, hi, integer);
            Axis {
                lo,
                hi,
                keys,
                decimals,
                log,
            }
        }
    }

    fn label(&self, v: f64) -> String {
        if self.log {
            tick(10f64.powf(v))
        } else {
            fixed(v, self.decimals)
        }
    }
}

/// Space around a panel's plot area (px): caption, x-axis labels, y-axis labels, margin.
const CAPTION_H: f64 = CAPTION_PX as f64 + 14.0;
const X_LABEL_H: f64 = 46.0;
const Y_LABEL_W: f64 = 72.0;
const MARGIN: f64 = 10.0;

/// A panel's chart: both axes in plot coordinates ([`Scale`]).
type Chart<'a, DB> = ChartContext<'a, DB, Cartesian2d<Ticked, Ticked>>;

/// Data to plot coordinates. Log axes are drawn in log10 units with labels showing 10^v: one
/// coordinate type for every panel keeps this renderer a single generic function. A value a
/// log axis cannot show (≤ 0) maps to `None`.
#[derive(Clone, Copy, Debug)]
struct Scale {
    log_x: bool,
    log_y: bool,
}

impl Scale {
    fn of(p: &Panel) -> Scale {
        Scale {
            log_x: p.log_x,
            log_y: p.log_y,
        }
    }

    fn x(self, x: f64) -> Option<f64> {
        if self.log_x {
            (x > 0.0).then(|| x.log10())
        } else {
            Some(x)
        }
    }

    fn y(self, y: f64) -> Option<f64> {
        if self.log_y {
            (y > 0.0).then(|| y.log10())
        } else {
            Some(y)
        }
    }
}

/// Every x and y coordinate the panel's marks reach, and whether it has bars.
fn extent(p: &Panel, s: Scale) -> (Vec<f64>, Vec<f64>, bool) {
    let mut xs: Vec<f64> = Vec::new();
    let mut ys: Vec<f64> = Vec::new();
    let mut has_bars = false;
    for m in &p.marks {
        match m {
            Mark::Line { points, .. } | Mark::Scatter { points, .. } => {
                xs.extend(points.iter().filter_map(|q| s.x(q.0)));
                ys.extend(points.iter().filter_map(|q| s.y(q.1)));
            }
            Mark::Band { points, .. } => {
                xs.extend(points.iter().filter_map(|q| s.x(q.0)));
                ys.extend(points.iter().flat_map(|q| [s.y(q.1), s.y(q.2)]).flatten());
            }
            Mark::HLine { y, .. } => ys.extend(s.y(*y)),
            Mark::Point { x, y, .. } => {
                xs.extend(s.x(*x));
                ys.extend(s.y(*y));
            }
            Mark::Bars { bars, .. } => {
                has_bars = true;
                for b in bars {
                    xs.extend([s.x(b.x0), s.x(b.x1)].into_iter().flatten());
                    ys.extend(s.y(b.y));
                    if let Some((lo, hi)) = b.whisker {
                        ys.extend([s.y(lo), s.y(hi)].into_iter().flatten());
                    }
                }
            }
        }
    }
    (xs, ys, has_bars)
}

/// The panel's axis ranges (x0, x1, y0, y1) in plot coordinates, for a drawing area of
/// `dim` pixels.
fn ranges(p: &Panel, s: Scale, dim: (u32, u32)) -> (f64, f64, f64, f64) {
    let (xs, mut ys, has_bars) = extent(p, s);
    let bars_from_zero = has_bars && !p.log_y && ys.iter().all(|v| *v >= 0.0);
    if has_bars && !p.log_y {
        ys.push(0.0);
    }
    let (mut x0, mut x1) = match &p.x_categories {
        Some(c) => (-0.5, c.len() as f64 - 0.5),
        None => range(xs.into_iter(), 0.0),
    };
    // Time and multiplier axes that start just after 0 start at 0 (the ANIS has no step 0).
    if p.x_categories.is_none() && !p.log_x && x0 > 0.0 && x0 <= 0.05 * (x1 - x0) {
        x0 = 0.0;
    }
    let (mut y0, mut y1) = range(ys.into_iter(), 0.05);
    if bars_from_zero {
        y0 = 0.0;
    }
    if p.equal_aspect && !p.log_x && !p.log_y {
        // Widen the range of the shorter side so that a metre is as long on both axes.
        let (w, h) = dim;
        let pw = (w as f64 - Y_LABEL_W - 2.0 * MARGIN).max(1.0);
        let ph = (h as f64 - CAPTION_H - X_LABEL_H - 2.0 * MARGIN).max(1.0);
        let (sx, sy) = ((x1 - x0) / pw, (y1 - y0) / ph);
        if sx > sy {
            let c = (y0 + y1) / 2.0;
            (y0, y1) = (c - sx * ph / 2.0, c + sx * ph / 2.0);
        } else {
            let c = (x0 + x1) / 2.0;
            (x0, x1) = (c - sy * pw / 2.0, c + sy * pw / 2.0);
        }
    }
    (x0, x1, y0, y1)
}

/// The panel's chart over the axes `xa` and `ya`, with its caption, grid and tick labels
/// drawn.
fn chart<'a, DB: DrawingBackend>(
    area: &'a DrawingArea<DB, Shift>,
    p: &Panel,
    xa: &Axis,
    ya: &Axis,
) -> Result<Chart<'a, DB>, String> {
    let e = |e: DrawingAreaErrorKind<DB::ErrorType>| e.to_string();
    let ticked = |a: &Axis| Ticked {
        lo: a.lo,
        hi: a.hi,
        keys: a.keys.clone(),
    };
    let mut chart = ChartBuilder::on(area)
        .caption(&p.title, ("sans-serif", CAPTION_PX))
        .margin(MARGIN as u32)
        .x_label_area_size(X_LABEL_H as u32)
        .y_label_area_size(Y_LABEL_W as u32)
        .build_cartesian_2d(ticked(xa), ticked(ya))
        .map_err(e)?;
    let cats = &p.x_categories;
    // More categories than labels fit (a sweep's divergence multipliers): every k-th label,
    // at most MAX_CATEGORY_LABELS of them.
    let every = cats
        .as_ref()
        .map_or(1, |c| c.len().div_ceil(MAX_CATEGORY_LABELS).max(1));
    let fx = |v: &f64| match cats {
        Some(c) => {
            let i = v.round();
            if (v - i).abs() < 1e-6
                && i >= 0.0
                && (i as usize) < c.len()
                && (i as usize).is_multiple_of(every)
            {
                c[i as usize].clone()
            } else {
                String::new()
            }
        }
        None => xa.label(*v),
    };
    let fy = |v: &f64| ya.label(*v);
    let mut mesh = chart.configure_mesh();
    mesh.x_desc(p.x_label.as_str())
        .y_desc(p.y_label.as_str())
        .label_style(("sans-serif", TICK_PX))
        .axis_desc_style(("sans-serif", AXIS_PX))
        .bold_line_style(BLACK.mix(0.12))
        .light_line_style(TRANSPARENT)
        .x_label_formatter(&fx)
        .y_label_formatter(&fy);
    mesh.draw().map_err(e)?;
    Ok(chart)
}

/// Where the marks of one panel are drawn.
struct Canvas<'c, 'a, DB: DrawingBackend> {
    chart: &'c mut Chart<'a, DB>,
    scale: Scale,
    /// The x axis's ends (horizontal lines span it).
    x: (f64, f64),
    /// The y axis's lower end (a whisker to a value a log axis cannot show ends there).
    y_lo: f64,
    /// Where bars start: 0, or the bottom of a log axis.
    base: f64,
    /// Points drawn so far: their value texts alternate above and below them, so that two
    /// divergence points close together do not write over each other.
    nth_point: usize,
}

impl<DB: DrawingBackend> Canvas<'_, '_, DB> {
    fn mark(&mut self, m: &Mark) -> Result<(), String> {
        match m {
            Mark::Band { ink, points, .. } => self.band(*ink, points),
            Mark::Line {
                ink,
                dashed,
                points,
                ..
            } => self.line(*ink, *dashed, points),
            Mark::Scatter { ink, points, .. } => self.scatter(*ink, points),
            Mark::HLine { ink, y, .. } => self.hline(*ink, *y),
            Mark::Point {
                ink, x, y, text, ..
            } => self.point(*ink, (*x, *y), text.as_deref()),
            Mark::Bars { ink, bars, .. } => self.bars(*ink, bars),
        }
    }

    fn band(&mut self, ink: Ink, points: &[(f64, f64, f64)]) -> Result<(), String> {
        let s = self.scale;
        let upper = points.iter().filter_map(|q| Some((s.x(q.0)?, s.y(q.2)?)));
        let lower = points
            .iter()
            .rev()
            .filter_map(|q| Some((s.x(q.0)?, s.y(q.1)?)));
        let poly: Vec<(f64, f64)> = upper.chain(lower).collect();
        if poly.len() < 3 {
            return Ok(());
        }
        let fill = color(ink).mix(0.18).filled();
        self.chart
            .draw_series(std::iter::once(Polygon::new(poly, fill)))
            .map_err(|e| e.to_string())?;
        Ok(())
    }

    fn line(&mut self, ink: Ink, dashed: bool, points: &[(f64, f64)]) -> Result<(), String> {
        let s = self.scale;
        let style = ShapeStyle {
            color: color(ink).to_rgba(),
            filled: false,
            stroke_width: if dashed { 1 } else { 2 },
        };
        let pts: Vec<(f64, f64)> = points
            .iter()
            .filter_map(|q| Some((s.x(q.0)?, s.y(q.1)?)))
            .collect();
        if dashed {
            self.chart
                .draw_series(DashedLineSeries::new(pts, 6, 4, style))
                .map_err(|e| e.to_string())?;
        } else {
            self.chart
                .draw_series(LineSeries::new(pts, style))
                .map_err(|e| e.to_string())?;
        }
        Ok(())
    }

    fn scatter(&mut self, ink: Ink, points: &[(f64, f64)]) -> Result<(), String> {
        let s = self.scale;
        let fill = color(ink).mix(0.7).filled();
        let dots: Vec<Circle<(f64, f64), i32>> = points
            .iter()
            .filter_map(|q| Some(Circle::new((s.x(q.0)?, s.y(q.1)?), 2, fill)))
            .collect();
        self.chart.draw_series(dots).map_err(|e| e.to_string())?;
        Ok(())
    }

    fn hline(&mut self, ink: Ink, y: f64) -> Result<(), String> {
        let Some(y) = self.scale.y(y) else {
            return Ok(());
        };
        let style = ShapeStyle {
            color: color(ink).to_rgba(),
            filled: false,
            stroke_width: 1,
        };
        let (x0, x1) = self.x;
        self.chart
            .draw_series(DashedLineSeries::new([(x0, y), (x1, y)], 6, 4, style))
            .map_err(|e| e.to_string())?;
        Ok(())
    }

    fn point(&mut self, ink: Ink, (x, y): (f64, f64), text: Option<&str>) -> Result<(), String> {
        let (Some(x), Some(y)) = (self.scale.x(x), self.scale.y(y)) else {
            return Ok(());
        };
        let c = color(ink);
        let font = ("sans-serif", TICK_PX).into_font().color(&c);
        let note = text.unwrap_or_default().to_string();
        let dy = if self.nth_point.is_multiple_of(2) {
            -20
        } else {
            6
        };
        self.nth_point += 1;
        self.chart
            .draw_series(std::iter::once(
                EmptyElement::at((x, y))
                    + Circle::new((0, 0), 5, c.filled())
                    + Text::new(note, (7, dy), font),
            ))
            .map_err(|e| e.to_string())?;
        Ok(())
    }

    fn bars(&mut self, ink: Ink, bars: &[Bar]) -> Result<(), String> {
        let (s, base, y_lo) = (self.scale, self.base, self.y_lo);
        let fill = color(ink).mix(0.85).filled();
        let rects: Vec<Rectangle<(f64, f64)>> = bars
            .iter()
            .filter_map(|b| {
                Some(Rectangle::new(
                    [(s.x(b.x0)?, base), (s.x(b.x1)?, s.y(b.y)?)],
                    fill,
                ))
            })
            .collect();
        self.chart.draw_series(rects).map_err(|e| e.to_string())?;
        let whiskers: Vec<PathElement<(f64, f64)>> = bars
            .iter()
            .filter_map(|b| {
                let (lo, hi) = b.whisker?;
                let xm = s.x((b.x0 + b.x1) / 2.0)?;
                Some(PathElement::new(
                    vec![(xm, s.y(lo).unwrap_or(y_lo)), (xm, s.y(hi)?)],
                    BLACK.stroke_width(1),
                ))
            })
            .collect();
        self.chart
            .draw_series(whiskers)
            .map_err(|e| e.to_string())?;
        Ok(())
    }
}

fn draw_panel<DB: DrawingBackend>(area: &DrawingArea<DB, Shift>, p: &Panel) -> Result<(), String> {
    let scale = Scale::of(p);
    let (x0, x1, y0, y1) = ranges(p, scale, area.dim_in_pixel());
    let xa = match &p.x_categories {
        Some(c) => Axis {
            lo: x0,
            hi: x1,
            keys: (0..c.len()).map(|i| i as f64).collect(),
            decimals: 0,
            log: false,
        },
        None => Axis::new(x0, x1, p.log_x, false),
    };
    let ya = Axis::new(y0, y1, p.log_y, p.integer_y);
    let mut chart = chart(area, p, &xa, &ya)?;
    let mut canvas = Canvas {
        chart: &mut chart,
        scale,
        x: (xa.lo, xa.hi),
        y_lo: ya.lo,
        base: if p.log_y { ya.lo } else { 0.0 },
        nth_point: 0,
    };
    for m in &p.marks {
        canvas.mark(m)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tick_labels_are_short() {
        assert_eq!(tick(0.0), "0");
        assert_eq!(tick(1.0), "1");
        assert_eq!(tick(0.25), "0.25");
        assert_eq!(tick(12.5), "12.5");
        assert_eq!(tick(1e-5), "1e-5");
        assert_eq!(tick(2.5e-5), "2.5e-5");
    }

    #[test]
    fn linear_ticks_are_multiples_of_a_1_2_5_step() {
        let (t, d) = linear_ticks(-0.05, 1.05, false);
        assert_eq!(t, [0.0, 0.2, 0.4, 0.6000000000000001, 0.8, 1.0]);
        assert_eq!(d, 1);
        assert_eq!(fixed(t[3], d), "0.6");
        // A tiny negative range end never gives a "-0" or an 8.7e-19 tick.
        let (t, d) = linear_ticks(-1e-18, 3.0, false);
        assert_eq!(t[0], 0.0);
        assert_eq!(fixed(t[0], d), "0");
        // Counts: integer ticks only, even over a short range.
        let (t, d) = linear_ticks(-0.1, 2.1, true);
        assert_eq!((t, d), (vec![0.0, 1.0, 2.0], 0));
    }

    #[test]
    fn log_ticks_are_powers_of_ten_or_1_2_5() {
        // 0.03 … 30: powers of ten only.
        let t: Vec<String> = log_ticks(0.03f64.log10(), 30f64.log10())
            .iter()
            .map(|v| tick(10f64.powf(*v)))
            .collect();
        assert_eq!(t, ["0.1", "1", "10"]);
        // 0.15 … 1.8: 1-2-5.
        let t: Vec<String> = log_ticks(0.15f64.log10(), 1.8f64.log10())
            .iter()
            .map(|v| tick(10f64.powf(*v)))
            .collect();
        assert_eq!(t, ["0.2", "0.5", "1"]);
        // Twelve decades: every second power at most seven ticks.
        let t = log_ticks(-6.0, 6.0);
        assert!(t.len() <= 7 && t.iter().all(|v| v.fract() == 0.0), "{t:?}");
    }

    #[test]
    fn grids_hold_every_panel() {
        for n in 1..12 {
            let (c, r) = grid(n);
            assert!(c * r >= n, "{n}");
        }
    }
}
