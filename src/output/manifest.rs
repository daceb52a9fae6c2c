//! `manifest.toml`: what a result folder holds and how to reproduce it.

use std::path::Path;

use serde::{Deserialize, Serialize};

use crate::error::OutputError;

/// One written table.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TableEntry {
    /// Table name (file `<name>.parquet`).
    pub name: String,
    /// Rows.
    pub rows: u64,
    /// File size in bytes.
    pub bytes: u64,
    /// FNV-1a 64 of the file's bytes (hex).
    pub checksum: String,
}

/// One evaluated quantity, as the manifest records it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct QuantityEntry {
    /// Name (`rmse_<name>`, `truth_<name>`, …).
    pub name: String,
    /// Unit.
    pub unit: String,
    /// Whether its error is a wrapped angle.
    pub angle: bool,
    /// `right` or `left` on the three quantities of a rotation (roll, pitch, yaw as ZYX Euler
    /// angles), whose error is the rotation error on that side
    /// ([`crate::linalg::so3::EulerRotation`]); absent otherwise.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rotation: Option<String>,
    /// On a position coordinate, its axis: `x`, `y`, `z` (a Cartesian frame, z up) or
    /// `north`, `east`, `down` ([`crate::system::PositionAxis`]); absent otherwise, and in
    /// folders written before roles were recorded (the figures then go by names).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub position: Option<String>,
    /// The measurement components that measure this quantity directly, each with its
    /// sensor: the fixes the position figures draw.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub fixes: Vec<FixEntry>,
}

/// A measurement component that measures a quantity directly ([`crate::system::PositionFix`]).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FixEntry {
    /// The sensor (the legend's `gps fixes`).
    pub sensor: String,
    /// The measurement component (trace column `z_<component>`).
    pub component: String,
}

impl Manifest {
    /// The binary that wrote the folder, `kfmc` when the manifest does not say.
    pub fn program(&self) -> &str {
        self.program.as_deref().unwrap_or("kfmc")
    }

    /// Whether the folder records position roles: a folder written before they were recorded
    /// has none, and its figures are chosen by quantity names as they were then.
    pub fn has_position_roles(&self) -> bool {
        self.quantities.iter().any(|q| q.position.is_some())
    }
}

/// Which part of a sharded study a folder holds.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ShardEntry {
    /// 0-based part index.
    pub index: u64,
    /// Number of parts.
    pub count: u64,
    /// First cell of the part.
    pub first_cell: u64,
    /// One past its last cell.
    pub end_cell: u64,
}

/// The sequential gate a study ran under.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SequentialEntry {
    /// The run counts of the looks; the last is the declared runs per cell.
    pub looks: Vec<u64>,
    /// The α-spending function (`obrien_fleming`, `pocock`).
    pub spending: String,
    /// The futility bounds' β, when the gate has them.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub futility_beta: Option<f64>,
    /// The exponent ρ of their β-spending β·t^ρ.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub futility_rho: Option<f64>,
    /// The gate's overall level (the consistency tests' α).
    pub alpha: f64,
}

/// What a simulation folder's tables mean, for the estimators that read them.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ExchangeEntry {
    /// Version of the exchange format.
    pub schema_version: u32,
    /// How errors are formed (e = truth − estimate).
    pub error_convention: String,
    /// How each run's seed derives from the master seed (the `seed` column of initial.parquet).
    pub run_seeds: String,
    /// The metadata keys an estimates file may carry to be checked against this folder.
    pub estimates_metadata: Vec<String>,
    /// Which input drives a step, what row 0 holds, and which quantities wrap (absent in
    /// folders written before it was recorded).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub step_convention: Option<StepConvention>,
    /// The spec's external filters: the estimates an outside program writes for these
    /// runs, one label each, with the variants a label declares (absent in folders written
    /// before it was recorded).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub external_filters: Vec<ExternalFilterEntry>,
}

/// An external filter of a simulated spec (`[[exchange.external_filters]]`): its label and,
/// when it declares variants, the multipliers its estimates name in their `q_scale` and
/// `r_scale` columns (every pair of them is a variant to write).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ExternalFilterEntry {
    /// The `filter` value of its rows.
    pub label: String,
    /// The `q_scale` values its rows take (the entry's list), when it declares them.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub q_scale: Option<Vec<f64>>,
    /// The `r_scale` values its rows take, when it declares them.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub r_scale: Option<Vec<f64>>,
}

/// How the rows of the exchange tables line up with the model's steps, and what wraps: what
/// a filter written outside kfmc must follow to estimate the runs kfmc simulated. The
/// sentences are the same for every system (they describe kfmc's step loop); the lists are
/// the system's.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct StepConvention {
    /// Which input drives the transition into step k.
    pub transition: String,
    /// Which measurement step k holds, and step 0's.
    pub measurement: String,
    /// What row 0 (step 0) of each table holds.
    pub row_0: String,
    /// The quantities whose error e = truth − estimate is wrapped (to [−π, π), or
    /// [−180°, 180°) in degrees) before it is scored.
    pub wrapped_errors: Vec<String>,
    /// Angle states that are continuous: their truth, their measurements and their errors
    /// are not wrapped (a roll passes ±π without a jump).
    pub continuous_angles: Vec<String>,
    /// The measurement components whose innovation z − h(x̂⁻) kfmc's filters wrap to
    /// [−π, π) (the measurement itself is not wrapped).
    pub wrapped_innovations: Vec<String>,
    /// The quantities scored as a rotation: three consecutive quantities whose error is the
    /// rotation vector (right: log(R̂ᵀR), left: log(RR̂ᵀ)) in their unit, not three wrapped
    /// angle differences; each entry names the three and the side.
    #[serde(default)]
    pub rotation_errors: Vec<String>,
}

/// What kind of result a folder holds: a writing command replaces only a folder of its own
/// kind (unless `--force`), so a mistaken `--out` cannot delete another command's tables.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum StudyKind {
    /// The tables of a study of kfmc's own filters: `kfmc run`, `kfmc check`, `kfmc merge`
    /// of a run's parts. `run` and `check` write the same tables into the same default
    /// folder, so they are one kind.
    Run,
    /// The world of every run (`kfmc simulate`, or `kfmc merge` of its parts).
    Simulate,
    /// A study with estimates read from files (`kfmc score`, `kfmc check --estimates`).
    Score,
    /// Rejection rates over replications (`kfmc power`, `kfmc check`'s replications).
    Power,
    /// A tuning search and its stages (`kfmc tune`).
    Tune,
    /// NIS verdicts from flight logs (`kfmc ulog nis`).
    Ulog,
}

impl StudyKind {
    /// The command that writes this kind of folder.
    pub fn command(self) -> &'static str {
        match self {
            StudyKind::Run => "run",
            StudyKind::Simulate => "simulate",
            StudyKind::Score => "score",
            StudyKind::Power => "power",
            StudyKind::Tune => "tune",
            StudyKind::Ulog => "ulog nis",
        }
    }

    /// What a folder of this kind holds, for messages.
    pub fn holds(self) -> &'static str {
        match self {
            StudyKind::Run => "the tables of a `kfmc run` (or `kfmc check`) study",
            StudyKind::Simulate => {
                "a `kfmc simulate` world (the truth, measurements and initial tables estimators read)"
            }
            StudyKind::Score => {
                "the tables of a `kfmc score` (or `kfmc check --estimates`) study of estimates read from files"
            }
            StudyKind::Power => "the rejection rates of a `kfmc power` study",
            StudyKind::Tune => "a `kfmc tune` search (tuning.parquet and its tune_* stages)",
            StudyKind::Ulog => "the NIS verdicts of `kfmc ulog nis` on flight logs",
        }
    }
}

/// The `format` of the manifests this kfmc writes: what makes a folder a kfmc result folder.
pub const FORMAT: &str = "kfmc-result/1";

/// What every `format` of a kfmc manifest starts with.
const FORMAT_FAMILY: &str = "kfmc-result/";

/// The largest `manifest.toml` read: far above any kfmc writes (its spec text is at most
/// 1 MiB), so that a foreign file of that name is not read whole.
const MAX_MANIFEST_BYTES: u64 = 64 << 20;

/// The manifest of a result folder.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    /// The manifest's format ([`FORMAT`]): a folder belongs to kfmc only by a manifest that
    /// says so. Absent in manifests written before it was recorded, which are trusted only
    /// when every table they list matches ([`super::folder::StudyFolder::prepare`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub format: Option<String>,
    /// kfmc version that wrote the folder: the library's, also inside a plugin crate's
    /// binary (what `merge` and `resume` compare).
    pub kfmc_version: String,
    /// The binary that wrote the folder (`kfmc`, or a plugin crate's own binary): the command
    /// that reproduces it. Absent in folders written before it was recorded (kfmc's).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub program: Option<String>,
    /// That binary's own version.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub program_version: Option<String>,
    /// Experiment name.
    pub experiment: String,
    /// `model.kind`: the system that made the folder.
    #[serde(default)]
    pub system: String,
    /// What kind of result the folder holds; absent in folders written before it was
    /// recorded ([`Manifest::kind`] then tells it from the rest of the manifest).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub kind: Option<StudyKind>,
    /// The evaluated quantities, in column order.
    #[serde(default)]
    pub quantities: Vec<QuantityEntry>,
    /// The filters' inputs (`u_<name>`).
    #[serde(default)]
    pub inputs: Vec<String>,
    /// The measurement components (`z_<name>`).
    #[serde(default)]
    pub measurements: Vec<String>,
    /// Sample time Δt (s).
    #[serde(default)]
    pub dt_s: f64,
    /// The spec file as given.
    pub spec_path: String,
    /// FNV-1a 64 of the spec text.
    pub spec_hash: String,
    /// The stamp of the simulated world ([`crate::experiment::Plan::world_stamp`]): what an
    /// estimates file made from this folder's runs carries as `kfmc.world_stamp`.
    #[serde(default)]
    pub world_stamp: String,
    /// Master seed actually used (after `--seed`).
    pub master_seed: u64,
    /// Runs per cell actually used (after `--runs`).
    pub runs_per_cell: u64,
    /// (scenario, noise scale) cells.
    pub cells: u64,
    /// Simulated runs.
    pub runs: u64,
    /// Filter runs.
    pub filter_runs: u64,
    /// Filter steps.
    pub filter_steps: u64,
    /// Worker threads (results do not depend on it).
    pub threads: u64,
    /// Runs per group handed to the trials (`--lanes`; 1 when off). Results do not depend on
    /// it. Absent in manifests written before it was recorded.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lanes: Option<u64>,
    /// The vector instruction set detected at run time (`avx512`, `avx2`, `sse2`, `neon`, or
    /// `scalar` when lanes are off). Results do not depend on it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub isa: Option<String>,
    /// Unix time the run started.
    pub started_unix_s: u64,
    /// Wall-clock duration.
    pub wall_s: f64,
    /// Throughput.
    pub runs_per_s: f64,
    /// Tables written.
    pub tables: Vec<TableEntry>,
    /// The other files kfmc wrote into the folder, as paths relative to it with `/`
    /// (`figures/rmse.png`, `report.html`, `describe.toml`): what `plot`, `report` and
    /// `describe` add to a committed study, listed before they are written.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub files: Vec<String>,
    /// The sub-folders kfmc wrote whole (a tuning search's `tune_*` stages), replaced with
    /// the study.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub folders: Vec<String>,
    /// Set only while a commit is replacing an earlier study: what that study listed, some of
    /// which may still be on disk. Readers refuse such a folder; the next writer knows from
    /// it what it may remove.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub replacing: Option<Listed>,
    /// Set in a folder written by `kfmc simulate`: what its exchange tables mean.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub exchange: Option<ExchangeEntry>,
    /// Set in the folder of one part of a sharded study (`kfmc run --shard i/n`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub shard: Option<ShardEntry>,
    /// Set when `kfmc check` ran the study under a sequential gate: each cell then holds the
    /// runs up to the look that settled it (`sequential.parquet`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sequential: Option<SequentialEntry>,
    /// The spec text, verbatim.
    pub spec: String,
}

/// What a manifest lists as written by kfmc.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Listed {
    /// Tables.
    #[serde(default)]
    pub tables: Vec<TableEntry>,
    /// Other files, relative to the folder.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub files: Vec<String>,
    /// Sub-folders written whole.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub folders: Vec<String>,
}

impl Listed {
    /// Everything `manifest` lists: its own entries and, during a commit, the earlier
    /// study's.
    pub fn of(manifest: &Manifest) -> Listed {
        let mut l = Listed {
            tables: manifest.tables.clone(),
            files: manifest.files.clone(),
            folders: manifest.folders.clone(),
        };
        if let Some(r) = &manifest.replacing {
            l.tables.extend(r.tables.iter().cloned());
            l.files.extend(r.files.iter().cloned());
            l.folders.extend(r.folders.iter().cloned());
        }
        l
    }

    /// What a manifest that does not parse as one still lists, as far as its TOML can be
    /// read: table entries with a name, and file and folder paths.
    fn salvaged(t: &toml::Table) -> Listed {
        let strings = |v: Option<&toml::Value>| -> Vec<String> {
            v.and_then(|v| v.as_array())
                .map(|a| {
                    a.iter()
                        .filter_map(|s| s.as_str().map(str::to_string))
                        .collect()
                })
                .unwrap_or_default()
        };
        let tables = |v: Option<&toml::Value>| -> Vec<TableEntry> {
            v.and_then(|v| v.as_array())
                .map(|a| {
                    a.iter()
                        .filter_map(|e| {
                            let e = e.as_table()?;
                            Some(TableEntry {
                                name: e.get("name")?.as_str()?.to_string(),
                                rows: e.get("rows").and_then(|v| v.as_integer()).unwrap_or(0)
                                    as u64,
                                bytes: u64::try_from(e.get("bytes")?.as_integer()?).ok()?,
                                checksum: e.get("checksum")?.as_str()?.to_string(),
                            })
                        })
                        .collect()
                })
                .unwrap_or_default()
        };
        let mut l = Listed {
            tables: tables(t.get("tables")),
            files: strings(t.get("files")),
            folders: strings(t.get("folders")),
        };
        if let Some(r) = t.get("replacing").and_then(|r| r.as_table()) {
            l.tables.extend(tables(r.get("tables")));
            l.files.extend(strings(r.get("files")));
            l.folders.extend(strings(r.get("folders")));
        }
        l
    }
}

/// What a folder's `manifest.toml` is, as a writer finds it.
#[derive(Debug)]
pub enum Found {
    /// There is none.
    Absent,
    /// Something that is not a regular file has the name (a symbolic link, a folder, …).
    NotAFile(&'static str),
    /// A manifest kfmc wrote: of this [`FORMAT`] (possibly in the middle of a commit,
    /// [`Manifest::replacing`]), or of an earlier one without `format`, which is trusted only
    /// once its tables are checked.
    Kfmc(Box<Manifest>),
    /// It says it is kfmc's (its `format` or its `kfmc_version`) but cannot be read as a
    /// manifest this kfmc trusts: why, and what it still lists.
    Damaged {
        /// What is wrong.
        why: String,
        /// What it lists, as far as it can be read.
        listed: Listed,
    },
    /// Not a kfmc manifest (a project's own `manifest.toml`): why not.
    Foreign(String),
}

impl Manifest {
    /// Tells what `dir/manifest.toml` is, without following a symbolic link or waiting on a
    /// FIFO.
    pub fn inspect(dir: &Path) -> Result<Found, OutputError> {
        let path = dir.join("manifest.toml");
        let meta = match std::fs::symlink_metadata(&path) {
            Ok(m) => m,
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Found::Absent),
            Err(source) => {
                return Err(OutputError::Io {
                    action: "cannot read",
                    path,
                    source,
                });
            }
        };
        if !meta.file_type().is_file() {
            return Ok(Found::NotAFile(super::atomic::type_name(meta.file_type())));
        }
        if meta.len() > MAX_MANIFEST_BYTES {
            return Ok(Found::Foreign(format!(
                "{} bytes, more than any manifest kfmc writes",
                meta.len()
            )));
        }
        let bytes = {
            use std::io::Read;
            let mut b = Vec::new();
            super::atomic::open_regular(&path)
                .and_then(|f| f.take(MAX_MANIFEST_BYTES).read_to_end(&mut b))
                .map_err(|source| OutputError::Io {
                    action: "cannot read",
                    path: path.clone(),
                    source,
                })?;
            b
        };
        let Ok(text) = String::from_utf8(bytes) else {
            return Ok(Found::Foreign("it is not UTF-8 text".into()));
        };
        let table = match text.parse::<toml::Table>() {
            Ok(t) => t,
            Err(e) => {
                // A manifest kfmc wrote starts with its format (or, before it was recorded,
                // its version): damaged past that line, it is still recognisably kfmc's.
                let first = text.lines().find(|l| !l.trim().is_empty()).unwrap_or("");
                let first = first.trim_start();
                return Ok(
                    if first.starts_with(&format!("format = \"{FORMAT_FAMILY}"))
                        || first.starts_with("kfmc_version = ")
                    {
                        Found::Damaged {
                            why: format!("it is not valid TOML: {}", one_line(&e.to_string())),
                            listed: Listed::default(),
                        }
                    } else {
                        Found::Foreign("it is not TOML".into())
                    },
                );
            }
        };
        match table.get("format") {
            Some(toml::Value::String(f)) if f == FORMAT => {}
            Some(toml::Value::String(f)) if f.starts_with(FORMAT_FAMILY) => {
                return Ok(Found::Damaged {
                    why: format!("its format `{f}` is not one this kfmc reads ({FORMAT})"),
                    listed: Listed::salvaged(&table),
                });
            }
            Some(other) => {
                return Ok(Found::Foreign(format!(
                    "its format is {other}, not {FORMAT}"
                )));
            }
            None if !table.get("kfmc_version").is_some_and(|v| v.is_str()) => {
                return Ok(Found::Foreign(format!(
                    "it has neither `format = \"{FORMAT}\"` nor the `kfmc_version` of an earlier kfmc manifest"
                )));
            }
            None => {}
        }
        match toml::from_str::<Manifest>(&text) {
            Ok(m) => Ok(Found::Kfmc(Box::new(m))),
            Err(e) => Ok(Found::Damaged {
                why: one_line(&e.to_string()),
                listed: Listed::salvaged(&table),
            }),
        }
    }

    /// Writes `manifest.toml` atomically into `dir`. Inside a study folder this is the commit
    /// record, written last ([`super::folder::StudyFolder::commit`]).
    pub fn write(&self, dir: &Path) -> Result<(), OutputError> {
        let text = toml::to_string(self).map_err(|e| OutputError::Format {
            path: dir.join("manifest.toml"),
            message: e.to_string(),
        })?;
        let path = dir.join("manifest.toml");
        // The commit record: written, synced and renamed into place, then the folder synced.
        super::atomic::write_atomic(&path, text.as_bytes()).map_err(|source| OutputError::Io {
            action: "cannot write",
            path,
            source,
        })
    }

    /// The kind of result the folder holds: as recorded, or, in a manifest written before the
    /// kind was recorded, told from what only that kind writes (the exchange section of a
    /// simulation, the power or tuning table, an external filter in the recorded spec).
    pub fn kind(&self) -> StudyKind {
        if let Some(k) = self.kind {
            return k;
        }
        let has = |t: &str| self.tables.iter().any(|e| e.name == t);
        if self.exchange.is_some() {
            StudyKind::Simulate
        } else if has("power") {
            StudyKind::Power
        } else if has("tuning") {
            StudyKind::Tune
        } else if spec_has_external_filter(&self.spec) {
            StudyKind::Score
        } else {
            StudyKind::Run
        }
    }

    /// Reads `manifest.toml` from `dir` (never through a symbolic link).
    pub fn read(dir: &Path) -> Result<Self, OutputError> {
        let path = dir.join("manifest.toml");
        let text = super::atomic::read_regular(&path).map_err(|source| OutputError::Io {
            action: "cannot read",
            path: path.clone(),
            source,
        })?;
        toml::from_str(&text).map_err(|e| OutputError::Format {
            path,
            message: e.to_string(),
        })
    }
}

/// A parser's message on one line (the TOML parser's spans the source over several).
fn one_line(message: &str) -> String {
    let lines: Vec<&str> = message
        .lines()
        .map(str::trim)
        .filter(|l| !l.is_empty())
        .collect();
    match lines.as_slice() {
        [] => String::new(),
        [one] => one.to_string(),
        [first, .., last] => format!("{first}: {last}"),
    }
}

/// Whether a spec's text declares a `kind = "external"` filter.
fn spec_has_external_filter(spec: &str) -> bool {
    let Ok(value) = spec.parse::<toml::Table>() else {
        return false;
    };
    value
        .get("filters")
        .and_then(|f| f.as_array())
        .is_some_and(|filters| {
            filters
                .iter()
                .any(|f| f.get("kind").and_then(|k| k.as_str()) == Some("external"))
        })
}
