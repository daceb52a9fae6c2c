//! Flight logs kfmc writes itself: a simulated filter's innovations with a **known** S,
//! written in the ULog format PX4 writes, so the verdict's calibration and power are tested
//! against known answers (a consistent filter, an over-confident one, …).
//!
//! Each aid source's innovation on each axis is an AR(1) series ν_k = ρ ν_{k−1} +
//! √(1 − ρ²) ε_k with marginal variance S_true; the log reports S = S_true · `s_scale`, so the
//! expected NIS is 1/`s_scale` (1: consistent; 2: over-confident, S halved; 0.5:
//! over-conservative, S doubled). A reset multiplies the innovations' variance by
//! `reset_inflation` for `reset_transient_s` seconds, as a filter's transient after a reset
//! would; `drift` makes the true variance grow linearly over the flight (non-stationary).

use std::io::BufWriter;
use std::path::Path;

use rand::{RngExt, SeedableRng};

use crate::exchange::ulog::writer::{Put, Writer};

/// Which topics carry the innovations.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Topics {
    /// `estimator_aid_src_gnss_vel` and `estimator_aid_src_baro_hgt` (PX4 v1.15 layout).
    AidSource,
    /// `estimator_innovations`, `estimator_innovation_variances` and
    /// `estimator_innovation_test_ratios`, each logged on its own rate limit (PX4 v1.13
    /// layout), so only some records pair.
    Innovations,
}

/// A simulated flight.
#[derive(Clone, Debug, PartialEq)]
pub struct Flight {
    /// File stem.
    pub name: String,
    /// Seconds logged.
    pub duration_s: f64,
    /// Take-off and landing times (s).
    pub air: (f64, f64),
    /// Updates per second of every source.
    pub rate_hz: f64,
    /// Lag-1 correlation of the innovations.
    pub rho: f64,
    /// Reported S / true S.
    pub s_scale: f64,
    /// The true variance at the end of the flight / at its start (1: stationary).
    pub drift: f64,
    /// EKF instances.
    pub instances: u8,
    /// When the primary switches from instance 0 to 1 (s).
    pub switch_at_s: Option<f64>,
    /// When instance 0 resets (s).
    pub reset_at_s: Option<f64>,
    /// Seconds after a reset whose innovations are inflated.
    pub reset_transient_s: f64,
    /// The variance factor of that transient.
    pub reset_inflation: f64,
    /// The topics written.
    pub topics: Topics,
    /// The gate γ of every source (its `EKF2_*_GATE` parameter).
    pub gate: f32,
    /// Seed of the innovations.
    pub seed: u64,
}

impl Flight {
    /// A consistent 10-minute flight at 10 Hz, white innovations, aid-source topics.
    pub fn consistent(name: &str, seed: u64) -> Flight {
        Flight {
            name: name.into(),
            duration_s: 660.0,
            air: (20.0, 640.0),
            rate_hz: 10.0,
            rho: 0.0,
            s_scale: 1.0,
            drift: 1.0,
            instances: 1,
            switch_at_s: None,
            reset_at_s: None,
            reset_transient_s: 0.0,
            reset_inflation: 1.0,
            topics: Topics::AidSource,
            gate: 5.0,
            seed,
        }
    }

    /// The flights of the test set: consistent, over-confident, over-conservative, correlated,
    /// non-stationary with a reset, a primary switch, the innovations topics, and a long
    /// flight, and a consistent flight with gates of 2 (whose rejection rate can be tested).
    pub fn presets() -> Vec<Flight> {
        let base = |n: &str, s: u64| Flight::consistent(n, s);
        vec![
            base("consistent", 1),
            Flight {
                s_scale: 0.5,
                ..base("over_confident", 2)
            },
            Flight {
                s_scale: 2.0,
                ..base("over_conservative", 3)
            },
            Flight {
                rho: 0.9,
                ..base("correlated", 4)
            },
            Flight {
                reset_at_s: Some(300.0),
                reset_transient_s: 4.0,
                reset_inflation: 25.0,
                ..base("reset", 5)
            },
            Flight {
                drift: 3.0,
                ..base("non_stationary", 6)
            },
            Flight {
                instances: 2,
                switch_at_s: Some(330.0),
                ..base("primary_switch", 7)
            },
            Flight {
                topics: Topics::Innovations,
                ..base("innovation_topics", 8)
            },
            Flight {
                gate: 2.0,
                ..base("low_gate", 10)
            },
            Flight {
                duration_s: 3700.0,
                air: (20.0, 3680.0),
                rho: 0.5,
                ..base("long", 9)
            },
        ]
    }
}

/// The sources written: (aid-source name, axes, true S, gate parameter).
const SOURCES: [(&str, usize, f64, &str); 2] = [
    ("gnss_vel", 3, 0.09, "EKF2_GPS_V_GATE"),
    ("baro_hgt", 1, 0.25, "EKF2_BARO_GATE"),
];

/// Writes `flight` as `<dir>/<name>.ulg`; returns the path.
pub fn write(flight: &Flight, dir: &Path) -> std::io::Result<std::path::PathBuf> {
    let path = dir.join(format!("{}.ulg", flight.name));
    let file = std::fs::File::create(&path)?;
    let mut w = Writer::new(BufWriter::new(file), 0)?;
    let v15 = flight.topics == Topics::AidSource;
    w.format("vehicle_land_detected:uint64_t timestamp;bool freefall;bool ground_contact;bool maybe_landed;bool landed;uint8_t[4] _padding0;")?;
    w.format("estimator_selector_status:uint64_t timestamp;uint64_t last_instance_change;uint8_t primary_instance;uint8_t instances_available;uint8_t[6] _padding0;")?;
    w.format("estimator_status:uint64_t timestamp;uint64_t timestamp_sample;uint8_t reset_count_vel_ne;uint8_t reset_count_vel_d;uint8_t reset_count_pos_ne;uint8_t reset_count_pod_d;uint8_t reset_count_quat;uint8_t[3] _padding0;")?;
    if v15 {
        w.format("estimator_aid_src_gnss_vel:uint64_t timestamp;uint64_t timestamp_sample;uint64_t time_last_fuse;uint32_t device_id;float[3] observation;float[3] observation_variance;float[3] innovation;float[3] innovation_filtered;float[3] innovation_variance;float[3] test_ratio;float[3] test_ratio_filtered;uint8_t estimator_instance;bool innovation_rejected;bool fused;uint8_t[5] _padding0;")?;
        w.format("estimator_aid_src_baro_hgt:uint64_t timestamp;uint64_t timestamp_sample;uint64_t time_last_fuse;uint32_t device_id;float observation;float observation_variance;float innovation;float innovation_filtered;float innovation_variance;float test_ratio;float test_ratio_filtered;uint8_t estimator_instance;bool innovation_rejected;bool fused;uint8_t[1] _padding0;")?;
    } else {
        for t in [
            "estimator_innovations",
            "estimator_innovation_variances",
            "estimator_innovation_test_ratios",
        ] {
            w.format(&format!("{t}:uint64_t timestamp;uint64_t timestamp_sample;float[2] gps_hvel;float gps_vvel;float[2] gps_hpos;float gps_vpos;float rng_vpos;float baro_vpos;float heading;float[3] mag_field;float airspeed;"))?;
        }
    }
    w.info_text("sys_name", "kfmc")?;
    w.info_text("ver_hw", "KFMC_SIMULATED")?;
    // v1.15.0 for the aid-source layout, v1.13.0 for the innovations topics.
    w.info_u32(
        "ver_sw_release",
        if v15 { 0x010F_00FF } else { 0x010D_00FF },
    )?;
    for (_, _, _, param) in SOURCES {
        w.param_f32(param, flight.gate)?;
    }
    w.param_i32("EKF2_LOG_VERBOSE", 1)?;
    w.subscribe(0, 0, "vehicle_land_detected")?;
    w.subscribe(1, 0, "estimator_selector_status")?;
    let n_inst = flight.instances.max(1);
    for i in 0..n_inst {
        w.subscribe(2 + u16::from(i), i, "estimator_status")?;
    }
    // Data ids: aid sources 10 + 2·instance + source; innovation topics 40 + 3·instance + t.
    for i in 0..n_inst {
        if v15 {
            w.subscribe(10 + 2 * u16::from(i), i, "estimator_aid_src_gnss_vel")?;
            w.subscribe(11 + 2 * u16::from(i), i, "estimator_aid_src_baro_hgt")?;
        } else {
            w.subscribe(40 + 3 * u16::from(i), i, "estimator_innovations")?;
            w.subscribe(41 + 3 * u16::from(i), i, "estimator_innovation_variances")?;
            w.subscribe(42 + 3 * u16::from(i), i, "estimator_innovation_test_ratios")?;
        }
    }
    let us = |s: f64| (s * 1e6).round() as u64 + 1_000_000;
    let mut rng = rand_pcg::Pcg64::seed_from_u64(flight.seed);
    let normal = rand_distr::StandardNormal;
    // One AR(1) state per instance × source × axis.
    let mut state: Vec<Vec<Vec<f64>>> = (0..n_inst)
        .map(|_| {
            SOURCES
                .iter()
                .map(|(_, axes, ..)| (0..*axes).map(|_| rng.sample::<f64, _>(normal)).collect())
                .collect()
        })
        .collect();
    let steps = (flight.duration_s * flight.rate_hz).floor() as u64;
    let innov = (1.0 - flight.rho * flight.rho).max(0.0).sqrt();
    let mut last_landed: Option<bool> = None;
    let mut last_primary: Option<u8> = None;
    let mut resets = 0u8;
    for k in 0..=steps {
        let t = k as f64 / flight.rate_hz;
        let ts = us(t);
        let landed = !(flight.air.0..flight.air.1).contains(&t);
        if last_landed != Some(landed) || k % 10 == 0 {
            w.data(
                0,
                &[
                    ("timestamp", Put::Scalar(ts as f64)),
                    ("landed", Put::Scalar(f64::from(u8::from(landed)))),
                    ("ground_contact", Put::Scalar(f64::from(u8::from(landed)))),
                ],
            )?;
            last_landed = Some(landed);
        }
        let primary = match flight.switch_at_s {
            Some(s) if t >= s && n_inst > 1 => 1,
            _ => 0,
        };
        if last_primary != Some(primary) || k % 10 == 0 {
            w.data(
                1,
                &[
                    ("timestamp", Put::Scalar(ts as f64)),
                    ("primary_instance", Put::Scalar(f64::from(primary))),
                    ("instances_available", Put::Scalar(f64::from(n_inst))),
                ],
            )?;
            last_primary = Some(primary);
        }
        let reset_now = flight
            .reset_at_s
            .is_some_and(|r| (r..r + 1.0 / flight.rate_hz).contains(&t));
        if reset_now {
            resets = resets.wrapping_add(1);
        }
        for i in 0..n_inst {
            if k % 5 == 0 || (reset_now && i == 0) {
                let r = if i == 0 { resets } else { 0 };
                w.data(
                    2 + u16::from(i),
                    &[
                        ("timestamp", Put::Scalar(ts as f64)),
                        ("timestamp_sample", Put::Scalar(ts as f64)),
                        ("reset_count_pos_ne", Put::Scalar(f64::from(r))),
                    ],
                )?;
            }
        }
        // The true variance's factor now: the drift, and a reset's transient on instance 0.
        let drift = 1.0 + (flight.drift - 1.0) * t / flight.duration_s.max(1e-9);
        for i in 0..n_inst {
            let transient = flight
                .reset_at_s
                .is_some_and(|r| i == 0 && (r..r + flight.reset_transient_s).contains(&t));
            let factor = drift
                * if transient {
                    flight.reset_inflation
                } else {
                    1.0
                };
            let mut values: Vec<Vec<(f64, f64)>> = Vec::new();
            for (s, (_, axes, s_true, _)) in SOURCES.iter().enumerate() {
                let mut v = Vec::with_capacity(*axes);
                for x in state[usize::from(i)][s].iter_mut().take(*axes) {
                    *x = flight.rho * *x + innov * rng.sample::<f64, _>(normal);
                    let nu = *x * (s_true * factor).sqrt();
                    v.push((nu, s_true * flight.s_scale));
                }
                values.push(v);
            }
            if v15 {
                write_aid(
                    &mut w,
                    10 + 2 * u16::from(i),
                    i,
                    ts,
                    &values[0],
                    flight.gate,
                )?;
                write_aid(
                    &mut w,
                    11 + 2 * u16::from(i),
                    i,
                    ts,
                    &values[1],
                    flight.gate,
                )?;
            } else {
                write_innovations(&mut w, 40 + 3 * u16::from(i), ts, &values, k, flight.gate)?;
            }
        }
        if k % 1000 == 0 {
            w.sync()?;
        }
    }
    w.finish()?;
    Ok(path)
}

fn write_aid<W: std::io::Write>(
    w: &mut Writer<W>,
    id: u16,
    instance: u8,
    ts: u64,
    v: &[(f64, f64)],
    gate: f32,
) -> std::io::Result<()> {
    let g2 = f64::from(gate).powi(2);
    let nu: Vec<f64> = v.iter().map(|x| x.0).collect();
    let s: Vec<f64> = v.iter().map(|x| x.1).collect();
    let ratio: Vec<f64> = v.iter().map(|x| x.0 * x.0 / x.1 / g2).collect();
    let rejected = ratio.iter().any(|r| *r > 1.0);
    w.data(
        id,
        &[
            ("timestamp", Put::Scalar(ts as f64 + 200.0)),
            ("timestamp_sample", Put::Scalar(ts as f64)),
            ("innovation", Put::Array(&nu)),
            ("innovation_variance", Put::Array(&s)),
            ("test_ratio", Put::Array(&ratio)),
            ("estimator_instance", Put::Scalar(f64::from(instance))),
            (
                "innovation_rejected",
                Put::Scalar(f64::from(u8::from(rejected))),
            ),
            ("fused", Put::Scalar(f64::from(u8::from(!rejected)))),
        ],
    )
}

/// The innovations topics of one update, each logged or not as a rate-limited logger would:
/// the innovations every update, the variances and test ratios on two of every three, so
/// about two thirds pair.
fn write_innovations<W: std::io::Write>(
    w: &mut Writer<W>,
    id: u16,
    ts: u64,
    v: &[Vec<(f64, f64)>],
    k: u64,
    gate: f32,
) -> std::io::Result<()> {
    let (g, b) = (&v[0], &v[1]);
    let field = |f: &dyn Fn(&(f64, f64)) -> f64| -> [Vec<f64>; 3] {
        [vec![f(&g[0]), f(&g[1])], vec![f(&g[2])], vec![f(&b[0])]]
    };
    let g2 = f64::from(gate).powi(2);
    let topics: [(u16, [Vec<f64>; 3]); 3] = [
        (id, field(&|x| x.0)),
        (id + 1, field(&|x| x.1)),
        (id + 2, field(&|x| x.0 * x.0 / x.1 / g2)),
    ];
    for (j, (tid, [hvel, vvel, baro])) in topics.iter().enumerate() {
        if j > 0 && k % 3 == 2 {
            continue;
        }
        w.data(
            *tid,
            &[
                ("timestamp", Put::Scalar(ts as f64 + 300.0)),
                ("timestamp_sample", Put::Scalar(ts as f64)),
                ("gps_hvel", Put::Array(hvel)),
                ("gps_vvel", Put::Scalar(vvel[0])),
                ("baro_vpos", Put::Scalar(baro[0])),
            ],
        )?;
    }
    Ok(())
}
