//! Divergence points as `robustness.m` defines them: for each state, the first noise
//! multiplier (in increasing order) whose RMSE exceeds the state's threshold — once for the
//! Monte Carlo mean RMSE and once per run, giving a distribution over runs.

use std::path::Path;

use super::spill::{Spill, SpillReader};
use crate::error::OutputError;

/// Rows of crossings a tracker keeps in memory per pass before it writes to its scratch file;
/// small, as every (scenario, filter) has a tracker alive until the tables are written.
pub(crate) const TRACKER_ROWS: usize = 4_096;

/// Tracks the first crossing per (run, state) and for the Monte Carlo mean, for one
/// (scenario, filter), in memory independent of the runs: the runs' crossings so far are a
/// [`Spill`], rewritten once per noise scale as that scale's runs arrive in run order (as a
/// study and `kfmc merge` feed them).
pub struct DivergenceTracker {
    nx: usize,
    dir: std::path::PathBuf,
    /// The crossings after the previous noise scales, read in step with the current one.
    previous: Option<SpillReader>,
    /// The crossings including the current noise scale: per run and state, the index of the
    /// smallest noise scale that crossed, NaN for none.
    current: Spill,
    next_run: usize,
    row: Vec<f64>,
    /// Per state: index of the smallest noise scale whose mean RMSE crossed.
    mc: Vec<Option<usize>>,
}

impl DivergenceTracker {
    /// A tracker of `nx` states whose scratch files go into `dir`.
    pub fn new(dir: &Path, nx: usize) -> Self {
        DivergenceTracker {
            nx,
            dir: dir.to_path_buf(),
            previous: None,
            current: Spill::with_capacity(dir, nx, TRACKER_ROWS),
            next_run: 0,
            row: vec![f64::NAN; nx],
            mc: vec![None; nx],
        }
    }

    /// Records a run's RMSE at noise scale `scale_index`. Each noise scale's runs come in
    /// run order, from run 0 up; a run out of order (rows read back from a damaged part or
    /// checkpoint) is an error naming the tracker's folder.
    pub fn observe_run(
        &mut self,
        run: usize,
        scale_index: usize,
        rmse: &[f64],
        thr: &[f64],
    ) -> Result<(), OutputError> {
        if run == 0 && self.next_run > 0 {
            let done = std::mem::replace(
                &mut self.current,
                Spill::with_capacity(&self.dir, self.nx, TRACKER_ROWS),
            );
            self.previous = Some(done.into_reader()?);
            self.next_run = 0;
        }
        if run != self.next_run {
            return Err(OutputError::Mismatch {
                path: self.dir.clone(),
                why: format!(
                    "holds runs out of order: run {run} of noise scale {scale_index} came where run {} was due",
                    self.next_run
                ),
            });
        }
        let seen = match self.previous.as_mut() {
            Some(p) => p.next_row(&mut self.row)?,
            None => false,
        };
        if !seen {
            self.row.fill(f64::NAN);
        }
        let s = scale_index as f64;
        for i in 0..self.nx {
            // NaN (a failed run) never counts as "not exceeding": treat it as a crossing.
            if (rmse[i] > thr[i] || rmse[i].is_nan()) && (self.row[i].is_nan() || s < self.row[i]) {
                self.row[i] = s;
            }
        }
        self.current.push(&self.row)?;
        self.next_run += 1;
        Ok(())
    }

    /// Records the Monte Carlo mean RMSE at noise scale `scale_index`.
    pub fn observe_mean(&mut self, scale_index: usize, mean_rmse: &[f64], thr: &[f64]) {
        for i in 0..self.nx {
            if mean_rmse[i] > thr[i] || mean_rmse[i].is_nan() {
                self.mc[i] = Some(self.mc[i].map_or(scale_index, |s| s.min(scale_index)));
            }
        }
    }

    /// First crossing of the mean, for state `i`.
    pub fn mc_crossing(&self, i: usize) -> Option<usize> {
        self.mc[i]
    }

    /// Calls `f(run, crossings)` for every run in order, `crossings[i]` being the first
    /// crossing of state `i` (the smallest noise-scale index), once every scale was observed.
    pub fn for_each_run(
        &mut self,
        mut f: impl FnMut(usize, &[Option<usize>]) -> Result<(), OutputError>,
    ) -> Result<(), OutputError> {
        let mut c = vec![None; self.nx];
        let mut run = 0;
        self.current.for_each_row(|row| {
            for (c, x) in c.iter_mut().zip(row) {
                *c = (!x.is_nan()).then_some(*x as usize);
            }
            f(run, &c)?;
            run += 1;
            Ok(())
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn crossings(t: &mut DivergenceTracker) -> Vec<Vec<Option<usize>>> {
        let mut v = Vec::new();
        t.for_each_run(|r, c| {
            assert_eq!(r, v.len());
            v.push(c.to_vec());
            Ok(())
        })
        .unwrap();
        v
    }

    #[test]
    fn keeps_the_smallest_crossing_whatever_the_order() {
        let dir = tempfile::tempdir().unwrap();
        let mut t = DivergenceTracker::new(dir.path(), 1);
        for (scale, rmse0) in [(5, 2.0), (3, 1.5), (1, 0.5)] {
            t.observe_run(0, scale, &[rmse0], &[1.0]).unwrap();
            t.observe_run(1, scale, &[0.5], &[1.0]).unwrap();
        }
        assert_eq!(crossings(&mut t), vec![vec![Some(3)], vec![None]]);
        t.observe_mean(4, &[1.1], &[1.0]);
        assert_eq!(t.mc_crossing(0), Some(4));
    }

    #[test]
    fn a_run_out_of_order_is_an_error_not_a_panic() {
        let dir = tempfile::tempdir().unwrap();
        let mut t = DivergenceTracker::new(dir.path(), 1);
        t.observe_run(0, 0, &[0.5], &[1.0]).unwrap();
        let err = t.observe_run(2, 0, &[0.5], &[1.0]).unwrap_err().to_string();
        assert!(
            err.contains("run 2 of noise scale 0 came where run 1 was due"),
            "{err}"
        );
    }

    /// Against a dense table of crossings, with more runs than the tracker keeps in memory
    /// (its passes go through scratch files) and failed runs (NaN).
    #[test]
    fn matches_a_dense_table_across_many_runs_and_scales() {
        let dir = tempfile::tempdir().unwrap();
        let (runs, nx, scales) = (3 * TRACKER_ROWS + 17, 2, 4);
        let mut t = DivergenceTracker::new(dir.path(), nx);
        let mut dense = vec![vec![None; nx]; runs];
        let thr = [1.0, 2.0];
        for j in 0..scales {
            for (r, d) in dense.iter_mut().enumerate() {
                let h = crate::sim::seed::mix64((r * scales + j) as u64);
                let rmse = [
                    (h % 1000) as f64 / 400.0,
                    if h.is_multiple_of(13) {
                        f64::NAN
                    } else {
                        (h >> 20) as f64 % 5.0
                    },
                ];
                for i in 0..nx {
                    if rmse[i] > thr[i] || rmse[i].is_nan() {
                        d[i] = Some(d[i].map_or(j, |s: usize| s.min(j)));
                    }
                }
                t.observe_run(r, j, &rmse, &thr).unwrap();
            }
        }
        assert_eq!(crossings(&mut t), dense);
        drop(t);
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
    }
}
