//! Per-run values of a cell in bounded memory, with exact across-run statistics.
//!
//! A cell's summary rows need the mean, standard deviation and exact 5/50/95 % quantiles of a
//! per-run value (a state's RMSE, a world metric) over all runs of the cell. Keeping every
//! value made memory grow with the runs; a [`Spill`] keeps at most [`SPILL_ROWS`] rows in
//! memory and writes the rest to a scratch file in the study folder (a temporary name of
//! kfmc's own, `.kfmc-<token>-<n>.scratch-N.partial`, removed when the spill is dropped; a
//! crash leaves it for the next writer in the folder, which removes it by the token the lock
//! file recorded). The statistics come from sequential passes over the rows in run order:
//!
//! * mean and standard deviation: the same sums in the same order as
//!   [`crate::metrics::mean_std`], so the bits are the same;
//! * quantiles: the values at the needed ranks are selected exactly by narrowing on the bits
//!   of the `f64::total_cmp` order, 11 bits per pass, until at most [`COLLECT_CAP`] candidates
//!   remain, which are then sorted. The ranks and the interpolation are those of
//!   [`crate::metrics::quantile_sorted`], so the values are bit-identical to sorting.
//!
//! Memory is `SPILL_ROWS × width × 8` bytes for the buffer plus, while summarising, 16 KiB
//! of counts and `COLLECT_CAP × 8` bytes of candidates per (column, rank): independent of
//! the number of runs. A spill that never exceeds its buffer touches no file and summarises
//! by sorting, as before.

use std::fs::File;
use std::io::{BufReader, BufWriter, Read, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

use super::{mean_std, quantile_sorted};
use crate::error::OutputError;

/// Rows a [`Spill`] keeps in memory before it writes to its scratch file.
pub const SPILL_ROWS: usize = 65_536;

/// Candidates at which the selection stops narrowing and sorts.
pub const COLLECT_CAP: usize = 8_192;

/// Bits of the order key fixed per narrowing pass (2,048 counts per column and rank).
pub(crate) const DIGIT_BITS: u32 = 11;

/// Read/write buffer of a scratch file.
pub(crate) const IO_BUFFER: usize = 64 << 10;

/// Mean, sample standard deviation and quantiles of one column's kept values.
#[derive(Clone, Debug, PartialEq)]
pub struct ColumnSummary {
    /// Values kept.
    pub n: u64,
    /// Mean (`None` without values).
    pub mean: Option<f64>,
    /// Sample standard deviation (`None` below two values).
    pub std: Option<f64>,
    /// One per requested quantile level, as [`quantile_sorted`] gives them.
    pub quantiles: Vec<Option<f64>>,
}

/// Rows of `width` f64 values in run order, in memory up to a bound and on disk beyond.
pub struct Spill {
    width: usize,
    cap_rows: usize,
    dir: PathBuf,
    buf: Vec<f64>,
    file: Option<(PathBuf, BufWriter<File>)>,
    spilled_rows: u64,
}

/// A `u64` whose order is `f64::total_cmp`'s (a bijection: it maps back to the same bits).
fn key(x: f64) -> u64 {
    let b = x.to_bits();
    if b >> 63 == 1 { !b } else { b | 1 << 63 }
}

fn unkey(k: u64) -> f64 {
    f64::from_bits(if k >> 63 == 1 { k & !(1 << 63) } else { !k })
}

/// The ranks [`quantile_sorted`] reads for level `q` out of `n` sorted values.
fn ranks(n: u64, q: f64) -> (u64, u64, f64) {
    let h = (n - 1) as f64 * q;
    (h.floor() as u64, h.ceil() as u64, h)
}

/// [`quantile_sorted`]'s interpolation, given the values at its two ranks.
fn interpolate(lo: u64, hi: u64, h: f64, a: f64, b: f64) -> Option<f64> {
    if lo == hi {
        return Some(a);
    }
    if a.is_infinite() || b.is_infinite() {
        return None;
    }
    Some(a + (h - lo as f64) * (b - a))
}

/// The search for the value of one rank of one column.
struct Target {
    column: usize,
    /// Rank among the candidates that share `prefix`.
    rank: u64,
    /// High bits of the key fixed so far, and their value.
    known: u32,
    prefix: u64,
    /// Candidates sharing the prefix.
    count: u64,
    counts: Vec<u64>,
    collected: Option<Vec<u64>>,
    value: Option<f64>,
}

impl Target {
    fn matches(&self, k: u64) -> bool {
        self.known == 0 || k >> (64 - self.known) == self.prefix
    }

    fn width(&self) -> u32 {
        DIGIT_BITS.min(64 - self.known)
    }

    fn observe(&mut self, k: u64) {
        if self.value.is_some() || !self.matches(k) {
            return;
        }
        if let Some(c) = self.collected.as_mut() {
            c.push(k);
        } else {
            let w = self.width();
            let digit = (k >> (64 - self.known - w)) & ((1u64 << w) - 1);
            self.counts[digit as usize] += 1;
        }
    }

    /// After a pass: fix the next digit, or pick the value among the sorted candidates.
    fn advance(&mut self) {
        if self.value.is_some() {
            return;
        }
        if let Some(mut c) = self.collected.take() {
            c.sort_unstable();
            self.value = Some(unkey(c[self.rank as usize]));
            return;
        }
        let w = self.width();
        let mut below = 0;
        let (digit, count) = self
            .counts
            .iter()
            .enumerate()
            .find_map(|(d, &c)| {
                if self.rank < below + c {
                    Some((d as u64, c))
                } else {
                    below += c;
                    None
                }
            })
            .expect("the rank is below the candidates' count");
        self.rank -= below;
        self.prefix = if self.known == 0 {
            digit
        } else {
            self.prefix << w | digit
        };
        self.known += w;
        self.count = count;
        self.counts.iter_mut().for_each(|c| *c = 0);
        if self.known == 64 {
            // Every candidate has this key, hence these bits.
            self.value = Some(unkey(self.prefix));
        } else if self.count as usize <= COLLECT_CAP {
            self.collected = Some(Vec::with_capacity(self.count as usize));
        }
    }
}

static NEXT_SCRATCH: AtomicU64 = AtomicU64::new(0);

impl Spill {
    /// An empty spill of rows of `width` values, whose scratch file (if it needs one) goes
    /// into `dir`.
    pub fn new(dir: &Path, width: usize) -> Self {
        Self::with_capacity(dir, width, SPILL_ROWS)
    }

    /// As [`Spill::new`], spilling beyond `cap_rows` rows (tests use a small one).
    pub fn with_capacity(dir: &Path, width: usize, cap_rows: usize) -> Self {
        Spill {
            width,
            cap_rows: cap_rows.max(1),
            dir: dir.to_path_buf(),
            buf: Vec::new(),
            file: None,
            spilled_rows: 0,
        }
    }

    /// Rows pushed so far.
    pub fn rows(&self) -> u64 {
        self.spilled_rows + (self.buf.len() / self.width.max(1)) as u64
    }

    /// Appends a row of `width` values.
    pub fn push(&mut self, row: &[f64]) -> Result<(), OutputError> {
        debug_assert_eq!(row.len(), self.width);
        self.buf.extend_from_slice(row);
        if self.buf.len() >= self.cap_rows * self.width.max(1) {
            self.write_out()?;
        }
        Ok(())
    }

    fn io_error(path: &Path, action: &'static str, source: std::io::Error) -> OutputError {
        OutputError::Io {
            action,
            path: path.to_path_buf(),
            source,
        }
    }

    fn write_out(&mut self) -> Result<(), OutputError> {
        if self.file.is_none() {
            let n = NEXT_SCRATCH.fetch_add(1, Ordering::Relaxed);
            let (path, f) =
                crate::output::atomic::create_temp_beside(&self.dir.join(format!("scratch-{n}")))
                    .map_err(|e| Self::io_error(&self.dir, "cannot create a scratch file in", e))?;
            self.file = Some((path, BufWriter::with_capacity(IO_BUFFER, f)));
        }
        let (path, w) = self.file.as_mut().expect("created above");
        for x in &self.buf {
            w.write_all(&x.to_bits().to_le_bytes())
                .map_err(|e| Self::io_error(path, "cannot write the scratch file", e))?;
        }
        self.spilled_rows += (self.buf.len() / self.width.max(1)) as u64;
        self.buf.clear();
        Ok(())
    }

    /// Calls `f` on every row, in the order pushed.
    pub fn for_each_row(
        &mut self,
        mut f: impl FnMut(&[f64]) -> Result<(), OutputError>,
    ) -> Result<(), OutputError> {
        if let Some((path, w)) = self.file.as_mut() {
            w.flush()
                .map_err(|e| Self::io_error(path, "cannot write the scratch file", e))?;
            let file = File::open(&*path)
                .map_err(|e| Self::io_error(path, "cannot read the scratch file", e))?;
            let mut r = BufReader::with_capacity(IO_BUFFER, file);
            let mut bytes = vec![0u8; self.width * 8];
            let mut row = vec![0.0; self.width];
            for _ in 0..self.spilled_rows {
                r.read_exact(&mut bytes)
                    .map_err(|e| Self::io_error(path, "cannot read the scratch file", e))?;
                for (x, b) in row.iter_mut().zip(bytes.chunks_exact(8)) {
                    *x = f64::from_bits(u64::from_le_bytes(b.try_into().expect("8 bytes")));
                }
                f(&row)?;
            }
        }
        for row in self.buf.chunks_exact(self.width.max(1)) {
            f(row)?;
        }
        Ok(())
    }

    /// The rows, to be read once in order while other spills are written (the divergence
    /// tracker's previous pass).
    pub fn into_reader(mut self) -> Result<SpillReader, OutputError> {
        let file = match self.file.take() {
            Some((path, mut w)) => {
                w.flush()
                    .map_err(|e| Self::io_error(&path, "cannot write the scratch file", e))?;
                drop(w);
                let f = File::open(&path)
                    .map_err(|e| Self::io_error(&path, "cannot read the scratch file", e))?;
                Some((path, BufReader::with_capacity(IO_BUFFER, f)))
            }
            None => None,
        };
        Ok(SpillReader {
            width: self.width,
            file,
            file_rows: self.spilled_rows,
            tail: std::mem::take(&mut self.buf),
            tail_at: 0,
            bytes: vec![0; self.width * 8],
        })
    }

    /// Per column: the summary of the values `keep(column, value)` accepts, at the quantile
    /// levels `levels`; exactly what sorting them and calling [`mean_std`] and
    /// [`quantile_sorted`] gives.
    pub fn summarise(
        &mut self,
        keep: impl Fn(usize, f64) -> bool,
        levels: &[f64],
    ) -> Result<Vec<ColumnSummary>, OutputError> {
        let width = self.width;
        if self.file.is_none() {
            return Ok((0..width)
                .map(|c| {
                    let mut v: Vec<f64> = self
                        .buf
                        .chunks_exact(width)
                        .map(|r| r[c])
                        .filter(|x| keep(c, *x))
                        .collect();
                    let (mean, std) = mean_std(&v);
                    v.sort_by(f64::total_cmp);
                    ColumnSummary {
                        n: v.len() as u64,
                        mean,
                        std,
                        quantiles: levels.iter().map(|q| quantile_sorted(&v, *q)).collect(),
                    }
                })
                .collect());
        }
        // Pass 1: counts and sums, in run order as `mean_std` adds them.
        let mut n = vec![0u64; width];
        // -0.0: where `Iterator::sum` of f64 starts.
        let mut sum = vec![-0.0f64; width];
        self.for_each_row(|row| {
            for (c, x) in row.iter().enumerate() {
                if keep(c, *x) {
                    n[c] += 1;
                    sum[c] += x;
                }
            }
            Ok(())
        })?;
        let mean: Vec<Option<f64>> = (0..width)
            .map(|c| (n[c] > 0).then(|| sum[c] / n[c] as f64))
            .collect();
        // Pass 2: squared deviations from the mean.
        let mut sq = vec![-0.0f64; width];
        self.for_each_row(|row| {
            for (c, x) in row.iter().enumerate() {
                if keep(c, *x)
                    && let Some(m) = mean[c]
                {
                    sq[c] += (x - m).powi(2);
                }
            }
            Ok(())
        })?;
        // The ranks every quantile needs, each searched once per column.
        let mut targets: Vec<Target> = Vec::new();
        let mut index = vec![Vec::new(); width];
        for c in 0..width {
            if n[c] == 0 {
                continue;
            }
            for &q in levels {
                let (lo, hi, _) = ranks(n[c], q);
                for r in [lo, hi] {
                    if !targets
                        .iter()
                        .any(|t| t.column == c && t.rank == r && t.known == 0)
                    {
                        index[c].push((r, targets.len()));
                        targets.push(Target {
                            column: c,
                            rank: r,
                            known: 0,
                            prefix: 0,
                            count: n[c],
                            counts: vec![0; 1 << DIGIT_BITS],
                            collected: (n[c] as usize <= COLLECT_CAP)
                                .then(|| Vec::with_capacity(n[c] as usize)),
                            value: None,
                        });
                    }
                }
            }
        }
        while targets.iter().any(|t| t.value.is_none()) {
            self.for_each_row(|row| {
                for t in targets.iter_mut() {
                    let x = row[t.column];
                    if keep(t.column, x) {
                        t.observe(key(x));
                    }
                }
                Ok(())
            })?;
            targets.iter_mut().for_each(Target::advance);
        }
        let at = |c: usize, r: u64| {
            let (_, i) = index[c]
                .iter()
                .find(|(rank, _)| *rank == r)
                .expect("every needed rank was searched");
            targets[*i].value.expect("searched to the end")
        };
        Ok((0..width)
            .map(|c| {
                let nf = n[c] as f64;
                ColumnSummary {
                    n: n[c],
                    mean: mean[c],
                    std: (n[c] >= 2).then(|| (sq[c] / (nf - 1.0)).sqrt()),
                    quantiles: levels
                        .iter()
                        .map(|&q| {
                            (n[c] > 0).then(|| {
                                let (lo, hi, h) = ranks(n[c], q);
                                interpolate(lo, hi, h, at(c, lo), at(c, hi))
                            })?
                        })
                        .collect(),
                }
            })
            .collect())
    }
}

/// A [`Spill`]'s rows, read once in order; removes the scratch file when dropped.
pub struct SpillReader {
    width: usize,
    file: Option<(PathBuf, BufReader<File>)>,
    file_rows: u64,
    tail: Vec<f64>,
    tail_at: usize,
    bytes: Vec<u8>,
}

impl SpillReader {
    /// Fills `row` with the next row; `false` after the last.
    pub fn next_row(&mut self, row: &mut [f64]) -> Result<bool, OutputError> {
        if self.file_rows > 0
            && let Some((path, r)) = self.file.as_mut()
        {
            r.read_exact(&mut self.bytes)
                .map_err(|e| Spill::io_error(path, "cannot read the scratch file", e))?;
            for (x, b) in row.iter_mut().zip(self.bytes.chunks_exact(8)) {
                *x = f64::from_bits(u64::from_le_bytes(b.try_into().expect("8 bytes")));
            }
            self.file_rows -= 1;
            return Ok(true);
        }
        let Some(t) = self.tail.get(self.tail_at..self.tail_at + self.width) else {
            return Ok(false);
        };
        row.copy_from_slice(t);
        self.tail_at += self.width;
        Ok(true)
    }
}

impl Drop for SpillReader {
    fn drop(&mut self) {
        if let Some((path, r)) = self.file.take() {
            drop(r);
            let _ = std::fs::remove_file(path);
        }
    }
}

impl Drop for Spill {
    fn drop(&mut self) {
        if let Some((path, w)) = self.file.take() {
            drop(w);
            let _ = std::fs::remove_file(path);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{RngExt, SeedableRng};

    fn sorted_summary(v: &[f64], levels: &[f64]) -> ColumnSummary {
        let (mean, std) = mean_std(v);
        let mut s = v.to_vec();
        s.sort_by(f64::total_cmp);
        ColumnSummary {
            n: v.len() as u64,
            mean,
            std,
            quantiles: levels.iter().map(|q| quantile_sorted(&s, *q)).collect(),
        }
    }

    fn bits(s: &ColumnSummary) -> (u64, Option<u64>, Option<u64>, Vec<Option<u64>>) {
        (
            s.n,
            s.mean.map(f64::to_bits),
            s.std.map(f64::to_bits),
            s.quantiles.iter().map(|q| q.map(f64::to_bits)).collect(),
        )
    }

    #[test]
    fn the_order_key_is_total_cmp_and_maps_back() {
        let xs = [
            f64::NEG_INFINITY,
            -1e300,
            -1.0,
            -f64::MIN_POSITIVE,
            -0.0,
            0.0,
            5e-324,
            1.0,
            1e300,
            f64::INFINITY,
            f64::NAN,
            -f64::NAN,
        ];
        for a in xs {
            assert_eq!(unkey(key(a)).to_bits(), a.to_bits());
            for b in xs {
                assert_eq!(key(a).cmp(&key(b)), a.total_cmp(&b), "{a} vs {b}");
            }
        }
    }

    /// Spilled and sorted summaries agree bit for bit, on data with ties, infinities,
    /// signed zeros, a filter, many values per bucket (narrowing passes) and few.
    #[test]
    fn spilled_summaries_are_bit_identical_to_sorting() {
        let dir = tempfile::tempdir().unwrap();
        let levels = [0.05, 0.5, 0.95, 0.0, 1.0, 0.333];
        let mut rng = rand_pcg::Pcg64::seed_from_u64(7);
        for (case, n) in [1usize, 2, 3, 17, 1000, 30_000, 100_003]
            .into_iter()
            .enumerate()
        {
            let width = 4;
            let mut spill = Spill::with_capacity(dir.path(), width, 64);
            let mut cols = vec![Vec::new(); width];
            for i in 0..n {
                let row = [
                    // Smooth: one exponent band holds most values.
                    1.0 + rng.random::<f64>(),
                    // Heavy ties and the odd infinity.
                    if i % 97 == 0 {
                        f64::INFINITY
                    } else {
                        (rng.random_range(0..5) as f64) * 0.5
                    },
                    // Both signs, zeros of both signs, a wide range.
                    match i % 7 {
                        0 => -0.0,
                        1 => 0.0,
                        _ => (rng.random::<f64>() - 0.5) * 10f64.powi(rng.random_range(-30..30)),
                    },
                    // All equal: narrowing must reach the last bit.
                    3.25,
                ];
                spill.push(&row).unwrap();
                for (c, x) in row.iter().enumerate() {
                    cols[c].push(*x);
                }
            }
            assert_eq!(spill.rows(), n as u64);
            // Column 1 keeps finite values only, as the sensors table does.
            let keep = |c: usize, x: f64| c != 1 || x.is_finite();
            let got = spill.summarise(keep, &levels).unwrap();
            for (c, col) in cols.iter().enumerate() {
                let kept: Vec<f64> = col.iter().copied().filter(|x| keep(c, *x)).collect();
                let want = sorted_summary(&kept, &levels);
                assert_eq!(
                    bits(&got[c]),
                    bits(&want),
                    "case {case} (n {n}), column {c}"
                );
            }
            if n > 64 {
                assert_eq!(
                    std::fs::read_dir(dir.path()).unwrap().count(),
                    1,
                    "a spilled series has its scratch file"
                );
            }
            drop(spill);
            assert_eq!(
                std::fs::read_dir(dir.path()).unwrap().count(),
                0,
                "the scratch file goes with the spill"
            );
        }
    }

    #[test]
    fn a_reader_returns_the_rows_in_order_and_removes_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let mut spill = Spill::with_capacity(dir.path(), 2, 3);
        for i in 0..10 {
            spill.push(&[i as f64, -(i as f64)]).unwrap();
        }
        let mut r = spill.into_reader().unwrap();
        let mut row = [0.0; 2];
        for i in 0..10 {
            assert!(r.next_row(&mut row).unwrap());
            assert_eq!(row, [i as f64, -(i as f64)]);
        }
        assert!(!r.next_row(&mut row).unwrap());
        drop(r);
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
    }

    #[test]
    fn censored_values_make_an_interpolated_quantile_unknown_as_when_sorting() {
        let dir = tempfile::tempdir().unwrap();
        let mut spill = Spill::with_capacity(dir.path(), 1, 2);
        let mut v = Vec::new();
        for i in 0..50 {
            let x = if i % 2 == 0 { f64::INFINITY } else { i as f64 };
            spill.push(&[x]).unwrap();
            v.push(x);
        }
        let got = spill.summarise(|_, _| true, &[0.05, 0.5, 0.95]).unwrap();
        assert_eq!(bits(&got[0]), bits(&sorted_summary(&v, &[0.05, 0.5, 0.95])));
        assert_eq!(got[0].quantiles[2], None);
    }
}
