//! `[model]` and `[initial_estimate]`: the system `model.kind` names, and the generic part of
//! the prior (the rest of both tables is the system's).

use crate::experiment::spec::Spec;
use crate::system::checker::Checker;
use crate::system::settings::InitialMode;
use crate::system::{InitialSpec, Registry, System};

/// `[model]`: the system `kind` names (`None` when it names none, which is reported), and the
/// rest of the table, which is the system's.
pub(super) fn model_table<'r>(
    c: &mut Checker,
    spec: &Spec,
    registry: &'r Registry,
) -> (String, toml::Table, Option<&'r dyn System>) {
    let mut model = spec.model.clone();
    // `None` when kind is absent or not a string, which is reported here.
    let given = match model.remove("kind") {
        Some(toml::Value::String(k)) => Some(k),
        Some(other) => {
            c.err(
                "model.kind",
                format!("expected a string, got {}", other.type_str()),
            );
            None
        }
        None => {
            c.err("model.kind", "missing; `kfmc list` shows the systems");
            None
        }
    };
    let system = given.as_deref().and_then(|k| registry.get(k));
    if let Some(k) = &given
        && system.is_none()
    {
        c.err(
            "model.kind",
            crate::system::checker::unknown_value("model", k, registry.kinds().into_iter()),
        );
    }
    (given.unwrap_or_default(), model, system)
}
/// `[initial_estimate]`: the mode is generic, P0 and any initialiser are the system's.
pub(super) fn initial_estimate_table(c: &mut Checker, spec: &Spec) -> InitialSpec {
    let ie = spec.initial_estimate.as_deref();
    let mode = c.choice(
        "initial_estimate.mode",
        ie.and_then(|i| i.mode.as_deref()),
        "truth",
        &["truth", "sampled", "batch_ls"],
    );
    InitialSpec {
        mode: match mode {
            "sampled" => InitialMode::Sampled,
            "batch_ls" => InitialMode::BatchLs,
            _ => InitialMode::Truth,
        },
        present: ie.is_some(),
        p0_std: ie.and_then(|i| i.p0_std.clone()),
    }
}
