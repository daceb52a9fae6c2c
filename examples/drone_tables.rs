//! Prints a drone study's results in the layout of seed 004's Tables 1–3: per route and
//! quantity, each sensor's RMSE against the truth (the `sensors` table, on the seed's 100 Hz
//! grid and natively) beside every filter's RMSE (the `summary` table), as Monte Carlo
//! means with p5–p95, and the seed's single-run numbers for comparison.
//!
//! ```text
//! cargo run --release --example drone_tables -- results/drone_paper
//! ```

use std::path::Path;

use kfmc::output::table::read;
use kfmc::systems::drone::{SEED_EKF_RMSE, SEED_TABLES};

struct Row {
    scenario: String,
    key: String,
    filter: String,
    mean: f64,
    p05: f64,
    p95: f64,
}

fn rows(path: &Path, key: &str, prefix: &str) -> Vec<Row> {
    let df = read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let text = |c: &str| df.column(c).unwrap().str().unwrap().clone();
    let num = |c: &str| df.column(c).unwrap().f64().unwrap().clone();
    let (s, k) = (text("scenario"), text(key));
    let f = df.column("filter").ok().map(|c| c.str().unwrap().clone());
    let (m, lo, hi) = (
        num(&format!("{prefix}mean")),
        num(&format!("{prefix}p05")),
        num(&format!("{prefix}p95")),
    );
    (0..df.height())
        .map(|i| Row {
            scenario: s.get(i).unwrap_or("").into(),
            key: k.get(i).unwrap_or("").into(),
            filter: f.as_ref().and_then(|f| f.get(i)).unwrap_or("").into(),
            mean: m.get(i).unwrap_or(f64::NAN),
            p05: lo.get(i).unwrap_or(f64::NAN),
            p95: hi.get(i).unwrap_or(f64::NAN),
        })
        .collect()
}

fn cell(r: Option<&Row>) -> String {
    r.map_or("—".into(), |r| {
        format!("{:.3} [{:.3}–{:.3}]", r.mean, r.p05, r.p95)
    })
}

fn main() {
    let dir = std::env::args()
        .nth(1)
        .expect("usage: drone_tables RESULTS_DIR");
    let dir = Path::new(&dir);
    let sensors = rows(&dir.join("sensors.parquet"), "metric", "");
    let summary = rows(&dir.join("summary.parquet"), "state", "rmse_");
    let mut scenarios: Vec<String> = sensors.iter().map(|r| r.scenario.clone()).collect();
    scenarios.dedup();
    let mut filters: Vec<String> = summary.iter().map(|r| r.filter.clone()).collect();
    filters.sort();
    filters.dedup();
    let quantities = [
        ("px", "m", vec!["gps_px", "imu_px"]),
        ("py", "m", vec!["gps_py", "imu_py"]),
        ("pz", "m", vec!["gps_pz", "imu_pz", "baro_pz"]),
        ("vx", "m/s", vec!["gps_vx"]),
        ("vy", "m/s", vec!["gps_vy"]),
        ("vz", "m/s", vec!["gps_vz"]),
        ("roll", "deg", vec!["imu_roll"]),
        ("pitch", "deg", vec!["imu_pitch"]),
        ("yaw", "deg", vec!["imu_yaw"]),
    ];
    for s in &scenarios {
        let table = match s.as_str() {
            "linear" => Some(0),
            "sinusoidal" => Some(1),
            "ramp" => Some(2),
            _ => None,
        };
        println!(
            "\n## {s}{}",
            table.map_or(String::new(), |t| format!(" (seed Table {})", t + 1))
        );
        print!("| quantity | sensor RMSE, grid (native) |");
        for f in &filters {
            print!(" {f} |");
        }
        println!(" seed sensor | seed EKF |");
        println!("|---|---|{}---|---|", "---|".repeat(filters.len()));
        for (qi, (q, unit, metrics)) in quantities.iter().enumerate() {
            let mut sensor_cells = Vec::new();
            for m in metrics {
                let find = |name: &str| sensors.iter().find(|r| &r.scenario == s && r.key == name);
                let text = match (find(&format!("{m}_grid")), find(&format!("{m}_native"))) {
                    (Some(g), Some(n)) => format!("{m}: {} ({:.3})", cell(Some(g)), n.mean),
                    _ => format!("{m}: {}", cell(find(m))),
                };
                sensor_cells.push(text);
            }
            print!("| {q} ({unit}) | {} |", sensor_cells.join("; "));
            for f in &filters {
                let r = summary
                    .iter()
                    .find(|r| &r.scenario == s && &r.filter == f && &r.key == q);
                print!(" {} |", cell(r));
            }
            let seed_sensor = table.map_or("—".into(), |t| {
                let idx: &[usize] = match qi {
                    0 => &[0, 6],
                    1 => &[1, 7],
                    2 => &[2, 8, 9],
                    3..=5 => &[qi],
                    _ => &[qi + 4],
                };
                idx.iter()
                    .map(|&i| format!("{:.3}", SEED_TABLES[t][i]))
                    .collect::<Vec<_>>()
                    .join(", ")
            });
            let seed_ekf = table.map_or("—".into(), |t| format!("{:.3}", SEED_EKF_RMSE[t][qi]));
            println!(" {seed_sensor} | {seed_ekf} |");
        }
        for m in [
            "accel_x", "accel_y", "accel_z", "gyro_x", "gyro_y", "gyro_z",
        ] {
            let r = sensors.iter().find(|r| &r.scenario == s && r.key == m);
            println!("| {m} | {} |{} | |", cell(r), " |".repeat(filters.len()));
        }
    }
}
