//! The output role: one schema definition for every table ([`schema`]), an atomic streaming
//! Parquet writer ([`table`]) and the manifest ([`manifest`]).
//!
//! Tables are written to a hidden temporary file in the output folder and renamed into place
//! only when complete, so a crash or Ctrl-C never leaves a half-written table under a real
//! name; [`folder`] locks a study's folder and commits its tables with the manifest last.
//! Large tables are streamed in row groups, so memory does not grow with the run count.
//! [`checkpoint`] journals their rows so an interrupted study can be resumed; [`atomic`] is
//! the durable write (temporary file, fsync, rename) under all of them.

pub mod atomic;
pub mod checkpoint;
pub mod folder;
pub mod manifest;
pub mod schema;
pub mod table;

pub use table::{FLUSH_ROWS, TableWriter, Value};
