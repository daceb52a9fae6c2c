//! The L1 model in the spec: defaults, and errors reported at their key paths.

use std::path::Path;

use kfmc::experiment::{self, Plan};
use kfmc::system::additive::AdditivePlan;
use kfmc::systems::linear_quadrotor::model::{Linear, LinearSensor};

/// The configured L1 system behind a plan (three measurement components).
fn l1(plan: &Plan) -> &AdditivePlan<6, 4, 3, Linear<3>> {
    plan.system
        .as_any()
        .downcast_ref()
        .expect("an L1 plan with 3 components")
}

fn errors(text: &str) -> Vec<(String, String)> {
    match experiment::parse(text, Path::new("t.toml")) {
        Ok(_) => vec![],
        Err(e) => e.0.into_iter().map(|e| (e.key_path, e.message)).collect(),
    }
}

const BASE: &str = r#"
[model]
kind = "linear_quadrotor"
sensor = "SENSOR"

[[scenarios]]
name = "hover"

[[filters]]
label = "f"
kind = "FILTER"
"#;

fn spec(sensor: &str, filter: &str) -> String {
    BASE.replace("SENSOR", sensor).replace("FILTER", filter)
}

#[test]
fn shipped_linear_nees_spec_holds_the_seeds_three_tests() {
    let plan = experiment::load(
        &Path::new(env!("CARGO_MANIFEST_DIR")).join("experiments/linear_nees.toml"),
    )
    .expect("valid spec");
    assert_eq!(plan.kind, "linear_quadrotor");
    assert_eq!(l1(&plan).model.sensor(), LinearSensor::Positions);
    assert_eq!(plan.runs, 200);
    assert_eq!(plan.dt_s(), 0.1);
    let c = plan.consistency.as_ref().unwrap();
    assert_eq!(c.alpha, 0.003);
    assert_eq!(c.subsets, [(50, 0.05), (100, 0.01)]);
    let labels: Vec<_> = plan.filters.iter().map(|f| f.label.as_str()).collect();
    assert_eq!(labels, ["kf", "information", "sqrt", "steady_state"]);
    assert_eq!(plan.filters[1].kind, "information");
    assert_eq!(plan.filters[2].kind, "sqrt");
}

#[test]
fn linear_defaults_are_the_seeds() {
    let plan = experiment::parse(&spec("xy", "sqrt"), Path::new("t.toml")).unwrap();
    let sys: &AdditivePlan<6, 4, 2, Linear<2>> =
        plan.system.as_any().downcast_ref().expect("an xy plan");
    assert_eq!(sys.model.sensor(), LinearSensor::Xy);
    assert_eq!(plan.layout().measurements.len(), 2);
    assert_eq!(
        sys.scenarios[0].x0.as_slice(),
        [1.0, 0.0, 1.0, 0.0, 1.0, 0.0]
    );
    assert_eq!(plan.scenarios[0].steps, 400);
    let r: Vec<f64> = sys.entries[0]
        .assumed_std()
        .1
        .iter()
        .map(|s| s * s)
        .collect();
    assert!((r[0] - 0.0933).abs() < 1e-15 && (r[1] - 0.0885).abs() < 1e-15);
    assert_eq!(plan.quantity_names()[5], "zdot");
}

#[test]
fn linear_spec_errors_name_their_key() {
    let e = errors(&spec("imu", "ekf"));
    assert_eq!(e[0].0, "model.sensor", "{e:?}");
    let e = errors(&spec("xy", "steady_state"));
    assert_eq!(e[0].0, "filters[0].kind", "{e:?}");
    assert!(errors(&spec("positions", "steady_state")).is_empty());
    let e =
        errors(&spec("positions", "ekf").replace("kind = \"ekf\"", "kind = \"ekf\"\nq_std = 0.1"));
    assert_eq!(e[0].0, "filters[0].q_std", "{e:?}");
    let e = errors(&spec("positions", "ekf").replace(
        "sensor = \"positions\"",
        "sensor = \"positions\"\nmass_kg = 1.0",
    ));
    assert_eq!(e[0].0, "model.mass_kg", "{e:?}");
    let e = errors(
        &spec("positions", "ekf").replace("name = \"hover\"", "name = \"hover\"\nx0 = [1.0, 2.0]"),
    );
    assert_eq!(e[0].0, "scenarios[0].x0", "{e:?}");
    // steady_state on the planar model is rejected too.
    let planar = "[model]\nkind = \"planar_quadrotor\"\n[[scenarios]]\nname = \"basic\"\n[[filters]]\nlabel = \"f\"\nkind = \"steady_state\"\n";
    assert_eq!(errors(planar)[0].0, "filters[0].kind");
}

#[test]
fn new_linear_keys_report_errors_at_their_key_paths() {
    let pos = |extra: &str| spec("positions", "ekf") + extra;
    let first = |text: &str| {
        let e = errors(text);
        assert!(!e.is_empty(), "no error for:\n{text}");
        e[0].0.clone()
    };
    // Batch least squares needs an observable sensor set and makes its own P0.
    let batch = "[initial_estimate]\nmode = \"batch_ls\"\n";
    assert!(errors(&pos(batch)).is_empty());
    let e = errors(&(spec("xy", "ekf") + batch));
    assert_eq!(e[0].0, "initial_estimate.mode");
    assert!(e[0].1.contains("rank"), "{e:?}");
    assert_eq!(
        first(&pos(
            "[initial_estimate]\nmode = \"batch_ls\"\np0_std = 2.0\n"
        )),
        "initial_estimate.p0_std"
    );
    // A one-sample run cannot determine six states from three measurements.
    let short =
        spec("positions", "ekf").replace("name = \"hover\"", "name = \"hover\"\nduration_s = 0.1");
    let e = errors(&(short + batch));
    assert_eq!(e[0].0, "initial_estimate.mode");
    assert!(e[0].1.contains("rank 3 of 6"), "{e:?}");
    // Subsets must fit inside the study.
    // (BASE has the default 100 runs.)
    assert_eq!(
        first(&pos(
            "[consistency]\n[[consistency.subsets]]\nruns = 200\nalpha = 0.05\n"
        )),
        "consistency.subsets[0].runs"
    );
    assert_eq!(
        first(&pos(
            "[consistency]\n[[consistency.subsets]]\nruns = 20\nalpha = 1.5\n"
        )),
        "consistency.subsets[0].alpha"
    );
    // open_loop never updates, so R settings would be silently ignored.
    let ol = spec("positions", "open_loop");
    assert!(errors(&ol).is_empty());
    assert_eq!(
        first(&ol.replace(
            "kind = \"open_loop\"",
            "kind = \"open_loop\"\nr_scale = 2.0"
        )),
        "filters[0].r_scale"
    );
    // Pole placement: poles or the seed's list, on the observable sensor set only.
    let pp = spec("positions", "pole_placement");
    assert_eq!(first(&pp), "filters[0]");
    let with = |extra: &str| {
        pp.replace(
            "kind = \"pole_placement\"",
            &format!("kind = \"pole_placement\"\n{extra}"),
        )
    };
    assert!(errors(&with("pole_scale = 0.5")).is_empty());
    assert_eq!(
        first(&with("pole_scale = 0.5\npoles = [[0.1, 0.0]]")),
        "filters[0].poles"
    );
    assert_eq!(first(&with("pole_scale = -0.5")), "filters[0].pole_scale");
    assert_eq!(
        first(&with("pole_scale = 0.5\npole_reading = \"sideways\"")),
        "filters[0].pole_reading"
    );
    assert_eq!(
        first(&with("poles = [[0.1, 0.0], [0.2, 0.0, 0.3]]")),
        "filters[0].poles[1]"
    );
    // Five poles for six states, and a complex pole without its conjugate.
    assert_eq!(
        first(&with("poles = [[0.1], [0.2], [0.3], [0.4], [0.5]]")),
        "filters[0].poles"
    );
    assert_eq!(
        first(&with(
            "poles = [[0.1, 0.2], [0.1, 0.2], [0.3], [0.4], [0.5], [0.6]]"
        )),
        "filters[0].poles"
    );
    assert!(
        errors(&with(
            "poles = [[0.1, 0.2], [0.1, -0.2], [0.3], [0.4], [0.5], [0.6]]"
        ))
        .is_empty()
    );
    assert_eq!(
        first(&with("pole_scale = 0.5\nq_scale = 2.0")),
        "filters[0].q_scale"
    );
    let e = errors(&spec("velocities", "pole_placement").replace(
        "kind = \"pole_placement\"",
        "kind = \"pole_placement\"\npole_scale = 0.5",
    ));
    assert_eq!(e[0].0, "filters[0].kind", "{e:?}");
    assert_eq!(
        first(&pos("").replace("kind = \"ekf\"", "kind = \"ekf\"\npole_scale = 0.5")),
        "filters[0].pole_scale"
    );
}

/// The whole pipeline on L1: the three linear-Gaussian filters of `linear_nees.toml` produce
/// the same per-run RMSE and NEES (paired runs), the truth's Q is the model's full Q, and the
/// consistency verdict of the KF passes at the seed's α = 0.05.
#[test]
fn linear_nees_study_runs_and_the_three_forms_agree() {
    use kfmc::output::table::read;
    use kfmc::runner::NullObserver;
    use kfmc::study::{ExecOptions, run};

    let dir = tempfile::tempdir().unwrap();
    let text = std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("experiments/linear_nees.toml"),
    )
    .unwrap()
    .replace(
        "output = \"results/linear_nees\"",
        &format!("output = \"{}\"", dir.path().join("out").display()),
    )
    .replace("runs = 200", "runs = 100");
    let path = dir.path().join("spec.toml");
    std::fs::write(&path, text).unwrap();
    let plan = experiment::load(&path).unwrap();
    run(
        &plan,
        &ExecOptions {
            threads: 2,
            ..Default::default()
        },
        &NullObserver,
    )
    .unwrap();
    let df = read(&plan.output.join("runs.parquet")).unwrap();
    assert_eq!(df.height(), 100 * 4);
    let filter = df.column("filter").unwrap().str().unwrap().clone();
    let col = |name: &str| df.column(name).unwrap().f64().unwrap().clone();
    let (rx, rzd, nees) = (col("rmse_x"), col("rmse_zdot"), col("nees_mean"));
    let rows = |label: &str| -> Vec<usize> {
        (0..df.height())
            .filter(|&i| filter.get(i) == Some(label))
            .collect()
    };
    let kf = rows("kf");
    assert_eq!(kf.len(), 100);
    for other in ["information", "sqrt"] {
        for (a, b) in kf.iter().zip(rows(other)) {
            for c in [&rx, &rzd, &nees] {
                let (x, y) = (c.get(*a).unwrap(), c.get(b).unwrap());
                assert!((x - y).abs() <= 1e-9, "{other}: {x} vs {y}");
            }
        }
    }
    // Every run of the KF has a finite, plausible NEES (n = 6 on average).
    for &i in &kf {
        let v = nees.get(i).unwrap();
        assert!(v > 2.0 && v < 12.0, "nees_mean {v}");
    }
}
