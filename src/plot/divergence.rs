//! The distribution of per-run divergence multipliers (divergence_runs.parquet).

use super::{Bar, Figure, FigureKind, Mark, Panel, Tables, file_part};
use crate::error::PlotError;

/// At most this many bins; fewer when the runs crossed at fewer distinct multipliers.
const MAX_BINS: usize = 20;

/// Counts of `values` in `bins` equal bins over [lo, hi] (the last bin includes hi).
pub fn histogram(values: &[f64], lo: f64, hi: f64, bins: usize) -> Vec<u64> {
    let mut counts = vec![0u64; bins];
    let w = (hi - lo) / bins as f64;
    for &v in values {
        let b = if w > 0.0 {
            (((v - lo) / w).floor() as usize).min(bins - 1)
        } else {
            0
        };
        counts[b] += 1;
    }
    counts
}

/// `divergence_hist`: per scenario, one panel per state with one histogram per filter of
/// the multiplier at which each run's RMSE first crossed the threshold. Runs that never
/// crossed (null `divergence_scale`) cannot be placed; the legend counts them.
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
            let all: Vec<f64> = per_filter
                .iter()
                .flat_map(|p| p.1.iter().copied())
                .collect();
            let lo = all.iter().copied().fold(f64::INFINITY, f64::min);
            let hi = all.iter().copied().fold(f64::NEG_INFINITY, f64::max);
            let mut distinct = all.clone();
            distinct.sort_by(f64::total_cmp);
            distinct.dedup();
            let bins = distinct.len().clamp(1, MAX_BINS);
            // One distinct value: a bin of width 1 around it rather than of width 0.
            let (lo, hi) = if all.is_empty() {
                (0.0, 1.0)
            } else if hi > lo {
                (lo, hi)
            } else {
                (lo - 0.5, hi + 0.5)
            };
            let w = (hi - lo) / bins as f64;
            let nf = per_filter.len().max(1) as f64;
            let marks = per_filter
                .iter()
                .enumerate()
                .map(|(j, (f, crossed, never))| {
                    let counts = histogram(crossed, lo, hi, bins);
                    let bars = counts
                        .iter()
                        .enumerate()
                        .map(|(b, &c)| {
                            let x0 = lo + b as f64 * w + j as f64 * w / nf;
                            Bar {
                                x0,
                                x1: x0 + w / nf,
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
    fn histogram_counts_every_value_once() {
        let v = [0.2, 0.4, 0.4, 1.0, 2.0];
        let c = histogram(&v, 0.2, 2.0, 3);
        assert_eq!(c.iter().sum::<u64>(), 5);
        assert_eq!(c, vec![3, 1, 1]);
        assert_eq!(histogram(&[3.0, 3.0], 3.0, 3.0, 1), vec![2]);
    }
}
