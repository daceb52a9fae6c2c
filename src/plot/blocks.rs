//! ANEES per block of quantities (position, velocity, attitude), from the traced runs'
//! estimates, truths and full covariances (traces.parquet `P_<qi>_<qj>`).
//!
//! The whole-state ANEES says whether a filter is consistent; the blocks say *where* it is not
//! (a drone filter's excess sits in position when the GPS latency is unmodelled, in attitude
//! when the gyro bias is). The blocks are those of [`crate::metrics::blocks::group`], the same
//! as the `block_anees_<block>` columns of the tables: for the drone `px, py, pz` (m),
//! `vx, vy, vz` (m/s), `roll, pitch, yaw` (deg).

use nalgebra::{DMatrix, DVector};

use super::errors::wants_log;
use super::{Figure, FigureKind, Ink, Mark, Panel, Tables, file_part, short};
use crate::error::PlotError;
use crate::linalg::so3::{ErrorSide, EulerRotation};
use crate::metrics::consistency::average_chi2_band;

/// One block: its name and the indices of its quantities in `Tables::states`.
#[derive(Clone, Debug, PartialEq)]
pub struct Block {
    /// `position`, `velocity`, `attitude`, or the unit.
    pub name: String,
    /// The quantities' unit.
    pub unit: String,
    /// The quantities.
    pub quantities: Vec<String>,
    idx: Vec<usize>,
}

/// The blocks of a folder's quantities, or none when blocks would say nothing the whole-state
/// ANEES does not (fewer than two blocks, or no block of three or more quantities — the planar
/// quadrotor's pairs), or the traces lack the covariance.
pub fn blocks(t: &Tables) -> Vec<Block> {
    let Some(tr) = &t.traces else {
        return Vec::new();
    };
    // A rotation's quantities form an attitude block as three angles do.
    let angle = |q: &str| {
        t.manifest
            .as_ref()
            .and_then(|m| m.quantities.iter().find(|e| e.name == q))
            .is_some_and(|e| e.angle || e.rotation.is_some())
    };
    // The tables' grouping ([`crate::metrics::blocks`]), one definition for both.
    let units: Vec<(String, bool)> = t
        .states
        .iter()
        .map(|q| (t.unit(q).to_string(), angle(q)))
        .collect();
    let out: Vec<Block> =
        crate::metrics::blocks::group(units.iter().map(|(u, a)| (u.as_str(), *a)))
            .into_iter()
            .map(|b| Block {
                name: b.name,
                unit: b.unit,
                quantities: b.indices.iter().map(|&i| t.states[i].clone()).collect(),
                idx: b.indices,
            })
            .collect();
    let covariances = out.iter().all(|b| {
        b.idx.iter().all(|&i| {
            b.idx
                .iter()
                .all(|&j| tr.has(&p_name(&t.states, i.max(j), i.min(j))))
        })
    });
    if out.len() < 2 || !out.iter().any(|b| b.idx.len() >= 3) || !covariances {
        return Vec::new();
    }
    out
}

/// The rotations among a folder's quantities (indices into `Tables::states`), from the
/// manifest: three consecutive quantities marked with the same side.
pub(super) fn rotations(t: &Tables) -> Vec<EulerRotation> {
    let side_of = |q: &str| {
        let e = t
            .manifest
            .as_ref()?
            .quantities
            .iter()
            .find(|e| e.name == q)?;
        match e.rotation.as_deref()? {
            "left" => Some((ErrorSide::Left, e.unit == "deg")),
            _ => Some((ErrorSide::Right, e.unit == "deg")),
        }
    };
    let sides: Vec<_> = t.states.iter().map(|s| side_of(s)).collect();
    let mut out = Vec::new();
    let mut i = 0;
    while i + 3 <= sides.len() {
        match sides[i] {
            Some((side, degrees)) if sides[i + 1] == sides[i] && sides[i + 2] == sides[i] => {
                out.push(EulerRotation {
                    first: i,
                    degrees,
                    side,
                });
                i += 3;
            }
            _ => i += 1,
        }
    }
    out
}

/// The period an angle quantity's error wraps with (360° or 2π), from the manifest; `None`
/// for any other quantity.
pub(super) fn period(t: &Tables, q: &str) -> Option<f64> {
    let m = t.manifest.as_ref()?;
    let e = m.quantities.iter().find(|e| e.name == q)?;
    e.angle.then(|| {
        if e.unit == "deg" {
            360.0
        } else {
            std::f64::consts::TAU
        }
    })
}

fn p_name(states: &[String], i: usize, j: usize) -> String {
    format!("P_{}_{}", states[i], states[j])
}

/// The per-step block ANEES of one (scenario, filter variant) over the traced runs.
#[derive(Clone, Debug, PartialEq)]
pub struct BlockCell {
    /// Scenario.
    pub scenario: String,
    /// Filter variant.
    pub filter: String,
    /// Noise scale of the traces.
    pub noise_scale: f64,
    /// Per block: (t, ANEES over the traced runs, runs averaged) for every step ≥ 1.
    pub series: Vec<Vec<(f64, f64, usize)>>,
}

impl BlockCell {
    /// Time average of a block's ANEES and the fraction of steps inside the per-step
    /// two-sided χ² band at `alpha`.
    pub fn time_average(&self, b: usize, dof: usize, alpha: f64) -> (f64, f64) {
        let s = &self.series[b];
        let mean = s.iter().map(|p| p.1).sum::<f64>() / s.len().max(1) as f64;
        let inside = s
            .iter()
            .filter(|p| {
                average_chi2_band(dof as f64, p.2 as f64, alpha).is_some_and(|bd| bd.contains(p.1))
            })
            .count();
        (mean, inside as f64 / s.len().max(1) as f64)
    }
}

/// The significance level of the folder's spec (`[consistency] alpha`, default 0.05).
pub fn alpha(t: &Tables) -> f64 {
    t.manifest
        .as_ref()
        .and_then(|m| m.spec.parse::<toml::Table>().ok())
        .and_then(|s| s.get("consistency")?.get("alpha")?.as_float())
        .unwrap_or(0.05)
}

/// Block NEES of every traced (scenario, filter variant), averaged over its traced runs per
/// step. Angle errors are wrapped to ±180° (±π rad), and a rotation's error is its rotation
/// error, as the tables score it. Steps whose block covariance is missing
/// or not positive definite are left out.
pub fn block_cells(t: &Tables, bl: &[Block]) -> Result<Vec<BlockCell>, PlotError> {
    let Some(tr) = &t.traces else {
        return Ok(Vec::new());
    };
    if bl.is_empty() {
        return Ok(Vec::new());
    }
    let scen = tr.strs("scenario")?;
    let filt = tr.strs("filter")?;
    let step = tr.f64s("step")?;
    let time = tr.f64s("t")?;
    let noise = tr.f64s("noise_scale")?;
    let n = t.states.len();
    let mut truth = Vec::with_capacity(n);
    let mut est = Vec::with_capacity(n);
    for s in &t.states {
        truth.push(tr.f64s(&format!("truth_{s}"))?);
        est.push(tr.f64s(&format!("est_{s}"))?);
    }
    let periods: Vec<Option<f64>> = t.states.iter().map(|s| period(t, s)).collect();
    let rotations = rotations(t);
    let mut pcols = std::collections::BTreeMap::new();
    for b in bl {
        for &i in &b.idx {
            for &j in &b.idx {
                let (a, c) = (i.max(j), i.min(j));
                if let std::collections::btree_map::Entry::Vacant(v) = pcols.entry((a, c)) {
                    v.insert(tr.f64s(&p_name(&t.states, a, c))?);
                }
            }
        }
    }
    // (scenario, filter) → step → per block (sum of NEES, runs, t).
    type Acc = std::collections::BTreeMap<i64, (f64, Vec<(f64, usize)>)>;
    let mut cells: Vec<((String, String), f64, Acc)> = Vec::new();
    for r in 0..tr.height() {
        let Some(k) = step[r] else { continue };
        if k < 1.0 {
            continue;
        }
        let key = (scen[r].clone(), filt[r].clone());
        let ci = match cells.iter().position(|c| c.0 == key) {
            Some(p) => p,
            None => {
                cells.push((key, noise[r].unwrap_or(f64::NAN), Acc::new()));
                cells.len() - 1
            }
        };
        let entry = cells[ci]
            .2
            .entry(k as i64)
            .or_insert_with(|| (time[r].unwrap_or(f64::NAN), vec![(0.0, 0); bl.len()]));
        for (bi, b) in bl.iter().enumerate() {
            let d = b.idx.len();
            let mut e = DVector::zeros(d);
            let mut p = DMatrix::zeros(d, d);
            let mut ok = true;
            for (a, &i) in b.idx.iter().enumerate() {
                match (truth[i][r], est[i][r]) {
                    (Some(x), Some(xh)) => {
                        let mut v = x - xh;
                        if let Some(per) = periods[i] {
                            v -= per * (v / per).round();
                        }
                        e[a] = v;
                    }
                    _ => ok = false,
                }
                for (c, &j) in b.idx.iter().enumerate() {
                    match pcols[&(i.max(j), i.min(j))][r] {
                        Some(v) => p[(a, c)] = v,
                        None => ok = false,
                    }
                }
            }
            if !ok {
                continue;
            }
            for rot in &rotations {
                let Some(a0) = b.idx.iter().position(|&i| i == rot.first) else {
                    continue;
                };
                if b.idx.get(a0 + 2) != Some(&(rot.first + 2)) {
                    continue;
                }
                // Both are present: `ok` checked every quantity of the block.
                let tv: Vec<f64> = (0..3).filter_map(|j| truth[rot.first + j][r]).collect();
                let ev: Vec<f64> = (0..3).filter_map(|j| est[rot.first + j][r]).collect();
                let local = EulerRotation { first: 0, ..*rot };
                let mut out = [0.0; 3];
                local.error_into(&tv, &ev, &mut out);
                for (j, v) in out.iter().enumerate() {
                    e[a0 + j] = *v;
                }
            }
            let Some(ch) = p.cholesky() else { continue };
            let nees = e.dot(&ch.solve(&e));
            if nees.is_finite() {
                entry.1[bi].0 += nees;
                entry.1[bi].1 += 1;
            }
        }
    }
    let mut out: Vec<BlockCell> = cells
        .into_iter()
        .map(|((scenario, filter), noise_scale, acc)| {
            let series = (0..bl.len())
                .map(|bi| {
                    acc.values()
                        .filter(|(_, v)| v[bi].1 > 0)
                        .map(|(tk, v)| (*tk, v[bi].0 / v[bi].1 as f64, v[bi].1))
                        .collect()
                })
                .collect();
            BlockCell {
                scenario,
                filter,
                noise_scale,
                series,
            }
        })
        .collect();
    // Scenario order of the summary, then filter colour order.
    let pos = |v: &[String], s: &str| v.iter().position(|x| x == s);
    out.sort_by(|a, b| {
        pos(&t.scenarios, &a.scenario)
            .cmp(&pos(&t.scenarios, &b.scenario))
            .then(pos(&t.filters, &a.filter).cmp(&pos(&t.filters, &b.filter)))
    });
    Ok(out)
}

/// `block_consistency`: per scenario, one panel per block with each filter variant's ANEES
/// over the traced runs against time (steps ≥ 1), the per-step χ² band for the traced runs and
/// the consistent mean (the block's size). Nothing unless [`blocks`] finds blocks.
pub fn block_consistency_series(t: &Tables) -> Result<Vec<Figure>, PlotError> {
    let bl = blocks(t);
    let cells = block_cells(t, &bl)?;
    let alpha = alpha(t);
    let mut figs = Vec::new();
    for sc in &t.scenarios {
        let mine: Vec<&BlockCell> = cells.iter().filter(|c| c.scenario == *sc).collect();
        if mine.is_empty() {
            continue;
        }
        let runs = mine
            .iter()
            .flat_map(|c| c.series.iter().flatten().map(|p| p.2))
            .max()
            .unwrap_or(0);
        let panels = bl
            .iter()
            .enumerate()
            .map(|(bi, b)| {
                let d = b.idx.len();
                let mut marks = Vec::new();
                // The band depends on the runs averaged only; draw it from the first cell.
                if let Some(c) = mine.first() {
                    let points: Vec<(f64, f64, f64)> = c.series[bi]
                        .iter()
                        .filter_map(|p| {
                            let band = average_chi2_band(d as f64, p.2 as f64, alpha)?;
                            Some((p.0, band.lo, band.hi))
                        })
                        .collect();
                    marks.push(Mark::Band {
                        label: Some(format!("χ² acceptance band (α = {})", short(alpha))),
                        ink: Ink::Reference,
                        points,
                    });
                }
                let mut plotted = Vec::new();
                for c in &mine {
                    let points: Vec<(f64, f64)> = c.series[bi].iter().map(|p| (p.0, p.1)).collect();
                    plotted.extend(points.iter().map(|p| p.1));
                    marks.push(Mark::Line {
                        label: Some(c.filter.clone()),
                        ink: t.ink(&c.filter),
                        dashed: false,
                        points,
                    });
                }
                marks.push(Mark::HLine {
                    label: Some("consistent mean (block size)".into()),
                    ink: Ink::Reference,
                    y: d as f64,
                });
                Panel {
                    title: format!(
                        "{} ({}), consistent mean {d}",
                        b.name,
                        b.quantities.join(", ")
                    ),
                    x_label: "t [s]".into(),
                    y_label: "block ANEES [–]".into(),
                    log_y: wants_log(plotted.into_iter()),
                    marks,
                    ..Panel::default()
                }
            })
            .collect();
        figs.push(Figure {
            kind: FigureKind::BlockConsistency,
            scenario: sc.clone(),
            name: format!("block_consistency_{}", file_part(sc)),
            title: format!(
                "{sc}: ANEES per block over {runs} traced run{} (noise ×{}), steps ≥ 1",
                if runs == 1 { "" } else { "s" },
                short(mine[0].noise_scale)
            ),
            panels,
        });
    }
    Ok(figs)
}
