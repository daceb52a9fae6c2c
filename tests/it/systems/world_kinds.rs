//! A world system selects kfmc's own filter kinds by name through `WorldKinds`: checked
//! against a second implementation, the additive kit. A world that simulates exactly what the
//! additive kit simulates (the same model, noise draws and seeds) must give tables equal to
//! the additive system's, value for value, for every kind, Q variant, noise scale and the
//! sampled initial estimate; the bridge adds nothing and loses nothing.

use std::path::Path;
use std::sync::Arc;

use kfmc::experiment;
use kfmc::linalg::{Matrix, Vector};
use kfmc::model::Model;
use kfmc::output::table::read;
use kfmc::prelude::{
    AdditivePlan, Catalogue, FilterSetup, Layout, Quantity, Realisation, ScenarioInfo, System,
    SystemPlan, SystemSpec, TruthNoise, World, WorldKinds, WorldPlan, common_kinds,
};
use kfmc::runner::NullObserver;
use kfmc::scenario::Scenario;
use kfmc::sim::{NoiseDraws, simulate};
use kfmc::study::{ExecOptions, run};
use kfmc::system::checker::Checker;

const DT: f64 = 0.1;
const STEPS: usize = 60;
const MEAS_STD: f64 = 0.5;
const P0_STD: [f64; 2] = [1.0, 0.5];

/// 1-D constant velocity, position measured, white-acceleration Q of its own.
#[derive(Clone, Copy, Debug)]
struct Cv;

impl Model<2, 1, 1> for Cv {
    fn dt_s(&self) -> f64 {
        DT
    }
    fn propagate(&self, x: &Vector<2>, u: &Vector<1>) -> Vector<2> {
        Vector::<2>::new(x[0] + DT * x[1] + 0.5 * DT * DT * u[0], x[1] + DT * u[0])
    }
    fn transition_jacobian(&self, _: &Vector<2>, _: &Vector<1>) -> Matrix<2, 2> {
        Matrix::<2, 2>::new(1.0, DT, 0.0, 1.0)
    }
    fn measure(&self, x: &Vector<2>, _: &Vector<1>) -> Vector<1> {
        Vector::<1>::new(x[0])
    }
    fn measurement_jacobian(&self, _: &Vector<2>, _: &Vector<1>) -> Matrix<1, 2> {
        Matrix::<1, 2>::new(1.0, 0.0)
    }
    fn process_noise_covariance(&self) -> Option<Matrix<2, 2>> {
        let s = 0.3 * 0.3;
        Some(Matrix::<2, 2>::new(
            s * DT.powi(3) / 3.0,
            s * DT * DT / 2.0,
            s * DT * DT / 2.0,
            s * DT,
        ))
    }
}

fn truth_noise() -> TruthNoise<2, 1> {
    TruthNoise {
        process_std: Vector::<2>::zeros(),
        measurement_std: Vector::<1>::new(MEAS_STD),
    }
}

fn scenario() -> Scenario<2, 1> {
    Scenario {
        name: "wave".into(),
        x0: Vector::<2>::new(0.0, 1.0),
        controls: (0..=STEPS)
            .map(|k| Vector::<1>::new((k as f64 * DT).sin()))
            .collect(),
    }
}

fn layout() -> Layout {
    Layout {
        quantities: vec![Quantity::new("p", "m"), Quantity::new("v", "m/s")],
        inputs: vec!["a".into()],
        measurements: vec!["z".into()],
        world_states: vec![],
        dt_s: DT,
    }
}

fn scenario_info() -> Vec<ScenarioInfo> {
    vec![ScenarioInfo {
        name: "wave".into(),
        steps: STEPS,
    }]
}

/// The world: what the additive kit simulates, drawn the same way from the same seed.
struct SameAsAdditive;

impl World<2, 1, 1> for SameAsAdditive {
    fn simulate(&self, _scenario: usize, noise_scale: f64, seed: u64) -> Realisation<2, 1, 1> {
        let sc = scenario();
        let draws = NoiseDraws::<2, 1>::draw(seed, sc.steps());
        let t = simulate(&Cv, &sc, &truth_noise(), noise_scale, None, &draws);
        Realisation {
            truth: t.truth,
            inputs: sc.controls,
            measurements: t.measurements,
            prior_draws: draws.initial.iter().copied().collect(),
            ..Realisation::default()
        }
    }
}

struct CvWorld;

impl System for CvWorld {
    fn kind(&self) -> &str {
        "cv_world"
    }
    fn catalogue(&self) -> Catalogue {
        Catalogue::default()
    }
    fn configure(&self, spec: &SystemSpec<'_>, c: &mut Checker) -> Option<Arc<dyn SystemPlan>> {
        let kinds = WorldKinds::new(common_kinds(), Cv, &[0.0, 0.0], &[MEAS_STD], &P0_STD);
        let entries = kinds.configure(spec, "cv_world", c);
        c.is_clean().then(|| {
            Arc::new(WorldPlan::new(
                Arc::new(SameAsAdditive),
                layout(),
                scenario_info(),
                entries,
            )) as Arc<dyn SystemPlan>
        })
    }
}

struct CvAdditive;

impl System for CvAdditive {
    fn kind(&self) -> &str {
        "cv_additive"
    }
    fn catalogue(&self) -> Catalogue {
        Catalogue::default()
    }
    fn configure(&self, spec: &SystemSpec<'_>, c: &mut Checker) -> Option<Arc<dyn SystemPlan>> {
        let entries = common_kinds().configure_entries(
            spec.filters,
            &FilterSetup::new(&Cv, "cv_additive", &[0.0, 0.0], &[MEAS_STD]),
            c,
        );
        c.is_clean().then(|| {
            Arc::new(AdditivePlan::new(
                Cv,
                layout(),
                vec![scenario()],
                truth_noise(),
                Vector::<2>::from_column_slice(&P0_STD),
                entries,
            )) as Arc<dyn SystemPlan>
        })
    }
}

const SPEC: &str = r#"
master_seed = 11
runs = 40
[model]
kind = "KIND"
[[scenarios]]
name = "wave"
[[filters]]
label = "ekf"
kind = "ekf"
q_scale = [0.5, 1.0, 2.0]
[[filters]]
label = "ukf"
kind = "ukf"
r_std = 0.7
[[filters]]
label = "information"
kind = "information"
[noise]
scales = [1.0, 3.0]
filter_noise = "matched"
[initial_estimate]
mode = "sampled"
[consistency]
alpha = 0.05
"#;

fn run_as(kind: &str, dir: &Path) {
    let registry = kfmc::systems::builtin().with(CvWorld).with(CvAdditive);
    let text = SPEC.replace("KIND", kind);
    let mut plan = experiment::parse_with(&text, Path::new("cv.toml"), &registry).unwrap();
    plan.output = dir.to_path_buf();
    run(
        &plan,
        &ExecOptions {
            threads: 2,
            ..Default::default()
        },
        &NullObserver,
    )
    .unwrap();
}

#[test]
fn a_world_running_kfmcs_kinds_by_name_equals_the_additive_kit_value_for_value() {
    let (world, additive) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    run_as("cv_world", world.path());
    run_as("cv_additive", additive.path());
    for table in [
        "runs.parquet",
        "steps.parquet",
        "summary.parquet",
        "consistency.parquet",
    ] {
        let (w, a) = (
            read(&world.path().join(table)).unwrap(),
            read(&additive.path().join(table)).unwrap(),
        );
        assert!(w.height() > 0, "{table} is empty");
        assert!(w.equals_missing(&a), "{table} differs:\n{w}\n{a}");
    }
    // Not vacuous: the variants differ from each other, and the filters ran.
    let runs = read(&world.path().join("runs.parquet")).unwrap();
    let status = runs.column("status").unwrap().str().unwrap().clone();
    assert!(status.iter().all(|s| s == Some("ok")), "a run failed");
    let rmse = runs.column("rmse_p").unwrap().f64().unwrap().clone();
    let distinct: std::collections::BTreeSet<u64> =
        rmse.iter().flatten().map(f64::to_bits).collect();
    assert!(distinct.len() > 40, "{distinct:?}");
}

#[test]
fn a_world_refuses_the_batch_initialiser_and_a_bad_p0_at_their_keys() {
    let registry = kfmc::systems::builtin().with(CvWorld);
    let text = SPEC.replace("KIND", "cv_world").replace(
        "mode = \"sampled\"",
        "mode = \"batch_ls\"\np0_std = [1.0, -2.0]",
    );
    let errors = experiment::parse_with(&text, Path::new("cv.toml"), &registry)
        .expect_err("two problems")
        .0;
    let keys: Vec<&str> = errors.iter().map(|e| e.key_path.as_str()).collect();
    assert_eq!(
        keys,
        ["initial_estimate.mode", "initial_estimate.p0_std[1]"],
        "{errors:#?}"
    );
}
