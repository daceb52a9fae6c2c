//! Blocks of quantities (position, velocity, attitude, …) and their NEES.
//!
//! The whole-state NEES says whether a filter is consistent; a block's NEES
//! e_bᵀ P_bb⁻¹ e_b (e_b the block's errors, P_bb its marginal covariance) says *where* it is
//! not: one block's excess can be masked by another's deficit in the whole-state average. A
//! block is the quantities sharing a unit, in the system's quantity order — for the drone
//! `px, py, pz` (m), `vx, vy, vz` (m/s), `roll, pitch, yaw` (deg). The figures
//! (`kfmc plot --kind block_consistency`) and the tables (`block_anees_<block>` columns of
//! `steps.parquet` and `consistency.parquet`) use this one grouping.

/// At most this many blocks are tracked per run (a layout with more units has no block
/// columns): the blocks travel with the run's options as fixed-size bit masks.
pub const MAX_BLOCKS: usize = 8;

/// A block of more quantities than this (other than the whole state) has no block NEES: its
/// covariance is factored in a fixed-size scratch array on the step loop's stack.
pub const MAX_BLOCK_LEN: usize = 16;

/// One block of quantities.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct QuantityBlock {
    /// `position` (unit m), `velocity` (m/s), `attitude` (angles), `unitless`, or the unit.
    pub name: String,
    /// The quantities' unit.
    pub unit: String,
    /// The quantities' indices in the layout's order.
    pub indices: Vec<usize>,
}

impl QuantityBlock {
    /// The block's name as it appears in column names: lower-case letters, digits and `_`.
    pub fn column_name(&self) -> String {
        column_safe(&self.name)
    }
}

fn column_safe(s: &str) -> String {
    let mut out: String = s
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() {
                c.to_ascii_lowercase()
            } else {
                '_'
            }
        })
        .collect();
    if out.is_empty() {
        out.push('_');
    }
    out
}

/// Groups quantities, given as (unit, whether an angle) in layout order, into blocks of equal
/// unit, in order of first appearance. Two blocks whose names would be the same column (two
/// angle units, or units differing only in punctuation) get the unit appended.
pub fn group<'a>(quantities: impl IntoIterator<Item = (&'a str, bool)>) -> Vec<QuantityBlock> {
    let mut out: Vec<QuantityBlock> = Vec::new();
    for (i, (unit, angle)) in quantities.into_iter().enumerate() {
        match out.iter_mut().find(|b| b.unit == unit) {
            Some(b) => b.indices.push(i),
            None => out.push(QuantityBlock {
                name: match unit {
                    "m" => "position".into(),
                    "m/s" => "velocity".into(),
                    _ if angle => "attitude".into(),
                    "" => "unitless".into(),
                    u => u.to_string(),
                },
                unit: unit.to_string(),
                indices: vec![i],
            }),
        }
    }
    let clashes: Vec<bool> = (0..out.len())
        .map(|b| (0..out.len()).any(|o| o != b && out[o].column_name() == out[b].column_name()))
        .collect();
    for (b, clash) in out.iter_mut().zip(clashes) {
        if clash {
            b.name = format!("{}_{}", b.name, column_safe(&b.unit));
        }
    }
    out
}

/// Blocks as bit masks over the quantities (a `Copy` value the step loop carries): block b
/// holds quantity i when bit i of `masks[b]` is set. Empty when the layout has more than
/// [`MAX_BLOCKS`] blocks or more than 64 quantities.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct BlockMasks {
    masks: [u64; MAX_BLOCKS],
    count: usize,
}

impl BlockMasks {
    /// The masks of `blocks` over `quantities` quantities (none when they do not fit).
    pub fn new(blocks: &[QuantityBlock], quantities: usize) -> Self {
        let mut m = BlockMasks::default();
        if blocks.len() > MAX_BLOCKS || quantities > 64 {
            return m;
        }
        for (b, blk) in blocks.iter().enumerate() {
            m.masks[b] = blk.indices.iter().fold(0, |acc, &i| acc | (1u64 << i));
        }
        m.count = blocks.len();
        m
    }

    /// Number of blocks.
    pub fn len(&self) -> usize {
        self.count
    }

    /// Whether there are no blocks.
    pub fn is_empty(&self) -> bool {
        self.count == 0
    }

    /// Block NEES e_bᵀ P_bb⁻¹ e_b of every block into `out[..len()]`, NaN where P_bb is not
    /// positive definite or the block is longer than [`MAX_BLOCK_LEN`]. A block of every
    /// quantity takes `full_nees`, the whole-state NEES, so that it equals the whole-state
    /// column bit for bit.
    pub fn nees<const N: usize>(
        &self,
        e: &crate::linalg::Vector<N>,
        p: &crate::linalg::Matrix<N, N>,
        full_nees: f64,
        out: &mut [f64],
    ) {
        let all = if N >= 64 { u64::MAX } else { (1u64 << N) - 1 };
        for (b, o) in out.iter_mut().enumerate().take(self.count) {
            let mask = self.masks[b];
            if mask == all {
                *o = full_nees;
                continue;
            }
            let m = mask.count_ones() as usize;
            if m > MAX_BLOCK_LEN {
                *o = f64::NAN;
                continue;
            }
            let mut idx = [0usize; MAX_BLOCK_LEN];
            let mut t = 0;
            for i in 0..N {
                if mask >> i & 1 == 1 {
                    idx[t] = i;
                    t += 1;
                }
            }
            let mut a = [0.0; MAX_BLOCK_LEN * MAX_BLOCK_LEN];
            let mut v = [0.0; MAX_BLOCK_LEN];
            for r in 0..m {
                v[r] = e[idx[r]];
                for c in 0..=r {
                    a[r * m + c] = p[(idx[r], idx[c])];
                }
            }
            *o = inverse_quadratic_form(&mut a[..m * m], m, &mut v[..m]).unwrap_or(f64::NAN);
        }
    }
}

/// vᵀ A⁻¹ v for a symmetric positive definite `n × n` matrix whose lower triangle is in `a`
/// (row-major; overwritten by its Cholesky factor), with `v` overwritten by L⁻¹v; `None`
/// when A is not positive definite (a pivot ≤ 0 or not finite).
pub fn inverse_quadratic_form(a: &mut [f64], n: usize, v: &mut [f64]) -> Option<f64> {
    cholesky_lower(a, n)?;
    Some(forward_norm_sq(a, n, v))
}

/// Factors the lower triangle of `a` (row-major `n × n`) in place into L with A = L Lᵀ;
/// `None` when a pivot is not positive and finite.
pub fn cholesky_lower(a: &mut [f64], n: usize) -> Option<()> {
    for j in 0..n {
        let mut d = a[j * n + j];
        for k in 0..j {
            d -= a[j * n + k] * a[j * n + k];
        }
        if !(d > 0.0 && d.is_finite()) {
            return None;
        }
        let d = d.sqrt();
        a[j * n + j] = d;
        for i in j + 1..n {
            let mut s = a[i * n + j];
            for k in 0..j {
                s -= a[i * n + k] * a[j * n + k];
            }
            a[i * n + j] = s / d;
        }
    }
    Some(())
}

/// ‖L⁻¹v‖² for a factor from [`cholesky_lower`]; `v` is overwritten by L⁻¹v.
pub fn forward_norm_sq(l: &[f64], n: usize, v: &mut [f64]) -> f64 {
    let mut sum = 0.0;
    for i in 0..n {
        let mut s = v[i];
        for k in 0..i {
            s -= l[i * n + k] * v[k];
        }
        v[i] = s / l[i * n + i];
        sum += v[i] * v[i];
    }
    sum
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::linalg::{Matrix, Vector};

    #[test]
    fn the_drone_layout_groups_into_position_velocity_attitude() {
        let q = [
            ("m", false),
            ("m", false),
            ("m", false),
            ("m/s", false),
            ("m/s", false),
            ("m/s", false),
            ("deg", true),
            ("deg", true),
            ("deg", true),
        ];
        let b = group(q);
        let names: Vec<&str> = b.iter().map(|b| b.name.as_str()).collect();
        assert_eq!(names, ["position", "velocity", "attitude"]);
        assert_eq!(b[2].indices, [6, 7, 8]);
        // Two angle units would both be `attitude`: the unit tells them apart.
        let b = group([("deg", true), ("rad", true), ("rad/s", false)]);
        let names: Vec<String> = b.iter().map(QuantityBlock::column_name).collect();
        assert_eq!(names, ["attitude_deg", "attitude_rad", "rad_s"]);
    }

    #[test]
    fn block_nees_is_the_marginal_quadratic_form() {
        // P with cross-covariances between the blocks: the block NEES uses the marginal
        // P_bb, not the inverse's block. By hand: block {0} → e0²/P00; block {1, 2}.
        let p = Matrix::<3, 3>::new(4.0, 1.0, 0.5, 1.0, 2.0, 0.3, 0.5, 0.3, 1.0);
        let e = Vector::<3>::new(2.0, 1.0, -1.0);
        let blocks = group([("m", false), ("s", false), ("s", false)]);
        let masks = BlockMasks::new(&blocks, 3);
        let mut out = [0.0; MAX_BLOCKS];
        masks.nees(&e, &p, f64::NAN, &mut out);
        assert!((out[0] - 1.0).abs() < 1e-15);
        // [1, −1] [[2, .3], [.3, 1]]⁻¹ [1, −1]ᵀ = (1·1 + 2·.3 + 2·1)/(2 − .09) = 3.6/1.91.
        assert!((out[1] - 3.6 / 1.91).abs() < 1e-14, "{}", out[1]);
        // One block of everything is the whole-state value given, bit for bit.
        let one = BlockMasks::new(&group([("m", false); 3]), 3);
        one.nees(&e, &p, 1.25, &mut out);
        assert_eq!(out[0], 1.25);
        // Not positive definite: NaN.
        let bad = Matrix::<3, 3>::new(1.0, 0.0, 0.0, 0.0, 1.0, 2.0, 0.0, 2.0, 1.0);
        masks.nees(&e, &bad, f64::NAN, &mut out);
        assert!(out[1].is_nan() && (out[0] - 4.0).abs() < 1e-15);
    }
}
