//! A world that is not the filters' model, through the public API only: a 1-D
//! constant-velocity target whose position sensor has a constant per-run bias b ~ N(0, σ_b²),
//! a world state no 2-state filter carries. Two filters are scored on the same quantities
//! [p, v]: a 2-state KF that ignores the bias, and a 3-state KF [p, v, b] mapped onto the
//! quantities by its marginal. NEES then has 2 degrees of freedom for both, the augmented
//! filter is consistent and the 2-state one is not.

use std::path::Path;
use std::sync::Arc;

use kfmc::experiment;
use kfmc::filter::{CovarianceUpdate, Ekf};
use kfmc::linalg::{Matrix, SmallCholesky, Vector};
use kfmc::model::{Availability, Measurement, Model};
use kfmc::output::table::read;
use kfmc::runner::NullObserver;
use kfmc::sim::seed::world_stream;
use kfmc::step_loop::{Identity, Marginal};
use kfmc::study::{ExecOptions, run};
use kfmc::system::checker::Checker;
use kfmc::system::world::{
    ModelFilter, NoiseSettings, Realisation, World, WorldFilter, WorldFilterEntry, WorldPlan,
};
use kfmc::system::{
    Catalogue, FilterInfo, Layout, Quantity, ScenarioInfo, System, SystemPlan, SystemSpec,
};
use rand_distr::{Distribution, StandardNormal};

const DT: f64 = 0.1;
const STEPS: usize = 100;
const ACCEL_STD: f64 = 0.2;
const MEAS_STD: f64 = 0.5;
const BIAS_STD: f64 = 2.0;

fn q2() -> Matrix<2, 2> {
    let s = ACCEL_STD * ACCEL_STD;
    Matrix::<2, 2>::new(
        s * DT.powi(3) / 3.0,
        s * DT * DT / 2.0,
        s * DT * DT / 2.0,
        s * DT,
    )
}

/// The filters' models: [p, v] and [p, v, b], both measuring p (+ b).
#[derive(Clone, Copy, Debug)]
struct Cv<const NX: usize>;

impl<const NX: usize> Model<NX, 1, 1> for Cv<NX> {
    fn dt_s(&self) -> f64 {
        DT
    }
    fn propagate(&self, x: &Vector<NX>, _u: &Vector<1>) -> Vector<NX> {
        let mut y = *x;
        y[0] += DT * x[1];
        y
    }
    fn transition_jacobian(&self, _x: &Vector<NX>, _u: &Vector<1>) -> Matrix<NX, NX> {
        let mut f = Matrix::<NX, NX>::identity();
        f[(0, 1)] = DT;
        f
    }
    fn measure(&self, x: &Vector<NX>, _u: &Vector<1>) -> Vector<1> {
        Vector::<1>::new(x[0] + if NX > 2 { x[2] } else { 0.0 })
    }
    fn measurement_jacobian(&self, _x: &Vector<NX>, _u: &Vector<1>) -> Matrix<1, NX> {
        Matrix::<1, NX>::from_fn(|_, j| if j == 0 || j == 2 { 1.0 } else { 0.0 })
    }
}

struct BiasedWorld;

impl World<2, 1, 1> for BiasedWorld {
    fn simulate(&self, _scenario: usize, noise_scale: f64, seed: u64) -> Realisation<2, 1, 1> {
        let mut process = world_stream(seed, 0);
        let mut sensor = world_stream(seed, 1);
        let mut bias_rng = world_stream(seed, 2);
        let mut prior_rng = world_stream(seed, 3);
        let n = |r: &mut rand_pcg::Pcg64| -> f64 { StandardNormal.sample(r) };
        let l = SmallCholesky::new(&q2()).expect("Q is SPD").l() * noise_scale;
        let bias = BIAS_STD * noise_scale * n(&mut bias_rng);
        let mut x = Vector::<2>::new(0.0, 1.0);
        let mut real = Realisation {
            prior_draws: (0..3).map(|_| n(&mut prior_rng)).collect(),
            ..Default::default()
        };
        for k in 0..=STEPS {
            if k > 0 {
                let w = l * Vector::<2>::new(n(&mut process), n(&mut process));
                x = Vector::<2>::new(x[0] + DT * x[1], x[1]) + w;
            }
            let z = x[0] + bias + MEAS_STD * noise_scale * n(&mut sensor);
            real.truth.push(x);
            real.inputs.push(Vector::<1>::zeros());
            real.measurements.push(Measurement {
                z: Vector::<1>::new(z),
                available: Availability::all(1),
            });
            real.world.push(bias);
        }
        real
    }
}

#[derive(Debug)]
struct Entry {
    augmented: bool,
}

impl WorldFilterEntry<2, 1, 1> for Entry {
    fn info(&self) -> FilterInfo {
        FilterInfo {
            kind: if self.augmented { "kf3" } else { "kf2" }.into(),
            has_covariance: true,
            q_scale: true,
            r_scale: true,
        }
    }
    fn prepare(&self, s: &NoiseSettings) -> Box<dyn WorldFilter<2, 1, 1>> {
        let fs2 = s.filter_scale * s.filter_scale;
        let r = Matrix::<1, 1>::new(MEAS_STD * MEAS_STD * fs2 * s.r_scale);
        let (p0v, p0p) = (1.0f64, 1.0f64);
        if self.augmented {
            let mut q = Matrix::<3, 3>::zeros();
            q.fixed_view_mut::<2, 2>(0, 0)
                .copy_from(&(q2() * (fs2 * s.q_scale)));
            let b0 = BIAS_STD * BIAS_STD * fs2;
            Box::new(ModelFilter {
                model: Cv::<3>,
                filter: Ekf {
                    q,
                    r,
                    update_form: CovarianceUpdate::Joseph,
                },
                eval: Marginal { indices: [0, 1] },
                // x̂0 = x0 + L ζ: the truth's start plus a draw from P0 (the bias prior is 0).
                prior: move |real: &Realisation<2, 1, 1>| {
                    let d = &real.prior_draws;
                    let x0 = real.truth[0];
                    (
                        Vector::<3>::new(x0[0] + p0p.sqrt() * d[0], x0[1] + p0v.sqrt() * d[1], 0.0),
                        Matrix::<3, 3>::from_diagonal(&Vector::<3>::new(p0p, p0v, b0)),
                    )
                },
            })
        } else {
            Box::new(ModelFilter {
                model: Cv::<2>,
                filter: Ekf {
                    q: q2() * (fs2 * s.q_scale),
                    r,
                    update_form: CovarianceUpdate::Joseph,
                },
                eval: Identity,
                prior: move |real: &Realisation<2, 1, 1>| {
                    let d = &real.prior_draws;
                    let x0 = real.truth[0];
                    (
                        Vector::<2>::new(x0[0] + p0p.sqrt() * d[0], x0[1] + p0v.sqrt() * d[1]),
                        Matrix::<2, 2>::from_diagonal(&Vector::<2>::new(p0p, p0v)),
                    )
                },
            })
        }
    }
}

struct BiasedSystem;

impl System for BiasedSystem {
    fn kind(&self) -> &str {
        "biased_cv"
    }
    fn catalogue(&self) -> Catalogue {
        Catalogue {
            about: "1-D constant velocity with a biased position sensor (test)".into(),
            sections: vec![],
        }
    }
    fn configure(&self, spec: &SystemSpec<'_>, c: &mut Checker) -> Option<Arc<dyn SystemPlan>> {
        let mut entries: Vec<Arc<dyn WorldFilterEntry<2, 1, 1>>> = Vec::new();
        for (i, f) in spec.filters.iter().enumerate() {
            match f.kind.as_str() {
                "kf2" => entries.push(Arc::new(Entry { augmented: false })),
                "kf3" => entries.push(Arc::new(Entry { augmented: true })),
                other => c.err(
                    format!("filters[{i}].kind"),
                    format!("unknown value `{other}`; expected one of: kf2, kf3"),
                ),
            }
        }
        let layout = Layout {
            quantities: vec![Quantity::new("p", "m"), Quantity::new("v", "m/s")],
            inputs: vec!["none".into()],
            measurements: vec!["z".into()],
            world_states: vec!["bias".into()],
            dt_s: DT,
        };
        let scenarios = spec
            .scenarios
            .iter()
            .map(|t| ScenarioInfo {
                name: t["name"].as_str().unwrap_or("").to_string(),
                steps: STEPS,
            })
            .collect();
        c.is_clean().then(|| {
            Arc::new(WorldPlan::new(
                Arc::new(BiasedWorld),
                layout,
                scenarios,
                entries,
            )) as Arc<dyn SystemPlan>
        })
    }
}

const SPEC: &str = r#"
master_seed = 5
runs = 200
trace_runs = 1
[model]
kind = "biased_cv"
[[scenarios]]
name = "drift"
[[filters]]
label = "ignores_bias"
kind = "kf2"
[[filters]]
label = "estimates_bias"
kind = "kf3"
[initial_estimate]
mode = "sampled"
[consistency]
alpha = 0.01
"#;

#[test]
fn an_augmented_state_filter_is_scored_on_the_worlds_quantities() {
    let registry = kfmc::systems::builtin().with(BiasedSystem);
    let tmp = tempfile::tempdir().unwrap();
    let mut plan = experiment::parse_with(SPEC, Path::new("biased.toml"), &registry).unwrap();
    plan.output = tmp.path().to_path_buf();
    run(
        &plan,
        &ExecOptions {
            threads: 2,
            ..Default::default()
        },
        &NullObserver,
    )
    .unwrap();

    // Both filters have the same error columns: the quantities, not their states.
    let runs = read(&tmp.path().join("runs.parquet")).unwrap();
    let names: Vec<String> = runs
        .get_column_names()
        .iter()
        .map(|s| s.to_string())
        .collect();
    assert!(names.contains(&"rmse_p".to_string()) && names.contains(&"rmse_v".to_string()));
    assert!(!names.iter().any(|n| n == "rmse_b" || n == "rmse_bias"));

    // The traces carry the world's bias and the 2×2 covariance of the quantities.
    let tr = read(&tmp.path().join("traces.parquet")).unwrap();
    for c in ["world_bias", "P_p_p", "P_v_p", "P_v_v", "est_p", "truth_v"] {
        assert!(tr.column(c).is_ok(), "missing {c}");
    }
    assert!(tr.column("P_b_b").is_err());

    // The verdicts: NEES with 2 degrees of freedom for both; the bias-blind filter's errors
    // carry b ~ N(0, 2²) against a claimed σ ≈ 0.5, the augmented one's are honest.
    let cons = read(&tmp.path().join("consistency.parquet")).unwrap();
    let filter = cons.column("filter").unwrap().str().unwrap().clone();
    let test = cons.column("test").unwrap().str().unwrap().clone();
    let pass = cons.column("pass").unwrap().bool().unwrap().clone();
    let stat = cons.column("statistic").unwrap().f64().unwrap().clone();
    let find = |f: &str, t: &str| {
        (0..cons.height())
            .find(|&i| filter.get(i) == Some(f) && test.get(i) == Some(t))
            .unwrap_or_else(|| panic!("no {t} row for {f}"))
    };
    // The 2-state filter's error transition is its own; the marginal of a 3-state filter has
    // none, so its calibrated test is absent and the model-free run-average test serves.
    assert!(
        (0..cons.height()).all(|i| !(filter.get(i) == Some("estimates_bias")
            && test.get(i) == Some("nees_time_average")))
    );
    let biased = find("ignores_bias", "nees_run_average_t");
    let honest = find("estimates_bias", "nees_run_average_t");
    // The average NEES over runs and steps, from the runs table.
    let rf = runs.column("filter").unwrap().str().unwrap().clone();
    let nees = runs.column("nees_mean").unwrap().f64().unwrap().clone();
    let mean_nees = |f: &str| {
        let v: Vec<f64> = (0..runs.height())
            .filter(|&i| rf.get(i) == Some(f))
            .filter_map(|i| nees.get(i))
            .collect();
        v.iter().sum::<f64>() / v.len() as f64
    };
    let (a_biased, a_honest) = (mean_nees("ignores_bias"), mean_nees("estimates_bias"));
    eprintln!(
        "mean NEES: ignores_bias {a_biased:.3} (t = {:.1}), estimates_bias {a_honest:.3} (t = {:.2}); dof 2",
        stat.get(biased).unwrap(),
        stat.get(honest).unwrap()
    );
    assert!(a_biased > 4.0);
    assert!(!pass.get(biased).unwrap());
    // 200 runs × 100 steps: the honest filter's average lies within 7.5 % of 2 (its standard
    // error here is about 0.03).
    assert!((a_honest - 2.0).abs() < 0.15, "{a_honest}");
    assert!(pass.get(honest).unwrap());
    assert!(pass.get(find("estimates_bias", "verdict")).unwrap());
    assert!(!pass.get(find("ignores_bias", "verdict")).unwrap());
}
