//! Divergence points as `robustness.m` defines them: for each state, the first noise
//! multiplier (in increasing order) whose RMSE exceeds the state's threshold — once for the
//! Monte Carlo mean RMSE and once per run, giving a distribution over runs.

/// Tracks the first crossing per (run, state) and for the Monte Carlo mean, for one
/// (scenario, filter).
#[derive(Clone, Debug, PartialEq)]
pub struct DivergenceTracker {
    nx: usize,
    /// Per run and state: index of the smallest noise scale that crossed.
    per_run: Vec<Option<usize>>,
    /// Per state: index of the smallest noise scale whose mean RMSE crossed.
    mc: Vec<Option<usize>>,
}

impl DivergenceTracker {
    /// A tracker for `runs` runs of `nx` states.
    pub fn new(runs: usize, nx: usize) -> Self {
        DivergenceTracker {
            nx,
            per_run: vec![None; runs * nx],
            mc: vec![None; nx],
        }
    }

    fn lower(slot: &mut Option<usize>, scale_index: usize) {
        *slot = Some(slot.map_or(scale_index, |s| s.min(scale_index)));
    }

    /// Records a run's RMSE at noise scale `scale_index`.
    pub fn observe_run(&mut self, run: usize, scale_index: usize, rmse: &[f64], thr: &[f64]) {
        for i in 0..self.nx {
            // NaN (a failed run) never counts as "not exceeding": treat it as a crossing.
            if rmse[i] > thr[i] || rmse[i].is_nan() {
                Self::lower(&mut self.per_run[run * self.nx + i], scale_index);
            }
        }
    }

    /// Records the Monte Carlo mean RMSE at noise scale `scale_index`.
    pub fn observe_mean(&mut self, scale_index: usize, mean_rmse: &[f64], thr: &[f64]) {
        for i in 0..self.nx {
            if mean_rmse[i] > thr[i] || mean_rmse[i].is_nan() {
                Self::lower(&mut self.mc[i], scale_index);
            }
        }
    }

    /// First crossing of the mean, for state `i`.
    pub fn mc_crossing(&self, i: usize) -> Option<usize> {
        self.mc[i]
    }

    /// First crossing of run `run`, for state `i`.
    pub fn run_crossing(&self, run: usize, i: usize) -> Option<usize> {
        self.per_run[run * self.nx + i]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keeps_the_smallest_crossing_whatever_the_order() {
        let mut t = DivergenceTracker::new(2, 1);
        t.observe_run(0, 5, &[2.0], &[1.0]);
        t.observe_run(0, 3, &[1.5], &[1.0]);
        t.observe_run(0, 1, &[0.5], &[1.0]);
        assert_eq!(t.run_crossing(0, 0), Some(3));
        assert_eq!(t.run_crossing(1, 0), None);
        t.observe_mean(4, &[1.1], &[1.0]);
        assert_eq!(t.mc_crossing(0), Some(4));
    }
}
