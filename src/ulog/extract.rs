//! From a ULog file to the innovation records of each EKF instance and aid source, with what
//! the verdict needs beside them: when the vehicle was in the air, which instance was the
//! primary, when each instance reset, and the gates of the log's parameters.
//!
//! Sources, by preference:
//! * `estimator_aid_src_<source>` (PX4 ≥ 1.14): one record per fusion attempt with the
//!   innovation, its variance, the test ratio, `innovation_rejected` and `fused` (scalars or
//!   per-axis arrays, by version) and `estimator_instance`;
//! * otherwise `estimator_innovations` joined with `estimator_innovation_variances` (and
//!   `estimator_innovation_test_ratios`) on `timestamp_sample` (`timestamp` before v1.12) and
//!   instance. Each topic is logged on its own rate limit, so only some records pair; the
//!   unpaired are counted. A source's record that repeats the previous one's values exactly
//!   was not updated in between (stale) and is dropped, as is one whose variance is not
//!   positive (the source was not in use);
//! * the legacy `ekf2_innovations` (before v1.11) is counted for `inspect`, not judged.

use std::collections::{BTreeMap, HashMap};
use std::path::Path;

use crate::exchange::ulog::{InfoValue, Layout, Message, Reader, UlogError};

/// Which topics a source's records came from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Family {
    /// `estimator_aid_src_*`.
    AidSource,
    /// `estimator_innovations` + `estimator_innovation_variances`.
    Innovations,
}

/// One axis of one record.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AxisValue {
    /// The innovation ν.
    pub innovation: f64,
    /// Its variance S (the diagonal element of HPHᵀ + R).
    pub variance: f64,
    /// PX4's test ratio ν²/(γ²S), when logged.
    pub test_ratio: Option<f64>,
    /// Whether PX4 rejected it, when logged.
    pub rejected: Option<bool>,
    /// Whether PX4 fused it, when logged.
    pub fused: Option<bool>,
}

/// One record of a source: every axis at one filter update.
#[derive(Clone, Debug, PartialEq)]
pub struct Record {
    /// The update's time (`timestamp_sample`, else `timestamp`), µs.
    pub t_us: u64,
    /// Per axis.
    pub axes: Vec<AxisValue>,
}

/// The records of one source of one EKF instance, in time order.
#[derive(Clone, Debug, PartialEq)]
pub struct SourceSeries {
    /// The aid source (`gnss_vel`, `baro_hgt`, …).
    pub source: String,
    /// The EKF instance.
    pub instance: u8,
    /// The topics it came from.
    pub family: Family,
    /// The records.
    pub records: Vec<Record>,
    /// Records dropped as stale repeats.
    pub stale: u64,
}

/// Pairing of `estimator_innovations` with `estimator_innovation_variances`, per instance.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Pairing {
    /// Innovation records.
    pub innovations: u64,
    /// Variance records.
    pub variances: u64,
    /// Innovation records with a variance record of the same update.
    pub paired: u64,
}

impl Pairing {
    /// Paired innovation records / innovation records.
    pub fn rate(&self) -> Option<f64> {
        (self.innovations > 0).then(|| self.paired as f64 / self.innovations as f64)
    }
}

/// Everything `ulog inspect` and `ulog nis` read from one log.
#[derive(Clone, Debug, Default)]
pub struct Extract {
    /// The header's start time (µs).
    pub start_us: u64,
    /// The last timestamp seen (µs).
    pub end_us: u64,
    /// `ver_sw_release` as `v1.14.3`, when logged.
    pub firmware: Option<String>,
    /// `ver_hw`.
    pub hardware: Option<String>,
    /// Parameters (initial values; a change in flight is counted apart).
    pub parameters: BTreeMap<String, f64>,
    /// Parameters changed while logging.
    pub parameter_changes: u64,
    /// (time µs, landed) from `vehicle_land_detected`.
    pub landed: Vec<(u64, bool)>,
    /// (time µs, primary instance) from `estimator_selector_status`.
    pub primary: Vec<(u64, u8)>,
    /// Per instance, the times (µs) at which one of its `estimator_status` reset counters
    /// changed.
    pub resets: BTreeMap<u8, Vec<u64>>,
    /// Per instance, the first time (µs) it published anything.
    pub first_seen: BTreeMap<u8, u64>,
    /// The judged series.
    pub series: Vec<SourceSeries>,
    /// Per instance, the pairing of the innovations topics (empty with aid sources only).
    pub pairing: BTreeMap<u8, Pairing>,
    /// Records of the legacy `ekf2_innovations` topic (inspected, not judged).
    pub legacy_records: u64,
    /// Topic name → (instances, records), every topic of the log.
    pub topics: BTreeMap<String, (Vec<u8>, u64)>,
    /// The reader's notes on damage and truncation.
    pub stats: crate::exchange::ulog::Stats,
}

/// `estimator_innovations` fields → (source, axis). Sources are named as PX4's aid-source
/// topics name them, so both families of topics meet in the same rows.
const INNOVATION_FIELDS: &[(&str, usize, &str, usize)] = &[
    ("gps_hvel", 0, "gnss_vel", 0),
    ("gps_hvel", 1, "gnss_vel", 1),
    ("gps_vvel", 0, "gnss_vel", 2),
    ("gps_hpos", 0, "gnss_pos", 0),
    ("gps_hpos", 1, "gnss_pos", 1),
    ("gps_vpos", 0, "gnss_hgt", 0),
    ("ev_hvel", 0, "ev_vel", 0),
    ("ev_hvel", 1, "ev_vel", 1),
    ("ev_vvel", 0, "ev_vel", 2),
    ("ev_hpos", 0, "ev_pos", 0),
    ("ev_hpos", 1, "ev_pos", 1),
    ("ev_vpos", 0, "ev_hgt", 0),
    ("fake_hvel", 0, "fake_vel", 0),
    ("fake_hvel", 1, "fake_vel", 1),
    ("fake_vvel", 0, "fake_vel", 2),
    ("fake_hpos", 0, "fake_pos", 0),
    ("fake_hpos", 1, "fake_pos", 1),
    ("fake_vpos", 0, "fake_hgt", 0),
    ("rng_vpos", 0, "rng_hgt", 0),
    ("baro_vpos", 0, "baro_hgt", 0),
    ("aux_hvel", 0, "aux_vel", 0),
    ("aux_hvel", 1, "aux_vel", 1),
    ("aux_vvel", 0, "aux_vel", 2),
    ("flow", 0, "optical_flow", 0),
    ("flow", 1, "optical_flow", 1),
    ("terr_flow", 0, "terrain_flow", 0),
    ("terr_flow", 1, "terrain_flow", 1),
    ("heading", 0, "heading", 0),
    ("mag_field", 0, "mag", 0),
    ("mag_field", 1, "mag", 1),
    ("mag_field", 2, "mag", 2),
    ("gravity", 0, "gravity", 0),
    ("gravity", 1, "gravity", 1),
    ("gravity", 2, "gravity", 2),
    ("drag", 0, "drag", 0),
    ("drag", 1, "drag", 1),
    ("airspeed", 0, "airspeed", 0),
    ("beta", 0, "sideslip", 0),
    ("hagl", 0, "terrain_range", 0),
    ("hagl_rate", 0, "terrain_rate", 0),
];

/// The gate parameter of a source (`EKF2_*_GATE`), newest name first.
pub fn gate_parameters(source: &str) -> &'static [&'static str] {
    match source {
        "baro_hgt" => &["EKF2_BARO_GATE"],
        "gnss_pos" | "gnss_hgt" => &["EKF2_GPS_P_GATE"],
        "gnss_vel" => &["EKF2_GPS_V_GATE"],
        "heading" | "mag_heading" | "gnss_yaw" | "ev_yaw" => &["EKF2_HDG_GATE"],
        "mag" => &["EKF2_MAG_GATE"],
        "airspeed" => &["EKF2_TAS_GATE"],
        "sideslip" => &["EKF2_BETA_GATE"],
        "optical_flow" | "terrain_flow" => &["EKF2_OF_GATE"],
        "rng_hgt" | "terrain_range" => &["EKF2_RNG_GATE"],
        "ev_pos" | "ev_hgt" => &["EKF2_EVP_GATE", "EKF2_EV_GATE"],
        "ev_vel" => &["EKF2_EVV_GATE", "EKF2_EV_GATE"],
        "aux_vel" => &["EKF2_AVEL_GATE"],
        "gravity" => &["EKF2_GRAV_GATE"],
        _ => &[],
    }
}

/// `ver_sw_release` (0xAABBCCTT: major, minor, patch, type) as `v1.14.3`.
pub fn firmware_name(v: u32) -> String {
    let tag = match v & 0xff {
        0 => "-dev",
        0x40..=0x7f => "-alpha",
        0x80..=0xbf => "-beta",
        0xc0..=0xfe => "-rc",
        _ => "",
    };
    format!("v{}.{}.{}{tag}", v >> 24, (v >> 16) & 0xff, (v >> 8) & 0xff)
}

/// The per-instance state of the innovations topics while reading.
#[derive(Default)]
struct InnovationTopics {
    /// (instance, time) → values of every mapped field of the variances and test ratios.
    variances: HashMap<(u8, u64), Vec<Option<f64>>>,
    ratios: HashMap<(u8, u64), Vec<Option<f64>>>,
    /// (instance, time, values) of the innovations, in log order.
    innovations: Vec<(u8, u64, Vec<Option<f64>>)>,
}

/// The mapped fields' values of a sample (None where the layout lacks the field).
fn mapped_values(layout: &Layout, payload: &[u8]) -> Vec<Option<f64>> {
    INNOVATION_FIELDS
        .iter()
        .map(|(field, i, _, _)| layout.get(payload, field, *i))
        .collect()
}

/// The update time of a sample: `timestamp_sample`, else `timestamp`.
fn sample_time(layout: &Layout, payload: &[u8]) -> Option<u64> {
    layout
        .u64_field(payload, "timestamp_sample")
        .or_else(|| layout.timestamp(payload))
}

/// Reads `path` once, streaming.
pub fn read(path: &Path) -> Result<Extract, UlogError> {
    let mut r = Reader::open(path)?;
    let mut x = Extract {
        start_us: r.start_us,
        ..Extract::default()
    };
    let mut topics = InnovationTopics::default();
    let mut aid: BTreeMap<(u8, String), SourceSeries> = BTreeMap::new();
    let mut last_resets: HashMap<u8, Vec<f64>> = HashMap::new();
    while let Some(msg) = r.next_message()? {
        match msg {
            Message::Info { key, value } => match (key, value) {
                ("ver_sw_release", InfoValue::Number(v)) => {
                    x.firmware = Some(firmware_name(v as u32));
                }
                ("ver_hw", InfoValue::Text(t)) => x.hardware = Some(t),
                _ => {}
            },
            Message::Parameter {
                name,
                value: InfoValue::Number(v),
                changed,
            } => {
                if changed {
                    x.parameter_changes += 1;
                } else {
                    x.parameters.insert(name.to_string(), v);
                }
            }
            Message::Subscribed(sub) => {
                let e = x.topics.entry(sub.name.clone()).or_default();
                if !e.0.contains(&sub.multi_id) {
                    e.0.push(sub.multi_id);
                }
            }
            Message::Data { sub, payload } => {
                let l = &sub.layout;
                let Some(ts) = l.timestamp(payload) else {
                    continue;
                };
                x.end_us = x.end_us.max(ts);
                if let Some(e) = x.topics.get_mut(&sub.name) {
                    e.1 += 1;
                }
                let inst = sub.multi_id;
                match sub.name.as_str() {
                    "vehicle_land_detected" => {
                        if let Some(v) = l.get(payload, "landed", 0) {
                            x.landed.push((ts, v != 0.0));
                        }
                    }
                    "estimator_selector_status" => {
                        if let Some(v) = l.get(payload, "primary_instance", 0) {
                            x.primary.push((ts, v as u8));
                        }
                    }
                    "estimator_status" => {
                        x.first_seen.entry(inst).or_insert(ts);
                        let counters: Vec<f64> = l
                            .fields
                            .iter()
                            .filter(|f| f.name.contains("reset_count"))
                            .filter_map(|f| l.value(payload, f, 0))
                            .collect();
                        let last = last_resets.entry(inst).or_insert_with(|| counters.clone());
                        if *last != counters {
                            x.resets.entry(inst).or_default().push(ts);
                            *last = counters;
                        }
                    }
                    "estimator_innovations" => {
                        if let Some(t) = sample_time(l, payload) {
                            x.first_seen.entry(inst).or_insert(ts);
                            topics
                                .innovations
                                .push((inst, t, mapped_values(l, payload)));
                        }
                    }
                    "estimator_innovation_variances" => {
                        if let Some(t) = sample_time(l, payload) {
                            topics
                                .variances
                                .insert((inst, t), mapped_values(l, payload));
                        }
                    }
                    "estimator_innovation_test_ratios" => {
                        if let Some(t) = sample_time(l, payload) {
                            topics.ratios.insert((inst, t), mapped_values(l, payload));
                        }
                    }
                    "ekf2_innovations" => x.legacy_records += 1,
                    name => {
                        if let Some(source) = name.strip_prefix("estimator_aid_src_") {
                            aid_record(&mut aid, source, inst, l, payload, ts);
                        }
                    }
                }
            }
            _ => {}
        }
    }
    x.stats = r.stats.clone();
    // The variance records per instance, for the pairing rates.
    for &(inst, _) in topics.variances.keys() {
        x.pairing.entry(inst).or_default().variances += 1;
    }
    let have_aid: std::collections::BTreeSet<(u8, String)> = aid.keys().cloned().collect();
    x.series = aid.into_values().collect();
    x.series
        .extend(pair_innovations(&topics, &mut x.pairing, &have_aid));
    x.series
        .sort_by(|a, b| (a.instance, &a.source).cmp(&(b.instance, &b.source)));
    Ok(x)
}

/// One `estimator_aid_src_<source>` sample into its series.
fn aid_record(
    aid: &mut BTreeMap<(u8, String), SourceSeries>,
    source: &str,
    multi_id: u8,
    l: &Layout,
    payload: &[u8],
    ts: u64,
) {
    let Some(innov) = l.field("innovation") else {
        return;
    };
    let instance = l
        .get(payload, "estimator_instance", 0)
        .map_or(multi_id, |v| v as u8);
    let t = sample_time(l, payload).unwrap_or(ts);
    let flag = |name: &str, i: usize| -> Option<bool> {
        let f = l.field(name)?;
        // A scalar flag (v1.15) covers every axis; an array (v1.14) has one per axis.
        let at = if f.count > 1 { i } else { 0 };
        l.value(payload, f, at).map(|v| v != 0.0)
    };
    let mut axes = Vec::with_capacity(innov.count);
    for i in 0..innov.count {
        let (Some(nu), Some(s)) = (
            l.value(payload, innov, i),
            l.get(payload, "innovation_variance", i),
        ) else {
            return;
        };
        axes.push(AxisValue {
            innovation: nu,
            variance: s,
            test_ratio: l.get(payload, "test_ratio", i),
            rejected: flag("innovation_rejected", i),
            fused: flag("fused", i),
        });
    }
    if axes
        .iter()
        .any(|a| !(a.variance > 0.0 && a.variance.is_finite() && a.innovation.is_finite()))
    {
        return;
    }
    let series = aid
        .entry((instance, source.to_string()))
        .or_insert_with(|| SourceSeries {
            source: source.to_string(),
            instance,
            family: Family::AidSource,
            records: Vec::new(),
            stale: 0,
        });
    if series.records.last().is_some_and(|r| r.t_us == t) {
        series.stale += 1;
        return;
    }
    series.records.push(Record { t_us: t, axes });
}

/// The innovations joined with their variances into per-source series (sources that also
/// have aid-source topics are left to those).
fn pair_innovations(
    topics: &InnovationTopics,
    pairing: &mut BTreeMap<u8, Pairing>,
    have_aid: &std::collections::BTreeSet<(u8, String)>,
) -> Vec<SourceSeries> {
    let mut out: BTreeMap<(u8, &str), SourceSeries> = BTreeMap::new();
    let mut seen: std::collections::HashSet<(u8, u64)> = Default::default();
    for (inst, t, nu) in &topics.innovations {
        let p = pairing.entry(*inst).or_default();
        // The same update logged twice is one record.
        if !seen.insert((*inst, *t)) {
            continue;
        }
        p.innovations += 1;
        let Some(var) = topics.variances.get(&(*inst, *t)) else {
            continue;
        };
        p.paired += 1;
        let ratio = topics.ratios.get(&(*inst, *t));
        // Group the mapped fields by source, axes in order.
        let mut by_source: BTreeMap<&str, Vec<(usize, AxisValue)>> = BTreeMap::new();
        let mut invalid: std::collections::BTreeSet<&str> = Default::default();
        for (k, (_, _, source, axis)) in INNOVATION_FIELDS.iter().enumerate() {
            let (Some(n), Some(s)) = (nu[k], var[k]) else {
                continue;
            };
            if !(s > 0.0 && s.is_finite() && n.is_finite()) {
                invalid.insert(source);
                continue;
            }
            let tr = ratio.and_then(|r| r[k]);
            by_source.entry(source).or_default().push((
                *axis,
                AxisValue {
                    innovation: n,
                    variance: s,
                    test_ratio: tr,
                    rejected: tr.map(|r| r > 1.0),
                    fused: None,
                },
            ));
        }
        for (source, mut axes) in by_source {
            if invalid.contains(source) || have_aid.contains(&(*inst, source.to_string())) {
                continue;
            }
            axes.sort_by_key(|(a, _)| *a);
            let axes: Vec<AxisValue> = axes.into_iter().map(|(_, v)| v).collect();
            let series = out.entry((*inst, source)).or_insert_with(|| SourceSeries {
                source: source.to_string(),
                instance: *inst,
                family: Family::Innovations,
                records: Vec::new(),
                stale: 0,
            });
            let repeat = series.records.last().is_some_and(|r| {
                r.axes.len() == axes.len()
                    && r.axes
                        .iter()
                        .zip(&axes)
                        .all(|(a, b)| a.innovation == b.innovation && a.variance == b.variance)
            });
            if repeat {
                series.stale += 1;
                continue;
            }
            series.records.push(Record { t_us: *t, axes });
        }
    }
    let mut v: Vec<SourceSeries> = out.into_values().collect();
    for s in &mut v {
        s.records.sort_by_key(|r| r.t_us);
    }
    v
}
