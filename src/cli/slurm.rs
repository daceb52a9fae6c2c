//! `kfmc slurm`: write Slurm job scripts for a sharded study: an array job (one part per task),
//! a merge job to run after it (`--dependency=afterok`), and `submit.sh` that submits both.

use super::*;

/// The arguments of `kfmc slurm`.
#[derive(Debug, clap::Args)]
pub struct Slurm {
    /// The experiment spec (TOML).
    pub spec: PathBuf,
    /// Number of array tasks (parts), 1 to 100,000.
    #[arg(long, value_parser = shard_count)]
    pub shards: usize,
    /// Output folder (overrides the spec's `output`); the scripts go to `<out>/slurm/`.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Slurm partition.
    #[arg(long)]
    pub partition: Option<String>,
    /// Time limit per task, in Slurm's format (e.g. 01:00:00).
    #[arg(long)]
    pub time: Option<String>,
    /// CPUs per task (kfmc uses them all), at least 1.
    #[arg(long, default_value_t = 1, value_parser = at_least_one)]
    pub cpus: usize,
    /// Runs per cell (overrides `runs`) in every task.
    #[arg(long)]
    pub runs: Option<usize>,
    /// Master seed (overrides `master_seed`) in every task.
    #[arg(long)]
    pub seed: Option<u64>,
}

impl Slurm {
    /// Runs the command.
    pub(super) fn execute(self, registry: &Registry) -> anyhow::Result<()> {
        let Self {
            spec,
            shards,
            out,
            partition,
            time,
            cpus,
            runs,
            seed,
        } = self;
        let mut plan = experiment::load_with(&spec, registry).map_err(KfmcError::from)?;
        plan.apply(&Overrides {
            runs,
            master_seed: seed,
            output: out,
            trace_runs: None,
        })
        .map_err(KfmcError::from)?;
        crate::study::check_limits(&plan, false).map_err(KfmcError::from)?;
        // An array task runs `kfmc run --shards`, which cannot compute a filter kfmc
        // does not run: every task would fail on the cluster.
        if let Some(f) = plan.filters.iter().find(|f| f.external) {
            return Err(KfmcError::Spec(crate::error::SpecErrors(vec![
                    crate::error::SpecError {
                        file: spec.clone(),
                        key_path: "filters".into(),
                        message: format!(
                            "filter `{}` is external (kind = \"external\"): the array tasks run `kfmc run`, which cannot compute it; shard `kfmc simulate --shard i/n` instead and score the merged simulation",
                            f.label
                        ),
                    },
                ]))
                .into());
        }
        let abs = |p: &std::path::Path| std::path::absolute(p).unwrap_or_else(|_| p.to_path_buf());
        let output = abs(&plan.output);
        let dir = output.join("slurm");
        let exe = std::env::current_exe().map_err(anyhow::Error::from)?;
        let files = crate::merge::slurm_scripts(
            &exe,
            &abs(&spec),
            &output,
            &plan.name,
            &crate::merge::SlurmOptions {
                shards,
                partition,
                time,
                cpus,
                runs,
                seed,
            },
        )
        .map_err(|(flag, message)| UsageError {
            flag: flag.into(),
            message,
        })?;
        std::fs::create_dir_all(&dir)
            .map_err(|e| anyhow::Error::from(e).context(format!("creating {}", dir.display())))?;
        for (name, text) in files {
            let path = dir.join(&name);
            crate::output::folder::write_atomic(&path, text.as_bytes()).map_err(|e| {
                anyhow::Error::from(e).context(format!("writing {}", path.display()))
            })?;
            if name.ends_with(".sh") {
                use std::os::unix::fs::PermissionsExt;
                let _ = std::fs::set_permissions(&path, std::fs::Permissions::from_mode(0o755));
            }
            outln!("{}", path.display());
        }
        Ok(())
    }
}
