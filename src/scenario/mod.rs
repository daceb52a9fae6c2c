//! The scenario role: initial state, control profile, duration.
//!
//! A [`Scenario`] is model-agnostic data (x0 and the control sequence u_0..u_K); each system builds its
//! own (the planar thrust profiles live in the planar system).

use crate::linalg::Vector;

/// One scenario: where the truth starts and the control applied at every step.
#[derive(Clone, Debug, PartialEq)]
pub struct Scenario<const NX: usize, const NU: usize> {
    /// Name used in the tables' `scenario` column and in seeding.
    pub name: String,
    /// True initial state x_0.
    pub x0: Vector<NX>,
    /// u_0 … u_K; u_k drives the transition from k−1 to k.
    pub controls: Vec<Vector<NU>>,
}

impl<const NX: usize, const NU: usize> Scenario<NX, NU> {
    /// Number of transitions K (the trajectory has K + 1 samples, k = 0..=K).
    pub fn steps(&self) -> usize {
        self.controls.len().saturating_sub(1)
    }

    /// A scenario with zero input for `steps` transitions (the L1 studies: the truth is
    /// driven by process noise alone).
    pub fn unforced(name: &str, x0: Vector<NX>, steps: usize) -> Self {
        Scenario {
            name: name.to_string(),
            x0,
            controls: vec![Vector::<NU>::zeros(); steps + 1],
        }
    }
}
