//! The ULog reader on the real logs the repository ships (their facts counted independently
//! with pyulog 1.2.1), the writer's round trip, and a seeded random-mutation fuzz over the
//! real logs: truncated, flipped, overwritten and shuffled bytes never panic.

use std::path::PathBuf;

use kfmc::exchange::ulog::writer::{Put, Writer};
use kfmc::exchange::ulog::{Message, Reader};
use kfmc::ulog::extract;

fn real(name: &str) -> PathBuf {
    crate::common::repo().join("tests/ulog").join(name)
}

const LOGS: [&str; 5] = [
    "px4_v1.14.3_fmu-v5_3ekf.ulg",
    "px4_v1.11.2_cubeorange.ulg",
    "px4_v1.13.0_sitl_3ekf.ulg",
    "px4_v1.15.0_sitl.ulg",
    "px4_v1.6.0_appended.ulg",
];

#[test]
fn the_real_logs_read_with_the_counts_pyulog_reads() {
    // (log, firmware, topic, instance count, records) as pyulog 1.2.1 reports them.
    let facts: [(&str, &str, &str, usize, u64); 6] = [
        (LOGS[0], "v1.14.3", "estimator_innovations", 3, 111),
        (LOGS[0], "v1.14.3", "estimator_selector_status", 1, 20),
        (LOGS[1], "v1.11.2", "estimator_innovation_variances", 1, 33),
        (
            LOGS[2],
            "v1.13.0",
            "estimator_innovations",
            3,
            1279 + 21 + 21,
        ),
        (LOGS[3], "v1.15.0", "vehicle_land_detected", 1, 39),
        (LOGS[4], "v1.6.0", "ekf2_innovations", 1, 184),
    ];
    for (log, fw, topic, instances, records) in facts {
        let x = extract::read(&real(log)).unwrap();
        assert!(
            x.firmware.as_deref().unwrap().starts_with(fw),
            "{log}: {:?}",
            x.firmware
        );
        // Instances subscribed; a log may subscribe instances that never publish (v1.13.0
        // subscribes six of estimator_innovations, three of which publish).
        let (inst, n) = &x.topics[topic];
        assert!(inst.len() >= instances, "{log} {topic}: {inst:?}");
        assert_eq!(*n, records, "{log} {topic}");
        assert!(
            !x.stats.truncated && x.stats.corrupt_bytes == 0,
            "{log}: {:?}",
            x.stats
        );
    }
    // v1.11.2 has no timestamp_sample: the innovations pair on `timestamp`, all of them.
    let x = extract::read(&real(LOGS[1])).unwrap();
    assert_eq!(x.pairing[&0].rate(), Some(1.0));
    // v1.14.3 logs each topic on its own rate limit: 23, 14 and 9 of 37 records pair.
    let x = extract::read(&real(LOGS[0])).unwrap();
    let paired: Vec<u64> = (0..3).map(|i| x.pairing[&i].paired).collect();
    assert_eq!(paired, [23, 14, 9]);
    // The gates come from the parameters, f32 as logged.
    assert_eq!(x.parameters["EKF2_GPS_P_GATE"], 5.0);
    assert!((x.parameters["EKF2_HDG_GATE"] - 2.6).abs() < 1e-6);
    // The legacy topic is counted, not judged.
    let x = extract::read(&real(LOGS[4])).unwrap();
    assert!(x.series.is_empty() && x.legacy_records == 184);
}

#[test]
fn nu_squared_over_s_is_the_test_ratio_times_the_gate_squared() {
    // The identity the issue checked on real logs, here on every paired record of v1.13.0.
    let x = extract::read(&real(LOGS[2])).unwrap();
    let mut checked = 0;
    for s in &x.series {
        let gate = match s.source.as_str() {
            "baro_hgt" => 5.0,
            "heading" => 2.6,
            _ => continue,
        };
        for r in &s.records {
            for a in &r.axes {
                if let Some(tr) = a.test_ratio.filter(|t| *t > 1e-6) {
                    let ratio = a.innovation * a.innovation / a.variance / (tr * gate * gate);
                    assert!((ratio - 1.0).abs() < 1e-3, "{} {ratio}", s.source);
                    checked += 1;
                }
            }
        }
    }
    assert!(checked > 100, "{checked}");
}

#[test]
fn a_written_log_reads_back_field_by_field() {
    let mut w = Writer::new(Vec::new(), 42).unwrap();
    w.format("inner:float a;int16_t[2] b;").unwrap();
    w.format("topic:uint64_t timestamp;inner[2] s;double d;bool ok;uint8_t[7] _padding0;")
        .unwrap();
    w.info_text("sys_name", "kfmc").unwrap();
    w.param_f32("EKF2_BARO_GATE", 2.5).unwrap();
    w.subscribe(3, 1, "topic").unwrap();
    w.data(
        3,
        &[
            ("timestamp", Put::Scalar(123.0)),
            ("s[1].a", Put::Scalar(-1.5)),
            ("s[0].b", Put::Array(&[7.0, -8.0])),
            ("d", Put::Scalar(std::f64::consts::PI)),
            ("ok", Put::Scalar(1.0)),
        ],
    )
    .unwrap();
    w.logging(b'6', 124, "hello").unwrap();
    let bytes = w.finish().unwrap();
    let mut r = Reader::new(std::io::Cursor::new(bytes), std::path::Path::new("mem")).unwrap();
    assert_eq!(r.start_us, 42);
    let mut seen = Vec::new();
    while let Some(m) = r.next_message().unwrap() {
        match m {
            Message::Info { key, .. } => seen.push(format!("info {key}")),
            Message::Parameter { name, value, .. } => seen.push(format!("param {name} {value:?}")),
            Message::Subscribed(s) => seen.push(format!("sub {} {}", s.name, s.multi_id)),
            Message::Data { sub, payload } => {
                let l = &sub.layout;
                assert_eq!(l.timestamp(payload), Some(123));
                assert_eq!(l.get(payload, "s[1].a", 0), Some(-1.5));
                assert_eq!(l.get(payload, "s[0].b", 1), Some(-8.0));
                assert_eq!(l.get(payload, "d", 0), Some(std::f64::consts::PI));
                assert_eq!(l.get(payload, "ok", 0), Some(1.0));
                assert_eq!(l.get(payload, "_padding0", 0), None);
                seen.push("data".into());
            }
            Message::Logging { text, .. } => seen.push(format!("log {text}")),
            Message::Dropout { .. } => {}
        }
    }
    assert_eq!(
        seen,
        [
            "info sys_name",
            "param EKF2_BARO_GATE Number(2.5)",
            "sub topic 1",
            "data",
            "log hello"
        ]
    );
}

/// A small deterministic generator (SplitMix64), so a failing input is reproducible from
/// its seed.
struct Mix(u64);
impl Mix {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    fn below(&mut self, n: usize) -> usize {
        (self.next() % n.max(1) as u64) as usize
    }
}

/// One mutation of `b`: truncate, flip bits, overwrite a run with random or extreme bytes,
/// duplicate or drop a slice, or swap two slices.
fn mutate(b: &mut Vec<u8>, rng: &mut Mix) -> String {
    let n = b.len();
    match rng.below(6) {
        0 => {
            let at = rng.below(n);
            b.truncate(at);
            format!("truncate at {at}")
        }
        1 => {
            let k = 1 + rng.below(16);
            for _ in 0..k {
                let at = rng.below(n);
                b[at] ^= 1 << rng.below(8);
            }
            format!("flip {k} bits")
        }
        2 => {
            let at = rng.below(n);
            let len = (1 + rng.below(64)).min(n - at);
            let fill = [0x00u8, 0xff, rng.next() as u8][rng.below(3)];
            for x in &mut b[at..at + len] {
                *x = if rng.below(2) == 0 {
                    fill
                } else {
                    rng.next() as u8
                };
            }
            format!("overwrite {len} at {at}")
        }
        3 => {
            let at = rng.below(n);
            let len = rng.below(4096).min(n - at);
            let copy = b[at..at + len].to_vec();
            let to = rng.below(b.len());
            b.splice(to..to, copy);
            format!("duplicate {len} from {at} to {to}")
        }
        4 => {
            let at = rng.below(n);
            let len = rng.below(4096).min(n - at);
            b.drain(at..at + len);
            format!("drop {len} at {at}")
        }
        _ => {
            // A message header made huge or of an unknown type, right after the header.
            let at = 16 + rng.below(n.saturating_sub(19).max(1));
            if at + 3 <= b.len() {
                b[at] = 0xff;
                b[at + 1] = 0xff;
                b[at + 2] = rng.next() as u8;
            }
            format!("header at {at}")
        }
    }
}

#[test]
fn mutated_real_logs_never_panic_the_reader_or_the_verdict() {
    let inputs: u64 = std::env::var("KFMC_FUZZ_INPUTS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(150);
    let seed: u64 = std::env::var("KFMC_FUZZ_SEED")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(20_261_207);
    let originals: Vec<Vec<u8>> = LOGS
        .iter()
        .map(|l| std::fs::read(real(l)).unwrap())
        .collect();
    let dir = tempfile::tempdir().unwrap();
    let (mut read_ok, mut refused) = (0, 0);
    for i in 0..inputs {
        let mut rng = Mix(seed ^ i.wrapping_mul(0xA24B_AED4_963E_E407));
        let which = rng.below(originals.len());
        let mut b = originals[which].clone();
        let mut what = Vec::new();
        for _ in 0..1 + rng.below(3) {
            if b.len() > 20 {
                what.push(mutate(&mut b, &mut rng));
            }
        }
        let path = dir.path().join(format!("in{i}.ulg"));
        std::fs::write(&path, &b).unwrap();
        let label = format!(
            "seed {seed} input {i}: {} with {}",
            LOGS[which],
            what.join(", ")
        );
        let outcome = std::panic::catch_unwind(|| extract::read(&path).map(|x| x.series.len()));
        match outcome {
            Err(_) => panic!("the reader panicked on {label}"),
            Ok(Ok(_)) => read_ok += 1,
            Ok(Err(e)) => {
                // A refusal names the file.
                assert!(
                    e.to_string().contains(&path.display().to_string()),
                    "{label}: {e}"
                );
                refused += 1;
            }
        }
        // Every tenth input also goes through the whole verdict, including ground samples.
        if i % 10 == 0 {
            let mut opts = kfmc::ulog::NisOptions::new(dir.path().join(format!("out{i}")));
            opts.include_ground = true;
            opts.instance = kfmc::ulog::InstanceSelection::All;
            let r = std::panic::catch_unwind(|| {
                kfmc::ulog::nis(&path, &opts, |_, _| {}).map(|o| o.cases.len())
            });
            assert!(r.is_ok(), "the verdict panicked on {label}");
        }
        std::fs::remove_file(&path).unwrap();
    }
    assert_eq!(read_ok + refused, inputs);
    assert!(read_ok > inputs / 2, "{read_ok} read, {refused} refused");
}
