//! Unit tests of the validation: range expansion and the world stamp.

use super::*;

#[test]
fn range_matches_the_seed_sweep() {
    let v = expand_range(0.2, 50.0, 0.2);
    assert_eq!(v.len(), 250);
    assert_eq!(v[0], 0.2);
    assert_eq!(v[2], 0.6);
    assert_eq!(*v.last().unwrap(), 50.0);
}

const WORLD: &str = r#"
name = "stamp"
master_seed = 7
runs = 12
[model]
kind = "linear_quadrotor"
sensor = "positions"
[[scenarios]]
name = "hover"
x0 = [1.0, 0.0, 1.0, 0.0, 1.0, 0.0]
duration_s = 5.0
[[scenarios]]
name = "drift"
x0 = [0.0, 0.5, 0.0, -0.5, 2.0, 0.0]
duration_s = 3.0
[noise]
scales = [1.0, 3.0]
[[filters]]
label = "kf"
kind = "ekf"
[initial_estimate]
mode = "sampled"
p0_std = 1.0
"#;

fn stamp(text: &str) -> String {
    crate::experiment::parse(text, Path::new("stamp.toml"))
        .expect("a valid spec")
        .world_stamp()
}

#[test]
fn the_world_stamp_ignores_what_does_not_change_the_world() {
    let base = stamp(WORLD);
    // Comments, layout, key order and number spelling.
    let reformatted = WORLD
        .replace("[model]\n", "# the truth\n[model]   # here\n")
        .replace(
            "kind = \"linear_quadrotor\"\nsensor = \"positions\"",
            "sensor = 'positions'\nkind    =   \"linear_quadrotor\"",
        )
        .replace("duration_s = 5.0", "duration_s = 5");
    assert_ne!(reformatted, WORLD);
    assert_eq!(stamp(&reformatted), base);
    // The filters, the run count, the name and the judging settings.
    let filters = WORLD
        .replace("kind = \"ekf\"", "kind = \"external\"")
        .replace("runs = 12", "runs = 3\ntrace_runs = 1")
        .replace("name = \"stamp\"", "name = \"other\"")
        + "[[filters]]\nlabel = \"sqrt\"\nkind = \"sqrt\"\n[consistency]\nalpha = 0.01\n";
    assert_eq!(stamp(&filters), base);
    // Scenario order: a run's streams follow its scenario's name.
    let (head, rest) = WORLD.split_once("[[scenarios]]").unwrap();
    let (hover, rest) = rest.split_once("[[scenarios]]").unwrap();
    let (drift, tail) = rest.split_once("[noise]").unwrap();
    let swapped = format!("{head}[[scenarios]]{drift}[[scenarios]]{hover}[noise]{tail}");
    assert_eq!(stamp(&swapped), base);
}

#[test]
fn the_world_stamp_follows_what_changes_the_world() {
    let base = stamp(WORLD);
    for (from, to) in [
        ("master_seed = 7", "master_seed = 8"),
        ("scales = [1.0, 3.0]", "scales = [1.0, 2.0]"),
        (
            "scales = [1.0, 3.0]",
            "scales = [1.0, 3.0]\ndraws = \"fresh\"",
        ),
        ("duration_s = 5.0", "duration_s = 4.0"),
        ("x0 = [1.0, 0.0,", "x0 = [1.5, 0.0,"),
        ("name = \"drift\"", "name = \"drift2\""),
        ("p0_std = 1.0", "p0_std = 2.0"),
        ("mode = \"sampled\"", "mode = \"truth\""),
        (
            "sensor = \"positions\"",
            "sensor = \"positions\"\nmeasurement_noise_std = 0.2",
        ),
    ] {
        let changed = WORLD.replace(from, to);
        assert_ne!(changed, WORLD, "{from}");
        assert_ne!(stamp(&changed), base, "{from} → {to} kept the stamp");
    }
    // The seed override (`--seed`) changes it as the spec's key does.
    let mut plan = crate::experiment::parse(WORLD, Path::new("stamp.toml")).unwrap();
    plan.master_seed = 8;
    assert_eq!(
        plan.world_stamp(),
        stamp(&WORLD.replace("master_seed = 7", "master_seed = 8"))
    );
}

/// A world system that takes its scenarios' lengths as given, without
/// [`Checker::scenario_steps`]: the validation itself must refuse a scenario of no step.
struct CarelessWorld;

struct Still;

impl crate::system::world::World<1, 0, 1> for Still {
    fn simulate(&self, _: usize, _: f64, _: u64) -> crate::system::world::Realisation<1, 0, 1> {
        crate::system::world::Realisation::default()
    }
}

impl crate::system::System for CarelessWorld {
    fn kind(&self) -> &str {
        "careless"
    }
    fn catalogue(&self) -> crate::system::Catalogue {
        crate::system::Catalogue::default()
    }
    fn configure(&self, spec: &SystemSpec<'_>, _: &mut Checker) -> Option<Arc<dyn SystemPlan>> {
        let scenarios = spec
            .scenarios
            .iter()
            .map(|t| crate::system::ScenarioInfo {
                name: t["name"].as_str().unwrap_or("").to_string(),
                // As a user's world might: a negative duration saturates to 0 steps.
                steps: t["duration_s"].as_float().unwrap_or(0.0).round() as usize,
            })
            .collect();
        let layout = Layout {
            quantities: vec![crate::system::Quantity::new("x", "m")],
            inputs: Vec::new(),
            measurements: vec!["x".into()],
            world_states: Vec::new(),
            dt_s: 1.0,
        };
        Some(Arc::new(crate::system::world::WorldPlan::new(
            Arc::new(Still),
            layout,
            scenarios,
            Vec::new(),
        )))
    }
}

#[test]
fn a_scenario_of_no_step_is_a_spec_error_at_its_duration() {
    let registry = Registry::new().with(CarelessWorld);
    let spec = |duration: &str| {
        format!(
            "name = \"n\"\n[model]\nkind = \"careless\"\n[[scenarios]]\nname = \"ok\"\nduration_s = 3.0\n[[scenarios]]\nname = \"back\"\nduration_s = {duration}\n"
        )
    };
    for duration in ["-5.0", "0.2", "nan"] {
        let errors = crate::experiment::parse_with(&spec(duration), Path::new("w.toml"), &registry)
            .expect_err("a scenario of no step")
            .0;
        let at: Vec<&SpecError> = errors
            .iter()
            .filter(|e| e.key_path == "scenarios[1].duration_s")
            .collect();
        assert_eq!(at.len(), 1, "{duration}: {errors:?}");
        assert_eq!(at[0].file, Path::new("w.toml"));
        assert!(
            at[0].message.contains("scenario `back`"),
            "{}",
            at[0].message
        );
        assert!(at[0].message.contains("no step"), "{}", at[0].message);
        // The scenario of three steps is not blamed.
        assert!(
            !errors
                .iter()
                .any(|e| e.key_path.starts_with("scenarios[0]"))
        );
    }
}
