//! Figures of single traced runs (traces.parquet): the position map (`trajectory`), the route
//! in three dimensions (`route`) and each quantity's estimate error with its ±3σ band
//! (`states`). Every one shows one deliberately chosen cell: the nominal noise scale
//! ([`super::nominal_scale`], the only one [`Tables::load`] keeps of the traces) and the
//! first traced run of each scenario; its title names the scenario, the scale and the run.
//!
//! The position figures are chosen by the position roles the system declared
//! ([`crate::system::PositionAxis`], recorded in `manifest.toml`): a map when the quantities
//! hold a plane's two axes, a route when they also hold a vertical one. A folder whose
//! manifest records no roles (written by an older kfmc) is plotted by quantity names as
//! then: `x, y` for the map, `px, py, pz` with `gps` sensors for the route.

use super::{Figure, FigureKind, Ink, Mark, Panel, Table, Tables, file_part, short};
use crate::error::PlotError;
use crate::linalg::so3::EulerRotation;

/// The rows of the first traced run of each scenario (at the nominal noise scale, the only
/// one [`Tables::load`] keeps), grouped by filter.
struct TracedRun {
    scenario: String,
    noise_scale: f64,
    run: i64,
    /// (filter label, row indices in step order).
    filters: Vec<(String, Vec<usize>)>,
}

impl TracedRun {
    /// The cell, for titles: `run 0, noise ×1`.
    fn cell(&self) -> String {
        format!("run {}, noise ×{}", self.run, short(self.noise_scale))
    }
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

/// The position axes a figure draws: the plane (drawn right and up), the height, and the
/// sensors whose fixes are drawn beside them.
#[derive(Clone, Debug, PartialEq)]
pub struct PositionMap {
    /// The panel title of the plane (`x–y plane`, `north–east plane`).
    pub plane_title: String,
    /// The quantity drawn to the right and its axis label.
    pub right: (String, String),
    /// The quantity drawn up and its axis label.
    pub up: (String, String),
    /// The vertical quantity, its axis label and whether the height is its negative (down).
    pub height: Option<(String, String, bool)>,
    /// The position sensors: name and its components measuring (right, up, height).
    pub fixes: Vec<FixSensor>,
}

/// A sensor that measures position quantities directly.
#[derive(Clone, Debug, PartialEq)]
pub struct FixSensor {
    /// The sensor name (legend `<name> fixes`).
    pub name: String,
    /// Its component measuring the right-hand quantity.
    pub right: Option<String>,
    /// Its component measuring the upward quantity.
    pub up: Option<String>,
    /// Its component measuring the vertical quantity.
    pub height: Option<String>,
}

/// The position map the folder's roles declare, when it records roles: `None` without
/// roles (an older folder), `Some(None)` when the roles make no plane (one frame's two plane
/// axes, each declared once, are needed).
fn map_by_roles(t: &Tables) -> Option<Option<PositionMap>> {
    let m = t.manifest.as_ref().filter(|m| m.has_position_roles())?;
    let with_role = |axis: &str| -> Option<Option<&crate::output::manifest::QuantityEntry>> {
        let mut found = m
            .quantities
            .iter()
            .filter(|q| q.position.as_deref() == Some(axis));
        let first = found.next();
        // An axis declared twice is ambiguous: no figure rather than a guess.
        if found.next().is_some() {
            return None;
        }
        Some(first)
    };
    let declared: Vec<&str> = m
        .quantities
        .iter()
        .filter_map(|q| q.position.as_deref())
        .collect();
    let ned = declared
        .iter()
        .any(|a| matches!(*a, "north" | "east" | "down"));
    let cartesian = declared.iter().any(|a| matches!(*a, "x" | "y" | "z"));
    if ned && cartesian {
        return Some(None);
    }
    let (right_axis, up_axis, height_axis) = if ned {
        ("east", "north", "down")
    } else {
        ("x", "y", "z")
    };
    let lookup = || -> Option<PositionMap> {
        let right = with_role(right_axis)??;
        let up = with_role(up_axis)??;
        let height = with_role(height_axis)?;
        let label = |axis: &str, q: &str| {
            let u = match t.unit(q) {
                "" => String::new(),
                u => format!(" [{u}]"),
            };
            if ned {
                format!("{axis} {q}{u}")
            } else {
                t.with_unit(q)
            }
        };
        let plane_title = if ned {
            "north–east plane".to_string()
        } else {
            format!("{}–{} plane", right.name, up.name)
        };
        let mut fixes: Vec<FixSensor> = Vec::new();
        let mut add = |q: &crate::output::manifest::QuantityEntry, slot: usize| {
            for f in &q.fixes {
                let i = match fixes.iter().position(|s| s.name == f.sensor) {
                    Some(i) => i,
                    None => {
                        fixes.push(FixSensor {
                            name: f.sensor.clone(),
                            right: None,
                            up: None,
                            height: None,
                        });
                        fixes.len() - 1
                    }
                };
                let s = &mut fixes[i];
                let c = match slot {
                    0 => &mut s.right,
                    1 => &mut s.up,
                    _ => &mut s.height,
                };
                c.get_or_insert_with(|| f.component.clone());
            }
        };
        add(right, 0);
        add(up, 1);
        if let Some(h) = height {
            add(h, 2);
        }
        Some(PositionMap {
            plane_title,
            right: (right.name.clone(), label("east", &right.name)),
            up: (up.name.clone(), label("north", &up.name)),
            height: height.map(|h| {
                let name = if ned {
                    format!("altitude −{}", h.name)
                } else {
                    format!("altitude {}", h.name)
                };
                let label = match t.unit(&h.name) {
                    "" => name,
                    u => format!("{name} [{u}]"),
                };
                (h.name.clone(), label, ned)
            }),
            fixes,
        })
    };
    Some(lookup())
}

/// The map of the `trajectory` figure: a plane without a vertical axis (by roles), or, in a
/// folder without roles, the quantities named `x` and `y`.
pub fn trajectory_map(t: &Tables) -> Option<PositionMap> {
    if let Some(by_roles) = map_by_roles(t) {
        return by_roles.filter(|m| m.height.is_none());
    }
    let tr = t.traces.as_ref()?;
    (tr.has("truth_x") && tr.has("truth_y")).then(|| PositionMap {
        plane_title: "x–y plane".into(),
        right: ("x".into(), t.with_unit("x")),
        up: ("y".into(), t.with_unit("y")),
        height: None,
        fixes: Vec::new(),
    })
}

/// The map of the `route` figure: a plane and a vertical axis (by roles), or, in a folder
/// without roles, the quantities named `px, py, pz` (north–east–down) with the sensors named
/// like a GPS that report all three (`z_<gps…>_px/py/pz`).
pub fn route_map(t: &Tables) -> Option<PositionMap> {
    if let Some(by_roles) = map_by_roles(t) {
        return by_roles.filter(|m| m.height.is_some());
    }
    let tr = t.traces.as_ref()?;
    let need = ["px", "py", "pz"];
    if !need
        .iter()
        .all(|q| tr.has(&format!("truth_{q}")) && tr.has(&format!("est_{q}")))
    {
        return None;
    }
    let unit = |s: &str| match t.unit(s) {
        "" => String::new(),
        u => format!(" [{u}]"),
    };
    let fixes = tr
        .names()
        .iter()
        .filter_map(|n| {
            n.strip_prefix("z_")?
                .strip_suffix("_px")
                .map(str::to_string)
        })
        .filter(|s| s.to_lowercase().contains("gps"))
        .filter(|s| tr.has(&format!("z_{s}_py")) && tr.has(&format!("z_{s}_pz")))
        .map(|s| FixSensor {
            right: Some(format!("{s}_py")),
            up: Some(format!("{s}_px")),
            height: Some(format!("{s}_pz")),
            name: s,
        })
        .collect();
    Some(PositionMap {
        plane_title: "north–east plane".into(),
        right: ("py".into(), format!("east py{}", unit("py"))),
        up: ("px".into(), format!("north px{}", unit("px"))),
        height: Some(("pz".into(), format!("altitude −pz{}", unit("pz")), true)),
        fixes,
    })
}

/// A column, or all nulls when the traces lack it (a fix component of another folder).
fn column(tr: &Table, name: &str) -> Result<Vec<Option<f64>>, PlotError> {
    if tr.has(name) {
        tr.f64s(name)
    } else {
        Ok(vec![None; tr.height()])
    }
}

/// The plane panel and, with a vertical axis, the height panel of every traced run: the
/// truth, every filter's estimate and each sensor's fixes (null between fixes).
fn map_figures(
    t: &Tables,
    map: &PositionMap,
    kind: FigureKind,
    what: &str,
) -> Result<Vec<Figure>, PlotError> {
    let Some(tr) = &t.traces else {
        return Ok(Vec::new());
    };
    let col = |prefix: &str, q: &str| column(tr, &format!("{prefix}_{q}"));
    let (tr_r, tr_u) = (col("truth", &map.right.0)?, col("truth", &map.up.0)?);
    let (es_r, es_u) = (col("est", &map.right.0)?, col("est", &map.up.0)?);
    let sign = |v: Vec<Option<f64>>, neg: bool| -> Vec<Option<f64>> {
        if neg {
            v.into_iter().map(|x| x.map(|z| -z)).collect()
        } else {
            v
        }
    };
    let height = match &map.height {
        Some((q, _, neg)) => Some((sign(col("truth", q)?, *neg), sign(col("est", q)?, *neg))),
        None => None,
    };
    let time = tr.f64s("t")?;
    // Per sensor: (name, plane points' columns, height column).
    type Fix = (
        String,
        Option<(Vec<Option<f64>>, Vec<Option<f64>>)>,
        Option<Vec<Option<f64>>>,
    );
    let mut fixes: Vec<Fix> = Vec::new();
    for s in &map.fixes {
        let plane = match (&s.right, &s.up) {
            (Some(r), Some(u)) => Some((col("z", r)?, col("z", u)?)),
            _ => None,
        };
        let h = match (&s.height, &map.height) {
            (Some(c), Some((_, _, neg))) => Some(sign(col("z", c)?, *neg)),
            _ => None,
        };
        if plane.is_some() || h.is_some() {
            fixes.push((s.name.clone(), plane, h));
        }
    }
    let mut figs = Vec::new();
    for r in traced_runs(t, tr)? {
        let mut plane = Vec::new();
        let mut alt = Vec::new();
        if let Some((_, rows)) = r.filters.first() {
            for (i, (s, p, h)) in fixes.iter().enumerate() {
                if let Some((fr, fu)) = p {
                    plane.push(Mark::Scatter {
                        label: Some(format!("{s} fixes")),
                        ink: Ink::Palette(7 + i),
                        points: pairs(rows, fr, fu),
                    });
                }
                if let Some(fh) = h {
                    alt.push(Mark::Scatter {
                        label: Some(format!("{s} fixes")),
                        ink: Ink::Palette(7 + i),
                        points: pairs(rows, &time, fh),
                    });
                }
            }
        }
        for (f, rows) in &r.filters {
            plane.push(Mark::Line {
                label: Some(f.clone()),
                ink: t.ink(f),
                dashed: false,
                points: pairs(rows, &es_r, &es_u),
            });
            if let Some((_, eh)) = &height {
                alt.push(Mark::Line {
                    label: Some(f.clone()),
                    ink: t.ink(f),
                    dashed: false,
                    points: pairs(rows, &time, eh),
                });
            }
        }
        // The truth last, so that estimates lying on it do not hide it.
        if let Some((_, rows)) = r.filters.first() {
            plane.push(Mark::Line {
                label: Some("truth".into()),
                ink: Ink::Truth,
                dashed: true,
                points: pairs(rows, &tr_r, &tr_u),
            });
            if let Some((th, _)) = &height {
                alt.push(Mark::Line {
                    label: Some("truth".into()),
                    ink: Ink::Truth,
                    dashed: true,
                    points: pairs(rows, &time, th),
                });
            }
        }
        let mut panels = vec![Panel {
            title: map.plane_title.clone(),
            x_label: map.right.1.clone(),
            y_label: map.up.1.clone(),
            equal_aspect: map.height.is_some(),
            marks: plane,
            ..Panel::default()
        }];
        if let Some((_, label, _)) = &map.height {
            panels.push(Panel {
                title: "altitude".into(),
                x_label: "t [s]".into(),
                y_label: label.clone(),
                marks: alt,
                ..Panel::default()
            });
        }
        figs.push(Figure {
            kind,
            scenario: r.scenario.clone(),
            name: format!("{}_{}", kind.name(), file_part(&r.scenario)),
            title: format!("{}: {what} ({})", r.scenario, r.cell()),
            panels,
        });
    }
    Ok(figs)
}

/// `trajectory`: the plane of the position roles (x against y) of the first traced run per
/// scenario at the nominal noise scale; truth, every filter and the fixes of sensors that
/// measure both axes.
pub fn trajectory_series(t: &Tables) -> Result<Vec<Figure>, PlotError> {
    match trajectory_map(t) {
        Some(map) => map_figures(t, &map, FigureKind::Trajectory, "trajectory"),
        None => Ok(Vec::new()),
    }
}

/// `route`: the position of the first traced run per scenario (nominal noise scale) as
/// projections, for systems whose position roles hold a vertical axis (the drone's
/// north–east–down `px, py, pz`, L1's `x, y, z`): the plane (equal scales) and the altitude
/// over time, each with the truth, every filter's estimate and the fixes of the sensors that
/// measure the positions directly (null between fixes).
pub fn route_series(t: &Tables) -> Result<Vec<Figure>, PlotError> {
    match route_map(t) {
        Some(map) => map_figures(t, &map, FigureKind::Route, "route"),
        None => Ok(Vec::new()),
    }
}

/// The error e = x − x̂ (truth − estimate, the tables' convention) of every quantity on
/// every trace row: an angle's wrapped to ±180° (±π rad), a rotation's the rotation error,
/// as the tables score them.
pub fn state_errors(t: &Tables, tr: &Table) -> Result<Vec<Vec<Option<f64>>>, PlotError> {
    let n = t.states.len();
    let mut truth = Vec::with_capacity(n);
    let mut est = Vec::with_capacity(n);
    for s in &t.states {
        truth.push(tr.f64s(&format!("truth_{s}"))?);
        est.push(tr.f64s(&format!("est_{s}"))?);
    }
    let periods: Vec<Option<f64>> = t
        .states
        .iter()
        .map(|s| super::blocks::period(t, s))
        .collect();
    let mut out: Vec<Vec<Option<f64>>> = (0..n)
        .map(|i| {
            (0..tr.height())
                .map(|r| {
                    let mut v = truth[i][r]? - est[i][r]?;
                    if let Some(per) = periods[i] {
                        v -= per * (v / per).round();
                    }
                    Some(v)
                })
                .collect()
        })
        .collect();
    for rot in super::blocks::rotations(t) {
        for r in 0..tr.height() {
            let tv: Option<Vec<f64>> = (0..3).map(|j| truth[rot.first + j][r]).collect();
            let ev: Option<Vec<f64>> = (0..3).map(|j| est[rot.first + j][r]).collect();
            let (Some(tv), Some(ev)) = (tv, ev) else {
                for col in out.iter_mut().skip(rot.first).take(3) {
                    col[r] = None;
                }
                continue;
            };
            let local = EulerRotation { first: 0, ..rot };
            let mut e = [0.0; 3];
            local.error_into(&tv, &ev, &mut e);
            for (j, v) in e.iter().enumerate() {
                out[rot.first + j][r] = Some(*v);
            }
        }
    }
    Ok(out)
}

/// `states`: per quantity, the estimate error e = x − x̂ of every filter over time (steps ≥ 1)
/// in the first traced run (nominal noise scale), with its ±3·sqrt(var) band around 0 where the
/// filter has a covariance (`var_<s>` null, e.g. the running mean: no band). A consistent
/// filter's error stays inside its band; a 2 m error is as visible as on a 300 m route.
pub fn states_series(t: &Tables) -> Result<Vec<Figure>, PlotError> {
    let Some(tr) = &t.traces else {
        return Ok(Vec::new());
    };
    let time = tr.f64s("t")?;
    let step = tr.f64s("step")?;
    let runs = traced_runs(t, tr)?;
    let errors = state_errors(t, tr)?;
    let mut vars = Vec::new();
    for s in &t.states {
        vars.push(tr.f64s(&format!("var_{s}"))?);
    }
    let mut figs = Vec::new();
    for mut r in runs {
        // From step 1, as the consistency figures: step 0 is the prior x̂0, whose ±3σ (P0)
        // would set every panel's scale and hide the errors after the first update.
        for (_, rows) in &mut r.filters {
            rows.retain(|&i| step[i].is_some_and(|k| k >= 1.0));
        }
        let mut panels = Vec::new();
        for ((s, err), var) in t.states.iter().zip(&errors).zip(&vars) {
            let mut marks = Vec::new();
            for (f, rows) in &r.filters {
                let band: Vec<(f64, f64, f64)> = rows
                    .iter()
                    .filter_map(|&i| {
                        let sd = var[i]?.max(0.0).sqrt();
                        Some((time[i]?, -3.0 * sd, 3.0 * sd))
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
                    points: pairs(rows, &time, err),
                });
            }
            marks.push(Mark::HLine {
                label: None,
                ink: Ink::Reference,
                y: 0.0,
            });
            let unit = match t.unit(s) {
                "" => String::new(),
                u => format!(" [{u}]"),
            };
            panels.push(Panel {
                title: s.clone(),
                x_label: "t [s]".into(),
                y_label: format!("{s} error{unit}"),
                marks,
                ..Panel::default()
            });
        }
        figs.push(Figure {
            kind: FigureKind::States,
            scenario: r.scenario.clone(),
            name: format!("states_{}", file_part(&r.scenario)),
            title: format!(
                "{}: estimate error (truth − estimate) with ±3σ ({})",
                r.scenario,
                r.cell()
            ),
            panels,
        });
    }
    Ok(figs)
}
