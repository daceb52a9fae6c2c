//! Numerical trouble is data: every built-in filter kind, driven into non-finite values or a
//! covariance that is not positive definite, records it in its run's row (status, step,
//! detail, or a counted covariance repair) and the batch completes with every row written.

use crate::common::kfmc;

fn run(spec: &str) -> polars::prelude::DataFrame {
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join("s.toml");
    let out = tmp.path().join("out");
    std::fs::write(&path, spec).unwrap();
    let o = kfmc()
        .args(["run", path.to_str().unwrap(), "--quiet", "--out"])
        .arg(&out)
        .output()
        .unwrap();
    assert_eq!(
        o.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&o.stderr)
    );
    kfmc::output::table::read(&out.join("runs.parquet")).unwrap()
}

/// (filter, status, detail, covariance repairs) of every row.
fn rows(df: &polars::prelude::DataFrame) -> Vec<(String, String, String, i64)> {
    let s = |c: &str| df.column(c).unwrap().str().unwrap().clone();
    let (f, st, d) = (s("filter"), s("status"), s("status_detail"));
    let rep = df
        .column("covariance_repairs")
        .unwrap()
        .i64()
        .unwrap()
        .clone();
    (0..df.height())
        .map(|i| {
            (
                f.get(i).unwrap().to_string(),
                st.get(i).unwrap().to_string(),
                d.get(i).unwrap_or("").to_string(),
                rep.get(i).unwrap(),
            )
        })
        .collect()
}

const PLANAR_FILTERS: &str = r#"
[[filters]]
label = "ekf"
kind = "ekf"
QSTD
[[filters]]
label = "joseph"
kind = "ekf"
covariance_update = "joseph"
QSTD
[[filters]]
label = "information"
kind = "information"
QSTD
[[filters]]
label = "sqrt"
kind = "sqrt"
QSTD
[[filters]]
label = "open_loop"
kind = "open_loop"
QSTD
[[filters]]
label = "ukf"
kind = "ukf"
QSTD
[[filters]]
label = "ckf"
kind = "ckf"
QSTD
"#;

#[test]
fn every_filter_records_non_finite_values_and_the_batch_completes() {
    // Thrusts of 1e306 N overflow the state within a step: every estimate becomes non-finite.
    let planar = format!(
        "runs = 4\n[model]\nkind = \"planar_quadrotor\"\n[[scenarios]]\nname = \"blowup\"\nx0 = [0.0, 0.0, 1.0, 0.0, 0.0, 0.0]\nduration_s = 1.0\nstages = [{{ from_step = 0, thrust_n = [1e306, 1e300] }}]\n{}[[filters]]\nlabel = \"running_mean\"\nkind = \"running_mean\"\n",
        PLANAR_FILTERS.replace("QSTD\n", "")
    );
    // L1 started at 1.7e308 m and m/s: x + ẋΔt overflows at the first step.
    let linear = "runs = 4\n[model]\nkind = \"linear_quadrotor\"\n[[scenarios]]\nname = \"blowup\"\nx0 = [1.7e308, 1.7e308, 1.0, 0.0, 1.0, 0.0]\nduration_s = 2.0\n[[filters]]\nlabel = \"kf\"\nkind = \"ekf\"\n[[filters]]\nlabel = \"steady_state\"\nkind = \"steady_state\"\n[[filters]]\nlabel = \"pole_placement\"\nkind = \"pole_placement\"\npole_scale = 0.5\n[[filters]]\nlabel = \"information\"\nkind = \"information\"\n[[filters]]\nlabel = \"sqrt\"\nkind = \"sqrt\"\n[[filters]]\nlabel = \"open_loop\"\nkind = \"open_loop\"\n[[filters]]\nlabel = \"ukf\"\nkind = \"ukf\"\n[[filters]]\nlabel = \"ckf\"\nkind = \"ckf\"\n";
    for (spec, filters) in [(planar, 8), (linear.to_string(), 8)] {
        let r = rows(&run(&spec));
        assert_eq!(
            r.len(),
            4 * filters,
            "every run of every filter has its row"
        );
        for (f, status, detail, _) in &r {
            assert_eq!(status, "numerical_failure", "{f}: {detail}");
            // Overflow shows as a non-finite value, or (the information form inverts first) as
            // a matrix that is no longer positive definite.
            assert!(
                detail.contains("non-finite") || detail.contains("not positive definite"),
                "{f}: {detail}"
            );
        }
    }
}

#[test]
fn a_covariance_that_is_not_positive_definite_is_a_failure_or_a_counted_repair() {
    // P0 = 10⁻⁶⁰⁰ I underflows to 0 and Q = 0: the covariance is singular from the start.
    let spec = format!(
        "runs = 4\n[model]\nkind = \"planar_quadrotor\"\n[[scenarios]]\nname = \"basic\"\nduration_s = 1.0\n{}[initial_estimate]\np0_std = 1e-300\n",
        PLANAR_FILTERS.replace("QSTD", "q_std = 0.0")
    );
    let r = rows(&run(&spec));
    assert_eq!(r.len(), 4 * 7);
    for (f, status, detail, repairs) in &r {
        let failed = status == "numerical_failure" && detail.contains("not positive definite");
        assert!(
            failed || *repairs > 0,
            "{f}: status {status} ({detail}), {repairs} repairs"
        );
    }
}
