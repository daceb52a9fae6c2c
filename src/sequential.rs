//! Group-sequential boundaries: a test looked at after each of several looks (here, batches of
//! Monte Carlo runs) with an overall false-alarm rate α, by Lan and DeMets' α-spending.
//!
//! The test statistic at look k is a Z statistic built from the runs so far,
//! Z_k = S_k / √I_k, where S_k is a sum of independent per-run contributions and I_k (the
//! *information*) is proportional to the number of runs. Under the null hypothesis and with a
//! drift θ under an alternative, Z_k ~ N(θ√I_k, 1) and Cov(Z_j, Z_k) = √(I_j/I_k): the
//! canonical joint distribution (Jennison & Turnbull, *Group Sequential Methods*, ch. 3). Only
//! the information *fractions* t_k = I_k/I_max matter for the boundaries.
//!
//! A spending function f(t) says how much of α may have been spent by fraction t (f(0) = 0,
//! f(1) = α). The boundary c_k at look k is the value with
//! P₀(no crossing before k, crossing at k) = f(t_k) − f(t_{k−1}), so that uneven or unplanned
//! looks keep the overall level. The probabilities are computed by the recursive numerical
//! integration of Armitage, McPherson and Rowe on a Simpson grid, the method gsDesign, rpact
//! and ldbounds use; the tests compare with rpact's published values.
//!
//! Two-sided tests are symmetric, each side spending α/2 with the one-sided function (as
//! gsDesign's symmetric designs do): the continuation region is |Z_k| < c_k.
//!
//! Futility (optional, non-binding): β-spending bounds b_k below which a look stops and
//! accepts the null. They need a drift, and the drift is the one at which the design has power
//! 1 − β at the last look with the futility bounds in place; the efficacy bounds are computed
//! ignoring futility (non-binding), so stopping for futility never raises the false-alarm rate.

use statrs::distribution::{ContinuousCDF, Normal};

/// Errors of a design that has no boundaries.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SequentialError {
    /// The looks' information fractions must increase strictly within (0, 1].
    #[error("look fractions must increase strictly within (0, 1]; got {0:?}")]
    Fractions(Vec<f64>),
    /// α (or β) outside (0, 1).
    #[error("{name} must lie in (0, 1); got {value}")]
    Level {
        /// "alpha" or "beta".
        name: &'static str,
        /// The value given.
        value: f64,
    },
    /// A user spending sequence that does not increase or overspends.
    #[error(
        "cumulative spending must be non-decreasing, start above 0 and end at most at the level; got {0:?}"
    )]
    Spending(Vec<f64>),
    /// The drift at which the design has the requested power could not be bracketed.
    #[error("no drift gives power 1 − β = {0} at the last look")]
    Drift(f64),
}

/// The shape of α (or β) spending over the information fraction t ∈ [0, 1].
#[derive(Debug, Clone, PartialEq)]
pub enum Spending {
    /// Lan–DeMets' O'Brien–Fleming type, f(t) = 2 − 2Φ(Φ⁻¹(1 − a/2)/√t): spends almost nothing
    /// early, so early looks stop only on overwhelming evidence.
    OBrienFleming,
    /// Lan–DeMets' Pocock type, f(t) = a·ln(1 + (e − 1)t): nearly constant boundaries.
    Pocock,
    /// Kim–DeMets power family, f(t) = a·t^ρ (ρ = 1 spends uniformly).
    Power(f64),
    /// Cumulative spending given look by look (as fractions of the level: the last is 1 when
    /// the last look is the planned end).
    User(Vec<f64>),
}

fn normal() -> Normal {
    Normal::new(0.0, 1.0).expect("the standard normal is valid")
}

impl Spending {
    /// Cumulative one-sided spending at fraction `t` (look `look`, for `User`) of level `a`.
    pub fn spent(&self, a: f64, t: f64, look: usize) -> f64 {
        let n = normal();
        match self {
            Spending::OBrienFleming => {
                if t <= 0.0 {
                    0.0
                } else {
                    2.0 * n.sf(n.inverse_cdf(1.0 - a / 2.0) / t.sqrt())
                }
            }
            Spending::Pocock => a * (1.0 + (std::f64::consts::E - 1.0) * t).ln(),
            Spending::Power(rho) => a * t.powf(*rho),
            Spending::User(fractions) => a * fractions[look],
        }
    }
}

/// One or two sides of the efficacy test.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Sides {
    /// Reject when Z_k ≥ c_k.
    One,
    /// Reject when |Z_k| ≥ c_k; each side spends half of α.
    Two,
}

/// A group-sequential design: its looks and boundaries on the Z scale.
#[derive(Debug, Clone, PartialEq)]
pub struct Boundaries {
    /// Information fractions of the looks, increasing, the last ≤ 1.
    pub fractions: Vec<f64>,
    /// Efficacy boundary c_k (reject when Z_k ≥ c_k, or |Z_k| ≥ c_k two-sided).
    pub efficacy: Vec<f64>,
    /// Cumulative α spent by each look (both sides together for a two-sided test).
    pub alpha_spent: Vec<f64>,
    /// Futility boundary b_k (stop, accepting the null, when Z_k < b_k; |Z_k| < b_k
    /// two-sided), when the design has one; the last equals the last efficacy boundary.
    pub futility: Option<Vec<f64>>,
    /// The drift θ (Z_k ~ N(θ√t_k, 1)) at which the design has power 1 − β, with futility.
    pub drift: Option<f64>,
}

/// The Simpson step is at most this on the Z scale, and at most a tenth of the transition
/// kernel's standard deviation √(Δt/t) to the next look (looks 1 % of a study apart still get
/// ten points per standard deviation), which keeps the quadrature error below 1e-9.
const MAX_STEP: f64 = 0.02;
/// The density of Z below θ√t − 9 (or above θ√t + 9) is below 1e-18: truncated there.
const TAIL: f64 = 9.0;

/// The sub-density of Z at a look on the region where the test continued, on a Simpson grid
/// over each interval of the region, weighted so that an integral is a dot product.
struct Density {
    z: Vec<f64>,
    weighted: Vec<f64>,
}

/// Simpson nodes and weights over [lo, hi] with step at most `step` (an even number of
/// intervals).
fn simpson(lo: f64, hi: f64, step: f64) -> impl Iterator<Item = (f64, f64)> {
    let intervals = (((hi - lo) / step).ceil() as usize).max(2);
    let intervals = intervals + intervals % 2;
    let h = (hi - lo) / intervals as f64;
    (0..=intervals).map(move |i| {
        let m = if i == 0 || i == intervals {
            1.0
        } else if i % 2 == 1 {
            4.0
        } else {
            2.0
        };
        (lo + h * i as f64, m * h / 3.0)
    })
}

/// The recursion's state between looks.
struct Recursion {
    theta: f64,
    /// Fraction of the last look (0 before the first).
    t: f64,
    density: Option<Density>,
}

impl Recursion {
    fn new(theta: f64) -> Recursion {
        Recursion {
            theta,
            t: 0.0,
            density: None,
        }
    }

    /// P(continued so far and Z at fraction `t` ≥ `c`) — or ≤ `c` with `lower`.
    fn tail(&self, t: f64, c: f64, lower: bool) -> f64 {
        let n = normal();
        match &self.density {
            None => {
                let x = c - self.theta * t.sqrt();
                if lower { n.cdf(x) } else { n.sf(x) }
            }
            Some(d) => {
                let dt = t - self.t;
                let (st, sp, sd) = (t.sqrt(), self.t.sqrt(), dt.sqrt());
                d.z.iter()
                    .zip(&d.weighted)
                    .map(|(&u, &w)| {
                        let x = (c * st - u * sp - self.theta * dt) / sd;
                        w * if lower { n.cdf(x) } else { n.sf(x) }
                    })
                    .sum()
            }
        }
    }

    /// Moves to the look at fraction `t`, continuing on the union of `region`'s intervals;
    /// `next` is the fraction of the following look (none after the last).
    fn advance(&mut self, t: f64, region: &[(f64, f64)], next: Option<f64>) {
        let Some(next) = next else {
            self.t = t;
            self.density = None;
            return;
        };
        let step = MAX_STEP.min(((next - t) / t).sqrt() / 10.0);
        let mean = self.theta * t.sqrt();
        let nodes: Vec<(f64, f64)> = region
            .iter()
            .map(|&(lo, hi)| (lo.max(mean - TAIL), hi.min(mean + TAIL)))
            .filter(|(lo, hi)| lo < hi)
            .flat_map(|(lo, hi)| simpson(lo, hi, step))
            .collect();
        let weighted = match &self.density {
            None => nodes.iter().map(|&(x, w)| w * phi(x - mean)).collect(),
            Some(d) => {
                let dt = t - self.t;
                let (st, sp, sd) = (t.sqrt(), self.t.sqrt(), dt.sqrt());
                // Density of Z_k at x: ∫ g(u) (√t/√Δt) φ((x√t − u√t' − θΔt)/√Δt) du.
                nodes
                    .iter()
                    .map(|&(x, w)| {
                        let g: f64 =
                            d.z.iter()
                                .zip(&d.weighted)
                                .map(|(&u, &wu)| wu * phi((x * st - u * sp - self.theta * dt) / sd))
                                .sum();
                        w * g * st / sd
                    })
                    .collect()
            }
        };
        self.density = Some(Density {
            z: nodes.iter().map(|&(x, _)| x).collect(),
            weighted,
        });
        self.t = t;
    }
}

/// The continuation region at a look: below the efficacy bound `c` (above −c two-sided) and,
/// with a futility bound `b`, at or above it (|Z| ≥ b two-sided).
fn region(c: f64, b: Option<f64>, sides: Sides) -> Vec<(f64, f64)> {
    match (sides, b) {
        (Sides::One, None) => vec![(f64::NEG_INFINITY, c)],
        (Sides::One, Some(b)) => vec![(b, c)],
        (Sides::Two, Some(b)) if b > 0.0 => vec![(-c, -b), (b, c)],
        (Sides::Two, _) => vec![(-c, c)],
    }
}

fn phi(x: f64) -> f64 {
    (-0.5 * x * x).exp() / (2.0 * std::f64::consts::PI).sqrt()
}

/// The c with `f(c)` = `target` for `f` decreasing in c, by bisection to 1e-12 (each
/// evaluation is one O(grid) integral, so 60 of them cost nothing).
fn solve_decreasing(target: f64, f: impl Fn(f64) -> f64) -> f64 {
    let (mut lo, mut hi) = (-TAIL - 10.0, TAIL + 10.0);
    for _ in 0..200 {
        let mid = 0.5 * (lo + hi);
        if f(mid) > target {
            lo = mid;
        } else {
            hi = mid;
        }
        if hi - lo < 1e-12 {
            break;
        }
    }
    0.5 * (lo + hi)
}

fn check_fractions(fractions: &[f64]) -> Result<(), SequentialError> {
    let ok = !fractions.is_empty()
        && fractions
            .iter()
            .all(|t| t.is_finite() && *t > 0.0 && *t <= 1.0)
        && fractions.windows(2).all(|w| w[0] < w[1]);
    if ok {
        Ok(())
    } else {
        Err(SequentialError::Fractions(fractions.to_vec()))
    }
}

fn check_level(name: &'static str, value: f64) -> Result<(), SequentialError> {
    if value > 0.0 && value < 1.0 {
        Ok(())
    } else {
        Err(SequentialError::Level { name, value })
    }
}

/// Cumulative spending of a whole test (both sides together) at each look.
fn cumulative(
    spending: &Spending,
    level: f64,
    sides: Sides,
    fractions: &[f64],
) -> Result<Vec<f64>, SequentialError> {
    let per_side = match sides {
        Sides::One => level,
        Sides::Two => level / 2.0,
    };
    let factor = match sides {
        Sides::One => 1.0,
        Sides::Two => 2.0,
    };
    if let Spending::User(f) = spending {
        let ok = f.len() == fractions.len()
            && f.first().is_some_and(|&x| x > 0.0)
            && f.windows(2).all(|w| w[0] <= w[1])
            && f.last().is_some_and(|&x| x <= 1.0 + 1e-12);
        if !ok {
            return Err(SequentialError::Spending(f.clone()));
        }
    }
    Ok(fractions
        .iter()
        .enumerate()
        .map(|(k, &t)| factor * spending.spent(per_side, t, k))
        .collect())
}

/// Efficacy boundaries for a test of level `alpha` looked at at `fractions`.
pub fn efficacy(
    fractions: &[f64],
    alpha: f64,
    spending: &Spending,
    sides: Sides,
) -> Result<Boundaries, SequentialError> {
    check_fractions(fractions)?;
    check_level("alpha", alpha)?;
    let spent = cumulative(spending, alpha, sides, fractions)?;
    let bounds = efficacy_from_spent(fractions, &spent, sides);
    Ok(Boundaries {
        fractions: fractions.to_vec(),
        efficacy: bounds,
        alpha_spent: spent,
        futility: None,
        drift: None,
    })
}

/// The boundaries that spend exactly `spent` (cumulative, both sides) under the null.
fn efficacy_from_spent(fractions: &[f64], spent: &[f64], sides: Sides) -> Vec<f64> {
    let mut rec = Recursion::new(0.0);
    let mut bounds = Vec::with_capacity(fractions.len());
    let mut before = 0.0;
    for (k, (&t, &cum)) in fractions.iter().zip(spent).enumerate() {
        let increment = (cum - before).max(0.0);
        before = cum;
        let c = if increment <= 0.0 {
            // Nothing to spend at this look: it cannot reject.
            f64::INFINITY
        } else {
            // Two-sided, the two tails are equal under the null: each takes half.
            let per_tail = match sides {
                Sides::One => increment,
                Sides::Two => increment / 2.0,
            };
            solve_decreasing(per_tail, |c| rec.tail(t, c, false))
        };
        rec.advance(t, &region(c, None, sides), fractions.get(k + 1).copied());
        bounds.push(c);
    }
    bounds
}

/// P(continued so far, and |Z| < b two-sided or Z < b one-sided) at fraction `t`.
fn below(rec: &Recursion, t: f64, b: f64, sides: Sides) -> f64 {
    match sides {
        Sides::One => rec.tail(t, b, true),
        Sides::Two if b > 0.0 => rec.tail(t, b, true) - rec.tail(t, -b, true),
        Sides::Two => 0.0,
    }
}

/// Futility bounds by β-spending at drift `theta`, with the efficacy bounds fixed
/// (non-binding); returns the bounds and how far the last one found lies below the last
/// efficacy bound (zero at the drift of the design, where the last futility bound meets it).
fn futility_at(
    fractions: &[f64],
    efficacy: &[f64],
    beta_spent: &[f64],
    sides: Sides,
    theta: f64,
) -> (Vec<f64>, f64) {
    let mut rec = Recursion::new(theta);
    let mut bounds = Vec::with_capacity(fractions.len());
    let mut before = 0.0;
    let mut gap = 0.0;
    for (k, (&t, &cum)) in fractions.iter().zip(beta_spent).enumerate() {
        let increment = (cum - before).max(0.0);
        before = cum;
        let c = efficacy[k];
        let found = solve_increasing(increment, |b| below(&rec, t, b, sides));
        let next = fractions.get(k + 1).copied();
        let b = if next.is_none() {
            gap = c - found;
            c
        } else {
            found.min(c)
        };
        rec.advance(t, &region(c, Some(b), sides), next);
        bounds.push(b);
    }
    (bounds, gap)
}

/// The b with `f(b)` = `target` for `f` increasing in b.
fn solve_increasing(target: f64, f: impl Fn(f64) -> f64) -> f64 {
    solve_decreasing(-target, |b| -f(b))
}

/// Efficacy boundaries as [`efficacy`], with non-binding futility bounds spending `beta` by
/// `beta_spending` at the drift for which the design's power is 1 − β.
pub fn with_futility(
    fractions: &[f64],
    alpha: f64,
    spending: &Spending,
    sides: Sides,
    beta: f64,
    beta_spending: &Spending,
) -> Result<Boundaries, SequentialError> {
    let mut design = efficacy(fractions, alpha, spending, sides)?;
    check_level("beta", beta)?;
    let beta_spent = cumulative(beta_spending, beta, Sides::One, fractions)?;
    // The gap at the last look decreases with the drift: bracket and bisect.
    let gap = |theta: f64| futility_at(fractions, &design.efficacy, &beta_spent, sides, theta).1;
    let (mut lo, mut hi) = (0.0, 1.0);
    while gap(hi) > 0.0 {
        hi *= 2.0;
        if hi > 64.0 {
            return Err(SequentialError::Drift(1.0 - beta));
        }
    }
    if gap(lo) < 0.0 {
        return Err(SequentialError::Drift(1.0 - beta));
    }
    for _ in 0..50 {
        let mid = 0.5 * (lo + hi);
        if gap(mid) > 0.0 {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    let theta = 0.5 * (lo + hi);
    design.futility = Some(futility_at(fractions, &design.efficacy, &beta_spent, sides, theta).0);
    design.drift = Some(theta);
    Ok(design)
}

/// A look's decision.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Decision {
    /// The statistic crossed the efficacy boundary: the null is rejected, stop.
    Reject,
    /// The statistic fell below the futility boundary: stop, the null stands.
    Accept,
    /// Neither: take the next look (at the last look, the null stands).
    Continue,
}

impl Boundaries {
    /// The decision at look `k` (0-based) for statistic `z`.
    pub fn decide(&self, k: usize, z: f64, sides: Sides) -> Decision {
        let c = self.efficacy[k];
        let x = match sides {
            Sides::One => z,
            Sides::Two => z.abs(),
        };
        if x >= c {
            return Decision::Reject;
        }
        if let Some(b) = &self.futility
            && x < b[k]
        {
            return Decision::Accept;
        }
        if k + 1 == self.efficacy.len() {
            Decision::Accept
        } else {
            Decision::Continue
        }
    }

    /// The probability of rejecting at each look at drift `theta` (with the futility bounds
    /// in place when the design has them): the power curve of the design, look by look.
    pub fn rejection_probabilities(&self, theta: f64, sides: Sides) -> Vec<f64> {
        let mut rec = Recursion::new(theta);
        let mut out = Vec::with_capacity(self.fractions.len());
        for (k, (&t, &c)) in self.fractions.iter().zip(&self.efficacy).enumerate() {
            let mut p = rec.tail(t, c, false);
            if sides == Sides::Two {
                p += rec.tail(t, -c, true);
            }
            out.push(p);
            let b = self.futility.as_ref().map(|b| b[k]);
            rec.advance(t, &region(c, b, sides), self.fractions.get(k + 1).copied());
        }
        out
    }
}

/// A sequential consistency gate: the fixed-N verdict's two tests (the calibrated NEES test
/// and the NIS test, each two-sided at α/2 by Bonferroni), each now a symmetric two-sided
/// group-sequential test at α/2 looked at after the first `looks[k]` runs of a cell.
///
/// A look reads the verdict's Bonferroni p-value p = min(1, 2·min(p_NEES, p_NIS)) at that
/// look's runs: it rejects ("inconsistent", stop) when min(p_NEES, p_NIS) is at most the
/// design's nominal two-sided level 2(1 − Φ(c_k)) — |Z| ≥ c_k for one of the tests — and, with
/// futility, accepts ("consistent", stop) when both p-values exceed 2(1 − Φ(b_k)). The last
/// look decides either way. A capped p = 1 (both p-values ≥ 0.5) accepts only when that
/// bound is below 0.5: when it cannot tell, the gate takes the next look, which can only make
/// it more conservative.
#[derive(Debug, Clone, PartialEq)]
pub struct Gate {
    /// Run counts of the looks, increasing; the last is the study's runs per cell.
    pub looks: Vec<usize>,
    /// The two-sided design at α/2 on the looks' fractions `looks[k] / looks.last()`.
    pub design: Boundaries,
}

/// Where a gate looks at a study of N runs per cell.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Looks {
    /// This many even looks ([`default_looks`]).
    Count(usize),
    /// The run counts of the looks, increasing and ending at N.
    RunCounts(Vec<usize>),
}

/// A gate's settings that cannot make a gate, naming the setting.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum GateError {
    /// The looks are not a count ≥ 1 or increasing run counts ≥ 2 ending at the study's runs.
    #[error("{0}")]
    Looks(String),
    /// The futility β is outside (0, 1).
    #[error("β must lie in (0, 1); got {0}")]
    Futility(f64),
    /// The futility β-spending exponent ρ is not positive.
    #[error("the β-spending exponent ρ must be positive; got {0}")]
    FutilityRho(f64),
    /// The design has no boundaries.
    #[error(transparent)]
    Design(#[from] SequentialError),
}

/// Most looks a gate may take, as a count or as a list of run counts (`check.looks`,
/// `--looks`, Python's `looks=`). The design's recursion costs time quadratic in the looks
/// (100 looks take under a second, about 20 s with futility bounds, whose drift search
/// repeats it), and a count is expanded into its looks' run counts before anything else:
/// beyond this a gate is refused before it allocates or computes anything.
pub const MAX_LOOKS: usize = 100;

/// The default looks: `count` looks of N/count runs (rounded, distinct, at least 2 runs each).
pub fn default_looks(runs: usize, count: usize) -> Vec<usize> {
    let mut looks: Vec<usize> = (1..=count)
        .map(|k| ((k * runs) as f64 / count as f64).round() as usize)
        .filter(|&n| n >= 2)
        .collect();
    looks.dedup();
    if looks.last() != Some(&runs) {
        looks.push(runs);
    }
    looks
}

/// What a gate is made of before the study's run count is known: the looks, how α is spent,
/// and the optional futility β (`[check] sequential`, `kfmc check --sequential`, `kfmc power
/// --sequential`).
#[derive(Debug, Clone, PartialEq)]
pub struct GateSettings {
    /// Where the gate looks.
    pub looks: Looks,
    /// How α is spent over the looks.
    pub spending: Spending,
    /// Non-binding futility bounds spending β, when given.
    pub futility_beta: Option<f64>,
    /// The exponent ρ of the futility bounds' β-spending β·t^ρ (default 2, quadratic).
    pub futility_rho: f64,
}

/// The default β-spending exponent of the futility bounds: quadratic.
pub const QUADRATIC_FUTILITY: f64 = 2.0;

impl Default for GateSettings {
    /// Ten even looks, O'Brien–Fleming-type spending, no futility bounds.
    fn default() -> Self {
        GateSettings {
            looks: Looks::Count(10),
            spending: Spending::OBrienFleming,
            futility_beta: None,
            futility_rho: QUADRATIC_FUTILITY,
        }
    }
}

impl GateSettings {
    /// The gate of a study of `runs` runs per cell at level `alpha`.
    pub fn gate(&self, runs: usize, alpha: f64) -> Result<Gate, GateError> {
        Gate::for_study_with(
            runs,
            alpha,
            &self.looks,
            &self.spending,
            self.futility_beta.map(|b| (b, self.futility_rho)),
        )
    }

    /// The spending function's name as a spec writes it (`obrien_fleming`, `pocock`, …).
    pub fn spending_name(&self) -> String {
        match &self.spending {
            Spending::OBrienFleming => "obrien_fleming".into(),
            Spending::Pocock => "pocock".into(),
            Spending::Power(rho) => format!("power({rho})"),
            Spending::User(v) => format!("user({v:?})"),
        }
    }
}

/// What a front end asks of the gate on top of a spec's `[check]` settings: the flags
/// `--sequential`, `--looks`, `--spending`, `--futility` and `--futility-rho` of `kfmc check`
/// and `kfmc power`, and the same keywords of the Python `check` and `power`. Each given
/// setting wins over the spec's; [`GateOverrides::apply`] is the one place they meet.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct GateOverrides {
    /// Ask for the gate (the spec may already have it: `[check] sequential = true`).
    pub sequential: bool,
    /// The looks, when given.
    pub looks: Option<Looks>,
    /// The α-spending, when given.
    pub spending: Option<Spending>,
    /// The futility β, when given.
    pub futility_beta: Option<f64>,
    /// The futility bounds' β-spending exponent ρ, when given (only with a futility β).
    pub futility_rho: Option<f64>,
}

/// A gate setting given where there is no gate to set, or given without the setting it
/// modifies; each front end names the setting in its own spelling.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum GateOverrideError {
    /// The setting (`looks`, `spending`, `futility_beta`, `futility_rho`) was given, but
    /// neither the caller nor the spec asks for the gate.
    NotSequential(GateSetting),
    /// `futility_rho` was given without a futility β of its own.
    RhoWithoutFutility,
}

/// One of a gate's settings, as [`GateOverrideError`] names it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum GateSetting {
    /// The looks.
    Looks,
    /// The α-spending.
    Spending,
    /// The futility β.
    Futility,
    /// The futility β-spending exponent.
    FutilityRho,
}

impl GateOverrides {
    /// The gate's settings: `None` when neither `sequential` nor `spec` asks for a gate (and
    /// then no other setting may be given), else the given settings over `spec`'s (the
    /// spec's `[check]` keys) over the defaults ([`GateSettings::default`]). Whether they
    /// make a gate for the study's runs is [`GateSettings::gate`]'s to say.
    pub fn apply(
        &self,
        spec: Option<&GateSettings>,
    ) -> Result<Option<GateSettings>, GateOverrideError> {
        if self.futility_rho.is_some() && self.futility_beta.is_none() {
            return Err(GateOverrideError::RhoWithoutFutility);
        }
        let base = match (self.sequential, spec) {
            (true, s) => Some(s.cloned().unwrap_or_default()),
            (false, s) => s.cloned(),
        };
        let Some(mut settings) = base else {
            let given = [
                (GateSetting::Looks, self.looks.is_some()),
                (GateSetting::Spending, self.spending.is_some()),
                (GateSetting::Futility, self.futility_beta.is_some()),
                (GateSetting::FutilityRho, self.futility_rho.is_some()),
            ]
            .into_iter()
            .find(|(_, given)| *given);
            return match given {
                Some((setting, _)) => Err(GateOverrideError::NotSequential(setting)),
                None => Ok(None),
            };
        };
        if let Some(looks) = &self.looks {
            settings.looks = looks.clone();
        }
        if let Some(spending) = &self.spending {
            settings.spending = spending.clone();
        }
        if self.futility_beta.is_some() {
            settings.futility_beta = self.futility_beta;
        }
        if let Some(rho) = self.futility_rho {
            settings.futility_rho = rho;
        }
        Ok(Some(settings))
    }
}

impl Gate {
    /// The gate of a study of `runs` runs per cell at level `alpha`: `looks`, `spending` for
    /// α and, with `futility_beta`, non-binding futility bounds spending β quadratically (t²)
    /// (the default of [`GateSettings`]).
    pub fn for_study(
        runs: usize,
        alpha: f64,
        looks: &Looks,
        spending: &Spending,
        futility_beta: Option<f64>,
    ) -> Result<Gate, GateError> {
        Gate::for_study_with(
            runs,
            alpha,
            looks,
            spending,
            futility_beta.map(|b| (b, QUADRATIC_FUTILITY)),
        )
    }

    /// [`Gate::for_study`] with futility bounds spending β by the Kim–DeMets power
    /// function β·t^ρ: `futility = (β, ρ)`. ρ = 2 (quadratic) spends little early; ρ = 1
    /// (linear) spends it evenly, so a consistent filter stops earlier, at some power against
    /// mistunings near the truth.
    pub fn for_study_with(
        runs: usize,
        alpha: f64,
        looks: &Looks,
        spending: &Spending,
        futility: Option<(f64, f64)>,
    ) -> Result<Gate, GateError> {
        let looks = match looks {
            Looks::Count(0) => {
                return Err(GateError::Looks("the count of looks must be ≥ 1".into()));
            }
            Looks::Count(count) if *count > MAX_LOOKS => {
                return Err(GateError::Looks(format!(
                    "{count} looks are more than a gate may take (at most {MAX_LOOKS})"
                )));
            }
            Looks::RunCounts(given) if given.len() > MAX_LOOKS => {
                return Err(GateError::Looks(format!(
                    "{} looks are more than a gate may take (at most {MAX_LOOKS})",
                    given.len()
                )));
            }
            Looks::Count(count) => default_looks(runs, *count),
            Looks::RunCounts(given) => {
                let ok = given.iter().all(|&n| n >= 2)
                    && given.windows(2).all(|w| w[0] < w[1])
                    && given.last() == Some(&runs);
                if !ok {
                    return Err(GateError::Looks(format!(
                        "the run counts must be ≥ 2, increase and end at the study's {runs} runs per cell; got {given:?}"
                    )));
                }
                given.clone()
            }
        };
        let beta_spending;
        let futility = match futility {
            Some((beta, _)) if !(beta > 0.0 && beta < 1.0) => {
                return Err(GateError::Futility(beta));
            }
            Some((_, rho)) if !(rho > 0.0 && rho.is_finite()) => {
                return Err(GateError::FutilityRho(rho));
            }
            Some((beta, rho)) => {
                beta_spending = Spending::Power(rho);
                Some((beta, &beta_spending))
            }
            None => None,
        };
        Ok(Gate::new(looks, alpha, spending, futility)?)
    }

    /// The gate of level `alpha` on `looks` (run counts, increasing), spending by `spending`,
    /// with non-binding futility spending `futility = (β, spending)` when given.
    pub fn new(
        looks: Vec<usize>,
        alpha: f64,
        spending: &Spending,
        futility: Option<(f64, &Spending)>,
    ) -> Result<Gate, SequentialError> {
        let last = *looks.last().ok_or(SequentialError::Fractions(Vec::new()))? as f64;
        let fractions: Vec<f64> = looks.iter().map(|&n| n as f64 / last).collect();
        let design = match futility {
            None => efficacy(&fractions, alpha / 2.0, spending, Sides::Two)?,
            Some((beta, beta_spending)) => with_futility(
                &fractions,
                alpha / 2.0,
                spending,
                Sides::Two,
                beta,
                beta_spending,
            )?,
        };
        Ok(Gate { looks, design })
    }

    /// Each test's nominal two-sided level at look `k`: it rejects at or below it.
    pub fn nominal_level(&self, k: usize) -> f64 {
        2.0 * normal().sf(self.design.efficacy[k])
    }

    /// Look `k`'s boundaries on the verdict's Bonferroni p-value p: the look rejects when
    /// p is at most the first and, with futility bounds, accepts when p exceeds the second
    /// (1 when it cannot), exactly as [`Gate::decide`] decides.
    pub fn p_boundaries(&self, k: usize) -> (f64, Option<f64>) {
        let reject = (2.0 * self.nominal_level(k)).min(1.0);
        let accept = self.design.futility.as_ref().map(|b| {
            if b[k] > 0.0 {
                (4.0 * normal().sf(b[k])).min(1.0)
            } else {
                1.0
            }
        });
        (reject, accept)
    }

    /// The decision at look `k` from the verdict's Bonferroni p-value at that look.
    pub fn decide(&self, k: usize, verdict_p: f64) -> Decision {
        // min(p_NEES, p_NIS); at the cap only a lower bound of it is known.
        let (smallest, capped) = if verdict_p >= 1.0 {
            (0.5, true)
        } else {
            (verdict_p / 2.0, false)
        };
        if !capped && smallest <= self.nominal_level(k) {
            return Decision::Reject;
        }
        let last = k + 1 == self.looks.len();
        if last {
            return Decision::Accept;
        }
        if let Some(b) = &self.design.futility {
            let keep_level = if b[k] > 0.0 {
                2.0 * normal().sf(b[k])
            } else {
                1.0
            };
            if smallest > keep_level || (capped && keep_level < 0.5) {
                return Decision::Accept;
            }
        }
        Decision::Continue
    }
}

#[cfg(test)]
mod tests;
