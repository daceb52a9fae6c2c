//! RMSE figures across the noise sweep (summary.parquet, divergence.parquet) and tuning
//! curves (tuning.parquet).

use super::{Bar, Figure, FigureKind, Ink, Mark, Panel, Tables, file_part, short};
use crate::error::PlotError;

/// Above this many noise scales the bar chart is unreadable; `rmse_growth` shows the sweep.
const MAX_BAR_SCALES: usize = 12;

/// The summary rows of one (scenario, filter, state), sorted by noise scale:
/// (noise_scale, rmse_mean, rmse_p05, rmse_p95).
pub type RmseRows = Vec<(f64, Option<f64>, Option<f64>, Option<f64>)>;

struct Summary {
    scen: Vec<String>,
    filt: Vec<String>,
    state: Vec<String>,
    noise: Vec<Option<f64>>,
    mean: Vec<Option<f64>>,
    p05: Vec<Option<f64>>,
    p95: Vec<Option<f64>>,
}

impl Summary {
    fn read(t: &Tables) -> Result<Summary, PlotError> {
        let s = &t.summary;
        Ok(Summary {
            scen: s.strs("scenario")?,
            filt: s.strs("filter")?,
            state: s.strs("state")?,
            noise: s.f64s("noise_scale")?,
            mean: s.f64s("rmse_mean")?,
            p05: s.f64s("rmse_p05")?,
            p95: s.f64s("rmse_p95")?,
        })
    }

    fn rows(&self, scenario: &str, filter: &str, state: &str) -> RmseRows {
        let mut v: RmseRows = (0..self.scen.len())
            .filter(|&i| {
                self.scen[i] == scenario && self.filt[i] == filter && self.state[i] == state
            })
            .filter_map(|i| Some((self.noise[i]?, self.mean[i], self.p05[i], self.p95[i])))
            .collect();
        v.sort_by(|a, b| a.0.total_cmp(&b.0));
        v
    }

    fn has(&self, scenario: &str, filter: &str) -> bool {
        (0..self.scen.len()).any(|i| self.scen[i] == scenario && self.filt[i] == filter)
    }
}

/// `rmse_cases`: per scenario and filter label, RMSE of each state at each noise scale as bars
/// (`rmse_mean`) with p5–p95 whiskers — the seeds' figures 15–19 with a spread over runs. The
/// label's variants (Q/R scales) stand side by side within each noise case, one series each.
pub fn rmse_cases_series(t: &Tables) -> Result<Vec<Figure>, PlotError> {
    if t.noise_scales.len() > MAX_BAR_SCALES {
        return Ok(Vec::new());
    }
    let sm = Summary::read(t)?;
    let cats: Vec<String> = t
        .noise_scales
        .iter()
        .map(|s| format!("×{}", short(*s)))
        .collect();
    let labels = super::first_appearance(&t.filter_labels);
    let mut figs = Vec::new();
    for scen in &t.scenarios {
        for label in &labels {
            let variants: Vec<&String> = t
                .filters
                .iter()
                .filter(|f| t.label_of(f) == label && sm.has(scen, f))
                .collect();
            if variants.is_empty() {
                continue;
            }
            let nv = variants.len() as f64;
            let width = 0.8 / nv;
            let panels = t
                .states
                .iter()
                .map(|s| {
                    let marks = variants
                        .iter()
                        .enumerate()
                        .map(|(j, f)| {
                            let bars = sm
                                .rows(scen, f, s)
                                .into_iter()
                                .filter_map(|(nz, mean, lo, hi)| {
                                    let i = t.noise_scales.iter().position(|x| *x == nz)? as f64;
                                    let x0 = i - 0.4 + j as f64 * width;
                                    Some(Bar {
                                        x0: x0 + 0.05 * width,
                                        x1: x0 + 0.95 * width,
                                        y: mean?,
                                        whisker: lo.zip(hi),
                                    })
                                })
                                .collect();
                            Mark::Bars {
                                label: Some(format!("{f} mean, p5–p95")),
                                ink: t.ink(f),
                                bars,
                            }
                        })
                        .collect();
                    Panel {
                        title: format!("RMSE of {s}"),
                        x_label: "truth-noise multiplier [–]".into(),
                        y_label: format!("RMSE {}", bracket(t, s)),
                        x_categories: Some(cats.clone()),
                        marks,
                        ..Panel::default()
                    }
                })
                .collect();
            figs.push(Figure {
                kind: FigureKind::RmseCases,
                scenario: scen.clone(),
                name: format!("rmse_cases_{}_{}", file_part(scen), file_part(label)),
                title: format!("{scen}, {label}: RMSE per noise case (mean over runs, p5–p95)"),
                panels,
            });
        }
    }
    Ok(figs)
}

fn bracket(t: &Tables, state: &str) -> String {
    match t.unit(state) {
        "" => String::new(),
        u => format!("[{u}]"),
    }
}

/// `rmse_growth`: per scenario, RMSE against the noise multiplier for each state and filter
/// (`rmse_mean` with the `rmse_p05`–`rmse_p95` band); log y for x and ẋ as the seeds draw
/// them. With divergence.parquet, each state's threshold is a horizontal line and each
/// filter's `mc_divergence_scale` a marked point on it.
pub fn rmse_growth_series(t: &Tables) -> Result<Vec<Figure>, PlotError> {
    if t.noise_scales.len() < 2 {
        return Ok(Vec::new());
    }
    let sm = Summary::read(t)?;
    let div = match &t.divergence {
        Some(d) => Some((
            d.strs("scenario")?,
            d.strs("filter")?,
            d.strs("state")?,
            d.f64s("threshold")?,
            d.f64s("mc_divergence_scale")?,
        )),
        None => None,
    };
    let mut figs = Vec::new();
    for scen in &t.scenarios {
        let mut panels = Vec::new();
        for s in &t.states {
            let mut marks = Vec::new();
            for f in t.filters.iter().filter(|f| sm.has(scen, f)) {
                let rows = sm.rows(scen, f, s);
                marks.push(Mark::Band {
                    label: None,
                    ink: t.ink(f),
                    points: rows
                        .iter()
                        .filter_map(|r| Some((r.0, r.2?, r.3?)))
                        .collect(),
                });
                marks.push(Mark::Line {
                    label: Some(format!("{f} mean, p5–p95")),
                    ink: t.ink(f),
                    dashed: false,
                    points: rows.iter().filter_map(|r| Some((r.0, r.1?))).collect(),
                });
            }
            if let Some((ds, df, dst, thr, mc)) = &div {
                let mut threshold_drawn = false;
                for i in (0..ds.len()).filter(|&i| ds[i] == *scen && dst[i] == *s) {
                    let Some(th) = thr[i] else { continue };
                    if !threshold_drawn {
                        marks.push(Mark::HLine {
                            label: Some("RMSE threshold".into()),
                            ink: Ink::Reference,
                            y: th,
                        });
                        threshold_drawn = true;
                    }
                    if let Some(x) = mc[i] {
                        marks.push(Mark::Point {
                            label: Some(format!("{} divergence point", df[i])),
                            ink: t.ink(&df[i]),
                            x,
                            y: th,
                            text: Some(format!("×{}", short(x))),
                        });
                    }
                }
            }
            let threshold = div.as_ref().and_then(|(ds, _, dst, thr, _)| {
                (0..ds.len())
                    .find(|&i| ds[i] == *scen && dst[i] == *s)
                    .and_then(|i| thr[i])
            });
            panels.push(Panel {
                title: match threshold {
                    Some(th) => format!("RMSE of {s} (threshold {})", short(th)),
                    None => format!("RMSE of {s}"),
                },
                x_label: "truth-noise multiplier [–]".into(),
                y_label: format!("RMSE {}", bracket(t, s)),
                log_y: s == "x" || s == "xdot",
                marks,
                ..Panel::default()
            });
        }
        figs.push(Figure {
            kind: FigureKind::RmseGrowth,
            scenario: scen.clone(),
            name: format!("rmse_growth_{}", file_part(scen)),
            title: format!("{scen}: RMSE against the truth-noise multiplier"),
            panels,
        });
    }
    Ok(figs)
}

/// `tuning`: per scenario, ANEES, ANIS and each state's RMSE against the filter's Q scale,
/// one curve per (filter, R scale). Nothing without tuning.parquet.
pub fn tuning_series(t: &Tables) -> Result<Vec<Figure>, PlotError> {
    let Some(tu) = &t.tuning else {
        return Ok(Vec::new());
    };
    let scen = tu.strs("scenario")?;
    let filt = tu.strs("filter")?;
    let q = tu.f64s("q_scale")?;
    let r = if tu.has("r_scale") {
        tu.f64s("r_scale")?
    } else {
        vec![None; tu.height()]
    };
    // (column, axis label, values, consistent mean)
    type Metric = (String, String, Vec<Option<f64>>, Option<usize>);
    let mut metrics: Vec<Metric> = Vec::new();
    for (col, title, reference) in [
        ("anees", "ANEES [–]", Some(t.states.len())),
        ("anis", "ANIS [–]", t.n_meas),
    ] {
        if tu.has(col) {
            metrics.push((col.into(), title.into(), tu.f64s(col)?, reference));
        }
    }
    for s in &t.states {
        let col = format!("rmse_{s}");
        if tu.has(&col) {
            metrics.push((
                col.clone(),
                format!("RMSE {}", bracket(t, s)),
                tu.f64s(&col)?,
                None,
            ));
        }
    }
    let qs: Vec<f64> = q.iter().flatten().copied().filter(|v| *v > 0.0).collect();
    let log_x = match (
        qs.iter().copied().reduce(f64::min),
        qs.iter().copied().reduce(f64::max),
    ) {
        (Some(lo), Some(hi)) => hi / lo >= 20.0,
        _ => false,
    };
    let noise = if tu.has("noise_scale") {
        tu.f64s("noise_scale")?
    } else {
        vec![None; tu.height()]
    };
    let mut scenarios = t.scenarios.clone();
    scenarios.extend(super::first_appearance(&scen));
    let mut figs = Vec::new();
    for sc in super::first_appearance(&scenarios) {
        let rows: Vec<usize> = (0..tu.height()).filter(|&i| scen[i] == sc).collect();
        if rows.is_empty() {
            continue;
        }
        // Curves: (noise scale, filter, r_scale) in order of first appearance — each noise
        // scale has its own search, and joining them makes a sawtooth.
        type Curve = (Option<u64>, String, Option<u64>);
        let mut curves: Vec<Curve> = Vec::new();
        for &i in &rows {
            let k = (
                noise[i].map(f64::to_bits),
                filt[i].clone(),
                r[i].map(f64::to_bits),
            );
            if !curves.contains(&k) {
                curves.push(k);
            }
        }
        let distinct = |f: &dyn Fn(&Curve) -> Option<u64>| {
            let mut v: Vec<Option<u64>> = curves.iter().map(f).collect();
            v.sort();
            v.dedup();
            v.len() > 1
        };
        let several_noise = distinct(&|c| c.0);
        let several_r = distinct(&|c| c.2);
        let palette = several_noise || several_r;
        let panels = metrics
            .iter()
            .map(|(col, title, v, reference)| {
                let mut marks = Vec::new();
                let mut plotted = Vec::new();
                for (ci, (nz, f, rs)) in curves.iter().enumerate() {
                    let mut pts: Vec<(f64, f64)> = rows
                        .iter()
                        .filter(|&&i| {
                            noise[i].map(f64::to_bits) == *nz
                                && filt[i] == *f
                                && r[i].map(f64::to_bits) == *rs
                        })
                        .filter_map(|&i| Some((q[i]?, v[i]?)))
                        .collect();
                    // The coarse grid and the refinement share their common Q scales.
                    pts.sort_by(|a, b| a.0.total_cmp(&b.0));
                    pts.dedup_by(|a, b| a.0 == b.0);
                    plotted.extend(pts.iter().map(|p| p.1));
                    let mut label = f.clone();
                    if several_noise && let Some(n) = nz {
                        label.push_str(&format!(", noise ×{}", short(f64::from_bits(*n))));
                    }
                    if several_r && let Some(rv) = rs {
                        label.push_str(&format!(", R×{}", short(f64::from_bits(*rv))));
                    }
                    marks.push(Mark::Line {
                        label: Some(label),
                        ink: if palette { Ink::Palette(ci) } else { t.ink(f) },
                        dashed: false,
                        points: pts,
                    });
                }
                if let Some(n) = reference {
                    marks.push(Mark::HLine {
                        label: Some("consistent mean (n states, p measurements)".into()),
                        ink: Ink::Reference,
                        y: *n as f64,
                    });
                }
                let is_stat = reference.is_some();
                Panel {
                    title: match reference {
                        Some(n) => format!("{} (consistent mean {n})", col.to_uppercase()),
                        None => col.clone(),
                    },
                    x_label: "Q scale [–]".into(),
                    y_label: title.clone(),
                    log_x,
                    log_y: is_stat && super::errors::wants_log(plotted.into_iter()),
                    marks,
                    ..Panel::default()
                }
            })
            .collect();
        figs.push(Figure {
            kind: FigureKind::Tuning,
            scenario: sc.clone(),
            name: format!("tuning_{}", file_part(&sc)),
            title: format!("{sc}: tuning curves against the filter's Q scale"),
            panels,
        });
    }
    Ok(figs)
}
