//! `kfmc describe` for a system: the analysis of [`crate::analysis`] applied to a study's
//! scenarios and filter variants.

use crate::analysis::{
    Description, FilterAnalysis, ScenarioAnalysis, SteadyStateAnalysis, TestDof, eigenvalues,
    input_matrix, observability, rows, same_matrix,
};
use crate::filter::steady_state::solve_dare;
use crate::linalg::{Matrix, diag_from_std};
use crate::metrics::RunConsistency;
use crate::model::{Availability, Model};
use crate::scenario::Scenario;
use crate::sim::TruthNoise;

use super::Layout;
use super::settings::RunSettings;

/// The layout part of a description: names, units and Δt (the experiment layer adds the
/// system's kind and the experiment's name).
pub fn header(l: &Layout) -> Description {
    Description {
        dt_s: l.dt_s,
        quantities: l
            .quantities
            .iter()
            .map(|q| {
                if q.unit.is_empty() {
                    q.name.clone()
                } else {
                    format!("{} [{}]", q.name, q.unit)
                }
            })
            .collect(),
        measurements: l.measurements.clone(),
        inputs: l.inputs.clone(),
        ..Default::default()
    }
}

/// The analysis of an additive-noise system built on one [`Model`]: see the module docs.
/// `clean` returns, for a study scenario, every filter variant's consistency sums on the
/// clean run (in plan order).
pub fn describe_model<const NX: usize, const NU: usize, const NZ: usize, M: Model<NX, NU, NZ>>(
    settings: &RunSettings,
    layout: &Layout,
    model: &M,
    scenarios: &[Scenario<NX, NU>],
    truth_noise: &TruthNoise<NX, NZ>,
    clean: impl Fn(usize) -> Vec<Option<RunConsistency>>,
) -> Description {
    let mut d = header(layout);
    let q = model
        .process_noise_covariance()
        .unwrap_or_else(|| diag_from_std(&truth_noise.process_std));
    let r = diag_from_std(&truth_noise.measurement_std);
    let meas = layout.measurement_names();
    for (ps, sp) in settings.scenarios.iter().enumerate() {
        let sc = &scenarios[sp.index];
        let steps = sc.steps();
        let mut a = ScenarioAnalysis {
            scenario: sp.name.clone(),
            steps,
            process_noise: rows(&q),
            measurement_noise: rows(&r),
            ..Default::default()
        };
        // The clean trajectory x_0..x_K and its Jacobians F_1..F_K, H_1..H_K.
        let mut x = sc.x0;
        let mut fs = Vec::with_capacity(steps);
        let mut hs = Vec::with_capacity(steps);
        let mut avail = Vec::with_capacity(steps);
        let mut first_x = sc.x0;
        for k in 1..=steps {
            let u = &sc.controls[k];
            fs.push(model.transition_jacobian(&x, u));
            if k == 1 {
                first_x = x;
            }
            x = model.propagate(&x, u);
            hs.push(model.measurement_jacobian(&x, u));
            avail.push(model.availability(k));
        }
        if steps == 0 {
            a.notes.push("no transitions: nothing to analyse".into());
            d.scenarios.push(a);
            continue;
        }
        a.time_invariant =
            fs.iter().all(|f| same_matrix(f, &fs[0])) && hs.iter().all(|h| same_matrix(h, &hs[0]));
        let all = Availability::all(NZ);
        a.single_rate = avail.iter().all(|v| *v == all);
        a.transition = rows(&fs[0]);
        a.measurement_matrix = rows(&hs[0]);
        let (g, affine) = input_matrix(|x, u| model.propagate(x, u), &first_x, &sc.controls[1]);
        a.input_matrix = rows(&g);
        a.input_matrix_method = if affine {
            "exact: f is affine in u"
        } else {
            "central difference"
        }
        .into();
        a.observability = observability(&fs, &hs, &avail, &meas, a.time_invariant);
        if a.time_invariant && a.single_rate {
            if a.observability
                .unobservable_modes
                .iter()
                .any(|m| m[0].hypot(m[1]) >= 1.0 - 1e-6)
            {
                a.notes.push(
                    "no steady state: an unobservable mode of F does not decay (|λ| ≥ 1), so (F, H) is not detectable"
                        .into(),
                );
            } else {
                match solve_dare(&fs[0], &hs[0], &q, &r) {
                    Ok(dare) => {
                        let closed = (Matrix::<NX, NX>::identity() - dare.gain * dare.h) * dare.f;
                        let poles = eigenvalues(&closed);
                        a.steady_state = Some(SteadyStateAnalysis {
                            gain: rows(&dare.gain),
                            prior_covariance: rows(&dare.p_prior),
                            posterior_covariance: rows(&dare.p_post),
                            spectral_radius: poles.first().map_or(0.0, |p| p[0].hypot(p[1])),
                            poles,
                            riccati_iterations: dare.iterations,
                        });
                    }
                    Err(e) => a.notes.push(format!("no steady state: {e}")),
                }
            }
        } else {
            a.notes.push(
                "no steady state: the model is time-varying or multi-rate, so the Kalman gain does not converge to one K∞"
                    .into(),
            );
        }
        let mut run_counts = vec![settings.runs];
        if let Some(c) = &settings.consistency {
            for (n, _) in &c.subsets {
                if !run_counts.contains(n) {
                    run_counts.push(*n);
                }
            }
        }
        for (f, sums) in settings.filters.iter().zip(clean(ps)) {
            let Some(sums) = sums else { continue };
            let n = NX as f64;
            let k = sums.nees_n as f64;
            let rho = sums.rho_sum.map(|s| 1.0 + 2.0 * s / (n * k));
            a.filters.push(FilterAnalysis {
                filter: f.label.clone(),
                q_scale: f.q_scale,
                r_scale: f.r_scale,
                first_step: sums.first_step.unwrap_or(1),
                nees_steps: sums.nees_n,
                rho,
                nis_dof_per_run: sums.nis_dof,
                dof: run_counts
                    .iter()
                    .map(|&runs| TestDof {
                        runs,
                        nees_effective_dof: rho.map(|rho| runs as f64 * k * n / rho),
                        nees_naive_dof: runs as f64 * k * n,
                        nis_dof: runs as u64 * sums.nis_dof,
                    })
                    .collect(),
            });
        }
        d.scenarios.push(a);
    }
    d
}
