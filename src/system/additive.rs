//! Systems whose world is the filter's model plus additive Gaussian noise.
//!
//! x_k = f(x_{k−1}, u_k) + w_k, z_k = h(x_k, u_k) + v_k, the evaluated quantities are the
//! states, and the filters' inputs are the scenario's controls. P1, P2, L1, the generic
//! linear-Gaussian system and most users' first systems are of this kind; they describe the
//! model, the scenarios and which filter kinds they offer, and [`AdditivePlan`] does the rest
//! (it is the [`SystemPlan`] and builds the [`Trial`]).
//!
//! Filter kinds are values of [`FilterKind`]: [`common_kinds`] work on any [`Model`]
//! (EKF, information, square-root, open loop, UKF, CKF), [`linear_kinds`] add the fixed-gain ones that
//! need a linear model (steady state, pole placement). A system adds its own (the planar
//! running mean) and a user adds theirs, through the same trait.

use std::any::Any;
use std::fmt::Debug;
use std::sync::{Arc, OnceLock};

use serde::Deserialize;

use super::checker::{Checker, non_negative, positive};
use super::settings::{FilterNoiseMode, InitialMode, RunSettings};
use super::spec_values::OneOrMany;
use super::trial::Trial;
use super::{FilterInfo, Layout, ScenarioInfo, SystemPlan};
use crate::filter::luenberger::{SeedPoleReading, seed_poles};
use crate::filter::sigma_point::SigmaPointError;
use crate::filter::{
    BatchInitial, CovarianceUpdate, Ekf, Filter, Information, Luenberger, OpenLoop,
    SigmaPointKalman, SigmaPoints, SquareRoot, SteadyState,
};
use crate::linalg::{Matrix, Vector, diag_from_std};
use crate::metrics::RunConsistency;
use crate::model::Model;
use crate::scenario::Scenario;
use crate::sim::{NoiseDraws, TruthNoise, simulate};
use crate::step_loop::{
    ConsistencyOptions, FilterOutput, Identity, Prior, RunContext, RunTrace, Unit, UnitResult,
    lower_triangle, run_filter,
};

/// The filter's assumed noise for one cell: Q and R after every scale is applied.
#[derive(Clone, Debug, PartialEq)]
pub struct AssumedNoise<const NX: usize, const NZ: usize> {
    /// Assumed process-noise covariance.
    pub q: Matrix<NX, NX>,
    /// Assumed measurement-noise covariance.
    pub r: Matrix<NZ, NZ>,
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
/// filter tables `tables` in order (as [`FilterKinds::configure_all`] returns them when no
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

    /// Validates every entry of `filters` whose kind is in this set; an unknown kind is an
    /// error at `filters[i].kind` listing the tags. `unknown` may explain a kind that exists
    /// elsewhere (another sensor set) and return its message instead. `process_std` and
    /// `measurement_std` are the truth's, the defaults of `q_std` and `r_std`.
    #[allow(clippy::too_many_arguments)]
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
                let msg = unknown(&f.kind).unwrap_or_else(|| {
                    format!(
                        "unknown value `{}`; expected one of: {}",
                        f.kind,
                        self.tags().join(", ")
                    )
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

/// Keys of the Kalman-type kinds: assumed noise and the covariance update.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct KalmanKeys {
    q_std: Option<OneOrMany>,
    r_std: Option<OneOrMany>,
    covariance_update: Option<String>,
    alpha: Option<f64>,
    beta: Option<f64>,
    kappa: Option<f64>,
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
    fn read_with<const NX: usize, const NZ: usize, M>(
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

/// Which Kalman-type filter an entry builds.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Kalman {
    Ekf(CovarianceUpdate),
    Information,
    Sqrt,
    OpenLoop,
    SteadyState,
    /// The unscented or the cubature filter, by its points.
    SigmaPoint(SigmaPoints),
}

impl Kalman {
    fn tag(self) -> &'static str {
        match self {
            Kalman::Ekf(_) => "ekf",
            Kalman::Information => "information",
            Kalman::Sqrt => "sqrt",
            Kalman::OpenLoop => "open_loop",
            Kalman::SteadyState => "steady_state",
            Kalman::SigmaPoint(SigmaPoints::Unscented { .. }) => "ukf",
            Kalman::SigmaPoint(SigmaPoints::Cubature) => "ckf",
        }
    }
}

#[derive(Debug)]
struct KalmanEntry {
    which: Kalman,
    noise: AssumedStd,
}

impl<const NX: usize, const NU: usize, const NZ: usize, M> FilterEntry<NX, NU, NZ, M>
    for KalmanEntry
where
    M: Model<NX, NU, NZ> + 'static,
{
    fn info(&self) -> FilterInfo {
        FilterInfo {
            kind: self.which.tag().into(),
            has_covariance: true,
            q_scale: true,
            r_scale: self.which != Kalman::OpenLoop,
        }
    }
    fn assumed_std(&self) -> (&[f64], &[f64]) {
        (&self.noise.q_std, &self.noise.r_std)
    }
    fn prepare(&self, model: &M, n: &AssumedNoise<NX, NZ>) -> Box<dyn RunFilter<NX, NU, NZ, M>> {
        let (q, r) = (n.q, n.r);
        match self.which {
            Kalman::Ekf(update_form) => Box::new(Ekf { q, r, update_form }),
            Kalman::Information => Box::new(Information::new(q, r)),
            Kalman::Sqrt => Box::new(SquareRoot::new(q, r)),
            Kalman::OpenLoop => Box::new(OpenLoop {
                predictor: Ekf {
                    q,
                    r,
                    update_form: CovarianceUpdate::Standard,
                },
            }),
            Kalman::SteadyState => Box::new(SteadyState::new(model, &q, &r)),
            Kalman::SigmaPoint(points) => Box::new(
                SigmaPointKalman::new(q, r, points)
                    .expect("the points' parameters were checked when the spec was validated"),
            ),
        }
    }
}

/// A Kalman-type kind (`ekf`, `information`, `sqrt`, `open_loop`, `steady_state`).
struct KalmanKind {
    which: Kalman,
    about: &'static str,
    /// An extra check of the model (steady state: detectability), with its message.
    requires: Option<fn(&dyn Any) -> Option<String>>,
}

impl<const NX: usize, const NU: usize, const NZ: usize, M> FilterKind<NX, NU, NZ, M> for KalmanKind
where
    M: Model<NX, NU, NZ> + 'static,
{
    fn tag(&self) -> &str {
        self.which.tag()
    }
    fn about(&self) -> String {
        self.about.to_string()
    }
    fn configure(
        &self,
        cx: &FilterContext<'_, NX, NZ, M>,
        c: &mut Checker,
    ) -> Option<Arc<dyn FilterEntry<NX, NU, NZ, M>>> {
        let keys: KalmanKeys = c.parse(&cx.key, cx.table)?;
        let mut which = self.which;
        match which {
            Kalman::Ekf(_) => {
                let form = c.choice(
                    &format!("{}.covariance_update", cx.key),
                    keys.covariance_update.as_deref(),
                    "standard",
                    &["standard", "joseph"],
                );
                which = Kalman::Ekf(if form == "joseph" {
                    CovarianceUpdate::Joseph
                } else {
                    CovarianceUpdate::Standard
                });
            }
            other => c.reject_present(
                &cx.key,
                &[("covariance_update", keys.covariance_update.is_some())],
                &format!("not used by a {} filter", other.tag()),
            ),
        }
        match which {
            Kalman::SigmaPoint(SigmaPoints::Unscented { .. }) => {
                let SigmaPoints::Unscented { alpha, beta, kappa } = SigmaPoints::DEFAULT_UNSCENTED
                else {
                    unreachable!("the default points are unscented")
                };
                let points = SigmaPoints::Unscented {
                    alpha: keys.alpha.unwrap_or(alpha),
                    beta: keys.beta.unwrap_or(beta),
                    kappa: keys.kappa.unwrap_or(kappa),
                };
                // Every parameter is checked on its own, so one bad key does not hide another.
                for e in unscented_problems(points, NX) {
                    c.err(format!("{}.{}", cx.key, e.key()), e.to_string());
                }
                which = Kalman::SigmaPoint(points);
            }
            other => c.reject_present(
                &cx.key,
                &[
                    ("alpha", keys.alpha.is_some()),
                    ("beta", keys.beta.is_some()),
                    ("kappa", keys.kappa.is_some()),
                ],
                &format!(
                    "not used by kind = \"{}\" (only ukf has sigma-point parameters)",
                    other.tag()
                ),
            ),
        }
        if which == Kalman::OpenLoop {
            c.reject_present(
                &cx.key,
                &[("r_std", keys.r_std.is_some())],
                "not used by an open_loop filter (it never updates)",
            );
        }
        if let Some(msg) = self.requires.and_then(|f| f(cx.model as &dyn Any)) {
            c.err(format!("{}.kind", cx.key), msg);
        }
        let noise = AssumedStd::read_with(
            cx,
            keys.q_std.as_ref(),
            keys.r_std.as_ref(),
            which != Kalman::OpenLoop,
            c,
        );
        Some(Arc::new(KalmanEntry { which, noise }))
    }
}

/// The problems of a set of unscented parameters, one per key.
fn unscented_problems(points: SigmaPoints, n: usize) -> Vec<SigmaPointError> {
    let SigmaPoints::Unscented { alpha, beta, kappa } = points else {
        return Vec::new();
    };
    let one = |p: SigmaPoints| p.weights(n).err();
    let mut out: Vec<SigmaPointError> = [
        one(SigmaPoints::Unscented {
            alpha,
            beta: 2.0,
            kappa: 0.0,
        }),
        one(SigmaPoints::Unscented {
            alpha: 1.0,
            beta,
            kappa: 0.0,
        }),
        one(SigmaPoints::Unscented {
            alpha: 1.0,
            beta: 2.0,
            kappa,
        }),
    ]
    .into_iter()
    .flatten()
    .collect();
    if out.is_empty()
        && let Err(e) = points.weights(n)
    {
        out.push(e);
    }
    out
}

/// The kinds that work on any model: `ekf`, `information`, `sqrt`, `open_loop`, `ukf`, `ckf`.
pub fn common_kinds<const NX: usize, const NU: usize, const NZ: usize, M>()
-> FilterKinds<NX, NU, NZ, M>
where
    M: Model<NX, NU, NZ> + 'static,
{
    FilterKinds::default()
        .with(KalmanKind {
            which: Kalman::Ekf(CovarianceUpdate::Standard),
            about: "extended Kalman filter; q_std, r_std, covariance_update = standard | joseph",
            requires: None,
        })
        .with(KalmanKind {
            which: Kalman::Information,
            about: "information filter (Y = P⁻¹, y = P⁻¹x̂); needs F invertible and Q positive definite; q_std, r_std",
            requires: None,
        })
        .with(KalmanKind {
            which: Kalman::Sqrt,
            about: "square-root filter (P = S Sᵀ by QR of stacked pre-arrays); q_std, r_std",
            requires: None,
        })
        .with(KalmanKind {
            which: Kalman::OpenLoop,
            about: "the time update alone (measurements ignored): propagated covariance vs Monte Carlo spread; q_std",
            requires: None,
        })
        .with(KalmanKind {
            which: Kalman::SigmaPoint(SigmaPoints::DEFAULT_UNSCENTED),
            about: "unscented Kalman filter (scaled sigma points, additive noise, circular means of angles); q_std, r_std, alpha = 1, beta = 2, kappa = 0 (defaults: every weight non-negative)",
            requires: None,
        })
        .with(KalmanKind {
            which: Kalman::SigmaPoint(SigmaPoints::Cubature),
            about: "cubature Kalman filter (third-degree spherical-radial rule, 2n equal weights); q_std, r_std",
            requires: None,
        })
}

/// [`common_kinds`] plus the fixed-gain kinds of a linear model: `steady_state` (the DARE)
/// and `pole_placement` (a Luenberger observer). `detectable` tells whether the model's
/// sensor set admits a steady state (and, for the placement, is observable); it returns the
/// message to give when it does not.
pub fn linear_kinds<const NX: usize, const NU: usize, const NZ: usize, M>(
    detectable: fn(&dyn Any) -> Option<String>,
) -> FilterKinds<NX, NU, NZ, M>
where
    M: Model<NX, NU, NZ> + 'static,
{
    common_kinds()
        .with(KalmanKind {
            which: Kalman::SteadyState,
            about: "fixed-gain KF from the discrete Riccati equation (detectable linear models); q_std, r_std",
            requires: Some(detectable),
        })
        .with(PolePlacementKind { detectable })
}

/// Keys of a pole-placement entry.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct PoleKeys {
    poles: Option<Vec<Vec<f64>>>,
    pole_scale: Option<f64>,
    pole_reading: Option<String>,
}

struct PolePlacementKind {
    detectable: fn(&dyn Any) -> Option<String>,
}

#[derive(Debug)]
struct PoleEntry<const NX: usize, const NZ: usize> {
    observer: Luenberger<NX, NZ>,
}

impl<const NX: usize, const NU: usize, const NZ: usize, M> FilterEntry<NX, NU, NZ, M>
    for PoleEntry<NX, NZ>
where
    M: Model<NX, NU, NZ> + 'static,
{
    fn info(&self) -> FilterInfo {
        FilterInfo {
            kind: "pole_placement".into(),
            has_covariance: false,
            q_scale: false,
            r_scale: false,
        }
    }
    fn assumed_std(&self) -> (&[f64], &[f64]) {
        (&[], &[])
    }
    fn prepare(
        &self,
        _model: &M,
        _noise: &AssumedNoise<NX, NZ>,
    ) -> Box<dyn RunFilter<NX, NU, NZ, M>> {
        Box::new(self.observer.clone())
    }
}

impl<const NX: usize, const NU: usize, const NZ: usize, M> FilterKind<NX, NU, NZ, M>
    for PolePlacementKind
where
    M: Model<NX, NU, NZ> + 'static,
{
    fn tag(&self) -> &str {
        "pole_placement"
    }
    fn about(&self) -> String {
        "Luenberger observer, gain by MIMO pole placement; poles = [[re, im], …] or pole_scale = a \
         (seed list a·{−0.707±0.707i, 1, −0.3536±0.3536i, 0.5}), pole_reading = printed | negated \
         (observable linear models); no covariance, so NEES/NIS are null"
            .into()
    }
    fn configure(
        &self,
        cx: &FilterContext<'_, NX, NZ, M>,
        c: &mut Checker,
    ) -> Option<Arc<dyn FilterEntry<NX, NU, NZ, M>>> {
        let keys: PoleKeys = c.parse(&cx.key, cx.table)?;
        let poles = pole_list(c, &cx.key, &keys);
        if let Some(msg) = (self.detectable)(cx.model as &dyn Any) {
            c.err(
                format!("{}.kind", cx.key),
                msg.replace("steady_state", "pole_placement"),
            );
            return None;
        }
        // Place now, so an impossible request is a spec error, not 100 failed runs.
        match Luenberger::<NX, NZ>::from_poles(cx.model, &poles?) {
            Ok(observer) => Some(Arc::new(PoleEntry { observer })),
            Err(e) => {
                // The seed's list has no `poles` in the file: its scale is what was asked.
                let k = if keys.poles.is_some() {
                    "poles"
                } else {
                    "pole_scale"
                };
                c.err(format!("{}.{k}", cx.key), e.to_string());
                None
            }
        }
    }
}

/// The poles of a pole_placement filter: explicit `poles`, or the seed's list
/// a·{−0.707 ± 0.707i, 1, −0.3536 ± 0.3536i, 0.5} with `pole_scale` = a and `pole_reading`.
fn pole_list(c: &mut Checker, key: &str, f: &PoleKeys) -> Option<Vec<(f64, f64)>> {
    match (&f.poles, f.pole_scale) {
        (Some(poles), None) => {
            if f.pole_reading.is_some() {
                c.err(
                    format!("{key}.pole_reading"),
                    "only the seed's list (pole_scale) has a reading; explicit poles are exact",
                );
            }
            let mut out = Vec::with_capacity(poles.len());
            for (i, p) in poles.iter().enumerate() {
                match p.as_slice() {
                    [re, im] if re.is_finite() && im.is_finite() => out.push((*re, *im)),
                    [re] if re.is_finite() => out.push((*re, 0.0)),
                    _ => {
                        c.err(
                            format!("{key}.poles[{i}]"),
                            format!("expected [re, im] (finite numbers), got {p:?}"),
                        );
                        return None;
                    }
                }
            }
            Some(out)
        }
        (None, Some(a)) => {
            if !positive(a) {
                c.err(
                    format!("{key}.pole_scale"),
                    format!("{a} is not a positive number"),
                );
                return None;
            }
            let reading = match c.choice(
                &format!("{key}.pole_reading"),
                f.pole_reading.as_deref(),
                "printed",
                &["printed", "negated"],
            ) {
                "negated" => SeedPoleReading::Negated,
                _ => SeedPoleReading::Printed,
            };
            Some(seed_poles(a, reading).to_vec())
        }
        (Some(_), Some(_)) => {
            c.err(
                format!("{key}.poles"),
                "give either poles or pole_scale (the seed's list times a), not both",
            );
            None
        }
        (None, None) => {
            c.err(
                key.to_string(),
                "a pole_placement filter needs poles = [[re, im], …] or pole_scale = a (the seed's list)",
            );
            None
        }
    }
}

/// A configured additive system: the model, its scenarios, the truth's noise and the
/// validated filter entries. It is the [`SystemPlan`]; [`SystemPlan::trial`] binds it to a
/// plan's runs.
pub struct AdditivePlan<const NX: usize, const NU: usize, const NZ: usize, M> {
    /// The model (the world's and the filters').
    pub model: M,
    /// Names and Δt.
    pub layout: Layout,
    /// The expanded scenarios (x0 and u_0..u_K).
    pub scenarios: Vec<Scenario<NX, NU>>,
    /// The scenarios as the generic code sees them (same order).
    pub scenario_info: Vec<ScenarioInfo>,
    /// The truth's noise at scale 1 (per-state std; a model with a full Q samples that).
    pub truth_noise: TruthNoise<NX, NZ>,
    /// P_0 = diag(p0_std²).
    pub p0_std: Vector<NX>,
    /// Per scenario: the batch least-squares initialiser (`initial_estimate.mode = "batch_ls"`).
    pub batch: Option<Vec<BatchInitial<NX>>>,
    /// The filter entries, in spec order.
    pub entries: Vec<Arc<dyn FilterEntry<NX, NU, NZ, M>>>,
    /// Their infos (same order).
    pub filter_info: Vec<FilterInfo>,
    /// The system's own sections of `kfmc describe` (e.g. the ranks of other sensor sets).
    pub analysis_sections: Vec<crate::analysis::Section>,
}

impl<const NX: usize, const NU: usize, const NZ: usize, M: Debug> Debug
    for AdditivePlan<NX, NU, NZ, M>
{
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("AdditivePlan")
            .field("model", &self.model)
            .field("layout", &self.layout)
            .field("scenarios", &self.scenario_info)
            .field("filters", &self.entries)
            .finish_non_exhaustive()
    }
}

impl<const NX: usize, const NU: usize, const NZ: usize, M> AdditivePlan<NX, NU, NZ, M>
where
    M: Model<NX, NU, NZ> + Debug + 'static,
{
    /// A plan from its parts; the filter infos are taken from the entries.
    pub fn new(
        model: M,
        layout: Layout,
        scenarios: Vec<Scenario<NX, NU>>,
        truth_noise: TruthNoise<NX, NZ>,
        p0_std: Vector<NX>,
        entries: Vec<Arc<dyn FilterEntry<NX, NU, NZ, M>>>,
    ) -> Self {
        AdditivePlan {
            scenario_info: scenarios
                .iter()
                .map(|s| ScenarioInfo {
                    name: s.name.clone(),
                    steps: s.steps(),
                })
                .collect(),
            filter_info: entries.iter().map(|e| e.info()).collect(),
            model,
            layout,
            scenarios,
            truth_noise,
            p0_std,
            batch: None,
            entries,
            analysis_sections: Vec::new(),
        }
    }
}

impl<const NX: usize, const NU: usize, const NZ: usize, M> SystemPlan
    for AdditivePlan<NX, NU, NZ, M>
where
    M: Model<NX, NU, NZ> + Debug + 'static,
{
    fn layout(&self) -> &Layout {
        &self.layout
    }
    fn scenarios(&self) -> &[ScenarioInfo] {
        &self.scenario_info
    }
    fn filters(&self) -> &[FilterInfo] {
        &self.filter_info
    }
    fn trial<'a>(&'a self, settings: &'a RunSettings) -> Box<dyn Trial + 'a> {
        Box::new(AdditiveTrial::new(self, settings))
    }
    fn as_any(&self) -> &dyn Any {
        self
    }
    fn describe(&self, settings: &RunSettings) -> Option<crate::analysis::Description> {
        let trial = AdditiveTrial::new(self, settings);
        let mut d = super::describe::describe_model(
            settings,
            &self.layout,
            &self.model,
            &self.scenarios,
            &self.truth_noise,
            |scenario| trial.clean_consistency(scenario),
        );
        d.sections.extend(self.analysis_sections.iter().cloned());
        Some(d)
    }
    fn filter_model(&self) -> Option<super::filter_model::FilterModel<'_>> {
        Some(super::filter_model::FilterModel::of_additive(
            &self.model,
            NU,
            &self.truth_noise,
            &self.p0_std,
            &self.scenarios,
        ))
    }
}

/// The trial of an [`AdditivePlan`] for one study's settings.
struct AdditiveTrial<'a, const NX: usize, const NU: usize, const NZ: usize, M> {
    sys: &'a AdditivePlan<NX, NU, NZ, M>,
    settings: &'a RunSettings,
    p0: Matrix<NX, NX>,
    p0_factor: Option<Matrix<NX, NX>>,
    /// The model's full discrete Q, which filters assume (times q_scale) when it exists.
    model_q: Option<Matrix<NX, NX>>,
    names: Vec<&'a str>,
    /// The angle quantities (index, in degrees), whose errors are wrapped.
    angles: Vec<(usize, bool)>,
    /// The rotations among the quantities, scored by their rotation error.
    rotations: Vec<crate::linalg::so3::EulerRotation>,
    /// What the consistency tests need of every run (the same for all of them).
    consistency: Option<ConsistencyOptions>,
    /// Per (filter variant, noise scale): the prepared filter, built on first use.
    prepared: Vec<OnceLock<Box<dyn RunFilter<NX, NU, NZ, M>>>>,
}

impl<'a, const NX: usize, const NU: usize, const NZ: usize, M> AdditiveTrial<'a, NX, NU, NZ, M>
where
    M: Model<NX, NU, NZ>,
{
    fn new(sys: &'a AdditivePlan<NX, NU, NZ, M>, settings: &'a RunSettings) -> Self {
        AdditiveTrial {
            p0: diag_from_std(&sys.p0_std),
            p0_factor: (settings.initial == InitialMode::Sampled)
                .then(|| Matrix::<NX, NX>::from_diagonal(&sys.p0_std)),
            model_q: sys.model.process_noise_covariance(),
            names: sys.layout.quantity_names(),
            angles: sys.layout.angles(),
            rotations: sys.layout.rotations(),
            consistency: settings.consistency_options(&sys.layout),
            prepared: (0..settings.filters.len() * settings.noise_scales.len())
                .map(|_| OnceLock::new())
                .collect(),
            sys,
            settings,
        }
    }

    /// The filter's Q and R for a variant at a truth-noise scale.
    fn assumed(&self, variant: usize, filter_scale: f64) -> AssumedNoise<NX, NZ> {
        let f = &self.settings.filters[variant];
        let (q_std, r_std) = self.sys.entries[f.entry].assumed_std();
        let q = match &self.model_q {
            Some(q) => q * (filter_scale * filter_scale * f.q_scale),
            None if q_std.len() == NX => {
                diag_from_std(&(Vector::<NX>::from_column_slice(q_std) * filter_scale)) * f.q_scale
            }
            None => Matrix::<NX, NX>::zeros(),
        };
        let r = if r_std.len() == NZ {
            diag_from_std(&(Vector::<NZ>::from_column_slice(r_std) * filter_scale)) * f.r_scale
        } else {
            Matrix::<NZ, NZ>::zeros()
        };
        AssumedNoise { q, r }
    }

    /// P_0 for a run of system scenario `si`; with the batch initialiser also x̂_0, set in
    /// `trajectory` from the run's own measurements (its covariance scaled as the filters'
    /// noise is).
    fn initial_estimate(
        &self,
        si: usize,
        trajectory: &mut crate::sim::Trajectory<NX, NZ>,
        filter_scale: f64,
    ) -> Matrix<NX, NX> {
        match &self.sys.batch {
            Some(batch) => {
                let b = &batch[si];
                trajectory.x0_hat = b.estimate(&trajectory.measurements);
                b.covariance * (filter_scale * filter_scale)
            }
            None => self.p0,
        }
    }

    /// The consistency sums of every filter variant on the clean (noise-free) run of study
    /// scenario `scenario`, with the filters' Q and R at noise scale 1: what `kfmc describe`
    /// calibrates the tests with. `None` for a variant without a covariance or an external one.
    fn clean_consistency(&self, scenario: usize) -> Vec<Option<RunConsistency>> {
        let (settings, sys) = (self.settings, self.sys);
        let si = settings.scenarios[scenario].index;
        let sc = &sys.scenarios[si];
        let draws = NoiseDraws::<NX, NZ>::draw(0, sc.steps());
        let mut trajectory = simulate(&sys.model, sc, &sys.truth_noise, 0.0, None, &draws);
        let p0 = self.initial_estimate(si, &mut trajectory, 1.0);
        let prior = Prior {
            x0_hat: &trajectory.x0_hat,
            p0: &p0,
        };
        let ctx = RunContext {
            truth: &trajectory.truth,
            inputs: &sc.controls,
            measurements: &trajectory.measurements,
            angles: &self.angles,
            rotations: &self.rotations,
            thresholds: None,
            quantity_names: &self.names,
            trace: false,
            export: false,
            consistency: Some(
                settings
                    .consistency_options(&sys.layout)
                    .unwrap_or_else(|| settings.consistency_options_with_lags(&sys.layout, 0)),
            ),
            unit: Unit {
                scenario,
                scale: 0,
                run: 0,
            },
        };
        settings
            .filters
            .iter()
            .enumerate()
            .map(|(fi, f)| {
                if f.external {
                    return None;
                }
                let filter = sys.entries[f.entry].prepare(&sys.model, &self.assumed(fi, 1.0));
                filter.run(&sys.model, &prior, &ctx).run.consistency
            })
            .collect()
    }
}

impl<const NX: usize, const NU: usize, const NZ: usize, M> Trial
    for AdditiveTrial<'_, NX, NU, NZ, M>
where
    M: Model<NX, NU, NZ>,
{
    fn run(&self, unit: &Unit) -> UnitResult {
        let settings = self.settings;
        let sys = self.sys;
        let si = settings.scenarios[unit.scenario].index;
        let scenario = &sys.scenarios[si];
        let noise_scale = settings.noise_scales[unit.scale];
        let seed = settings.run_seed(&scenario.name, unit.scale, unit.run);
        let draws = NoiseDraws::<NX, NZ>::draw(seed, scenario.steps());
        let mut trajectory = simulate(
            &sys.model,
            scenario,
            &sys.truth_noise,
            noise_scale,
            self.p0_factor.as_ref(),
            &draws,
        );
        let traced = unit.run < settings.trace_runs;
        let filter_scale = match settings.filter_noise {
            FilterNoiseMode::Nominal => 1.0,
            FilterNoiseMode::Matched => noise_scale,
        };
        let p0 = self.initial_estimate(si, &mut trajectory, filter_scale);
        let prior = Prior {
            x0_hat: &trajectory.x0_hat,
            p0: &p0,
        };
        let ctx = RunContext {
            truth: &trajectory.truth,
            inputs: &scenario.controls,
            measurements: &trajectory.measurements,
            angles: &self.angles,
            rotations: &self.rotations,
            thresholds: settings.rmse_thresholds.as_deref(),
            quantity_names: &self.names,
            trace: traced,
            export: settings.export_estimates,
            consistency: self.consistency,
            unit: *unit,
        };
        let keep = traced || settings.export_estimates;
        let mut trace = keep.then(|| {
            let mut t = RunTrace::of_world(
                &scenario.controls,
                &trajectory.truth,
                &trajectory.measurements,
                Vec::new(),
            );
            t.initial = Some((trajectory.x0_hat.as_slice().to_vec(), lower_triangle(&p0)));
            t
        });
        let mut filters = Vec::with_capacity(settings.filters.len());
        for (fi, f) in settings.filters.iter().enumerate() {
            let mut out = if f.external {
                crate::score::replay(
                    settings.estimates.as_deref(),
                    fi,
                    &f.label,
                    &sys.model,
                    &ctx,
                )
            } else {
                let slot = &self.prepared[fi * settings.noise_scales.len() + unit.scale];
                let filter = slot.get_or_init(|| {
                    sys.entries[f.entry].prepare(&sys.model, &self.assumed(fi, filter_scale))
                });
                filter.run(&sys.model, &prior, &ctx)
            };
            if let Some(t) = trace.as_mut() {
                t.push_filter(&mut out, NX);
            }
            filters.push(out.run);
        }
        UnitResult {
            unit: *unit,
            seed,
            filters,
            trace,
            world_metrics: Vec::new(),
        }
    }

    fn steps(&self, scenario: usize) -> usize {
        self.sys.scenarios[self.settings.scenarios[scenario].index].steps()
    }

    fn layout(&self) -> &Layout {
        &self.sys.layout
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// x_k = x_{k−1} + w_k, z = x[0], with its own Q.
    struct Walk(Matrix<2, 2>);

    impl Model<2, 1, 1> for Walk {
        fn dt_s(&self) -> f64 {
            0.1
        }
        fn propagate(&self, x: &Vector<2>, _: &Vector<1>) -> Vector<2> {
            *x
        }
        fn transition_jacobian(&self, _: &Vector<2>, _: &Vector<1>) -> Matrix<2, 2> {
            Matrix::<2, 2>::identity()
        }
        fn measure(&self, x: &Vector<2>, _: &Vector<1>) -> Vector<1> {
            Vector::<1>::new(x[0])
        }
        fn measurement_jacobian(&self, _: &Vector<2>, _: &Vector<1>) -> Matrix<1, 2> {
            Matrix::<1, 2>::new(1.0, 0.0)
        }
        fn process_noise_covariance(&self) -> Option<Matrix<2, 2>> {
            Some(self.0)
        }
    }

    fn configure(q: Matrix<2, 2>, process_std: &[f64]) -> (usize, Vec<String>) {
        let kinds = common_kinds::<2, 1, 1, Walk>();
        let filters = vec![super::super::FilterTable {
            key: "filters[0]".into(),
            label: "ekf".into(),
            kind: "ekf".into(),
            keys: toml::Table::new(),
        }];
        let mut c = Checker::new(std::path::Path::new("t.toml"), "");
        let entries = kinds.configure_all(
            &filters,
            &Walk(q),
            "walk",
            process_std,
            &[0.1],
            &|_| None,
            &mut c,
        );
        let errors = c.into_errors().iter().map(|e| e.to_string()).collect();
        (entries.len(), errors)
    }

    /// With a full Q the filters assume it, so the truth's per-state std (which a model
    /// with a full Q need not have) is not demanded as the default of q_std; a Q that is no
    /// covariance is refused at `model`, singular ones are accepted.
    #[test]
    fn a_full_q_needs_no_per_state_std_and_must_be_a_covariance() {
        let singular = Matrix::<2, 2>::new(1.0, 2.0, 2.0, 4.0);
        let (n, errors) = configure(singular, &[f64::NAN, -1.0]);
        assert_eq!((n, errors.len()), (1, 0), "{errors:?}");
        let indefinite = Matrix::<2, 2>::new(1.0, 2.0, 2.0, 1.0);
        let (_, errors) = configure(indefinite, &[1.0, 1.0]);
        assert_eq!(errors.len(), 1, "{errors:?}");
        assert!(
            errors[0].contains("t.toml: model: the walk model's process-noise covariance Q"),
            "{errors:?}"
        );
    }
}
