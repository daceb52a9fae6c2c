//! No writer deletes or overwrites what kfmc did not write.
//!
//! * A matrix: folder states (empty, a study of the command's own kind, of another kind,
//!   foreign files, a project's own `manifest.toml`, user files with table names, user
//!   `.partial` entries, symbolic links, a manifest from an earlier kfmc, intact or with a
//!   changed table, a damaged manifest) × every writing command (`run`, `check`, `simulate`,
//!   `score`, `merge`, `power`, `tune`, `describe`, `plot`, `report`) × with and without
//!   `--force`. The tree is hashed before and after (symbolic links by their target, and
//!   what they point to outside): every change lies inside what the folder's manifest lists
//!   (before or after the command), the manifest itself or the lock file; every entry the
//!   state planted as the user's is byte for byte as it was; a refused command changes
//!   nothing; no temporary file remains. `KFMC_OWNERSHIP_BIN` runs it against another kfmc
//!   binary (an older build, to see what it did).
//! * One test per case the hostile review reported, each of which an earlier kfmc failed.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use kfmc::output::folder::verify;

const SPEC: &str = r#"
name = "ownership"
master_seed = 7
runs = 2
[model]
kind = "linear_quadrotor"
sensor = "positions"
[[scenarios]]
name = "hover"
x0 = [1.0, 0.0, 1.0, 0.0, 1.0, 0.0]
duration_s = 1.0
[noise]
scales = [1.0, 3.0]
[[filters]]
label = "kf"
kind = "KIND"
[initial_estimate]
mode = "sampled"
p0_std = 1.0
[consistency]
alpha = 0.05
[divergence]
rmse_thresholds = [0.5, 0.5, 0.5, 0.5, 0.5, 0.5]
"#;

const ASSERTION: &str = r#"
[[check.assert]]
kind = "rmse_below"
filter = "kf"
state = "x"
max = 100.0
"#;

fn kfmc() -> Command {
    match std::env::var_os("KFMC_OWNERSHIP_BIN") {
        Some(bin) => Command::new(bin),
        None => crate::common::kfmc(),
    }
}

fn output(cmd: &mut Command) -> (i32, String) {
    let o = cmd.output().expect("kfmc runs");
    (
        o.status.code().unwrap_or(-1),
        String::from_utf8_lossy(&o.stderr).into_owned(),
    )
}

fn ok(cmd: &mut Command) {
    let (code, err) = output(cmd);
    assert_eq!(code, 0, "{cmd:?}: {err}");
}

fn s(p: &Path) -> String {
    p.to_str().unwrap().to_string()
}

/// The inputs every command reads, outside every folder written, and a finished result
/// folder of each kind to copy from.
struct World {
    _tmp: tempfile::TempDir,
    dir: PathBuf,
}

impl World {
    fn new() -> World {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().to_path_buf();
        let w = World { _tmp: tmp, dir };
        std::fs::write(w.p("run.toml"), SPEC.replace("KIND", "ekf")).unwrap();
        std::fs::write(
            w.p("check.toml"),
            format!("{}{ASSERTION}", SPEC.replace("KIND", "ekf")),
        )
        .unwrap();
        std::fs::write(w.p("ext.toml"), SPEC.replace("KIND", "external")).unwrap();
        ok(kfmc()
            .args(["run", "-q", "--export-estimates", "--out"])
            .arg(w.p("exported"))
            .arg(w.p("run.toml")));
        std::fs::copy(w.p("exported/estimates.parquet"), w.p("kf.parquet")).unwrap();
        ok(kfmc()
            .args(["simulate", "-q", "--out"])
            .arg(w.p("sim"))
            .arg(w.p("ext.toml")));
        for i in 0..2 {
            ok(kfmc()
                .args(["run", "-q", "--shard", &format!("{i}/2"), "--out"])
                .arg(w.p("sharded"))
                .arg(w.p("run.toml")));
        }
        // One finished folder of each kind; the run's with its figures, report and
        // description added.
        for cmd in [Cmd::Run, Cmd::Simulate, Cmd::Score, Cmd::Power, Cmd::Tune] {
            let out = w.template(cmd.kind());
            let (code, err) = output(&mut w.command(cmd, &out, false));
            assert!(code == 0, "{cmd:?}: {err}");
        }
        let run = w.template("run");
        for cmd in [Cmd::Plot, Cmd::Report, Cmd::Describe] {
            let (code, err) = output(&mut w.command(cmd, &run, false));
            assert!(code == 0, "{cmd:?}: {err}");
        }
        w
    }

    fn p(&self, name: &str) -> PathBuf {
        self.dir.join(name)
    }

    fn template(&self, kind: &str) -> PathBuf {
        self.p("templates").join(kind)
    }

    /// The command line of `cmd` writing into `out`.
    fn command(&self, cmd: Cmd, out: &Path, force: bool) -> Command {
        let mut c = kfmc();
        let o = s(out);
        let args: Vec<String> = match cmd {
            Cmd::Run => vec!["run".into(), s(&self.p("run.toml")), "--out".into(), o],
            Cmd::Check => vec!["check".into(), s(&self.p("check.toml")), "--out".into(), o],
            Cmd::Simulate => vec!["simulate".into(), s(&self.p("ext.toml")), "--out".into(), o],
            Cmd::Score => vec![
                "score".into(),
                s(&self.p("sim")),
                "--estimates".into(),
                s(&self.p("kf.parquet")),
                "--out".into(),
                o,
            ],
            Cmd::Merge => vec!["merge".into(), o],
            Cmd::Power => vec![
                "power".into(),
                s(&self.p("run.toml")),
                "--replications".into(),
                "1".into(),
                "--out".into(),
                o,
            ],
            Cmd::Tune => vec!["tune".into(), s(&self.p("run.toml")), "--out".into(), o],
            Cmd::Describe => vec![
                "describe".into(),
                s(&self.p("run.toml")),
                "--out".into(),
                s(&out.join("describe.toml")),
            ],
            Cmd::Plot => vec!["plot".into(), o],
            Cmd::Report => vec!["report".into(), o],
        };
        c.args(&args);
        if !matches!(cmd, Cmd::Merge | Cmd::Describe | Cmd::Plot | Cmd::Report) {
            c.arg("-q");
        }
        if force {
            c.arg("--force");
        }
        c.stdout(std::process::Stdio::null());
        c
    }
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Cmd {
    Run,
    Check,
    Simulate,
    Score,
    Merge,
    Power,
    Tune,
    Describe,
    Plot,
    Report,
}

impl Cmd {
    const ALL: [Cmd; 10] = [
        Cmd::Run,
        Cmd::Check,
        Cmd::Simulate,
        Cmd::Score,
        Cmd::Merge,
        Cmd::Power,
        Cmd::Tune,
        Cmd::Describe,
        Cmd::Plot,
        Cmd::Report,
    ];

    /// The kind of folder it writes (for `describe`, `plot` and `report`: the study they add
    /// to).
    fn kind(self) -> &'static str {
        match self {
            Cmd::Simulate => "simulate",
            Cmd::Score => "score",
            Cmd::Power => "power",
            Cmd::Tune => "tune",
            _ => "run",
        }
    }

    fn takes_force(self) -> bool {
        !matches!(self, Cmd::Describe | Cmd::Plot | Cmd::Report)
    }

    /// Exit codes of a command that ran (`check` exits 3 or 4 on a judged case).
    fn ran(self, code: i32) -> bool {
        code == 0 || (self == Cmd::Check && (code == 3 || code == 4))
    }
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum State {
    Empty,
    OwnKind,
    OtherKind,
    Foreign,
    ProjectManifest,
    TableNamed,
    TableNamedInStudy,
    Partial,
    PartialInStudy,
    LinksBeside,
    LinkedTable,
    LockLink,
    CheckpointLink,
    Legacy,
    LegacyChanged,
    Damaged,
}

impl State {
    const ALL: [State; 16] = [
        State::Empty,
        State::OwnKind,
        State::OtherKind,
        State::Foreign,
        State::ProjectManifest,
        State::TableNamed,
        State::TableNamedInStudy,
        State::Partial,
        State::PartialInStudy,
        State::LinksBeside,
        State::LinkedTable,
        State::LockLink,
        State::CheckpointLink,
        State::Legacy,
        State::LegacyChanged,
        State::Damaged,
    ];
}

/// Copies a folder tree (symbolic links as links).
fn copy_tree(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        let t = e.file_type().unwrap();
        let dest = to.join(e.file_name());
        if t.is_dir() {
            copy_tree(&e.path(), &dest);
        } else if t.is_symlink() {
            std::os::unix::fs::symlink(std::fs::read_link(e.path()).unwrap(), &dest).unwrap();
        } else {
            std::fs::copy(e.path(), &dest).unwrap();
        }
    }
}

/// Writes `text` at `rel` inside `dir`, creating folders on the way.
fn plant(dir: &Path, rel: &str, text: &str) {
    let p = dir.join(rel);
    std::fs::create_dir_all(p.parent().unwrap()).unwrap();
    std::fs::write(p, text).unwrap();
}

/// Rewrites the first line of `dir/manifest.toml` that starts with `key = ` (`None` drops it).
fn edit_manifest(dir: &Path, key: &str, value: Option<&str>) {
    let path = dir.join("manifest.toml");
    let text = std::fs::read_to_string(&path).unwrap();
    let mut done = false;
    let mut out = String::new();
    for line in text.lines() {
        if !done && line.starts_with(&format!("{key} = ")) {
            done = true;
            if let Some(v) = value {
                out.push_str(&format!("{key} = {v}\n"));
            }
        } else {
            out.push_str(line);
            out.push('\n');
        }
    }
    // An earlier kfmc's manifest has no `format` to drop.
    assert!(done || value.is_none(), "{} has no `{key}`", path.display());
    std::fs::write(&path, out).unwrap();
}

/// Sets up `state` in `out` for `cmd` (with `outside/` beside it, which links point into);
/// returns the entries (relative to `out`) that are the user's.
fn set_up(w: &World, state: State, cmd: Cmd, out: &Path) -> Vec<String> {
    let outside = out.parent().unwrap().join("outside");
    plant(&outside, "secret.txt", "the user's file outside\n");
    plant(&outside, "dir/kept.txt", "the user's folder outside\n");
    let own = || copy_tree(&w.template(cmd.kind()), out);
    let mut user: Vec<&str> = Vec::new();
    match state {
        State::Empty => {}
        State::OwnKind => own(),
        State::OtherKind => {
            let other = if cmd.kind() == "simulate" {
                "run"
            } else {
                "simulate"
            };
            copy_tree(&w.template(other), out);
        }
        State::Foreign => {
            plant(out, "notes.txt", "mine\n");
            plant(out, "data/x.csv", "1,2\n");
            user = vec!["notes.txt", "data"];
        }
        State::ProjectManifest => {
            plant(out, "manifest.toml", "[project]\nname = \"mine\"\n");
            plant(out, "README.md", "my project\n");
            user = vec!["manifest.toml", "README.md"];
        }
        State::TableNamed => {
            for t in ["runs", "summary", "estimates", "truth", "power", "tuning"] {
                plant(out, &format!("{t}.parquet"), "the user's own table\n");
            }
            user = vec![
                "runs.parquet",
                "summary.parquet",
                "estimates.parquet",
                "truth.parquet",
                "power.parquet",
                "tuning.parquet",
            ];
        }
        State::TableNamedInStudy => {
            own();
            plant(out, "estimates.parquet", "the user's estimates\n");
            user = vec!["estimates.parquet"];
        }
        State::Partial | State::PartialInStudy => {
            if state == State::PartialInStudy {
                own();
            } else {
                plant(out, "readme.txt", "k\n");
                user.push("readme.txt");
            }
            plant(out, ".backup.partial/sub/d", "x\n");
            plant(out, ".runs.parquet.partial", "a stream\n");
            plant(out, ".mine.parquet.partial", "python's stream\n");
            plant(out, ".manifest.toml.partial", "mine\n");
            plant(
                out,
                ".kfmc-0123456789abcdef-1.runs.parquet.partial",
                "named like kfmc's, by no kfmc\n",
            );
            user.extend([
                ".backup.partial",
                ".runs.parquet.partial",
                ".mine.parquet.partial",
                ".manifest.toml.partial",
                ".kfmc-0123456789abcdef-1.runs.parquet.partial",
            ]);
        }
        State::LinksBeside => {
            own();
            std::os::unix::fs::symlink("../outside/secret.txt", out.join("link.txt")).unwrap();
            std::os::unix::fs::symlink("../outside/dir", out.join("linked_dir")).unwrap();
            user = vec!["link.txt", "linked_dir"];
        }
        State::LinkedTable => {
            own();
            let table = match cmd.kind() {
                "simulate" => "truth.parquet",
                "power" => "power.parquet",
                "tune" => "tuning.parquet",
                _ => "summary.parquet",
            };
            std::fs::remove_file(out.join(table)).unwrap();
            std::os::unix::fs::symlink("../outside/secret.txt", out.join(table)).unwrap();
            // The link's name is listed; the link is not kfmc's.
            user = vec![table];
        }
        State::LockLink => {
            own();
            std::os::unix::fs::symlink("../outside/secret.txt", out.join(".kfmc.lock")).unwrap();
            user = vec![".kfmc.lock"];
        }
        State::CheckpointLink => {
            own();
            std::os::unix::fs::symlink("../outside/dir", out.join(".checkpoint")).unwrap();
            user = vec![".checkpoint"];
        }
        State::Legacy => {
            own();
            edit_manifest(out, "format", None);
        }
        State::LegacyChanged => {
            own();
            edit_manifest(out, "format", None);
            let table = match cmd.kind() {
                "simulate" => "truth.parquet",
                "power" => "power.parquet",
                "tune" => "tuning.parquet",
                _ => "summary.parquet",
            };
            plant(out, table, "the user's bytes over a kfmc table\n");
            user = vec![table];
        }
        State::Damaged => {
            own();
            edit_manifest(out, "kind", Some("\"bogus\""));
        }
    }
    if cmd == Cmd::Merge {
        // What a merge reads.
        copy_tree(&w.p("sharded/parts"), &out.join("parts"));
    }
    user.into_iter().map(String::from).collect()
}

/// One entry of a tree, as compared.
#[derive(Clone, Debug, PartialEq)]
enum Node {
    Dir,
    File(Vec<u8>),
    Link(PathBuf),
    Other,
}

/// Every entry under `root` (not following links), by relative path.
fn tree(root: &Path) -> BTreeMap<String, Node> {
    fn walk(root: &Path, rel: &str, into: &mut BTreeMap<String, Node>) {
        let Ok(entries) = std::fs::read_dir(root.join(rel)) else {
            return;
        };
        for e in entries.flatten() {
            let name = e.file_name().to_string_lossy().into_owned();
            let r = if rel.is_empty() {
                name
            } else {
                format!("{rel}/{name}")
            };
            let t = e.file_type().unwrap();
            if t.is_dir() {
                into.insert(r.clone(), Node::Dir);
                walk(root, &r, into);
            } else if t.is_symlink() {
                into.insert(r, Node::Link(std::fs::read_link(e.path()).unwrap()));
            } else if t.is_file() {
                into.insert(r, Node::File(std::fs::read(e.path()).unwrap_or_default()));
            } else {
                into.insert(r, Node::Other);
            }
        }
    }
    let mut m = BTreeMap::new();
    walk(root, "", &mut m);
    m
}

/// Whether a `manifest.toml` says it is kfmc's (a `format` or a `kfmc_version` line).
fn kfmc_looking(manifest: &Node) -> bool {
    let Node::File(bytes) = manifest else {
        return false;
    };
    String::from_utf8_lossy(bytes)
        .lines()
        .any(|l| l.starts_with("format = \"kfmc-result/") || l.starts_with("kfmc_version = "))
}

/// What a manifest's text lists (tables as files, other files, whole folders), when the file
/// is kfmc's (a `format` or a `kfmc_version`).
fn listed(manifest: Option<&Node>) -> (Vec<String>, Vec<String>) {
    let Some(Node::File(bytes)) = manifest else {
        return (Vec::new(), Vec::new());
    };
    let Ok(t) = String::from_utf8_lossy(bytes).parse::<toml::Table>() else {
        return (Vec::new(), Vec::new());
    };
    if !t.contains_key("format") && !t.contains_key("kfmc_version") {
        return (Vec::new(), Vec::new());
    }
    let mut files = Vec::new();
    let mut folders = Vec::new();
    let mut add = |t: &toml::Table| {
        for e in t
            .get("tables")
            .and_then(|v| v.as_array())
            .into_iter()
            .flatten()
        {
            if let Some(n) = e.get("name").and_then(|n| n.as_str()) {
                files.push(format!("{n}.parquet"));
            }
        }
        for f in t
            .get("files")
            .and_then(|v| v.as_array())
            .into_iter()
            .flatten()
        {
            files.extend(f.as_str().map(String::from));
        }
        for f in t
            .get("folders")
            .and_then(|v| v.as_array())
            .into_iter()
            .flatten()
        {
            folders.extend(f.as_str().map(String::from));
        }
    };
    add(&t);
    if let Some(r) = t.get("replacing").and_then(|r| r.as_table()) {
        add(r);
    }
    (files, folders)
}

/// Whether kfmc's own temporary name (`.kfmc-<token>-<n>.<name>.partial`) is `name`.
fn is_kfmc_temp(name: &str) -> bool {
    let Some(rest) = name.strip_prefix(".kfmc-") else {
        return false;
    };
    name.ends_with(".partial")
        && rest
            .split_once('-')
            .is_some_and(|(t, _)| t.len() == 16 && t.bytes().all(|b| b.is_ascii_hexdigit()))
}

/// The problems of one case: what changed that the manifest does not list, a user entry
/// changed, the outside touched, a temporary file left.
fn judge(
    cmd: Cmd,
    code: i32,
    user: &[String],
    before: &BTreeMap<String, Node>,
    after: &BTreeMap<String, Node>,
    outside: (&BTreeMap<String, Node>, &BTreeMap<String, Node>),
) -> Vec<String> {
    let mut problems = Vec::new();
    for u in user {
        let mine = |m: &BTreeMap<String, Node>| -> Vec<(String, Node)> {
            m.iter()
                .filter(|(k, _)| *k == u || k.starts_with(&format!("{u}/")))
                .map(|(k, v)| (k.clone(), v.clone()))
                .collect()
        };
        if mine(before) != mine(after) {
            problems.push(format!("the user's {u} changed"));
        }
    }
    if outside.0 != outside.1 {
        problems.push("a file outside the folder changed".into());
    }
    let (mut files, mut folders) = listed(before.get("manifest.toml"));
    let (f2, d2) = listed(after.get("manifest.toml"));
    files.extend(f2);
    folders.extend(d2);
    let lock_was_link = matches!(before.get(".kfmc.lock"), Some(Node::Link(_)));
    let manifest_was_users = before
        .get("manifest.toml")
        .is_some_and(|m| !kfmc_looking(m));
    let allowed = |p: &str| -> bool {
        if p == ".kfmc.lock" {
            return !lock_was_link;
        }
        if p == "manifest.toml" {
            return !manifest_was_users;
        }
        if files
            .iter()
            .any(|f| f == p || f.starts_with(&format!("{p}/")))
        {
            return true;
        }
        if folders
            .iter()
            .any(|d| p == d || p.starts_with(&format!("{d}/")))
        {
            return true;
        }
        // A description kfmc wrote where no manifest lists it says so on its first line.
        p == "describe.toml"
            && matches!(after.get(p), Some(Node::File(b)) if b.starts_with(b"format = \"kfmc-describe/1\""))
    };
    let mut changed: Vec<&String> = before
        .keys()
        .chain(after.keys())
        .filter(|k| before.get(*k) != after.get(*k))
        .collect();
    changed.sort();
    changed.dedup();
    for p in &changed {
        if !allowed(p) {
            problems.push(format!("{p} changed and no manifest lists it"));
        }
    }
    if !cmd.ran(code) && changed.iter().any(|p| p.as_str() != ".kfmc.lock") {
        problems.push(format!(
            "refused (exit {code}) but changed {:?}",
            changed
                .iter()
                .filter(|p| p.as_str() != ".kfmc.lock")
                .collect::<Vec<_>>()
        ));
    }
    for p in after.keys() {
        if p.split('/').any(is_kfmc_temp) && !before.contains_key(p) {
            problems.push(format!("{p}: a temporary file left behind"));
        }
    }
    problems
}

/// One case of the matrix: its outcome, and what was wrong.
struct Outcome {
    state: State,
    cmd: Cmd,
    force: bool,
    code: i32,
    problems: Vec<String>,
    err: String,
}

fn run_case(w: &World, n: usize, state: State, cmd: Cmd, force: bool) -> Outcome {
    let case = w.p("cases").join(n.to_string());
    let out = case.join("out");
    let user = set_up(w, state, cmd, &out);
    let outside = case.join("outside");
    let (before, outside_before) = (tree(&out), tree(&outside));
    let started = Instant::now();
    let mut child = w
        .command(cmd, &out, force)
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    // A writer that waits on something is a failure of its own: it is stopped.
    let code = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break status.code().unwrap_or(-1);
        }
        if started.elapsed() > Duration::from_secs(60) {
            let _ = child.kill();
            let _ = child.wait();
            break -2;
        }
        std::thread::sleep(Duration::from_millis(5));
    };
    let mut err = String::new();
    if let Some(mut e) = child.stderr.take() {
        use std::io::Read;
        let _ = e.read_to_string(&mut err);
    }
    let (after, outside_after) = (tree(&out), tree(&outside));
    let mut problems = judge(
        cmd,
        code,
        &user,
        &before,
        &after,
        (&outside_before, &outside_after),
    );
    if code == -2 {
        problems.push("did not finish within 60 s".into());
    }
    if cmd.ran(code)
        && !matches!(cmd, Cmd::Describe)
        && let Err(e) = verify(&out)
    {
        problems.push(format!("exit {code}, but the folder is not readable: {e}"));
    }
    let _ = std::fs::remove_dir_all(&case);
    Outcome {
        state,
        cmd,
        force,
        code,
        problems,
        err: err.trim().lines().last().unwrap_or("").to_string(),
    }
}

#[test]
fn no_writer_changes_a_byte_outside_what_the_manifest_lists() {
    let started = Instant::now();
    let w = World::new();
    let mut cases = Vec::new();
    for state in State::ALL {
        for cmd in Cmd::ALL {
            for force in [false, true] {
                if force && !cmd.takes_force() {
                    continue;
                }
                cases.push((state, cmd, force));
            }
        }
    }
    let next = std::sync::atomic::AtomicUsize::new(0);
    let outcomes = std::sync::Mutex::new(Vec::new());
    std::thread::scope(|scope| {
        for _ in 0..2 {
            scope.spawn(|| {
                loop {
                    let i = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                    let Some(&(state, cmd, force)) = cases.get(i) else {
                        break;
                    };
                    let o = run_case(&w, i, state, cmd, force);
                    outcomes.lock().unwrap().push(o);
                }
            });
        }
    });
    let mut outcomes = outcomes.into_inner().unwrap();
    outcomes.sort_by_key(|o| {
        (
            State::ALL.iter().position(|s| *s == o.state),
            Cmd::ALL.iter().position(|c| *c == o.cmd),
            o.force,
        )
    });
    let mut table = String::new();
    let mut bad = Vec::new();
    for o in &outcomes {
        table.push_str(&format!(
            "{:<18} {:<9} {:<7} exit {:>2}  {}\n",
            format!("{:?}", o.state),
            format!("{:?}", o.cmd).to_lowercase(),
            if o.force { "--force" } else { "" },
            o.code,
            if o.code == 0 { "" } else { o.err.as_str() }
        ));
        if !o.problems.is_empty() {
            bad.push(format!(
                "{:?} × {:?}{}: {} (exit {}: {})",
                o.state,
                o.cmd,
                if o.force { " --force" } else { "" },
                o.problems.join("; "),
                o.code,
                o.err
            ));
        }
    }
    eprintln!(
        "{} cases in {:.1} s:\n{table}",
        outcomes.len(),
        started.elapsed().as_secs_f64()
    );
    assert!(
        bad.is_empty(),
        "{} of {} cases:\n{}",
        bad.len(),
        outcomes.len(),
        bad.join("\n")
    );
    // Not vacuous: every study writer wrote into the empty folder and into its own kind's,
    // and was refused over a project's manifest, forced or not.
    for o in &outcomes {
        let study = o.cmd.takes_force();
        match o.state {
            State::Empty | State::OwnKind | State::Legacy if study => {
                assert!(
                    o.cmd.ran(o.code),
                    "{:?} × {:?}: exit {}: {}",
                    o.state,
                    o.cmd,
                    o.code,
                    o.err
                )
            }
            State::ProjectManifest
            | State::TableNamed
            | State::LinkedTable
            | State::LockLink
            | State::CheckpointLink
            | State::LegacyChanged
                if study =>
            {
                assert_eq!(o.code, 1, "{:?} × {:?}: {}", o.state, o.cmd, o.err)
            }
            _ => {}
        }
    }
}

/// Writes a `kfmc run` study of `w`'s spec into `out`.
fn study(w: &World, out: &Path) {
    ok(&mut w.command(Cmd::Run, out, false));
}

#[test]
fn a_refused_command_keeps_the_users_partial_entries_which_do_not_make_a_folder_empty() {
    let w = World::new();
    let f = w.p("f");
    plant(&f, ".backup.partial/sub/d", "x\n");
    plant(&f, "readme.txt", "k\n");
    let (code, err) = output(&mut w.command(Cmd::Run, &f, false));
    assert_eq!(code, 1, "{err}");
    assert!(
        err.contains("is not empty and is not a kfmc result folder"),
        "{err}"
    );
    assert_eq!(
        std::fs::read_to_string(f.join(".backup.partial/sub/d")).unwrap(),
        "x\n"
    );
    // Only `.partial` entries: still not empty.
    std::fs::remove_file(f.join("readme.txt")).unwrap();
    let (code, err) = output(&mut w.command(Cmd::Run, &f, false));
    assert_eq!(code, 1, "{err}");
    assert!(err.contains(".backup.partial"), "{err}");
    // Forced, the study is written beside it; a re-run keeps a stream Python writes there.
    ok(&mut w.command(Cmd::Run, &f, true));
    plant(&f, ".mine.parquet.partial", "1,000 runs streaming\n");
    ok(&mut w.command(Cmd::Run, &f, false));
    assert_eq!(
        std::fs::read_to_string(f.join(".backup.partial/sub/d")).unwrap(),
        "x\n"
    );
    assert_eq!(
        std::fs::read_to_string(f.join(".mine.parquet.partial")).unwrap(),
        "1,000 runs streaming\n"
    );
    verify(&f).unwrap();
}

#[test]
fn a_projects_own_manifest_is_never_replaced() {
    let w = World::new();
    let p = w.p("project");
    plant(
        &p,
        "manifest.toml",
        "[package]\nname = \"mine\"\nversion = \"1.0\"\n",
    );
    for force in [false, true] {
        let (code, err) = output(&mut w.command(Cmd::Run, &p, force));
        assert_eq!(code, 1, "force {force}: {err}");
        assert!(err.contains("is not a kfmc manifest"), "{err}");
    }
    assert_eq!(
        std::fs::read_to_string(p.join("manifest.toml")).unwrap(),
        "[package]\nname = \"mine\"\nversion = \"1.0\"\n"
    );
    assert_eq!(
        std::fs::read_dir(&p).unwrap().count(),
        1,
        "nothing was written beside it"
    );
}

#[test]
fn a_damaged_manifest_or_one_of_an_unknown_kind_is_refused_unless_forced() {
    let w = World::new();
    for (name, damage) in [
        ("unknown_kind", "kind"),
        ("truncated", "truncate"),
        ("newer_format", "format"),
    ] {
        let sim = w.p(name);
        copy_tree(&w.template("simulate"), &sim);
        match damage {
            "kind" => edit_manifest(&sim, "kind", Some("\"sharded-simulate\"")),
            "format" => edit_manifest(&sim, "format", Some("\"kfmc-result/9\"")),
            _ => {
                let text = std::fs::read_to_string(sim.join("manifest.toml")).unwrap();
                std::fs::write(sim.join("manifest.toml"), &text[..text.len() / 2]).unwrap();
            }
        }
        let before = tree(&sim);
        let (code, err) = output(&mut w.command(Cmd::Run, &sim, false));
        assert_eq!(code, 1, "{name}: {err}");
        assert!(
            err.contains("damaged kfmc manifest") && err.contains("--force"),
            "{name}: {err}"
        );
        assert!(tree(&sim) == before, "{name}: the folder changed");
        // Forced, the run replaces the study (its tables still match what it listed, or are
        // refused by name where nothing says they are kfmc's).
        let (code, err) = output(&mut w.command(Cmd::Run, &sim, true));
        if name == "truncated" {
            // Nothing readable lists its tables: they stay, named.
            assert_eq!(code, 1, "{name}: {err}");
            assert!(err.contains("has the name of a kfmc table"), "{err}");
            assert!(tree(&sim) == before, "{name}: the folder changed");
        } else {
            assert_eq!(code, 0, "{name}: {err}");
            let m = verify(&sim).unwrap();
            assert_eq!(m.kind(), kfmc::output::manifest::StudyKind::Run);
            assert!(
                !sim.join("truth.parquet").exists(),
                "{name}: the listed table stayed"
            );
        }
    }
}

#[test]
fn score_never_deletes_its_own_input() {
    let w = World::new();
    // Estimates named like kfmc's table, in the folder scored into.
    let d = w.p("d");
    std::fs::create_dir_all(&d).unwrap();
    std::fs::copy(w.p("kf.parquet"), d.join("estimates.parquet")).unwrap();
    let kf = std::fs::read(w.p("kf.parquet")).unwrap();
    for force in [false, true] {
        let mut c = kfmc();
        c.args(["score", "-q"])
            .arg(w.p("sim"))
            .arg("--estimates")
            .arg(d.join("estimates.parquet"))
            .arg("--out")
            .arg(&d);
        if force {
            c.arg("--force");
        }
        let (code, err) = output(&mut c);
        assert_eq!(code, 1, "force {force}: {err}");
        assert!(err.contains("estimates.parquet"), "{err}");
        assert_eq!(std::fs::read(d.join("estimates.parquet")).unwrap(), kf);
    }
    // Any input file inside the folder written, whatever its name: score, check, a spec.
    let scored = w.p("scored");
    ok(&mut w.command(Cmd::Score, &scored, false));
    std::fs::copy(w.p("kf.parquet"), scored.join("mine.parquet")).unwrap();
    let (code, err) = output(
        kfmc()
            .args(["score", "-q"])
            .arg(w.p("sim"))
            .arg("--estimates")
            .arg(scored.join("mine.parquet"))
            .arg("--out")
            .arg(&scored),
    );
    assert_eq!(code, 1, "{err}");
    assert!(
        err.contains("is read by this command and lies inside its output folder"),
        "{err}"
    );
    std::fs::write(
        w.p("ext_check.toml"),
        format!("{}{ASSERTION}", SPEC.replace("KIND", "external")),
    )
    .unwrap();
    let checked = w.p("checked");
    let check = |estimates: &Path| {
        output(
            kfmc()
                .args(["check", "-q", "--out"])
                .arg(&checked)
                .arg(w.p("ext_check.toml"))
                .arg("--estimates")
                .arg(estimates),
        )
    };
    let (code, err) = check(&w.p("kf.parquet"));
    assert_eq!(code, 0, "{err}");
    std::fs::copy(w.p("kf.parquet"), checked.join("mine.parquet")).unwrap();
    let (code, err) = check(&checked.join("mine.parquet"));
    assert_eq!(code, 1, "{err}");
    assert!(err.contains("lies inside its output folder"), "{err}");
    assert_eq!(std::fs::read(checked.join("mine.parquet")).unwrap(), kf);
    let spec_inside = w.p("spec_inside");
    plant(&spec_inside, "spec.toml", &SPEC.replace("KIND", "ekf"));
    let (code, err) = output(
        kfmc()
            .args(["run", "-q", "--force", "--out"])
            .arg(&spec_inside)
            .arg(spec_inside.join("spec.toml")),
    );
    assert_eq!(code, 1, "{err}");
    assert!(err.contains("spec.toml is read by this command"), "{err}");
}

#[test]
fn a_simulation_rerun_keeps_a_users_estimates_file() {
    let w = World::new();
    let sim = w.p("mysim");
    ok(&mut w.command(Cmd::Simulate, &sim, false));
    std::fs::copy(w.p("kf.parquet"), sim.join("estimates.parquet")).unwrap();
    for force in [false, true] {
        let (code, err) = output(&mut w.command(Cmd::Simulate, &sim, force));
        assert_eq!(code, 1, "force {force}: {err}");
        assert!(
            err.contains("estimates.parquet has the name of a kfmc table")
                && err.contains("even with --force"),
            "{err}"
        );
        assert_eq!(
            std::fs::read(sim.join("estimates.parquet")).unwrap(),
            std::fs::read(w.p("kf.parquet")).unwrap()
        );
    }
}

#[test]
fn a_lock_file_that_is_a_link_or_a_fifo_is_refused_and_its_target_kept() {
    let w = World::new();
    let d = w.p("locked");
    study(&w, &d);
    std::fs::write(w.p("outside.txt"), "keep me\n").unwrap();
    std::os::unix::fs::symlink(w.p("outside.txt"), d.join(".kfmc.lock")).unwrap();
    for force in [false, true] {
        let (code, err) = output(&mut w.command(Cmd::Run, &d, force));
        assert_eq!(code, 1, "{err}");
        assert!(err.contains(".kfmc.lock is a symbolic link"), "{err}");
    }
    assert_eq!(
        std::fs::read_to_string(w.p("outside.txt")).unwrap(),
        "keep me\n"
    );
    std::fs::remove_file(d.join(".kfmc.lock")).unwrap();
    assert!(
        Command::new("mkfifo")
            .arg(d.join(".kfmc.lock"))
            .status()
            .unwrap()
            .success()
    );
    let mut child = w
        .command(Cmd::Run, &d, false)
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let started = Instant::now();
    while child.try_wait().unwrap().is_none() {
        if started.elapsed() > Duration::from_secs(30) {
            let _ = child.kill();
            panic!("kfmc waits on a FIFO planted as .kfmc.lock");
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    let o = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains(".kfmc.lock is a FIFO"), "{err}");
}

#[test]
fn a_checkpoint_link_is_refused_and_nothing_is_journaled_through_it() {
    let w = World::new();
    let d = w.p("d");
    std::fs::create_dir_all(&d).unwrap();
    std::fs::create_dir_all(w.p("elsewhere")).unwrap();
    std::os::unix::fs::symlink(w.p("elsewhere"), d.join(".checkpoint")).unwrap();
    for force in [false, true] {
        let (code, err) = output(&mut w.command(Cmd::Run, &d, force));
        assert_eq!(code, 1, "{err}");
        assert!(err.contains(".checkpoint is a symbolic link"), "{err}");
    }
    assert_eq!(std::fs::read_dir(w.p("elsewhere")).unwrap().count(), 0);
}

#[test]
fn a_manifest_of_an_earlier_kfmc_is_trusted_only_when_its_tables_match_and_is_then_upgraded() {
    let w = World::new();
    let d = w.p("legacy");
    study(&w, &d);
    edit_manifest(&d, "format", None);
    verify(&d).unwrap();
    let mut seeded = w.command(Cmd::Run, &d, false);
    seeded.args(["--seed", "9"]);
    ok(&mut seeded);
    let m = verify(&d).unwrap();
    assert_eq!(m.format.as_deref(), Some("kfmc-result/1"));
    assert_eq!(m.master_seed, 9);
    // One table changed: not trusted, so not replaced; forced, the changed table is kept and
    // named.
    edit_manifest(&d, "format", None);
    std::fs::write(d.join("summary.parquet"), "the user's\n").unwrap();
    let (code, err) = output(&mut w.command(Cmd::Run, &d, false));
    assert_eq!(code, 1, "{err}");
    assert!(
        err.contains("damaged kfmc manifest") && err.contains("summary.parquet does not match"),
        "{err}"
    );
    let (code, err) = output(&mut w.command(Cmd::Run, &d, true));
    assert_eq!(code, 1, "{err}");
    assert!(
        err.contains("summary.parquet has the name of a kfmc table"),
        "{err}"
    );
    assert_eq!(
        std::fs::read_to_string(d.join("summary.parquet")).unwrap(),
        "the user's\n"
    );
}

#[test]
fn a_rerun_removes_the_figures_and_report_it_listed_and_nothing_else() {
    let w = World::new();
    let d = w.p("plotted");
    study(&w, &d);
    ok(&mut w.command(Cmd::Plot, &d, false));
    ok(&mut w.command(Cmd::Report, &d, false));
    ok(&mut w.command(Cmd::Describe, &d, false));
    plant(&d, "figures/my_sketch.png", "mine\n");
    let m = verify(&d).unwrap();
    assert!(
        m.files.iter().any(|f| f.starts_with("figures/")),
        "{:?}",
        m.files
    );
    assert!(m.files.contains(&"report.html".to_string()));
    let figures: Vec<String> = m
        .files
        .iter()
        .filter(|f| f.starts_with("figures/"))
        .cloned()
        .collect();
    let mut seeded = w.command(Cmd::Run, &d, false);
    seeded.args(["--seed", "5"]);
    ok(&mut seeded);
    for f in &figures {
        assert!(
            !d.join(f).exists(),
            "{f}: a stale figure of the earlier study"
        );
    }
    assert!(
        !d.join("report.html").exists(),
        "the earlier study's report"
    );
    assert_eq!(
        std::fs::read_to_string(d.join("figures/my_sketch.png")).unwrap(),
        "mine\n"
    );
    assert!(
        d.join("describe.toml").exists(),
        "the spec's description is kept"
    );
    assert_eq!(verify(&d).unwrap().files, vec!["describe.toml".to_string()]);
    // A figure the manifest does not list is not drawn over.
    plant(&d, &figures[0], "mine too\n");
    let (code, err) = output(&mut w.command(Cmd::Plot, &d, false));
    assert_eq!(code, 1, "{err}");
    assert!(
        err.contains(&format!("{} was not written by kfmc", figures[0])),
        "{err}"
    );
    assert_eq!(
        std::fs::read_to_string(d.join(&figures[0])).unwrap(),
        "mine too\n"
    );
    // A report and a description kfmc did not write are not replaced.
    plant(&d, "report.html", "<p>my notes</p>\n");
    let (code, err) = output(&mut w.command(Cmd::Report, &d, false));
    assert_eq!(code, 1, "{err}");
    assert!(err.contains("report.html was not written by kfmc"), "{err}");
    let mine = w.p("mine");
    plant(&mine, "describe.toml", "my = \"notes\"\n");
    let (code, err) = output(&mut w.command(Cmd::Describe, &mine, false));
    assert_eq!(code, 1, "{err}");
    assert!(
        err.contains("describe.toml was not written by kfmc"),
        "{err}"
    );
    assert_eq!(
        std::fs::read_to_string(mine.join("describe.toml")).unwrap(),
        "my = \"notes\"\n"
    );
}

#[test]
fn a_forced_tune_keeps_the_users_tune_folders() {
    let w = World::new();
    let d = w.p("tuned");
    copy_tree(&w.template("tune"), &d);
    plant(&d, "tune_notes/n.txt", "mine\n");
    let mut again = w.command(Cmd::Tune, &d, true);
    again.args(["--seed", "4"]);
    ok(&mut again);
    assert_eq!(
        std::fs::read_to_string(d.join("tune_notes/n.txt")).unwrap(),
        "mine\n"
    );
    // A folder kfmc did not list where a stage goes is refused before the search runs.
    let fresh = w.p("fresh");
    plant(&fresh, "tune_coarse/mine.txt", "mine\n");
    let (code, err) = output(&mut w.command(Cmd::Tune, &fresh, true));
    assert_eq!(code, 1, "{err}");
    assert!(err.contains("tune_coarse"), "{err}");
    assert_eq!(
        std::fs::read_to_string(fresh.join("tune_coarse/mine.txt")).unwrap(),
        "mine\n"
    );
}

#[test]
fn a_killed_writers_temporary_files_go_and_no_one_elses() {
    let w = World::new();
    let d = w.p("killed");
    study(&w, &d);
    // As a writer killed before its commit leaves the folder: its lock file naming its token,
    // its temporary files; beside them, a user's and another program's.
    let token = "00112233445566aa";
    std::fs::write(
        d.join(".kfmc.lock"),
        format!(
            "host = \"h\"\npid = 1\nstarted_unix_s = 0\ntoken = \"{token}\"\norphans = []\n# end\n"
        ),
    )
    .unwrap();
    plant(
        &d,
        &format!(".kfmc-{token}-3.runs.parquet.partial"),
        "half a table\n",
    );
    plant(
        &d,
        &format!(".kfmc-{token}-4.power-replication.partial/x"),
        "half a study\n",
    );
    plant(
        &d,
        ".kfmc-ffeeddccbbaa9988-1.runs.parquet.partial",
        "not the killed one's\n",
    );
    plant(&d, ".runs.parquet.partial", "the user's\n");
    ok(&mut w.command(Cmd::Run, &d, false));
    assert!(
        !d.join(format!(".kfmc-{token}-3.runs.parquet.partial"))
            .exists()
    );
    assert!(
        !d.join(format!(".kfmc-{token}-4.power-replication.partial"))
            .exists()
    );
    assert!(
        d.join(".kfmc-ffeeddccbbaa9988-1.runs.parquet.partial")
            .exists()
    );
    assert!(d.join(".runs.parquet.partial").exists());
    assert!(!d.join(".kfmc.lock").exists());
}
