//! The innovation-whiteness test judges correlation, not scale, and `kfmc check` says
//! "outside" when a statistic is outside its band: the 2-D constant-velocity KF of
//! `experiments/whiteness_cv.toml`, whose truth noise is 0.5, 1 and 10 times what the filter
//! assumes (Q/R ratio kept, so the gain is optimal and the innovations white) and whose
//! Q × 3 variant has a wrong gain.
//!
//! One fixed master seed: this is the behaviour of the gate on one study, not a rate. The
//! rates are in `tests/it/statistics/calibration.rs` (exact null samples) and the docs (`kfmc power`).

use crate::common::{f64s, i64s, read, repo, run_cli, spec_in_tempdir, strs};
use kfmc::metrics::consistency::scaled_chi2_test;

const ALPHA: f64 = 0.05;

#[test]
fn whiteness_gate_ignores_the_innovations_scale_and_reports_outside_when_outside() {
    let text = std::fs::read_to_string(repo().join("experiments/whiteness_cv.toml")).unwrap()
        + "\n[[check.assert]]\nkind = \"white\"\nfilter = \"kf\"\n\n[[check.assert]]\nkind = \"consistent\"\nfilter = \"kf\"\n";
    let (dir, spec) = spec_in_tempdir(&text);
    let out = dir.path().join("out");
    let (code, stdout, err) = run_cli(&[
        "check",
        spec.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--quiet",
    ]);
    assert_eq!(code, 3, "{stdout}{err}");
    let line = |case: &str| {
        stdout
            .lines()
            .find(|l| l.contains(case))
            .unwrap_or_else(|| panic!("no case {case}: {stdout}"))
            .to_string()
    };
    for noise in ["0.5", "1", "10"] {
        // White innovations at every scale (S off by 0.25× and 100×): the whiteness test
        // passes; the old band, divided by Σ‖w‖², failed at 10 and could not fail at 0.5.
        let ok = line(&format!("white[square noise={noise} kf q=1 r=1]"));
        assert!(ok.trim_start().starts_with("PASS"), "{ok}");
        assert!(ok.contains(" in ["), "{ok}");
        // The gain error is correlation in time whatever the scale.
        let bad = line(&format!("white[square noise={noise} kf q=3 r=1]"));
        assert!(bad.trim_start().starts_with("FAIL"), "{bad}");
        assert!(
            bad.contains(" outside [") && !bad.contains(" in ["),
            "{bad}"
        );
    }
    // The verdict's line names what its row holds.
    let v = line("consistent[square noise=1 kf q=1 r=1]");
    assert!(
        v.contains("Bonferroni p-value 2·min(p_NEES, p_NIS) = ")
            && v.contains("(must exceed α = 0.0500)"),
        "{v}"
    );

    // The verdict row: statistic = p_value = min(1, 2·min(p_NEES, p_NIS)), lower = α.
    let c = read(&out.join("consistency.parquet"));
    let col = |name: &str| -> Vec<Option<f64>> {
        c.column(name).unwrap().f64().unwrap().iter().collect()
    };
    let test: Vec<String> = c
        .column("test")
        .unwrap()
        .str()
        .unwrap()
        .iter()
        .map(|s| s.unwrap().to_string())
        .collect();
    let (stat, lower, dof, p) = (col("statistic"), col("lower"), col("dof"), col("p_value"));
    let pass: Vec<Option<bool>> = c.column("pass").unwrap().bool().unwrap().iter().collect();
    let mut verdicts = 0;
    for i in 0..c.height() {
        if test[i] != "verdict" {
            continue;
        }
        // A cell's rows come together, the verdict last: its tests are the nearest above.
        let cell = |name: &str| (0..i).rev().find(|&j| test[j] == name).unwrap();
        let (pa, pb) = (
            p[cell("nees_time_average")].unwrap(),
            p[cell("nis_time_average")].unwrap(),
        );
        let want = (2.0 * pa.min(pb)).min(1.0);
        assert_eq!(
            (stat[i], p[i], lower[i]),
            (Some(want), Some(want), Some(ALPHA))
        );
        assert_eq!(pass[i], Some(want > ALPHA));
        verdicts += 1;
    }
    assert_eq!(verdicts, 6);

    // The report draws the NIS time average in the α/2 band the verdict judges it by: for
    // two components at every step, mean·ν/2 ~ χ²(ν) with the row's dof ν.
    let (code, o, e) = run_cli(&["report", out.to_str().unwrap()]);
    assert_eq!(code, 0, "{o}{e}");
    let html = std::fs::read_to_string(out.join("report.html")).unwrap();
    let table = &html[html.find("id=\"verdict-table\"").unwrap()..];
    let table = &table[..table.find("</table>").unwrap()];
    let nis = (0..c.height())
        .find(|&i| test[i] == "nis_time_average")
        .unwrap();
    let half =
        scaled_chi2_test("x", stat[nis].unwrap(), 2.0, dof[nis].unwrap(), ALPHA / 2.0).unwrap();
    let own = (lower[nis].unwrap(), half.lower.unwrap());
    let shown = |x: f64| format!("[{:.3}", x);
    assert!(
        table.contains(&shown(own.1)),
        "α/2 band {own:?} not drawn: {table}"
    );
    assert!(
        !table.contains(&shown(own.0)),
        "α band {own:?} drawn: {table}"
    );
    assert!(html.contains("at α/2 each"));
}

/// A slow oscillator (period 20 s, sampled every 0.1 s) whose position is measured: its KF
/// has the right gain at every noise scale (Q/R kept), but its prior P0 is not scaled with
/// `noise.scales`. At × 0.1 the initial error is therefore 10× larger, in standard
/// deviations, than the filter's model of the noise would make it, and the innovations of
/// the first few seconds, dominated by the prior's decay, are correlated in time.
const OSCILLATOR: &str = r#"
name = "whiteness_oscillator"
master_seed = 7
runs = 20
[model]
kind = "linear"
states = ["x", "v"]
measurements = ["x"]
dt_s = 0.1
a = [[0.0, 1.0], [-0.098696, 0.0]]
gamma = [[0.0], [1.0]]
q_tilde = [[0.01]]
c = [[1.0, 0.0]]
r = [[1.0]]
[[scenarios]]
name = "swing"
x0 = [5.0, 0.0]
duration_s = 40.0
[[filters]]
label = "kf"
kind = "ekf"
[noise]
scales = [0.1, 1.0]
filter_noise = "nominal"
[initial_estimate]
mode = "sampled"
p0_std = 1.0
[consistency]
alpha = 0.05
whiteness_lags = 5
"#;

/// `kfmc power` of the oscillator with `extra` appended to `[consistency]`: per noise scale,
/// the whiteness test's (rejections, replications, Clopper–Pearson 95 % interval).
fn oscillator_whiteness(extra: &str, replications: usize) -> Vec<(f64, i64, i64, f64, f64)> {
    let (dir, spec) = spec_in_tempdir(&format!("{OSCILLATOR}{extra}"));
    let out = dir.path().join("power");
    let (code, o, e) = run_cli(&[
        "power",
        "-q",
        "-R",
        &replications.to_string(),
        "--threads",
        "2",
        "--out",
        out.to_str().unwrap(),
        spec.to_str().unwrap(),
    ]);
    assert_eq!(code, 0, "{o}{e}");
    let df = read(&out.join("power.parquet"));
    let (scale, test) = (f64s(&df, "noise_scale"), strs(&df, "test"));
    let (rej, reps) = (i64s(&df, "rejections"), i64s(&df, "replications"));
    let (lo, hi) = (f64s(&df, "rejection_ci_lo"), f64s(&df, "rejection_ci_hi"));
    (0..df.height())
        .filter(|&i| test[i] == "innovation_whiteness")
        .map(|i| {
            (
                scale[i].unwrap(),
                rej[i],
                reps[i],
                lo[i].unwrap(),
                hi[i].unwrap(),
            )
        })
        .collect()
}

#[test]
fn a_whiteness_burn_in_forgets_a_prior_that_is_not_scaled_with_the_noise() {
    const R: usize = 200;
    let without = oscillator_whiteness("", R);
    let with = oscillator_whiteness("whiteness_burn_in = 150\n", R);
    assert_eq!((without.len(), with.len()), (2, 2), "{without:?} {with:?}");
    for (&(scale, rej, reps, lo, hi), &(scale_b, rej_b, reps_b, lo_b, hi_b)) in
        without.iter().zip(&with)
    {
        assert_eq!((scale, reps, reps_b), (scale_b, R as i64, R as i64));
        // With the first 15 s left out, the false-alarm rate is α's at both scales: α lies
        // in the Clopper–Pearson interval of the rate.
        assert!(
            lo_b <= ALPHA && ALPHA <= hi_b,
            "noise × {scale}, burn-in 150: {rej_b}/{reps_b} rejections, [{lo_b:.3}, {hi_b:.3}]"
        );
        if scale == 0.1 {
            // Without it the prior's decay is read as correlation: far above α.
            assert!(
                lo > ALPHA,
                "noise × 0.1, no burn-in: {rej}/{reps} rejections, [{lo:.3}, {hi:.3}]"
            );
        } else {
            // At × 1 the prior is the filter's own: white from the first step.
            assert!(
                lo <= ALPHA && ALPHA <= hi,
                "noise × 1, no burn-in: {rej}/{reps} rejections, [{lo:.3}, {hi:.3}]"
            );
        }
    }
}
