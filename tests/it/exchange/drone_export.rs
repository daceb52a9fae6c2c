//! The drone's filters update sensor by sensor and never form the joint innovation
//! covariance S: their export carries the whitened innovation L⁻¹ν with S = I, so scoring the
//! export recomputes exactly the NIS and whiteness tests of the filter's own study (before,
//! `nu_` without `S_` made every scored run a numerical failure).

use crate::common::{kfmc, read, repo};

/// `experiments/drone_principled.toml` with its `error_state` filter alone, of `kind`.
fn spec(kind: &str) -> String {
    let text = std::fs::read_to_string(repo().join("experiments/drone_principled.toml")).unwrap();
    let head = &text[..text.find("[[filters]]").unwrap()];
    let rest = &text[text.find("[[filters]]").unwrap()..];
    let tail = rest
        .match_indices("\n[")
        .find(|(i, _)| !rest[i + 1..].starts_with("[[filters]]"))
        .map_or("", |(i, _)| &rest[i..]);
    format!(
        "{}[[filters]]\nlabel = \"error_state\"\nkind = \"{kind}\"\n{tail}",
        head.replace("runs = 200", "runs = 4")
    )
}

fn ok(c: &mut std::process::Command) {
    let o = c.output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
}

#[test]
fn a_drone_export_scores_to_its_own_nis_and_whiteness() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    std::fs::write(dir.join("run.toml"), spec("error_state")).unwrap();
    std::fs::write(dir.join("ext.toml"), spec("external")).unwrap();
    ok(kfmc()
        .args(["run", "-q", "--export-estimates", "--out"])
        .arg(dir.join("run"))
        .arg(dir.join("run.toml")));
    ok(kfmc()
        .args(["simulate", "-q", "--out"])
        .arg(dir.join("sim"))
        .arg(dir.join("ext.toml")));
    ok(kfmc()
        .args(["score", "-q"])
        .arg(dir.join("sim"))
        .arg("--estimates")
        .arg(dir.join("run/estimates.parquet")));

    let runs = read(&dir.join("sim/score/runs.parquet"));
    let status = runs.column("status").unwrap().str().unwrap().clone();
    assert_eq!(runs.height(), 16);
    assert!(
        (0..runs.height()).all(|i| status.get(i) == Some("ok")),
        "{runs}"
    );
    let rows = |path: &str| {
        let df = read(&dir.join(path));
        let test = df.column("test").unwrap().str().unwrap().clone();
        let scen = df.column("scenario").unwrap().str().unwrap().clone();
        let stat = df.column("statistic").unwrap().f64().unwrap().clone();
        let mut out = Vec::new();
        for i in 0..df.height() {
            let t = test.get(i).unwrap();
            if t == "nis_time_average" || t == "innovation_whiteness" {
                out.push((scen.get(i).unwrap().to_string(), t.to_string(), stat.get(i)));
            }
        }
        out
    };
    let (own, scored) = (
        rows("run/consistency.parquet"),
        rows("sim/score/consistency.parquet"),
    );
    assert_eq!(own.len(), 8, "{own:?}");
    // The same numbers: the NIS ‖L⁻¹ν‖² and the whitened sequence are exported as they are.
    for (a, b) in own.iter().zip(&scored) {
        assert_eq!((&a.0, &a.1), (&b.0, &b.1));
        let (x, y) = (a.2.unwrap(), b.2.unwrap());
        assert!(
            (x - y).abs() <= 1e-12 * x.abs().max(1e-12),
            "{a:?} vs {b:?}"
        );
    }
}
