//! `kfmc describe`: a system's analysis, computed from the same model the runs use.
//!
//! For each scenario the model is linearised along its clean (noise-free) trajectory:
//!
//! * **Matrices.** F, H and the input matrix G at the first transition, with the truth's Q and
//!   R at noise scale 1. A model whose Jacobians are the same at every step is reported as
//!   time-invariant; its G is then exact (f(0, e_j) − f(0, 0)), otherwise a central
//!   difference.
//! * **Observability of x_0 from z_1..z_W.** The rank of the stacked rows H_k Φ_k with
//!   Φ_k = F_k ⋯ F_1, using only the components that report at step k, over a window W long
//!   enough for every component to report NX times (so a multi-rate sensor counts). For a
//!   time-invariant, single-rate model this is the rank of [H; HF; …; HF^{n−1}] (F is
//!   invertible for a discretised model), and also per measurement component and per
//!   sensor group (components with the same reporting schedule).
//! * **Steady state.** For a time-invariant, single-rate, detectable model: the DARE for the
//!   truth's Q and R, the gain K∞ and the poles of the error dynamics (I − K∞H)F.
//! * **Filters.** For every filter variant with an error transition A_k, the NEES variance
//!   inflation ρ = 1 + (2/(nK)) Σ tr(P_k⁻¹ W_k) (see [`crate::metrics::consistency`]) along
//!   the clean trajectory — exact for a linear filter, whose P_k and A_k do not depend on the
//!   data — and the effective degrees of freedom ν = N·K·n/ρ of the NEES test for the spec's
//!   run counts, beside the exact χ² dof of the NIS test.
//!
//! This module is the mathematics; [`crate::system::describe`] applies it to a study's scenarios
//! and filter variants. A system that is not built on [`crate::model::Model`] may implement
//! [`crate::system::SystemPlan::describe`] itself, or add its own sections.

use std::fmt::Write as _;

use serde::Serialize;

use crate::linalg::{Matrix, Vector};
use crate::model::Availability;

/// Relative singular-value threshold of the observability ranks (L1's sensor sets, the
/// detectability check of `steady_state`, `kfmc describe`).
pub const RANK_TOL: f64 = 1e-10;

/// What `kfmc describe` reports of a spec.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct Description {
    /// `model.kind`.
    pub kind: String,
    /// The experiment name.
    pub experiment: String,
    /// Sample time Δt in seconds.
    pub dt_s: f64,
    /// The evaluated quantities, with units.
    pub quantities: Vec<String>,
    /// The measurement components.
    pub measurements: Vec<String>,
    /// The inputs.
    pub inputs: Vec<String>,
    /// Per scenario, the linearised analysis (empty when the system offers none).
    pub scenarios: Vec<ScenarioAnalysis>,
    /// The system's own sections (e.g. the ranks of sensor sets other than the spec's).
    pub sections: Vec<Section>,
    /// What could not be analysed, and why.
    pub notes: Vec<String>,
    /// The model kfmc's filters use, at full precision, for filters written elsewhere
    /// ([`crate::system::SystemPlan::filter_model`]); absent for a system without one.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub filter_model: Option<crate::model::exposed::FilterModelRecord>,
}

/// A titled list of named values a system adds to its description.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Section {
    /// Title.
    pub title: String,
    /// (name, value) rows.
    pub rows: Vec<SectionRow>,
}

/// One row of a [`Section`].
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct SectionRow {
    /// What the value is.
    pub name: String,
    /// The value, as text.
    pub value: String,
}

/// The analysis of one scenario.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct ScenarioAnalysis {
    /// Scenario name.
    pub scenario: String,
    /// Transitions K.
    pub steps: usize,
    /// Whether F_k and H_k are the same at every step of the clean trajectory.
    pub time_invariant: bool,
    /// Whether every measurement component reports at every step.
    pub single_rate: bool,
    /// F (at the first transition).
    pub transition: Vec<Vec<f64>>,
    /// G = ∂f/∂u (at the first transition).
    pub input_matrix: Vec<Vec<f64>>,
    /// How G was obtained (`exact` for a time-invariant model, else `central difference`).
    pub input_matrix_method: String,
    /// H (at step 1, every component).
    pub measurement_matrix: Vec<Vec<f64>>,
    /// The truth's Q at noise scale 1.
    pub process_noise: Vec<Vec<f64>>,
    /// The truth's R at noise scale 1.
    pub measurement_noise: Vec<Vec<f64>>,
    /// Observability of x_0.
    pub observability: Observability,
    /// The steady-state Kalman filter, when there is one.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub steady_state: Option<SteadyStateAnalysis>,
    /// Per filter variant.
    pub filters: Vec<FilterAnalysis>,
    /// What could not be computed for this scenario, and why.
    pub notes: Vec<String>,
}

/// Observability ranks.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct Observability {
    /// State dimension n.
    pub states: usize,
    /// Measurements z_1..z_W stacked.
    pub window_steps: usize,
    /// Rank with every component.
    pub rank: usize,
    /// Rank with one component alone.
    pub per_component: Vec<GroupRank>,
    /// Rank with one sensor group alone (components with the same reporting schedule); only
    /// for multi-rate models, where the groups differ from the whole set.
    pub per_group: Vec<GroupRank>,
    /// The eigenvalues (re, im) of F on its unobservable subspace (time-invariant models).
    pub unobservable_modes: Vec<[f64; 2]>,
}

/// The rank of a subset of the measurement components.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct GroupRank {
    /// The components, joined by `+`.
    pub components: String,
    /// Rank.
    pub rank: usize,
}

/// The steady-state Kalman filter for the truth's Q and R.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct SteadyStateAnalysis {
    /// K∞.
    pub gain: Vec<Vec<f64>>,
    /// P∞⁻ (predicted).
    pub prior_covariance: Vec<Vec<f64>>,
    /// P∞ (updated).
    pub posterior_covariance: Vec<Vec<f64>>,
    /// Eigenvalues (re, im) of (I − K∞H)F, sorted by modulus, largest first.
    pub poles: Vec<[f64; 2]>,
    /// The largest pole modulus.
    pub spectral_radius: f64,
    /// Riccati iterations to convergence.
    pub riccati_iterations: usize,
}

/// A filter variant's test calibration along the clean trajectory.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct FilterAnalysis {
    /// Label.
    pub filter: String,
    /// Q multiplier.
    pub q_scale: f64,
    /// R multiplier.
    pub r_scale: f64,
    /// First step in the consistency sums.
    pub first_step: usize,
    /// Steps K in the NEES sum.
    pub nees_steps: u64,
    /// ρ, when the filter exposes its error transition.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub rho: Option<f64>,
    /// NIS degrees of freedom of one run (Σ_k p_k).
    pub nis_dof_per_run: u64,
    /// Per run count N of the spec (the study's, then the consistency subsets'): the NEES
    /// test's effective dof ν = N·K·n/ρ and the NIS test's exact dof N·Σp.
    pub dof: Vec<TestDof>,
}

/// Degrees of freedom of the time-averaged tests at one run count.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct TestDof {
    /// Runs N.
    pub runs: usize,
    /// ν = N·K·n/ρ.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub nees_effective_dof: Option<f64>,
    /// N·K·n, what the test would use if the steps were independent.
    pub nees_naive_dof: f64,
    /// N·Σp.
    pub nis_dof: u64,
}

/// The observability rank of (F, H) and the eigenvalues of F on its unobservable subspace.
///
/// O = [H; HF; …; HF^{NX−1}] (faer's SVD); its null space N (orthonormal, from the right
/// singular vectors) is F-invariant, so the unobservable modes are the eigenvalues of NᵀFN.
pub fn unobservable_modes<const NX: usize, const NZ: usize>(
    f: &Matrix<NX, NX>,
    h: &Matrix<NZ, NX>,
) -> (usize, Vec<(f64, f64)>) {
    let mut o = faer::Mat::<f64>::zeros(NX * NZ, NX);
    let mut hf = *h;
    for blk in 0..NX {
        for i in 0..NZ {
            for j in 0..NX {
                o[(blk * NZ + i, j)] = hf[(i, j)];
            }
        }
        hf *= f;
    }
    let Ok(svd) = o.svd() else {
        return (0, vec![]);
    };
    let s = svd.S().column_vector();
    let max = (0..s.nrows()).map(|i| s[i]).fold(0.0_f64, f64::max);
    let rank = (0..s.nrows()).filter(|&i| s[i] > RANK_TOL * max).count();
    if rank == NX {
        return (rank, vec![]);
    }
    let v = svd.V();
    let n = nalgebra::DMatrix::<f64>::from_fn(NX, NX - rank, |i, j| v[(i, rank + j)]);
    let fd = nalgebra::DMatrix::<f64>::from_fn(NX, NX, |i, j| f[(i, j)]);
    let fu = n.transpose() * fd * &n;
    let Ok(ev) = faer::Mat::<f64>::from_fn(fu.nrows(), fu.ncols(), |i, j| fu[(i, j)]).eigenvalues()
    else {
        return (rank, vec![]);
    };
    let mut modes: Vec<(f64, f64)> = ev.into_iter().map(|c| (c.re, c.im)).collect();
    modes.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.total_cmp(&b.1)));
    (rank, modes)
}

/// A fixed-size matrix as rows.
pub fn rows<const R: usize, const C: usize>(m: &Matrix<R, C>) -> Vec<Vec<f64>> {
    (0..R)
        .map(|i| (0..C).map(|j| m[(i, j)]).collect())
        .collect()
}

/// Whether two matrices agree to rounding (relative to the larger entry).
pub fn same_matrix<const R: usize, const C: usize>(a: &Matrix<R, C>, b: &Matrix<R, C>) -> bool {
    let scale = a.amax().max(b.amax()).max(1.0);
    (a - b).amax() <= 1e-12 * scale
}

/// The rank of stacked rows (each normalised to unit length first, which leaves the rank
/// unchanged and keeps rows of very different scales, such as H Φ_k late in a window of an
/// unstable model, from hiding each other).
pub fn stacked_rank(rows: &[Vec<f64>], cols: usize) -> usize {
    let kept: Vec<&Vec<f64>> = rows
        .iter()
        .filter(|r| r.iter().any(|v| *v != 0.0))
        .collect();
    if kept.is_empty() || cols == 0 {
        return 0;
    }
    let m = faer::Mat::<f64>::from_fn(kept.len(), cols, |i, j| {
        let norm = kept[i].iter().map(|v| v * v).sum::<f64>().sqrt();
        kept[i][j] / norm
    });
    crate::linalg::numerical_rank(m.as_ref(), RANK_TOL)
}

/// Eigenvalues (re, im) of a square matrix, sorted by modulus, largest first.
pub fn eigenvalues<const N: usize>(m: &Matrix<N, N>) -> Vec<[f64; 2]> {
    let a = faer::Mat::<f64>::from_fn(N, N, |i, j| m[(i, j)]);
    let Ok(ev) = a.eigenvalues() else {
        return Vec::new();
    };
    let mut out: Vec<[f64; 2]> = ev.into_iter().map(|c| [c.re, c.im]).collect();
    out.sort_by(|a, b| {
        b[0].hypot(b[1])
            .total_cmp(&a[0].hypot(a[1]))
            .then(b[1].total_cmp(&a[1]))
    });
    out
}

/// G = ∂f/∂u at (x, u), and whether it is exact: for f affine in u (successive unit steps in
/// each input change f by the same amount) the unit difference is G to rounding; otherwise a
/// central difference.
pub fn input_matrix<const NX: usize, const NU: usize>(
    propagate: impl Fn(&Vector<NX>, &Vector<NU>) -> Vector<NX>,
    x: &Vector<NX>,
    u: &Vector<NU>,
) -> (Matrix<NX, NU>, bool) {
    let mut g = Matrix::<NX, NU>::zeros();
    let base = propagate(x, u);
    let mut affine = true;
    for j in 0..NU {
        let (mut u1, mut u2) = (*u, *u);
        u1[j] += 1.0;
        u2[j] += 2.0;
        let f1 = propagate(x, &u1);
        let (d1, d2) = (f1 - base, propagate(x, &u2) - f1);
        affine &= (d1 - d2).amax() <= 1e-12 * base.amax().max(d1.amax()).max(1.0);
        g.set_column(j, &d1);
    }
    if !affine {
        for j in 0..NU {
            let h = 1e-6 * u[j].abs().max(1.0);
            let (mut up, mut dn) = (*u, *u);
            up[j] += h;
            dn[j] -= h;
            g.set_column(j, &((propagate(x, &up) - propagate(x, &dn)) / (2.0 * h)));
        }
    }
    (g, affine)
}

/// Observability of x_0 from z_1..z_W along Jacobians F_k, H_k (see the module docs).
pub fn observability<const NX: usize, const NZ: usize>(
    fs: &[Matrix<NX, NX>],
    hs: &[Matrix<NZ, NX>],
    avail: &[Availability],
    names: &[&str],
    time_invariant: bool,
) -> Observability {
    // Long enough for every component to report NX times (a multi-rate sensor counts).
    let mut reports = [0usize; NZ];
    let mut window = fs.len();
    for (k, av) in avail.iter().enumerate() {
        for (i, r) in reports.iter_mut().enumerate() {
            if av.has(i) {
                *r += 1;
            }
        }
        if reports.iter().all(|r| *r >= NX) {
            window = k + 1;
            break;
        }
    }
    // rows_of[i]: the rows H_k,i Φ_k of component i over the window.
    let mut rows_of: Vec<Vec<Vec<f64>>> = vec![Vec::new(); NZ];
    let mut phi = Matrix::<NX, NX>::identity();
    for k in 0..window {
        phi = fs[k] * phi;
        let hp = hs[k] * phi;
        for (i, r) in rows_of.iter_mut().enumerate() {
            if avail[k].has(i) {
                r.push((0..NX).map(|j| hp[(i, j)]).collect());
            }
        }
    }
    let rank_of = |comps: &[usize]| {
        let stacked: Vec<Vec<f64>> = comps.iter().flat_map(|&i| rows_of[i].clone()).collect();
        stacked_rank(&stacked, NX)
    };
    let every: Vec<usize> = (0..NZ).collect();
    let mut o = Observability {
        states: NX,
        window_steps: window,
        rank: rank_of(&every),
        per_component: (0..NZ)
            .map(|i| GroupRank {
                components: names.get(i).copied().unwrap_or("?").to_string(),
                rank: rank_of(&[i]),
            })
            .collect(),
        ..Default::default()
    };
    // Sensor groups: components with the same reporting schedule over the window.
    let schedule = |i: usize| -> Vec<bool> { avail[..window].iter().map(|a| a.has(i)).collect() };
    let mut groups: Vec<(Vec<bool>, Vec<usize>)> = Vec::new();
    for i in 0..NZ {
        let s = schedule(i);
        match groups.iter_mut().find(|(g, _)| *g == s) {
            Some((_, members)) => members.push(i),
            None => groups.push((s, vec![i])),
        }
    }
    if groups.len() > 1 {
        o.per_group = groups
            .iter()
            .map(|(_, members)| GroupRank {
                components: members
                    .iter()
                    .map(|&i| names.get(i).copied().unwrap_or("?"))
                    .collect::<Vec<_>>()
                    .join("+"),
                rank: rank_of(members),
            })
            .collect();
    }
    if time_invariant && o.rank < NX {
        let (_, modes) = unobservable_modes(&fs[0], &hs[0]);
        o.unobservable_modes = modes.into_iter().map(|(re, im)| [re, im]).collect();
    }
    o
}

fn fmt_num(v: f64) -> String {
    if v == 0.0 {
        return "0".into();
    }
    let a = v.abs();
    if v.fract() == 0.0 && a < 1e15 {
        return format!("{v:.0}");
    }
    if (1e-3..1e7).contains(&a) {
        let s = format!("{v:.6}");
        let s = s.trim_end_matches('0').trim_end_matches('.');
        s.to_string()
    } else {
        format!("{v:.4e}")
    }
}

fn fmt_complex(p: &[f64; 2]) -> String {
    if p[1] == 0.0 {
        fmt_num(p[0])
    } else {
        let sign = if p[1] < 0.0 { '−' } else { '+' };
        format!("{} {sign} {}i", fmt_num(p[0]), fmt_num(p[1].abs()))
    }
}

fn write_matrix(out: &mut String, title: &str, m: &[Vec<f64>], rows: &[&str], cols: &[&str]) {
    if m.is_empty() || m[0].is_empty() {
        let _ = writeln!(out, "    {title}: (empty)");
        return;
    }
    let cells: Vec<Vec<String>> = m
        .iter()
        .map(|r| r.iter().map(|v| fmt_num(*v)).collect())
        .collect();
    let row_w = rows.iter().map(|r| r.chars().count()).max().unwrap_or(0);
    let widths: Vec<usize> = (0..m[0].len())
        .map(|j| {
            cells
                .iter()
                .map(|r| r[j].chars().count())
                .chain(cols.get(j).map(|c| c.chars().count()))
                .max()
                .unwrap_or(1)
        })
        .collect();
    let _ = writeln!(out, "    {title}:");
    let mut head = format!("      {:row_w$}", "");
    for (j, w) in widths.iter().enumerate() {
        let _ = write!(head, "  {:>w$}", cols.get(j).copied().unwrap_or(""));
    }
    let _ = writeln!(out, "{}", head.trim_end());
    for (i, r) in cells.iter().enumerate() {
        let mut line = format!("      {:row_w$}", rows.get(i).copied().unwrap_or(""));
        for (j, w) in widths.iter().enumerate() {
            let _ = write!(line, "  {:>w$}", r[j]);
        }
        let _ = writeln!(out, "{line}");
    }
}

/// Row and column names of the printed matrices.
struct Names<'a> {
    /// The quantities without their units.
    states: Vec<&'a str>,
    meas: Vec<&'a str>,
    inputs: Vec<&'a str>,
}

/// One scenario's analysis: its matrices, observability, steady-state filter and test
/// calibration.
fn render_scenario(s: &mut String, a: &ScenarioAnalysis, n: &Names<'_>) {
    let _ = writeln!(
        s,
        "\nscenario {} (K = {}): {}, {}",
        a.scenario,
        a.steps,
        if a.time_invariant {
            "time-invariant"
        } else {
            "time-varying (matrices at the first transition of the clean trajectory)"
        },
        if a.single_rate {
            "single-rate"
        } else {
            "multi-rate"
        }
    );
    write_matrix(s, "F", &a.transition, &n.states, &n.states);
    if !a.input_matrix.is_empty() && !a.input_matrix[0].is_empty() {
        write_matrix(
            s,
            &format!("G ({})", a.input_matrix_method),
            &a.input_matrix,
            &n.states,
            &n.inputs,
        );
    }
    write_matrix(s, "H", &a.measurement_matrix, &n.meas, &n.states);
    write_matrix(
        s,
        "Q (truth, noise scale 1)",
        &a.process_noise,
        &n.states,
        &n.states,
    );
    write_matrix(
        s,
        "R (truth, noise scale 1)",
        &a.measurement_noise,
        &n.meas,
        &n.meas,
    );
    render_observability(s, &a.observability);
    if let Some(ss) = &a.steady_state {
        let _ = writeln!(
            s,
            "    steady-state Kalman filter (truth Q, R; {} Riccati iterations):",
            ss.riccati_iterations
        );
        write_matrix(s, "  K∞", &ss.gain, &n.states, &n.meas);
        let poles: Vec<String> = ss.poles.iter().map(fmt_complex).collect();
        let _ = writeln!(s, "      poles of (I − K∞H)F: {}", poles.join(", "));
        let _ = writeln!(s, "      spectral radius: {}", fmt_num(ss.spectral_radius));
    }
    render_calibration(s, &a.filters);
    for n in &a.notes {
        let _ = writeln!(s, "    note: {n}");
    }
}

fn render_observability(s: &mut String, o: &Observability) {
    let _ = writeln!(
        s,
        "    observability of x0 from z_1..z_{}: rank {} of {}",
        o.window_steps, o.rank, o.states
    );
    for g in &o.per_component {
        let _ = writeln!(s, "      {} alone: rank {}", g.components, g.rank);
    }
    for g in &o.per_group {
        let _ = writeln!(s, "      sensor group {}: rank {}", g.components, g.rank);
    }
    if !o.unobservable_modes.is_empty() {
        let modes: Vec<String> = o.unobservable_modes.iter().map(fmt_complex).collect();
        let _ = writeln!(s, "      unobservable modes of F: {}", modes.join(", "));
    }
}

/// Each filter variant's test calibration: ρ and the tests' degrees of freedom.
fn render_calibration(s: &mut String, filters: &[FilterAnalysis]) {
    if !filters.is_empty() {
        let _ = writeln!(s, "    test calibration along the clean trajectory:");
    }
    for f in filters {
        let name = if f.q_scale == 1.0 && f.r_scale == 1.0 {
            f.filter.clone()
        } else {
            format!("{} Q×{} R×{}", f.filter, f.q_scale, f.r_scale)
        };
        let rho = f.rho.map_or("— (no error transition)".into(), fmt_num);
        let _ = writeln!(
            s,
            "      {name}: ρ = {rho}, K = {} steps from step {}, NIS dof per run {}",
            f.nees_steps, f.first_step, f.nis_dof_per_run
        );
        for d in &f.dof {
            let _ = writeln!(
                s,
                "        N = {}: NEES effective dof ν = {} (naive N·K·n = {}), NIS dof {}",
                d.runs,
                d.nees_effective_dof.map_or("—".into(), fmt_num),
                fmt_num(d.nees_naive_dof),
                d.nis_dof
            );
        }
    }
}

/// The model kfmc's filters use, as its conventions: what is wrapped, what is a rotation.
fn render_filter_model(s: &mut String, m: &crate::model::exposed::FilterModelRecord) {
    let c = &m.convention;
    let _ = writeln!(
        s,
        "\nfilter-side model ({}; at full precision: [filter_model] of describe.toml, kfmc.model in Python):",
        m.form
    );
    let _ = writeln!(s, "  {}", c.transition);
    let _ = writeln!(s, "  {}", c.measurement);
    let list = |v: &[String]| {
        if v.is_empty() {
            "none".to_string()
        } else {
            v.join(", ")
        }
    };
    let _ = writeln!(s, "  errors wrapped: {}", list(&c.wrapped_errors));
    if !c.rotation_errors.is_empty() {
        let _ = writeln!(
            s,
            "  rotations (error = rotation vector): {}",
            list(&c.rotation_errors)
        );
    }
    if !c.continuous_angles.is_empty() {
        let _ = writeln!(
            s,
            "  continuous angles (truth, z and error not wrapped): {}",
            list(&c.continuous_angles)
        );
    }
    if !c.wrapped_innovations.is_empty() {
        let _ = writeln!(
            s,
            "  innovations kfmc's filters wrap to [−π, π): {}",
            list(&c.wrapped_innovations)
        );
    }
}

impl Description {
    /// The description as TOML (`describe.toml`).
    pub fn to_toml(&self) -> String {
        toml::to_string(self).unwrap_or_else(|e| format!("# could not serialise: {e}\n"))
    }

    /// The description as text for a terminal.
    pub fn render(&self) -> String {
        let mut s = String::new();
        let _ = writeln!(s, "{} (model.kind = \"{}\")", self.experiment, self.kind);
        let _ = writeln!(s, "  Δt = {} s", fmt_num(self.dt_s));
        let _ = writeln!(s, "  states: {}", self.quantities.join(", "));
        let _ = writeln!(s, "  measurements: {}", self.measurements.join(", "));
        if !self.inputs.is_empty() {
            let _ = writeln!(s, "  inputs: {}", self.inputs.join(", "));
        }
        let names = Names {
            states: self
                .quantities
                .iter()
                .map(|q| q.split(' ').next().unwrap_or(q))
                .collect(),
            meas: self.measurements.iter().map(String::as_str).collect(),
            inputs: self.inputs.iter().map(String::as_str).collect(),
        };
        for a in &self.scenarios {
            render_scenario(&mut s, a, &names);
        }
        for sec in &self.sections {
            let _ = writeln!(s, "\n{}:", sec.title);
            let w = sec
                .rows
                .iter()
                .map(|r| r.name.chars().count())
                .max()
                .unwrap_or(0);
            for r in &sec.rows {
                let _ = writeln!(s, "  {:w$}  {}", r.name, r.value);
            }
        }
        if let Some(m) = &self.filter_model {
            render_filter_model(&mut s, m);
        }
        for n in &self.notes {
            let _ = writeln!(s, "\nnote: {n}");
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stacked_rank_ignores_row_scale() {
        // Two independent rows of very different size, and a dependent third.
        let r = vec![
            vec![1e-12, 0.0, 0.0],
            vec![0.0, 1e9, 0.0],
            vec![0.0, 2e9, 0.0],
        ];
        assert_eq!(stacked_rank(&r, 3), 2);
        assert_eq!(stacked_rank(&[], 3), 0);
    }

    #[test]
    fn eigenvalues_of_a_rotation_are_on_the_unit_circle() {
        let (c, s) = (0.6_f64, 0.8_f64);
        let m = Matrix::<2, 2>::new(c, -s, s, c);
        let ev = eigenvalues(&m);
        assert_eq!(ev.len(), 2);
        for e in &ev {
            assert!((e[0] - 0.6).abs() < 1e-14 && (e[1].abs() - 0.8).abs() < 1e-14);
        }
    }

    #[test]
    fn input_matrix_of_an_affine_map_is_exact() {
        let g_true = Matrix::<2, 1>::new(0.5, 0.1);
        let f = |x: &Vector<2>, u: &Vector<1>| x * 2.0 + g_true * u;
        let (g, exact) = input_matrix(f, &Vector::<2>::new(1.0, 2.0), &Vector::<1>::new(3.0));
        assert!(exact);
        assert!((g - g_true).amax() < 1e-15);
        // Quadratic in u: a central difference, close to 2u at u = 3.
        let f = |_: &Vector<2>, u: &Vector<1>| Vector::<2>::new(u[0] * u[0], 0.0);
        let (g, exact) = input_matrix(f, &Vector::<2>::zeros(), &Vector::<1>::new(3.0));
        assert!(!exact);
        assert!((g[(0, 0)] - 6.0).abs() < 1e-6);
    }
}
