//! The full error-state filter (`kind = "error_state"`): a nominal navigation state with the
//! attitude as a rotation matrix, and a 19-state error δ = [δp, δv, δφ, δb_a, δb_g, δd, δd_b]
//! (δφ a small rotation on the NED side, C_true = exp([δφ]×) Ĉ): accelerometer and gyro
//! biases as random walks with their turn-on spread as prior, the GPS drift as the world's
//! first-order Gauss–Markov process, the barometer drift as a random walk.
//!
//! The GPS velocity latency L and the barometer delay D are compensated with the filter's own
//! motion over the last L (resp. D) seconds: v(t − L) = v(t) − Σ Δv and z(t − D) = z(t) − Σ Δz
//! over the nominal increments of that window; the window's share of the error enters the
//! measurement Jacobian to first order (δv(t − L) ≈ δv + L [Ĉ f̂]× δφ + L Ĉ δb_a,
//! δz(t − D) ≈ δz − D δv_z).
//!
//! It reports its belief as the total state [p, v, Θ, b_a, b_g, d, d_b] with the covariance
//! mapped through δΘ = E(Θ) δφ, and is scored on the nine quantities through its marginal.

use std::collections::VecDeque;

use super::filters::Degrees;
use super::kinematics::{euler_of, euler_of_nav_rotation, exp_so3, rate_transform, rotation, skew};
use super::world::{DroneParams, ImuOutput};
use super::{NQ, NU, NZ, gps_fix_prior, z};
use crate::filter::{Filter, FilterError, Innovation, check_finite};
use crate::linalg::{Matrix, Vector};
use crate::model::{Availability, Measurement, Model};
use crate::system::FilterInfo;
use crate::system::world::{NoiseSettings, Realisation, WorldFilter, WorldFilterEntry};
use crate::trial::{FilterOutput, Prior, RunContext, run_filter};

/// State size.
pub const NX: usize = 19;
const BA: usize = 9;
const BG: usize = 12;
const D: usize = 15;
const DB: usize = 18;

/// The error-state filter's settings (every variance already scaled for the cell).
#[derive(Clone, Debug, PartialEq)]
pub struct ErrorState {
    /// Δt.
    pub dt: f64,
    /// The accelerometer channel.
    pub imu: ImuOutput,
    /// g (NED).
    pub g: Vector<3>,
    /// Accelerometer white variance per sample.
    pub accel_var: Vector<3>,
    /// Gyro white variance per sample.
    pub gyro_var: Vector<3>,
    /// Accelerometer bias random-walk variance per step.
    pub accel_rw_var: Vector<3>,
    /// Gyro bias random-walk variance per step.
    pub gyro_rw_var: Vector<3>,
    /// GPS drift: e^{−Δt/τ} and the stationary variance.
    pub drift_phi: f64,
    /// Stationary GPS drift variance.
    pub drift_var: Vector<3>,
    /// Barometer drift variance per step.
    pub baro_rw_var: f64,
    /// GPS position, velocity white variances; barometer white variance.
    pub r_gps_p: Vector<3>,
    /// GPS velocity white variance.
    pub r_gps_v: Vector<3>,
    /// Barometer white variance.
    pub r_baro: f64,
    /// Latency window (steps) and delay window (steps).
    pub latency_steps: usize,
    /// Barometer delay window (steps).
    pub delay_steps: usize,
}

/// The belief: nominal state, rotation, error covariance, and the motion windows.
#[derive(Clone, Debug, PartialEq)]
pub struct EsBelief {
    x: Vector<NX>,
    c: Matrix<3, 3>,
    p: Matrix<NX, NX>,
    dv: VecDeque<Vector<3>>,
    dz: VecDeque<f64>,
}

fn v3(x: &Vector<NX>, at: usize) -> Vector<3> {
    Vector::<3>::new(x[at], x[at + 1], x[at + 2])
}

impl ErrorState {
    fn accel(&self, c: &Matrix<3, 3>, x: &Vector<NX>, u: &Vector<NU>) -> (Vector<3>, Vector<3>) {
        let f = u.fixed_rows::<3>(0).into_owned() - v3(x, BA);
        let mut a = c * f;
        if self.imu == ImuOutput::SpecificForce {
            a += self.g;
        }
        (a, f)
    }

    /// The error-state transition F over one step at the nominal state.
    pub fn error_transition(
        &self,
        c: &Matrix<3, 3>,
        x: &Vector<NX>,
        u: &Vector<NU>,
    ) -> Matrix<NX, NX> {
        let dt = self.dt;
        let (_, f) = self.accel(c, x, u);
        let da_dphi = -skew(&(c * f));
        let mut m = Matrix::<NX, NX>::identity();
        for i in 0..3 {
            m[(i, 3 + i)] = dt;
        }
        m.fixed_view_mut::<3, 3>(0, 6)
            .copy_from(&(da_dphi * (0.5 * dt * dt)));
        m.fixed_view_mut::<3, 3>(3, 6).copy_from(&(da_dphi * dt));
        m.fixed_view_mut::<3, 3>(0, BA)
            .copy_from(&(-c * (0.5 * dt * dt)));
        m.fixed_view_mut::<3, 3>(3, BA).copy_from(&(-c * dt));
        m.fixed_view_mut::<3, 3>(6, BG).copy_from(&(-c * dt));
        for i in 0..3 {
            m[(D + i, D + i)] = self.drift_phi;
        }
        m
    }

    fn process_noise(&self, c: &Matrix<3, 3>) -> Matrix<NX, NX> {
        let dt = self.dt;
        let qa = c * Matrix::<3, 3>::from_diagonal(&self.accel_var) * c.transpose();
        let qg = c * Matrix::<3, 3>::from_diagonal(&self.gyro_var) * c.transpose();
        let mut q = Matrix::<NX, NX>::zeros();
        q.fixed_view_mut::<3, 3>(0, 0)
            .copy_from(&(qa * (dt.powi(4) / 4.0)));
        q.fixed_view_mut::<3, 3>(0, 3)
            .copy_from(&(qa * (dt.powi(3) / 2.0)));
        q.fixed_view_mut::<3, 3>(3, 0)
            .copy_from(&(qa * (dt.powi(3) / 2.0)));
        q.fixed_view_mut::<3, 3>(3, 3).copy_from(&(qa * (dt * dt)));
        q.fixed_view_mut::<3, 3>(6, 6).copy_from(&(qg * (dt * dt)));
        let phi2 = self.drift_phi * self.drift_phi;
        for i in 0..3 {
            q[(BA + i, BA + i)] = self.accel_rw_var[i];
            q[(BG + i, BG + i)] = self.gyro_rw_var[i];
            q[(D + i, D + i)] = self.drift_var[i] * (1.0 - phi2);
        }
        q[(DB, DB)] = self.baro_rw_var;
        q
    }
}

/// The total-state description of the same model (Euler attitude): what the error state
/// linearises. The filter integrates the attitude on the rotation group instead and uses
/// this model's instantaneous measurement function; its Jacobian is by central differences.
impl Model<NX, NU, NZ> for ErrorState {
    fn dt_s(&self) -> f64 {
        self.dt
    }
    fn propagate(&self, x: &Vector<NX>, u: &Vector<NU>) -> Vector<NX> {
        let e = v3(x, 6);
        let (a, _) = self.accel(&rotation(&e), x, u);
        let w = u.fixed_rows::<3>(3).into_owned() - v3(x, BG);
        let de = rate_transform(&e) * w * self.dt;
        let mut y = *x;
        for i in 0..3 {
            y[i] += x[3 + i] * self.dt + 0.5 * a[i] * self.dt * self.dt;
            y[3 + i] += a[i] * self.dt;
            y[6 + i] += de[i];
            y[D + i] *= self.drift_phi;
        }
        y
    }
    fn transition_jacobian(&self, x: &Vector<NX>, u: &Vector<NU>) -> Matrix<NX, NX> {
        let mut m = Matrix::<NX, NX>::zeros();
        for j in 0..NX {
            let h = 1e-6 * x[j].abs().max(1.0);
            let (mut a, mut b) = (*x, *x);
            a[j] += h;
            b[j] -= h;
            m.set_column(
                j,
                &((self.propagate(&a, u) - self.propagate(&b, u)) / (2.0 * h)),
            );
        }
        m
    }
    fn measure(&self, x: &Vector<NX>, _u: &Vector<NU>) -> Vector<NZ> {
        let mut h = Vector::<NZ>::zeros();
        for i in 0..3 {
            h[z::GPS_P + i] = x[i] + x[D + i];
            h[z::GPS_V + i] = x[3 + i];
        }
        h[z::BARO] = -x[2] + x[DB];
        h
    }
    fn measurement_jacobian(&self, _x: &Vector<NX>, _u: &Vector<NU>) -> Matrix<NZ, NX> {
        let mut h = Matrix::<NZ, NX>::zeros();
        for i in 0..3 {
            h[(z::GPS_P + i, i)] = 1.0;
            h[(z::GPS_P + i, D + i)] = 1.0;
            h[(z::GPS_V + i, 3 + i)] = 1.0;
        }
        h[(z::BARO, 2)] = -1.0;
        h[(z::BARO, DB)] = 1.0;
        h
    }
}

/// The error-state EKF over [`ErrorState`].
#[derive(Clone, Copy, Debug, Default)]
pub struct ErrorStateEkf;

fn sync_euler(b: &mut EsBelief) {
    let e = euler_of(&b.c);
    for i in 0..3 {
        b.x[6 + i] = e[i];
    }
}

impl Filter<NX, NU, NZ, ErrorState> for ErrorStateEkf {
    type Belief = EsBelief;

    fn init(
        &self,
        m: &ErrorState,
        x0_hat: &Vector<NX>,
        p0: &Matrix<NX, NX>,
        _z0: &Measurement<NZ>,
    ) -> EsBelief {
        // P0 arrives in total-state (Euler) coordinates; the error state's is δφ = E⁻¹ δΘ.
        let e = v3(x0_hat, 6);
        let mut j = Matrix::<NX, NX>::identity();
        let inv = euler_of_nav_rotation(&e)
            .try_inverse()
            .unwrap_or_else(Matrix::<3, 3>::identity);
        j.fixed_view_mut::<3, 3>(6, 6).copy_from(&inv);
        EsBelief {
            x: *x0_hat,
            c: rotation(&e),
            p: j * p0 * j.transpose(),
            // The drone hovers before t = 0: the windows start with no motion.
            dv: std::iter::repeat_n(Vector::<3>::zeros(), m.latency_steps).collect(),
            dz: std::iter::repeat_n(0.0, m.delay_steps).collect(),
        }
    }

    fn predict(&self, m: &ErrorState, b: &mut EsBelief, u: &Vector<NU>) -> Result<(), FilterError> {
        let dt = m.dt;
        let f = m.error_transition(&b.c, &b.x, u);
        let q = m.process_noise(&b.c);
        let (a, _) = m.accel(&b.c, &b.x, u);
        let w = u.fixed_rows::<3>(3).into_owned() - v3(&b.x, BG);
        let z_before = b.x[2];
        for i in 0..3 {
            b.x[i] += b.x[3 + i] * dt + 0.5 * a[i] * dt * dt;
            b.x[3 + i] += a[i] * dt;
            b.x[D + i] *= m.drift_phi;
        }
        b.c *= exp_so3(&(w * dt));
        sync_euler(b);
        if m.latency_steps > 0 {
            b.dv.pop_front();
            b.dv.push_back(a * dt);
        }
        if m.delay_steps > 0 {
            b.dz.pop_front();
            b.dz.push_back(b.x[2] - z_before);
        }
        b.p = f * b.p * f.transpose() + q;
        check_finite(&b.x, &b.p)
    }

    fn update(
        &self,
        m: &ErrorState,
        b: &mut EsBelief,
        u: &Vector<NU>,
        zm: &Measurement<NZ>,
    ) -> Result<Option<Innovation<NZ>>, FilterError> {
        let mut used = 0u32;
        for i in (z::GPS_P..z::GPS_V + 3).chain([z::BARO]) {
            if zm.available.has(i) {
                used |= 1 << i;
            }
        }
        let used = Availability(used);
        if used.count() == 0 {
            return Ok(None);
        }
        let mut h_pred = m.measure(&b.x, u);
        let mut hm = m.measurement_jacobian(&b.x, u);
        let lat = m.latency_steps as f64 * m.dt;
        let dv: Vector<3> = b.dv.iter().sum();
        let (_, f) = m.accel(&b.c, &b.x, u);
        let cf = skew(&(b.c * f)) * lat;
        let cl = b.c * lat;
        for i in 0..3 {
            h_pred[z::GPS_V + i] -= dv[i];
            for j in 0..3 {
                hm[(z::GPS_V + i, 6 + j)] = cf[(i, j)];
                hm[(z::GPS_V + i, BA + j)] = cl[(i, j)];
            }
        }
        h_pred[z::BARO] += b.dz.iter().sum::<f64>();
        hm[(z::BARO, 5)] = m.delay_steps as f64 * m.dt;
        let var = |i: usize| match i {
            _ if i < z::GPS_V => m.r_gps_p[i - z::GPS_P],
            _ if i < z::IMU_P => m.r_gps_v[i - z::GPS_V],
            _ => m.r_baro,
        };
        let mut dx = Vector::<NX>::zeros();
        let mut residual = Vector::<NZ>::zeros();
        let mut whitened = Vector::<NZ>::zeros();
        for i in (0..NZ).filter(|&i| used.has(i)) {
            let h = hm.row(i).into_owned();
            let nu = zm.z[i] - h_pred[i];
            let ph = b.p * h.transpose();
            let s = (h * ph)[(0, 0)] + var(i);
            if !(s > 0.0 && s.is_finite()) {
                return Err(FilterError::NotPositiveDefinite {
                    which: "innovation covariance S",
                });
            }
            let k = ph / s;
            let inn = nu - (h * dx)[(0, 0)];
            dx += k * inn;
            let i_kh = Matrix::<NX, NX>::identity() - k * h;
            b.p = i_kh * b.p * i_kh.transpose() + k * k.transpose() * var(i);
            residual[i] = inn;
            whitened[i] = inn / s.sqrt();
        }
        // Inject the error into the nominal state and reset it to zero.
        for i in (0..NX).filter(|i| !(6..9).contains(i)) {
            b.x[i] += dx[i];
        }
        b.c = exp_so3(&v3(&dx, 6)) * b.c;
        sync_euler(b);
        check_finite(&b.x, &b.p)?;
        Ok(Some(Innovation::new(residual, whitened, used)))
    }

    fn mean(&self, b: &EsBelief) -> Vector<NX> {
        b.x
    }

    fn covariance(&self, b: &EsBelief) -> Option<Matrix<NX, NX>> {
        let mut j = Matrix::<NX, NX>::identity();
        j.fixed_view_mut::<3, 3>(6, 6)
            .copy_from(&euler_of_nav_rotation(&v3(&b.x, 6)));
        Some(j * b.p * j.transpose())
    }
}

/// The validated `error_state` entry.
#[derive(Debug)]
pub struct ErrorStateEntry {
    /// The world's parameters (the filter assumes them).
    pub params: DroneParams,
}

struct EsRun {
    model: ErrorState,
    params: DroneParams,
    noise_scale: f64,
    fs2: f64,
}

impl WorldFilter<NQ, NU, NZ> for EsRun {
    fn run(
        &self,
        real: &Realisation<NQ, NU, NZ>,
        ctx: &RunContext<'_, NQ, NU, NZ>,
    ) -> FilterOutput {
        let p = &self.params;
        let (x9, var9) = gps_fix_prior(real, p, self.noise_scale, self.fs2);
        let mut x0 = Vector::<NX>::zeros();
        let mut p0 = Matrix::<NX, NX>::zeros();
        for i in 0..9 {
            x0[i] = x9[i];
            p0[(i, i)] = var9[i];
        }
        for i in 0..3 {
            p0[(BA + i, BA + i)] = p.accel_bias_std[i].powi(2) * self.fs2;
            p0[(BG + i, BG + i)] = p.gyro_bias_std[i].powi(2) * self.fs2;
            // x̂_p = p + d + n with d̂ = 0: the position and drift errors are correlated.
            let dv = p.gps_drift_std[i].powi(2) * self.fs2;
            p0[(D + i, D + i)] = dv;
            p0[(i, D + i)] = -dv;
            p0[(D + i, i)] = -dv;
        }
        let prior = Prior {
            x0_hat: &x0,
            p0: &p0,
        };
        run_filter(&self.model, &ErrorStateEkf, &Degrees, &prior, ctx)
    }
}

impl WorldFilterEntry<NQ, NU, NZ> for ErrorStateEntry {
    fn info(&self) -> FilterInfo {
        FilterInfo {
            kind: "error_state".into(),
            has_covariance: true,
            q_scale: true,
            r_scale: true,
        }
    }
    fn prepare(&self, s: &NoiseSettings) -> Box<dyn WorldFilter<NQ, NU, NZ>> {
        let p = &self.params;
        let fs2 = s.filter_scale * s.filter_scale;
        let (qs, rs) = (s.q_scale, s.r_scale);
        let sq = |a: [f64; 3], k: f64| Vector::<3>::from(a).map(|x| x * x * k);
        let model = ErrorState {
            dt: p.dt_s,
            imu: p.imu_output,
            g: p.gravity(),
            accel_var: sq(p.accel_white_std, fs2 * qs),
            gyro_var: sq(p.gyro_white_std, fs2 * qs),
            accel_rw_var: sq(p.accel_bias_rw, fs2 * qs * p.dt_s),
            gyro_rw_var: sq(p.gyro_bias_rw, fs2 * qs * p.dt_s),
            drift_phi: (-p.dt_s / p.gps_drift_tau_s).exp(),
            drift_var: sq(p.gps_drift_std, fs2 * qs),
            baro_rw_var: p.baro_drift_rw.powi(2) * p.dt_s * fs2 * qs,
            r_gps_p: sq(p.gps_position_std, fs2 * rs),
            r_gps_v: sq(p.gps_velocity_std, fs2 * rs),
            r_baro: p.baro_std.powi(2) * fs2 * rs,
            latency_steps: (p.gps_velocity_latency_s / p.dt_s).round() as usize,
            delay_steps: (p.baro_delay_s / p.dt_s).round() as usize,
        };
        Box::new(EsRun {
            model,
            params: p.clone(),
            noise_scale: s.noise_scale,
            fs2,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn error_transition_matches_the_total_state_jacobian_at_level_attitude() {
        // At Θ = 0 with no net body rate the NED-side rotation error is the Euler error
        // (E = I and nothing rotates it), so the two linearisations agree.
        let p = DroneParams::default();
        let es = ErrorState {
            dt: p.dt_s,
            imu: ImuOutput::SpecificForce,
            g: p.gravity(),
            accel_var: Vector::<3>::repeat(0.5),
            gyro_var: Vector::<3>::repeat(0.005),
            accel_rw_var: Vector::<3>::zeros(),
            gyro_rw_var: Vector::<3>::zeros(),
            drift_phi: 0.99,
            drift_var: Vector::<3>::repeat(0.04),
            baro_rw_var: 0.0,
            r_gps_p: Vector::<3>::repeat(1.0),
            r_gps_v: Vector::<3>::repeat(0.02),
            r_baro: 1.0,
            latency_steps: 20,
            delay_steps: 100,
        };
        let mut x = Vector::<NX>::zeros();
        x[3] = 2.0;
        x[BA] = 0.03;
        x[BG + 2] = 0.004;
        let u = Vector::<6>::new(0.8, -0.4, -9.7, 0.0, 0.0, 0.004);
        let fe = es.error_transition(&Matrix::<3, 3>::identity(), &x, &u);
        let ft = es.transition_jacobian(&x, &u);
        let diff = (fe - ft).amax();
        assert!(diff < 1e-8, "{diff}");
        // Some entries are non-trivial (tilt couples g into velocity).
        assert!((fe[(3, 7)] + 9.7 * es.dt).abs() < 1e-3 * es.dt);
    }
}
