//! Draws a [`Figure`] with plotters, to PNG or SVG, with the bundled DejaVu Sans so that text
//! renders on a machine without any font package (plotters' `ab_glyph` backend reads only
//! fonts registered at runtime).

use std::path::Path;
use std::sync::OnceLock;

use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::FontStyle;

use super::{Figure, Format, Ink, Mark, Panel};
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

/// (columns, rows) of the panel grid.
fn grid(n: usize) -> (usize, usize) {
    match n {
        0 | 1 => (1, 1),
        2 => (2, 1),
        3 => (3, 1),
        4 => (2, 2),
        n => {
            let cols = n.div_ceil(2).min(4);
            (cols, n.div_ceil(cols))
        }
    }
}

/// Pixel size of a figure.
pub fn size(fig: &Figure) -> (u32, u32) {
    let (c, r) = grid(fig.panels.len());
    if c == 1 && r == 1 {
        (860, 620)
    } else {
        (c as u32 * 520, r as u32 * 400 + 40)
    }
}

/// Draws `fig` into a file of the given format.
pub fn to_file(fig: &Figure, path: &Path, format: Format) -> Result<(), PlotError> {
    ensure_font()?;
    let err = |message: String| PlotError::Draw {
        path: path.to_path_buf(),
        message,
    };
    let dims = size(fig);
    // Drawn under a temporary name (keeping the extension, which picks the encoder) and
    // renamed into place, so a full disk or a kill never leaves a truncated figure.
    let stem = path
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    let ext = path
        .extension()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    let tmp = path.with_file_name(format!(".{stem}.partial.{ext}"));
    let drawn = match format {
        Format::Png => {
            let root = BitMapBackend::new(&tmp, dims).into_drawing_area();
            draw(&root, fig)
                .map_err(err)
                .and_then(|()| root.present().map_err(|e| err(e.to_string())))
        }
        Format::Svg => {
            let root = SVGBackend::new(&tmp, dims).into_drawing_area();
            draw(&root, fig)
                .map_err(err)
                .and_then(|()| root.present().map_err(|e| err(e.to_string())))
        }
    };
    let moved = drawn.and_then(|()| {
        std::fs::rename(&tmp, path).map_err(|source| PlotError::Io {
            action: "cannot move the figure to",
            path: path.to_path_buf(),
            source,
        })
    });
    if moved.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    moved
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
    let body = root
        .titled(&fig.title, ("sans-serif", 22))
        .map_err(|e| e.to_string())?;
    let (cols, rows) = grid(fig.panels.len());
    for (area, panel) in body.split_evenly((rows, cols)).iter().zip(&fig.panels) {
        draw_panel(area, panel)?;
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

/// A tick label: up to 4 significant digits, scientific notation for extremes.
fn tick(v: f64) -> String {
    if v == 0.0 {
        return "0".into();
    }
    let a = v.abs();
    if !(1e-3..1e5).contains(&a) {
        return format!("{v:.1e}");
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

fn draw_panel<DB: DrawingBackend>(area: &DrawingArea<DB, Shift>, p: &Panel) -> Result<(), String> {
    let e = |e: DrawingAreaErrorKind<DB::ErrorType>| e.to_string();
    // Log axes are drawn in log10 units with labels showing 10^v: one coordinate type for
    // every panel keeps this renderer a single generic function.
    let tx = |x: f64| {
        if p.log_x {
            (x > 0.0).then(|| x.log10())
        } else {
            Some(x)
        }
    };
    let ty = |y: f64| {
        if p.log_y {
            (y > 0.0).then(|| y.log10())
        } else {
            Some(y)
        }
    };
    let mut xs: Vec<f64> = Vec::new();
    let mut ys: Vec<f64> = Vec::new();
    let mut has_bars = false;
    for m in &p.marks {
        match m {
            Mark::Line { points, .. } => {
                xs.extend(points.iter().filter_map(|q| tx(q.0)));
                ys.extend(points.iter().filter_map(|q| ty(q.1)));
            }
            Mark::Band { points, .. } => {
                xs.extend(points.iter().filter_map(|q| tx(q.0)));
                ys.extend(points.iter().flat_map(|q| [ty(q.1), ty(q.2)]).flatten());
            }
            Mark::HLine { y, .. } => ys.extend(ty(*y)),
            Mark::Point { x, y, .. } => {
                xs.extend(tx(*x));
                ys.extend(ty(*y));
            }
            Mark::Bars { bars, .. } => {
                has_bars = true;
                for b in bars {
                    xs.extend([tx(b.x0), tx(b.x1)].into_iter().flatten());
                    ys.extend(ty(b.y));
                    if let Some((lo, hi)) = b.whisker {
                        ys.extend([ty(lo), ty(hi)].into_iter().flatten());
                    }
                }
            }
        }
    }
    if has_bars && !p.log_y {
        ys.push(0.0);
    }
    let (x0, x1) = match &p.x_categories {
        Some(c) => (-0.5, c.len() as f64 - 0.5),
        None => range(xs.into_iter(), 0.0),
    };
    let (y0, y1) = range(ys.into_iter(), 0.05);
    let mut chart = ChartBuilder::on(area)
        .caption(&p.title, ("sans-serif", 16))
        .margin(10)
        .x_label_area_size(42)
        .y_label_area_size(64)
        .build_cartesian_2d(x0..x1, y0..y1)
        .map_err(e)?;
    let cats = p.x_categories.clone();
    let fx = move |v: &f64| match &cats {
        Some(c) => {
            let i = v.round();
            if (v - i).abs() < 1e-6 && i >= 0.0 && (i as usize) < c.len() {
                c[i as usize].clone()
            } else {
                String::new()
            }
        }
        None if p.log_x => tick(10f64.powf(*v)),
        None => tick(*v),
    };
    let fy = |v: &f64| {
        if p.log_y {
            tick(10f64.powf(*v))
        } else {
            tick(*v)
        }
    };
    let mut mesh = chart.configure_mesh();
    mesh.x_desc(p.x_label.as_str())
        .y_desc(p.y_label.as_str())
        .label_style(("sans-serif", 12))
        .axis_desc_style(("sans-serif", 14))
        .light_line_style(TRANSPARENT)
        .x_label_formatter(&fx)
        .y_label_formatter(&fy);
    if let Some(c) = &p.x_categories {
        mesh.x_labels(c.len() + 1);
    }
    mesh.draw().map_err(e)?;

    let mut labelled = false;
    let base = if p.log_y { y0 } else { 0.0 };
    for m in &p.marks {
        match m {
            Mark::Band { label, ink, points } => {
                let c = color(*ink);
                let upper = points.iter().filter_map(|q| Some((tx(q.0)?, ty(q.2)?)));
                let lower = points
                    .iter()
                    .rev()
                    .filter_map(|q| Some((tx(q.0)?, ty(q.1)?)));
                let poly: Vec<(f64, f64)> = upper.chain(lower).collect();
                if poly.len() < 3 {
                    continue;
                }
                let a = chart
                    .draw_series(std::iter::once(Polygon::new(poly, c.mix(0.18).filled())))
                    .map_err(e)?;
                if let Some(l) = label {
                    labelled = true;
                    a.label(l.as_str()).legend(move |(x, y)| {
                        Rectangle::new([(x, y - 5), (x + 20, y + 5)], c.mix(0.3).filled())
                    });
                }
            }
            Mark::Line {
                label,
                ink,
                dashed,
                points,
            } => {
                let c = color(*ink);
                let style = ShapeStyle {
                    color: c.to_rgba(),
                    filled: false,
                    stroke_width: if *dashed { 1 } else { 2 },
                };
                let pts: Vec<(f64, f64)> = points
                    .iter()
                    .filter_map(|q| Some((tx(q.0)?, ty(q.1)?)))
                    .collect();
                let a = if *dashed {
                    chart
                        .draw_series(DashedLineSeries::new(pts, 6, 4, style))
                        .map_err(e)?
                } else {
                    chart.draw_series(LineSeries::new(pts, style)).map_err(e)?
                };
                if let Some(l) = label {
                    labelled = true;
                    a.label(l.as_str())
                        .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], style));
                }
            }
            Mark::HLine { label, ink, y } => {
                let Some(y) = ty(*y) else { continue };
                let style = ShapeStyle {
                    color: color(*ink).to_rgba(),
                    filled: false,
                    stroke_width: 1,
                };
                let a = chart
                    .draw_series(DashedLineSeries::new([(x0, y), (x1, y)], 6, 4, style))
                    .map_err(e)?;
                if let Some(l) = label {
                    labelled = true;
                    a.label(l.as_str())
                        .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], style));
                }
            }
            Mark::Point { label, ink, x, y } => {
                let (Some(x), Some(y)) = (tx(*x), ty(*y)) else {
                    continue;
                };
                let c = color(*ink);
                let a = chart
                    .draw_series(std::iter::once(Circle::new((x, y), 5, c.filled())))
                    .map_err(e)?;
                if let Some(l) = label {
                    labelled = true;
                    a.label(l.as_str())
                        .legend(move |(x, y)| Circle::new((x + 10, y), 4, c.filled()));
                }
            }
            Mark::Bars { label, ink, bars } => {
                let c = color(*ink);
                let rects: Vec<Rectangle<(f64, f64)>> = bars
                    .iter()
                    .filter_map(|b| {
                        Some(Rectangle::new(
                            [(tx(b.x0)?, base), (tx(b.x1)?, ty(b.y)?)],
                            c.mix(0.85).filled(),
                        ))
                    })
                    .collect();
                let a = chart.draw_series(rects).map_err(e)?;
                if let Some(l) = label {
                    labelled = true;
                    a.label(l.as_str()).legend(move |(x, y)| {
                        Rectangle::new([(x, y - 5), (x + 20, y + 5)], c.mix(0.85).filled())
                    });
                }
                let whiskers: Vec<PathElement<(f64, f64)>> = bars
                    .iter()
                    .filter_map(|b| {
                        let (lo, hi) = b.whisker?;
                        let xm = tx((b.x0 + b.x1) / 2.0)?;
                        Some(PathElement::new(
                            vec![(xm, ty(lo).unwrap_or(y0)), (xm, ty(hi)?)],
                            BLACK.stroke_width(1),
                        ))
                    })
                    .collect();
                chart.draw_series(whiskers).map_err(e)?;
            }
        }
    }
    if labelled {
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK.mix(0.4))
            .label_font(("sans-serif", 12))
            .position(SeriesLabelPosition::UpperLeft)
            .draw()
            .map_err(e)?;
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
        assert_eq!(tick(1e-5), "1.0e-5");
    }

    #[test]
    fn grids_hold_every_panel() {
        for n in 1..12 {
            let (c, r) = grid(n);
            assert!(c * r >= n, "{n}");
        }
    }
}
