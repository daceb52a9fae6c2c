//! Sharded studies: `kfmc run --shard i/n` runs one of n disjoint, deterministic parts of a
//! plan into `<out>/parts/part-i-of-n/`, and [`merge`] combines the parts into the tables one
//! process would have written, byte for byte.
//!
//! A part is a contiguous range of the plan's cells ((scenario, noise scale) pairs in the
//! order one process folds them), and every cell is folded whole inside one part, so a
//! part's runs, steps, summary, consistency and traces rows are exactly the single process's
//! rows for those cells, in the same order; merging concatenates them through the same
//! writer (same row groups, same bytes). Divergence points look across all noise scales of a
//! scenario, so the merge computes them from the merged runs and summary rows, with the same
//! order-independent trackers a single process uses. Memory is one part's table at a time.

use std::path::{Path, PathBuf};
use std::time::Instant;

use crate::error::{KfmcError, OutputError};
use crate::experiment::{self, Overrides};
use crate::output::folder::{FolderLock, StudyFolder, verify};
use crate::output::manifest::Manifest;
use crate::output::schema;
use crate::output::table::{
    FinishedTable, TableWriter, columns_of, for_each_row, for_each_row_group,
};
use crate::study::{DivergenceFeed, Shard, divergence_tables};
use crate::system::Registry;

/// The shard a run executes: `--shard i/n`, else a scheduler's array index from the
/// environment (Slurm's `SLURM_ARRAY_TASK_ID` with `SLURM_ARRAY_TASK_COUNT`, `_MIN` and
/// `_STEP`; a Kubernetes Indexed Job's `JOB_COMPLETION_INDEX` with `--shards n`).
pub fn shard_from(
    flag: Option<&str>,
    shards: Option<usize>,
    env: &dyn Fn(&str) -> Option<String>,
) -> Result<Option<Shard>, String> {
    let num = |what: &str, v: &str| {
        v.trim()
            .parse::<usize>()
            .map_err(|_| format!("{what} `{v}` is not a non-negative integer"))
    };
    let check = |index: usize, count: usize| {
        if count == 0 || index >= count {
            Err(format!("part {index} of {count}: need 0 ≤ i < n and n ≥ 1"))
        } else if count > crate::study::MAX_SHARDS {
            Err(format!(
                "{count} parts: at most {}",
                crate::study::MAX_SHARDS
            ))
        } else {
            Ok(Some(Shard { index, count }))
        }
    };
    if let Some(f) = flag {
        let (i, n) = f
            .split_once('/')
            .ok_or_else(|| format!("`{f}` is not of the form i/n (e.g. 0/4)"))?;
        return check(num("the part index", i)?, num("the part count", n)?);
    }
    if let Some(id) = env("SLURM_ARRAY_TASK_ID") {
        let id = num("SLURM_ARRAY_TASK_ID", &id)?;
        let min = env("SLURM_ARRAY_TASK_MIN").map_or(Ok(0), |v| num("SLURM_ARRAY_TASK_MIN", &v))?;
        let step =
            env("SLURM_ARRAY_TASK_STEP").map_or(Ok(1), |v| num("SLURM_ARRAY_TASK_STEP", &v))?;
        let count =
            match (shards, env("SLURM_ARRAY_TASK_COUNT")) {
                (Some(n), _) => n,
                (None, Some(c)) => num("SLURM_ARRAY_TASK_COUNT", &c)?,
                (None, None) => return Err(
                    "SLURM_ARRAY_TASK_ID is set but not SLURM_ARRAY_TASK_COUNT; pass --shards N"
                        .into(),
                ),
            };
        if step == 0 || id < min || (id - min) % step != 0 {
            return Err(format!(
                "array task {id} is not min + k·step ({min} + k·{step})"
            ));
        }
        return check((id - min) / step, count);
    }
    if let Some(idx) = env("JOB_COMPLETION_INDEX") {
        let n =
            shards.ok_or("JOB_COMPLETION_INDEX is set; pass --shards N (the Job's completions)")?;
        return check(num("JOB_COMPLETION_INDEX", &idx)?, n);
    }
    if shards.is_some() {
        return Err(
            "--shards needs an index: --shard i/n, or a scheduler's array index in the environment"
                .into(),
        );
    }
    Ok(None)
}

/// What a merge wrote.
#[derive(Clone, Debug, PartialEq)]
pub struct MergeReport {
    /// Parts combined.
    pub parts: usize,
    /// Tables and their row counts.
    pub tables: Vec<(String, u64)>,
    /// Wall-clock seconds.
    pub wall_s: f64,
}

struct Part {
    dir: PathBuf,
    manifest: Manifest,
    // A merge holds every part while it reads it, so that no part is rewritten under it.
    _lock: Option<FolderLock>,
}

/// The part folders under `dir/parts`, each verified, in part order; every problem is named.
/// A part folder that is not a complete part, and why.
type Problem = (PathBuf, String);

fn parts(dir: &Path, lock: bool) -> Result<(Vec<Part>, Vec<Problem>), OutputError> {
    let root = dir.join("parts");
    // A part is read where it lies, inside the merged folder: never through a link.
    crate::output::folder::refuse_link(&root)?;
    let entries = std::fs::read_dir(&root).map_err(|source| OutputError::Io {
        action: "cannot list the parts in",
        path: root.clone(),
        source,
    })?;
    let mut found = Vec::new();
    let mut problems = Vec::new();
    let mut names: Vec<PathBuf> = entries.filter_map(|e| e.ok()).map(|e| e.path()).collect();
    names.sort();
    for path in names {
        match std::fs::symlink_metadata(&path) {
            Ok(m) if m.file_type().is_symlink() && path.is_dir() => {
                let why = format!(
                    "{}: is a symbolic link; kfmc reads a part only where it lies, in the study's parts folder",
                    path.display()
                );
                problems.push((path, why));
                continue;
            }
            Ok(m) if m.file_type().is_dir() => {}
            _ => continue,
        }
        let held = if lock {
            match FolderLock::acquire(&path) {
                Ok(l) => Some(l),
                Err(e) => {
                    let why = format!("{}: {e}", path.display());
                    problems.push((path, why));
                    continue;
                }
            }
        } else {
            None
        };
        match verify(&path) {
            Ok(manifest) if manifest.shard.is_some() => found.push(Part {
                dir: path,
                manifest,
                _lock: held,
            }),
            Ok(_) => problems.push((
                path.clone(),
                format!("{}: not a part (no shard in its manifest)", path.display()),
            )),
            Err(e) => {
                let why = format!("{}: {e}", path.display());
                problems.push((path, why));
            }
        }
    }
    Ok((found, problems))
}

/// A human-readable list of a sharded study's parts: complete, missing or broken.
pub fn status(dir: &Path) -> Result<String, OutputError> {
    let progress = |d: &Path| -> Result<Option<String>, OutputError> {
        Ok(match crate::output::checkpoint::Index::read(d) {
            Ok(index) => index.map(|i| {
                format!(
                    "{} of {} cells checkpointed (continue with `kfmc run SPEC --resume`)",
                    i.cells_done,
                    i.end_cell.saturating_sub(i.first_cell)
                )
            }),
            // Status reports what it finds; a checkpoint that cannot be read is one thing.
            Err(e) => Some(match std::error::Error::source(&e) {
                Some(cause) => format!("a checkpoint that cannot be read: {e}: {cause}"),
                None => format!("a checkpoint that cannot be read: {e}"),
            }),
        })
    };
    if !dir.join("parts").is_dir()
        && let Some(p) = progress(dir)?
    {
        return Ok(format!("{}: an interrupted run, {p}\n", dir.display()));
    }
    let (found, problems) = parts(dir, false)?;
    let mut s = String::new();
    // The study is the largest group of parts that `merge` would combine (same kind, spec,
    // seed, runs and part count); parts of any other split or study are listed apart, never
    // counted towards it.
    let key = |m: &Manifest| {
        (
            m.kind(),
            m.spec_hash.clone(),
            m.master_seed,
            m.runs_per_cell,
            m.shard.as_ref().map_or(0, |s| s.count),
        )
    };
    let mut groups: Vec<(_, usize)> = Vec::new();
    for p in &found {
        let k = key(&p.manifest);
        match groups.iter_mut().find(|(g, _)| *g == k) {
            Some((_, n)) => *n += 1,
            None => groups.push((k, 1)),
        }
    }
    let study = groups
        .iter()
        .rev()
        .max_by_key(|(_, n)| *n)
        .map(|(k, _)| k.clone());
    let (ours, others): (Vec<&Part>, Vec<&Part>) = found
        .iter()
        .partition(|p| study.as_ref() == Some(&key(&p.manifest)));
    let count = study.as_ref().map(|k| k.4);
    let done: Vec<u64> = ours
        .iter()
        .filter_map(|p| p.manifest.shard.as_ref().map(|s| s.index))
        .collect();
    match count {
        Some(n) => {
            s.push_str(&format!(
                "{}: {} of {n} parts complete ({} parts)\n",
                dir.display(),
                done.len(),
                study.as_ref().map_or("run", |k| k.0.command())
            ));
            for i in 0..n {
                let state = if done.contains(&i) {
                    "complete".to_string()
                } else {
                    let folder = crate::study::Shard {
                        index: i as usize,
                        count: n as usize,
                    }
                    .folder(dir);
                    progress(&folder)?
                        .map_or("missing".into(), |p| format!("running or interrupted, {p}"))
                };
                s.push_str(&format!("  part {i:>5} of {n}: {state}\n"));
            }
        }
        None => s.push_str(&format!("{}: no complete part\n", dir.display())),
    }
    for p in &others {
        let m = &p.manifest;
        let (i, n) = m.shard.as_ref().map_or((0, 0), |s| (s.index, s.count));
        s.push_str(&format!(
            "  of another study (`kfmc merge` refuses it; remove it): {}: a `kfmc {}` part {i} of {n}, spec {}, seed {}, {} runs per cell\n",
            p.dir.display(),
            m.kind().command(),
            m.spec_hash,
            m.master_seed,
            m.runs_per_cell
        ));
    }
    for (path, why) in &problems {
        // A part being computed, or killed, says how far its checkpoint got.
        match progress(path)? {
            Some(p) => s.push_str(&format!(
                "  running or interrupted: {}: {p}\n",
                path.display()
            )),
            None => s.push_str(&format!("  incomplete: {why}\n")),
        }
    }
    if dir.join("manifest.toml").exists() && verify(dir).is_ok() {
        s.push_str("  merged: yes (manifest.toml verified)\n");
    }
    Ok(s)
}

/// A SIGINT or SIGTERM stops a merge like a run: nothing committed, the partial tables
/// removed as their writers drop, the parts untouched.
fn stop_if_interrupted() -> Result<(), OutputError> {
    if crate::runner::interrupted() {
        Err(OutputError::Interrupted)
    } else {
        Ok(())
    }
}

fn mismatch(dir: &Path, why: String) -> KfmcError {
    KfmcError::Output(OutputError::Mismatch {
        path: dir.to_path_buf(),
        why,
    })
}

/// Merges the parts in `dir/parts` into `dir`'s tables and manifest. Refuses parts of another
/// spec, seed or run count, a different n, or a missing part, naming it.
pub fn merge(dir: &Path, force: bool, registry: &Registry) -> Result<MergeReport, KfmcError> {
    let started = Instant::now();
    if !dir.is_dir() {
        return Err(OutputError::NotAStudy {
            path: dir.to_path_buf(),
            why: "no such folder".into(),
        }
        .into());
    }
    // Held before anything in the folder is read: a second merge (or any writer) is refused
    // instead of reading parts that are being replaced or writing beside this one.
    let folder = StudyFolder::lock(dir)?;
    let (found, problems) = parts(dir, true)?;
    if let Some((_, p)) = problems.first() {
        return Err(mismatch(
            dir,
            format!("has a part that is not complete: {p}"),
        ));
    }
    let ordered = parts_in_order(dir, &found)?;
    let m0 = &ordered[0].manifest;
    let next_cell = ordered
        .last()
        .and_then(|p| p.manifest.shard.as_ref())
        .map_or(0, |s| s.end_cell);
    let mut plan = experiment::parse_with(&m0.spec, Path::new(&m0.spec_path), registry)?;
    plan.apply(&Overrides {
        runs: Some(m0.runs_per_cell as usize),
        master_seed: Some(m0.master_seed),
        output: Some(dir.to_path_buf()),
        trace_runs: Some(0),
    })?;
    if next_cell as usize != plan.scenarios.len() * plan.noise_scales.len() {
        return Err(mismatch(
            dir,
            format!(
                "parts cover {next_cell} cells of {}",
                plan.scenarios.len() * plan.noise_scales.len()
            ),
        ));
    }
    // A sharded `kfmc simulate`: its tables concatenate, and there is nothing to fold.
    let simulation = m0.exchange.is_some();
    if simulation {
        plan.filters.clear();
        plan.rmse_thresholds = None;
    }
    folder.prepare(m0.kind(), force)?;
    let mut finished = concatenate_tables(dir, &ordered, &plan)?;
    finished.extend(divergence_from_parts(dir, &ordered, &plan)?);
    let manifest = merged_manifest(&ordered, &plan);
    // The last moment a stop can be honoured without a commit.
    stop_if_interrupted()?;
    let tables = folder.commit(finished, manifest)?;
    Ok(MergeReport {
        parts: ordered.len(),
        tables,
        wall_s: started.elapsed().as_secs_f64(),
    })
}

/// The parts of one study, by index, covering consecutive cells from the first: refuses a
/// part of another kind, spec, seed, run count or part count, a missing part or a gap.
fn parts_in_order<'p>(dir: &Path, found: &'p [Part]) -> Result<Vec<&'p Part>, KfmcError> {
    let Some(first) = found.first() else {
        return Err(mismatch(
            dir,
            "has no parts (run `kfmc run SPEC --shard i/n` first)".into(),
        ));
    };
    let m0 = &first.manifest;
    let n = m0.shard.as_ref().map_or(0, |s| s.count);
    for p in found {
        let m = &p.manifest;
        // As a resume refuses another version's checkpoint: rows of another kfmc may differ.
        let ours = env!("CARGO_PKG_VERSION");
        if m.kfmc_version != ours {
            return Err(mismatch(
                &p.dir,
                format!(
                    "is a part written by kfmc {} (this is {ours}): another version may compute other rows; run the part again with this kfmc",
                    m.kfmc_version
                ),
            ));
        }
        let s = m.shard.as_ref().expect("parts() keeps shards only");
        // The kind first: a simulation's part among a run's has another spec too, and the
        // kind is what the user must be told.
        for (what, a, b) in [
            (
                "kind",
                &format!("`kfmc {}`", m.kind().command()),
                &format!("`kfmc {}`", m0.kind().command()),
            ),
            ("spec (hash)", &m.spec_hash, &m0.spec_hash),
            (
                "master seed",
                &m.master_seed.to_string(),
                &m0.master_seed.to_string(),
            ),
            (
                "runs per cell",
                &m.runs_per_cell.to_string(),
                &m0.runs_per_cell.to_string(),
            ),
            ("part count", &s.count.to_string(), &n.to_string()),
        ] {
            if a != b {
                return Err(mismatch(
                    &p.dir,
                    format!("is a part of another study: its {what} is {a}, the first part's {b}"),
                ));
            }
        }
    }
    let mut by_index: Vec<Option<&Part>> = vec![None; n as usize];
    for p in found {
        let i = p.manifest.shard.as_ref().map_or(0, |s| s.index) as usize;
        by_index[i] = Some(p);
    }
    if let Some(i) = by_index.iter().position(Option::is_none) {
        return Err(mismatch(
            dir,
            format!("is missing part {i} of {n} (`kfmc status` lists the parts)"),
        ));
    }
    let ordered: Vec<&Part> = by_index.into_iter().flatten().collect();
    let mut next_cell = 0;
    for p in &ordered {
        let s = p.manifest.shard.as_ref().expect("a part");
        if s.first_cell != next_cell {
            return Err(mismatch(
                &p.dir,
                format!("starts at cell {}, expected {next_cell}", s.first_cell),
            ));
        }
        next_cell = s.end_cell;
    }

    Ok(ordered)
}

/// Every table of the parts, concatenated in part order row group by row group (memory does
/// not grow with the parts' sizes).
fn concatenate_tables(
    dir: &Path,
    ordered: &[&Part],
    plan: &experiment::Plan,
) -> Result<Vec<FinishedTable>, KfmcError> {
    let mut finished = Vec::new();
    for name in schema::TABLES {
        let files: Vec<PathBuf> = ordered
            .iter()
            .map(|p| p.dir.join(format!("{name}.parquet")))
            .filter(|f| f.exists())
            .collect();
        if files.is_empty() {
            continue;
        }
        let mut writer: Option<TableWriter> = None;
        for f in &files {
            // Row group by row group: memory does not grow with the parts' sizes.
            for_each_row_group(f, |df| {
                stop_if_interrupted()?;
                let w = match writer.as_mut() {
                    Some(w) => w,
                    None => writer.insert(TableWriter::create_with_metadata(
                        dir,
                        name,
                        columns_of(&df, f)?,
                        &plan.table_metadata(name),
                    )?),
                };
                w.append_frame(&df, f)
            })?;
        }
        finished.push(writer.expect("at least one part").finish()?);
    }
    Ok(finished)
}

/// The divergence tables, which look across every noise scale of a scenario and so are
/// rebuilt from the parts' runs and summary rows (none for a study without thresholds).
fn divergence_from_parts(
    dir: &Path,
    ordered: &[&Part],
    plan: &experiment::Plan,
) -> Result<Vec<FinishedTable>, KfmcError> {
    let mut finished = Vec::new();
    if let Some(thr) = plan.rmse_thresholds.clone() {
        let mut feed = DivergenceFeed::new(plan, dir);
        for p in ordered {
            for runs in [true, false] {
                let (name, columns) = if runs {
                    ("runs", feed.runs_columns().to_vec())
                } else {
                    ("summary", feed.summary_columns().to_vec())
                };
                let path = p.dir.join(format!("{name}.parquet"));
                let mut row_index = 0u64;
                // Row group by row group: a part's runs table grows with its runs.
                for_each_row_group(&path, |df| {
                    stop_if_interrupted()?;
                    for_each_row(&df, &columns, &path, |row| {
                        let bad = |why: &str| OutputError::Mismatch {
                            path: path.clone(),
                            why: format!("row {row_index} {why}"),
                        };
                        if runs {
                            feed.run_row(row, &bad)?;
                        } else {
                            feed.summary_row(row, &bad)?;
                        }
                        row_index += 1;
                        Ok(())
                    })
                })?;
            }
        }
        let mut trackers = feed.into_trackers();
        let (d, dr) = divergence_tables(plan, dir, &mut trackers, &plan.quantity_names(), &thr)?;
        finished.push(d.finish()?);
        finished.push(dr.finish()?);
    }
    Ok(finished)
}

/// The merged folder's manifest: the first part's, for the whole plan, with the parts' wall
/// times summed.
fn merged_manifest(ordered: &[&Part], plan: &experiment::Plan) -> Manifest {
    let m0 = &ordered[0].manifest;
    let mut manifest = m0.clone();
    manifest.shard = None;
    let size = plan.size();
    manifest.cells = size.cells as u64;
    manifest.runs = size.runs as u64;
    manifest.filter_runs = size.filter_runs as u64;
    manifest.filter_steps = size.filter_steps;
    manifest.wall_s = ordered.iter().map(|p| p.manifest.wall_s).sum();
    manifest.runs_per_s = size.runs as f64 / manifest.wall_s.max(1e-9);
    manifest.tables.clear();
    manifest
}

/// Options of `kfmc slurm`.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SlurmOptions {
    /// Number of array tasks (parts).
    pub shards: usize,
    /// `--partition`, when given.
    pub partition: Option<String>,
    /// `--time` per task (Slurm's format, e.g. `01:00:00`).
    pub time: Option<String>,
    /// CPUs per task (and kfmc's `--threads`).
    pub cpus: usize,
    /// `--runs` override passed to every task.
    pub runs: Option<usize>,
    /// `--seed` override passed to every task.
    pub seed: Option<u64>,
}

/// The job scripts of a sharded study on Slurm: an array job (one task per part) and a merge
/// job meant to run `--dependency=afterok` on it, plus `submit.sh`, which submits both. Paths
/// are made absolute so the scripts run from any directory on a shared file system. Returns
/// (file name, contents), or the flag whose value cannot go into a script and why: every
/// value is checked against a strict character set, so none can add a line or a directive.
pub fn slurm_scripts(
    kfmc: &Path,
    spec: &Path,
    output: &Path,
    name: &str,
    o: &SlurmOptions,
) -> Result<Vec<(String, String)>, (&'static str, String)> {
    let strict = |flag: &'static str, v: &str, ok: fn(char) -> bool, set: &str| {
        if v.is_empty() || v.len() > 256 || !v.chars().all(ok) {
            Err((flag, format!("{v:?} is not a Slurm value of {set}")))
        } else {
            Ok(())
        }
    };
    if let Some(p) = &o.partition {
        strict(
            "--partition",
            p,
            |c| c.is_ascii_alphanumeric() || "_.,-".contains(c),
            "letters, digits and _ . , -",
        )?;
    }
    if let Some(t) = &o.time {
        strict(
            "--time",
            t,
            |c| c.is_ascii_alphanumeric() || ":-".contains(c),
            "digits, letters and : - (e.g. 01:00:00, 2-00:00:00, UNLIMITED)",
        )?;
    }
    if o.shards == 0 || o.shards > crate::study::MAX_SHARDS {
        return Err((
            "--shards",
            format!("{} parts: need 1 to {}", o.shards, crate::study::MAX_SHARDS),
        ));
    }
    if o.cpus == 0 {
        return Err(("--cpus", "0 CPUs per task: need at least 1".into()));
    }
    // Paths are single-quoted where the shell reads them, but `#SBATCH --output=` and the
    // comments take them verbatim: no control characters, and none that sbatch splits on or
    // expands (`%` is its file-name pattern).
    for (flag, p) in [("--out", output), ("kfmc's own path", kfmc), ("SPEC", spec)] {
        let text = p.display().to_string();
        if text.chars().any(char::is_control)
            || (flag == "--out"
                && text
                    .chars()
                    .any(|c| c.is_whitespace() || "%\"'\\".contains(c)))
        {
            return Err((
                flag,
                format!(
                    "{text:?} cannot go into a Slurm script (control characters, or in the output folder whitespace, quotes, backslashes or %)"
                ),
            ));
        }
    }
    // The spec's name only labels the jobs: anything outside a job name's safe set becomes _.
    let name: String = name
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || "_.-".contains(c) {
                c
            } else {
                '_'
            }
        })
        .collect();
    let q = |p: &Path| format!("'{}'", p.display().to_string().replace('\'', "'\\''"));
    let logs = output.join("slurm");
    let mut common = format!(
        "#SBATCH --job-name=kfmc-{name}\n#SBATCH --cpus-per-task={}\n",
        o.cpus
    );
    if let Some(p) = &o.partition {
        common.push_str(&format!("#SBATCH --partition={p}\n"));
    }
    if let Some(t) = &o.time {
        common.push_str(&format!("#SBATCH --time={t}\n"));
    }
    let mut overrides = String::new();
    if let Some(r) = o.runs {
        overrides.push_str(&format!(" --runs {r}"));
    }
    if let Some(s) = o.seed {
        overrides.push_str(&format!(" --seed {s}"));
    }
    let array = format!(
        "#!/bin/bash\n# One part of {name} per array task: kfmc reads SLURM_ARRAY_TASK_ID (and the\n# array's min and step) and writes {out}/parts/part-<i>-of-{n:05}/. A task that is\n# requeued (preempted, node failure) continues from its part's checkpoint (--resume).\n{common}#SBATCH --array=0-{last}\n#SBATCH --output={logs}/%x-%A_%a.out\nset -euo pipefail\nexec {kfmc} run {spec} --out {out_q} --shards {n} --resume --quiet --threads \"${{SLURM_CPUS_PER_TASK:-1}}\"{overrides}\n",
        out = output.display(),
        n = o.shards,
        last = o.shards.saturating_sub(1),
        logs = logs.display(),
        kfmc = q(kfmc),
        spec = q(spec),
        out_q = q(output),
    );
    let merge = format!(
        "#!/bin/bash\n# Merges the parts of {name} into {out}: run it with --dependency=afterok on the array.\n#SBATCH --job-name=kfmc-{name}-merge\n#SBATCH --cpus-per-task=1\n{part}{time}#SBATCH --output={logs}/%x-%j.out\nset -euo pipefail\nexec {kfmc} merge {out_q}\n",
        out = output.display(),
        part = o
            .partition
            .as_ref()
            .map_or(String::new(), |p| format!("#SBATCH --partition={p}\n")),
        time = o
            .time
            .as_ref()
            .map_or(String::new(), |t| format!("#SBATCH --time={t}\n")),
        logs = logs.display(),
        kfmc = q(kfmc),
        out_q = q(output),
    );
    let submit = format!(
        "#!/bin/bash\n# Submits the array, then the merge once every task succeeded. Extra arguments go to both\n# sbatch calls (e.g. --wait to block until the merge is done).\nset -euo pipefail\ncd \"$(dirname \"$0\")\"\nmkdir -p {logs}\narray=$(sbatch --parsable \"$@\" array.sbatch)\narray=${{array%%;*}}\necho \"array job $array ({n} tasks)\"\nsbatch --parsable --dependency=afterok:$array \"$@\" merge.sbatch\n",
        logs = q(&logs),
        n = o.shards,
    );
    Ok(vec![
        ("array.sbatch".into(), array),
        ("merge.sbatch".into(), merge),
        ("submit.sh".into(), submit),
    ])
}
