//! Figures of single traced runs (traces.parquet): the x–y trajectory and each state over time
//! with the estimate's ±3σ band.

use super::{Figure, FigureKind, Ink, Mark, Panel, Table, Tables, file_part, short};
use crate::error::PlotError;

/// The rows of the first traced run of each scenario (at the smallest noise scale, the only
/// one [`Tables::load`] keeps), grouped by filter.
struct TracedRun {
    scenario: String,
    noise_scale: f64,
    run: i64,
    /// (filter label, row indices in step order).
    filters: Vec<(String, Vec<usize>)>,
}

fn traced_runs(t: &Tables, tr: &Table) -> Result<Vec<TracedRun>, PlotError> {
    let scen = tr.strs("scenario")?;
    let filt = tr.strs("filter")?;
    let run = tr.f64s("run")?;
    let noise = tr.f64s("noise_scale")?;
    let mut out = Vec::new();
    let mut scenarios = t.scenarios.clone();
    scenarios.extend(super::first_appearance(&scen));
    scenarios = super::first_appearance(&scenarios);
    for s in scenarios {
        let rows: Vec<usize> = (0..tr.height()).filter(|&i| scen[i] == s).collect();
        let Some(first) = rows.iter().filter_map(|&i| run[i]).reduce(f64::min) else {
            continue;
        };
        let rows: Vec<usize> = rows
            .into_iter()
            .filter(|&i| run[i] == Some(first))
            .collect();
        let labels =
            super::first_appearance(&rows.iter().map(|&i| filt[i].clone()).collect::<Vec<_>>());
        let filters = labels
            .into_iter()
            .map(|f| {
                let r: Vec<usize> = rows.iter().copied().filter(|&i| filt[i] == f).collect();
                (f, r)
            })
            .collect();
        out.push(TracedRun {
            noise_scale: noise[rows[0]].unwrap_or(f64::NAN),
            scenario: s,
            run: first as i64,
            filters,
        });
    }
    Ok(out)
}

fn pairs(rows: &[usize], x: &[Option<f64>], y: &[Option<f64>]) -> Vec<(f64, f64)> {
    rows.iter().filter_map(|&i| Some((x[i]?, y[i]?))).collect()
}

/// `trajectory`: x against y of the first traced run per scenario; truth and every filter.
pub fn trajectory_series(t: &Tables) -> Result<Vec<Figure>, PlotError> {
    let Some(tr) = &t.traces else {
        return Ok(Vec::new());
    };
    if !tr.has("truth_x") || !tr.has("truth_y") {
        return Ok(Vec::new());
    }
    let (tx, ty) = (tr.f64s("truth_x")?, tr.f64s("truth_y")?);
    let (ex, ey) = (tr.f64s("est_x")?, tr.f64s("est_y")?);
    let mut figs = Vec::new();
    for r in traced_runs(t, tr)? {
        let mut marks = Vec::new();
        for (f, rows) in &r.filters {
            marks.push(Mark::Line {
                label: Some(f.clone()),
                ink: t.ink(f),
                dashed: false,
                points: pairs(rows, &ex, &ey),
            });
        }
        // The truth last, so that estimates lying on it do not hide it.
        if let Some((_, rows)) = r.filters.first() {
            marks.push(Mark::Line {
                label: Some("truth".into()),
                ink: Ink::Truth,
                dashed: true,
                points: pairs(rows, &tx, &ty),
            });
        }
        figs.push(Figure {
            kind: FigureKind::Trajectory,
            scenario: r.scenario.clone(),
            name: format!("trajectory_{}", file_part(&r.scenario)),
            title: format!(
                "{}: trajectory (run {}, noise ×{})",
                r.scenario,
                r.run,
                short(r.noise_scale)
            ),
            panels: vec![Panel {
                title: "x–y plane".into(),
                x_label: t.with_unit("x"),
                y_label: t.with_unit("y"),
                marks,
                ..Panel::default()
            }],
        });
    }
    Ok(figs)
}

/// `states`: each state over time, truth and estimates with ±3·sqrt(var) bands where the
/// filter has a covariance (`var_<s>` null, e.g. the running mean: no band).
pub fn states_series(t: &Tables) -> Result<Vec<Figure>, PlotError> {
    let Some(tr) = &t.traces else {
        return Ok(Vec::new());
    };
    let time = tr.f64s("t")?;
    let runs = traced_runs(t, tr)?;
    let mut cols = Vec::new();
    for s in &t.states {
        cols.push((
            tr.f64s(&format!("truth_{s}"))?,
            tr.f64s(&format!("est_{s}"))?,
            tr.f64s(&format!("var_{s}"))?,
        ));
    }
    let mut figs = Vec::new();
    for r in runs {
        let mut panels = Vec::new();
        for (s, (truth, est, var)) in t.states.iter().zip(&cols) {
            let mut marks = Vec::new();
            for (f, rows) in &r.filters {
                let band: Vec<(f64, f64, f64)> = rows
                    .iter()
                    .filter_map(|&i| {
                        let (m, sd) = (est[i]?, var[i]?.max(0.0).sqrt());
                        Some((time[i]?, m - 3.0 * sd, m + 3.0 * sd))
                    })
                    .collect();
                if !band.is_empty() {
                    marks.push(Mark::Band {
                        label: None,
                        ink: t.ink(f),
                        points: band,
                    });
                }
            }
            for (f, rows) in &r.filters {
                marks.push(Mark::Line {
                    label: Some(f.clone()),
                    ink: t.ink(f),
                    dashed: false,
                    points: pairs(rows, &time, est),
                });
            }
            if let Some((_, rows)) = r.filters.first() {
                marks.push(Mark::Line {
                    label: Some("truth".into()),
                    ink: Ink::Truth,
                    dashed: true,
                    points: pairs(rows, &time, truth),
                });
            }
            panels.push(Panel {
                title: s.clone(),
                x_label: "t [s]".into(),
                y_label: t.with_unit(s),
                marks,
                ..Panel::default()
            });
        }
        figs.push(Figure {
            kind: FigureKind::States,
            scenario: r.scenario.clone(),
            name: format!("states_{}", file_part(&r.scenario)),
            title: format!(
                "{}: states and estimates ±3σ (run {}, noise ×{})",
                r.scenario,
                r.run,
                short(r.noise_scale)
            ),
            panels,
        });
    }
    Ok(figs)
}

/// `route`: the position of the first traced run per scenario as projections, for systems
/// whose quantities include `px, py, pz` in a north–east–down frame (the drone): the
/// north–east plane (equal scales) and the altitude −pz over time, each with the truth, every
/// filter's estimate and the fixes of the position sensors named `gps` (`z_<gps…>_px/py/pz`,
/// null between fixes).
pub fn route_series(t: &Tables) -> Result<Vec<Figure>, PlotError> {
    let Some(tr) = &t.traces else {
        return Ok(Vec::new());
    };
    let need = [
        "truth_px", "truth_py", "truth_pz", "est_px", "est_py", "est_pz",
    ];
    if !need.iter().all(|c| tr.has(c)) {
        return Ok(Vec::new());
    }
    let time = tr.f64s("t")?;
    let (tn, te, td) = (
        tr.f64s("truth_px")?,
        tr.f64s("truth_py")?,
        tr.f64s("truth_pz")?,
    );
    let (en, ee, ed) = (tr.f64s("est_px")?, tr.f64s("est_py")?, tr.f64s("est_pz")?);
    let up = |v: &[Option<f64>]| v.iter().map(|x| x.map(|z| -z)).collect::<Vec<_>>();
    let (tu, eu) = (up(&td), up(&ed));
    // Position sensors: z_<sensor>_px with its _py and _pz, sensor named like a GPS.
    let sensors: Vec<String> = tr
        .names()
        .iter()
        .filter_map(|n| {
            n.strip_prefix("z_")?
                .strip_suffix("_px")
                .map(str::to_string)
        })
        .filter(|s| s.to_lowercase().contains("gps"))
        .filter(|s| tr.has(&format!("z_{s}_py")) && tr.has(&format!("z_{s}_pz")))
        .collect();
    let mut fixes = Vec::new();
    for s in &sensors {
        let d = tr.f64s(&format!("z_{s}_pz"))?;
        fixes.push((
            s.clone(),
            tr.f64s(&format!("z_{s}_px"))?,
            tr.f64s(&format!("z_{s}_py"))?,
            up(&d),
        ));
    }
    let mut figs = Vec::new();
    for r in traced_runs(t, tr)? {
        let mut plane = Vec::new();
        let mut alt = Vec::new();
        if let Some((_, rows)) = r.filters.first() {
            for (i, (s, n, e, u)) in fixes.iter().enumerate() {
                plane.push(Mark::Scatter {
                    label: Some(format!("{s} fixes")),
                    ink: Ink::Palette(7 + i),
                    points: pairs(rows, e, n),
                });
                alt.push(Mark::Scatter {
                    label: Some(format!("{s} fixes")),
                    ink: Ink::Palette(7 + i),
                    points: pairs(rows, &time, u),
                });
            }
        }
        for (f, rows) in &r.filters {
            plane.push(Mark::Line {
                label: Some(f.clone()),
                ink: t.ink(f),
                dashed: false,
                points: pairs(rows, &ee, &en),
            });
            alt.push(Mark::Line {
                label: Some(f.clone()),
                ink: t.ink(f),
                dashed: false,
                points: pairs(rows, &time, &eu),
            });
        }
        if let Some((_, rows)) = r.filters.first() {
            plane.push(Mark::Line {
                label: Some("truth".into()),
                ink: Ink::Truth,
                dashed: true,
                points: pairs(rows, &te, &tn),
            });
            alt.push(Mark::Line {
                label: Some("truth".into()),
                ink: Ink::Truth,
                dashed: true,
                points: pairs(rows, &time, &tu),
            });
        }
        let unit = |s: &str| match t.unit(s) {
            "" => String::new(),
            u => format!(" [{u}]"),
        };
        figs.push(Figure {
            kind: FigureKind::Route,
            scenario: r.scenario.clone(),
            name: format!("route_{}", file_part(&r.scenario)),
            title: format!(
                "{}: route (run {}, noise ×{})",
                r.scenario,
                r.run,
                short(r.noise_scale)
            ),
            panels: vec![
                Panel {
                    title: "north–east plane".into(),
                    x_label: format!("east py{}", unit("py")),
                    y_label: format!("north px{}", unit("px")),
                    equal_aspect: true,
                    marks: plane,
                    ..Panel::default()
                },
                Panel {
                    title: "altitude".into(),
                    x_label: "t [s]".into(),
                    y_label: format!("altitude −pz{}", unit("pz")),
                    marks: alt,
                    ..Panel::default()
                },
            ],
        });
    }
    Ok(figs)
}
