//! Runs in groups (`--lanes`): every result equals the per-unit scalar path's, bit for bit,
//! for every bundled spec, for a cell's tail group, for 1 and 2 threads; a run of a group that
//! fails numerically fails in its own row while the others go on unchanged; and the switch's
//! precedence (`--lanes` over `KFMC_LANES` over auto) is what the manifest records.

use std::path::Path;

use crate::common::{kfmc, repo, table_bytes};
use kfmc::experiment::{self, Overrides};
use kfmc::filter::{CovarianceUpdate, Ekf};
use kfmc::linalg::{Matrix, Vector};
use kfmc::metrics::RunStatus;
use kfmc::model::{Availability, Measurement, Model};
use kfmc::runner::NullObserver;
use kfmc::runner::lanes::{Isa, LanesMode, groups};
use kfmc::step_loop::Unit;
use kfmc::step_loop::{Identity, Prior, RunContext, run_filter};
use kfmc::study::{ExecOptions, run};
use kfmc::systems::linear_quadrotor::model::{Linear, LinearSensor};

/// The first runs of every cell of every bundled spec, run in the executor's groups with
/// lanes on, against each run alone with lanes off: the full debug form of each result (every
/// per-step value, status, consistency sums, trace), which prints an f64 by its shortest
/// round-tripping text, so equal text is equal bits.
#[test]
fn every_bundled_spec_gives_the_scalar_paths_bits_with_lanes_on() {
    let mut specs: Vec<_> = std::fs::read_dir(repo().join("experiments"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "toml"))
        .collect();
    specs.sort();
    let mut compared = 0;
    let mut grouped = 0;
    for path in &specs {
        // Specs that need files beside them (outside estimates) do not load on their own.
        let Ok(mut on) = experiment::load(path) else {
            continue;
        };
        on.lanes = LanesMode::Auto;
        let mut off = experiment::load(path).unwrap();
        off.lanes = LanesMode::Off;
        let (trial_on, trial_off) = (on.trial(), off.trial());
        assert_eq!(trial_off.lanes(), 1, "{}", path.display());
        let width = trial_on.lanes();
        // A group of two where the trial takes groups, one run elsewhere (a trial without
        // groups runs the same code either way); the tail of a cell is exercised by the whole
        // studies below, which keeps this test to seconds.
        let n = if width > 1 { 2.min(on.runs) } else { 1 };
        for scenario in 0..on.scenarios.len() {
            for scale in 0..on.noise_scales.len() {
                let unit = |run| Unit {
                    scenario,
                    scale,
                    run,
                };
                for g in groups(0..n, on.runs, width) {
                    let units: Vec<Unit> = g.clone().map(unit).collect();
                    grouped += usize::from(units.len() > 1);
                    let results = trial_on.run_group(&units);
                    assert_eq!(results.len(), units.len());
                    for (u, r) in units.iter().zip(results) {
                        let alone = trial_off.run(u);
                        assert_eq!(
                            format!("{r:?}"),
                            format!("{alone:?}"),
                            "{} {u:?}",
                            path.display()
                        );
                        compared += 1;
                    }
                }
            }
        }
    }
    assert!(compared > 50, "only {compared} runs compared");
    if Isa::detect().width() > 1 {
        assert!(grouped > 10, "only {grouped} groups of more than one run");
    }
}

/// Runs a bundled spec with `runs` runs per cell into `out`.
fn study(spec: &str, runs: usize, lanes: LanesMode, threads: usize, out: &Path) {
    let mut plan = experiment::load(&repo().join("experiments").join(spec)).unwrap();
    plan.apply(&Overrides {
        runs: Some(runs),
        output: Some(out.to_path_buf()),
        ..Default::default()
    })
    .unwrap();
    plan.lanes = lanes;
    run(
        &plan,
        &ExecOptions {
            threads,
            ..Default::default()
        },
        &NullObserver,
    )
    .expect("study runs");
}

/// Whole studies of the KF family on L1 and on a multi-rate linear-from-TOML system (the
/// position sensor reports every 10th step, so the masked update is shared too), with 13 runs
/// per cell (a tail group whatever the width): every table byte-identical with lanes off on
/// one thread and lanes on on two.
#[test]
fn linear_studies_write_the_same_tables_with_lanes_on_and_off_on_one_and_two_threads() {
    for spec in ["linear_nees.toml", "linear_cv_target.toml"] {
        let dir = tempfile::tempdir().unwrap();
        let (a, b) = (dir.path().join("off"), dir.path().join("on"));
        study(spec, 13, LanesMode::Off, 1, &a);
        study(spec, 13, LanesMode::Auto, 2, &b);
        let (ta, tb) = (table_bytes(&a), table_bytes(&b));
        assert!(ta.len() >= 3, "{spec}: {} tables", ta.len());
        assert_eq!(
            ta.iter().map(|t| &t.0).collect::<Vec<_>>(),
            tb.iter().map(|t| &t.0).collect::<Vec<_>>()
        );
        for ((name, x), (_, y)) in ta.iter().zip(&tb) {
            assert!(x == y, "{spec}: {name} differs with lanes on");
        }
    }
}

/// Four runs of L1 (positions sensor) with one prior covariance: run 2's measurement at step
/// 40 is NaN, so its estimate becomes NaN there.
struct Group {
    model: Linear<3>,
    truth: Vec<Vec<Vector<6>>>,
    inputs: Vec<Vector<4>>,
    meas: Vec<Vec<Measurement<3>>>,
    x0: Vec<Vector<6>>,
    p0: Matrix<6, 6>,
}

fn group(steps: usize) -> Group {
    let model = Linear::<3>::new(LinearSensor::Positions, 0.01).unwrap();
    let inputs: Vec<Vector<4>> = (0..=steps)
        .map(|k| Vector::<4>::new(0.1 * (k as f64 * 0.05).sin(), 0.0, 0.02, -0.01))
        .collect();
    // A deterministic scatter per run and step, different in every run.
    let wobble = |r: usize, k: usize, i: usize| {
        ((r * 7919 + k * 104_729 + i * 31) % 1000) as f64 / 1e4 - 0.05
    };
    let mut truth = Vec::new();
    let mut meas = Vec::new();
    let mut x0 = Vec::new();
    for r in 0..4 {
        let mut x = Vector::<6>::from_fn(|i, _| 0.1 * (i + r) as f64);
        let mut xs = vec![x];
        let mut zs = vec![Measurement {
            z: Vector::<3>::zeros(),
            available: Availability::all(3),
        }];
        for (k, u) in inputs.iter().enumerate().skip(1) {
            x = model.propagate(&x, u) + Vector::<6>::from_fn(|i, _| 0.01 * wobble(r, k, i));
            xs.push(x);
            let mut z = model.measure(&x, u) + Vector::<3>::from_fn(|i, _| wobble(r, k, i + 6));
            if r == 2 && k == 40 {
                z[1] = f64::NAN;
            }
            // Every third step only the first component reports (the masked update).
            let available = if k % 3 == 0 {
                Availability(0b001)
            } else {
                Availability::all(3)
            };
            zs.push(Measurement { z, available });
        }
        x0.push(Vector::<6>::from_fn(|i, _| 0.1 * (i + r) as f64 + 0.05));
        truth.push(xs);
        meas.push(zs);
    }
    Group {
        model,
        truth,
        inputs,
        meas,
        x0,
        p0: Matrix::<6, 6>::identity() * 0.04,
    }
}

fn contexts<'a>(g: &'a Group, names: &'a [&'a str]) -> Vec<RunContext<'a, 6, 4, 3>> {
    (0..4)
        .map(|r| RunContext {
            truth: &g.truth[r],
            inputs: &g.inputs,
            measurements: &g.meas[r],
            angles: &[],
            rotations: &[],
            thresholds: None,
            quantity_names: names,
            trace: r == 1,
            export: false,
            consistency: None,
            unit: Unit {
                scenario: 0,
                scale: 0,
                run: r,
            },
        })
        .collect()
}

#[test]
fn a_run_that_fails_in_a_group_fails_in_its_own_row_and_the_others_go_on_unchanged() {
    let g = group(120);
    let names = ["x", "y", "z", "vx", "vy", "vz"];
    let ctxs = contexts(&g, &names);
    let priors: Vec<Prior<'_, 6>> =
        g.x0.iter()
            .map(|x0_hat| Prior { x0_hat, p0: &g.p0 })
            .collect();
    for update_form in [CovarianceUpdate::Standard, CovarianceUpdate::Joseph] {
        let ekf = Ekf::<6, 3> {
            q: Matrix::<6, 6>::identity() * 1e-4,
            r: Matrix::<3, 3>::identity() * 1e-3,
            update_form,
        };
        let shared = kfmc::system::group::run_group_shared(&ekf, &g.model, &priors, &ctxs)
            .expect("the group shares one covariance recursion");
        for (r, out) in shared.iter().enumerate() {
            let alone = run_filter(&g.model, &ekf, &Identity, &priors[r], &ctxs[r]);
            assert_eq!(
                format!("{:?}", out.run),
                format!("{:?}", alone.run),
                "run {r}"
            );
            assert_eq!(
                format!("{:?}", out.trace),
                format!("{:?}", alone.trace),
                "run {r}"
            );
            match (&out.run.status, r) {
                (RunStatus::NumericalFailure { step, detail }, 2) => {
                    assert_eq!(*step, 40);
                    assert!(detail.contains("state estimate"), "{detail}");
                }
                (status, 2) => panic!("run 2 should fail at step 40: {status:?}"),
                (status, _) => assert_eq!(*status, RunStatus::Ok, "run {r}"),
            }
        }
        assert!(
            shared[1].trace.is_some(),
            "the traced run keeps its trajectory"
        );
    }
}

#[test]
fn a_covariance_that_fails_stops_every_run_of_the_group_at_the_scalar_paths_step() {
    let g = group(20);
    let names = ["x", "y", "z", "vx", "vy", "vz"];
    let ctxs = contexts(&g, &names);
    let priors: Vec<Prior<'_, 6>> =
        g.x0.iter()
            .map(|x0_hat| Prior { x0_hat, p0: &g.p0 })
            .collect();
    // R = −I makes S = H P⁻ Hᵀ − I negative definite at the first update.
    let ekf = Ekf::<6, 3> {
        q: Matrix::<6, 6>::identity() * 1e-4,
        r: -Matrix::<3, 3>::identity(),
        update_form: CovarianceUpdate::Standard,
    };
    let shared = kfmc::system::group::run_group_shared(&ekf, &g.model, &priors, &ctxs).unwrap();
    for (r, out) in shared.iter().enumerate() {
        let alone = run_filter(&g.model, &ekf, &Identity, &priors[r], &ctxs[r]);
        assert_eq!(
            format!("{:?}", out.run),
            format!("{:?}", alone.run),
            "run {r}"
        );
        assert!(
            matches!(&out.run.status, RunStatus::NumericalFailure { step: 1, detail } if detail.contains("innovation covariance S")),
            "{:?}",
            out.run.status
        );
    }
    // A group whose runs start from different covariances is not shared.
    let p_other = g.p0 * 2.0;
    let mut mixed = priors.clone();
    mixed[3] = Prior {
        x0_hat: &g.x0[3],
        p0: &p_other,
    };
    assert!(kfmc::system::group::run_group_shared(&ekf, &g.model, &mixed, &ctxs).is_none());
}

/// The `lanes` and `isa` a manifest records.
fn manifest_lanes(dir: &Path) -> (String, String) {
    let text = std::fs::read_to_string(dir.join("manifest.toml")).unwrap();
    let field = |key: &str| {
        text.lines()
            .find_map(|l| l.strip_prefix(&format!("{key} = ")))
            .unwrap_or_else(|| panic!("no {key} in the manifest"))
            .trim_matches('"')
            .to_string()
    };
    (field("lanes"), field("isa"))
}

#[test]
fn the_flag_wins_over_kfmc_lanes_which_wins_over_auto_and_the_manifest_records_the_path() {
    let dir = tempfile::tempdir().unwrap();
    let spec = repo().join("experiments/linear_nees.toml");
    let detected = Isa::detect();
    // (KFMC_LANES, --lanes, the lanes and ISA the manifest must record)
    type Case<'a> = (Option<&'a str>, Option<&'a str>, (usize, Isa));
    let cases: [Case<'_>; 4] = [
        (None, None, (detected.width(), detected)),
        (Some("off"), None, (1, Isa::Scalar)),
        (Some("off"), Some("auto"), (detected.width(), detected)),
        (Some("auto"), Some("off"), (1, Isa::Scalar)),
    ];
    for (i, (env, flag, (lanes, isa))) in cases.into_iter().enumerate() {
        let out = dir.path().join(format!("case{i}"));
        let mut cmd = kfmc();
        cmd.args(["run", "--quiet", "--runs", "3", "--out"])
            .arg(&out)
            .arg(&spec)
            .env_remove("KFMC_LANES");
        if let Some(v) = env {
            cmd.env("KFMC_LANES", v);
        }
        if let Some(f) = flag {
            cmd.args(["--lanes", f]);
        }
        let o = cmd.output().unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        assert_eq!(
            manifest_lanes(&out),
            (lanes.to_string(), isa.name().to_string()),
            "KFMC_LANES={env:?} --lanes {flag:?}"
        );
    }
    // A value the variable cannot hold is a usage error naming it (exit 2), not a silent auto.
    let o = kfmc()
        .args(["run", "--quiet", "--runs", "3", "--out"])
        .arg(dir.path().join("bad"))
        .arg(&spec)
        .env("KFMC_LANES", "fast")
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("KFMC_LANES"));
}
