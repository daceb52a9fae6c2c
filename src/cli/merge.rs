//! `kfmc merge`: combine the parts of a sharded study (`run --shard i/n`) into the tables one
//! process would have written, byte for byte.

use super::*;

/// The arguments of `kfmc merge`.
#[derive(Debug, clap::Args)]
pub struct Merge {
    /// The study's output folder (holding `parts/`).
    pub dir: PathBuf,
    /// Write into the folder although it holds files no kfmc study wrote, or another
    /// kind of result than the parts'.
    #[arg(long)]
    pub force: bool,
}

impl Merge {
    /// Runs the command.
    pub(super) fn execute(self, registry: &Registry) -> anyhow::Result<()> {
        let Self { dir, force } = self;
        let report = crate::merge::merge(&dir, force, registry)
            .map_err(anyhow::Error::from)
            .map_err(|e| e.context(format!("merging {}", dir.display())))?;
        outln!(
            "{} parts merged in {:.1} s → {}",
            report.parts,
            report.wall_s,
            dir.display()
        );
        print_tables(&report.tables);
        Ok(())
    }
}
