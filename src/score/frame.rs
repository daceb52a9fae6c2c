//! Typed columns of one block of a table in the exchange format, with errors that name the
//! file and the column: one accessor for every reader of the format (estimates, and the
//! recorded tables of [`crate::exchange::recorded`]).

use std::path::Path;

use polars::prelude::*;

use crate::error::OutputError;

use super::format_err;

/// A block of rows read from `path`.
#[derive(Clone, Copy)]
pub(crate) struct FrameColumns<'a> {
    /// The file (or `<estimates N>` for a table in memory), for messages.
    pub path: &'a Path,
    /// The rows.
    pub df: &'a DataFrame,
}

impl FrameColumns<'_> {
    /// A column polars cannot read as asked, named with its file.
    pub fn column_err(&self, name: &str, e: PolarsError) -> OutputError {
        format_err(self.path, format!("column `{name}`: {e}"))
    }

    /// A numeric column as float64 (float32 widened exactly; integers converted).
    pub fn floats(&self, name: &str) -> Result<Float64Chunked, OutputError> {
        let c = (self.df.column(name))
            .and_then(|c| c.cast(&DataType::Float64))
            .map_err(|e| self.column_err(name, e))?;
        Ok(c.f64().map_err(|e| self.column_err(name, e))?.clone())
    }

    /// A float column when the block has it.
    pub fn optional_floats(&self, name: &str) -> Result<Option<Float64Chunked>, OutputError> {
        if self.df.schema().contains(name) {
            self.floats(name).map(Some)
        } else {
            Ok(None)
        }
    }

    /// An integer column as int64; a column of another type (a float `run`, say) is refused
    /// rather than rounded.
    pub fn ints(&self, name: &str) -> Result<Int64Chunked, OutputError> {
        let c = (self.df.column(name)).map_err(|e| self.column_err(name, e))?;
        if !c.dtype().is_integer() {
            return Err(format_err(
                self.path,
                format!("column `{name}` must be an integer, not {}", c.dtype()),
            ));
        }
        let c = c
            .cast(&DataType::Int64)
            .map_err(|e| self.column_err(name, e))?;
        Ok(c.i64().map_err(|e| self.column_err(name, e))?.clone())
    }

    /// A string column as it is (no cast).
    pub fn strs(&self, name: &str) -> Result<StringChunked, OutputError> {
        let c = (self.df.column(name)).map_err(|e| self.column_err(name, e))?;
        Ok(c.str().map_err(|e| self.column_err(name, e))?.clone())
    }

    /// A key column of strings, a categorical one read as its strings.
    pub fn strings(&self, name: &str) -> Result<StringChunked, OutputError> {
        let c = (self.df.column(name))
            .and_then(|c| c.cast(&DataType::String))
            .map_err(|e| self.column_err(name, e))?;
        Ok(c.str().map_err(|e| self.column_err(name, e))?.clone())
    }
}
