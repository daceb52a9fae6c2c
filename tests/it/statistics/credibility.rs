//! Credibility measures in the tables: per-block ANEES, Li and Zhao's NCI and inclination
//! indicator, and the credible filter's reference values beside them.

use crate::common;
use crate::common::{f64s, run_cli as run, strs};
use polars::prelude::DataFrame;

/// A generic linear system: a double integrator with a position sensor. `units` are the two
/// states' units (one block when equal); `filters` are the `[[filters]]` entries.
fn spec(seed: u64, runs: usize, units: &str, filters: &str) -> String {
    format!(
        r#"
name = "credibility"
master_seed = {seed}
runs = {runs}
[model]
kind = "linear"
states = ["p", "v"]
state_units = {units}
inputs = ["u"]
measurements = ["p"]
dt_s = 0.1
a = [[0.0, 1.0], [0.0, 0.0]]
b = [[0.0], [1.0]]
c = [[1.0, 0.0]]
gamma = [[0.0], [1.0]]
q_tilde = [[0.5]]
r = [[0.2]]
[[scenarios]]
name = "s"
x0 = [0.0, 0.0]
duration_s = 8.0
{filters}
[initial_estimate]
mode = "sampled"
p0_std = 1.0
[consistency]
alpha = 0.05
"#
    )
}

fn study(text: &str) -> (tempfile::TempDir, DataFrame, DataFrame) {
    let (dir, path) = common::spec_in_tempdir(text);
    let out = dir.path().join("out");
    let (code, _, err) = run(&[
        "run",
        path.to_str().unwrap(),
        "-q",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{err}");
    let steps = common::read(&out.join("steps.parquet"));
    let cons = common::read(&out.join("consistency.parquet"));
    (dir, steps, cons)
}

/// The value of `col` on the consistency row of `filter`'s `test`.
fn cell(cons: &DataFrame, filter: &str, test: &str, col: &str) -> Option<f64> {
    let (f, t) = (strs(cons, "filter"), strs(cons, "test"));
    let i = (0..f.len())
        .find(|&i| f[i] == filter && t[i] == test)
        .unwrap_or_else(|| panic!("no row {filter}/{test}"));
    f64s(cons, col)[i]
}

const KF: &str = r#"
[[filters]]
label = "kf"
kind = "ekf"
"#;

#[test]
fn one_block_has_the_whole_state_anees() {
    // Both states in metres: one block, `position`, which is the whole state.
    let (_d, steps, cons) = study(&spec(3, 25, r#"["m", "m"]"#, KF));
    let block = f64s(&steps, "block_anees_position");
    let anees = f64s(&steps, "anees");
    assert_eq!(block, anees, "per step, bit for bit");
    assert!(block.iter().skip(1).all(Option::is_some));
    // Its band is the whole-state band.
    assert_eq!(
        f64s(&steps, "block_anees_position_lo"),
        f64s(&steps, "anees_lo")
    );
    assert_eq!(
        f64s(&steps, "block_anees_position_hi"),
        f64s(&steps, "anees_hi")
    );
    // The time average (sampled prior: no burn-in, steps 1..=K) is the verdict's ANEES.
    let stat = cell(&cons, "kf", "nees_time_average", "statistic").unwrap();
    let avg = cell(&cons, "kf", "nees_time_average", "block_anees_position").unwrap();
    assert!((stat - avg).abs() <= 1e-12 * stat, "{stat} vs {avg}");
    // No other block column.
    let blocks: Vec<String> = cons
        .get_column_names()
        .iter()
        .filter(|c| c.starts_with("block_anees_") && !c.contains("_position"))
        .map(|c| c.to_string())
        .collect();
    assert!(blocks.is_empty(), "{blocks:?}");
}

#[test]
fn two_blocks_sum_to_more_than_nothing_and_have_their_own_bands() {
    // Metres and metres per second: two blocks of one state each. Their per-step ANEES is
    // e_i²/P_ii, averaged over runs; its band is that of χ²(runs)/runs.
    let (_d, steps, cons) = study(&spec(4, 30, r#"["m", "m/s"]"#, KF));
    for b in ["position", "velocity"] {
        let v = f64s(&steps, &format!("block_anees_{b}"));
        assert!(v.iter().skip(1).all(|x| x.is_some_and(|x| x > 0.0)), "{b}");
        let avg = cell(
            &cons,
            "kf",
            "nees_time_average",
            &format!("block_anees_{b}"),
        )
        .unwrap();
        // A consistent filter: each block's average near its dimension (1).
        assert!((avg - 1.0).abs() < 0.2, "{b}: {avg}");
        let frac = cell(
            &cons,
            "kf",
            "nees_time_average",
            &format!("block_anees_{b}_inside_fraction"),
        )
        .unwrap();
        assert!(frac > 0.8, "{b}: {frac}");
    }
    let lo = f64s(&steps, "block_anees_position_lo");
    let anees_lo = f64s(&steps, "anees_lo");
    // One dof per run instead of two: a wider band, so a lower lower bound.
    assert!(lo[5].unwrap() < anees_lo[5].unwrap());
}

#[test]
fn nci_and_its_reference_are_reported_per_step_and_per_cell() {
    let (_d, steps, cons) = study(&spec(5, 20, r#"["m", "m/s"]"#, KF));
    let nci = f64s(&steps, "nci");
    let reference = f64s(&steps, "nci_credible_reference");
    // Step 0: x̂_0 drawn from N(x_0, P_0), Σ̂ regular: defined too.
    assert!(nci.iter().all(Option::is_some));
    // 20 runs of 2 quantities everywhere: one reference value.
    let r0 = reference[0].unwrap();
    assert!(reference.iter().all(|r| *r == Some(r0)));
    // A Monte Carlo of the definition at this M and n, independently seeded, agrees.
    let want = kfmc::metrics::credibility::simulate_reference(20, 2, 20_000, 99).unwrap();
    assert!((r0 - want.0).abs() < 0.03 * want.0, "{r0} vs {want:?}");
    let avg = cell(&cons, "kf", "nees_time_average", "nci").unwrap();
    let ref_avg = cell(&cons, "kf", "nees_time_average", "nci_credible_reference").unwrap();
    assert!((ref_avg - r0).abs() < 1e-12 * r0);
    // A consistent filter's NCI is near its reference (within 1.5 dB over 80 steps).
    assert!((avg - ref_avg).abs() < 1.5, "{avg} vs {ref_avg}");
}

#[test]
fn scaled_covariances_incline_the_right_way_over_replications() {
    // Q and R scaled by c scale a linear filter's P by c once the prior is forgotten: c = 0.25
    // is optimistic (inclination > 0), c = 4 pessimistic (< 0). A rate over 20 independent
    // studies (master seeds 1..=20, 20 runs each), with its Clopper–Pearson 95 % interval.
    let filters = r#"
[[filters]]
label = "small_p"
kind = "ekf"
q_scale = 0.25
r_scale = 0.25
[[filters]]
label = "large_p"
kind = "ekf"
q_scale = 4.0
r_scale = 4.0
"#;
    let reps = 20u64;
    let (mut optimistic, mut pessimistic) = (0u64, 0u64);
    for seed in 1..=reps {
        let (_d, _steps, cons) = study(&spec(seed, 20, r#"["m", "m/s"]"#, filters));
        let small = cell(&cons, "small_p", "nees_time_average", "inclination").unwrap();
        let large = cell(&cons, "large_p", "nees_time_average", "inclination").unwrap();
        optimistic += u64::from(small > 0.0);
        pessimistic += u64::from(large < 0.0);
    }
    let (lo_o, _) = kfmc::power::clopper_pearson(optimistic, reps);
    let (lo_p, _) = kfmc::power::clopper_pearson(pessimistic, reps);
    assert!(
        lo_o > 0.8 && lo_p > 0.8,
        "optimistic {optimistic}/{reps} (≥ {lo_o:.3}), pessimistic {pessimistic}/{reps} (≥ {lo_p:.3})"
    );
}

#[test]
fn studies_without_consistency_tests_have_no_credibility_columns() {
    let text = spec(6, 5, r#"["m", "m/s"]"#, KF).replace("[consistency]\nalpha = 0.05\n", "");
    let (dir, path) = common::spec_in_tempdir(&text);
    let out = dir.path().join("out");
    let (code, _, err) = run(&[
        "run",
        path.to_str().unwrap(),
        "-q",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{err}");
    let steps = common::read(&out.join("steps.parquet"));
    assert!(
        steps
            .get_column_names()
            .iter()
            .all(|c| !c.starts_with("block_anees") && *c != "nci")
    );
}

#[test]
fn covariance_information_and_square_root_forms_agree() {
    // Three implementations of one Kalman filter: the same P up to round-off, so the same
    // block ANEES, NCI and inclination to round-off.
    let filters = r#"
[[filters]]
label = "kf"
kind = "ekf"
[[filters]]
label = "information"
kind = "information"
[[filters]]
label = "sqrt"
kind = "sqrt"
"#;
    let (_d, steps, cons) = study(&spec(8, 15, r#"["m", "m/s"]"#, filters));
    for col in [
        "block_anees_position",
        "block_anees_velocity",
        "nci",
        "inclination",
    ] {
        let want = cell(&cons, "kf", "nees_time_average", col).unwrap();
        for f in ["information", "sqrt"] {
            let got = cell(&cons, f, "nees_time_average", col).unwrap();
            assert!(
                (got - want).abs() <= 1e-8 * want.abs().max(1.0),
                "{f} {col}: {got} vs {want}"
            );
        }
    }
    // Per step too.
    let f = strs(&steps, "filter");
    let nci = f64s(&steps, "nci");
    let kf: Vec<f64> = (0..f.len())
        .filter(|&i| f[i] == "kf")
        .map(|i| nci[i].unwrap())
        .collect();
    let sq: Vec<f64> = (0..f.len())
        .filter(|&i| f[i] == "sqrt")
        .map(|i| nci[i].unwrap())
        .collect();
    assert_eq!(kf.len(), sq.len());
    for (a, b) in kf.iter().zip(&sq) {
        assert!((a - b).abs() <= 1e-8 * a.max(1.0), "{a} vs {b}");
    }
}

#[test]
fn the_credibility_columns_do_not_depend_on_the_thread_count() {
    let text = spec(9, 40, r#"["m", "m/s"]"#, KF);
    let (dir, path) = common::spec_in_tempdir(&text);
    let mut tables = Vec::new();
    for threads in ["1", "2"] {
        let out = dir.path().join(format!("t{threads}"));
        let (code, _, err) = run(&[
            "run",
            path.to_str().unwrap(),
            "-q",
            "--threads",
            threads,
            "--out",
            out.to_str().unwrap(),
        ]);
        assert_eq!(code, 0, "{err}");
        tables.push(common::table_bytes(&out));
    }
    assert!(
        tables[0] == tables[1],
        "tables differ between 1 and 2 threads"
    );
}

/// The book's table of one step's NCI spread (`statistics/credibility.md`): per n, the
/// standard deviation (dB) at M = 5, 20, 200 and 1,000 runs (`None` where M < n).
fn book_nci_spread() -> Vec<(usize, [Option<f64>; 4])> {
    let page =
        std::fs::read_to_string(common::repo().join("docs/src/statistics/credibility.md")).unwrap();
    let header = "| n | M = 5 | M = 20 | M = 200 | M = 1,000 |";
    let at = page
        .find(header)
        .unwrap_or_else(|| panic!("credibility.md has no table `{header}`"));
    page[at..]
        .lines()
        .skip(2)
        .take_while(|l| l.starts_with('|'))
        .map(|l| {
            let cells: Vec<&str> = l.split('|').map(str::trim).collect();
            let n = cells[1].parse().expect("n");
            let v = |i: usize| cells[2 + i].parse::<f64>().ok();
            (n, [v(0), v(1), v(2), v(3)])
        })
        .collect()
}

/// One step's NCI (dB) from M errors e_i ~ N(0, I_n) with P = I, written from the definition
/// independently of `kfmc::metrics::credibility` (Σ̂ inverted, not factored).
fn nci_by_inverse(e: &[nalgebra::DVector<f64>]) -> f64 {
    let m = e.len() as f64;
    let n = e[0].len();
    let mut s = nalgebra::DMatrix::<f64>::zeros(n, n);
    for x in e {
        s += x * x.transpose() / m;
    }
    let inv = s.try_inverse().unwrap();
    e.iter()
        .map(|x| {
            (x.norm_squared() / (x.transpose() * &inv * x)[(0, 0)])
                .log10()
                .abs()
        })
        .sum::<f64>()
        * 10.0
        / m
}

#[test]
fn the_books_per_step_nci_spread_is_what_a_credible_filter_gives() {
    use kfmc::metrics::credibility::{asymptotic_nci_sd, simulate_spread};
    use rand::SeedableRng;
    use rand_distr::{Distribution, StandardNormal};
    const MS: [usize; 4] = [5, 20, 200, 1000];
    // A standard deviation from R replications has a relative standard error of about
    // √((κ − 1)/(4R)) (κ the kurtosis, under 4 here): 1.6 % at R = 3,000. The book's values
    // come from 20,000 replications at another seed, so 4 standard errors of the difference
    // and the table's rounding (3 significant digits) bound the gap.
    const R: usize = 3000;
    let book = book_nci_spread();
    assert_eq!(
        book.iter().map(|r| r.0).collect::<Vec<_>>(),
        vec![2, 3, 6, 9],
        "{book:?}"
    );
    let mut sd = std::collections::HashMap::new();
    for (n, row) in &book {
        for (m, stated) in MS.iter().zip(row) {
            let got = simulate_spread(*m, *n, R, 99).map(|s| s.nci_sd);
            assert_eq!(got.is_some(), stated.is_some(), "n = {n}, M = {m}");
            let (Some(got), Some(stated)) = (got, *stated) else {
                continue;
            };
            assert!(
                (got - stated).abs() <= 0.07 * got + 0.0005,
                "n = {n}, M = {m}: the book says {stated}, a credible filter gives {got:.4}"
            );
            sd.insert((*n, *m), got);
        }
    }
    // Second method at large M: the closed-form limit. At M = 1,000 the finite-M excess is
    // under 2 % (the example's 20,000 replications), so 4 standard errors and 2 % bound it.
    for n in [2, 3, 6, 9] {
        let limit = asymptotic_nci_sd(1000, n);
        let got = sd[&(n, 1000)];
        assert!(
            (got / limit - 1.0).abs() < 0.085,
            "n = {n}, M = 1,000: {got:.4} by simulation, {limit:.4} in the limit"
        );
    }
    // The spread depends on n: at M = 200 one step's NCI spreads 3.4× more in two
    // dimensions than in nine, so a single value for every n cannot stand for both.
    assert!(sd[&(2, 200)] > 3.0 * sd[&(9, 200)], "{sd:?}");
    // Second method at small M, where no limit holds: the definition written independently,
    // at its own seed.
    for (m, n) in [(5usize, 2usize), (20, 9)] {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(4242);
        let values: Vec<f64> = (0..R)
            .map(|_| {
                let e: Vec<nalgebra::DVector<f64>> = (0..m)
                    .map(|_| nalgebra::DVector::from_fn(n, |_, _| StandardNormal.sample(&mut rng)))
                    .collect();
                nci_by_inverse(&e)
            })
            .collect();
        let mean = values.iter().sum::<f64>() / R as f64;
        let own = (values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (R - 1) as f64).sqrt();
        let got = sd[&(n, m)];
        assert!(
            (got / own - 1.0).abs() < 0.07,
            "M = {m}, n = {n}: {got:.4} from kfmc, {own:.4} from the definition"
        );
    }
}
