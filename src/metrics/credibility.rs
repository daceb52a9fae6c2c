//! Credibility measures beyond the NEES average: Li and Zhao's (2006) noncredibility index
//! (NCI) and inclination indicator, and the ANEES of each block of quantities.
//!
//! Per run i and step k, with e the error and P the filter's covariance,
//! ρ = (eᵀP⁻¹e) / (eᵀΣ̂⁻¹e), where Σ̂_k is the actual mean-square-error matrix at step k,
//! estimated from the cell's runs. Then, over the M_k runs of step k,
//!
//! * NCI_k = (10/M_k) Σ_i |log₁₀ ρ_i| (dB): how far P is from the actual MSE in either
//!   direction;
//! * inclination_k = (10/M_k) Σ_i log₁₀ ρ_i (dB): > 0 optimistic (P too small), < 0
//!   pessimistic.
//!
//! The choices an implementation must make, and this one's:
//!
//! * Σ̂_k = (1/M_k) Σ_i e_i e_iᵀ: the mean-square-error matrix, *not* mean-removed (a bias
//!   is part of what the filter's P should cover) and divided by M_k, not M_k − 1 (it is the
//!   MSE about zero, not a variance about an estimated mean).
//! * Σ̂_k is estimated from the same runs that are scored (each run's own e_i is in it), as
//!   Li and Zhao do. A perfectly credible filter therefore does not score 0: see
//!   [`credible_reference`], reported beside every NCI.
//! * The runs of step k are those whose NEES_k is defined (the run reached step k, its
//!   covariance was positive definite) and whose errors are finite.
//! * A step with M_k < n runs, a Σ̂_k that is not positive definite (Cholesky fails), or a
//!   run whose ρ is 0 or not finite (an error of exactly zero) has no NCI: null, never an
//!   approximation. Step 0 (x̂_0 = x_0 in truth mode) is null this way.
//!
//! Σ̂_k is known only after every run of the cell, so each run's errors and NEES are kept
//! (in memory up to [`CREDIBILITY_BYTES`], in the study folder's scratch file beyond) and read
//! again in run order once the cell is complete. A cell is always folded whole in one process
//! (shards split by cells), so the values are the same for any thread count and any sharding.

use std::collections::HashMap;
use std::path::Path;
use std::sync::Mutex;

use super::StepValues;
use super::blocks::{cholesky_lower, forward_norm_sq};
use crate::error::OutputError;
use crate::spill::Spill;

/// Bytes of per-run errors a cell keeps in memory per filter before spilling to the study
/// folder's scratch file.
pub const CREDIBILITY_BYTES: usize = 16 << 20;

/// Replications behind [`credible_reference`]: at least this many, and at least
/// [`REFERENCE_DRAWS`] error vectors in all.
pub const REFERENCE_REPLICATIONS: usize = 400;

/// Error vectors drawn for one [`credible_reference`] value (at least).
pub const REFERENCE_DRAWS: usize = 400_000;

/// The per-step credibility values of one cell and filter.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct CredibilityStep {
    /// Per block: (Σ block NEES, runs) over the runs with a defined block NEES.
    pub blocks: Vec<(f64, u32)>,
    /// M_k: the runs behind Σ̂_k.
    pub runs: u32,
    /// NCI_k in dB.
    pub nci: Option<f64>,
    /// Inclination_k in dB.
    pub inclination: Option<f64>,
}

impl CredibilityStep {
    /// The block's ANEES at this step and its runs (`None` without runs).
    pub fn block_anees(&self, b: usize) -> Option<(f64, u32)> {
        let (s, n) = self.blocks[b];
        (n > 0).then(|| (s / n as f64, n))
    }
}

/// Folds a cell's runs of one filter into per-step block sums, Σ e eᵀ and the kept errors.
pub struct CredibilityFold {
    nx: usize,
    nb: usize,
    samples: usize,
    block_sum: Vec<f64>,
    block_n: Vec<u32>,
    /// Per step: the lower triangle of Σ_i e_i e_iᵀ over the runs of step k.
    outer: Vec<f64>,
    outer_n: Vec<u32>,
    /// One row per run: (e_k, NEES_k) for k = 0..=K, NaN where not defined.
    rows: Spill,
    row: Vec<f64>,
}

impl CredibilityFold {
    /// A fold for `nx` quantities in `blocks` blocks over `steps + 1` samples; scratch space
    /// goes into `dir`.
    pub fn new(dir: &Path, nx: usize, blocks: usize, steps: usize) -> Self {
        let samples = steps + 1;
        let width = samples * (nx + 1);
        let ntri = nx * (nx + 1) / 2;
        CredibilityFold {
            nx,
            nb: blocks,
            samples,
            block_sum: vec![0.0; samples * blocks],
            block_n: vec![0; samples * blocks],
            outer: vec![0.0; samples * ntri],
            outer_n: vec![0; samples],
            rows: Spill::with_capacity(dir, width, CREDIBILITY_BYTES / (8 * width.max(1))),
            row: vec![f64::NAN; width],
        }
    }

    /// Adds one run (in run order).
    pub fn push(&mut self, v: &StepValues) -> Result<(), OutputError> {
        let (nx, nb) = (self.nx, self.nb);
        let ntri = nx * (nx + 1) / 2;
        self.row.fill(f64::NAN);
        let c = v.completed.min(self.samples);
        for k in 0..c {
            if let Some(b) = v.cred_blocks.get(k * nb..(k + 1) * nb) {
                for (j, &x) in b.iter().enumerate() {
                    if !x.is_nan() {
                        self.block_sum[k * nb + j] += x;
                        self.block_n[k * nb + j] += 1;
                    }
                }
            }
            let nees = v.nees[k];
            let Some(e) = v.cred_err.get(k * nx..(k + 1) * nx) else {
                continue;
            };
            if nees.is_nan() || !e.iter().all(|x| x.is_finite()) {
                continue;
            }
            let o = &mut self.outer[k * ntri..(k + 1) * ntri];
            let mut t = 0;
            for i in 0..nx {
                for j in 0..=i {
                    o[t] += e[i] * e[j];
                    t += 1;
                }
            }
            self.outer_n[k] += 1;
            let r = &mut self.row[k * (nx + 1)..(k + 1) * (nx + 1)];
            r[..nx].copy_from_slice(e);
            r[nx] = nees;
        }
        self.rows.push(&self.row)
    }

    /// The per-step values, once every run of the cell has been pushed: Σ̂_k from the sums,
    /// then a second pass over the kept errors in run order.
    pub fn finish(&mut self) -> Result<Vec<CredibilityStep>, OutputError> {
        let (nx, nb, samples) = (self.nx, self.nb, self.samples);
        let ntri = nx * (nx + 1) / 2;
        // Cholesky factors of Σ̂_k, row-major n × n (lower), where defined.
        let factors: Vec<Option<Vec<f64>>> = (0..samples)
            .map(|k| {
                let m = self.outer_n[k] as usize;
                if m == 0 || m < nx {
                    return None;
                }
                let mut a = vec![0.0; nx * nx];
                let mut t = 0;
                for i in 0..nx {
                    for j in 0..=i {
                        a[i * nx + j] = self.outer[k * ntri + t] / m as f64;
                        t += 1;
                    }
                }
                cholesky_lower(&mut a, nx).map(|()| a)
            })
            .collect();
        let mut abs_sum = vec![0.0; samples];
        let mut sum = vec![0.0; samples];
        let mut bad = vec![false; samples];
        let mut v = vec![0.0; nx];
        self.rows.for_each_row(|row| {
            for k in 0..samples {
                let Some(l) = &factors[k] else { continue };
                let r = &row[k * (nx + 1)..(k + 1) * (nx + 1)];
                let nees = r[nx];
                if nees.is_nan() {
                    continue;
                }
                v.copy_from_slice(&r[..nx]);
                let rho = nees / forward_norm_sq(l, nx, &mut v);
                let lg = rho.log10();
                if lg.is_finite() {
                    abs_sum[k] += lg.abs();
                    sum[k] += lg;
                } else {
                    bad[k] = true;
                }
            }
            Ok(())
        })?;
        Ok((0..samples)
            .map(|k| {
                let m = self.outer_n[k];
                let ok = factors[k].is_some() && !bad[k];
                CredibilityStep {
                    blocks: (0..nb)
                        .map(|b| (self.block_sum[k * nb + b], self.block_n[k * nb + b]))
                        .collect(),
                    runs: m,
                    nci: ok.then(|| 10.0 * abs_sum[k] / m as f64),
                    inclination: ok.then(|| 10.0 * sum[k] / m as f64),
                }
            })
            .collect())
    }
}

/// NCI and inclination (dB) of one step from its runs' errors and covariances, computed
/// directly from the definition (Σ̂ = (1/M) Σ e eᵀ, ρ_i = e_iᵀP_i⁻¹e_i / e_iᵀΣ̂⁻¹e_i):
/// the reference the fold is tested against, and the kernel of [`credible_reference`].
/// `errors` holds M rows of n values; `nees` the M values e_iᵀP_i⁻¹e_i.
pub fn nci_of(errors: &[f64], nees: &[f64], n: usize) -> Option<(f64, f64)> {
    let m = nees.len();
    if m == 0 || m < n || errors.len() != m * n {
        return None;
    }
    let mut a = vec![0.0; n * n];
    for e in errors.chunks_exact(n) {
        for i in 0..n {
            for j in 0..=i {
                a[i * n + j] += e[i] * e[j];
            }
        }
    }
    a.iter_mut().for_each(|x| *x /= m as f64);
    cholesky_lower(&mut a, n)?;
    let (mut abs, mut sum) = (0.0, 0.0);
    let mut v = vec![0.0; n];
    for (e, &q) in errors.chunks_exact(n).zip(nees) {
        v.copy_from_slice(e);
        let lg = (q / forward_norm_sq(&a, n, &mut v)).log10();
        if !lg.is_finite() {
            return None;
        }
        abs += lg.abs();
        sum += lg;
    }
    Some((10.0 * abs / m as f64, 10.0 * sum / m as f64))
}

/// The references computed so far, by (M, n).
type ReferenceCache = HashMap<(usize, usize), Option<(f64, f64)>>;

/// What a perfectly credible filter scores at one step with M runs of n quantities: the mean
/// NCI and the mean inclination (dB) when every run's error is drawn from N(0, P) with P the
/// true covariance — both then depend on M and n alone (ρ is unchanged by e → Ae, P → APAᵀ,
/// so P = I loses nothing). A Monte Carlo at a fixed seed, computed once per (M, n) and
/// kept: max([`REFERENCE_REPLICATIONS`], ⌈[`REFERENCE_DRAWS`]/M⌉) replications of M draws;
/// `None` when M < n (Σ̂ singular). Its Monte Carlo standard error, [`simulate_spread`]'s
/// standard deviation over √replications, grows with M and falls with n: at M = 1,000 it is
/// 2.3 % of the NCI for n = 2 and 0.6 % for n = 9, and under 0.01 dB of the inclination
/// (the book's credibility chapter tabulates it).
pub fn credible_reference(m: usize, n: usize) -> Option<(f64, f64)> {
    static CACHE: Mutex<Option<ReferenceCache>> = Mutex::new(None);
    if let Some(v) = CACHE
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
        .get_or_insert_with(HashMap::new)
        .get(&(m, n))
    {
        return *v;
    }
    let v = simulate_reference(m, n, reference_replications(m), 0x6b66_6d63_6e63_6931);
    CACHE
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
        .get_or_insert_with(HashMap::new)
        .insert((m, n), v);
    v
}

/// Replications behind the reference at M runs.
pub fn reference_replications(m: usize) -> usize {
    REFERENCE_REPLICATIONS.max(REFERENCE_DRAWS.div_ceil(m.max(1)))
}

/// The credible filter's mean NCI and inclination over `replications` replications of `m`
/// draws of e ~ N(0, I_n), P = I, from `seed` (a function of its arguments alone).
pub fn simulate_reference(
    m: usize,
    n: usize,
    replications: usize,
    seed: u64,
) -> Option<(f64, f64)> {
    let (mut nci, mut incl, mut used) = (0.0, 0.0, 0usize);
    replicate_credible(m, n, replications, seed, |a, b| {
        nci += a;
        incl += b;
        used += 1;
    });
    (used > 0).then(|| (nci / used as f64, incl / used as f64))
}

/// Calls `each(nci, inclination)` for every replication of `m` draws of e ~ N(0, I_n),
/// P = I, from `seed`, in order (a replication whose Σ̂ is singular is skipped).
fn replicate_credible(
    m: usize,
    n: usize,
    replications: usize,
    seed: u64,
    mut each: impl FnMut(f64, f64),
) {
    use rand::SeedableRng;
    use rand_distr::{Distribution, StandardNormal};
    if m == 0 || n == 0 || m < n || replications == 0 {
        return;
    }
    let mut rng = rand_pcg::Pcg64::seed_from_u64(seed ^ ((m as u64) << 20) ^ n as u64);
    let mut errors = vec![0.0; m * n];
    let mut nees = vec![0.0; m];
    for _ in 0..replications {
        for (e, q) in errors.chunks_exact_mut(n).zip(&mut nees) {
            for x in e.iter_mut() {
                *x = StandardNormal.sample(&mut rng);
            }
            *q = e.iter().map(|x| x * x).sum();
        }
        if let Some((a, b)) = nci_of(&errors, &nees, n) {
            each(a, b);
        }
    }
}

/// How one step's NCI and inclination of a perfectly credible filter spread over
/// independent steps (or studies): mean and standard deviation (dB) over the replications
/// of [`simulate_spread`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CredibleSpread {
    /// Replications with a defined value.
    pub replications: usize,
    /// Mean NCI.
    pub nci_mean: f64,
    /// Standard deviation of one step's NCI.
    pub nci_sd: f64,
    /// Mean inclination.
    pub inclination_mean: f64,
    /// Standard deviation of one step's inclination.
    pub inclination_sd: f64,
}

/// The spread of one step's NCI and inclination at M = `m` runs of `n` quantities when P is
/// exactly the error covariance: `replications` replications of `m` draws of e ~ N(0, I_n)
/// from `seed`, the same draws as [`simulate_reference`] makes. `None` when M < n or fewer
/// than two replications are defined.
pub fn simulate_spread(
    m: usize,
    n: usize,
    replications: usize,
    seed: u64,
) -> Option<CredibleSpread> {
    let mut values = Vec::with_capacity(replications);
    replicate_credible(m, n, replications, seed, |a, b| values.push((a, b)));
    let nci: Vec<f64> = values.iter().map(|v| v.0).collect();
    let incl: Vec<f64> = values.iter().map(|v| v.1).collect();
    let (nci_mean, nci_sd) = super::mean_std(&nci);
    let (inclination_mean, inclination_sd) = super::mean_std(&incl);
    Some(CredibleSpread {
        replications: values.len(),
        nci_mean: nci_mean?,
        nci_sd: nci_sd?,
        inclination_mean: inclination_mean?,
        inclination_sd: inclination_sd?,
    })
}

/// 10/ln 10: dB per natural-log unit.
const DB: f64 = 10.0 / std::f64::consts::LN_10;

/// The large-M limit of the standard deviation of one step's NCI of a credible filter, in
/// dB, at M runs of n quantities.
///
/// With Σ̂ = I + Δ, √M·Δ tends to a symmetric Gaussian matrix W (Var W_ii = 2, Var W_ij = 1),
/// and 10 log₁₀ ρ_i ≈ (10/ln 10)·u_iᵀΔu_i with u_i = e_i/|e_i| uniform on the sphere. Over
/// M runs the directions average out, so √M·NCI tends to (10/ln 10)·g(W) with
/// g(W) = E_u|uᵀWu|. For unit u and v, uᵀWu and vᵀWv are normal with variance 2 and
/// correlation c² = (u·v)², whence E g = 2/√π (the reference ≈ 4.9/√M dB) and
///
/// ```text
/// Var g = (4/π)·(E h(T) − 1),  h(t) = √(1 − t²) + t·arcsin t,  T = c² ~ Beta(1/2, (n − 1)/2)
/// ```
///
/// (E h(T) by quadrature). It shrinks like 1/n for large n (Var g ≈ 6/(π n (n + 2))): a
/// step's NCI is much noisier in two dimensions than in nine. The finite-M value is
/// [`simulate_spread`]'s.
pub fn asymptotic_nci_sd(m: usize, n: usize) -> f64 {
    // E h(T) with c = sin φ: the density of c ∝ (1 − c²)^((n−3)/2) becomes cos^(n−2) φ on
    // [0, π/2] (by symmetry), smooth for every n ≥ 2. Simpson's rule.
    if n == 1 {
        // c = ±1: E h(1) = π/2.
        return DB * (2.0 - 4.0 / std::f64::consts::PI).sqrt() / (m as f64).sqrt();
    }
    let steps = 4000;
    let dphi = std::f64::consts::FRAC_PI_2 / steps as f64;
    let (mut num, mut den) = (0.0, 0.0);
    for i in 0..=steps {
        let phi = i as f64 * dphi;
        let w = if i == 0 || i == steps {
            1.0
        } else if i % 2 == 1 {
            4.0
        } else {
            2.0
        };
        let t = phi.sin().powi(2);
        let h = (1.0 - t * t).max(0.0).sqrt() + t * t.asin();
        let density = phi.cos().powi(n as i32 - 2);
        num += w * h * density;
        den += w * density;
    }
    let var_g = 4.0 / std::f64::consts::PI * (num / den - 1.0);
    DB * var_g.sqrt() / (m as f64).sqrt()
}

/// The large-M limit of the standard deviation of one step's inclination of a credible
/// filter, in dB: its runs' directions average uᵀΔu to tr(Δ)/n, whose standard deviation is
/// √(2/(n M)), so (10/ln 10)·√(2/(n M)).
pub fn asymptotic_inclination_sd(m: usize, n: usize) -> f64 {
    DB * (2.0 / (n as f64 * m as f64)).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nci_by_hand_for_three_runs_in_two_dimensions() {
        // Errors (1, 0), (0, 2), (1, 1); P = I for every run, so NEES = |e|².
        // Σ̂ = (1/3)[[2, 1], [1, 5]], Σ̂⁻¹ = (3/9)[[5, −1], [−1, 2]] = [[5/3, −1/3], [−1/3, 2/3]].
        // eᵀΣ̂⁻¹e: 5/3; 8/3; 5/3 − 2/3 + 2/3 = 5/3. NEES: 1; 4; 2.
        // ρ: 3/5; 3/2; 6/5. NCI = (10/3)(|lg .6| + lg 1.5 + lg 1.2),
        // inclination = (10/3) lg(.6 · 1.5 · 1.2) = (10/3) lg 1.08.
        let e = [1.0, 0.0, 0.0, 2.0, 1.0, 1.0];
        let q = [1.0, 4.0, 2.0];
        let (nci, incl) = nci_of(&e, &q, 2).unwrap();
        let l = |x: f64| x.log10();
        let want_nci = 10.0 / 3.0 * (l(0.6).abs() + l(1.5) + l(1.2));
        assert!((nci - want_nci).abs() < 1e-12, "{nci} vs {want_nci}");
        assert!((incl - 10.0 / 3.0 * l(1.08)).abs() < 1e-12, "{incl}");
        // Fewer runs than dimensions: Σ̂ singular, no value.
        assert_eq!(nci_of(&e[..2], &q[..1], 2), None);
    }

    #[test]
    fn the_fold_equals_the_definition_step_by_step() {
        // Runs folded through StepValues (one stopping early, one with an undefined NEES)
        // against nci_of on the runs each step keeps.
        use rand::{RngExt, SeedableRng};
        let mut rng = rand_pcg::Pcg64::seed_from_u64(5);
        let (nx, steps, runs) = (2usize, 6usize, 9usize);
        let dir = std::env::temp_dir();
        // A capacity of 2 rows: the kept errors go through the scratch file.
        let mut fold = CredibilityFold::new(&dir, nx, 1, steps);
        fold.rows = Spill::with_capacity(&dir, (steps + 1) * (nx + 1), 2);
        let mut raw: Vec<Vec<(Vec<f64>, f64)>> = Vec::new();
        for r in 0..runs {
            let completed = if r == 3 { 4 } else { steps + 1 };
            let mut v = StepValues::new(nx, steps);
            v.enable_credibility(1);
            let mut mine = Vec::new();
            for k in 0..completed {
                let e = [rng.random::<f64>() - 0.5, rng.random::<f64>() * 2.0 - 1.0];
                let nees = if r == 5 && k == 2 {
                    f64::NAN
                } else {
                    rng.random::<f64>() * 3.0 + 0.1
                };
                v.record_credibility(k, &e, &[nees * 0.5]);
                v.record::<2>(&e, nees, f64::NAN, 0);
                mine.push((e.to_vec(), nees));
            }
            fold.push(&v).unwrap();
            raw.push(mine);
        }
        let got = fold.finish().unwrap();
        for (k, g) in got.iter().enumerate() {
            let kept: Vec<&(Vec<f64>, f64)> = raw
                .iter()
                .filter_map(|r| r.get(k))
                .filter(|(_, q)| !q.is_nan())
                .collect();
            let e: Vec<f64> = kept.iter().flat_map(|(e, _)| e.clone()).collect();
            let q: Vec<f64> = kept.iter().map(|(_, q)| *q).collect();
            assert_eq!(g.runs as usize, q.len(), "step {k}");
            let want = nci_of(&e, &q, nx).unwrap();
            assert!((g.nci.unwrap() - want.0).abs() < 1e-12, "step {k}");
            assert!((g.inclination.unwrap() - want.1).abs() < 1e-12, "step {k}");
            let (anees, n) = g.block_anees(0).unwrap();
            assert_eq!(n as usize, q.len());
            let mean = q.iter().sum::<f64>() * 0.5 / q.len() as f64;
            assert!((anees - mean).abs() < 1e-12);
        }
    }

    #[test]
    fn the_reference_matches_an_independent_monte_carlo() {
        // The cached reference against a Monte Carlo of the same definition at another seed
        // with as many replications: both estimate the same mean, and 20 replications of M =
        // 10 runs in n = 3 give per-replication NCI values whose spread bounds the gap. The
        // tolerance is 4 standard errors of the difference of two independent means.
        let (m, n) = (10usize, 3usize);
        let reps = reference_replications(m);
        let (a_nci, a_incl) = credible_reference(m, n).unwrap();
        let (b_nci, b_incl) = simulate_reference(m, n, reps, 12345).unwrap();
        // Per-replication standard deviation, from a smaller run.
        let sd = |f: fn((f64, f64)) -> f64| {
            let v: Vec<f64> = (0..200)
                .map(|s| f(simulate_reference(m, n, 1, 777 + s).unwrap()))
                .collect();
            crate::metrics::mean_std(&v).1.unwrap()
        };
        let tol_nci = 4.0 * sd(|x| x.0) * (2.0 / reps as f64).sqrt();
        let tol_incl = 4.0 * sd(|x| x.1) * (2.0 / reps as f64).sqrt();
        assert!(
            (a_nci - b_nci).abs() < tol_nci,
            "{a_nci} vs {b_nci} ± {tol_nci}"
        );
        assert!(
            (a_incl - b_incl).abs() < tol_incl,
            "{a_incl} vs {b_incl} ± {tol_incl}"
        );
        // Same-run estimation: a credible filter does not score 0.
        assert!(a_nci > 0.1 && a_incl != 0.0, "{a_nci} {a_incl}");
        // Deterministic: the same value every time.
        assert_eq!(credible_reference(m, n), Some((a_nci, a_incl)));
        assert_eq!(credible_reference(2, 3), None);
    }
}
