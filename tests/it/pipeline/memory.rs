//! Memory independent of the runs per cell: a cell with more runs than a spill keeps in
//! memory still gets exact across-run statistics (checked against sorting the runs table),
//! leaves no scratch file behind; `validate`'s estimate bounds the tables on disk; plans the
//! estimate or the limits refuse are refused naming the key.

use std::path::Path;

use crate::common::read;
use crate::common::run_cli as run;

/// Two filters on the linear quadrotor, 3 steps a run: cheap enough for 70,000 runs.
fn spec(out: &Path, runs: usize) -> String {
    format!(
        r#"
name = "many_runs"
master_seed = 5
runs = {runs}
output = "{}"
[model]
kind = "linear_quadrotor"
sensor = "positions"
[[scenarios]]
name = "hover"
x0 = [1.0, 0.0, 1.0, 0.0, 1.0, 0.0]
duration_s = 0.3
[[filters]]
label = "kf"
kind = "ekf"
[[filters]]
label = "open"
kind = "open_loop"
"#,
        out.display()
    )
}

/// numpy's type-7 quantile of sorted values, as kfmc documents it.
fn quantile(sorted: &[f64], q: f64) -> f64 {
    let h = (sorted.len() - 1) as f64 * q;
    let (lo, hi) = (h.floor() as usize, h.ceil() as usize);
    sorted[lo] + (h - lo as f64) * (sorted[hi] - sorted[lo])
}

#[test]
fn a_spilled_cell_summary_is_exactly_the_sorted_runs_table() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("out");
    let path = tmp.path().join("s.toml");
    // More runs than a spill keeps in memory (65,536), so the scratch path is taken.
    let runs = kfmc::metrics::spill::SPILL_ROWS + 4_464;
    std::fs::write(&path, spec(&out, runs)).unwrap();
    let (code, _, err) = run(&["run", path.to_str().unwrap(), "--quiet"]);
    assert_eq!(code, 0, "{err}");
    let leftovers: Vec<String> = std::fs::read_dir(&out)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with('.'))
        .collect();
    assert!(leftovers.is_empty(), "left behind: {leftovers:?}");

    let runs_df = read(&out.join("runs.parquet"));
    let summary = read(&out.join("summary.parquet"));
    let filters = runs_df.column("filter").unwrap().str().unwrap().clone();
    let mut checked = 0;
    for i in 0..summary.height() {
        let f = summary
            .column("filter")
            .unwrap()
            .str()
            .unwrap()
            .get(i)
            .unwrap();
        let state = summary
            .column("state")
            .unwrap()
            .str()
            .unwrap()
            .get(i)
            .unwrap();
        let col = runs_df
            .column(&format!("rmse_{state}"))
            .unwrap()
            .f64()
            .unwrap()
            .clone();
        // In run order, as the study adds them.
        let v: Vec<f64> = (0..runs_df.height())
            .filter(|&r| filters.get(r) == Some(f))
            .filter_map(|r| col.get(r))
            .collect();
        assert_eq!(v.len(), runs, "{f} {state}: every run completed");
        let n = v.len() as f64;
        let mean = v.iter().sum::<f64>() / n;
        let std = (v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0)).sqrt();
        let mut s = v.clone();
        s.sort_by(f64::total_cmp);
        let got = |c: &str| summary.column(c).unwrap().f64().unwrap().get(i).unwrap();
        let n_runs = summary
            .column("runs")
            .unwrap()
            .i64()
            .unwrap()
            .get(i)
            .unwrap();
        assert_eq!(n_runs as usize, runs);
        for (c, want) in [
            ("rmse_mean", mean),
            ("rmse_std", std),
            ("rmse_p05", quantile(&s, 0.05)),
            ("rmse_p50", quantile(&s, 0.50)),
            ("rmse_p95", quantile(&s, 0.95)),
        ] {
            assert_eq!(got(c).to_bits(), want.to_bits(), "{f} {state} {c}");
        }
        checked += 1;
    }
    assert_eq!(checked, 2 * 6, "two filters × six states");
}

/// The estimate is an upper bound on the tables as written (compressed Parquet), and not
/// a wild one: within a factor of 40 of what a modest plan wrote.
#[test]
fn the_estimate_bounds_the_tables_on_disk() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("out");
    let path = tmp.path().join("s.toml");
    let text = spec(&out, 2_000).replace("duration_s = 0.3", "duration_s = 20.0")
        + "trace_runs = 3\n[noise]\nscales = [1.0, 2.0]\n";
    // `trace_runs` belongs to the top level: move it above the first table.
    let text = text.replace("trace_runs = 3\n", "").replacen(
        "runs = 2000\n",
        "runs = 2000\ntrace_runs = 3\n",
        1,
    );
    std::fs::write(&path, &text).unwrap();
    let plan = kfmc::experiment::load(&path).unwrap();
    let estimate = kfmc::study::resources(&plan);
    let (code, stdout, err) = run(&["validate", path.to_str().unwrap()]);
    assert_eq!(code, 0, "{err}");
    assert!(stdout.contains("estimated peak memory"), "{stdout}");
    assert!(stdout.contains("scratch up to 0.0 B"), "{stdout}");
    let (code, _, err) = run(&["run", path.to_str().unwrap(), "--quiet"]);
    assert_eq!(code, 0, "{err}");
    let on_disk: u64 = std::fs::read_dir(&out)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "parquet"))
        .map(|p| std::fs::metadata(p).unwrap().len())
        .sum();
    let ratio = estimate.disk_bytes as f64 / on_disk as f64;
    assert!(
        (1.0..=40.0).contains(&ratio),
        "estimate {} B, on disk {on_disk} B (ratio {ratio:.2})",
        estimate.disk_bytes
    );
}

/// Beyond the buffers, more runs cost scratch disk but no memory, with the consistency tests
/// and divergence points too.
#[test]
fn the_memory_estimate_does_not_grow_with_the_runs() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("out");
    let estimate = |runs: usize| {
        let text = spec(&out, runs)
            + "[noise]\nscales = [1.0, 2.0]\n[divergence]\nrmse_thresholds = [1.0, 1.0, 1.0, 1.0, 1.0, 1.0]\n[consistency]\nalpha = 0.05\n[[consistency.subsets]]\nruns = 50\nalpha = 0.01\n";
        kfmc::study::resources(&kfmc::experiment::parse(&text, Path::new("e.toml")).unwrap())
    };
    let (small, large) = (estimate(100_000), estimate(100_000_000));
    assert_eq!(small.memory_bytes, large.memory_bytes);
    assert!(large.scratch_bytes > 500 * small.scratch_bytes);
    assert!(estimate(1_000).memory_bytes < small.memory_bytes);
}

#[test]
fn plans_beyond_the_limits_are_refused_naming_the_key() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("out");
    let cases: [(String, &[&str]); 3] = [
        // Beyond the runs limit: refused at once, no allocation attempted.
        (
            spec(&out, 1_000_000_000_000),
            &["runs:", "at most 1000000000"],
        ),
        // Runs alone no longer cost memory, but tables and scratch files cost disk.
        (
            spec(&out, 1_000_000_000),
            &["(plan)", "of tables", "of scratch files", "--allow-large"],
        ),
        // Long runs cost memory (every unit in flight holds its per-step values): refused.
        (
            spec(&out, 100).replace("duration_s = 0.3", "duration_s = 100000.0"),
            &["(plan)", "of memory", "--allow-large"],
        ),
    ];
    for (text, needles) in cases {
        let path = tmp.path().join("big.toml");
        std::fs::write(&path, &text).unwrap();
        for cmd in ["validate", "run"] {
            let (code, _, err) = run(&[cmd, path.to_str().unwrap()]);
            assert_eq!(code, 2, "{cmd}: {err}");
            assert!(err.contains("big.toml"), "names the file: {err}");
            for n in needles {
                assert!(err.contains(n), "{cmd}: missing `{n}` in {err}");
            }
        }
        assert!(!out.exists(), "nothing was started");
    }
}

// ---------------------------------------------------------------------------------------
// Consistency tests in bounded memory: the streaming fold against the slice-based code it
// replaced, kept here verbatim as the reference.

use kfmc::metrics::RunConsistency;
use kfmc::metrics::consistency::{
    CellSums, ConsistencyFold, Direction, TestResult, VERDICT, cell_tests, normal_quantile,
    normal_two_sided_p, scaled_chi2_test, t_test,
};
use rand::{RngExt, SeedableRng};
use rand_pcg::Pcg64;

/// `cell_tests` as it was when a study kept every run's sums (before the streaming fold).
fn reference_cell_tests(
    runs: &[RunConsistency],
    n: usize,
    state_names: &[&str],
    alpha: f64,
    steps_inside: (Option<f64>, Option<f64>),
) -> Vec<TestResult> {
    let mut out = Vec::new();
    let runs: Vec<&RunConsistency> = runs.iter().filter(|r| r.nees_n > 0).collect();
    if runs.is_empty() {
        return out;
    }
    let nf = n as f64;
    let nees_n: u64 = runs.iter().map(|r| r.nees_n).sum();
    let nees_sum: f64 = runs.iter().map(|r| r.nees_sum).sum();
    let a_bar = nees_sum / nees_n as f64;
    let rho: Option<f64> = runs
        .iter()
        .map(|r| r.rho_sum.map(|s| 1.0 + 2.0 * s / (nf * r.nees_n as f64)))
        .sum::<Option<f64>>()
        .map(|s| s / runs.len() as f64);
    let nees = rho.and_then(|rho| {
        scaled_chi2_test(
            "nees_time_average",
            a_bar,
            nf,
            nf * nees_n as f64 / rho,
            alpha,
        )
    });
    out.extend(nees.clone());
    let nis_n: u64 = runs.iter().map(|r| r.nis_n).sum();
    let nis_dof: u64 = runs.iter().map(|r| r.nis_dof).sum();
    let nis = (nis_n > 0 && nis_dof > 0)
        .then(|| {
            let nis_sum: f64 = runs.iter().map(|r| r.nis_sum).sum();
            let p_bar = nis_dof as f64 / nis_n as f64;
            scaled_chi2_test(
                "nis_time_average",
                nis_sum / nis_n as f64,
                p_bar,
                nis_dof as f64,
                alpha,
            )
        })
        .flatten();
    out.extend(nis.clone());
    let initial: Option<Vec<f64>> = runs.iter().map(|r| r.initial_nees).collect();
    if let Some(v) = initial {
        let mean = v.iter().sum::<f64>() / v.len() as f64;
        out.extend(scaled_chi2_test(
            "initial_nees",
            mean,
            nf,
            nf * v.len() as f64,
            alpha,
        ));
    }
    let per_run: Vec<f64> = runs.iter().map(|r| r.nees_sum / r.nees_n as f64).collect();
    out.extend(t_test("nees_run_average_t", &per_run, nf, alpha, true));
    for (name, frac) in [
        ("anees_steps_inside", steps_inside.0),
        ("anis_steps_inside", steps_inside.1),
    ] {
        if let Some(f) = frac {
            out.push(TestResult {
                test: name.into(),
                statistic: f,
                lower: Some(1.0 - alpha),
                upper: None,
                dof: None,
                p_value: None,
                pass: f >= 1.0 - alpha,
                direction: None,
            });
        }
    }
    let lags = runs[0].lag_prod.len();
    let w_sq: f64 = runs.iter().map(|r| r.w_sq).sum();
    // Sums that are not finite, or innovations all zero, leave the test not computed.
    let prods: Vec<f64> = (0..lags)
        .map(|l| runs.iter().map(|r| r.lag_prod[l]).sum())
        .collect();
    let any_pairs = (0..lags).any(|l| runs.iter().map(|r| r.lag_pairs[l]).sum::<u64>() > 0);
    let finite = w_sq.is_finite() && prods.iter().all(|p| p.is_finite());
    if lags > 0 && nis_dof > 0 && any_pairs && (!finite || w_sq <= 0.0) {
        out.push(TestResult::not_computed(
            "innovation_whiteness",
            None,
            None,
            Some(lags as f64),
        ));
    } else if lags > 0 && nis_dof > 0 && w_sq > 0.0 {
        let variance = w_sq / nis_dof as f64;
        let crit = normal_quantile(1.0 - alpha / (2.0 * lags as f64));
        let mut worst: Option<(f64, f64, f64)> = None;
        for l in 0..lags {
            let prod: f64 = runs.iter().map(|r| r.lag_prod[l]).sum();
            let pairs: u64 = runs.iter().map(|r| r.lag_pairs[l]).sum();
            if pairs == 0 {
                continue;
            }
            let m = pairs as f64;
            let rho_l = prod / m / variance;
            let z = rho_l * m.sqrt();
            if worst.is_none_or(|(wz, _, _)| z.abs() > wz) {
                worst = Some((z.abs(), rho_l, crit / m.sqrt()));
            }
        }
        if let Some((z, rho_l, bound)) = worst {
            out.push(TestResult {
                test: "innovation_whiteness".into(),
                statistic: rho_l,
                lower: Some(-bound),
                upper: Some(bound),
                dof: Some(lags as f64),
                p_value: Some((normal_two_sided_p(z) * lags as f64).min(1.0)),
                pass: z <= crit,
                direction: None,
            });
        }
    }
    for (i, state) in state_names.iter().enumerate() {
        let v: Vec<f64> = runs
            .iter()
            .map(|r| r.nme_sum[i] / r.nees_n as f64)
            .collect();
        if let Some(mut t) = t_test(&format!("bias_{state}"), &v, 0.0, alpha, true) {
            t.direction = None;
            out.push(t);
        }
    }
    // The model-free test stands in only for a filter that exposes no transition on any run;
    // a test not computed (a NaN statistic or p-value) leaves no verdict.
    let nees = nees.or_else(|| {
        (runs.len() >= 20 && runs.iter().all(|r| r.rho_sum.is_none()))
            .then(|| out.iter().find(|t| t.test == "nees_run_average_t").cloned())
            .flatten()
    });
    if let (Some(a), Some(b)) = (&nees, &nis)
        && a.computed()
        && b.computed()
    {
        let (pa, pb) = (a.p_value.unwrap_or(0.0), b.p_value.unwrap_or(0.0));
        let pass = pa > alpha / 2.0 && pb > alpha / 2.0;
        let side = |t: &TestResult| {
            let centre = (t.lower.unwrap_or(0.0) + t.upper.unwrap_or(0.0)) / 2.0;
            if t.statistic > centre {
                Direction::Optimistic
            } else {
                Direction::Pessimistic
            }
        };
        let p = (2.0 * pa.min(pb)).min(1.0);
        let direction = (!pass).then(|| if pa <= pb { side(a) } else { side(b) });
        out.push(TestResult {
            test: VERDICT.into(),
            statistic: p,
            lower: Some(alpha),
            upper: None,
            dof: None,
            p_value: Some(p),
            pass,
            direction,
        });
    }
    out
}

/// The study's burn-in column as it was computed from the kept sums.
fn reference_burn_in(runs: &[RunConsistency]) -> Option<usize> {
    runs.iter()
        .map(|r| r.first_step)
        .try_fold(0usize, |m, s| s.map(|s| m.max(s.saturating_sub(1))))
}

/// A test result with its floats as bits, so equality is bit-identity (NaN included).
fn bits(t: &TestResult) -> String {
    let b = |x: Option<f64>| x.map(f64::to_bits);
    format!(
        "{} {:x} {:?} {:?} {:?} {:?} {} {:?}",
        t.test,
        t.statistic.to_bits(),
        b(t.lower),
        b(t.upper),
        b(t.dof),
        b(t.p_value),
        t.pass,
        t.direction
    )
}

fn all_bits(v: &[TestResult]) -> Vec<String> {
    v.iter().map(bits).collect()
}

/// Random run sums that reach every branch of the tests: runs without NEES steps, missing
/// ρ or initial NEES, unforgotten priors, signed zeros, all-equal (zero-variance) columns,
/// optimistic and pessimistic cells, no whiteness lags.
fn random_cell(rng: &mut Pcg64, runs: usize, n: usize) -> Vec<RunConsistency> {
    let lags = rng.random_range(0..4usize);
    let flavour = rng.random_range(0..6u32);
    let scale = [0.5, 1.0, 1.0, 2.0, 1e-3, 1e6][rng.random_range(0..6usize)];
    (0..runs)
        .map(|_| {
            let steps = if rng.random_range(0..20) == 0 {
                0
            } else {
                rng.random_range(1..50u64)
            };
            let k = steps as f64;
            let signed_zero = |rng: &mut Pcg64| {
                if rng.random_range(0..2) == 0 {
                    -0.0
                } else {
                    0.0
                }
            };
            RunConsistency {
                first_step: match flavour {
                    0 if rng.random_range(0..50) == 0 => None,
                    1 => Some(rng.random_range(1..10)),
                    _ => Some(1),
                },
                nees_sum: scale * k * n as f64 * rng.random_range(0.2..3.0),
                nees_n: steps,
                rho_sum: match flavour {
                    2 => None,
                    3 if rng.random_range(0..100) == 0 => None,
                    _ => Some(k * rng.random_range(0.0..2.0)),
                },
                nis_sum: scale * k * 3.0 * rng.random_range(0.2..3.0),
                nis_dof: 3 * steps,
                nis_n: steps,
                nme_sum: (0..n)
                    .map(|i| match (flavour, i) {
                        (4, 0) => signed_zero(rng),
                        (4, 1) => 0.25 * k,
                        _ => rng.random_range(-1.0..1.0) * k.sqrt(),
                    })
                    .collect(),
                lag_prod: (0..lags).map(|_| rng.random_range(-1.0..1.0) * k).collect(),
                lag_pairs: (0..lags)
                    .map(|l| 3 * steps.saturating_sub(l as u64 + 1))
                    .collect(),
                w_sq: if flavour == 5 {
                    signed_zero(rng)
                } else {
                    3.0 * k * rng.random_range(0.5..1.5)
                },
                w_n: 3 * steps,
                initial_nees: match flavour {
                    1 | 3 => Some(rng.random_range(0.0..20.0)),
                    _ => None,
                },
            }
        })
        .collect()
}

#[test]
fn streaming_consistency_tests_are_bit_identical_to_the_slice_based_ones() {
    let tmp = tempfile::tempdir().unwrap();
    let states = ["a", "b", "c", "d"];
    let mut rng = Pcg64::seed_from_u64(16);
    let mut spilled = 0;
    for case in 0..120 {
        let runs = match case % 4 {
            0 => rng.random_range(0..5usize),
            1 => rng.random_range(5..40),
            _ => rng.random_range(40..3_000),
        };
        let cell = random_cell(&mut rng, runs, states.len());
        let alpha = [0.05, 0.01, 0.003][case % 3];
        let inside = (Some(rng.random_range(0.8..1.0)), None);
        // The slice entry point (now a two-pass wrapper over `CellSums`).
        assert_eq!(
            all_bits(&cell_tests(&cell, states.len(), &states, alpha, inside)),
            all_bits(&reference_cell_tests(
                &cell,
                states.len(),
                &states,
                alpha,
                inside
            )),
            "case {case}: cell_tests"
        );
        // The study's fold, whole cell and two prefixes, with a buffer small enough that
        // most cases go through the scratch file.
        let cuts = [
            usize::MAX,
            rng.random_range(0..=runs + 1),
            rng.random_range(0..=runs + 1),
        ];
        let cap = rng.random_range(1..200);
        let mut fold = ConsistencyFold::with_capacity(tmp.path(), states.len(), 4, &cuts, cap);
        for (run, r) in cell.iter().enumerate() {
            fold.push(run, r).unwrap();
        }
        spilled += (cell.iter().filter(|r| r.nees_n > 0).count() > cap) as usize;
        let sums: Vec<CellSums> = fold.finish().unwrap();
        assert_eq!(sums.len(), 3);
        for (s, cut) in sums.iter().zip(cuts) {
            let prefix = &cell[..cut.min(runs)];
            assert_eq!(s.runs(), prefix.len(), "case {case}");
            assert_eq!(s.burn_in(), reference_burn_in(prefix), "case {case}");
            assert_eq!(
                all_bits(&s.tests(&states, alpha, inside)),
                all_bits(&reference_cell_tests(
                    prefix,
                    states.len(),
                    &states,
                    alpha,
                    inside
                )),
                "case {case}, first {cut} runs"
            );
        }
        drop(fold);
        assert_eq!(
            std::fs::read_dir(tmp.path()).unwrap().count(),
            0,
            "scratch removed"
        );
    }
    assert!(spilled > 50, "the scratch path was taken ({spilled} cases)");
}

/// A study cell with more runs than the fold keeps in memory writes the consistency table
/// the kept-sums code gives on the same runs (recomputed here through the library).
#[test]
fn a_spilled_cell_gives_the_consistency_table_of_the_kept_sums() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("out");
    let path = tmp.path().join("s.toml");
    let runs = kfmc::metrics::spill::SPILL_ROWS + 4_464;
    // x̂_0 = x_0 (the default), so the prior is forgotten over a burn-in; subsets below and
    // above the in-memory buffer.
    let text = spec(&out, runs).replace("duration_s = 0.3", "duration_s = 0.5")
        + "[consistency]\nalpha = 0.01\nwhiteness_lags = 2\n[[consistency.subsets]]\nruns = 50\nalpha = 0.05\n[[consistency.subsets]]\nruns = 66000\nalpha = 0.003\n";
    std::fs::write(&path, &text).unwrap();
    let (code, _, err) = run(&["run", path.to_str().unwrap(), "--quiet"]);
    assert_eq!(code, 0, "{err}");

    let plan = kfmc::experiment::load(&path).unwrap();
    let trial = plan.trial();
    let states = trial.layout().quantity_names();
    let nf = plan.filters.len();
    let mut kept: Vec<Vec<RunConsistency>> = vec![Vec::new(); nf];
    for run in 0..runs {
        let r = trial.run(&kfmc::step_loop::Unit {
            scenario: 0,
            scale: 0,
            run,
        });
        for (fi, f) in r.filters.iter().enumerate() {
            kept[fi].extend(f.consistency.clone());
        }
    }
    assert!(kept.iter().all(|k| k.len() == runs), "every run has sums");

    let table = read(&out.join("consistency.parquet"));
    let s = |c: &str, i: usize| {
        table
            .column(c)
            .unwrap()
            .str()
            .unwrap()
            .get(i)
            .map(str::to_string)
    };
    let f = |c: &str, i: usize| table.column(c).unwrap().f64().unwrap().get(i);
    let int = |c: &str, i: usize| table.column(c).unwrap().i64().unwrap().get(i);
    let mut rows = 0;
    for (fi, fp) in plan.filters.iter().enumerate() {
        let mine: Vec<usize> = (0..table.height())
            .filter(|&i| s("filter", i).as_deref() == Some(fp.label.as_str()))
            .collect();
        // The per-step fractions come from the step accumulator, not from these sums.
        let frac = |name: &str| {
            mine.iter()
                .find(|&&i| s("test", i).as_deref() == Some(name))
                .and_then(|&i| f("statistic", i))
        };
        let inside = (frac("anees_steps_inside"), frac("anis_steps_inside"));
        let cp = plan.consistency.as_ref().unwrap();
        let mut want: Vec<(String, f64, i64, Option<i64>)> = Vec::new();
        let mut evaluations = vec![(runs, cp.alpha, inside)];
        evaluations.extend(cp.subsets.iter().map(|&(n, a)| (n, a, (None, None))));
        for (n, alpha, inside) in evaluations {
            let prefix = &kept[fi][..n];
            let burn_in = reference_burn_in(prefix).map(|b| b as i64);
            for t in reference_cell_tests(prefix, states.len(), &states, alpha, inside) {
                want.push((bits(&t), alpha, n as i64, burn_in));
            }
        }
        let got: Vec<(String, f64, i64, Option<i64>)> = mine
            .iter()
            .map(|&i| {
                let t = TestResult {
                    test: s("test", i).unwrap(),
                    statistic: f("statistic", i).unwrap(),
                    lower: f("lower", i),
                    upper: f("upper", i),
                    dof: f("dof", i),
                    p_value: f("p_value", i),
                    pass: table
                        .column("pass")
                        .unwrap()
                        .bool()
                        .unwrap()
                        .get(i)
                        .unwrap(),
                    direction: match s("direction", i).as_deref() {
                        Some("optimistic") => Some(Direction::Optimistic),
                        Some("pessimistic") => Some(Direction::Pessimistic),
                        _ => None,
                    },
                };
                (
                    bits(&t),
                    f("alpha", i).unwrap(),
                    int("runs", i).unwrap(),
                    int("burn_in_steps", i),
                )
            })
            .collect();
        assert!(want.len() > 20, "{}: {} tests", fp.label, want.len());
        assert_eq!(got, want, "{}", fp.label);
        rows += got.len();
    }
    assert_eq!(rows, table.height(), "no other rows");
}
