//! Per-step figures across runs (steps.parquet): absolute error quantiles and consistency.

use super::{Figure, FigureKind, Ink, Mark, Panel, Table, Tables, file_part, short};
use crate::error::PlotError;

/// One (scenario, noise scale) cell of the per-step table, rows grouped by filter.
pub(crate) struct StepCell {
    pub scenario: String,
    pub noise_scale: f64,
    pub filters: Vec<(String, Vec<usize>)>,
}

pub(crate) fn step_cells(t: &Tables, st: &Table) -> Result<Vec<StepCell>, PlotError> {
    let scen = st.strs("scenario")?;
    let filt = st.strs("filter")?;
    let noise = st.f64s("noise_scale")?;
    let mut cells: Vec<StepCell> = Vec::new();
    for i in 0..st.height() {
        let Some(nz) = noise[i] else { continue };
        let c = match cells
            .iter_mut()
            .position(|c| c.scenario == scen[i] && c.noise_scale == nz)
        {
            Some(p) => &mut cells[p],
            None => {
                cells.push(StepCell {
                    scenario: scen[i].clone(),
                    noise_scale: nz,
                    filters: Vec::new(),
                });
                cells.last_mut().expect("just pushed")
            }
        };
        match c.filters.iter_mut().find(|(f, _)| *f == filt[i]) {
            Some((_, rows)) => rows.push(i),
            None => c.filters.push((filt[i].clone(), vec![i])),
        }
    }
    // Scenario order of the summary, then ascending noise.
    cells.sort_by(|a, b| {
        let pos = |s: &str| t.scenarios.iter().position(|x| x == s);
        pos(&a.scenario)
            .cmp(&pos(&b.scenario))
            .then(a.noise_scale.total_cmp(&b.noise_scale))
    });
    Ok(cells)
}

/// File stem `<kind>_<scenario>`, with `_ns<scale>` when the folder has several scales.
fn stem(kind: &str, t: &Tables, c: &StepCell) -> String {
    if t.noise_scales.len() > 1 {
        format!(
            "{kind}_{}_ns{}",
            file_part(&c.scenario),
            file_part(&short(c.noise_scale))
        )
    } else {
        format!("{kind}_{}", file_part(&c.scenario))
    }
}

/// A nullable numeric column.
type Column = Vec<Option<f64>>;

fn line(rows: &[usize], x: &[Option<f64>], y: &[Option<f64>]) -> Vec<(f64, f64)> {
    rows.iter().filter_map(|&i| Some((x[i]?, y[i]?))).collect()
}

fn band(
    rows: &[usize],
    x: &[Option<f64>],
    lo: &[Option<f64>],
    hi: &[Option<f64>],
) -> Vec<(f64, f64, f64)> {
    rows.iter()
        .filter_map(|&i| Some((x[i]?, lo[i]?, hi[i]?)))
        .collect()
}

/// `errors`: |e| over time per state and filter — the median across runs with its p5–p95
/// band (`abs_err_p50_<s>`, `abs_err_p05_<s>`, `abs_err_p95_<s>`). Tables written before
/// those columns existed get the RMS over runs, sqrt(`mse_<s>`), without a band.
pub fn errors_series(t: &Tables) -> Result<Vec<Figure>, PlotError> {
    let Some(st) = &t.steps else {
        return Ok(Vec::new());
    };
    let time = st.f64s("t")?;
    let quantiles = t.states.iter().all(|s| st.has(&format!("abs_err_p50_{s}")));
    let mut cols = Vec::new();
    for s in &t.states {
        cols.push(if quantiles {
            (
                st.f64s(&format!("abs_err_p05_{s}"))?,
                st.f64s(&format!("abs_err_p50_{s}"))?,
                st.f64s(&format!("abs_err_p95_{s}"))?,
            )
        } else {
            let rms: Vec<Option<f64>> = st
                .f64s(&format!("mse_{s}"))?
                .into_iter()
                .map(|v| v.map(f64::sqrt))
                .collect();
            (Vec::new(), rms, Vec::new())
        });
    }
    let mut figs = Vec::new();
    for c in step_cells(t, st)? {
        let mut panels = Vec::new();
        for (s, (p05, p50, p95)) in t.states.iter().zip(&cols) {
            let mut marks = Vec::new();
            if quantiles {
                for (f, rows) in &c.filters {
                    marks.push(Mark::Band {
                        label: None,
                        ink: t.ink(f),
                        points: band(rows, &time, p05, p95),
                    });
                }
            }
            for (f, rows) in &c.filters {
                marks.push(Mark::Line {
                    label: Some(if quantiles {
                        format!("{f} median, p5–p95")
                    } else {
                        format!("{f} RMS over runs")
                    }),
                    ink: t.ink(f),
                    dashed: false,
                    points: line(rows, &time, p50),
                });
            }
            panels.push(Panel {
                title: format!("|e| of {s}"),
                x_label: "t [s]".into(),
                y_label: match t.unit(s) {
                    "" => "|e|".into(),
                    u => format!("|e| [{u}]"),
                },
                marks,
                ..Panel::default()
            });
        }
        figs.push(Figure {
            kind: FigureKind::Errors,
            scenario: c.scenario.clone(),
            name: stem("errors", t, &c),
            title: format!(
                "{}: absolute error across runs (noise ×{})",
                c.scenario,
                short(c.noise_scale)
            ),
            panels,
        });
    }
    Ok(figs)
}

/// Whether a positive series spans so many orders of magnitude that a linear axis would flatten
/// the consistent filters into the floor (one ANEES of 45 beside others near 6). Judged on the
/// 2nd to 98th percentile, so that one transient (the first update's NIS under a wide P0) does
/// not turn a whole panel logarithmic.
pub(crate) fn wants_log(values: impl Iterator<Item = f64>) -> bool {
    let mut v: Vec<f64> = values.filter(|v| v.is_finite()).collect();
    if v.is_empty() {
        return false;
    }
    v.sort_by(f64::total_cmp);
    let at = |q: f64| v[((v.len() - 1) as f64 * q).round() as usize];
    let (lo, hi) = (at(0.02), at(0.98));
    v[0] > 0.0 && hi / lo > 30.0
}

/// `consistency`: ANEES and ANIS over time per filter variant with the χ² acceptance band from
/// `anees_lo`/`anees_hi` and `anis_lo`/`anis_hi` when the table has them, and the consistent
/// filter's mean (n states, p measurement components) as a reference line. Step 0 is left
/// out: its "estimate" is the prior x̂0, whose NEES says how x̂0 was drawn (0 when x̂0 = x0),
/// not how the filter behaves, and its spike would set the axis. Variants whose bands are
/// equal (the same runs reached every step) share one band, drawn once in grey. A log axis
/// when the curves span more than a factor of 30. Filters without a covariance (all-null
/// ANEES) are left out; a cell with none is skipped.
pub fn consistency_series(t: &Tables) -> Result<Vec<Figure>, PlotError> {
    let Some(st) = &t.steps else {
        return Ok(Vec::new());
    };
    let time = st.f64s("t")?;
    let step = if st.has("step") {
        st.f64s("step")?
    } else {
        vec![None; st.height()]
    };
    let stat = |name: &str| -> Result<(Column, Option<(Column, Column)>), PlotError> {
        let v = st.f64s(name)?;
        let (lo, hi) = (format!("{name}_lo"), format!("{name}_hi"));
        let b = if st.has(&lo) && st.has(&hi) {
            Some((st.f64s(&lo)?, st.f64s(&hi)?))
        } else {
            None
        };
        Ok((v, b))
    };
    let stats = [
        ("anees", "ANEES", stat("anees")?, Some(t.states.len())),
        ("anis", "ANIS", stat("anis")?, t.n_meas),
    ];
    let mut figs = Vec::new();
    for c in step_cells(t, st)? {
        let mut panels = Vec::new();
        let mut any = false;
        for (_, title, (v, b), reference) in &stats {
            let mut marks = Vec::new();
            let with_values: Vec<(&String, Vec<usize>)> = c
                .filters
                .iter()
                .filter(|(_, rows)| rows.iter().any(|&i| v[i].is_some()))
                .map(|(f, rows)| {
                    let after_prior = rows
                        .iter()
                        .copied()
                        .filter(|&i| step[i].is_none_or(|k| k > 0.0))
                        .collect();
                    (f, after_prior)
                })
                .collect();
            if let Some((lo, hi)) = b {
                let bands: Vec<Vec<(f64, f64, f64)>> = with_values
                    .iter()
                    .map(|(_, rows)| band(rows, &time, lo, hi))
                    .collect();
                if bands.windows(2).all(|w| w[0] == w[1]) {
                    if let Some(first) = bands.into_iter().next() {
                        marks.push(Mark::Band {
                            label: Some("χ² acceptance band".into()),
                            ink: Ink::Reference,
                            points: first,
                        });
                    }
                } else {
                    for ((f, _), points) in with_values.iter().zip(bands) {
                        marks.push(Mark::Band {
                            label: Some(format!("{f} χ² acceptance band")),
                            ink: t.ink(f),
                            points,
                        });
                    }
                }
            }
            let mut plotted = Vec::new();
            for (f, rows) in &with_values {
                any = true;
                let points = line(rows, &time, v);
                plotted.extend(points.iter().map(|p| p.1));
                marks.push(Mark::Line {
                    label: Some((*f).clone()),
                    ink: t.ink(f),
                    dashed: false,
                    points,
                });
            }
            if let Some(n) = reference {
                marks.push(Mark::HLine {
                    label: Some("consistent mean (n states, p measurements)".into()),
                    ink: Ink::Reference,
                    y: *n as f64,
                });
            }
            let log_y = wants_log(plotted.into_iter());
            panels.push(Panel {
                title: match reference {
                    Some(n) => format!("{title} (consistent mean {n})"),
                    None => title.to_string(),
                },
                x_label: "t [s]".into(),
                y_label: format!("{title} [–]"),
                log_y,
                marks,
                ..Panel::default()
            });
        }
        if !any {
            continue;
        }
        figs.push(Figure {
            kind: FigureKind::Consistency,
            scenario: c.scenario.clone(),
            name: stem("consistency", t, &c),
            title: format!(
                "{}: ANEES and ANIS across runs, steps ≥ 1 (noise ×{})",
                c.scenario,
                short(c.noise_scale)
            ),
            panels,
        });
    }
    Ok(figs)
}
