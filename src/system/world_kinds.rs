//! kfmc's filter kinds on a [`super::world::World`]: a world system whose evaluated quantities are the state
//! of a [`Model`] its filters assume selects `ekf`, `ukf`, `information`, … by name, with the
//! same keys, assumed-noise scaling and initial-estimate modes as an additive system.
//!
//! The world may be anything the model is not (other dynamics, heavier-tailed noise, states
//! the filters do not carry); only the filters' side is the model. A system builds a
//! [`WorldKinds`] from the kinds it offers ([`super::kinds::common_kinds`], its own, a user's
//! [`super::filter_kind::FnKind`]) and the model, and its `configure` calls
//! [`WorldKinds::configure`] for the [`super::world::WorldPlan`]'s entries.

use std::sync::Arc;

use super::checker::{Checker, positive};
use super::filter_kind::{AssumedNoise, FilterEntry, FilterKinds, FilterSetup, RunFilter};
use super::settings::InitialMode;
use super::world::{NoiseSettings, Realisation, WorldFilter, WorldFilterEntry};
use super::{FilterInfo, SystemSpec};
use crate::linalg::{Matrix, Vector, diag_from_std};
use crate::model::Model;
use crate::step_loop::{FilterOutput, Prior, RunContext};

/// Filter kinds that run a [`Model`] of the world's quantities on a [`super::world::World`].
pub struct WorldKinds<const N: usize, const NU: usize, const NZ: usize, M> {
    kinds: FilterKinds<N, NU, NZ, M>,
    model: Arc<M>,
    process_std: Vec<f64>,
    measurement_std: Vec<f64>,
    p0_std: Vec<f64>,
}

impl<const N: usize, const NU: usize, const NZ: usize, M> WorldKinds<N, NU, NZ, M>
where
    M: Model<N, NU, NZ> + 'static,
{
    /// The `kinds` on filters that assume `model`. `process_std` and `measurement_std` are
    /// the defaults of an entry's `q_std` and `r_std` (what the filters assume when the spec
    /// does not say: usually the world's own noise levels at scale 1); `p0_std` is the default
    /// of `initial_estimate.p0_std`.
    pub fn new(
        kinds: FilterKinds<N, NU, NZ, M>,
        model: M,
        process_std: &[f64],
        measurement_std: &[f64],
        p0_std: &[f64],
    ) -> Self {
        WorldKinds {
            kinds,
            model: Arc::new(model),
            process_std: process_std.to_vec(),
            measurement_std: measurement_std.to_vec(),
            p0_std: p0_std.to_vec(),
        }
    }

    /// The kinds, for the system's [`super::Catalogue`].
    pub fn kinds(&self) -> &FilterKinds<N, NU, NZ, M> {
        &self.kinds
    }

    /// Validates the spec's filter entries (named `system` in messages) and its
    /// `[initial_estimate]`, reporting problems at their key paths. `initial_estimate.mode`
    /// is `truth` (x̂_0 = q_0) or `sampled` (x̂_0 = q_0 + diag(p0_std) ζ with ζ the first N of
    /// [`Realisation::prior_draws`], which the world must then draw as standard normals);
    /// P_0 = diag(p0_std²).
    pub fn configure(
        &self,
        spec: &SystemSpec<'_>,
        system: &str,
        c: &mut Checker,
    ) -> Vec<Arc<dyn WorldFilterEntry<N, NU, NZ>>> {
        if spec.initial.mode == InitialMode::BatchLs {
            c.err(
                "initial_estimate.mode",
                format!(
                    "batch_ls needs the system's own initialiser, which the {system} world system does not have; use \"truth\" or \"sampled\""
                ),
            );
        }
        let p0_std = c.vector(
            "initial_estimate.p0_std",
            spec.initial.p0_std.as_ref(),
            N,
            &self.p0_std,
            positive,
            "a positive number",
        );
        let entries = self.kinds.configure_entries(
            spec.filters,
            &FilterSetup::new(
                &*self.model,
                system,
                &self.process_std,
                &self.measurement_std,
            ),
            c,
        );
        if p0_std.len() != N {
            return Vec::new();
        }
        let p0_std = Vector::<N>::from_column_slice(&p0_std);
        let start = Arc::new(Start {
            p0: diag_from_std(&p0_std),
            factor: (spec.initial.mode == InitialMode::Sampled)
                .then(|| Matrix::<N, N>::from_diagonal(&p0_std)),
        });
        entries
            .into_iter()
            .map(|entry| {
                Arc::new(KindEntry {
                    entry,
                    model: Arc::clone(&self.model),
                    start: Arc::clone(&start),
                }) as Arc<dyn WorldFilterEntry<N, NU, NZ>>
            })
            .collect()
    }
}

/// The filters' initial estimate: P_0, and L_0 = diag(p0_std) when x̂_0 is sampled.
#[derive(Debug)]
struct Start<const N: usize> {
    p0: Matrix<N, N>,
    factor: Option<Matrix<N, N>>,
}

/// A validated entry of a kind, on the world.
struct KindEntry<const N: usize, const NU: usize, const NZ: usize, M> {
    entry: Arc<dyn FilterEntry<N, NU, NZ, M>>,
    model: Arc<M>,
    start: Arc<Start<N>>,
}

impl<const N: usize, const NU: usize, const NZ: usize, M> std::fmt::Debug
    for KindEntry<N, NU, NZ, M>
{
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("KindEntry")
            .field("entry", &self.entry)
            .field("start", &self.start)
            .finish_non_exhaustive()
    }
}

impl<const N: usize, const NU: usize, const NZ: usize, M> WorldFilterEntry<N, NU, NZ>
    for KindEntry<N, NU, NZ, M>
where
    M: Model<N, NU, NZ> + 'static,
{
    fn info(&self) -> FilterInfo {
        self.entry.info()
    }

    fn prepare(&self, noise: &NoiseSettings) -> Box<dyn WorldFilter<N, NU, NZ>> {
        let model_q = self.model.process_noise_covariance();
        let assumed = AssumedNoise::for_cell(
            self.entry.assumed_std(),
            model_q.as_ref(),
            noise.filter_scale,
            noise.q_scale,
            noise.r_scale,
        );
        Box::new(KindFilter {
            filter: self.entry.prepare(&self.model, &assumed),
            model: Arc::clone(&self.model),
            start: Arc::clone(&self.start),
        })
    }
}

/// A prepared filter of a kind, on the world.
struct KindFilter<const N: usize, const NU: usize, const NZ: usize, M> {
    filter: Box<dyn RunFilter<N, NU, NZ, M>>,
    model: Arc<M>,
    start: Arc<Start<N>>,
}

impl<const N: usize, const NU: usize, const NZ: usize, M> WorldFilter<N, NU, NZ>
    for KindFilter<N, NU, NZ, M>
where
    M: Model<N, NU, NZ> + 'static,
{
    fn run(
        &self,
        realisation: &Realisation<N, NU, NZ>,
        ctx: &RunContext<'_, N, NU, NZ>,
    ) -> FilterOutput {
        let x0 = realisation.truth[0];
        let x0_hat = match &self.start.factor {
            None => x0,
            Some(l) if realisation.prior_draws.len() >= N => {
                x0 + l * Vector::<N>::from_column_slice(&realisation.prior_draws[..N])
            }
            Some(_) => {
                return FilterOutput::failed_at_start(
                    ctx,
                    format!(
                        "initial_estimate.mode = \"sampled\" needs {N} standard normals in the world's prior_draws, and it drew {}",
                        realisation.prior_draws.len()
                    ),
                );
            }
        };
        let prior = Prior {
            x0_hat: &x0_hat,
            p0: &self.start.p0,
        };
        self.filter.run(&self.model, &prior, ctx)
    }
}
