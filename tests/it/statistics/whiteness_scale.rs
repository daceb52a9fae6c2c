//! The innovation-whiteness test judges correlation, not scale, and `kfmc check` says
//! "outside" when a statistic is outside its band: the 2-D constant-velocity KF of
//! `experiments/whiteness_cv.toml`, whose truth noise is 0.5, 1 and 10 times what the filter
//! assumes (Q/R ratio kept, so the gain is optimal and the innovations white) and whose
//! Q × 3 variant has a wrong gain.
//!
//! One fixed master seed: this is the behaviour of the gate on one study, not a rate. The
//! rates are in `tests/it/statistics/calibration.rs` (exact null samples) and the docs (`kfmc power`).

use crate::common::{read, repo, run_cli, spec_in_tempdir};
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
