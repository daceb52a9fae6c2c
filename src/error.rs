//! Library errors (`thiserror`). The CLI prints the whole cause chain and maps each kind to a
//! documented exit code.

use std::fmt;
use std::path::PathBuf;

/// One problem in a spec, with the file and the key path (`filters[1].q_std`).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct SpecError {
    /// The spec file.
    pub file: PathBuf,
    /// Dotted key path; empty for file-level problems (unreadable, bad TOML syntax).
    pub key_path: String,
    /// What is wrong.
    pub message: String,
}

impl fmt::Display for SpecError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.key_path.is_empty() {
            write!(f, "{}: {}", self.file.display(), self.message)
        } else {
            write!(
                f,
                "{}: {}: {}",
                self.file.display(),
                self.key_path,
                self.message
            )
        }
    }
}

/// Every problem found in a spec (validation reports them all at once).
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub struct SpecErrors(pub Vec<SpecError>);

impl fmt::Display for SpecErrors {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let n = self.0.len();
        write!(
            f,
            "invalid spec ({n} problem{})",
            if n == 1 { "" } else { "s" }
        )?;
        for e in &self.0 {
            write!(f, "\n  {e}")?;
        }
        Ok(())
    }
}

/// Writing or reading a result table failed.
#[derive(Debug, thiserror::Error)]
pub enum OutputError {
    /// File-system trouble at a path.
    #[error("{action} {path}")]
    Io {
        /// What was attempted.
        action: &'static str,
        /// Where.
        path: PathBuf,
        /// The cause.
        #[source]
        source: std::io::Error,
    },
    /// Polars failed to build, write or read a table.
    #[error("{action} {path}")]
    Polars {
        /// What was attempted.
        action: &'static str,
        /// Where.
        path: PathBuf,
        /// The cause.
        #[source]
        source: polars::prelude::PolarsError,
    },
    /// A table exists but is not what kfmc wrote.
    #[error("{path}: {message}")]
    Format {
        /// The table.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// Another kfmc process is writing into the folder.
    #[error(
        "{path} is being written by another kfmc ({holder}); wait for it or choose another --out"
    )]
    Locked {
        /// The folder.
        path: PathBuf,
        /// The process holding the lock: its pid, host and start time as it recorded them.
        holder: String,
    },
    /// The folder holds another command's result, which this command would replace.
    #[error(
        "{path} holds {holds} (experiment `{experiment}`: {tables}); `kfmc {command}` replaces only a folder of its own kind: choose another --out, or pass --force to replace it"
    )]
    OtherKind {
        /// The folder.
        path: PathBuf,
        /// What it holds.
        holds: &'static str,
        /// Its experiment.
        experiment: String,
        /// Its tables, listed.
        tables: String,
        /// The command that was refused.
        command: &'static str,
    },
    /// The folder holds files that no kfmc study wrote.
    #[error(
        "{path} is not empty and is not a kfmc result folder ({count} other entries, e.g. `{example}`); choose another --out, or pass --force to write into it"
    )]
    Foreign {
        /// The folder.
        path: PathBuf,
        /// One of the foreign entries.
        example: String,
        /// How many.
        count: usize,
    },
    /// An entry of a result folder is not what kfmc keeps there: a symbolic link, a FIFO, a
    /// file where kfmc keeps a folder, ….
    #[error(
        "{path} is {what}: kfmc uses only regular files and folders inside a result folder and opens nothing there through a symbolic link; remove it, or choose another --out"
    )]
    NotPlain {
        /// The entry.
        path: PathBuf,
        /// What it is ("a symbolic link", "a FIFO (named pipe)", …).
        what: &'static str,
    },
    /// A writer would replace or remove a file that kfmc did not write (one its manifest does
    /// not list, or one changed since).
    #[error(
        "{path} {why}; kfmc replaces or removes only what a result folder's manifest lists, even with --force: move it out of the folder, or choose another --out"
    )]
    NotOurs {
        /// The file.
        path: PathBuf,
        /// Why it is not kfmc's.
        why: String,
    },
    /// `manifest.toml` is not one kfmc wrote (a project's own, say).
    #[error(
        "{path} is not a kfmc manifest ({why}); kfmc does not replace it, even with --force: choose another --out"
    )]
    ForeignManifest {
        /// The manifest.
        path: PathBuf,
        /// Why it is not kfmc's.
        why: String,
    },
    /// `manifest.toml` looks like kfmc's but cannot be trusted to say what kfmc wrote.
    #[error(
        "{path} is a damaged kfmc manifest ({why}); choose another --out, or pass --force to replace the study it describes (kfmc then removes only the tables it lists that still match it)"
    )]
    DamagedManifest {
        /// The manifest.
        path: PathBuf,
        /// What is wrong.
        why: String,
    },
    /// A file the command reads lies inside the folder it writes.
    #[error(
        "{input} is read by this command and lies inside its output folder {folder}; kfmc does not write into a folder that holds its own input: move the file out of the folder, or choose another --out"
    )]
    InputInOutput {
        /// The input.
        input: PathBuf,
        /// The output folder.
        folder: PathBuf,
    },
    /// A folder a reader was given is not a complete kfmc study.
    #[error("{path} is not a complete kfmc result folder: {why}")]
    NotAStudy {
        /// The folder.
        path: PathBuf,
        /// Why not.
        why: String,
    },
    /// A table does not match the manifest that should describe it.
    #[error("{path} {why}")]
    Mismatch {
        /// The table.
        path: PathBuf,
        /// What does not match.
        why: String,
    },
    /// The run was interrupted (SIGINT or SIGTERM); nothing was committed.
    #[error("interrupted; no table of this run was committed and the partial files were removed")]
    Interrupted,
    /// The run was interrupted after a checkpoint: nothing was committed, but the complete
    /// cells are kept for `kfmc run SPEC --resume`.
    #[error(
        "interrupted; no table of this run was committed, and the checkpoint in {dir} keeps {cells_done} of {cells} cells: continue with `kfmc run SPEC --resume`"
    )]
    InterruptedCheckpointed {
        /// The checkpoint's folder.
        dir: PathBuf,
        /// Cells the checkpoint holds.
        cells_done: u64,
        /// Cells of the run.
        cells: u64,
    },
}

/// Drawing figures or writing the report failed.
#[derive(Debug, thiserror::Error)]
pub enum PlotError {
    /// `--only` asked for figure kinds the folder's tables cannot give.
    #[error(
        "{path} has no data for the figures {lacking} asked for with --only (its tables give: {available})"
    )]
    NoFigures {
        /// The result folder.
        path: PathBuf,
        /// The kinds asked for and not drawable, comma-separated.
        lacking: String,
        /// The kinds the tables do give, comma-separated (or "none").
        available: String,
    },
    /// A table a figure needs is not in the result folder.
    #[error("{path} is missing ({why})")]
    MissingTable {
        /// The expected table.
        path: PathBuf,
        /// What needs it.
        why: String,
    },
    /// A table has not the columns kfmc writes.
    #[error("{path}: {message}")]
    Columns {
        /// The table.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// Reading a table (or the manifest) failed.
    #[error(transparent)]
    Output(#[from] OutputError),
    /// The plotting backend failed.
    #[error("cannot draw {path}: {message}")]
    Draw {
        /// The figure file.
        path: PathBuf,
        /// The backend's message.
        message: String,
    },
    /// File-system trouble at a path.
    #[error("{action} {path}")]
    Io {
        /// What was attempted.
        action: &'static str,
        /// Where.
        path: PathBuf,
        /// The cause.
        #[source]
        source: std::io::Error,
    },
}

/// Any kfmc error.
#[derive(Debug, thiserror::Error)]
pub enum KfmcError {
    /// The spec is invalid.
    #[error(transparent)]
    Spec(#[from] SpecErrors),
    /// Results could not be written or read.
    #[error(transparent)]
    Output(#[from] OutputError),
    /// Figures or the report could not be made.
    #[error(transparent)]
    Plot(#[from] PlotError),
    /// The thread pool could not be built.
    #[error("cannot build a thread pool of {threads} threads")]
    ThreadPool {
        /// Requested threads.
        threads: usize,
        /// The cause.
        #[source]
        source: rayon::ThreadPoolBuildError,
    },
}
