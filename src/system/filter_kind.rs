//! The filter-kind API of additive systems: what a `kind = "…"` of a `[[filters]]` entry is.
//!
//! A [`FilterKind`] validates one entry into a [`FilterEntry`], which builds the filter of
//! each cell from the model and the cell's [`AssumedNoise`]; a system offers a set of kinds,
//! [`FilterKinds`]. A filter whose only settings are its assumed noise needs none of this
//! plumbing: [`FnKind::new`] makes its kind from a function that builds the filter.

use std::fmt::Debug;
use std::sync::Arc;

use super::FilterInfo;
use super::checker::{Checker, non_negative, positive};
use super::spec_values::OneOrMany;
use crate::filter::Filter;
use crate::linalg::{Matrix, Vector, diag_from_std};
use crate::model::Model;
use crate::step_loop::{FilterOutput, Identity, Prior, RunContext, run_filter};

/// The filter's assumed noise for one cell: Q and R after every scale is applied.
#[derive(Clone, Debug, PartialEq)]
pub struct AssumedNoise<const NX: usize, const NZ: usize> {
    /// Assumed process-noise covariance.
    pub q: Matrix<NX, NX>,
    /// Assumed measurement-noise covariance.
    pub r: Matrix<NZ, NZ>,
}

impl<const NX: usize, const NZ: usize> AssumedNoise<NX, NZ> {
    /// A cell's Q and R from an entry's [`FilterEntry::assumed_std`] (`q_std`, `r_std`) or the
    /// model's full Q (`model_q`, which filters assume when the model has one): the standard
    /// deviations times `filter_scale` (1, or the truth's multiplier in `matched` mode), the
    /// covariances times the variant's `q_scale` and `r_scale`. A kind without assumed noise
    /// (empty std) gets zeros, which it does not read.
    pub fn for_cell(
        (q_std, r_std): (&[f64], &[f64]),
        model_q: Option<&Matrix<NX, NX>>,
        filter_scale: f64,
        q_scale: f64,
        r_scale: f64,
    ) -> Self {
        let q = match model_q {
            Some(q) => q * (filter_scale * filter_scale * q_scale),
            None if q_std.len() == NX => {
                diag_from_std(&(Vector::<NX>::from_column_slice(q_std) * filter_scale)) * q_scale
            }
            None => Matrix::<NX, NX>::zeros(),
        };
        let r = if r_std.len() == NZ {
            diag_from_std(&(Vector::<NZ>::from_column_slice(r_std) * filter_scale)) * r_scale
        } else {
            Matrix::<NZ, NZ>::zeros()
        };
        AssumedNoise { q, r }
    }
}

/// A filter ready to run: one virtual call per run, then the monomorphised step loop. Every
/// [`Filter`] is one.
pub trait RunFilter<const NX: usize, const NU: usize, const NZ: usize, M>: Send + Sync {
    /// Runs the filter on one run of the world.
    fn run(
        &self,
        model: &M,
        prior: &Prior<'_, NX>,
        ctx: &RunContext<'_, NX, NU, NZ>,
    ) -> FilterOutput;
    /// Runs the filter on a group of runs of one cell (`priors[i]` with `ctxs[i]`), one
    /// output per run, each equal to [`RunFilter::run`]'s; the default runs them one by one.
    fn run_group(
        &self,
        model: &M,
        priors: &[Prior<'_, NX>],
        ctxs: &[RunContext<'_, NX, NU, NZ>],
    ) -> Vec<FilterOutput> {
        priors
            .iter()
            .zip(ctxs)
            .map(|(p, c)| self.run(model, p, c))
            .collect()
    }
}

impl<const NX: usize, const NU: usize, const NZ: usize, M, F> RunFilter<NX, NU, NZ, M> for F
where
    M: Model<NX, NU, NZ>,
    F: Filter<NX, NU, NZ, M> + Send,
{
    fn run(
        &self,
        model: &M,
        prior: &Prior<'_, NX>,
        ctx: &RunContext<'_, NX, NU, NZ>,
    ) -> FilterOutput {
        run_filter(model, self, &Identity, prior, ctx)
    }

    fn run_group(
        &self,
        model: &M,
        priors: &[Prior<'_, NX>],
        ctxs: &[RunContext<'_, NX, NU, NZ>],
    ) -> Vec<FilterOutput> {
        self.as_kalman()
            .and_then(|ekf| super::group::run_group_shared(ekf, model, priors, ctxs))
            .unwrap_or_else(|| {
                priors
                    .iter()
                    .zip(ctxs)
                    .map(|(p, c)| self.run(model, p, c))
                    .collect()
            })
    }
}

/// A validated `[[filters]]` entry of an additive system.
pub trait FilterEntry<const NX: usize, const NU: usize, const NZ: usize, M>:
    Send + Sync + Debug
{
    /// What the generic code needs to know of it.
    fn info(&self) -> FilterInfo;
    /// The assumed process- and measurement-noise standard deviations at scale 1 (used when
    /// the model has no full Q of its own).
    fn assumed_std(&self) -> (&[f64], &[f64]);
    /// Builds the filter for one cell (filter variant × truth-noise scale). Called once per
    /// cell and cached, so a Riccati solution or a pole placement is computed once.
    fn prepare(&self, model: &M, noise: &AssumedNoise<NX, NZ>)
    -> Box<dyn RunFilter<NX, NU, NZ, M>>;
    /// Checks the entry at `key` (`filters[i]`) against the scenarios, once they are known:
    /// `samples` is K + 1 of the longest one. A kind whose keys count samples (a window)
    /// refuses what no scenario can fill; the default accepts everything.
    fn check_scenarios(&self, key: &str, samples: usize, checker: &mut Checker) {
        let _ = (key, samples, checker);
    }
}

/// Runs [`FilterEntry::check_scenarios`] on every entry; `entries` must be the system's
/// filter tables `tables` in order (as [`FilterKinds::configure_entries`] returns them when no
/// entry failed). Each problem is named at its table's key, the entry's place in the spec's
/// list (which differs from its place in `tables` when external filters precede it).
pub fn check_scenarios<const NX: usize, const NU: usize, const NZ: usize, M>(
    entries: &[Arc<dyn FilterEntry<NX, NU, NZ, M>>],
    tables: &[super::FilterTable],
    samples: usize,
    c: &mut Checker,
) {
    for (e, table) in entries.iter().zip(tables) {
        e.check_scenarios(&table.key, samples, c);
    }
}

/// What a filter kind is given to validate one entry.
#[derive(Debug)]
pub struct FilterContext<'a, const NX: usize, const NZ: usize, M> {
    /// The entry's key path, `filters[i]`.
    pub key: String,
    /// The entry's own keys (without `label`, `kind`, `q_scale`, `r_scale`).
    pub table: &'a toml::Table,
    /// The model the filter assumes.
    pub model: &'a M,
    /// The system's `model.kind`, for messages.
    pub system: &'a str,
    /// The truth's process-noise std per state at scale 1 (the default `q_std`).
    pub process_std: &'a [f64],
    /// The truth's measurement-noise std per component (the default `r_std`).
    pub measurement_std: &'a [f64],
    /// Whether the model has its own full Q, which filters assume (then `q_std` is refused).
    pub full_q: bool,
}

/// A filter kind: the `kind = "…"` of a `[[filters]]` entry.
pub trait FilterKind<const NX: usize, const NU: usize, const NZ: usize, M>: Send + Sync {
    /// The `kind` tag.
    fn tag(&self) -> &str;
    /// One line for `kfmc list`: what it is and its keys.
    fn about(&self) -> String;
    /// Validates one entry into a [`FilterEntry`], reporting problems with their key paths.
    fn configure(
        &self,
        cx: &FilterContext<'_, NX, NZ, M>,
        checker: &mut Checker,
    ) -> Option<Arc<dyn FilterEntry<NX, NU, NZ, M>>>;
}

/// What a system's `[[filters]]` entries are validated against
/// ([`FilterKinds::configure_entries`]): the model the filters assume, the system's `model.kind`
/// for messages, and the truth's noise standard deviations at scale 1, the defaults of
/// `q_std` and `r_std`.
#[derive(Clone, Copy)]
pub struct FilterSetup<'a, M> {
    /// The model the filters assume.
    pub model: &'a M,
    /// The system's `model.kind`, for messages.
    pub system: &'a str,
    /// The truth's process-noise std per state (the default `q_std`).
    pub process_std: &'a [f64],
    /// The truth's measurement-noise std per component (the default `r_std`).
    pub measurement_std: &'a [f64],
    /// Explains a kind this set does not have (one registered for another sensor set), or
    /// gives `None` for the usual message listing the tags.
    pub unknown: Option<UnknownKind<'a>>,
}

/// The message for a kind a set does not have, or `None` for the usual one listing the tags
/// ([`FilterSetup::explaining_unknown`]).
pub type UnknownKind<'a> = &'a dyn Fn(&str) -> Option<String>;

impl<'a, M> FilterSetup<'a, M> {
    /// The setup of a system's entries; an unknown kind gets the usual message.
    pub fn new(
        model: &'a M,
        system: &'a str,
        process_std: &'a [f64],
        measurement_std: &'a [f64],
    ) -> Self {
        FilterSetup {
            model,
            system,
            process_std,
            measurement_std,
            unknown: None,
        }
    }

    /// The setup with `unknown` explaining a kind this set does not have (its message, or
    /// `None` for the usual one): a kind that exists for another sensor set, say.
    pub fn explaining_unknown(mut self, unknown: UnknownKind<'a>) -> Self {
        self.unknown = Some(unknown);
        self
    }
}

impl<M> std::fmt::Debug for FilterSetup<'_, M> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FilterSetup")
            .field("system", &self.system)
            .field("process_std", &self.process_std)
            .field("measurement_std", &self.measurement_std)
            .finish_non_exhaustive()
    }
}

/// A system's filter kinds, in the order `kfmc list` shows them.
pub struct FilterKinds<const NX: usize, const NU: usize, const NZ: usize, M> {
    kinds: Vec<Arc<dyn FilterKind<NX, NU, NZ, M>>>,
}

impl<const NX: usize, const NU: usize, const NZ: usize, M> Clone for FilterKinds<NX, NU, NZ, M> {
    fn clone(&self) -> Self {
        FilterKinds {
            kinds: self.kinds.clone(),
        }
    }
}

impl<const NX: usize, const NU: usize, const NZ: usize, M> Default for FilterKinds<NX, NU, NZ, M> {
    fn default() -> Self {
        FilterKinds { kinds: Vec::new() }
    }
}

impl<const NX: usize, const NU: usize, const NZ: usize, M> FilterKinds<NX, NU, NZ, M> {
    /// Adds a kind (one with the same tag is replaced).
    pub fn with(mut self, kind: impl FilterKind<NX, NU, NZ, M> + 'static) -> Self {
        self.push(Arc::new(kind));
        self
    }
    /// Adds a shared kind (one with the same tag is replaced).
    pub fn push(&mut self, kind: Arc<dyn FilterKind<NX, NU, NZ, M>>) {
        match self.kinds.iter().position(|k| k.tag() == kind.tag()) {
            Some(i) => self.kinds[i] = kind,
            None => self.kinds.push(kind),
        }
    }
    /// The kind with this tag.
    pub fn get(&self, tag: &str) -> Option<&dyn FilterKind<NX, NU, NZ, M>> {
        self.kinds
            .iter()
            .find(|k| k.tag() == tag)
            .map(|k| k.as_ref())
    }
    /// Every tag, in order.
    pub fn tags(&self) -> Vec<&str> {
        self.kinds.iter().map(|k| k.tag()).collect()
    }
    /// (tag, about) for `kfmc list`.
    pub fn catalogue(&self) -> Vec<(String, String)> {
        self.kinds
            .iter()
            .map(|k| (k.tag().to_string(), k.about()))
            .collect()
    }

    /// The entries of `filters` validated as [`FilterKinds::configure_entries`] does, with
    /// the setup's parts as separate arguments.
    #[deprecated(
        note = "use configure_entries(filters, &FilterSetup::new(model, system, process_std, measurement_std), c)"
    )]
    #[allow(
        clippy::too_many_arguments,
        reason = "the signature of before FilterSetup, kept for one release"
    )]
    pub fn configure_all(
        &self,
        filters: &[super::FilterTable],
        model: &M,
        system: &str,
        process_std: &[f64],
        measurement_std: &[f64],
        unknown: &dyn Fn(&str) -> Option<String>,
        c: &mut Checker,
    ) -> Vec<Arc<dyn FilterEntry<NX, NU, NZ, M>>>
    where
        M: Model<NX, NU, NZ>,
    {
        let setup = FilterSetup::new(model, system, process_std, measurement_std)
            .explaining_unknown(unknown);
        self.configure_entries(filters, &setup, c)
    }

    /// Validates every entry of `filters` whose kind is in this set against `setup` (the
    /// model, and the truth's noise whose standard deviations are the defaults of `q_std` and
    /// `r_std`); an unknown kind is an error at `filters[i].kind` listing the tags, or the
    /// setup's explanation of it ([`FilterSetup::explaining_unknown`]).
    pub fn configure_entries(
        &self,
        filters: &[super::FilterTable],
        setup: &FilterSetup<'_, M>,
        c: &mut Checker,
    ) -> Vec<Arc<dyn FilterEntry<NX, NU, NZ, M>>>
    where
        M: Model<NX, NU, NZ>,
    {
        let FilterSetup {
            model,
            system,
            process_std,
            measurement_std,
            unknown,
        } = *setup;
        // A model with its own full Q is what its filters assume (times q_scale), so a q_std
        // would be silently ignored: the kinds refuse it.
        let full_q = model.process_noise_covariance().is_some();
        // The truth draws w_k ~ N(0, Q) through a factor of Q: a Q that is no covariance is
        // refused here rather than replaced by anything else.
        if let Some(q) = model.process_noise_covariance()
            && crate::sim::process_factor(&q).is_none()
        {
            c.err(
                "model",
                format!(
                    "the {system} model's process-noise covariance Q is not a finite, symmetric, positive semi-definite matrix, so the truth cannot draw its noise from it"
                ),
            );
        }
        let mut out = Vec::new();
        for f in filters {
            let key = f.key.clone();
            let Some(kind) = self.get(&f.kind) else {
                let msg = unknown.and_then(|u| u(&f.kind)).unwrap_or_else(|| {
                    let tags = self.tags();
                    super::checker::unknown_value("value", &f.kind, tags.iter().copied())
                });
                c.err(format!("{key}.kind"), msg);
                continue;
            };
            let cx = FilterContext {
                key,
                table: &f.keys,
                model,
                system,
                process_std,
                measurement_std,
                full_q,
            };
            out.extend(kind.configure(&cx, c));
        }
        out
    }
}

/// The assumed-noise part every Kalman-type entry shares.
#[derive(Clone, Debug, PartialEq)]
pub struct AssumedStd {
    /// Assumed process-noise std per state (at noise scale 1 in `matched` mode).
    pub q_std: Vec<f64>,
    /// Assumed measurement-noise std per component.
    pub r_std: Vec<f64>,
}

impl AssumedStd {
    /// Reads `q_std` and `r_std` (defaults: the truth's) from an entry.
    ///
    /// A default the filter cannot use (a truth with no measurement noise gives R = 0) is
    /// reported at the entry, `filters[i]`, since its `r_std` is not in the file.
    pub fn read<const NX: usize, const NZ: usize, M>(
        cx: &FilterContext<'_, NX, NZ, M>,
        q_std: Option<&OneOrMany>,
        r_std: Option<&OneOrMany>,
        c: &mut Checker,
    ) -> Self {
        Self::read_with(cx, q_std, r_std, true, c)
    }

    /// [`AssumedStd::read`]; `uses_r`: whether the filter updates, so that R must be
    /// positive definite even when it is the default.
    pub(super) fn read_with<const NX: usize, const NZ: usize, M>(
        cx: &FilterContext<'_, NX, NZ, M>,
        q_std: Option<&OneOrMany>,
        r_std: Option<&OneOrMany>,
        uses_r: bool,
        c: &mut Checker,
    ) -> Self {
        let bad_default = |given: bool, d: &[f64], ok: fn(f64) -> bool| {
            (!given).then(|| d.iter().position(|x| !ok(*x))).flatten()
        };
        // With a full Q the filters assume it and never read the per-state std.
        if !cx.full_q
            && let Some(i) = bad_default(q_std.is_some(), cx.process_std, non_negative)
        {
            c.err(
                cx.key.clone(),
                format!(
                    "q_std is not set and defaults to the truth's process noise std, whose component {i} is {}, not a non-negative number; set q_std",
                    cx.process_std[i]
                ),
            );
        }
        if uses_r && let Some(i) = bad_default(r_std.is_some(), cx.measurement_std, positive) {
            c.err(
                cx.key.clone(),
                format!(
                    "r_std is not set and defaults to the truth's measurement noise std, whose component {i} is {}; R must be positive definite: set r_std",
                    cx.measurement_std[i]
                ),
            );
        }
        if cx.full_q && q_std.is_some() {
            c.err(
                format!("{}.q_std", cx.key),
                format!(
                    "{} filters assume the model's full Q; scale it with q_scale",
                    cx.system
                ),
            );
        }
        AssumedStd {
            q_std: c.vector(
                &format!("{}.q_std", cx.key),
                q_std,
                NX,
                cx.process_std,
                non_negative,
                "a non-negative number",
            ),
            r_std: c.vector(
                &format!("{}.r_std", cx.key),
                r_std,
                NZ,
                cx.measurement_std,
                positive,
                "a positive number (R must be positive definite)",
            ),
        }
    }
}

/// A filter kind made from a function: for a filter whose only settings are its assumed
/// noise. Its entries take `q_std` and `r_std` (defaults: the truth's; `q_std` is refused
/// when the model has its own full Q, which filters assume) besides `label`, `kind`,
/// `q_scale` and `r_scale`, and each cell runs the filter `build` makes from the model and
/// the cell's assumed Q and R (after every scale). A filter with keys of its own implements
/// [`FilterKind`] instead.
///
/// ```
/// use kfmc::filter::{CovarianceUpdate, Ekf};
/// use kfmc::prelude::*;
///
/// // kfmc's EKF in the Joseph form under a tag of its own, in one expression.
/// fn kinds<M: Model<6, 2, 3> + 'static>() -> FilterKinds<6, 2, 3, M> {
///     common_kinds().with(FnKind::new(
///         "joseph_ekf",
///         "EKF, Joseph update; q_std, r_std",
///         |_model: &M, noise: &AssumedNoise<6, 3>| Ekf {
///             q: noise.q,
///             r: noise.r,
///             update_form: CovarianceUpdate::Joseph,
///         },
///     ))
/// }
/// # let tags = kinds::<kfmc::systems::planar::model::Planar<3>>();
/// # assert!(tags.tags().contains(&"joseph_ekf"));
/// ```
pub struct FnKind<B> {
    tag: String,
    about: String,
    has_covariance: bool,
    build: Arc<B>,
}

impl<B> FnKind<B> {
    /// The kind `tag` (its line in `kfmc list` is `about`) whose filters `build` makes.
    pub fn new<const NX: usize, const NZ: usize, M, F>(
        tag: impl Into<String>,
        about: impl Into<String>,
        build: B,
    ) -> Self
    where
        B: Fn(&M, &AssumedNoise<NX, NZ>) -> F,
    {
        FnKind {
            tag: tag.into(),
            about: about.into(),
            has_covariance: true,
            build: Arc::new(build),
        }
    }

    /// The kind of a filter that carries no covariance (an observer, a running mean): its
    /// NEES and NIS are null and no consistency verdict is formed for it.
    pub fn without_covariance(mut self) -> Self {
        self.has_covariance = false;
        self
    }
}

/// A validated entry of an [`FnKind`].
struct FnEntry<B> {
    tag: String,
    has_covariance: bool,
    noise: AssumedStd,
    build: Arc<B>,
}

impl<B> Debug for FnEntry<B> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FnEntry")
            .field("kind", &self.tag)
            .field("noise", &self.noise)
            .finish_non_exhaustive()
    }
}

impl<const NX: usize, const NU: usize, const NZ: usize, M, B, F> FilterEntry<NX, NU, NZ, M>
    for FnEntry<B>
where
    M: Model<NX, NU, NZ> + 'static,
    B: Fn(&M, &AssumedNoise<NX, NZ>) -> F + Send + Sync + 'static,
    F: Filter<NX, NU, NZ, M> + Send + Sync + 'static,
{
    fn info(&self) -> FilterInfo {
        FilterInfo {
            kind: self.tag.clone(),
            has_covariance: self.has_covariance,
            q_scale: true,
            r_scale: true,
        }
    }
    fn assumed_std(&self) -> (&[f64], &[f64]) {
        (&self.noise.q_std, &self.noise.r_std)
    }
    fn prepare(
        &self,
        model: &M,
        noise: &AssumedNoise<NX, NZ>,
    ) -> Box<dyn RunFilter<NX, NU, NZ, M>> {
        Box::new((self.build)(model, noise))
    }
}

/// The keys of an [`FnKind`] entry (every other key is an error at its key path).
#[derive(Debug, Default, serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct NoiseKeys {
    q_std: Option<OneOrMany>,
    r_std: Option<OneOrMany>,
}

impl<const NX: usize, const NU: usize, const NZ: usize, M, B, F> FilterKind<NX, NU, NZ, M>
    for FnKind<B>
where
    M: Model<NX, NU, NZ> + 'static,
    B: Fn(&M, &AssumedNoise<NX, NZ>) -> F + Send + Sync + 'static,
    F: Filter<NX, NU, NZ, M> + Send + Sync + 'static,
{
    fn tag(&self) -> &str {
        &self.tag
    }
    fn about(&self) -> String {
        self.about.clone()
    }
    fn configure(
        &self,
        cx: &FilterContext<'_, NX, NZ, M>,
        c: &mut Checker,
    ) -> Option<Arc<dyn FilterEntry<NX, NU, NZ, M>>> {
        let keys: NoiseKeys = c.parse(&cx.key, cx.table)?;
        let noise = AssumedStd::read(cx, keys.q_std.as_ref(), keys.r_std.as_ref(), c);
        Some(Arc::new(FnEntry {
            tag: self.tag.clone(),
            has_covariance: self.has_covariance,
            noise,
            build: Arc::clone(&self.build),
        }))
    }
}
