//! `kfmc plot`: draw every figure the tables of a result folder support (read from the Parquet
//! files).

use super::*;

/// The arguments of `kfmc plot`.
#[derive(Debug, clap::Args)]
pub struct Plot {
    /// A folder written by `kfmc run`.
    pub dir: PathBuf,
    /// Figure folder (default: DIR/figures).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Image format.
    #[arg(long, value_enum, default_value_t = Format::Png)]
    pub format: Format,
    /// Only these figure kinds (repeatable); default: all the data supports.
    #[arg(long, value_enum, num_args = 1..)]
    pub only: Vec<FigureKind>,
}

impl Plot {
    /// Runs the command.
    pub(super) fn execute(self) -> anyhow::Result<()> {
        let Self {
            dir,
            out,
            format,
            only,
        } = self;
        let files = plot_dir(&dir, &PlotOptions { out, format, only })?;
        for f in &files {
            outln!("{}", f.display());
        }
        Ok(())
    }
}
