//! The canonical text of a simulated world, which the world stamp hashes.

use crate::experiment::spec::OneOrMany;
use crate::system::settings::{Draws, InitialMode};

/// The canonical text of a world (all of [`Plan::world`]): the system, its model table, the
/// scenarios (sorted, as a run's streams depend on its scenario's name, not its position),
/// the prior's settings, the noise multipliers and how their draws relate. Tables are written
/// with sorted keys and numbers by their bits, so neither comments, key order, formatting nor
/// `1` against `1.0` change it. Filters, run counts and the judging settings are left out:
/// they do not change what run i's world is.
pub(super) fn world_canonical(
    kind: &str,
    model: &toml::Table,
    scenarios: &[toml::Table],
    initial: InitialMode,
    p0_std: Option<&OneOrMany>,
    noise_scales: &[f64],
    draws: Draws,
) -> String {
    let mut model = model.clone();
    model.remove("kind");
    let mut scen: Vec<String> = scenarios
        .iter()
        .map(|s| canonical_value(&toml::Value::Table(s.clone())))
        .collect();
    scen.sort();
    let p0 = match p0_std {
        None => "default".to_string(),
        Some(OneOrMany::One(v)) => canonical_f64(*v),
        Some(OneOrMany::Many(v)) => {
            let items: Vec<String> = v.iter().map(|x| canonical_f64(*x)).collect();
            format!("[{}]", items.join(","))
        }
    };
    let scales: Vec<String> = noise_scales.iter().map(|x| canonical_f64(*x)).collect();
    format!(
        "kfmc world 1\nkind = {kind:?}\nmodel = {}\nscenarios = [{}]\ninitial = {initial:?}\np0_std = {p0}\nnoise_scales = [{}]\ndraws = {draws:?}\n",
        canonical_value(&toml::Value::Table(model)),
        scen.join(","),
        scales.join(","),
    )
}

/// A number by its bits (−0 as 0), so every spelling of one value gives one text.
fn canonical_f64(v: f64) -> String {
    let v = if v == 0.0 { 0.0 } else { v };
    format!("f{:016x}", v.to_bits())
}

/// A TOML value in one spelling: tables with sorted keys, integers that are exact floats as
/// those floats (a model parameter written `1` means `1.0`).
fn canonical_value(v: &toml::Value) -> String {
    match v {
        toml::Value::String(s) => format!("{s:?}"),
        toml::Value::Integer(i) => {
            let f = *i as f64;
            if f as i64 == *i && f.abs() < 9_007_199_254_740_992.0 {
                canonical_f64(f)
            } else {
                format!("i{i}")
            }
        }
        toml::Value::Float(f) => canonical_f64(*f),
        toml::Value::Boolean(b) => b.to_string(),
        toml::Value::Datetime(d) => format!("d{d}"),
        toml::Value::Array(a) => {
            let items: Vec<String> = a.iter().map(canonical_value).collect();
            format!("[{}]", items.join(","))
        }
        toml::Value::Table(t) => {
            let mut items: Vec<(&String, String)> =
                t.iter().map(|(k, v)| (k, canonical_value(v))).collect();
            items.sort_by(|a, b| a.0.cmp(b.0));
            let items: Vec<String> = items
                .into_iter()
                .map(|(k, v)| format!("{k:?}={v}"))
                .collect();
            format!("{{{}}}", items.join(","))
        }
    }
}
