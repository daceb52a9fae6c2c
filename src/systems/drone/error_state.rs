//! The full error-state filter (`kind = "error_state"`): a nominal navigation state with the
//! attitude as a rotation matrix, and a 19-state error ξ = [ξ_p, ξ_v, ξ_φ, δb_a, δb_g, δd,
//! δd_b]: accelerometer and gyro biases as random walks with their turn-on spread as prior,
//! the GPS drift as the world's first-order Gauss–Markov process, the barometer drift as a
//! random walk.
//!
//! The navigation error is the left-invariant error of the invariant EKF (Barrau and
//! Bonnabel, 2017), expressed in the estimated body axes: C = Ĉ exp(\[ξ_φ\]×),
//! v − v̂ = Ĉ ξ_v, p − p̂ = Ĉ ξ_p. Its transition depends only on the bias-corrected IMU
//! samples, never on the estimated attitude. With the NED-side error δφ the transition holds
//! −\[(Ĉf)×\] and −Ĉ, which move with every correction of the heading; when the specific force
//! keeps one direction in the navigation frame (a constant acceleration, the `linear` route),
//! the rotation about that direction is unobservable, the heading error grows with the gyro
//! bias to several degrees, and an attitude-dependent transition lets the filter take the
//! changes of its own heading estimate for information about the heading: its heading
//! variance falls below what the data can give and the attitude block turns optimistic. In
//! the body-frame error the unobservable rotation stays unobservable.
//!
//! The GPS velocity latency L is handled by stochastic cloning: the state carries
//! n = ⌈L / T_gps⌉ copies of the velocity, each taken L before the GPS epoch that will report
//! it, and the GPS velocity is a measurement of the oldest copy. The copy's error keeps its
//! correlation with the rest of the state, so the accelerometer noise of the last L seconds,
//! which is in the current velocity error but not in the reported one, is accounted for. (A
//! window compensation v(t − L) ≈ v(t) − Σ Δv̂ with first-order window terms in H would leave
//! that noise out; with the default IMU it is about a third of the filter's velocity
//! variance, so such a filter is overconfident in velocity, and through the tilt coupling in
//! attitude.)
//!
//! The barometer delay D is compensated with the filter's own motion over the last D seconds,
//! z(t − D) = z(t) − Σ Δz over the nominal increments of that window, with δz(t − D) ≈
//! δz − D δv_z: the accelerometer noise of that window moves z by a variance of about
//! σ_a² Δt D³ / 3, three orders below the barometer's.
//!
//! The velocity clones are navigation-frame copies (their error is v_c − v̂_c, additive, like
//! the biases and drifts). The filter reports its belief as the total state
//! [p, v, Θ, b_a, b_g, d, d_b, clones] with its own error covariance, and is scored on the
//! nine quantities through [`EsDegrees`]: position and velocity errors Ĉ ξ, the attitude
//! error's covariance native to it as a body-side rotation error (turned to the navigation
//! axes for the left error), and mapped through δΘ = T(Θ) ξ_φ for Euler-angle errors.

use std::collections::VecDeque;

use super::filters::Degrees;
use super::kinematics::{
    euler_of, exp_so3, inverse_rate_transform, rate_transform, rotation, skew,
};
use super::world::{DroneParams, ImuOutput};
use super::{NQ, NU, NZ, gps_fix_prior, z};
use crate::filter::{Filter, FilterError, Innovation, check_finite};
use crate::linalg::so3::ErrorSide;
use crate::linalg::{Matrix, Vector};
use crate::model::{Availability, Measurement, Model};
use crate::system::FilterInfo;
use crate::system::world::{NoiseSettings, Realisation, WorldFilter, WorldFilterEntry};
use crate::trial::{Evaluate, FilterOutput, Prior, RunContext, run_filter};

/// State size without velocity clones.
pub const NX: usize = 19;
/// The most velocity clones the filter carries (a GPS velocity latency of up to this many GPS
/// periods).
pub const MAX_CLONES: usize = 3;
const BA: usize = 9;
const BG: usize = 12;
const D: usize = 15;
const DB: usize = 18;
/// First velocity clone (the oldest).
const CLONE: usize = NX;

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
    /// GPS velocity latency (steps).
    pub latency_steps: usize,
    /// Barometer delay window (steps).
    pub delay_steps: usize,
    /// Steps between GPS epochs.
    pub gps_period: usize,
}

/// Velocity clones the filter needs for a latency of `latency_steps` with GPS epochs every
/// `gps_period` steps: one per epoch whose velocity instant has passed but whose report has
/// not arrived, ⌈L / T⌉.
pub fn clones_needed(latency_steps: usize, gps_period: usize) -> usize {
    latency_steps.div_ceil(gps_period.max(1))
}

/// The belief: nominal state (with the clones' nominal velocities), rotation, error
/// covariance, the barometer's motion window, and the step count (clones are taken on a
/// schedule of steps).
#[derive(Clone, Debug, PartialEq)]
pub struct EsBelief<const N: usize> {
    x: Vector<N>,
    c: Matrix<3, 3>,
    p: Matrix<N, N>,
    dz: VecDeque<f64>,
    step: usize,
}

fn v3<const N: usize>(x: &Vector<N>, at: usize) -> Vector<3> {
    Vector::<3>::new(x[at], x[at + 1], x[at + 2])
}

/// The velocity the GPS reports on: the oldest clone, or v itself without latency.
fn reported_velocity<const N: usize>() -> usize {
    if N > NX { CLONE } else { 3 }
}

/// The re-arrangement that drops the oldest clone, moves every other one up and copies the
/// velocity into the newest: of the nominal state (a copy) and of the error (P ← J P Jᵀ with
/// J this matrix: the newest clone's error v − v̂ = Ĉ ξ_v, exact to first order).
fn clone_shift<const N: usize>(c: &Matrix<3, 3>) -> Matrix<N, N> {
    let mut j = Matrix::<N, N>::identity();
    let mut at = CLONE;
    while at < N {
        for i in 0..3 {
            j[(at + i, at + i)] = 0.0;
        }
        if at + 3 < N {
            for i in 0..3 {
                j[(at + i, at + 3 + i)] = 1.0;
            }
        } else {
            j.fixed_view_mut::<3, 3>(at, 3).copy_from(c);
        }
        at += 3;
    }
    j
}

/// The same re-arrangement of the nominal state: the clones move up and the newest is the
/// current velocity.
fn shift_clones<const N: usize>(x: &mut Vector<N>) {
    let mut at = CLONE;
    while at < N {
        let src = if at + 3 < N { at + 3 } else { 3 };
        for i in 0..3 {
            x[at + i] = x[src + i];
        }
        at += 3;
    }
}

/// The right Jacobian of SO(3) at θ: exp(θ + δ) ≈ exp(θ) exp(J_r(θ) δ).
fn right_jacobian(theta: &Vector<3>) -> Matrix<3, 3> {
    let a = theta.norm();
    let k = skew(theta);
    if a < 1e-6 {
        return Matrix::<3, 3>::identity() - k * 0.5 + k * k * (1.0 / 6.0);
    }
    Matrix::<3, 3>::identity() - k * ((1.0 - a.cos()) / (a * a))
        + k * k * ((a - a.sin()) / (a * a * a))
}

impl ErrorState {
    fn accel<const N: usize>(
        &self,
        c: &Matrix<3, 3>,
        x: &Vector<N>,
        u: &Vector<NU>,
    ) -> (Vector<3>, Vector<3>) {
        let f = u.fixed_rows::<3>(0).into_owned() - v3(x, BA);
        let mut a = c * f;
        if self.imu == ImuOutput::SpecificForce {
            a += self.g;
        }
        (a, f)
    }

    /// The error-state transition F over one step (the clones are constant). With the
    /// bias-corrected IMU sample f̂ = f_m − b̂_a, ω̂ = ω_m − b̂_g and Γ = exp(\[ω̂\]× Δt):
    ///
    /// ```text
    /// ξ_φ' = Γᵀ ξ_φ − J_r(ω̂Δt) Δt δb_g
    /// ξ_v' = Γᵀ (ξ_v − Δt [f̂×] ξ_φ − Δt δb_a)
    /// ξ_p' = Γᵀ (ξ_p + Δt ξ_v − ½Δt² [f̂×] ξ_φ − ½Δt² δb_a)
    /// ```
    ///
    /// (the first-order expansion of the nominal step of `predict` about the estimate; it does
    /// not depend on the estimated attitude).
    pub fn error_transition<const N: usize>(&self, x: &Vector<N>, u: &Vector<NU>) -> Matrix<N, N> {
        let dt = self.dt;
        let f = u.fixed_rows::<3>(0).into_owned() - v3(x, BA);
        let theta = (u.fixed_rows::<3>(3).into_owned() - v3(x, BG)) * dt;
        let gt = exp_so3(&theta).transpose();
        let gfx = gt * skew(&f);
        let mut m = Matrix::<N, N>::identity();
        m.fixed_view_mut::<3, 3>(0, 0).copy_from(&gt);
        m.fixed_view_mut::<3, 3>(0, 3).copy_from(&(gt * dt));
        m.fixed_view_mut::<3, 3>(0, 6)
            .copy_from(&(gfx * (-0.5 * dt * dt)));
        m.fixed_view_mut::<3, 3>(0, BA)
            .copy_from(&(gt * (-0.5 * dt * dt)));
        m.fixed_view_mut::<3, 3>(3, 3).copy_from(&gt);
        m.fixed_view_mut::<3, 3>(3, 6).copy_from(&(gfx * -dt));
        m.fixed_view_mut::<3, 3>(3, BA).copy_from(&(gt * -dt));
        m.fixed_view_mut::<3, 3>(6, 6).copy_from(&gt);
        m.fixed_view_mut::<3, 3>(6, BG)
            .copy_from(&(right_jacobian(&theta) * -dt));
        for i in 0..3 {
            m[(D + i, D + i)] = self.drift_phi;
        }
        m
    }

    /// Q over one step: the IMU's white noise enters where the biases do (body axes), the
    /// random walks and the drift as their own.
    fn process_noise<const N: usize>(&self, x: &Vector<N>, u: &Vector<NU>) -> Matrix<N, N> {
        let dt = self.dt;
        let theta = (u.fixed_rows::<3>(3).into_owned() - v3(x, BG)) * dt;
        let gt = exp_so3(&theta).transpose();
        let jr = right_jacobian(&theta);
        let qa = gt * Matrix::<3, 3>::from_diagonal(&self.accel_var) * gt.transpose();
        let qg = jr * Matrix::<3, 3>::from_diagonal(&self.gyro_var) * jr.transpose();
        let mut q = Matrix::<N, N>::zeros();
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

/// The map from the filter's error to the navigation frame's: the identity except Ĉ on the
/// position and velocity errors (and `attitude` on the rotation error's).
fn to_navigation<const N: usize>(c: &Matrix<3, 3>, attitude: &Matrix<3, 3>) -> Matrix<N, N> {
    let mut g = Matrix::<N, N>::identity();
    g.fixed_view_mut::<3, 3>(0, 0).copy_from(c);
    g.fixed_view_mut::<3, 3>(3, 3).copy_from(c);
    g.fixed_view_mut::<3, 3>(6, 6).copy_from(attitude);
    g
}

/// The total-state description of the same model (Euler attitude): what the error state
/// linearises. The filter integrates the attitude on the rotation group instead and uses
/// this model's measurement function; its Jacobian is by central differences.
impl<const N: usize> Model<N, NU, NZ> for ErrorState {
    fn dt_s(&self) -> f64 {
        self.dt
    }
    fn propagate(&self, x: &Vector<N>, u: &Vector<NU>) -> Vector<N> {
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
    fn transition_jacobian(&self, x: &Vector<N>, u: &Vector<NU>) -> Matrix<N, N> {
        let mut m = Matrix::<N, N>::zeros();
        for j in 0..N {
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
    fn measure(&self, x: &Vector<N>, _u: &Vector<NU>) -> Vector<NZ> {
        let mut h = Vector::<NZ>::zeros();
        let v = reported_velocity::<N>();
        for i in 0..3 {
            h[z::GPS_P + i] = x[i] + x[D + i];
            h[z::GPS_V + i] = x[v + i];
        }
        h[z::BARO] = -x[2] + x[DB];
        h
    }
    fn measurement_jacobian(&self, _x: &Vector<N>, _u: &Vector<NU>) -> Matrix<NZ, N> {
        let mut h = Matrix::<NZ, N>::zeros();
        let v = reported_velocity::<N>();
        for i in 0..3 {
            h[(z::GPS_P + i, i)] = 1.0;
            h[(z::GPS_P + i, D + i)] = 1.0;
            h[(z::GPS_V + i, v + i)] = 1.0;
        }
        h[(z::BARO, 2)] = -1.0;
        h[(z::BARO, DB)] = 1.0;
        h
    }
}

/// The error-state EKF over [`ErrorState`].
#[derive(Clone, Copy, Debug, Default)]
pub struct ErrorStateEkf;

fn sync_euler<const N: usize>(b: &mut EsBelief<N>) {
    let e = euler_of(&b.c);
    for i in 0..3 {
        b.x[6 + i] = e[i];
    }
}

impl<const N: usize> Filter<N, NU, NZ, ErrorState> for ErrorStateEkf {
    type Belief = EsBelief<N>;

    fn init(
        &self,
        m: &ErrorState,
        x0_hat: &Vector<N>,
        p0: &Matrix<N, N>,
        _z0: &Measurement<NZ>,
    ) -> EsBelief<N> {
        // P0 arrives in total-state coordinates (NED position and velocity, Euler angles):
        // ξ_p = Ĉᵀ δp, ξ_v = Ĉᵀ δv and the body-side rotation ξ_φ = T(Θ)⁻¹ δΘ.
        let e = v3(x0_hat, 6);
        let c = rotation(&e);
        let ct = c.transpose();
        let j = to_navigation::<N>(&ct, &inverse_rate_transform(&e));
        EsBelief {
            x: *x0_hat,
            c,
            p: j * p0 * j.transpose(),
            // The drone hovers before t = 0: the window starts with no motion.
            dz: std::iter::repeat_n(0.0, m.delay_steps).collect(),
            step: 0,
        }
    }

    fn predict(
        &self,
        m: &ErrorState,
        b: &mut EsBelief<N>,
        u: &Vector<NU>,
    ) -> Result<(), FilterError> {
        let dt = m.dt;
        let f = m.error_transition(&b.x, u);
        let q = m.process_noise(&b.x, u);
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
        b.step += 1;
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
        b: &mut EsBelief<N>,
        u: &Vector<NU>,
        zm: &Measurement<NZ>,
    ) -> Result<Option<Innovation<NZ>>, FilterError> {
        let innovation = self.update_sensors(m, b, u, zm)?;
        // After the update of the step whose velocity a later epoch reports (t = s + L), the
        // oldest clone has been used and the current velocity becomes the newest.
        if N > NX && (b.step + m.latency_steps).is_multiple_of(m.gps_period.max(1)) {
            let j = clone_shift::<N>(&b.c);
            shift_clones(&mut b.x);
            b.p = j * b.p * j.transpose();
        }
        Ok(innovation)
    }

    fn mean(&self, b: &EsBelief<N>) -> Vector<N> {
        b.x
    }

    fn covariance(&self, b: &EsBelief<N>) -> Option<Matrix<N, N>> {
        Some(b.p)
    }
}

/// The error-state filter's evaluation: position and velocity errors Ĉ ξ_p, Ĉ ξ_v; its
/// rotation error ξ_φ (C = Ĉ exp(\[ξ_φ\]×), the right error) is the attitude quantities'
/// error as it stands for a right rotation error, turned to the navigation axes (Ĉ ξ_φ) for
/// the left one, and mapped by T(Θ̂) for Euler-angle errors.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct EsDegrees {
    /// How the attitude is scored: `None`, as three wrapped Euler-angle differences.
    pub rotation: Option<ErrorSide>,
}

impl<const N: usize> Evaluate<N, NQ> for EsDegrees {
    fn mean(&self, x: &Vector<N>) -> Vector<NQ> {
        Evaluate::<N, NQ>::mean(&Degrees::default(), x)
    }
    fn covariance(&self, x: &Vector<N>, p: &Matrix<N, N>) -> Matrix<NQ, NQ> {
        let e = v3(x, 6);
        let c = rotation(&e);
        let attitude = match self.rotation {
            None => rate_transform(&e),
            Some(ErrorSide::Left) => c,
            Some(ErrorSide::Right) => Matrix::<3, 3>::identity(),
        };
        let g = to_navigation::<NQ>(&c, &attitude);
        let nav = g * p.fixed_view::<NQ, NQ>(0, 0) * g.transpose();
        let x9 = x.fixed_rows::<NQ>(0).into_owned();
        // Radians to the quantities' degrees; the attitude is already in its scored chart.
        Evaluate::<NQ, NQ>::covariance(&Degrees::default(), &x9, &nav)
    }
    fn transition(&self, _a: &Matrix<N, N>) -> Option<Matrix<NQ, NQ>> {
        // A marginal of the larger error state does not evolve on its own.
        None
    }
}

impl ErrorStateEkf {
    /// The sequential scalar updates with the GPS and the barometer, and the injection.
    fn update_sensors<const N: usize>(
        &self,
        m: &ErrorState,
        b: &mut EsBelief<N>,
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
        let mut h_pred = Model::<N, NU, NZ>::measure(m, &b.x, u);
        let mut hm = Model::<N, NU, NZ>::measurement_jacobian(m, &b.x, u);
        h_pred[z::BARO] += b.dz.iter().sum::<f64>();
        hm[(z::BARO, 5)] = m.delay_steps as f64 * m.dt;
        // The Jacobian in navigation-frame errors, then in the filter's: δp = Ĉ ξ_p, δv = Ĉ ξ_v.
        let hm = hm * to_navigation::<N>(&b.c, &Matrix::<3, 3>::identity());
        let var = |i: usize| match i {
            _ if i < z::GPS_V => m.r_gps_p[i - z::GPS_P],
            _ if i < z::IMU_P => m.r_gps_v[i - z::GPS_V],
            _ => m.r_baro,
        };
        let mut dx = Vector::<N>::zeros();
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
            let i_kh = Matrix::<N, N>::identity() - k * h;
            b.p = i_kh * b.p * i_kh.transpose() + k * k.transpose() * var(i);
            residual[i] = inn;
            whitened[i] = inn / s.sqrt();
        }
        // Inject the error into the nominal state and reset it to zero: X̂ ← X̂ exp(ξ) on the
        // navigation states (to first order in ξ_v, ξ_p), additively on the others.
        let (dp, dv) = (b.c * v3(&dx, 0), b.c * v3(&dx, 3));
        for i in 0..3 {
            b.x[i] += dp[i];
            b.x[3 + i] += dv[i];
        }
        for i in 9..N {
            b.x[i] += dx[i];
        }
        b.c *= exp_so3(&v3(&dx, 6));
        sync_euler(b);
        check_finite(&b.x, &b.p)?;
        Ok(Some(Innovation::new(residual, whitened, used)))
    }
}

/// The validated `error_state` entry.
#[derive(Debug)]
pub struct ErrorStateEntry {
    /// The world's parameters (the filter assumes them).
    pub params: DroneParams,
}

impl ErrorStateEntry {
    /// The GPS velocity latency in steps.
    pub fn latency_steps(&self) -> usize {
        (self.params.gps_velocity_latency_s / self.params.dt_s).round() as usize
    }

    /// Velocity clones the world's latency needs.
    pub fn clones(&self) -> usize {
        clones_needed(self.latency_steps(), self.params.gps_period())
    }

    fn build<const N: usize>(
        &self,
        model: ErrorState,
        s: &NoiseSettings,
    ) -> Box<dyn WorldFilter<NQ, NU, NZ>> {
        Box::new(EsRun::<N> {
            model,
            params: self.params.clone(),
            noise_scale: s.noise_scale,
            fs2: s.filter_scale * s.filter_scale,
        })
    }
}

/// The filter with `N − 19` state entries of velocity clones (three per clone).
struct EsRun<const N: usize> {
    model: ErrorState,
    params: DroneParams,
    noise_scale: f64,
    fs2: f64,
}

impl<const N: usize> WorldFilter<NQ, NU, NZ> for EsRun<N> {
    fn run(
        &self,
        real: &Realisation<NQ, NU, NZ>,
        ctx: &RunContext<'_, NQ, NU, NZ>,
    ) -> FilterOutput {
        let p = &self.params;
        let (x9, var9) = gps_fix_prior(real, p, self.noise_scale, self.fs2);
        let mut x0 = Vector::<N>::zeros();
        let mut p0 = Matrix::<N, N>::zeros();
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
        // The drone hovers before t = 0, so every clone is the initial velocity: the same
        // estimate with the same error (x ← J x, P ← J P Jᵀ with the clone rows copying v).
        let mut j = Matrix::<N, N>::identity();
        for at in (CLONE..N).step_by(3) {
            for i in 0..3 {
                j[(at + i, at + i)] = 0.0;
                j[(at + i, 3 + i)] = 1.0;
            }
        }
        x0 = j * x0;
        p0 = j * p0 * j.transpose();
        let prior = Prior {
            x0_hat: &x0,
            p0: &p0,
        };
        let eval = EsDegrees {
            rotation: self.params.attitude_error,
        };
        run_filter(&self.model, &ErrorStateEkf, &eval, &prior, ctx)
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
            latency_steps: self.latency_steps(),
            delay_steps: (p.baro_delay_s / p.dt_s).round() as usize,
            gps_period: p.gps_period(),
        };
        match self.clones() {
            0 => self.build::<NX>(model, s),
            1 => self.build::<{ NX + 3 }>(model, s),
            2 => self.build::<{ NX + 6 }>(model, s),
            // Validation refuses more than MAX_CLONES.
            _ => self.build::<{ NX + 3 * MAX_CLONES }>(model, s),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The filter's settings for the unit tests (biases' random walks off).
    fn model(latency_steps: usize, delay_steps: usize, gps_period: usize) -> ErrorState {
        let p = DroneParams::default();
        ErrorState {
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
            latency_steps,
            delay_steps,
            gps_period,
        }
    }

    /// The true state X̂ exp(ξ) of a nominal state (rotation `c`, state `x`) and an error ξ
    /// of the first 19 entries: rotation, and the state vector with p, v, biases and drifts.
    fn perturbed(c: &Matrix<3, 3>, x: &Vector<NX>, xi: &Vector<NX>) -> (Matrix<3, 3>, Vector<NX>) {
        let mut y = *x;
        let (dp, dv) = (c * v3(xi, 0), c * v3(xi, 3));
        for i in 0..3 {
            y[i] += dp[i];
            y[3 + i] += dv[i];
        }
        for i in 9..NX {
            y[i] += xi[i];
        }
        (c * exp_so3(&v3(xi, 6)), y)
    }

    /// One noise-free step of the nominal equations of `predict` (rotation, state).
    fn step(
        m: &ErrorState,
        c: &Matrix<3, 3>,
        x: &Vector<NX>,
        u: &Vector<NU>,
    ) -> (Matrix<3, 3>, Vector<NX>) {
        let (a, _) = m.accel(c, x, u);
        let w = u.fixed_rows::<3>(3).into_owned() - v3(x, BG);
        let mut y = *x;
        for i in 0..3 {
            y[i] += x[3 + i] * m.dt + 0.5 * a[i] * m.dt * m.dt;
            y[3 + i] += a[i] * m.dt;
            y[D + i] *= m.drift_phi;
        }
        (c * exp_so3(&(w * m.dt)), y)
    }

    /// The error ξ of a true state (rotation `ct`, state `xt`) against a nominal one: the
    /// inverse of [`perturbed`].
    fn error_of(
        c: &Matrix<3, 3>,
        x: &Vector<NX>,
        ct: &Matrix<3, 3>,
        xt: &Vector<NX>,
    ) -> Vector<NX> {
        let mut xi = xt - x;
        let (dp, dv) = (c.transpose() * v3(&xi, 0), c.transpose() * v3(&xi, 3));
        let phi = crate::linalg::so3::log(&(c.transpose() * ct));
        for i in 0..3 {
            xi[i] = dp[i];
            xi[3 + i] = dv[i];
            xi[6 + i] = phi[i];
        }
        xi
    }

    #[test]
    fn error_transition_is_the_derivative_of_the_nominal_step() {
        // At a tilted, turning attitude with biases: perturb the nominal state by ±h along
        // each error direction, take both through the nominal step and read the error after
        // it; the central difference is the transition's column.
        let m = model(20, 100, 10);
        let mut x = Vector::<NX>::zeros();
        x[3] = 12.0;
        x[4] = -3.0;
        x[BA] = 0.03;
        x[BA + 2] = -0.02;
        x[BG + 2] = 0.004;
        x[D] = 0.3;
        let c = rotation(&Vector::<3>::new(0.3, -0.2, 1.1));
        let u = Vector::<6>::new(0.8, -0.4, -9.7, 0.3, -0.2, 0.5);
        let f = m.error_transition(&x, &u);
        let (c1, x1) = step(&m, &c, &x, &u);
        let h = 1e-6;
        let mut worst = 0.0f64;
        for j in 0..NX {
            let mut e = Vector::<NX>::zeros();
            e[j] = h;
            let (ca, xa) = perturbed(&c, &x, &e);
            let (cb, xb) = perturbed(&c, &x, &(-e));
            let (ca, xa) = step(&m, &ca, &xa, &u);
            let (cb, xb) = step(&m, &cb, &xb, &u);
            let col = (error_of(&c1, &x1, &ca, &xa) - error_of(&c1, &x1, &cb, &xb)) / (2.0 * h);
            worst = worst.max((col - f.column(j)).amax());
        }
        assert!(worst < 1e-8, "{worst}");
        // The tilt couples the specific force into velocity: −[f̂×] Δt.
        let fb = u.fixed_rows::<3>(0).into_owned() - v3(&x, BA);
        assert!(
            (f[(3, 7)] - fb[2] * m.dt).abs() < 1e-3 * fb[2].abs() * m.dt,
            "{}",
            f[(3, 7)]
        );
    }

    #[test]
    fn the_covariance_propagates_the_same_whatever_the_estimated_attitude() {
        // Two beliefs with the same covariance, biases and IMU samples but attitude estimates
        // 30° of heading and a few degrees of tilt apart: the propagated covariances are the
        // same, so a correction of the heading estimate cannot change what the filter believes
        // it knows about the heading. (With the navigation-side error the transition holds
        // −[(Ĉf)×] and −Ĉ, and they differ.)
        use rand::SeedableRng;
        use rand_distr::{Distribution, StandardNormal};
        let m = model(20, 100, 10);
        let mut x = Vector::<NX>::zeros();
        x[BA] = 0.02;
        x[BG + 2] = 0.003;
        let p0 =
            Matrix::<NX, NX>::from_diagonal(&Vector::<NX>::from_fn(|i, _| 0.01 + 0.001 * i as f64));
        let none = Measurement {
            z: Vector::<NZ>::zeros(),
            available: Availability(0),
        };
        let f = ErrorStateEkf;
        let mut a: EsBelief<NX> = f.init(&m, &x, &p0, &none);
        x[6] = 3f64.to_radians();
        x[7] = -2f64.to_radians();
        x[8] = 30f64.to_radians();
        let mut b: EsBelief<NX> = f.init(&m, &x, &p0, &none);
        b.p = a.p;
        let mut rng = rand_pcg::Pcg64::seed_from_u64(8);
        for _ in 0..200 {
            let mut u = Vector::<6>::new(1.0, 0.15, -9.79, 0.0, 0.0, 0.0);
            for i in 0..6 {
                let s: f64 = StandardNormal.sample(&mut rng);
                u[i] += s * if i < 3 { 0.72 } else { 0.071 };
            }
            f.predict(&m, &mut a, &u).unwrap();
            f.predict(&m, &mut b, &u).unwrap();
        }
        assert_eq!(a.p, b.p);
        assert!(a.c != b.c);
    }

    #[test]
    fn measurement_jacobian_is_the_derivative_of_the_prediction() {
        // The rows the update uses (navigation-frame H times the map of the filter's error),
        // against central differences of the predicted GPS and barometer readings.
        let m = model(0, 100, 10);
        let mut x = Vector::<NX>::zeros();
        x[2] = -100.0;
        x[3] = 12.0;
        x[5] = -1.5;
        x[D + 1] = 0.2;
        let c = rotation(&Vector::<3>::new(0.2, 0.1, -2.0));
        let u = Vector::<6>::zeros();
        // The barometer reads −z(t − D) ≈ −z + D v_z (the window's nominal motion is a
        // constant of the update): its sensitivity to the current error.
        let predict = |x: &Vector<NX>| {
            let mut h = Model::<NX, NU, NZ>::measure(&m, x, &u);
            h[z::BARO] += m.delay_steps as f64 * m.dt * x[5];
            h
        };
        let mut hm = Model::<NX, NU, NZ>::measurement_jacobian(&m, &x, &u);
        hm[(z::BARO, 5)] = m.delay_steps as f64 * m.dt;
        let hm = hm * to_navigation::<NX>(&c, &Matrix::<3, 3>::identity());
        let h = 1e-6;
        for j in 0..NX {
            let mut e = Vector::<NX>::zeros();
            e[j] = h;
            let (_, xa) = perturbed(&c, &x, &e);
            let (_, xb) = perturbed(&c, &x, &(-e));
            let col = (predict(&xa) - predict(&xb)) / (2.0 * h);
            for i in (z::GPS_P..z::GPS_V + 3).chain([z::BARO]) {
                assert!(
                    (col[i] - hm[(i, j)]).abs() < 1e-7,
                    "row {i}, column {j}: {} against {}",
                    col[i],
                    hm[(i, j)]
                );
            }
        }
    }

    /// Runs the filter without measurements under a constant acceleration and checks, at every
    /// GPS epoch t before its update, that the oldest clone holds the velocity of t − L (the
    /// initial velocity for t − L ≤ 0, as the drone hovers before t = 0).
    fn clone_schedule<const N: usize>(latency_steps: usize, gps_period: usize) {
        assert_eq!(N, NX + 3 * clones_needed(latency_steps, gps_period));
        let p = DroneParams::default();
        let m = model(latency_steps, 0, gps_period);
        let mut x0 = Vector::<N>::zeros();
        for at in std::iter::once(3).chain((CLONE..N).step_by(3)) {
            x0[at] = 1.0;
        }
        let p0 = Matrix::<N, N>::identity() * 1e-4;
        let none = Measurement {
            z: Vector::<NZ>::zeros(),
            available: Availability(0),
        };
        let f = ErrorStateEkf;
        let mut b: EsBelief<N> = f.init(&m, &x0, &p0, &none);
        // Specific force cancelling gravity plus 0.5 m/s² north: v_x(k) = 1 + 0.005 k.
        let u = Vector::<6>::new(0.5, 0.0, -p.gravity_m_s2, 0.0, 0.0, 0.0);
        let mut v = vec![1.0];
        for k in 1..=70 {
            f.predict(&m, &mut b, &u).unwrap();
            if k % gps_period == 0 {
                let want = if latency_steps == 0 {
                    b.x[3]
                } else {
                    v[k.saturating_sub(latency_steps)]
                };
                let got = Model::<N, NU, NZ>::measure(&m, &b.x, &u)[z::GPS_V];
                assert!(
                    (got - want).abs() < 1e-12,
                    "L = {latency_steps}, T = {gps_period}, epoch {k}: {got} against {want}"
                );
            }
            assert!(f.update(&m, &mut b, &u, &none).unwrap().is_none());
            v.push(b.x[3]);
        }
        assert!((v[70] - 1.35).abs() < 1e-12);
    }

    #[test]
    fn the_gps_velocity_reads_the_clone_taken_one_latency_before_its_epoch() {
        assert_eq!(clones_needed(0, 10), 0);
        assert_eq!(clones_needed(5, 10), 1);
        assert_eq!(clones_needed(10, 10), 1);
        assert_eq!(clones_needed(20, 10), 2);
        assert_eq!(clones_needed(25, 10), 3);
        clone_schedule::<NX>(0, 10);
        clone_schedule::<{ NX + 3 }>(5, 10);
        clone_schedule::<{ NX + 3 }>(10, 10);
        clone_schedule::<{ NX + 6 }>(20, 10);
        clone_schedule::<{ NX + 9 }>(25, 10);
        clone_schedule::<{ NX + 6 }>(7, 5);
    }
}
