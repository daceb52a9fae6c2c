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
