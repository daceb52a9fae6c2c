//! The drone's world: the seed's rigid body flying a route, and its IMU, GPS and barometer.
//!
//! Truth is closed-form (every route is a net acceleration a(t) that integrates exactly, and
//! the attitude is an explicit Θ(t) whose body rates are ω = T(Θ)⁻¹ Θ̇), so the truth has no
//! discretisation error of its own and the delayed sensors can read it at any past instant.
//! The drone hovers at rest at the start point for t < 0.

use rand_distr::{Distribution, StandardNormal};
use rand_pcg::Pcg64;

use super::kinematics::{Euler, inverse_rate_transform, rate_transform, rotation};
use super::{NQ, NU, NZ, z};
use crate::linalg::Vector;
use crate::linalg::so3::ErrorSide;
use crate::model::{Availability, Measurement};
use crate::sim::seed::world_stream;
use crate::system::world::{Realisation, World};
use crate::trial::wrap_angle;

/// What the IMU's accelerometer channel reports.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ImuOutput {
    /// The real specific force f = Rᵀ(a − g).
    SpecificForce,
    /// The seed's "gravity-subtracted" acceleration Rᵀa, formed with the *true* attitude.
    GravitySubtracted,
}

/// Every parameter of the world (defaults: the calibration of seed 004's drone, as the systems chapter of the docs lists it).
#[derive(Clone, Debug, PartialEq)]
pub struct DroneParams {
    /// Step Δt (the IMU's sample time).
    pub dt_s: f64,
    /// g, along +z (down).
    pub gravity_m_s2: f64,
    /// Accelerometer channel.
    pub imu_output: ImuOutput,
    /// Accelerometer white noise per sample, per axis (m/s²).
    pub accel_white_std: [f64; 3],
    /// Accelerometer turn-on bias σ (m/s²).
    pub accel_bias_std: [f64; 3],
    /// Accelerometer bias random walk (m/s²/√s).
    pub accel_bias_rw: [f64; 3],
    /// Gyro white noise per sample (rad/s).
    pub gyro_white_std: [f64; 3],
    /// Gyro turn-on bias σ (rad/s).
    pub gyro_bias_std: [f64; 3],
    /// Gyro bias random walk (rad/s/√s).
    pub gyro_bias_rw: [f64; 3],
    /// GPS rate (Hz).
    pub gps_rate_hz: f64,
    /// GPS position white noise (m).
    pub gps_position_std: [f64; 3],
    /// GPS Gauss–Markov drift, stationary σ (m).
    pub gps_drift_std: [f64; 3],
    /// Its correlation time τ (s).
    pub gps_drift_tau_s: f64,
    /// GPS velocity white noise (m/s).
    pub gps_velocity_std: [f64; 3],
    /// GPS velocity latency: the velocity reported at t is v(t − L).
    pub gps_velocity_latency_s: f64,
    /// Barometer rate (Hz).
    pub baro_rate_hz: f64,
    /// Barometer altitude white noise (m).
    pub baro_std: f64,
    /// Barometer random-walk drift (m/√s), from 0 at t = 0.
    pub baro_drift_rw: f64,
    /// Barometer delay D: the altitude reported at t is −z(t − D).
    pub baro_delay_s: f64,
    /// The error of the attitude the principled filters start from, σ per angle (deg).
    pub initial_attitude_std_deg: [f64; 3],
    /// How the filters' attitude is scored (`model.attitude_error`; not part of the world):
    /// as a rotation error on this side, or, with `None`, as three wrapped Euler-angle
    /// differences.
    pub attitude_error: Option<ErrorSide>,
}

impl Default for DroneParams {
    fn default() -> Self {
        DroneParams {
            dt_s: 0.01,
            gravity_m_s2: 9.81,
            imu_output: ImuOutput::GravitySubtracted,
            accel_white_std: [0.72; 3],
            accel_bias_std: [0.037; 3],
            accel_bias_rw: [0.002; 3],
            gyro_white_std: [0.071; 3],
            gyro_bias_std: [0.0060; 3],
            gyro_bias_rw: [2e-4; 3],
            gps_rate_hz: 10.0,
            gps_position_std: [1.09, 1.09, 3.19],
            gps_drift_std: [0.20, 0.20, 0.40],
            gps_drift_tau_s: 60.0,
            gps_velocity_std: [0.147, 0.147, 0.183],
            gps_velocity_latency_s: 0.20,
            baro_rate_hz: 50.0,
            baro_std: 1.06,
            baro_drift_rw: 0.05,
            baro_delay_s: 1.0,
            initial_attitude_std_deg: [1.0, 1.0, 2.0],
            attitude_error: Some(ErrorSide::Right),
        }
    }
}

impl DroneParams {
    /// Steps between GPS epochs.
    pub fn gps_period(&self) -> usize {
        (1.0 / (self.gps_rate_hz * self.dt_s)).round() as usize
    }
    /// Steps between barometer epochs.
    pub fn baro_period(&self) -> usize {
        (1.0 / (self.baro_rate_hz * self.dt_s)).round() as usize
    }
    /// g as a NED vector.
    pub fn gravity(&self) -> Vector<3> {
        Vector::<3>::new(0.0, 0.0, self.gravity_m_s2)
    }
}

/// A route: net acceleration a_i(t) = c0_i + c1_i t + A_i cos(2πt/T_i) for t ≥ 0 and an
/// attitude Θ_j(t) = Θ0_j + B_j (1 − cos(2πt/P_j)) / 2 (zero rates at t = 0, as at hover, which
/// holds the attitude Θ0).
#[derive(Clone, Debug, PartialEq)]
pub struct Route {
    /// Start position (NED, m).
    pub start_m: [f64; 3],
    /// c0 (m/s²).
    pub accel_m_s2: [f64; 3],
    /// c1 (m/s³).
    pub jerk_m_s3: [f64; 3],
    /// A (m/s²).
    pub wave_m_s2: [f64; 3],
    /// T (s); the wave term is absent where A = 0.
    pub wave_period_s: [f64; 3],
    /// B (rad): peak-to-peak roll, pitch, yaw.
    pub attitude_rad: [f64; 3],
    /// P (s).
    pub attitude_period_s: [f64; 3],
    /// Θ0 (rad): the attitude held at hover, to which the swing adds.
    pub attitude_offset_rad: [f64; 3],
}

/// One instant of the truth.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct State {
    /// Position (NED, m).
    pub p: Vector<3>,
    /// Velocity (m/s).
    pub v: Vector<3>,
    /// Net acceleration (m/s²).
    pub a: Vector<3>,
    /// Attitude (rad).
    pub euler: Euler,
    /// Body rates (rad/s).
    pub omega: Vector<3>,
}

impl Route {
    /// The built-in routes: the seed's R1–R3 and a route with attitude motion.
    pub fn builtin(name: &str) -> Option<Route> {
        let base = Route {
            start_m: [0.0, 0.0, -100.0],
            accel_m_s2: [0.0; 3],
            jerk_m_s3: [0.0; 3],
            wave_m_s2: [0.0; 3],
            wave_period_s: [1.0; 3],
            attitude_rad: [0.0; 3],
            attitude_period_s: [1.0; 3],
            attitude_offset_rad: [0.0; 3],
        };
        Some(match name {
            "linear" => Route {
                accel_m_s2: [1.00, 0.15, 0.02],
                ..base
            },
            "sinusoidal" => Route {
                accel_m_s2: [0.0, 0.0, 0.095],
                wave_m_s2: [0.65, 1.25, 0.0],
                wave_period_s: [20.0, 10.0, 1.0],
                ..base
            },
            "ramp" => Route {
                jerk_m_s3: [0.0835, 0.038, 0.0238],
                ..base
            },
            "maneuver" => Route {
                accel_m_s2: [0.0, 0.0, 0.095],
                wave_m_s2: [0.65, 1.25, 0.0],
                wave_period_s: [20.0, 10.0, 1.0],
                attitude_rad: [20f64.to_radians(), 15f64.to_radians(), 90f64.to_radians()],
                attitude_period_s: [8.0, 12.0, 20.0],
                ..base
            },
            _ => return None,
        })
    }

    /// The truth at time t (hover at the start point before 0).
    pub fn at(&self, t: f64) -> State {
        let p0 = Vector::<3>::from(self.start_m);
        if t <= 0.0 {
            return State {
                p: p0,
                v: Vector::<3>::zeros(),
                a: Vector::<3>::zeros(),
                euler: Euler::from(self.attitude_offset_rad),
                omega: Vector::<3>::zeros(),
            };
        }
        let (mut p, mut v, mut a) = (p0, Vector::<3>::zeros(), Vector::<3>::zeros());
        for i in 0..3 {
            let (c0, c1, aw) = (self.accel_m_s2[i], self.jerk_m_s3[i], self.wave_m_s2[i]);
            let w = 2.0 * std::f64::consts::PI / self.wave_period_s[i];
            a[i] = c0 + c1 * t;
            v[i] = c0 * t + c1 * t * t / 2.0;
            p[i] += c0 * t * t / 2.0 + c1 * t.powi(3) / 6.0;
            if aw != 0.0 {
                a[i] += aw * (w * t).cos();
                v[i] += aw * (w * t).sin() / w;
                p[i] += aw * (1.0 - (w * t).cos()) / (w * w);
            }
        }
        let (mut euler, mut rates) = (Euler::from(self.attitude_offset_rad), Vector::<3>::zeros());
        for j in 0..3 {
            let b = self.attitude_rad[j];
            if b != 0.0 {
                let w = 2.0 * std::f64::consts::PI / self.attitude_period_s[j];
                let swing = b * (1.0 - (w * t).cos()) / 2.0;
                // Without an offset the swing alone, so that its sign (−0 at rest) is kept.
                euler[j] = if euler[j] == 0.0 {
                    swing
                } else {
                    euler[j] + swing
                };
                rates[j] = b * w * (w * t).sin() / 2.0;
            }
        }
        State {
            p,
            v,
            a,
            omega: inverse_rate_transform(&euler) * rates,
            euler,
        }
    }
}

/// One scenario: a route and its length.
#[derive(Clone, Debug, PartialEq)]
pub struct DroneScenario {
    /// Name.
    pub name: String,
    /// The route.
    pub route: Route,
    /// Transitions K.
    pub steps: usize,
    /// Which of the seed's tables (1–3) the paper filter's R comes from.
    pub seed_table: usize,
}

/// The world of the drone system.
#[derive(Clone, Debug)]
pub struct DroneWorld {
    /// Parameters.
    pub params: DroneParams,
    /// Scenarios, in spec order.
    pub scenarios: Vec<DroneScenario>,
}

/// Names of the world states recorded per step (trace columns `world_<name>`).
pub const WORLD_STATES: [&str; 10] = [
    "accel_bias_x",
    "accel_bias_y",
    "accel_bias_z",
    "gyro_bias_x",
    "gyro_bias_y",
    "gyro_bias_z",
    "gps_drift_x",
    "gps_drift_y",
    "gps_drift_z",
    "baro_drift",
];

/// Number of standard normals in [`Realisation::prior_draws`]: the initial attitude error.
pub const PRIOR_DRAWS: usize = 3;

fn n(r: &mut Pcg64) -> f64 {
    StandardNormal.sample(r)
}

/// The sensor-table rows: each raw sensor and pseudo-measurement against the truth,
/// natively (at its own instants) and on the 100 Hz grid the seed interpolated onto.
pub fn sensor_metric_names() -> Vec<String> {
    let mut v = Vec::new();
    for (sensor, comps) in [
        ("gps", ["px", "py", "pz"]),
        ("gps", ["vx", "vy", "vz"]),
        ("baro", ["pz", "", ""]),
    ] {
        for c in comps.iter().filter(|c| !c.is_empty()) {
            for proto in ["native", "grid"] {
                v.push(format!("{sensor}_{c}_{proto}"));
            }
        }
    }
    for c in ["px", "py", "pz", "roll", "pitch", "yaw"] {
        v.push(format!("imu_{c}"));
    }
    for c in [
        "accel_x", "accel_y", "accel_z", "gyro_x", "gyro_y", "gyro_z",
    ] {
        v.push(c.to_string());
    }
    v
}

/// The grid protocol: every sensor linearly interpolated onto every step between its own
/// instants, as the seed did; between epochs k0 < k < k1 this reads the measurement of k1,
/// which lies in the future of k. Beyond the last epoch the last value is held.
pub fn grid(measurements: &[Measurement<NZ>]) -> Vec<Measurement<NZ>> {
    let mut out: Vec<Measurement<NZ>> = measurements.to_vec();
    for i in 0..NZ {
        let epochs: Vec<usize> = (0..measurements.len())
            .filter(|&k| measurements[k].available.has(i))
            .collect();
        let Some(&first) = epochs.first() else {
            continue;
        };
        for (k, m) in out.iter_mut().enumerate() {
            let j = epochs.partition_point(|&e| e <= k);
            let value = if k < first {
                measurements[first].z[i]
            } else if j == epochs.len() {
                measurements[epochs[j - 1]].z[i]
            } else {
                let (k0, k1) = (epochs[j - 1], epochs[j]);
                let s = (k - k0) as f64 / (k1 - k0) as f64;
                let (z0, z1) = (measurements[k0].z[i], measurements[k1].z[i]);
                if (z::ROLL..z::ROLL + 3).contains(&i) {
                    z0 + s * wrap_angle(z1 - z0, false)
                } else {
                    z0 + s * (z1 - z0)
                }
            };
            m.z[i] = value;
        }
    }
    for m in &mut out {
        m.available = Availability::all(NZ);
    }
    out
}

impl DroneWorld {
    fn simulate_scenario(
        &self,
        scenario: usize,
        noise_scale: f64,
        seed: u64,
    ) -> (Realisation<NQ, NU, NZ>, Vec<State>, Vec<Vector<6>>) {
        let pr = &self.params;
        let sc = &self.scenarios[scenario];
        let dt = pr.dt_s;
        let g = pr.gravity();
        let s = noise_scale;
        let mut accel_rng = world_stream(seed, 0);
        let mut gyro_rng = world_stream(seed, 1);
        let mut accel_bias_rng = world_stream(seed, 2);
        let mut gyro_bias_rng = world_stream(seed, 3);
        let mut gps_pos_rng = world_stream(seed, 4);
        let mut gps_vel_rng = world_stream(seed, 5);
        let mut gps_drift_rng = world_stream(seed, 6);
        let mut baro_rng = world_stream(seed, 7);
        let mut baro_drift_rng = world_stream(seed, 8);
        let mut prior_rng = world_stream(seed, 9);

        let v3 = |a: [f64; 3]| Vector::<3>::from(a) * s;
        let mut ba = v3(pr.accel_bias_std)
            .component_mul(&Vector::<3>::from_fn(|_, _| n(&mut accel_bias_rng)));
        let mut bg =
            v3(pr.gyro_bias_std).component_mul(&Vector::<3>::from_fn(|_, _| n(&mut gyro_bias_rng)));
        let mut drift =
            v3(pr.gps_drift_std).component_mul(&Vector::<3>::from_fn(|_, _| n(&mut gps_drift_rng)));
        let phi = (-dt / pr.gps_drift_tau_s).exp();
        let drift_step = v3(pr.gps_drift_std) * (1.0 - phi * phi).sqrt();
        let mut baro_drift = 0.0;
        let (gps_period, baro_period) = (pr.gps_period(), pr.baro_period());

        let k_max = sc.steps;
        let mut real = Realisation {
            prior_draws: (0..PRIOR_DRAWS).map(|_| n(&mut prior_rng)).collect(),
            scenario,
            ..Default::default()
        };
        let mut truth = Vec::with_capacity(k_max + 1);
        let mut clean_imu = Vec::with_capacity(k_max + 1);
        // Strapdown pseudo-measurements, from the true start.
        let start = sc.route.at(0.0);
        let (mut ip, mut iv, mut ie) = (start.p, start.v, start.euler);
        for k in 0..=k_max {
            let t = k as f64 * dt;
            let st = sc.route.at(t);
            if k > 0 {
                let rw = dt.sqrt() * s;
                for i in 0..3 {
                    ba[i] += pr.accel_bias_rw[i] * rw * n(&mut accel_bias_rng);
                    bg[i] += pr.gyro_bias_rw[i] * rw * n(&mut gyro_bias_rng);
                    drift[i] = phi * drift[i] + drift_step[i] * n(&mut gps_drift_rng);
                }
                baro_drift += pr.baro_drift_rw * rw * n(&mut baro_drift_rng);
            }
            let r_true = rotation(&st.euler);
            let f_clean = match pr.imu_output {
                ImuOutput::SpecificForce => r_true.transpose() * (st.a - g),
                ImuOutput::GravitySubtracted => r_true.transpose() * st.a,
            };
            let clean = Vector::<6>::new(
                f_clean[0],
                f_clean[1],
                f_clean[2],
                st.omega[0],
                st.omega[1],
                st.omega[2],
            );
            let mut u = clean;
            for i in 0..3 {
                u[i] += ba[i] + pr.accel_white_std[i] * s * n(&mut accel_rng);
                u[3 + i] += bg[i] + pr.gyro_white_std[i] * s * n(&mut gyro_rng);
            }
            if k > 0 {
                let fm = u.fixed_rows::<3>(0).into_owned();
                let wm = u.fixed_rows::<3>(3).into_owned();
                let mut a_nav = rotation(&ie) * fm;
                if pr.imu_output == ImuOutput::SpecificForce {
                    a_nav += g;
                }
                ip += iv * dt + a_nav * (dt * dt / 2.0);
                iv += a_nav * dt;
                ie += rate_transform(&ie) * wm * dt;
            }
            let mut m = Measurement {
                z: Vector::<NZ>::zeros(),
                available: Availability(0),
            };
            let mut set = |i: usize, v: f64| {
                m.z[i] = v;
                m.available.0 |= 1 << i;
            };
            if k % gps_period == 0 {
                let late = sc.route.at(t - pr.gps_velocity_latency_s);
                for i in 0..3 {
                    set(
                        z::GPS_P + i,
                        st.p[i] + drift[i] + pr.gps_position_std[i] * s * n(&mut gps_pos_rng),
                    );
                    set(
                        z::GPS_V + i,
                        late.v[i] + pr.gps_velocity_std[i] * s * n(&mut gps_vel_rng),
                    );
                }
            }
            for i in 0..3 {
                set(z::IMU_P + i, ip[i]);
                set(z::ROLL + i, ie[i]);
            }
            if k % baro_period == 0 {
                let old = sc.route.at(t - pr.baro_delay_s);
                set(
                    z::BARO,
                    -old.p[2] + baro_drift + pr.baro_std * s * n(&mut baro_rng),
                );
            }
            real.truth.push(quantities(&st));
            real.inputs.push(u);
            real.measurements.push(m);
            real.world
                .extend(ba.iter().chain(bg.iter()).chain(drift.iter()));
            real.world.push(baro_drift);
            truth.push(st);
            clean_imu.push(clean);
        }
        (real, truth, clean_imu)
    }
}

/// The evaluated quantities of a truth state: p, v, and the attitude in degrees.
pub fn quantities(st: &State) -> Vector<NQ> {
    let mut q = Vector::<NQ>::zeros();
    q.fixed_rows_mut::<3>(0).copy_from(&st.p);
    q.fixed_rows_mut::<3>(3).copy_from(&st.v);
    for j in 0..3 {
        q[6 + j] = wrap_angle(st.euler[j].to_degrees(), true);
    }
    q
}

fn rms(sum: f64, n: usize) -> f64 {
    if n == 0 {
        f64::NAN
    } else {
        (sum / n as f64).sqrt()
    }
}

/// The sensor table's values for one realisation (in [`sensor_metric_names`] order).
fn sensor_metrics(
    real: &Realisation<NQ, NU, NZ>,
    truth: &[State],
    clean_imu: &[Vector<6>],
) -> Vec<f64> {
    let grid_z = grid(&real.measurements);
    let err = |m: &Measurement<NZ>, i: usize, st: &State| -> f64 {
        match i {
            _ if (z::GPS_P..z::GPS_P + 3).contains(&i) => m.z[i] - st.p[i - z::GPS_P],
            _ if (z::GPS_V..z::GPS_V + 3).contains(&i) => m.z[i] - st.v[i - z::GPS_V],
            _ if (z::IMU_P..z::IMU_P + 3).contains(&i) => m.z[i] - st.p[i - z::IMU_P],
            z::BARO => -m.z[i] - st.p[2],
            _ => wrap_angle((m.z[i] - st.euler[i - z::ROLL]).to_degrees(), true),
        }
    };
    let rmse = |ms: &[Measurement<NZ>], i: usize| {
        let (mut s, mut c) = (0.0, 0usize);
        for (m, st) in ms.iter().zip(truth) {
            if m.available.has(i) {
                let e = err(m, i, st);
                s += e * e;
                c += 1;
            }
        }
        rms(s, c)
    };
    let mut out = Vec::new();
    for i in (z::GPS_P..z::GPS_P + 3)
        .chain(z::GPS_V..z::GPS_V + 3)
        .chain([z::BARO])
    {
        out.push(rmse(&real.measurements, i));
        out.push(rmse(&grid_z, i));
    }
    for i in (z::IMU_P..z::IMU_P + 3).chain(z::ROLL..z::ROLL + 3) {
        out.push(rmse(&real.measurements, i));
    }
    // IMU samples drive steps 1..=K; the one at step 0 is never used.
    for c in 0..6 {
        let s: f64 = real.inputs[1..]
            .iter()
            .zip(&clean_imu[1..])
            .map(|(u, c0)| (u[c] - c0[c]).powi(2))
            .sum();
        out.push(rms(s, real.inputs.len() - 1));
    }
    out
}

impl World<NQ, NU, NZ> for DroneWorld {
    fn simulate(&self, scenario: usize, noise_scale: f64, seed: u64) -> Realisation<NQ, NU, NZ> {
        let (mut real, truth, clean) = self.simulate_scenario(scenario, noise_scale, seed);
        real.metrics = sensor_metrics(&real, &truth, &clean);
        real
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn routes_integrate_exactly() {
        // Central differences of the closed forms recover v and a; hover before t = 0.
        for name in ["linear", "sinusoidal", "ramp", "maneuver"] {
            let r = Route::builtin(name).unwrap();
            for &t in &[0.5, 3.0, 11.7, 19.9] {
                let h = 1e-4;
                let (a, b, c) = (r.at(t - h), r.at(t), r.at(t + h));
                assert!(
                    ((c.p - a.p) / (2.0 * h) - b.v).amax() < 1e-6,
                    "{name} v at {t}"
                );
                assert!(
                    ((c.v - a.v) / (2.0 * h) - b.a).amax() < 1e-6,
                    "{name} a at {t}"
                );
                let rates = (c.euler - a.euler) / (2.0 * h);
                assert!((rate_transform(&b.euler) * b.omega - rates).amax() < 1e-6);
            }
            assert_eq!(r.at(-0.3).p, Vector::<3>::new(0.0, 0.0, -100.0));
        }
        // R1 by hand: p(20) = p0 + ½ a 20².
        let p = Route::builtin("linear").unwrap().at(20.0).p;
        assert!((p - Vector::<3>::new(200.0, 30.0, -96.0)).amax() < 1e-9);
    }

    #[test]
    fn grid_interpolates_between_epochs_and_reads_the_future() {
        let mut ms = vec![
            Measurement {
                z: Vector::<NZ>::zeros(),
                available: Availability(0),
            };
            21
        ];
        ms[0].z[0] = 1.0;
        ms[0].available = Availability(1);
        ms[10].z[0] = 3.0;
        ms[10].available = Availability(1);
        let g = grid(&ms);
        assert_eq!(g[0].z[0], 1.0);
        assert!((g[5].z[0] - 2.0).abs() < 1e-15);
        assert!((g[9].z[0] - 2.8).abs() < 1e-15);
        assert_eq!(g[20].z[0], 3.0);
    }
}
