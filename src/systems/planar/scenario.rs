//! The four planar-quadrotor scenarios of `Planar_Quadrotor.m` as *data*: staged thrusts with
//! the small cos/sin ripple, so a spec can also define its own.
//!
//! u_k = thrust_stage(k) ⊙ (1 + a·[cos(ω t_k), sin(ω t_k)]), t_k = k·Δt, a = 0.001, ω = 2 rad/s.
//!
//! Where the seed's prose and code disagree the code wins, because the code is what
//! produced the seed's figures:
//! * `fall`: the prose says 3.2 N per rotor, the code uses `u · 0.54` = 2.7 N;
//! * `roll`, stage 3 (`t = 300:500`) lasts 201 samples (2.01 s), not 2 s; stage 4 starts at
//!   k = 501;
//! * `horizontal`, the last loop runs to `length(time)` and so writes one element past the end
//!   (MATLAB grows the array); the extra sample is never used.

use crate::linalg::Vector;
use crate::scenario::Scenario;

/// A constant-thrust stage starting at a step index.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ThrustStage {
    /// First step k of the stage (the stage lasts until the next one starts).
    pub from_step: usize,
    /// Base thrusts `[u1, u2]` in N.
    pub thrust_n: [f64; 2],
}

/// A staged thrust profile with the seeds' periodic ripple.
#[derive(Clone, Debug, PartialEq)]
pub struct ThrustProfile {
    /// Stages in increasing `from_step`; the first starts at 0.
    pub stages: Vec<ThrustStage>,
    /// Relative ripple amplitude a (0.001 in the seeds).
    pub ripple: f64,
    /// Ripple angular frequency ω in rad/s (2 in the seeds).
    pub ripple_rad_s: f64,
}

/// A planar scenario definition before it is expanded into a control sequence.
#[derive(Clone, Debug, PartialEq)]
pub struct PlanarScenarioDef {
    /// Name.
    pub name: String,
    /// Initial state `[x, ẋ, y, ẏ, θ, θ̇]`.
    pub x0: [f64; 6],
    /// Duration in seconds (10 in the seeds: 1001 samples at Δt = 0.01).
    pub duration_s: f64,
    /// The thrust profile.
    pub profile: ThrustProfile,
}

/// Names of the built-in planar scenarios.
pub const BUILTIN_PLANAR: [&str; 4] = ["basic", "horizontal", "roll", "fall"];

fn stages(list: &[(usize, f64, f64)]) -> Vec<ThrustStage> {
    list.iter()
        .map(|&(from_step, u1, u2)| ThrustStage {
            from_step,
            thrust_n: [u1, u2],
        })
        .collect()
}

/// One of the seeds' four scenarios by name, exactly as `Planar_Quadrotor.m` codes it.
pub fn builtin(name: &str) -> Option<PlanarScenarioDef> {
    // u1 = u2 = 5 N nominal; each factor multiplies it first, as MATLAB evaluates `u1 * 0.81 * (…)`.
    let u = 5.0;
    let pi = std::f64::consts::PI;
    let (x0, st) = match name {
        "basic" => (
            [0.0, 0.0, 1.0, 0.0, 0.0, 0.0],
            stages(&[(0, u * 0.6, u * 0.6)]),
        ),
        "horizontal" => (
            [0.0, 3.0, 10.0, 0.0, -pi / 2.0, 0.0],
            stages(&[
                (0, u * 0.81, u * 0.8),
                (110, u * 0.8, u * 0.81),
                (220, u * 0.8, u * 0.8),
            ]),
        ),
        "roll" => (
            [0.0, 0.0, 50.0, 5.0, 0.0, 0.0],
            stages(&[
                (0, u * 0.808, u * 0.8),
                (200, u * 0.0, u * 0.0),
                (300, u * 0.0, u * 0.008),
                (501, u, u),
            ]),
        ),
        "fall" => (
            [
                0.0,
                -1.0,
                15.0,
                -3.0,
                -(pi / 2.0 - (3.0f64 / 1.0).atan()),
                0.0,
            ],
            stages(&[(0, u * 0.54, u * 0.54)]),
        ),
        _ => return None,
    };
    Some(PlanarScenarioDef {
        name: name.to_string(),
        x0,
        duration_s: 10.0,
        profile: ThrustProfile {
            stages: st,
            ripple: 0.001,
            ripple_rad_s: 2.0,
        },
    })
}

impl PlanarScenarioDef {
    /// Number of transitions K for a sample time: `round(duration / Δt)`.
    pub fn steps(&self, dt_s: f64) -> usize {
        (self.duration_s / dt_s).round() as usize
    }

    /// Expands the profile into u_0..u_K at sample time `dt_s`.
    pub fn expand(&self, dt_s: f64) -> Scenario<6, 2> {
        let k_max = self.steps(dt_s);
        let p = &self.profile;
        let mut stage = 0;
        let controls = (0..=k_max)
            .map(|k| {
                while stage + 1 < p.stages.len() && p.stages[stage + 1].from_step <= k {
                    stage += 1;
                }
                let base = p.stages[stage].thrust_n;
                let t = k as f64 * dt_s;
                let w = p.ripple_rad_s * t;
                Vector::<2>::new(
                    base[0] * (1.0 + p.ripple * w.cos()),
                    base[1] * (1.0 + p.ripple * w.sin()),
                )
            })
            .collect();
        Scenario {
            name: self.name.clone(),
            x0: Vector::<6>::from_column_slice(&self.x0),
            controls,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn roll_profile_stages_at_the_seed_indices() {
        let s = builtin("roll").unwrap().expand(0.01);
        assert_eq!(s.controls.len(), 1001);
        let ripple = |k: usize, f: fn(f64) -> f64| 1.0 + 0.001 * f(2.0 * k as f64 * 0.01);
        assert!((s.controls[199][0] - 4.04 * ripple(199, f64::cos)).abs() < 1e-12);
        assert_eq!(s.controls[200], Vector::<2>::zeros());
        assert_eq!(s.controls[299], Vector::<2>::zeros());
        assert_eq!(s.controls[300][0], 0.0);
        assert!((s.controls[500][1] - 0.04 * ripple(500, f64::sin)).abs() < 1e-15);
        assert!((s.controls[501][0] - 5.0 * ripple(501, f64::cos)).abs() < 1e-12);
    }

    #[test]
    fn fall_uses_the_coded_thrust_not_the_prose() {
        let s = builtin("fall").unwrap().expand(0.01);
        assert!((s.controls[0][0] - 2.7 * 1.001).abs() < 1e-12); // cos 0 = 1
        assert!((s.controls[0][1] - 2.7).abs() < 1e-12); // sin 0 = 0
    }
}
