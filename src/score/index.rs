//! A study's keys as indexes: what every row of an estimates file is checked against.

use std::collections::HashMap;
use std::path::Path;

use crate::error::OutputError;

use super::rows::RowGroup;
use super::{StudyFilter, StudyKeys, format_err};

/// A study's keys as indexes: what every row of an estimates file is checked against.
pub(super) struct KeyIndex<'a> {
    pub(super) study: &'a StudyKeys<'a>,
    /// External filter label → the study's filter indexes of its variants.
    label_of: HashMap<&'a str, Vec<usize>>,
    scenario_of: HashMap<&'a str, usize>,
    /// A noise multiplier's bits → its index (the values must be the simulation's exactly).
    scale_of: HashMap<u64, usize>,
    /// Per cell (scenario-major): the first row index and the samples K + 1 per run.
    pub(super) cells: Vec<(u64, usize)>,
    /// Rows of every cell together.
    pub(super) total: u64,
}

impl<'a> KeyIndex<'a> {
    pub(super) fn new(study: &'a StudyKeys<'a>) -> Self {
        let n_scales = study.noise_scales.len();
        let mut cells = Vec::with_capacity(study.scenarios.len() * n_scales);
        let mut total = 0u64;
        for &(_, steps) in &study.scenarios {
            for _ in 0..n_scales {
                cells.push((total, steps + 1));
                total += (study.runs * (steps + 1)) as u64;
            }
        }
        KeyIndex {
            label_of: study
                .filters
                .iter()
                .enumerate()
                .filter(|(_, f)| f.external)
                .fold(
                    HashMap::new(),
                    |mut m: HashMap<&str, Vec<usize>>, (i, f)| {
                        m.entry(f.label).or_default().push(i);
                        m
                    },
                ),
            scenario_of: study
                .scenarios
                .iter()
                .enumerate()
                .map(|(i, (name, _))| (*name, i))
                .collect(),
            scale_of: study
                .noise_scales
                .iter()
                .enumerate()
                .map(|(i, s)| (s.to_bits(), i))
                .collect(),
            cells,
            total,
            study,
        }
    }

    /// The study filter index of row `i`'s label, which must be an external filter's, and of
    /// its variant: the `q_scale`/`r_scale` columns name it when the label declares variants.
    pub(super) fn filter(
        &self,
        path: &Path,
        rows: &RowGroup,
        i: usize,
    ) -> Result<usize, OutputError> {
        let label = rows.filter.get(i).ok_or_else(|| {
            format_err(
                path,
                format!("column `filter`: null at row {}", rows.first_row + i),
            )
        })?;
        let variants = self.label_of.get(label).ok_or_else(|| {
            let declared = self.study.filters.iter().any(|f| f.label == label);
            format_err(
                path,
                if declared {
                    format!(
                        "column `filter`: `{label}` is one of kfmc's filters, not an external one (set kind = \"external\" in the spec to score it from a file) at {}",
                        rows.key(i)
                    )
                } else {
                    format!(
                        "column `filter`: `{label}` is not a filter of the spec; declare it with [[filters]] label = \"{label}\", kind = \"external\" (at {})",
                        rows.key(i)
                    )
                },
            )
        })?;
        self.variant(path, rows, i, label, variants)
    }

    /// Which of `label`'s variants (study filter indexes) row `i` names. A label without
    /// declared variants takes rows whose `q_scale` and `r_scale` are null (or absent); one
    /// with them needs a column for each axis it declares, with one of the declared values
    /// (exactly), and 1 or null on an axis it does not declare.
    fn variant(
        &self,
        path: &Path,
        rows: &RowGroup,
        i: usize,
        label: &str,
        variants: &[usize],
    ) -> Result<usize, OutputError> {
        let first = &self.study.filters[variants[0]];
        let keyed = first.multipliers.is_some();
        let mut want = [1.0f64; 2];
        for (axis, (name, declared, column)) in [
            ("q_scale", first.q_column, rows.q_scale.as_ref()),
            ("r_scale", first.r_column, rows.r_scale.as_ref()),
        ]
        .into_iter()
        .enumerate()
        {
            let of = |f: &StudyFilter| f.multipliers.map_or(1.0, |m| [m.0, m.1][axis]);
            let mut declared_values: Vec<f64> = variants
                .iter()
                .map(|&v| of(&self.study.filters[v]))
                .collect();
            declared_values.sort_by(f64::total_cmp);
            declared_values.dedup();
            let list = declared_values
                .iter()
                .map(|v| v.to_string())
                .collect::<Vec<_>>()
                .join(", ");
            let value = column.and_then(|c| c.get(i));
            match (declared, column, value) {
                (true, None, _) => {
                    return Err(format_err(
                        path,
                        format!(
                            "missing column `{name}`: filter `{label}` declares {name} variants ({name} = {list}) in the spec, so its rows name their variant in a `{name}` column (first row of `{label}`: {})",
                            rows.key(i)
                        ),
                    ));
                }
                (true, Some(_), None) => {
                    return Err(format_err(
                        path,
                        format!(
                            "column `{name}`: null at {}; filter `{label}` declares {name} = {list}, and each of its rows names its variant",
                            rows.key(i)
                        ),
                    ));
                }
                (true, Some(_), Some(v)) => {
                    if !declared_values.iter().any(|d| d.to_bits() == v.to_bits()) {
                        return Err(format_err(
                            path,
                            format!(
                                "column `{name}`: {v} is not a variant of filter `{label}`, which declares {name} = {list} (the values exactly; add {v} to the spec's list to score it) at {}",
                                rows.key(i)
                            ),
                        ));
                    }
                    want[axis] = v;
                }
                (false, _, Some(v)) if !keyed || v != 1.0 => {
                    return Err(format_err(
                        path,
                        format!(
                            "column `{name}`: {v} at {}, but filter `{label}` declares no {name} variants (list {name} = [...] in its [[filters]] entry to score variants; else leave `{name}` null for its rows)",
                            rows.key(i)
                        ),
                    ));
                }
                (false, _, _) => {}
            }
        }
        if !keyed {
            return Ok(variants[0]);
        }
        Ok(variants
            .iter()
            .copied()
            .find(|&v| {
                self.study.filters[v].multipliers.is_some_and(|(q, r)| {
                    q.to_bits() == want[0].to_bits() && r.to_bits() == want[1].to_bits()
                })
            })
            .expect("the variants are every declared (q_scale, r_scale) pair"))
    }

    /// The cell of row `i`'s (scenario, noise scale): its first row index and its samples
    /// K + 1 per run.
    pub(super) fn cell(
        &self,
        path: &Path,
        rows: &RowGroup,
        i: usize,
    ) -> Result<(u64, usize), OutputError> {
        let si = rows
            .scenario
            .get(i)
            .and_then(|s| self.scenario_of.get(s).copied())
            .ok_or_else(|| {
                format_err(
                    path,
                    format!(
                        "column `scenario`: not a scenario of this study at {}",
                        rows.key(i)
                    ),
                )
            })?;
        let sj = rows
            .noise
            .get(i)
            .and_then(|v| self.scale_of.get(&v.to_bits()).copied())
            .ok_or_else(|| {
                format_err(path, format!("column `noise_scale`: not a noise scale of this study (values must be the simulation's exactly) at {}", rows.key(i)))
            })?;
        Ok(self.cells[si * self.study.noise_scales.len() + sj])
    }

    /// The row index of row `i`'s (run, step) among every cell's rows, in its `cell`
    /// ([`KeyIndex::cell`]).
    pub(super) fn row(
        &self,
        path: &Path,
        rows: &RowGroup,
        i: usize,
        (base, samples): (u64, usize),
    ) -> Result<u64, OutputError> {
        let runs = self.study.runs;
        let r = rows
            .run
            .get(i)
            .filter(|r| (0..runs as i64).contains(r))
            .ok_or_else(|| {
                format_err(
                    path,
                    format!("column `run`: outside 0..{runs} at {}", rows.key(i)),
                )
            })?;
        let k = rows
            .step
            .get(i)
            .filter(|k| (0..samples as i64).contains(k))
            .ok_or_else(|| {
                format_err(
                    path,
                    format!(
                        "column `step`: outside 0..={} at {}",
                        samples - 1,
                        rows.key(i)
                    ),
                )
            })?;
        Ok(base + r as u64 * samples as u64 + k as u64)
    }
}
