//! Streaming quantiles with bounded memory: an exact phase, then the P² algorithm of Jain &
//! Chlamtac (1985).
//!
//! The per-step error quantiles of a cell (`abs_err_p05_<state>` …) fold one value per run,
//! and the runs of a cell can number in the millions, so the values cannot always be kept.
//! [`QuantileSketch`] keeps them while there are at most a cap chosen by the caller and
//! answers exactly (type 7, as the other quantile columns); beyond the cap P² — fed with every
//! value from the first, in order — takes over. The study sets the cap from a memory budget
//! ([`super::ABS_ERR_EXACT_BYTES`]), so studies of up to a few thousand runs per cell get exact
//! quantiles, and the exact phase is also the cheaper one: P²'s marker updates cost several
//! divisions per value. P² keeps five markers per quantile and moves them with a
//! piecewise-parabolic update. Its result depends on the order of the observations, which is
//! why the caller folds runs in run order: the tables stay bit-identical for any thread count.

use super::{quantile_sorted, quantile_type7};

/// Values kept for the exact phase of a [`QuantileSketch`].
pub const EXACT_CAP: usize = 32;

/// One P² estimator of the `p`-quantile.
#[derive(Clone, Debug, PartialEq)]
pub struct P2Quantile {
    p: f64,
    /// Observations seen.
    count: usize,
    /// Marker heights q_0..q_4 (the first observations while `count < 5`).
    q: [f64; 5],
    /// Actual marker positions n_0..n_4 (1-based, as in the paper).
    n: [f64; 5],
    /// Desired positions n'_1..n'_3 of the middle markers (the extreme markers' are always
    /// 1 and the count, and are never read).
    desired: [f64; 3],
    /// Increments of the desired positions per observation.
    inc: [f64; 3],
}

impl P2Quantile {
    /// An estimator of the `p`-quantile, 0 < p < 1.
    pub fn new(p: f64) -> Self {
        P2Quantile {
            p,
            count: 0,
            q: [0.0; 5],
            n: [1.0, 2.0, 3.0, 4.0, 5.0],
            desired: [1.0 + 2.0 * p, 1.0 + 4.0 * p, 3.0 + 2.0 * p],
            inc: [p / 2.0, p, (1.0 + p) / 2.0],
        }
    }

    /// Observations seen.
    pub fn count(&self) -> usize {
        self.count
    }

    /// Adds one observation (callers drop non-finite values: the marker arithmetic would turn
    /// an infinity into NaN).
    pub fn push(&mut self, x: f64) {
        if self.count < 5 {
            self.q[self.count] = x;
            self.count += 1;
            if self.count == 5 {
                self.q.sort_by(f64::total_cmp);
            }
            return;
        }
        self.count += 1;
        let q = &mut self.q;
        // The cell k with q_k ≤ x < q_{k+1}, stretching the extreme markers if needed.
        let k = if x < q[0] {
            q[0] = x;
            0
        } else if x >= q[4] {
            q[4] = x;
            3
        } else {
            // The markers are sorted, so the largest i with q_i ≤ x is a count: no branch to
            // mispredict on a value that falls anywhere.
            (x >= q[1]) as usize + (x >= q[2]) as usize + (x >= q[3]) as usize
        };
        for (i, n) in self.n.iter_mut().enumerate().skip(1) {
            // + 0 leaves a position unchanged: the same sums as incrementing n[k + 1..].
            *n += if i > k { 1.0 } else { 0.0 };
        }
        for (d, inc) in self.desired.iter_mut().zip(self.inc) {
            *d += inc;
        }
        let n = &mut self.n;
        for i in 1..4 {
            let d = self.desired[i - 1] - n[i];
            if (d >= 1.0 && n[i + 1] - n[i] > 1.0) || (d <= -1.0 && n[i - 1] - n[i] < -1.0) {
                let d = d.signum();
                let parabolic = q[i]
                    + d / (n[i + 1] - n[i - 1])
                        * ((n[i] - n[i - 1] + d) * (q[i + 1] - q[i]) / (n[i + 1] - n[i])
                            + (n[i + 1] - n[i] - d) * (q[i] - q[i - 1]) / (n[i] - n[i - 1]));
                q[i] = if q[i - 1] < parabolic && parabolic < q[i + 1] {
                    parabolic
                } else {
                    // The parabola would break the markers' order: fall back to linear.
                    let j = if d > 0.0 { i + 1 } else { i - 1 };
                    q[i] + d * (q[j] - q[i]) / (n[j] - n[i])
                };
                n[i] += d;
            }
        }
    }

    /// The current estimate; exact (type 7) below five observations, `None` with none.
    pub fn estimate(&self) -> Option<f64> {
        match self.count {
            0 => None,
            c if c < 5 => {
                let mut v = self.q[..c].to_vec();
                v.sort_by(f64::total_cmp);
                quantile_sorted(&v, self.p)
            }
            _ => Some(self.q[2]),
        }
    }
}

/// Several quantiles of one stream: exact up to a number of values chosen by the caller (at
/// least [`EXACT_CAP`]), P² beyond.
#[derive(Clone, Debug, PartialEq)]
pub struct QuantileSketch {
    /// The values so far, while there are at most `cap`; emptied when P² takes over.
    exact: Vec<f64>,
    cap: usize,
    /// Whether P² has taken over (it then holds every value, from the first).
    estimating: bool,
    p2: Vec<P2Quantile>,
}

impl QuantileSketch {
    /// A sketch of the quantiles `probs` (each in (0, 1)), exact up to [`EXACT_CAP`] values.
    pub fn new(probs: &[f64]) -> Self {
        Self::with_exact_cap(probs, EXACT_CAP)
    }

    /// A sketch that answers exactly up to `cap` values (at least [`EXACT_CAP`]): it keeps
    /// them, 8 bytes each, and hands them to P² in arrival order on the first value beyond.
    pub fn with_exact_cap(probs: &[f64], cap: usize) -> Self {
        QuantileSketch {
            exact: Vec::new(),
            cap: cap.max(EXACT_CAP),
            estimating: false,
            p2: probs.iter().map(|&p| P2Quantile::new(p)).collect(),
        }
    }

    /// Makes room for `values` more exact values (never past the cap) in one allocation, for
    /// a caller that knows how many will come: growing by doubling copies each value about
    /// once more and, over a cell's thousand sketches, keeps the allocator mapping memory.
    pub fn reserve(&mut self, values: usize) {
        if !self.estimating {
            let room = values.min(self.cap - self.exact.len());
            self.exact.reserve_exact(room);
        }
    }

    /// Adds one observation; non-finite values are not counted.
    pub fn push(&mut self, x: f64) {
        if !x.is_finite() {
            return;
        }
        if !self.estimating {
            if self.exact.len() < self.cap {
                if self.exact.len() == self.exact.capacity() {
                    // Doubling, but never past the cap: the budget bounds the capacity.
                    let more = self.exact.len().max(8).min(self.cap - self.exact.len());
                    self.exact.reserve_exact(more);
                }
                self.exact.push(x);
                return;
            }
            // Leaving the exact phase: P² starts from the very first value, in arrival order,
            // so the result is the same as if it had run from the start (and studies within
            // the cap never pay for it).
            for e in &mut self.p2 {
                self.exact.iter().for_each(|&v| e.push(v));
            }
            self.exact = Vec::new();
            self.estimating = true;
        }
        for e in &mut self.p2 {
            e.push(x);
        }
    }

    /// The `i`-th quantile (in the order given to [`QuantileSketch::new`]).
    pub fn estimate(&self, i: usize) -> Option<f64> {
        self.estimates().get(i).copied().flatten()
    }

    /// Every quantile, in the order given to [`QuantileSketch::new`]. In the exact phase each
    /// is type 7 from the two order statistics around it, found by selection (linear time)
    /// rather than a sort: the same values `quantile_sorted` reads from the sorted data.
    /// The quantiles are taken from the lowest up, and each selection only searches the
    /// values above the order statistic the one before it placed: for the 5 %, 50 % and 95 %
    /// of |e| that is 2.45 instead of 3 passes over the values.
    pub fn estimates(&self) -> Vec<Option<f64>> {
        if self.estimating {
            return self.p2.iter().map(P2Quantile::estimate).collect();
        }
        // Selection on integer keys in `f64::total_cmp`'s order: the comparisons are plain
        // integer ones, the order statistics the same values.
        let mut v: Vec<u64> = self.exact.iter().map(|&x| total_order_key(x)).collect();
        let len = v.len();
        let mut order: Vec<usize> = (0..self.p2.len()).collect();
        order.sort_by(|&a, &b| self.p2[a].p.total_cmp(&self.p2[b].p));
        let mut out = vec![None; self.p2.len()];
        // v[..placed] holds the `placed` smallest values, v[placed − 1] the largest of them.
        let mut placed = 0;
        for q in order {
            let mut selected: Option<usize> = None;
            out[q] = quantile_type7(len, self.p2[q].p, |i| {
                from_total_order_key(match selected {
                    // x_(⌊h⌋): placed by an earlier quantile, or selected among those above.
                    None => {
                        selected = Some(i);
                        if i + 1 == placed {
                            v[i]
                        } else {
                            debug_assert!(i >= placed, "quantiles are taken in increasing order");
                            let x = *v[placed..].select_nth_unstable(i - placed).1;
                            placed = i + 1;
                            x
                        }
                    }
                    // x_(⌊h⌋+1): the smallest of the values after x_(⌊h⌋).
                    Some(lo) => *v[lo + 1..]
                        .iter()
                        .min()
                        .expect("h < len − 1 leaves a value above"),
                })
            });
        }
        out
    }
}

/// An unsigned key whose integer order is `f64::total_cmp`'s order on the values.
fn total_order_key(x: f64) -> u64 {
    let bits = x.to_bits();
    // Negative values: every bit but the sign flipped (as total_cmp does), then the sign bit
    // flipped for all, so that negatives come first as unsigned integers.
    (bits ^ ((((bits as i64) >> 63) as u64) >> 1)) ^ (1 << 63)
}

/// The value of a [`total_order_key`].
fn from_total_order_key(k: u64) -> f64 {
    let t = k ^ (1 << 63);
    f64::from_bits(t ^ ((((t as i64) >> 63) as u64) >> 1))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A deterministic permutation of 0..n (n prime): well mixed, no RNG needed.
    fn mixed(n: usize) -> Vec<f64> {
        (0..n).map(|i| ((i * 7919) % n) as f64).collect()
    }

    fn exact(v: &[f64], p: f64) -> f64 {
        let mut s = v.to_vec();
        s.sort_by(f64::total_cmp);
        quantile_sorted(&s, p).unwrap()
    }

    #[test]
    fn total_order_keys_sort_as_total_cmp_and_round_trip() {
        let mut xs = vec![
            f64::NEG_INFINITY,
            -1e300,
            -1.5,
            -f64::MIN_POSITIVE,
            -5e-324,
            -0.0,
            0.0,
            5e-324,
            f64::MIN_POSITIVE,
            1.0,
            1.0 + f64::EPSILON,
            1e300,
            f64::INFINITY,
            f64::NAN,
            -f64::NAN,
        ];
        xs.extend(mixed(101).iter().map(|x| (x - 50.0) * 0.37));
        for a in &xs {
            assert_eq!(
                from_total_order_key(total_order_key(*a)).to_bits(),
                a.to_bits()
            );
            for b in &xs {
                assert_eq!(
                    total_order_key(*a).cmp(&total_order_key(*b)),
                    a.total_cmp(b),
                    "{a} vs {b}"
                );
            }
        }
    }

    #[test]
    fn small_samples_are_exact() {
        let data = [3.0, 1.0, 4.0, 1.0, 5.0, 9.0, 2.0, 6.0, 5.0, 3.0, 5.0];
        let probs = [0.05, 0.5, 0.95];
        for n in 1..=data.len() {
            let mut s = QuantileSketch::new(&probs);
            data[..n].iter().for_each(|&x| s.push(x));
            for (i, &p) in probs.iter().enumerate() {
                assert_eq!(
                    s.estimate(i),
                    Some(exact(&data[..n], p)),
                    "n = {n}, p = {p}"
                );
            }
        }
        assert_eq!(QuantileSketch::new(&probs).estimate(0), None);
    }

    /// Jain & Chlamtac's update as printed (every marker's desired position advanced, the
    /// cell found by a search, the positions above it incremented): the reference that
    /// [`P2Quantile::push`]'s branch-free form must match bit for bit.
    fn textbook_p2(p: f64, xs: &[f64]) -> f64 {
        let mut q: Vec<f64> = xs[..5].to_vec();
        q.sort_by(f64::total_cmp);
        let mut n = [1.0, 2.0, 3.0, 4.0, 5.0];
        let mut desired = [1.0, 1.0 + 2.0 * p, 1.0 + 4.0 * p, 3.0 + 2.0 * p, 5.0];
        let inc = [0.0, p / 2.0, p, (1.0 + p) / 2.0, 1.0];
        for &x in &xs[5..] {
            let k = if x < q[0] {
                q[0] = x;
                0
            } else if x >= q[4] {
                q[4] = x;
                3
            } else {
                (0..4).rev().find(|&i| x >= q[i]).unwrap()
            };
            for v in &mut n[k + 1..] {
                *v += 1.0;
            }
            for (d, i) in desired.iter_mut().zip(inc) {
                *d += i;
            }
            for i in 1..4 {
                let d = desired[i] - n[i];
                if (d >= 1.0 && n[i + 1] - n[i] > 1.0) || (d <= -1.0 && n[i - 1] - n[i] < -1.0) {
                    let d = d.signum();
                    let parabolic = q[i]
                        + d / (n[i + 1] - n[i - 1])
                            * ((n[i] - n[i - 1] + d) * (q[i + 1] - q[i]) / (n[i + 1] - n[i])
                                + (n[i + 1] - n[i] - d) * (q[i] - q[i - 1]) / (n[i] - n[i - 1]));
                    q[i] = if q[i - 1] < parabolic && parabolic < q[i + 1] {
                        parabolic
                    } else {
                        let j = if d > 0.0 { i + 1 } else { i - 1 };
                        q[i] + d * (q[j] - q[i]) / (n[j] - n[i])
                    };
                    n[i] += d;
                }
            }
        }
        q[2]
    }

    /// Continuous, heavy-tailed or heavily tied values by `case % 3` (ties hit the `x ≥ q_i`
    /// edges of P² and the equal order statistics of the exact phase).
    fn test_stream(rng: &mut rand_pcg::Pcg64, case: usize, len: usize) -> Vec<f64> {
        use rand::RngExt;
        (0..len)
            .map(|_| match case % 3 {
                0 => rng.random::<f64>(),
                1 => rng.random::<f64>().powi(-2),
                _ => rng.random_range(0..4) as f64,
            })
            .collect()
    }

    #[test]
    fn p2_matches_the_textbook_update_bit_for_bit() {
        use rand::SeedableRng;
        let mut rng = rand_pcg::Pcg64::seed_from_u64(16);
        for case in 0..300 {
            let len = 5 + case * 7;
            let xs = test_stream(&mut rng, case, len);
            for p in [0.05, 0.5, 0.95] {
                let mut e = P2Quantile::new(p);
                xs.iter().for_each(|&x| e.push(x));
                assert_eq!(
                    e.estimate().unwrap().to_bits(),
                    textbook_p2(p, &xs).to_bits(),
                    "case {case}, p = {p}"
                );
            }
        }
    }

    #[test]
    fn the_exact_phase_equals_sorting_and_the_p2_phase_does_not_depend_on_the_cap() {
        use rand::SeedableRng;
        let mut rng = rand_pcg::Pcg64::seed_from_u64(17);
        let probs = [0.05, 0.5, 0.95];
        for case in 0..200 {
            let len = 1 + case * 13;
            let xs = test_stream(&mut rng, case, len);
            // Within its cap a sketch is type 7 of the sorted values, bit for bit.
            let mut exact = QuantileSketch::with_exact_cap(&probs, len);
            xs.iter().for_each(|&x| exact.push(x));
            let mut sorted = xs.clone();
            sorted.sort_by(f64::total_cmp);
            for (i, &p) in probs.iter().enumerate() {
                assert_eq!(
                    exact.estimate(i).map(f64::to_bits),
                    quantile_sorted(&sorted, p).map(f64::to_bits),
                    "case {case}, p = {p}"
                );
            }
            // Probabilities out of order, repeated, and close enough to share an order
            // statistic: each selection reuses what the lower ones placed.
            let mixed = [0.95, 0.05, 0.5, 0.5, 0.501, 0.999, 0.001];
            let mut sketch = QuantileSketch::with_exact_cap(&mixed, len);
            xs.iter().for_each(|&x| sketch.push(x));
            for (&p, got) in mixed.iter().zip(sketch.estimates()) {
                assert_eq!(
                    got.map(f64::to_bits),
                    quantile_sorted(&sorted, p).map(f64::to_bits),
                    "case {case}, p = {p} among {mixed:?}"
                );
            }
            // Beyond its cap it is P² from the first value, whatever the cap was.
            let cap = len / 2;
            let mut small = QuantileSketch::new(&probs);
            let mut large = QuantileSketch::with_exact_cap(&probs, cap);
            xs.iter().for_each(|&x| {
                small.push(x);
                large.push(x);
            });
            if len > cap.max(EXACT_CAP) {
                assert_eq!(small.estimates(), large.estimates(), "case {case}");
            }
        }
    }

    #[test]
    fn p2_alone_is_exact_below_five_values() {
        let mut e = P2Quantile::new(0.5);
        for x in [4.0, 2.0, 8.0] {
            e.push(x);
        }
        assert_eq!(e.estimate(), Some(4.0));
    }

    #[test]
    fn p2_tracks_the_exact_quantiles_of_a_uniform_stream() {
        // 0..10006 shuffled: exact p-quantile = p·10006. P² is within 0.5 % of the range.
        let v = mixed(10_007);
        for p in [0.05, 0.5, 0.95] {
            let mut s = QuantileSketch::new(&[p]);
            v.iter().for_each(|&x| s.push(x));
            let (got, want) = (s.estimate(0).unwrap(), exact(&v, p));
            assert!(
                (got - want).abs() < 0.005 * 10_006.0,
                "p = {p}: {got} vs {want}"
            );
        }
    }

    #[test]
    fn p2_tracks_a_skewed_stream() {
        // |e| of errors is skewed: squares of a uniform stream, like sqrt(sq_err) inverted.
        let v: Vec<f64> = mixed(4_001).iter().map(|x| (x / 4_000.0).powi(2)).collect();
        for p in [0.05, 0.5, 0.95] {
            let mut s = QuantileSketch::new(&[p]);
            v.iter().for_each(|&x| s.push(x));
            let (got, want) = (s.estimate(0).unwrap(), exact(&v, p));
            assert!((got - want).abs() < 0.01, "p = {p}: {got} vs {want}");
        }
    }

    #[test]
    fn non_finite_values_are_skipped_and_order_is_deterministic() {
        let mut a = QuantileSketch::new(&[0.5]);
        let mut b = QuantileSketch::new(&[0.5]);
        for x in mixed(101) {
            a.push(x);
            b.push(x);
        }
        b.push(f64::NAN);
        b.push(f64::INFINITY);
        assert_eq!(
            a.estimate(0).unwrap().to_bits(),
            b.estimate(0).unwrap().to_bits()
        );
    }
}
