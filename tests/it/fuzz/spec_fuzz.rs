//! Fuzzing spec validation on the stable toolchain: the bundled specs, mutated by a seeded
//! PRNG (keys dropped, duplicated, renamed or added; values retyped; numbers set to NaN, ±inf,
//! 0, negative or huge; arrays emptied; names set to unicode or path tricks; the text itself
//! truncated or shuffled), are fed to `kfmc::experiment::parse` in-process.
//!
//! The properties: validation never panics, and every error names the file and a key path
//! that is empty (the TOML does not parse, or the whole file is at fault) or exists in the
//! mutated document — or, for a required key that is absent, whose parent exists.
//!
//! `cargo test --release --test it fuzz::spec_fuzz::` runs 20,000 mutations and replays
//! `tests/fuzz_corpus/`; the long offline run is
//! `KFMC_FUZZ_INPUTS=1000000 cargo test --release --test it fuzz::spec_fuzz:: -- --ignored --nocapture`
//! (`KFMC_FUZZ_SEED` picks another stream, `KFMC_FUZZ_OUT` keeps the failing inputs).

use std::cell::{Cell, RefCell};
use std::panic::{AssertUnwindSafe, catch_unwind};
use std::path::Path;
use std::time::Instant;

use kfmc::system::checker::{key_path_parts, path_key};
use rand::{RngExt, SeedableRng};
use rand_pcg::Pcg64;
use toml::Value;

const FILE: &str = "fuzz.toml";

/// The bundled specs' texts. `fast`: the batch least-squares spec with 4 s instead of 40 s, as
/// its fit (dense in K) would otherwise take most of the CI run's time.
fn bundled(fast: bool) -> Vec<String> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("experiments");
    let mut paths: Vec<_> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "toml"))
        .collect();
    paths.sort();
    paths
        .iter()
        .map(|p| std::fs::read_to_string(p).unwrap())
        .map(|t| {
            if fast && t.contains("mode = \"batch_ls\"") {
                t.replace("duration_s = 40.0", "duration_s = 4.0")
            } else {
                t
            }
        })
        .collect()
}

/// Every key the built-in systems read, so added keys reach the code paths of other kinds.
const KEYS: &[&str] = &[
    "name",
    "description",
    "master_seed",
    "runs",
    "output",
    "trace_runs",
    "kind",
    "sensor",
    "mass_kg",
    "arm_m",
    "inertia_kg_m2",
    "gravity_m_s2",
    "dt_s",
    "process_noise_std",
    "measurement_noise_std",
    "base",
    "x0",
    "duration_s",
    "stages",
    "from_step",
    "thrust_n",
    "ripple",
    "ripple_rad_s",
    "label",
    "q_std",
    "r_std",
    "covariance_update",
    "window",
    "poles",
    "pole_scale",
    "pole_reading",
    "q_scale",
    "r_scale",
    "scales",
    "filter_noise",
    "mode",
    "p0_std",
    "rmse_thresholds",
    "alpha",
    "beta",
    "kappa",
    "whiteness_lags",
    "whiteness_burn_in",
    "subsets",
    "assert",
    "filter",
    "scenario",
    "state",
    "max",
    "test",
    "start",
    "stop",
    "step",
];

/// Every enumerated value, so a mutated string can switch kinds, sensors and modes.
const WORDS: &[&str] = &[
    "planar_quadrotor",
    "linear_quadrotor",
    "ekf",
    "information",
    "sqrt",
    "open_loop",
    "steady_state",
    "pole_placement",
    "running_mean",
    "ukf",
    "ckf",
    "p1",
    "imu",
    "positions",
    "velocities",
    "xy",
    "truth",
    "sampled",
    "batch_ls",
    "nominal",
    "matched",
    "standard",
    "joseph",
    "printed",
    "negated",
    "consistent",
    "white",
    "unbiased",
    "test_passes",
    "rmse_below",
    "basic",
    "horizontal",
    "roll",
    "fall",
    "hover",
    "verdict",
    "innovation_whiteness",
    "nees_time_average",
    "bias_x",
    "bias_q",
    "x",
    "theta",
    "zdot",
    "kf",
];

/// Names that are path tricks, unicode, empty, or only differ from others by a separator.
const HOSTILE: &[&str] = &[
    "",
    " ",
    ".",
    "..",
    "a/b",
    "a\\b",
    "x_y",
    "x/y",
    "../../etc",
    "/tmp/x",
    "C:\\x",
    "名前",
    "θ",
    "🚀",
    "a b",
    "\u{0}",
    "\n",
    "\u{202e}abc",
    "BASIC",
    "Basic",
    "ekf",
    "basic",
];

enum Step {
    Key(String),
    Index(usize),
}

struct Mutator {
    rng: Pcg64,
}

impl Mutator {
    fn pick<'a, T>(&mut self, xs: &'a [T]) -> &'a T {
        &xs[self.rng.random_range(0..xs.len())]
    }

    fn number(&mut self, old: Option<f64>) -> Value {
        let x = old.unwrap_or(1.0);
        match self.rng.random_range(0..20) {
            0 => Value::Float(f64::NAN),
            1 => Value::Float(f64::INFINITY),
            2 => Value::Float(f64::NEG_INFINITY),
            3 => Value::Float(0.0),
            4 => Value::Float(-0.0),
            5 => Value::Float(-x),
            6 => Value::Float(1e300),
            7 => Value::Float(-1e300),
            8 => Value::Float(1e-300),
            9 => Value::Float(5e-324),
            10 => Value::Float(f64::MAX),
            11 => Value::Float(x * 10.0),
            12 => Value::Float(x * 0.1),
            13 => Value::Integer(0),
            14 => Value::Integer(-1),
            15 => Value::Integer(i64::MAX),
            16 => Value::Integer(i64::MIN),
            17 => Value::Integer(self.rng.random_range(1..2000)),
            18 => Value::Float(x + 1.0),
            _ => Value::Integer(x as i64),
        }
    }

    fn string(&mut self) -> Value {
        match self.rng.random_range(0..3) {
            0 => Value::String(self.pick(WORDS).to_string()),
            1 => Value::String(self.pick(HOSTILE).to_string()),
            _ => Value::String("a".repeat(self.rng.random_range(60..400))),
        }
    }

    fn value(&mut self, depth: usize) -> Value {
        match self.rng.random_range(0..10) {
            0..=2 => self.number(None),
            3 | 4 => self.string(),
            5 => Value::Boolean(self.rng.random()),
            6 => Value::Array(vec![]),
            7 => {
                let n = *self.pick(&[1usize, 2, 3, 4, 5, 6, 7]);
                Value::Array((0..n).map(|_| self.number(Some(1.0))).collect())
            }
            8 if depth < 2 => {
                let mut t = toml::Table::new();
                for _ in 0..self.rng.random_range(0..4) {
                    let k = self.pick(KEYS).to_string();
                    let v = self.value(depth + 1);
                    t.insert(k, v);
                }
                Value::Table(t)
            }
            _ => {
                let mut t = toml::Table::new();
                t.insert("start".into(), self.number(Some(0.2)));
                t.insert("stop".into(), self.number(Some(2.0)));
                t.insert("step".into(), self.number(Some(0.2)));
                Value::Table(t)
            }
        }
    }

    fn key(&mut self, k: &str) -> String {
        match self.rng.random_range(0..6) {
            0 => format!("{k}x"),
            1 => k.chars().skip(1).collect(),
            2 => k.to_uppercase(),
            3 => format!("{k}θ"),
            4 => self.pick(KEYS).to_string(),
            _ => format!("_{k}"),
        }
    }

    /// Every node below the root, as a path of steps.
    fn nodes(v: &Value, path: &mut Vec<usize>, out: &mut Vec<Vec<usize>>) {
        let children: Vec<&Value> = match v {
            Value::Table(t) => t.values().collect(),
            Value::Array(a) => a.iter().collect(),
            _ => return,
        };
        for (i, c) in children.into_iter().enumerate() {
            path.push(i);
            out.push(path.clone());
            Self::nodes(c, path, out);
            path.pop();
        }
    }

    fn steps(root: &Value, path: &[usize]) -> Vec<Step> {
        let mut v = root;
        let mut out = Vec::new();
        for &i in path {
            match v {
                Value::Table(t) => {
                    let (k, next) = t.iter().nth(i).unwrap();
                    out.push(Step::Key(k.clone()));
                    v = next;
                }
                Value::Array(a) => {
                    out.push(Step::Index(i));
                    v = &a[i];
                }
                _ => unreachable!(),
            }
        }
        out
    }

    fn node_mut<'a>(root: &'a mut Value, steps: &[Step]) -> &'a mut Value {
        let mut v = root;
        for s in steps {
            v = match (s, v) {
                (Step::Key(k), Value::Table(t)) => t.get_mut(k).unwrap(),
                (Step::Index(i), Value::Array(a)) => &mut a[*i],
                _ => unreachable!(),
            };
        }
        v
    }

    /// One structural or value mutation of the document.
    fn mutate(&mut self, root: &mut Value) {
        let mut all = Vec::new();
        Self::nodes(root, &mut Vec::new(), &mut all);
        if all.is_empty() {
            return;
        }
        let path = self.pick(&all).clone();
        let steps = Self::steps(root, &path);
        let (last, parent_steps) = steps.split_last().unwrap();
        let choice = self.rng.random_range(0..12);
        let node = Self::node_mut(root, &steps);
        match choice {
            // Value-level: numbers, strings, arrays, retyping.
            0 | 1 => {
                let old = match node {
                    Value::Float(f) => Some(*f),
                    Value::Integer(i) => Some(*i as f64),
                    _ => None,
                };
                *node = self.number(old);
            }
            2 => {
                if let Value::String(_) = node {
                    *node = self.string();
                } else {
                    *node = self.value(0);
                }
            }
            3 => *node = self.value(0),
            4 => {
                if let Value::Array(a) = node {
                    a.clear();
                } else {
                    *node = Value::Array(vec![]);
                }
            }
            5 => {
                if let Value::Table(t) = node {
                    let k = self.pick(KEYS).to_string();
                    let v = self.value(0);
                    t.insert(k, v);
                } else if let Value::Array(a) = node
                    && let Some(x) = a.first().cloned()
                {
                    a.push(x);
                }
            }
            6 => {
                if let Value::Array(a) = node {
                    a.truncate(1);
                }
            }
            // Structural: drop, duplicate, rename, move.
            _ => {
                let parent = Self::node_mut(root, parent_steps);
                match (parent, last) {
                    (Value::Table(t), Step::Key(k)) => {
                        let v = t.remove(k).unwrap();
                        match choice {
                            7 | 8 => {}
                            9 => {
                                let nk = self.key(k);
                                t.insert(k.clone(), v.clone());
                                t.insert(nk, v);
                            }
                            _ => {
                                let nk = self.key(k);
                                t.insert(nk, v);
                            }
                        }
                    }
                    (Value::Array(a), Step::Index(i)) => match choice {
                        7 | 8 => {
                            a.remove(*i);
                        }
                        _ => {
                            let x = a[*i].clone();
                            a.insert(*i, x);
                        }
                    },
                    _ => unreachable!(),
                }
            }
        }
    }

    /// One textual mutation: what a person's editor can do to a file.
    fn mutate_text(&mut self, text: &str) -> String {
        let lines: Vec<&str> = text.lines().collect();
        if lines.is_empty() {
            return text.to_string();
        }
        let i = self.rng.random_range(0..lines.len());
        match self.rng.random_range(0..5) {
            0 => {
                let cut = self.rng.random_range(0..=text.len());
                let mut cut = cut;
                while !text.is_char_boundary(cut) {
                    cut -= 1;
                }
                text[..cut].to_string()
            }
            1 => {
                let mut l = lines.clone();
                l.insert(i, lines[i]);
                l.join("\n")
            }
            2 => {
                let mut l = lines.clone();
                l.remove(i);
                l.join("\n")
            }
            3 => {
                let mut l: Vec<String> = lines.iter().map(|s| s.to_string()).collect();
                let c = *self.pick(&['[', ']', '{', '}', '=', '"', '\'', '#', ',', '.', 'θ']);
                let pos = self.rng.random_range(0..=l[i].chars().count());
                let at = l[i].char_indices().nth(pos).map_or(l[i].len(), |(b, _)| b);
                l[i].insert(at, c);
                l.join("\n")
            }
            _ => {
                let j = self.rng.random_range(0..lines.len());
                let mut l = lines.clone();
                l.swap(i, j);
                l.join("\n")
            }
        }
    }

    /// A mutated spec: 1–4 mutations of a bundled one, sometimes a textual one on top.
    fn input(&mut self, specs: &[(String, Value)]) -> String {
        let (text, doc) = self.pick(specs);
        if self.rng.random_range(0..20) == 0 {
            return self.mutate_text(text);
        }
        let mut doc = doc.clone();
        for _ in 0..self.rng.random_range(1..=4) {
            self.mutate(&mut doc);
        }
        let Value::Table(t) = &doc else {
            unreachable!()
        };
        let out = match toml::to_string(t) {
            Ok(s) => s,
            Err(_) => return text.clone(),
        };
        if self.rng.random_range(0..10) == 0 {
            self.mutate_text(&out)
        } else {
            out
        }
    }
}

/// Whether the key path `parts` (as [`key_path_parts`] splits `filters[1].q_std`) names a
/// value of `doc`. The document is read lazily, as the spec's own parser does, so a value
/// the full parser refuses, like an integer out of range, still has its key.
fn resolves(doc: &toml::de::DeTable<'_>, parts: &[(String, Vec<usize>)]) -> bool {
    let mut table = Some(doc);
    for (name, indices) in parts {
        let found = table.and_then(|t| t.iter().find(|(k, _)| &path_key(k.get_ref()) == name));
        let Some((_, v)) = found else {
            return false;
        };
        let mut cur = v.get_ref();
        for &i in indices {
            match cur.get(i) {
                Some(next) => cur = next.get_ref(),
                None => return false,
            }
        }
        table = cur.as_table();
    }
    true
}

/// Why one input breaks a property, if it does.
fn violation(text: &str) -> Option<String> {
    FUZZING.with(|f| f.set(true));
    let result = catch_unwind(AssertUnwindSafe(|| {
        kfmc::experiment::parse(text, Path::new(FILE)).map(|plan| {
            // What `validate` and `run` do next with a plan must not panic either.
            let _ = kfmc::study::check_limits(&plan, false);
            let _ = plan.size();
        })
    }));
    FUZZING.with(|f| f.set(false));
    let errors = match result {
        Err(p) => {
            let msg = LAST_PANIC
                .with(|l| l.borrow_mut().take())
                .unwrap_or_else(|| {
                    p.downcast_ref::<String>()
                        .cloned()
                        .or_else(|| p.downcast_ref::<&str>().map(|s| s.to_string()))
                        .unwrap_or_default()
                });
            return Some(format!("panicked: {msg}"));
        }
        Ok(Ok(())) => return None,
        Ok(Err(e)) => e.0,
    };
    if errors.is_empty() {
        return Some("Err with no error".into());
    }
    let doc = toml::de::DeTable::parse(text).ok();
    for e in errors {
        if e.file != Path::new(FILE) {
            return Some(format!("error names {} not {FILE}: {e}", e.file.display()));
        }
        if e.key_path.is_empty() {
            continue;
        }
        let Some(doc) = &doc else {
            return Some(format!("key path on a document that does not parse: {e}"));
        };
        let doc = doc.get_ref();
        let Some(mut parts) = key_path_parts(&e.key_path) else {
            return Some(format!("malformed key path: {e}"));
        };
        if resolves(doc, &parts) {
            continue;
        }
        // A required key that is absent is named at its own path, below a parent that exists.
        let absent = e.message.contains("missing") || e.message.contains("required");
        if let Some(last) = parts.last_mut()
            && last.1.pop().is_none()
        {
            parts.pop();
        }
        if !(absent && resolves(doc, &parts)) {
            return Some(format!("key path not in the document: {e}"));
        }
    }
    None
}

thread_local! {
    static FUZZING: Cell<bool> = const { Cell::new(false) };
    static LAST_PANIC: RefCell<Option<String>> = const { RefCell::new(None) };
}

/// Keeps the message of a panic inside [`violation`] (with its location) instead of printing
/// thousands of them; the test's own assertions still print.
fn quiet_panics() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        let default = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            if FUZZING.with(|f| f.get()) {
                LAST_PANIC.with(|p| *p.borrow_mut() = Some(info.to_string()));
            } else {
                default(info);
            }
        }));
    });
}

struct Outcome {
    inputs: u64,
    /// Inputs that broke a property (only the first few are kept in `failures`).
    failed: u64,
    failures: Vec<(String, String)>,
}

fn fuzz(seed: u64, inputs: u64, keep: usize, fast: bool) -> Outcome {
    let specs: Vec<(String, Value)> = bundled(fast)
        .into_iter()
        .map(|t| {
            let v = Value::Table(t.parse::<toml::Table>().unwrap());
            (t, v)
        })
        .collect();
    let mut m = Mutator {
        rng: Pcg64::seed_from_u64(seed),
    };
    let (mut failed, mut failures) = (0, Vec::new());
    for _ in 0..inputs {
        let text = m.input(&specs);
        if let Some(why) = violation(&text) {
            failed += 1;
            if failures.len() < keep {
                failures.push((why, text));
            }
        }
    }
    Outcome {
        inputs,
        failed,
        failures,
    }
}

fn report(failures: &[(String, String)]) -> String {
    failures
        .iter()
        .take(5)
        .map(|(why, text)| format!("{why}\n--- input ---\n{text}\n-------------"))
        .collect::<Vec<_>>()
        .join("\n")
}

#[test]
fn mutated_bundled_specs_never_panic_and_name_real_keys() {
    quiet_panics();
    let start = Instant::now();
    let o = fuzz(0x5eed_f022, 20_000, 20, true);
    println!(
        "spec fuzz: {} inputs in {:.1} s",
        o.inputs,
        start.elapsed().as_secs_f64()
    );
    assert!(
        o.failures.is_empty(),
        "{} of {} inputs broke a property; first ones:\n{}",
        o.failed,
        o.inputs,
        report(&o.failures)
    );
}

#[test]
fn the_fuzz_corpus_replays_clean() {
    quiet_panics();
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fuzz_corpus");
    let mut n = 0;
    for e in std::fs::read_dir(&dir).unwrap() {
        let p = e.unwrap().path();
        if p.extension().is_none_or(|e| e != "toml") {
            continue;
        }
        let text = std::fs::read_to_string(&p).unwrap();
        if let Some(why) = violation(&text) {
            panic!("{}: {why}", p.display());
        }
        n += 1;
    }
    assert!(n >= 5, "the corpus holds {n} inputs");
}

/// The long offline run, on every core: `KFMC_FUZZ_INPUTS` inputs (default 1,000,000).
#[test]
#[ignore = "long: run offline with --ignored"]
fn long_fuzz() {
    quiet_panics();
    let total: u64 = std::env::var("KFMC_FUZZ_INPUTS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(1_000_000);
    let seed: u64 = std::env::var("KFMC_FUZZ_SEED")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(1);
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get()) as u64;
    let start = Instant::now();
    let outcomes: Vec<Outcome> = std::thread::scope(|s| {
        let handles: Vec<_> = (0..threads)
            .map(|t| {
                let n = total / threads + u64::from(t < total % threads);
                s.spawn(move || fuzz(seed.wrapping_mul(1_000_003).wrapping_add(t), n, 50, false))
            })
            .collect();
        handles.into_iter().map(|h| h.join().unwrap()).collect()
    });
    let inputs: u64 = outcomes.iter().map(|o| o.inputs).sum();
    let failed: u64 = outcomes.iter().map(|o| o.failed).sum();
    let failures: Vec<(String, String)> = outcomes.into_iter().flat_map(|o| o.failures).collect();
    println!(
        "spec fuzz: {inputs} inputs in {:.1} s on {threads} threads, {failed} failed (first 50 per thread kept)",
        start.elapsed().as_secs_f64(),
    );
    if let Ok(out) = std::env::var("KFMC_FUZZ_OUT") {
        std::fs::create_dir_all(&out).unwrap();
        for (i, (why, text)) in failures.iter().enumerate() {
            let body = format!("# {}\n{text}", why.replace('\n', " "));
            std::fs::write(Path::new(&out).join(format!("fail_{i:04}.toml")), body).unwrap();
        }
    }
    assert!(failures.is_empty(), "{}", report(&failures));
}
