//! `kfmc ulog inspect`: what a log holds for a NIS verdict, and what cannot be judged and why.

use std::fmt::Write as _;
use std::path::Path;

use super::extract::{self, Extract, Family};
use crate::exchange::ulog::UlogError;

/// The text `kfmc ulog inspect` prints for `path`, and the extract it read.
pub fn inspect(path: &Path) -> Result<(String, Extract), UlogError> {
    let x = extract::read(path)?;
    Ok((render(path, &x), x))
}

/// The report of an extract.
pub fn render(path: &Path, x: &Extract) -> String {
    let mut s = String::new();
    let secs = |t: u64| t.saturating_sub(x.start_us) as f64 * 1e-6;
    let _ = writeln!(s, "{}", path.display());
    let _ = writeln!(
        s,
        "  firmware {}, hardware {}, {:.1} s logged",
        x.firmware.as_deref().unwrap_or("(not logged)"),
        x.hardware.as_deref().unwrap_or("(not logged)"),
        secs(x.end_us)
    );
    if x.stats.truncated || x.stats.corrupt_bytes > 0 || x.stats.bad_data > 0 {
        let _ = writeln!(
            s,
            "  damage: {}{} bytes skipped, {} unreadable samples",
            if x.stats.truncated {
                "the log is cut off; "
            } else {
                ""
            },
            x.stats.corrupt_bytes,
            x.stats.bad_data
        );
    }
    if x.stats.dropouts.0 > 0 {
        let _ = writeln!(
            s,
            "  dropouts: {} ({} ms lost)",
            x.stats.dropouts.0, x.stats.dropouts.1
        );
    }
    // Instances and the primary.
    let mut instances: Vec<u8> = x.first_seen.keys().copied().collect();
    instances.extend(x.series.iter().map(|v| v.instance));
    instances.sort_unstable();
    instances.dedup();
    let _ = writeln!(s, "  EKF instances: {}", list(&instances));
    if x.primary.is_empty() {
        let _ = writeln!(
            s,
            "  primary: no estimator_selector_status; instance 0 is taken as the primary"
        );
    } else {
        let mut changes: Vec<String> = Vec::new();
        let mut last = None;
        for (t, p) in &x.primary {
            if last != Some(*p) {
                changes.push(format!("{p} from {:.1} s", secs(*t)));
                last = Some(*p);
            }
        }
        let _ = writeln!(s, "  primary: {}", changes.join(", then "));
    }
    // In the air.
    if x.landed.is_empty() {
        let _ = writeln!(
            s,
            "  in the air: no vehicle_land_detected; every sample counts as in the air"
        );
    } else {
        let mut spans = Vec::new();
        let mut from = None;
        for (t, landed) in &x.landed {
            match (from, landed) {
                (None, false) => from = Some(*t),
                (Some(f), true) => {
                    spans.push(format!("{:.1}–{:.1} s", secs(f), secs(*t)));
                    from = None;
                }
                _ => {}
            }
        }
        if let Some(f) = from {
            spans.push(format!("{:.1} s – end", secs(f)));
        }
        let _ = writeln!(
            s,
            "  in the air: {}",
            if spans.is_empty() {
                "never (every sample is on the ground: nothing to judge by default)".into()
            } else {
                spans.join(", ")
            }
        );
    }
    for (i, r) in &x.resets {
        let _ = writeln!(
            s,
            "  resets of instance {i}: {}",
            r.iter()
                .map(|t| format!("{:.1} s", secs(*t)))
                .collect::<Vec<_>>()
                .join(", ")
        );
    }
    // Parameters.
    let verbose = x.parameters.get("EKF2_LOG_VERBOSE");
    let _ = writeln!(
        s,
        "  EKF2_LOG_VERBOSE: {}",
        verbose.map_or("(not in the log)".into(), |v| format!("{v}"))
    );
    let gates: Vec<String> = x
        .parameters
        .iter()
        .filter(|(k, _)| k.starts_with("EKF2_") && k.ends_with("GATE"))
        .map(|(k, v)| format!("{k} = {}", (v * 1e6).round() / 1e6))
        .collect();
    let _ = writeln!(
        s,
        "  gates: {}",
        if gates.is_empty() {
            "(none in the log)".into()
        } else {
            gates.join(", ")
        }
    );
    if x.parameter_changes > 0 {
        let _ = writeln!(s, "  parameters changed in flight: {}", x.parameter_changes);
    }
    // Sources.
    let _ = writeln!(s, "  aid sources (instance: records, rate):");
    if x.series.is_empty() {
        let _ = writeln!(s, "    none");
    }
    for v in &x.series {
        let span = match (v.records.first(), v.records.last()) {
            (Some(a), Some(b)) if b.t_us > a.t_us => (b.t_us - a.t_us) as f64 * 1e-6,
            _ => 0.0,
        };
        let rate = if span > 0.0 {
            format!("{:.2} Hz", (v.records.len() - 1) as f64 / span)
        } else {
            "—".into()
        };
        let _ = writeln!(
            s,
            "    {:<14} instance {}: {} records over {:.1} s, {rate}, {} axes, from {}{}",
            v.source,
            v.instance,
            v.records.len(),
            span,
            v.records.first().map_or(0, |r| r.axes.len()),
            match v.family {
                Family::AidSource => format!("estimator_aid_src_{}", v.source),
                Family::Innovations => "estimator_innovations + _innovation_variances".into(),
            },
            if v.stale > 0 {
                format!(", {} stale repeats dropped", v.stale)
            } else {
                String::new()
            }
        );
    }
    for (i, p) in &x.pairing {
        let _ = writeln!(
            s,
            "  pairing, instance {i}: {} of {} innovation records have a variance record of the same update ({}); {} variance records",
            p.paired,
            p.innovations,
            p.rate()
                .map_or("—".into(), |r| format!("{:.0} %", 100.0 * r)),
            p.variances
        );
    }
    // What cannot be judged.
    let mut cannot = Vec::new();
    if x.legacy_records > 0 {
        cannot.push(format!(
            "ekf2_innovations ({} records): the legacy topic (before PX4 v1.11) is inspected, not judged",
            x.legacy_records
        ));
    }
    if x.series.is_empty() && x.legacy_records == 0 {
        cannot.push(
            "no innovations: the log has neither estimator_aid_src_* nor estimator_innovations with their variances".into(),
        );
    }
    for (i, p) in &x.pairing {
        if p.innovations > 0 && p.paired == 0 {
            cannot.push(format!(
                "instance {i}: no innovation record pairs with a variance record (timestamps differ)"
            ));
        }
    }
    let n = super::batch_means_minimum();
    cannot.push(format!(
        "a series needs {n} effective samples ({} batches of ≥ {} integrated autocorrelation times) for a verdict; shorter series are incomplete",
        crate::metrics::batch_means::BATCHES,
        crate::metrics::batch_means::TAU_MULTIPLE
    ));
    let _ = writeln!(s, "  cannot be judged:");
    for c in cannot {
        let _ = writeln!(s, "    {c}");
    }
    s
}

fn list(v: &[u8]) -> String {
    if v.is_empty() {
        "none".into()
    } else {
        v.iter().map(u8::to_string).collect::<Vec<_>>().join(", ")
    }
}
