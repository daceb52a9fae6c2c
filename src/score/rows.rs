//! A block of an estimates file's rows as it is read: its columns, typed, and its values
//! row by row as the spill holds them.

use std::collections::HashMap;
use std::path::Path;

use polars::prelude::*;

use crate::error::OutputError;

use super::columns::EstimateColumns;
use super::rotation::{euler_columns, quaternion_columns};
use super::{FAILED_COLUMN, format_err};

/// An estimates file's columns, as they are read.
pub(super) struct FileColumns {
    pub(super) columns: EstimateColumns,
    /// The value columns in spill order.
    names: Vec<String>,
    /// Values per row.
    pub(super) width: usize,
    /// Where null means "not given" and a non-finite number is an error: the innovation and
    /// the error transition.
    innovation: std::ops::Range<usize>,
    transition: std::ops::Range<usize>,
}

impl FileColumns {
    pub(super) fn new(columns: EstimateColumns) -> Self {
        let width = columns.width();
        let nu_at = columns.nq() + columns.ntri();
        FileColumns {
            names: columns.value_columns(),
            innovation: if columns.innovations {
                nu_at..nu_at + columns.nz()
            } else {
                0..0
            },
            transition: if columns.transition {
                width - columns.nq() * columns.nq()..width
            } else {
                0..0
            },
            width,
            columns,
        }
    }

    /// Row `i`'s values into `buf` (NaN where null), refusing a non-finite innovation or
    /// transition entry and a transition given in part.
    pub(super) fn values(
        &self,
        path: &Path,
        rows: &RowGroup,
        i: usize,
        buf: &mut Vec<f64>,
    ) -> Result<(), OutputError> {
        let values = &rows.values;
        buf.clear();
        buf.extend(values.iter().map(|c| c.get(i).unwrap_or(f64::NAN)));
        let non_finite = |t: &usize| values[*t].get(i).is_some_and(|v| !v.is_finite());
        if let Some(t) = self
            .innovation
            .clone()
            .chain(self.transition.clone())
            .find(non_finite)
        {
            return Err(format_err(
                path,
                format!(
                    "column `{}`: {} at {} (null means not given; a NaN or infinite value is an error)",
                    self.names[t],
                    buf[t],
                    rows.key(i)
                ),
            ));
        }
        let a = self.transition.clone();
        let given = a.clone().filter(|t| values[*t].get(i).is_some()).count();
        if given != 0 && given != a.len() {
            let t = a
                .clone()
                .find(|t| values[*t].get(i).is_none())
                .expect("some entry is null");
            return Err(format_err(
                path,
                format!(
                    "column `{}`: null at {} where the row gives {given} other A_ entries (give the whole error transition of a step, or none)",
                    self.names[t],
                    rows.key(i)
                ),
            ));
        }
        Ok(())
    }
}

/// Rows the reader checks and spills at once: a file's row group or a table's batch is
/// read in blocks of at most this many rows, so a table handed over as one batch of
/// millions of rows costs no more memory than a file's row group (a block's values, row by
/// row, are 4,096 × the row's width × 8 bytes: 2.4 MB for L1's 72 values).
pub(super) const BLOCK_ROWS: usize = 4096;

/// One block of rows of a row group or batch: its key and value columns, typed, and the
/// values row by row as the spill holds them.
pub(super) struct RowGroup {
    /// The file row of the group's first row (for messages).
    pub(super) first_row: usize,
    pub(super) scenario: StringChunked,
    pub(super) filter: StringChunked,
    pub(super) noise: Float64Chunked,
    pub(super) run: Int64Chunked,
    pub(super) step: Int64Chunked,
    /// The variant columns, when the file has them.
    pub(super) q_scale: Option<Float64Chunked>,
    pub(super) r_scale: Option<Float64Chunked>,
    /// The `failed` column, when the file has it.
    pub(super) failed: Option<BooleanChunked>,
    values: Vec<Float64Chunked>,
    /// The values row by row (`width` per row, the spill's order), NaN where null.
    pub(super) table: Vec<f64>,
    /// Rows with a non-null, non-finite innovation or transition entry: an error, whose
    /// message [`FileColumns::values`] forms when the row is reached.
    flagged: Vec<bool>,
}

impl RowGroup {
    pub(super) fn new(
        path: &Path,
        df: &DataFrame,
        first_row: usize,
        columns: &FileColumns,
    ) -> Result<Self, OutputError> {
        let frame = super::FrameColumns { path, df };
        let strs = |name: &str| frame.strs(name);
        let floats = |name: &str| frame.floats(name);
        let ints = |name: &str| frame.ints(name);
        let optional = |name: &str| frame.optional_floats(name);
        // A rotation given as a quaternion is read as the Euler angles its `est_` columns
        // would hold.
        let cols = &columns.columns;
        let mut from_quaternions = HashMap::new();
        for r in &cols.quaternions {
            let quat: Vec<Float64Chunked> = quaternion_columns(&cols.quantities, r)
                .iter()
                .map(|n| floats(n))
                .collect::<Result<_, _>>()?;
            for (j, e) in euler_columns(r, &quat).into_iter().enumerate() {
                from_quaternions.insert(format!("est_{}", cols.quantities[r.first + j]), e);
            }
        }
        let values: Vec<Float64Chunked> = columns
            .names
            .iter()
            .map(|n| from_quaternions.remove(n).map_or_else(|| floats(n), Ok))
            .collect::<Result<_, _>>()?;
        // Column by column into rows: one pass over each column's contiguous values, where
        // reading row by row would look every value up through its chunk.
        let (height, width) = (df.height(), columns.width);
        let mut table = vec![f64::NAN; height * width];
        let mut flagged = vec![false; height];
        for (t, column) in values.iter().enumerate() {
            let checked = columns.innovation.contains(&t) || columns.transition.contains(&t);
            let mut i = 0;
            for array in column.downcast_iter() {
                let given = array.validity();
                for (k, v) in array.values().iter().enumerate() {
                    if given.is_none_or(|g| g.get_bit(k)) {
                        table[(i + k) * width + t] = *v;
                        if checked && !v.is_finite() {
                            flagged[i + k] = true;
                        }
                    }
                }
                i += array.len();
            }
        }
        Ok(RowGroup {
            first_row,
            scenario: strs("scenario")?,
            filter: strs("filter")?,
            noise: floats("noise_scale")?,
            run: ints("run")?,
            step: ints("step")?,
            q_scale: optional("q_scale")?,
            r_scale: optional("r_scale")?,
            failed: match df.column(FAILED_COLUMN) {
                Ok(c) if c.dtype() == &DataType::Boolean => Some(
                    c.bool()
                        .map_err(|e| frame.column_err(FAILED_COLUMN, e))?
                        .clone(),
                ),
                Ok(c) => {
                    return Err(format_err(
                        path,
                        format!(
                            "column `{FAILED_COLUMN}` must be boolean (true from the step at which the filter failed), not {}",
                            c.dtype()
                        ),
                    ));
                }
                Err(_) => None,
            },
            values,
            table,
            flagged,
        })
    }

    /// Whether row `i` gives its innovation and transition as the format asks: finite
    /// where not null, and the transition whole or not at all. A row that does not is one
    /// [`FileColumns::values`] refuses.
    pub(super) fn row_is_clean(&self, columns: &FileColumns, i: usize) -> bool {
        if self.flagged[i] {
            return false;
        }
        // No entry of the transition is a non-null NaN (the row is not flagged), so NaN
        // there is null.
        let row = &self.table[i * columns.width..(i + 1) * columns.width];
        let a = &row[columns.transition.clone()];
        let given = a.iter().filter(|v| !v.is_nan()).count();
        given == 0 || given == a.len()
    }

    /// Whether row `i` has the same filter, variant, scenario and noise scale as row `j`.
    pub(super) fn same_cell_and_filter(&self, i: usize, j: usize) -> bool {
        let bits = |c: &Float64Chunked, k: usize| c.get(k).map(f64::to_bits);
        let variant =
            |c: &Option<Float64Chunked>| c.as_ref().is_none_or(|c| bits(c, i) == bits(c, j));
        self.filter.get(i).is_some()
            && self.filter.get(i) == self.filter.get(j)
            && self.scenario.get(i).is_some()
            && self.scenario.get(i) == self.scenario.get(j)
            && bits(&self.noise, i).is_some()
            && bits(&self.noise, i) == bits(&self.noise, j)
            && variant(&self.q_scale)
            && variant(&self.r_scale)
    }

    /// Row `i`'s key, for messages.
    pub(super) fn key(&self, i: usize) -> String {
        let o = |v: Option<String>| v.unwrap_or_else(|| "null".into());
        let mut key = format!(
            "scenario = {}, noise_scale = {}, run = {}, step = {}, filter = {}",
            o(self.scenario.get(i).map(|s| format!("{s:?}"))),
            o(self.noise.get(i).map(|v| v.to_string())),
            o(self.run.get(i).map(|v| v.to_string())),
            o(self.step.get(i).map(|v| v.to_string())),
            o(self.filter.get(i).map(|s| format!("{s:?}"))),
        );
        for (name, c) in [("q_scale", &self.q_scale), ("r_scale", &self.r_scale)] {
            if let Some(c) = c {
                key.push_str(&format!(
                    ", {name} = {}",
                    o(c.get(i).map(|v| v.to_string()))
                ));
            }
        }
        key
    }
}
