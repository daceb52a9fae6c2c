//! The built-in filter kinds of additive systems: [`common_kinds`] work on any [`Model`]
//! (EKF, information, square-root, open loop, UKF, CKF), [`linear_kinds`] add the fixed-gain
//! ones that need a linear model (steady state, pole placement). They are made through the
//! same [`FilterKind`] trait a user's kind implements.

use std::any::Any;
use std::sync::Arc;

use serde::Deserialize;

use super::FilterInfo;
use super::checker::{Checker, positive};
use super::filter_kind::{
    AssumedNoise, AssumedStd, FilterContext, FilterEntry, FilterKind, FilterKinds, RunFilter,
};
use super::spec_values::OneOrMany;
use crate::filter::luenberger::{SeedPoleReading, seed_poles};
use crate::filter::sigma_point::SigmaPointError;
use crate::filter::{
    CovarianceUpdate, Ekf, Information, Luenberger, OpenLoop, SigmaPointKalman, SigmaPoints,
    SquareRoot, SteadyState,
};
use crate::model::Model;

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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::linalg::{Matrix, Vector};
    use crate::system::filter_kind::FilterSetup;

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
        let entries = kinds.configure_entries(
            &filters,
            &FilterSetup::new(&Walk(q), "walk", process_std, &[0.1]),
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

    /// The deprecated `configure_all` (the setup as separate arguments) configures what
    /// `configure_entries` does and reports the same problems, an unknown kind explained by
    /// its `unknown` too.
    #[test]
    #[allow(deprecated)]
    fn the_deprecated_configure_all_is_configure_entries() {
        let kinds = common_kinds::<2, 1, 1, Walk>();
        let table = |kind: &str| super::super::FilterTable {
            key: "filters[0]".into(),
            label: kind.into(),
            kind: kind.into(),
            keys: toml::from_str("r_std = 0.2").unwrap(),
        };
        let walk = Walk(Matrix::<2, 2>::identity());
        let filters = [table("ekf"), table("ukf"), table("gimbal")];
        let explain = |kind: &str| (kind == "gimbal").then(|| "only on the drone".to_string());
        let mut old = Checker::new(std::path::Path::new("t.toml"), "");
        let by_arguments = kinds.configure_all(
            &filters,
            &walk,
            "walk",
            &[0.1, 0.1],
            &[0.1],
            &explain,
            &mut old,
        );
        let mut new = Checker::new(std::path::Path::new("t.toml"), "");
        let setup =
            FilterSetup::new(&walk, "walk", &[0.1, 0.1], &[0.1]).explaining_unknown(&explain);
        let by_setup = kinds.configure_entries(&filters, &setup, &mut new);
        let infos = |e: &[Arc<dyn FilterEntry<2, 1, 1, Walk>>]| -> Vec<(String, Vec<f64>)> {
            e.iter()
                .map(|e| (e.info().kind.clone(), e.assumed_std().1.to_vec()))
                .collect()
        };
        assert_eq!(infos(&by_arguments), infos(&by_setup));
        assert_eq!(by_setup.len(), 2);
        let errors =
            |c: Checker| -> Vec<String> { c.into_errors().iter().map(|e| e.to_string()).collect() };
        let (old, new) = (errors(old), errors(new));
        assert_eq!(old, new);
        assert!(
            old.len() == 1 && old[0].contains("only on the drone"),
            "{old:?}"
        );
    }

    /// A kind made from a function takes the assumed-noise keys and nothing else, reports a
    /// stray key at its path, and carries what it declares (that its filters run with each
    /// cell's Q and R is `tests/it/systems/own_filter.rs`: the user's EKF made this way equals
    /// kfmc's to round-off).
    #[test]
    fn a_kind_made_from_a_function_reads_the_noise_keys_and_says_what_it_declares() {
        use crate::filter::{CovarianceUpdate, Ekf};
        use crate::system::filter_kind::FnKind;
        let kinds = FilterKinds::<2, 1, 1, Walk>::default().with(
            FnKind::new("mine", "mine", |_: &Walk, n: &AssumedNoise<2, 1>| Ekf {
                q: n.q,
                r: n.r,
                update_form: CovarianceUpdate::Joseph,
            })
            .without_covariance(),
        );
        let table = |text: &str| super::super::FilterTable {
            key: "filters[3]".into(),
            label: "m".into(),
            kind: "mine".into(),
            keys: toml::from_str(text).unwrap(),
        };
        let walk = Walk(Matrix::<2, 2>::identity());
        let mut c = Checker::new(std::path::Path::new("t.toml"), "");
        let entries = kinds.configure_entries(
            &[table("r_std = 0.5"), table("r_stdd = 0.5")],
            &FilterSetup::new(&walk, "walk", &[0.1, 0.1], &[0.1]),
            &mut c,
        );
        let errors: Vec<String> = c.into_errors().iter().map(|e| e.key_path.clone()).collect();
        assert_eq!(errors, ["filters[3].r_stdd"]);
        let info = entries[0].info();
        assert_eq!((info.kind.as_str(), info.has_covariance), ("mine", false));
        assert_eq!(entries[0].assumed_std().1, [0.5]);
    }
}
