//! `model.kind = "linear"`: a linear-Gaussian system from TOML matrices.
//!
//! L1 written as a generic system reproduces the built-in L1 study byte for byte (continuous
//! and discrete forms); multi-rate groups report on their period; the linear filter family
//! agrees on a system of another size; spec mistakes are errors at their key paths.

use std::path::Path;

use crate::common::{f64s, kfmc, repo, strs};
use kfmc::experiment::{self, Overrides, Plan};
use kfmc::model::Model;
use kfmc::output::table::read;
use kfmc::runner::NullObserver;
use kfmc::study::{ExecOptions, run};
use kfmc::systems::linear::LinearPlan;
use kfmc::systems::linear_quadrotor::model::{ContinuousLinear, Linear, LinearSensor};
use polars::prelude::*;

/// Runs `plan` with `runs` runs (`trace` of them traced) into `out`.
fn run_plan(mut plan: Plan, out: &Path, runs: usize, trace: usize) {
    plan.apply(&Overrides {
        runs: Some(runs),
        master_seed: None,
        output: Some(out.to_path_buf()),
        trace_runs: Some(trace),
    })
    .expect("overrides");
    run(
        &plan,
        &ExecOptions {
            threads: 2,
            ..Default::default()
        },
        &NullObserver,
    )
    .expect("study runs");
}

fn parse(text: &str) -> Plan {
    experiment::parse(text, Path::new("t.toml")).unwrap_or_else(|e| panic!("{e}\n{text}"))
}

fn errors(text: &str) -> Vec<(String, String)> {
    match experiment::parse(text, Path::new("t.toml")) {
        Ok(_) => vec![],
        Err(e) => e.0.into_iter().map(|e| (e.key_path, e.message)).collect(),
    }
}

fn linear<const NX: usize, const NZ: usize>(plan: &Plan) -> &LinearPlan<NX, NZ> {
    plan.system
        .as_any()
        .downcast_ref()
        .expect("a linear plan of these sizes")
}

fn bytes(dir: &Path, table: &str) -> Vec<u8> {
    std::fs::read(dir.join(format!("{table}.parquet")))
        .unwrap_or_else(|e| panic!("{table}.parquet: {e}"))
}

const TABLES: [&str; 5] = ["runs", "steps", "summary", "consistency", "traces"];

/// A matrix as a TOML nested array, each f64 in its shortest round-trip form.
fn toml_matrix<const R: usize, const C: usize>(m: &nalgebra::SMatrix<f64, R, C>) -> String {
    let rows: Vec<String> = (0..R)
        .map(|i| {
            let row: Vec<String> = (0..C).map(|j| format!("{:?}", m[(i, j)])).collect();
            format!("[{}]", row.join(", "))
        })
        .collect();
    format!("[{}]", rows.join(", "))
}

#[test]
fn l1_from_toml_reproduces_linear_nees_byte_for_byte() {
    let tmp = tempfile::tempdir().unwrap();
    let out = |name: &str| tmp.path().join(name);
    let builtin = experiment::load(&repo().join("experiments/linear_nees.toml")).unwrap();
    let generic = experiment::load(&repo().join("experiments/linear_generic_l1.toml")).unwrap();
    assert_eq!(generic.kind, "linear");

    // The same discretisation code gives the same matrices, bit for bit.
    let l1 = Linear::<3>::new(LinearSensor::Positions, 0.1).unwrap();
    let m = &linear::<6, 3>(&generic).additive.model;
    assert_eq!(m.f(), &l1.discrete().f);
    assert_eq!(m.g(), &l1.discrete().g);
    assert_eq!(m.q(), &l1.discrete().q);
    assert_eq!(m.h(), l1.h());
    assert_eq!(m.process_noise_covariance(), Some(l1.discrete().q));

    // The discrete form, given F, G, Q of the continuous one in round-trip decimals.
    let d = ContinuousLinear::seed().discretise(0.1);
    let text = std::fs::read_to_string(repo().join("experiments/linear_generic_l1.toml")).unwrap();
    let start = text.find("\na = [").unwrap();
    let end = text.find("\nr = [").unwrap();
    let discrete = format!(
        "{}\nf = {}\ng = {}\nh = {}\nq = {}{}",
        &text[..start],
        toml_matrix(&d.f),
        toml_matrix(&d.g),
        toml_matrix(l1.h()),
        toml_matrix(&d.q),
        &text[end..]
    );
    let discrete = experiment::parse(&discrete, &repo().join("experiments/x.toml")).unwrap();

    run_plan(builtin, &out("builtin"), 20, 2);
    run_plan(generic, &out("generic"), 20, 2);
    run_plan(discrete, &out("discrete"), 20, 2);
    for table in TABLES {
        let reference = bytes(&out("builtin"), table);
        assert_eq!(
            reference,
            bytes(&out("generic"), table),
            "{table}.parquet: continuous form differs from linear_quadrotor"
        );
        assert_eq!(
            reference,
            bytes(&out("discrete"), table),
            "{table}.parquet: discrete form differs from linear_quadrotor"
        );
    }
}

/// A 2-D constant-velocity target; `EXTRA` is replaced by more `[model]` keys or tables.
const CV: &str = r#"
name = "cv"
master_seed = 5
runs = 40
[model]
kind = "linear"
states = ["px", "vx", "py", "vy"]
measurements = ["px", "py", "vx", "vy"]
dt_s = 0.1
a = [[0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0], [0.0, 0.0, 0.0, 0.0]]
c = [[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
gamma = [[0.0, 0.0], [1.0, 0.0], [0.0, 0.0], [0.0, 1.0]]
q_tilde = [[0.05, 0.0], [0.0, 0.05]]
r = [[4.0, 0.0, 0.0, 0.0], [0.0, 4.0, 0.0, 0.0], [0.0, 0.0, 0.09, 0.0], [0.0, 0.0, 0.0, 0.09]]
EXTRA
[[scenarios]]
name = "straight"
x0 = [0.0, 10.0, 0.0, 0.0]
duration_s = 20.0
[[filters]]
label = "kf"
kind = "ekf"
[initial_estimate]
mode = "sampled"
p0_std = [2.0, 1.0, 2.0, 1.0]
"#;

/// A component that did not report: null (or NaN) in the traces.
fn missing(v: Option<f64>) -> bool {
    v.is_none_or(f64::is_nan)
}

fn steps(df: &DataFrame) -> Vec<i64> {
    let c = df.column("step").unwrap().i64().unwrap().clone();
    (0..c.len()).map(|i| c.get(i).unwrap()).collect()
}

#[test]
fn a_sensor_group_reports_only_every_n_steps() {
    let group = "[[model.sensor_groups]]\ncomponents = [\"px\", \"py\"]\nperiod_steps = 5\n";
    let plan = parse(&CV.replace("EXTRA", group));
    let m = &linear::<4, 4>(&plan).additive.model;
    for k in 0..=200 {
        let a = m.availability(k);
        assert_eq!(a.count(), if k % 5 == 0 { 4 } else { 2 }, "step {k}");
        assert!(a.has(2) && a.has(3), "the velocities report at every step");
    }
    // rate_hz = 2 at Δt = 0.1 s is the same schedule.
    let by_rate = parse(&CV.replace("EXTRA", &group.replace("period_steps = 5", "rate_hz = 2.0")));
    assert_eq!(linear::<4, 4>(&by_rate).additive.model.groups(), m.groups());

    let tmp = tempfile::tempdir().unwrap();
    run_plan(plan, tmp.path(), 40, 1);
    // The traces: z_px is missing (NaN) between fixes, z_vx never.
    let tr = read(&tmp.path().join("traces.parquet")).unwrap();
    let step = steps(&tr);
    let (zpx, zvx) = (f64s(&tr, "z_px"), f64s(&tr, "z_vx"));
    assert_eq!(step.len(), 201);
    for (i, k) in step.iter().enumerate() {
        assert_eq!(missing(zpx[i]), k % 5 != 0, "z_px at step {k}");
        assert!(!missing(zvx[i]), "z_vx at step {k}");
    }
    // The steps table: the NIS has 4 degrees of freedom at a fix and 2 between, so the ANIS
    // (a consistent KF) and its χ² band sit at 4 and at 2.
    let st = read(&tmp.path().join("steps.parquet")).unwrap();
    let (anis, lo, hi) = (
        f64s(&st, "anis"),
        f64s(&st, "anis_lo"),
        f64s(&st, "anis_hi"),
    );
    let mean = |fix: bool| {
        let v: Vec<f64> = (1..=200)
            .filter(|k| (k % 5 == 0) == fix)
            .map(|k| anis[k].unwrap())
            .collect();
        v.iter().sum::<f64>() / v.len() as f64
    };
    assert!(
        (mean(true) - 4.0).abs() < 0.3,
        "ANIS at fixes {}",
        mean(true)
    );
    assert!(
        (mean(false) - 2.0).abs() < 0.15,
        "ANIS between {}",
        mean(false)
    );
    for k in 1..=200 {
        let dof = if k % 5 == 0 { 4.0 } else { 2.0 };
        let (l, h) = (lo[k].unwrap(), hi[k].unwrap());
        assert!(
            l < dof && dof < h && h < dof + 2.0,
            "band at step {k}: [{l}, {h}]"
        );
    }
}

/// A 1-D constant-acceleration model in the discrete form: [p, v, a], a jerk input (padded to
/// the compiled input size), position and acceleration sensors, the position at a third of the
/// rate, and a full Q.
fn ca_spec(out: &Path, filters: &str) -> String {
    let dt: f64 = 0.5;
    let s = 0.1;
    let f = format!(
        "[[1.0, {dt:?}, {:?}], [0.0, 1.0, {dt:?}], [0.0, 0.0, 1.0]]",
        dt * dt / 2.0
    );
    let g = format!(
        "[[{:?}], [{:?}], [{dt:?}]]",
        dt.powi(3) / 6.0,
        dt * dt / 2.0
    );
    let q = [
        [dt.powi(5) / 20.0, dt.powi(4) / 8.0, dt.powi(3) / 6.0],
        [dt.powi(4) / 8.0, dt.powi(3) / 3.0, dt * dt / 2.0],
        [dt.powi(3) / 6.0, dt * dt / 2.0, dt],
    ]
    .map(|row| {
        let r: Vec<String> = row.iter().map(|v| format!("{:?}", v * s)).collect();
        format!("[{}]", r.join(", "))
    })
    .join(", ");
    format!(
        r#"
name = "ca"
master_seed = 9
runs = 30
trace_runs = 3
output = "{out}"
[model]
kind = "linear"
states = ["p", "v", "a"]
state_units = ["m", "m/s", "m/s2"]
inputs = ["jerk"]
measurements = ["p", "acc"]
dt_s = {dt:?}
f = {f}
g = {g}
h = [[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
q = [{q}]
r = [[0.5, 0.0], [0.0, 0.02]]
[[model.sensor_groups]]
components = ["p"]
period_steps = 3
[[scenarios]]
name = "push"
x0 = [0.0, 1.0, 0.0]
duration_s = 50.0
stages = [{{ from_step = 0, u = [0.0] }}, {{ from_step = 20, u = [0.3] }}, {{ from_step = 30, u = [-0.3] }}, {{ from_step = 40, u = [0.0] }}]
{filters}
[initial_estimate]
mode = "sampled"
p0_std = [1.0, 0.5, 0.2]
"#,
        out = out.display()
    )
}

const FAMILY: &str = r#"
[[filters]]
label = "kf"
kind = "ekf"
[[filters]]
label = "joseph"
kind = "ekf"
covariance_update = "joseph"
[[filters]]
label = "information"
kind = "information"
[[filters]]
label = "sqrt"
kind = "sqrt"
"#;

#[test]
fn kf_information_and_sqrt_agree_on_a_three_state_system() {
    let tmp = tempfile::tempdir().unwrap();
    let (_d, path) = crate::common::spec_in_tempdir(&ca_spec(tmp.path(), FAMILY));
    let plan = experiment::load(&path).expect("valid spec");
    let sys = linear::<3, 2>(&plan);
    assert!(sys.additive.model.process_noise_covariance().is_some());
    let out = plan.output.clone();
    run(
        &plan,
        &ExecOptions {
            threads: 2,
            ..Default::default()
        },
        &NullObserver,
    )
    .unwrap();

    let tr = read(&out.join("traces.parquet")).unwrap();
    let label = strs(&tr, "filter");
    // Every estimate and covariance entry of the four forms agrees to round-off.
    let cols: Vec<String> = tr
        .get_column_names()
        .into_iter()
        .map(|c| c.to_string())
        .filter(|c| c.starts_with("est_") || c.starts_with("P_"))
        .collect();
    assert_eq!(cols.len(), 3 + 6);
    let rows_of = |l: &str| -> Vec<usize> { (0..label.len()).filter(|&i| label[i] == l).collect() };
    let kf = rows_of("kf");
    assert_eq!(kf.len(), 3 * 101);
    let mut worst = 0.0f64;
    for other in ["joseph", "information", "sqrt"] {
        let rows = rows_of(other);
        assert_eq!(rows.len(), kf.len());
        for c in &cols {
            let v = f64s(&tr, c);
            for (&a, &b) in kf.iter().zip(&rows) {
                let (a, b) = (v[a].unwrap(), v[b].unwrap());
                let d = (a - b).abs() / a.abs().max(1.0);
                worst = worst.max(d);
                assert!(d < 1e-9, "{other} {c}: {a} vs {b}");
            }
        }
    }
    println!("largest relative difference from kf: {worst:.1e}");

    // The traces carry the real input only, with the stage values.
    let u = f64s(&tr, "u_jerk");
    let step = steps(&tr);
    for i in kf.iter().take(101) {
        let expected = match step[*i] {
            20..=29 => 0.3,
            30..=39 => -0.3,
            _ => 0.0,
        };
        assert_eq!(u[*i], Some(expected), "u at step {}", step[*i]);
    }
    assert!(
        !tr.get_column_names()
            .iter()
            .any(|c| c.as_str().starts_with("u_") && c.as_str() != "u_jerk")
    );
    // The position reports every third step.
    let zp = f64s(&tr, "z_p");
    for i in kf.iter().take(101) {
        assert_eq!(missing(zp[*i]), step[*i] % 3 != 0);
    }
    // And every run of every form completed.
    let runs = read(&out.join("runs.parquet")).unwrap();
    assert!(strs(&runs, "status").iter().all(|s| s == "ok"));
}

#[test]
fn fixed_gain_kinds_and_batch_ls_work_on_a_generic_system() {
    let tmp = tempfile::tempdir().unwrap();
    let fixed = r#"
[[filters]]
label = "kf"
kind = "ekf"
[[filters]]
label = "steady_state"
kind = "steady_state"
[[filters]]
label = "placed"
kind = "pole_placement"
poles = [[0.6], [0.6], [0.5, 0.1], [0.5, -0.1]]
[[filters]]
label = "open_loop"
kind = "open_loop"
"#;
    let plan = parse(
        &CV.replace("EXTRA", "")
            .replace("[[filters]]\nlabel = \"kf\"\nkind = \"ekf\"\n", fixed),
    );
    run_plan(plan, &tmp.path().join("fixed"), 10, 0);
    let runs = read(&tmp.path().join("fixed/runs.parquet")).unwrap();
    assert!(strs(&runs, "status").iter().all(|s| s == "ok"));

    let batch = CV.replace("EXTRA", "").replace(
        "mode = \"sampled\"\np0_std = [2.0, 1.0, 2.0, 1.0]",
        "mode = \"batch_ls\"",
    );
    let plan = parse(&batch);
    assert!(linear::<4, 4>(&plan).additive.batch.is_some());
    run_plan(plan, &tmp.path().join("batch"), 10, 0);
    let runs = read(&tmp.path().join("batch/runs.parquet")).unwrap();
    assert!(
        f64s(&runs, "nees_mean")
            .iter()
            .all(|v| v.unwrap().is_finite())
    );
}

/// A 2-state discrete spec; `MODEL` is replaced by more `[model]` keys.
const DISCRETE: &str = r#"
[model]
kind = "linear"
states = ["p", "v"]
inputs = ["acc"]
measurements = ["p"]
dt_s = 0.1
f = [[1.0, 0.1], [0.0, 1.0]]
g = [[0.005], [0.1]]
h = [[1.0, 0.0]]
q = [[0.001, 0.0], [0.0, 0.01]]
r = [[0.25]]
MODEL
[[scenarios]]
name = "s"
duration_s = 5.0
[[filters]]
label = "f"
kind = "ekf"
"#;

fn first_error(text: &str) -> (String, String) {
    let e = errors(text);
    assert!(!e.is_empty(), "no error for:\n{text}");
    e[0].clone()
}

#[test]
fn linear_spec_errors_name_their_key() {
    let base = DISCRETE.replace("MODEL", "");
    assert!(errors(&base).is_empty());
    let case = |old: &str, new: &str| first_error(&base.replace(old, new));

    // Shapes: rows, then columns, each with the expected count.
    let (k, m) = case("f = [[1.0, 0.1], [0.0, 1.0]]", "f = [[1.0, 0.1]]");
    assert_eq!(k, "model.f");
    assert!(m.contains("expected 2 rows"), "{m}");
    let (k, m) = case("f = [[1.0, 0.1], [0.0, 1.0]]", "f = [[1.0, 0.1], [0.0]]");
    assert_eq!(k, "model.f[1]");
    assert!(m.contains("expected 2 columns"), "{m}");
    assert_eq!(
        case("g = [[0.005], [0.1]]", "g = [[0.005, 1.0], [0.1, 1.0]]").0,
        "model.g[0]"
    );
    assert_eq!(
        case("h = [[1.0, 0.0]]", "h = [[1.0, 0.0], [0.0, 1.0]]").0,
        "model.h"
    );
    assert_eq!(case("r = [[0.25]]", "r = [[0.25, 0.0]]").0, "model.r[0]");
    // A flat list where a matrix belongs is a type error at the element, with its line.
    let (k, m) = case("h = [[1.0, 0.0]]", "h = [1.0, 0.0]");
    assert_eq!(k, "model.h[0]");
    assert!(m.contains("line"), "{m}");
    assert_eq!(
        case("f = [[1.0, 0.1]", "f = [[1.0, nan]").0,
        "model.f[0][1]"
    );

    // Q: symmetric, positive semidefinite; a singular Q only when diagonal.
    let (k, m) = case(
        "q = [[0.001, 0.0], [0.0, 0.01]]",
        "q = [[0.001, 0.0], [0.0002, 0.01]]",
    );
    assert_eq!(k, "model.q[1][0]");
    assert!(m.contains("symmetric") && m.contains("q[0][1] = 0"), "{m}");
    let (k, m) = case(
        "q = [[0.001, 0.0], [0.0, 0.01]]",
        "q = [[0.001, 0.0], [0.0, -0.01]]",
    );
    assert_eq!(k, "model.q");
    assert!(m.contains("positive semidefinite"), "{m}");
    let (k, m) = case(
        "q = [[0.001, 0.0], [0.0, 0.01]]",
        "q = [[1.0, 2.0], [2.0, 4.0]]",
    );
    assert_eq!(k, "model.q");
    assert!(m.contains("singular"), "{m}");
    let zero_p = base.replace(
        "q = [[0.001, 0.0], [0.0, 0.01]]",
        "q = [[0.0, 0.0], [0.0, 0.01]]",
    );
    assert!(errors(&zero_p).is_empty(), "a diagonal Q may have zeros");
    // With a full Q the filters assume it, so q_std is refused; a diagonal singular Q takes it.
    let q_std = |t: &str| t.replace("kind = \"ekf\"", "kind = \"ekf\"\nq_std = [0.1, 0.1]");
    assert_eq!(first_error(&q_std(&base)).0, "filters[0].q_std");
    assert!(errors(&q_std(&zero_p)).is_empty());

    // R: diagonal and positive.
    let two = base
        .replace("measurements = [\"p\"]", "measurements = [\"p\", \"v\"]")
        .replace("h = [[1.0, 0.0]]", "h = [[1.0, 0.0], [0.0, 1.0]]");
    let r = |v: &str| first_error(&two.replace("r = [[0.25]]", v));
    assert_eq!(r("r = [[0.25, 0.01], [0.01, 0.1]]").0, "model.r[0][1]");
    assert_eq!(r("r = [[0.25, 0.0], [0.0, 0.0]]").0, "model.r[1][1]");

    // Keys: unknown ones (with the line), both forms at once, missing ones.
    let (k, m) = first_error(&DISCRETE.replace("MODEL", "mass_kg = 1.0"));
    assert_eq!(k, "model.mass_kg");
    assert!(m.contains("unknown field") && m.contains("line 13"), "{m}");
    assert_eq!(
        first_error(&DISCRETE.replace("MODEL", "a = [[0.0, 1.0], [0.0, 0.0]]")).0,
        "model.a"
    );
    assert_eq!(case("h = [[1.0, 0.0]]\n", "").0, "model.h");
    assert_eq!(case("g = [[0.005], [0.1]]\n", "").0, "model.g");
    assert_eq!(case("dt_s = 0.1", "dt_s = -0.1").0, "model.dt_s");
    assert_eq!(
        case("inputs = [\"acc\"]\n", "").0,
        "model.g",
        "g without inputs"
    );
    assert_eq!(
        case("states = [\"p\", \"v\"]", "states = [\"p\", \"p\"]").0,
        "model.states[1]"
    );
    assert_eq!(
        case("states = [\"p\", \"v\"]", "states = [\"p\", \"v w\"]").0,
        "model.states[1]"
    );
    assert_eq!(
        first_error(&DISCRETE.replace("MODEL", "state_units = [\"m\"]")).0,
        "model.state_units"
    );

    // Position roles: state names in axis order, 2 or 3 of them, in a known frame.
    let pos = |keys: &str| first_error(&DISCRETE.replace("MODEL", keys));
    assert!(errors(&DISCRETE.replace("MODEL", "positions = [\"p\", \"v\"]")).is_empty());
    let (k, m) = pos("positions = [\"p\", \"w\"]");
    assert_eq!(k, "model.positions[1]");
    assert!(m.contains("unknown state `w`") && m.contains("p, v"), "{m}");
    assert_eq!(pos("positions = [\"p\", \"p\"]").0, "model.positions[1]");
    let (k, m) = pos("positions = [\"p\"]");
    assert_eq!(k, "model.positions");
    assert!(m.contains("2 or 3"), "{m}");
    let (k, m) = pos("positions = [\"p\", \"v\"]\nposition_frame = \"enu\"");
    assert_eq!(k, "model.position_frame");
    assert!(m.contains("xyz, ned"), "{m}");
    assert_eq!(
        pos("position_frame = \"ned\"").0,
        "model.position_frame",
        "a frame without positions"
    );

    // Sizes that are not compiled, named by the key that sets them.
    let five = base.replace(
        "states = [\"p\", \"v\"]",
        "states = [\"a\", \"b\", \"c\", \"d\", \"e\"]",
    );
    let (k, m) = first_error(&five);
    assert_eq!(k, "model.states");
    assert!(
        m.contains("compiled") && m.contains("6 states: 2/3/4/6"),
        "{m}"
    );
    let four = base.replace(
        "states = [\"p\", \"v\"]",
        "states = [\"a\", \"b\", \"c\", \"d\"]",
    );
    assert_eq!(first_error(&four).0, "model.measurements");

    // Sensor groups.
    let group = |g: &str| first_error(&DISCRETE.replace("MODEL", g));
    assert_eq!(
        group("[[model.sensor_groups]]\ncomponents = [\"p\", \"q\"]\nperiod_steps = 2").0,
        "model.sensor_groups[0].components[1]"
    );
    assert_eq!(
        group("[[model.sensor_groups]]\ncomponents = [\"p\"]\nrate_hz = 3.0").0,
        "model.sensor_groups[0].rate_hz"
    );
    assert_eq!(
        group("[[model.sensor_groups]]\ncomponents = [\"p\"]\nperiod_steps = 0").0,
        "model.sensor_groups[0].period_steps"
    );
    assert_eq!(
        group("[[model.sensor_groups]]\ncomponents = [\"p\"]\nperiod_steps = 2\nrate_hz = 5.0").0,
        "model.sensor_groups[0].rate_hz"
    );
    assert_eq!(
        group("[[model.sensor_groups]]\ncomponents = [\"p\"]").0,
        "model.sensor_groups[0]"
    );
    assert_eq!(
        group("[[model.sensor_groups]]\ncomponents = [\"p\"]\nperiod_steps = 2\n[[model.sensor_groups]]\ncomponents = [\"p\"]\nperiod_steps = 3").0,
        "model.sensor_groups[1].components[0]"
    );

    // Scenarios: x0 size, required duration, stages.
    let sc = |old: &str, new: &str| first_error(&base.replace(old, new));
    assert_eq!(
        sc("duration_s = 5.0", "duration_s = 5.0\nx0 = [1.0]").0,
        "scenarios[0].x0"
    );
    assert_eq!(sc("duration_s = 5.0\n", "").0, "scenarios[0].duration_s");
    assert_eq!(
        sc(
            "duration_s = 5.0",
            "duration_s = 5.0\nstages = [{ from_step = 0, u = [1.0] }, { from_step = 5, u = [1.0, 2.0] }]"
        )
        .0,
        "scenarios[0].stages[1].u"
    );
    assert_eq!(
        sc(
            "duration_s = 5.0",
            "duration_s = 5.0\nstages = [{ from_step = 3, u = [1.0] }]"
        )
        .0,
        "scenarios[0].stages[0].from_step"
    );
    assert_eq!(
        sc("duration_s = 5.0", "duration_s = 5.0\nspeed = 3").0,
        "scenarios[0].speed"
    );
    assert_eq!(
        first_error(&format!(
            "{base}[initial_estimate]\np0_std = [1.0, 2.0, 3.0]\n"
        ))
        .0,
        "initial_estimate.p0_std"
    );
}

#[test]
fn the_fixed_gain_kinds_need_a_detectable_or_observable_model() {
    let base = DISCRETE.replace("MODEL", "");
    let kind = |t: &str, k: &str| t.replace("kind = \"ekf\"", &format!("kind = \"{k}\""));
    assert!(errors(&kind(&base, "steady_state")).is_empty());
    // Velocity only: the position is an unobserved integrator; no steady state, no x0 by
    // batch least squares.
    let velocity = base.replace("h = [[1.0, 0.0]]", "h = [[0.0, 1.0]]");
    let (k, m) = first_error(&kind(&velocity, "steady_state"));
    assert_eq!(k, "filters[0].kind");
    assert!(m.contains("rank is 1 of 2") && m.contains("1.0000"), "{m}");
    let (k, m) = first_error(&kind(&velocity, "pole_placement").replace(
        "kind = \"pole_placement\"",
        "kind = \"pole_placement\"\npoles = [[0.5], [0.4]]",
    ));
    assert_eq!(k, "filters[0].kind");
    assert!(m.starts_with("pole_placement needs"), "{m}");
    let (k, m) = first_error(&format!(
        "{velocity}[initial_estimate]\nmode = \"batch_ls\"\n"
    ));
    assert_eq!(k, "initial_estimate.mode");
    assert!(m.contains("rank 1 of 2"), "{m}");
    // An unobserved mode that decays is detectable: the steady state exists, but poles
    // cannot be placed.
    let decaying = base
        .replace(
            "f = [[1.0, 0.1], [0.0, 1.0]]",
            "f = [[1.0, 0.0], [0.0, 0.5]]",
        )
        .replace("inputs = [\"acc\"]\n", "")
        .replace("g = [[0.005], [0.1]]\n", "");
    assert!(errors(&kind(&decaying, "steady_state")).is_empty());
    let placed = kind(&decaying, "pole_placement").replace(
        "kind = \"pole_placement\"",
        "kind = \"pole_placement\"\npoles = [[0.5], [0.4]]",
    );
    assert_eq!(first_error(&placed).0, "filters[0].poles");
    // The seed's pole list is for six states; the error is at the key the spec has.
    let seed_list = kind(&base, "pole_placement").replace(
        "kind = \"pole_placement\"",
        "kind = \"pole_placement\"\npole_scale = 0.5",
    );
    assert_eq!(first_error(&seed_list).0, "filters[0].pole_scale");
}

#[test]
fn shipped_linear_specs_load_and_list_shows_the_system() {
    let l1 = experiment::load(&repo().join("experiments/linear_generic_l1.toml")).unwrap();
    assert_eq!(l1.layout().inputs, ["t1", "t2", "t3", "t4"]);
    assert_eq!(l1.quantity_names(), ["x", "xdot", "y", "ydot", "z", "zdot"]);
    assert_eq!(l1.layout().quantities[1].unit, "m/s");
    let cv = experiment::load(&repo().join("experiments/linear_cv_target.toml")).unwrap();
    let sys = linear::<4, 4>(&cv);
    assert_eq!(sys.inputs, 2);
    assert_eq!(sys.additive.model.groups()[0].period, 10);
    assert_eq!(cv.scenarios[0].steps, 600);
    let u = &sys.additive.scenarios[0].controls;
    assert_eq!(
        (u[199][1], u[200][1], u[299][1], u[300][1]),
        (0.0, 1.0, 1.0, 0.0)
    );
    assert!(
        u.iter().all(|u| u[2] == 0.0 && u[3] == 0.0),
        "padding is zero"
    );

    let registry = kfmc::systems::builtin();
    let cat = registry.get("linear").expect("registered").catalogue();
    let text = format!("{cat:?}");
    for word in [
        "q_tilde",
        "sensor_groups",
        "stages",
        "steady_state",
        "batch_ls",
    ] {
        assert!(text.contains(word), "catalogue lacks {word}");
    }
    let o = kfmc().arg("list").output().expect("kfmc runs");
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success());
    assert!(out.contains("\nlinear — linear-Gaussian system"), "{out}");
    assert!(
        out.contains("sizes (states: measurement components)"),
        "{out}"
    );
}

/// The position roles only say how results are shown: the world stamp (which ties estimates
/// to a study's runs) is the same with and without them, and still changes with the model.
#[test]
fn position_roles_leave_the_world_stamp_alone() {
    let path = repo().join("experiments/linear_cv_target.toml");
    let text = std::fs::read_to_string(&path).unwrap();
    let stamp = |t: &str| experiment::parse(t, &path).unwrap().world_stamp();
    let with_roles = stamp(&text);
    let line = text
        .lines()
        .find(|l| l.starts_with("positions ="))
        .expect("the spec declares its positions");
    let without = text.replace(&format!("{line}\n"), "");
    assert_ne!(without, text);
    assert_eq!(stamp(&without), with_roles);
    let framed = text.replace(line, &format!("{line}\nposition_frame = \"xyz\""));
    assert_eq!(stamp(&framed), with_roles);
    // A key of the world does change it.
    let other = text.replace("dt_s = ", "dt_s = 0.5 #");
    assert_ne!(other, text);
    assert_ne!(stamp(&other), with_roles);
}
