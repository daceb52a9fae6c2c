//! The L1 model in the spec: defaults, and errors reported at their key paths.

use std::path::Path;

use kfmc::experiment::{self, FilterKind, ModelKind};

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
fn shipped_linear_nees_spec_is_the_seeds_test_1() {
    let plan = experiment::load(
        &Path::new(env!("CARGO_MANIFEST_DIR")).join("experiments/linear_nees.toml"),
    )
    .expect("valid spec");
    assert_eq!(plan.model.kind, ModelKind::LinearPositions);
    assert_eq!(plan.runs, 50);
    assert_eq!(plan.model.params.dt_s, 0.1);
    assert_eq!(plan.consistency.unwrap().alpha, 0.05);
    let labels: Vec<_> = plan.filters.iter().map(|f| f.label.as_str()).collect();
    assert_eq!(labels, ["kf", "information", "sqrt", "steady_state"]);
    assert_eq!(plan.filters[1].kind, FilterKind::Information);
    assert_eq!(plan.filters[2].kind, FilterKind::Sqrt);
}

#[test]
fn linear_defaults_are_the_seeds() {
    let plan = experiment::parse(&spec("xy", "sqrt"), Path::new("t.toml")).unwrap();
    assert_eq!(plan.model.kind, ModelKind::LinearXy);
    assert_eq!(plan.model.kind.nz(), 2);
    assert_eq!(plan.scenarios[0].x0, [1.0, 0.0, 1.0, 0.0, 1.0, 0.0]);
    assert_eq!(plan.scenarios[0].steps(plan.model.params.dt_s), 400);
    let r: Vec<f64> = plan.filters[0].r_std.iter().map(|s| s * s).collect();
    assert!((r[0] - 0.0933).abs() < 1e-15 && (r[1] - 0.0885).abs() < 1e-15);
    assert_eq!(plan.model.kind.state_names()[5], "zdot");
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
    .replace("runs = 50", "runs = 8");
    let path = dir.path().join("spec.toml");
    std::fs::write(&path, text).unwrap();
    let plan = experiment::load(&path).unwrap();
    run(&plan, &ExecOptions { threads: 2 }, &NullObserver).unwrap();
    let df = read(&plan.output.join("runs.parquet")).unwrap();
    assert_eq!(df.height(), 8 * 4);
    let filter = df.column("filter").unwrap().str().unwrap().clone();
    let col = |name: &str| df.column(name).unwrap().f64().unwrap().clone();
    let (rx, rzd, nees) = (col("rmse_x"), col("rmse_zdot"), col("nees_mean"));
    let rows = |label: &str| -> Vec<usize> {
        (0..df.height())
            .filter(|&i| filter.get(i) == Some(label))
            .collect()
    };
    let kf = rows("kf");
    assert_eq!(kf.len(), 8);
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
