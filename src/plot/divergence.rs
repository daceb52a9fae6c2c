//! The distribution of per-run divergence multipliers (divergence_runs.parquet).

use super::{Bar, Figure, FigureKind, Mark, Panel, Tables, file_part, short};
use crate::error::PlotError;

/// How many of `values` equal each of `grid`'s points (the multipliers are points of the
/// study's noise-scale grid, so a count is exact, never a bin's).
pub fn counts_on(values: &[f64], grid: &[f64]) -> Vec<u64> {
    grid.iter()
        .map(|g| values.iter().filter(|v| *v == g).count() as u64)
        .collect()
}

/// `divergence_hist`: per scenario, one panel per state with one bar per filter at each
/// noise multiplier of the study's grid at which runs first crossed the threshold, its height
/// the number of runs that crossed there. The x axis is ordinal: one slot per such multiplier,
/// in ascending order and labelled with it, so a count sits at its multiplier on any grid
/// (equal-width bins over a non-uniform grid would not). Runs that never crossed (null
/// `divergence_scale`) cannot be placed; the legend counts them.
pub fn divergence_hist_series(t: &Tables) -> Result<Vec<Figure>, PlotError> {
    let Some(dr) = &t.divergence_runs else {
        return Ok(Vec::new());
    };
    let scen = dr.strs("scenario")?;
    let filt = dr.strs("filter")?;
    let state = dr.strs("state")?;
    let scale = dr.f64s("divergence_scale")?;
    let mut figs = Vec::new();
    for sc in &t.scenarios {
        if !scen.contains(sc) {
            continue;
        }
        let mut panels = Vec::new();
        for s in &t.states {
            // Per filter: (label, crossed multipliers, runs that never crossed).
            let per_filter: Vec<(&String, Vec<f64>, usize)> = t
                .filters
                .iter()
                .filter_map(|f| {
                    let rows: Vec<usize> = (0..dr.height())
                        .filter(|&i| scen[i] == *sc && filt[i] == *f && state[i] == *s)
                        .collect();
                    if rows.is_empty() {
                        return None;
                    }
                    let crossed: Vec<f64> = rows.iter().filter_map(|&i| scale[i]).collect();
                    let never = rows.len() - crossed.len();
                    Some((f, crossed, never))
                })
                .collect();
            // The multipliers at which any run crossed, ascending: the bars' positions.
            let mut at: Vec<f64> = per_filter
                .iter()
                .flat_map(|p| p.1.iter().copied())
                .collect();
            at.sort_by(f64::total_cmp);
            at.dedup();
            let nf = per_filter.len().max(1) as f64;
            let marks = per_filter
                .iter()
                .enumerate()
                .map(|(j, (f, crossed, never))| {
                    let counts = counts_on(crossed, &at);
                    let bars = at
                        .iter()
                        .zip(&counts)
                        .enumerate()
                        .map(|(b, (_, &c))| {
                            // The filters share the multiplier's slot, 0.8 wide around b.
                            let w = 0.8 / nf;
                            let x0 = b as f64 - 0.4 + j as f64 * w;
                            Bar {
                                x0,
                                x1: x0 + w,
                                y: c as f64,
                                whisker: None,
                            }
                        })
                        .collect();
                    Mark::Bars {
                        label: Some(format!(
                            "{f} ({never} of {} runs never diverged)",
                            crossed.len() + never
                        )),
                        ink: t.ink(f),
                        bars,
                    }
                })
                .collect();
            panels.push(Panel {
                title: format!("divergence of {s}"),
                x_label: "divergence multiplier [–]".into(),
                y_label: "runs [count]".into(),
                integer_y: true,
                x_categories: Some(at.iter().map(|v| short(*v)).collect()),
                marks,
                ..Panel::default()
            });
        }
        figs.push(Figure {
            kind: FigureKind::DivergenceHist,
            scenario: sc.clone(),
            name: format!("divergence_hist_{}", file_part(sc)),
            title: format!("{sc}: noise multiplier at which each run diverges"),
            panels,
        });
    }
    Ok(figs)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counts_sit_on_their_grid_points() {
        let grid = [0.5, 1.0, 2.0, 7.0, 20.0];
        let c = counts_on(&[7.0, 7.0, 2.0, 20.0], &grid);
        assert_eq!(c, vec![0, 0, 1, 2, 1]);
    }
}
