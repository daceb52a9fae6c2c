//! The column types an estimates file may use, checked before any value is read.

use std::path::Path;

use polars::prelude::*;

use crate::error::OutputError;

use super::{FAILED_COLUMN, format_err};

/// What a column holds, as far as the estimates format is concerned.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum ColumnClass {
    /// float64, float32.
    Float,
    /// Any integer width, signed or not.
    Integer,
    /// Strings.
    Text,
    /// No values at all (a column of nulls).
    Null,
    /// Booleans (the `failed` column).
    Bool,
    /// Anything else: decimal, map, struct, list, dates, binary, dictionary, …
    Other,
}

/// An Arrow type's class and its name for messages.
fn arrow_class(dtype: &ArrowDataType) -> (ColumnClass, String) {
    use ArrowDataType as A;
    let class = match dtype {
        A::Float32 | A::Float64 => ColumnClass::Float,
        A::Int8 | A::Int16 | A::Int32 | A::Int64 | A::UInt8 | A::UInt16 | A::UInt32 | A::UInt64 => {
            ColumnClass::Integer
        }
        A::Utf8 | A::LargeUtf8 | A::Utf8View => ColumnClass::Text,
        A::Null => ColumnClass::Null,
        A::Boolean => ColumnClass::Bool,
        _ => ColumnClass::Other,
    };
    let name = match dtype {
        A::Boolean => "bool".to_string(),
        A::Int8 => "int8".into(),
        A::Int16 => "int16".into(),
        A::Int32 => "int32".into(),
        A::Int64 => "int64".into(),
        A::UInt8 => "uint8".into(),
        A::UInt16 => "uint16".into(),
        A::UInt32 => "uint32".into(),
        A::UInt64 => "uint64".into(),
        A::Utf8 | A::LargeUtf8 | A::Utf8View => "string".into(),
        A::Float16 => "float16".into(),
        A::Float32 => "float32".into(),
        A::Float64 => "float64".into(),
        A::Decimal(p, s) | A::Decimal32(p, s) | A::Decimal64(p, s) | A::Decimal256(p, s) => {
            format!("decimal({p}, {s})")
        }
        A::Map(..) => "map".into(),
        A::Struct(_) => "struct".into(),
        A::List(_) | A::LargeList(_) | A::FixedSizeList(..) => "list".into(),
        A::Dictionary(..) => "dictionary (categorical)".into(),
        A::Binary | A::LargeBinary | A::BinaryView | A::FixedSizeBinary(_) => "binary".into(),
        A::Extension(e) => format!("extension `{}`", e.name),
        other => format!("{other:?}").to_lowercase(),
    };
    (class, name)
}

/// A polars type's class and its name for messages.
fn polars_class(dtype: &DataType) -> (ColumnClass, String) {
    let class = if dtype.is_float() {
        ColumnClass::Float
    } else if dtype.is_integer() {
        ColumnClass::Integer
    } else if dtype.is_string() {
        ColumnClass::Text
    } else if dtype.is_null() {
        ColumnClass::Null
    } else if dtype.is_bool() {
        ColumnClass::Bool
    } else {
        ColumnClass::Other
    };
    (class, dtype.to_string())
}

/// Refuses a column whose type the estimates format does not take, naming the file, the
/// column and its type. The keys keep their documented types (`scenario` and `filter`
/// strings, `run` and `step` integers, `noise_scale`, `q_scale` and `r_scale` numbers,
/// `failed` bool); a value column is float64 or float32 (or all null): a bool, integer or string there is a
/// writer's mistake that a conversion would hide (`True` scored as 1.0), and a decimal, map
/// or other nested column is not a number at all.
fn check_column_class(
    path: &Path,
    name: &str,
    (class, type_name): (ColumnClass, String),
) -> Result<(), OutputError> {
    use ColumnClass::*;
    let (ok, wanted) = match name {
        "scenario" | "filter" => (matches!(class, Text | Null), "a string column"),
        "run" | "step" => (matches!(class, Integer | Null), "an integer column"),
        "noise_scale" | "q_scale" | "r_scale" => {
            (matches!(class, Float | Integer | Null), "a float64 column")
        }
        FAILED_COLUMN => (matches!(class, Bool | Null), "a bool column"),
        _ => (
            matches!(class, Float | Null),
            "a value column: float64 or float32",
        ),
    };
    if ok {
        return Ok(());
    }
    Err(format_err(
        path,
        format!(
            "column `{name}` holds {type_name} values; it must be {wanted} (kfmc converts no other type; `kfmc schema estimates SPEC` lists the columns and their types)"
        ),
    ))
}

/// Refuses an Arrow column (of a Parquet file's schema, or of a table handed over through
/// the Arrow C stream interface) whose type the estimates format does not take, before any
/// of its values is read, naming `path`, the column and its type: the keys keep their
/// documented types (`scenario` and `filter` strings, `run` and `step` integers,
/// `noise_scale`, `q_scale` and `r_scale` numbers), and a value column is float64 or float32
/// (or all null).
pub fn check_arrow_column(
    path: &Path,
    name: &str,
    dtype: &ArrowDataType,
) -> Result<(), OutputError> {
    check_column_class(path, name, arrow_class(dtype))
}

/// [`check_arrow_column`] for every column of a table already in memory.
pub fn check_frame_columns(path: &Path, df: &DataFrame) -> Result<(), OutputError> {
    for c in df.columns() {
        check_column_class(path, c.name(), polars_class(c.dtype()))?;
    }
    Ok(())
}
