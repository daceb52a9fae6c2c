//! `[[filters]]`: the entries the system validates, and each entry's variants over its
//! `q_scale` × `r_scale` multipliers.

use super::POSITIVE;
use crate::experiment::spec::{Scales, Spec};
use crate::system::checker::{Checker, non_negative, positive};
use crate::system::limits;
use crate::system::settings::{DeclaredScales, FilterPlan};
use crate::system::{FilterTable, SystemPlan};

/// The `kind` of a `[[filters]]` entry whose estimates come from outside kfmc.
pub const EXTERNAL_KIND: &str = "external";
/// Expands `start, start+step, … ≤ stop`; values are rounded to 12 significant digits so a
/// grid like 0.2, 0.4, 0.6 prints as written rather than as 0.6000000000000001.
pub fn expand_range(start: f64, stop: f64, step: f64) -> Vec<f64> {
    let n = ((stop - start) / step + 1e-9).floor() as usize + 1;
    (0..n)
        .map(|i| {
            let v = start + i as f64 * step;
            if v == 0.0 || !v.is_finite() {
                return v;
            }
            // log10 of a subnormal is about −324, so the exponent stays far from overflow.
            let mag = 10f64.powi(11 - v.abs().log10().floor() as i32);
            let r = (v * mag).round() / mag;
            if r.is_finite() { r } else { v }
        })
        .collect()
}
/// Expands a list or range of multipliers, checking each is `ok`; `None` gives `default`.
pub(super) fn scale_list(
    c: &mut Checker,
    key: &str,
    v: Option<&Scales>,
    default: f64,
    ok: fn(f64) -> bool,
    what: &str,
) -> Vec<f64> {
    let mut out = match v {
        None => vec![default],
        Some(Scales::List(v)) => v.clone(),
        Some(Scales::Range { start, stop, step }) => {
            if !(positive(*step) && non_negative(*start) && stop.is_finite() && stop >= start) {
                c.err(key, "a range needs 0 ≤ start ≤ stop and step > 0");
                vec![default]
            } else if (stop - start) / step >= limits::MAX_SCALES as f64 {
                c.err(key, format!("more than {} values", limits::MAX_SCALES));
                vec![default]
            } else {
                expand_range(*start, *stop, *step)
            }
        }
    };
    if out.is_empty() {
        c.err(key, "at least one value is required");
    }
    if out.len() > limits::MAX_SCALES {
        c.err(
            key,
            format!("{} values; at most {}", out.len(), limits::MAX_SCALES),
        );
        out.truncate(1);
    }
    if let Some(bad) = out.iter().find(|x| !ok(**x)) {
        c.err(key, format!("{bad} is not {what}"));
    }
    out.sort_by(f64::total_cmp);
    if out.windows(2).any(|w| w[0] == w[1]) {
        c.err(key, "duplicate values");
    }
    out
}
/// The `[[filters]]` entries the system validates. External filters are kfmc's, not the
/// system's: the system sees the others only, and `system_index[i]` is spec entry i's
/// position among them.
pub(super) fn filter_tables(
    c: &mut Checker,
    spec: &Spec,
) -> (Vec<Option<usize>>, Vec<FilterTable>) {
    let mut system_index = Vec::with_capacity(spec.filters.len());
    let mut tables: Vec<FilterTable> = Vec::new();
    for (i, f) in spec.filters.iter().enumerate() {
        if f.kind == EXTERNAL_KIND {
            system_index.push(None);
            for k in f.keys.keys() {
                c.err(
                    format!("filters[{i}].{}", crate::system::checker::path_key(k)),
                    "an external filter has no keys besides label, kind and its variants q_scale, r_scale (its settings are its own)",
                );
            }
        } else {
            system_index.push(Some(tables.len()));
            tables.push(FilterTable {
                key: format!("filters[{i}]"),
                label: f.label.clone(),
                kind: f.kind.clone(),
                keys: f.keys.clone(),
            });
        }
    }
    (system_index, tables)
}
/// The filter variants: each (q_scale, r_scale) pair of an entry, with the same label; the
/// scales are key columns of every table.
pub(super) fn filter_variants(
    c: &mut Checker,
    spec: &Spec,
    system_index: &[Option<usize>],
    system: Option<&dyn SystemPlan>,
) -> Vec<FilterPlan> {
    let mut filters = Vec::new();
    for (i, f) in spec.filters.iter().enumerate() {
        let key = format!("filters[{i}]");
        let declared = DeclaredScales {
            q_scale: f.q_scale.is_some(),
            r_scale: f.r_scale.is_some(),
        };
        let q_key = format!("{key}.q_scale");
        let r_key = format!("{key}.r_scale");
        let Some(entry) = system_index[i] else {
            // An external filter's variants: the multipliers it applied to its own assumed
            // Q and R, named by its estimates' `q_scale`/`r_scale` columns.
            let q_scales = scale_list(c, &q_key, f.q_scale.as_ref(), 1.0, positive, POSITIVE);
            let r_scales = scale_list(c, &r_key, f.r_scale.as_ref(), 1.0, positive, POSITIVE);
            for &q_scale in &q_scales {
                for &r_scale in &r_scales {
                    filters.push(FilterPlan {
                        label: f.label.clone(),
                        kind: f.kind.clone(),
                        entry: usize::MAX,
                        external: true,
                        q_scale,
                        r_scale,
                        declared,
                    });
                }
            }
            continue;
        };
        if let Some(info) = system.and_then(|s| s.filters().get(entry)) {
            let msg = format!("not used by a {} filter", info.kind);
            c.reject_present(
                &key,
                &[
                    ("q_scale", f.q_scale.is_some() && !info.q_scale),
                    ("r_scale", f.r_scale.is_some() && !info.r_scale),
                ],
                &msg,
            );
        }
        let q_scales = scale_list(c, &q_key, f.q_scale.as_ref(), 1.0, positive, POSITIVE);
        let r_scales = scale_list(c, &r_key, f.r_scale.as_ref(), 1.0, positive, POSITIVE);
        for &q_scale in &q_scales {
            for &r_scale in &r_scales {
                filters.push(FilterPlan {
                    label: f.label.clone(),
                    kind: f.kind.clone(),
                    entry,
                    external: false,
                    q_scale,
                    r_scale,
                    declared,
                });
            }
        }
    }
    filters
}
