//! Unit tests of `src/metrics/mod.rs`, kept apart so that the module reads as its role.

use super::*;

#[test]
fn quantiles_match_numpy_type_7() {
    // numpy.percentile([1, 2, 3, 4, 10], [5, 50, 95]) = [1.2, 3.0, 8.8]
    let v = [1.0, 2.0, 3.0, 4.0, 10.0];
    assert!((quantile_sorted(&v, 0.05).unwrap() - 1.2).abs() < 1e-12);
    assert_eq!(quantile_sorted(&v, 0.5), Some(3.0));
    assert!((quantile_sorted(&v, 0.95).unwrap() - 8.8).abs() < 1e-12);
    assert_eq!(quantile_sorted(&[1.0, f64::INFINITY], 0.5), None);
    assert_eq!(quantile_sorted(&[1.0, 2.0, f64::INFINITY], 0.5), Some(2.0));
}

#[test]
fn mean_std_by_hand() {
    let (m, s) = mean_std(&[2.0, 4.0, 4.0, 4.0, 5.0, 5.0, 7.0, 9.0]);
    assert_eq!(m, Some(5.0));
    assert!((s.unwrap() - (32.0f64 / 7.0).sqrt()).abs() < 1e-12);
}

#[test]
fn divergence_step_is_where_the_crossing_became_certain() {
    // Two samples (K = 1), threshold 1: RMSE² = (0 + 9)/2 = 4.5 > 1 → diverged at step 1.
    let mut v = StepValues::new(1, 1);
    v.record(&[0.0], f64::NAN, f64::NAN, 0);
    v.record(&[3.0], f64::NAN, f64::NAN, 0);
    let r = v.finish(None, Some(&[1.0]), &["x"], 0);
    assert!((r.rmse[0] - 4.5f64.sqrt()).abs() < 1e-15);
    assert_eq!(r.status.step(), Some(1));
    assert_eq!(r.status.label(), "diverged");
    assert_eq!(r.nees_mean, None);
}

#[test]
fn a_run_whose_rmse_or_mean_nees_overflows_failed_numerically() {
    // Each squared error (1e308) is finite; their sum over two steps is not.
    let mut v = StepValues::new(2, 2);
    for _ in 0..3 {
        v.record(&[1.0, 1e154], 2.0, f64::NAN, 0);
    }
    let r = v.finish(None, None, &["a", "b"], 0);
    assert_eq!(r.status.label(), "numerical_failure", "{:?}", r.status);
    assert_eq!(r.status.step(), Some(1));
    assert!(
        r.status.detail().unwrap().contains("of b"),
        "{:?}",
        r.status
    );
    // Finite errors, NEES whose sum overflows at step 2.
    let mut v = StepValues::new(1, 3);
    v.record(&[1.0], f64::NAN, f64::NAN, 0);
    for _ in 0..3 {
        v.record(&[1.0], 1e308, f64::NAN, 0);
    }
    let r = v.finish(None, None, &["a"], 0);
    assert_eq!(r.status.label(), "numerical_failure", "{:?}", r.status);
    assert_eq!(r.status.step(), Some(2));
}

#[test]
fn values_on_reused_buffers_start_as_fresh_ones() {
    // Buffers of a longer, wider run come back: the new values must not see them.
    let mut big = StepValues::new(3, 700);
    for k in 0..=700 {
        big.record(&[k as f64, 1.0, 2.0], 3.0, 4.0, 2);
    }
    drop(big);
    let mut small = StepValues::new(2, 9);
    assert_eq!(small.sq_err.len(), 20);
    assert!(
        small
            .sq_err
            .iter()
            .chain(&small.nees)
            .chain(&small.nis)
            .all(|x| x.is_nan())
    );
    assert_eq!(small.abs_err.len(), 20);
    assert!(small.abs_err.iter().all(|x| x.is_nan()));
    assert_eq!(small.nis_dof, vec![0; 10]);
    small.record(&[3.0, 4.0], f64::NAN, 1.0, 1);
    let run = small.finish(None, None, &["a", "b"], 0);
    assert_eq!(run.rmse, vec![3.0, 4.0]);
    assert_eq!((run.nees_mean, run.nis_mean), (None, Some(1.0)));
}

#[test]
fn folded_steps_equal_statistics_computed_from_the_raw_errors() {
    // Runs recorded step by step (some stopping early, some values NaN) and folded, against
    // sums, means and sorted |e| quantiles taken directly from the errors. 150 runs: two
    // full pending blocks and a partial one; 451 samples: a grid of every third step.
    use rand::{RngExt, SeedableRng};
    let mut rng = rand_pcg::Pcg64::seed_from_u64(3);
    let (nx, steps, runs) = (2, 450, 150);
    let stride = abs_err_stride(steps + 1);
    assert_eq!(stride, 3);
    // Exact |e| quantiles for every run of the cell (the default cap is 32).
    let mut acc = StepAccumulator::with_exact_cap(nx, steps, runs);
    // Per run: errors, NEES and NIS per step it reached.
    let mut raw: Vec<(Vec<f64>, Vec<f64>, Vec<f64>)> = Vec::new();
    for r in 0..runs {
        let completed = if r % 5 == 0 {
            rng.random_range(1..=steps)
        } else {
            steps + 1
        };
        let mut v = StepValues::new(nx, steps);
        let mut e = Vec::new();
        let (mut nees, mut nis) = (Vec::new(), Vec::new());
        for _ in 0..completed {
            let row: Vec<f64> = (0..nx)
                .map(|_| {
                    if rng.random::<f64>() < 0.02 {
                        f64::NAN
                    } else {
                        rng.random::<f64>() * 2.0 - 1.0
                    }
                })
                .collect();
            let x = if rng.random::<f64>() < 0.1 {
                f64::NAN
            } else {
                rng.random::<f64>() * 4.0
            };
            v.record::<2>(row.as_slice().try_into().unwrap(), x, x + 1.0, 2);
            e.extend(row);
            nees.push(x);
            nis.push(x + 1.0);
        }
        let run = v.finish(None, None, &["a", "b"], 0);
        let n = completed as f64;
        for i in 0..nx {
            let ss: f64 = e.iter().skip(i).step_by(nx).map(|x| x * x).sum();
            let want = (ss / n).sqrt();
            assert!(
                run.rmse[i] == want || (run.rmse[i].is_nan() && want.is_nan()),
                "run {r} rmse {i}"
            );
        }
        let defined: Vec<f64> = nees[1..].iter().copied().filter(|x| !x.is_nan()).collect();
        let want =
            (!defined.is_empty()).then(|| defined.iter().sum::<f64>() / defined.len() as f64);
        assert_eq!(run.nees_mean, want, "run {r}");
        acc.fold(&run.steps);
        raw.push((e, nees, nis));
    }
    let mut checked = 0;
    for k in 0..=steps {
        let row = acc.row(k);
        let reached: Vec<_> = raw.iter().filter(|(_, nees, _)| nees.len() > k).collect();
        assert_eq!(row.runs as usize, reached.len(), "step {k}");
        let nees: Vec<f64> = reached
            .iter()
            .map(|r| r.1[k])
            .filter(|x| !x.is_nan())
            .collect();
        assert_eq!(row.nees_runs as usize, nees.len());
        assert_eq!(row.nis_dof, 2 * nees.len() as u64);
        for i in 0..nx {
            let e: Vec<f64> = reached.iter().map(|r| r.0[k * nx + i]).collect();
            let mse: f64 = e.iter().map(|x| x * x).sum::<f64>() / e.len() as f64;
            assert!(row.mse[i] == mse || (row.mse[i].is_nan() && mse.is_nan()));
            if k % stride != 0 {
                assert_eq!(row.abs_err[i], [None; 3], "off the grid at step {k}");
                continue;
            }
            let mut abs: Vec<f64> = e
                .iter()
                .map(|x| (x * x).sqrt())
                .filter(|x| x.is_finite())
                .collect();
            abs.sort_by(f64::total_cmp);
            let want = ABS_ERR_QUANTILES.map(|q| quantile_sorted(&abs, q));
            assert_eq!(row.abs_err[i], want, "step {k}, state {i}");
            checked += 1;
        }
    }
    assert_eq!(checked, (steps / stride + 1) * nx);
}

#[test]
fn the_divergence_step_equals_a_step_by_step_scan() {
    // The reference: every running sum checked at every step, first (step, state) kept.
    fn scan(sq: &[f64], nx: usize, limit: &[f64]) -> Option<(usize, usize)> {
        let mut sums = vec![0.0; nx];
        for (k, row) in sq.chunks_exact(nx).enumerate() {
            for i in 0..nx {
                sums[i] += row[i];
                if sums[i] > limit[i] {
                    return Some((k, i));
                }
            }
        }
        None
    }
    use rand::{RngExt, SeedableRng};
    let mut rng = rand_pcg::Pcg64::seed_from_u64(11);
    let (nx, steps) = (3, 40);
    let mut crossings = 0;
    for case in 0..2000 {
        let mut v = StepValues::new(nx, steps - 1);
        let mut errors: Vec<f64> = (0..steps * nx)
            .map(|_| {
                // NaN before or after a crossing, and ties between states at one step.
                if rng.random::<f64>() < 0.01 {
                    f64::NAN
                } else {
                    (rng.random::<f64>() * 2.0).sqrt()
                }
            })
            .collect();
        if case % 7 == 0 {
            for k in 0..steps {
                errors[k * nx + 2] = errors[k * nx];
            }
        }
        let completed = steps - rng.random_range(0..5);
        for row in errors.chunks_exact(nx).take(completed) {
            v.record::<3>(row.try_into().unwrap(), f64::NAN, f64::NAN, 0);
        }
        let thr: Vec<f64> = (0..nx).map(|_| 0.6 + rng.random::<f64>() * 0.6).collect();
        let limit: Vec<f64> = thr.iter().map(|t| t * t * steps as f64).collect();
        let squares: Vec<f64> = errors[..completed * nx].iter().map(|e| e * e).collect();
        let want = scan(&squares, nx, &limit);
        let got = v.finish(None, Some(&thr), &["a", "b", "c"], 0);
        crossings += usize::from(want.is_some());
        assert_eq!(got.status.step(), want.map(|(k, _)| k), "case {case}");
        if let Some((_, i)) = want {
            let name = ["a", "b", "c"][i];
            assert!(
                got.status
                    .detail()
                    .unwrap()
                    .starts_with(&format!("rmse_{name} "))
            );
        }
    }
    // Both outcomes occur often enough for the comparison to mean something.
    assert!(
        (200..1800).contains(&crossings),
        "{crossings} of 2000 crossed"
    );
}
