//! The drone's filters: one sequential-update EKF engine ([`SeqEkf`]) and the models it runs
//! — the paper's ([`PaperModel`]) and the principled total-state ones ([`Principled`]).
//!
//! Every measurement component is a scalar update in component order, which is the paper's
//! order (GPS position, GPS velocity, IMU position, barometer, IMU Euler angles). With the
//! diagonal R of every filter here, processing the components one at a time is the joint
//! update over the available rows (tested), and the scalar innovations divided by their
//! standard deviations are the joint innovation whitened by the Cholesky factor of S in that
//! order, so NIS and the whiteness test mean what they mean for any filter.

use super::kinematics::{d_rate_transform_times, d_rotation_times, rate_transform, rotation};
use super::world::ImuOutput;
use super::{NU, NZ, z};
use crate::filter::{CovarianceUpdate, Filter, FilterError, Innovation, check_finite};
use crate::linalg::so3::{self, ErrorSide, EulerRotation};
use crate::linalg::{Matrix, SmallCholesky, Vector, symmetrize};
use crate::model::{Availability, Measurement, Model};
use crate::trial::{Evaluate, wrap_angle};

/// A drone filter model: the [`Model`] (f, F, h, H) plus what the sequential EKF needs
/// besides: a state-dependent Q, the diagonal R, and an optional state augmentation after
/// each update (stochastic clones).
pub trait Nav<const NX: usize>: Model<NX, NU, NZ> {
    /// Q_k at the previous estimate and the IMU sample of the step.
    fn process_noise(&self, x: &Vector<NX>, u: &Vector<NU>) -> Matrix<NX, NX>;
    /// R_ii of each component; 0 for a component the filter does not use.
    fn variances(&self) -> &[f64; NZ];
    /// Covariance update form.
    fn update_form(&self) -> CovarianceUpdate;
    /// A linear re-arrangement of the state after the update of a step (x ← J x,
    /// P ← J P Jᵀ), e.g. shifting velocity clones at a GPS epoch; `None` for no change.
    fn augment(&self, _available: Availability) -> Option<Matrix<NX, NX>> {
        None
    }
}

/// The sequential-update EKF over a [`Nav`] model.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct SeqEkf;

/// Its belief: mean, covariance, and what forms the step's error transition
/// A_k = J (I − k_n h_n) ⋯ (I − k_1 h_1) F: F, the scalar updates' gains and rows, and the
/// augmentation J. A_k is formed only when asked for (the consistency tests, exports): forming
/// it every step cost one 9 × 9 product per scalar update, about a third of the step's
/// products.
#[derive(Clone, Debug, PartialEq)]
pub struct NavBelief<const NX: usize> {
    /// x̂
    pub x: Vector<NX>,
    /// P
    pub p: Matrix<NX, NX>,
    f: Matrix<NX, NX>,
    /// The first `updates` entries: each scalar update's gain k and row h, in order.
    gains: [(Vector<NX>, RowVector<NX>); NZ],
    updates: usize,
    augmentation: Option<Matrix<NX, NX>>,
}

/// A row of H.
type RowVector<const NX: usize> = nalgebra::RowSVector<f64, NX>;

impl<const NX: usize, M: Nav<NX>> Filter<NX, NU, NZ, M> for SeqEkf {
    type Belief = NavBelief<NX>;

    fn init(
        &self,
        _model: &M,
        x0_hat: &Vector<NX>,
        p0: &Matrix<NX, NX>,
        _z0: &Measurement<NZ>,
    ) -> NavBelief<NX> {
        NavBelief {
            x: *x0_hat,
            p: *p0,
            f: Matrix::<NX, NX>::identity(),
            gains: [(Vector::<NX>::zeros(), RowVector::<NX>::zeros()); NZ],
            updates: 0,
            augmentation: None,
        }
    }

    fn predict(&self, model: &M, b: &mut NavBelief<NX>, u: &Vector<NU>) -> Result<(), FilterError> {
        let f = model.transition_jacobian(&b.x, u);
        let q = model.process_noise(&b.x, u);
        b.x = model.propagate(&b.x, u);
        b.p = f * b.p * f.transpose() + q;
        b.f = f;
        b.updates = 0;
        b.augmentation = None;
        check_finite(&b.x, &b.p)
    }

    fn update(
        &self,
        model: &M,
        b: &mut NavBelief<NX>,
        u: &Vector<NU>,
        zm: &Measurement<NZ>,
    ) -> Result<Option<Innovation<NZ>>, FilterError> {
        let var = model.variances();
        let used = Availability(
            zm.available.0
                & (0..NZ)
                    .filter(|&i| var[i] > 0.0)
                    .fold(0u32, |m, i| m | 1 << i),
        );
        if b.updates > 0 || b.augmentation.is_some() {
            // An update without a prediction since the last one: its transition follows the
            // one already held.
            b.f = Filter::<NX, NU, NZ, M>::error_transition(self, b).expect("always formed");
            b.updates = 0;
            b.augmentation = None;
        }
        let mut result = None;
        if used.count() > 0 {
            let mut residual = Vector::<NZ>::zeros();
            let mut whitened = Vector::<NZ>::zeros();
            // h and H once per step at the prior mean; after each scalar update the predicted
            // measurement moves with the correction, h(x) ≈ h(x⁻) + H (x − x⁻), which is exact
            // for the linear sensors here and first order for the compensated barometer.
            let x_prior = b.x;
            let h_prior = model.measure(&b.x, u);
            let h_all = model.measurement_jacobian(&b.x, u);
            let resid = model.residual(&zm.z, &h_prior);
            for i in (0..NZ).filter(|&i| used.has(i)) {
                let h = h_all.row(i).into_owned();
                let moved = (h * (b.x - x_prior))[(0, 0)];
                let nu = resid[i] - moved;
                let ph = b.p * h.transpose();
                let s = (h * ph)[(0, 0)] + var[i];
                if !(s > 0.0 && s.is_finite()) {
                    return Err(FilterError::NotPositiveDefinite {
                        which: "innovation covariance S",
                    });
                }
                let k = ph / s;
                b.x += k * nu;
                let i_kh = Matrix::<NX, NX>::identity() - k * h;
                b.p = match model.update_form() {
                    CovarianceUpdate::Standard => i_kh * b.p,
                    CovarianceUpdate::Joseph => {
                        i_kh * b.p * i_kh.transpose() + k * k.transpose() * var[i]
                    }
                };
                b.gains[b.updates] = (k, h);
                b.updates += 1;
                residual[i] = nu;
                whitened[i] = nu / s.sqrt();
            }
            check_finite(&b.x, &b.p)?;
            result = Some(Innovation::new(residual, whitened, used));
        }
        if let Some(j) = model.augment(zm.available) {
            b.x = j * b.x;
            b.p = j * b.p * j.transpose();
            b.augmentation = Some(j);
        }
        Ok(result)
    }

    fn mean(&self, b: &NavBelief<NX>) -> Vector<NX> {
        b.x
    }

    fn covariance(&self, b: &NavBelief<NX>) -> Option<Matrix<NX, NX>> {
        Some(b.p)
    }

    fn covariance_ref<'b>(&self, b: &'b NavBelief<NX>) -> Option<&'b Matrix<NX, NX>> {
        Some(&b.p)
    }

    fn error_transition(&self, b: &NavBelief<NX>) -> Option<Matrix<NX, NX>> {
        // The products the update would have formed, in its order: the same bits.
        let mut a = b.f;
        if b.updates > 0 {
            let mut gains = Matrix::<NX, NX>::identity();
            for (k, h) in &b.gains[..b.updates] {
                gains = (Matrix::<NX, NX>::identity() - k * h) * gains;
            }
            a = gains * a;
        }
        if let Some(j) = &b.augmentation {
            a = j * a;
        }
        Some(a)
    }

    fn repair_covariance(&self, b: &mut NavBelief<NX>) -> bool {
        let sym = symmetrize(&b.p);
        let scale = (sym.trace() / NX as f64).abs().max(f64::MIN_POSITIVE);
        let mut jitter = 1e-12 * scale;
        for _ in 0..8 {
            let candidate = sym + Matrix::<NX, NX>::identity() * jitter;
            if SmallCholesky::new(&candidate).is_some() {
                b.p = candidate;
                return true;
            }
            jitter *= 100.0;
        }
        false
    }
}

/// The evaluation of a state whose first nine entries are [p, v, Θ (rad)]: the quantities
/// with the attitude in degrees, G = diag(I₆, (180/π) I₃) applied to the covariance. With
/// `rotation` set, the attitude is scored as a rotation on that side, and the Euler-angle
/// covariance is mapped into its tangent space by the chart Jacobian J at the estimate
/// (G = diag(I₆, (180/π) J)).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Degrees {
    /// How the attitude is scored: `None`, as three wrapped Euler-angle differences.
    pub rotation: Option<ErrorSide>,
}

const DEG: f64 = 180.0 / std::f64::consts::PI;

/// The drone's attitude quantities (roll, pitch, yaw in degrees, from index 6) as a rotation.
pub fn attitude(side: ErrorSide) -> EulerRotation {
    EulerRotation {
        first: 6,
        degrees: true,
        side,
    }
}

impl Degrees {
    /// The chart Jacobian of the attitude at the quantities `q` (none without rotation).
    fn chart(&self, q: &Vector<9>) -> Option<Matrix<3, 3>> {
        self.rotation
            .map(|side| attitude(side).chart_jacobian(q.as_slice()))
    }
}

impl<const NX: usize> Evaluate<NX, 9> for Degrees {
    fn mean(&self, x: &Vector<NX>) -> Vector<9> {
        Vector::<9>::from_fn(|i, _| if i < 6 { x[i] } else { x[i] * DEG })
    }
    fn covariance(&self, x: &Vector<NX>, p: &Matrix<NX, NX>) -> Matrix<9, 9> {
        let g = |i: usize| if i < 6 { 1.0 } else { DEG };
        let euler = Matrix::<9, 9>::from_fn(|i, j| p[(i, j)] * g(i) * g(j));
        match self.chart(&Evaluate::<NX, 9>::mean(self, x)) {
            None => euler,
            Some(j) => so3::transform_blocks(&euler, &[(6, j)]),
        }
    }
    fn transition(&self, a: &Matrix<NX, NX>) -> Option<Matrix<9, 9>> {
        // Only a state that is exactly the quantities has its own error transition: G A G⁻¹.
        (NX == 9).then(|| {
            let g = |i: usize| if i < 6 { 1.0 } else { DEG };
            Matrix::<9, 9>::from_fn(|i, j| a[(i, j)] * g(i) / g(j))
        })
    }
    fn transition_at(&self, x: &Vector<NX>, a: &Matrix<NX, NX>) -> Option<Matrix<9, 9>> {
        let euler = Evaluate::<NX, 9>::transition(self, a)?;
        match self.chart(&Evaluate::<NX, 9>::mean(self, x)) {
            None => Some(euler),
            Some(j) => so3::conjugate_blocks(&euler, &[(6, j)]),
        }
    }
}

fn wrap_attitude<const NZ2: usize>(z: &Vector<NZ2>, zp: &Vector<NZ2>) -> Vector<NZ2> {
    let mut r = z - zp;
    for i in z::ROLL..z::ROLL + 3 {
        r[i] = wrap_angle(r[i], false);
    }
    r
}

/// The paper's EKF model (seed §3–4): state [p, v, Θ], prediction with R and T from the
/// previous estimate, F as printed, every sensor and pseudo-measurement observed directly.
#[derive(Clone, Debug, PartialEq)]
pub struct PaperModel {
    /// Δt.
    pub dt: f64,
    /// How the IMU sample becomes the seed's body acceleration.
    pub imu: ImuOutput,
    /// g (NED).
    pub g: Vector<3>,
    /// Q per step.
    pub q: Matrix<9, 9>,
    /// R_ii per component.
    pub r: [f64; NZ],
}

impl PaperModel {
    /// The body-frame acceleration a of the seed's equations: the IMU sample when it is the
    /// seed's gravity-subtracted output, else the specific force with g removed through the
    /// filter's own attitude.
    fn body_accel(&self, x: &Vector<9>, u: &Vector<NU>) -> Vector<3> {
        let f = u.fixed_rows::<3>(0).into_owned();
        match self.imu {
            ImuOutput::GravitySubtracted => f,
            ImuOutput::SpecificForce => f + rotation(&att(x)).transpose() * self.g,
        }
    }
}

fn att<const NX: usize>(x: &Vector<NX>) -> Vector<3> {
    Vector::<3>::new(x[6], x[7], x[8])
}

impl Model<9, NU, NZ> for PaperModel {
    fn dt_s(&self) -> f64 {
        self.dt
    }
    fn propagate(&self, x: &Vector<9>, u: &Vector<NU>) -> Vector<9> {
        let dt = self.dt;
        let e = att(x);
        let ra = rotation(&e) * self.body_accel(x, u);
        let w = u.fixed_rows::<3>(3).into_owned();
        let mut y = *x;
        for i in 0..3 {
            y[i] += x[3 + i] * dt + 0.5 * ra[i] * dt * dt;
            y[3 + i] += ra[i] * dt;
        }
        let de = rate_transform(&e) * w * dt;
        for i in 0..3 {
            y[6 + i] += de[i];
        }
        y
    }
    fn transition_jacobian(&self, x: &Vector<9>, u: &Vector<NU>) -> Matrix<9, 9> {
        let dt = self.dt;
        let e = att(x);
        let w = u.fixed_rows::<3>(3).into_owned();
        let mut f = Matrix::<9, 9>::identity();
        for i in 0..3 {
            f[(i, 3 + i)] = dt;
        }
        f.fixed_view_mut::<3, 3>(3, 6)
            .copy_from(&(d_rotation_times(&e, &self.body_accel(x, u)) * dt));
        f.fixed_view_mut::<3, 3>(6, 6)
            .copy_from(&(Matrix::<3, 3>::identity() + d_rate_transform_times(&e, &w) * dt));
        f
    }
    fn measure(&self, x: &Vector<9>, _u: &Vector<NU>) -> Vector<NZ> {
        let mut h = Vector::<NZ>::zeros();
        for i in 0..3 {
            h[z::GPS_P + i] = x[i];
            h[z::GPS_V + i] = x[3 + i];
            h[z::IMU_P + i] = x[i];
            h[z::ROLL + i] = x[6 + i];
        }
        h[z::BARO] = -x[2];
        h
    }
    fn measurement_jacobian(&self, _x: &Vector<9>, _u: &Vector<NU>) -> Matrix<NZ, 9> {
        let mut h = Matrix::<NZ, 9>::zeros();
        for i in 0..3 {
            h[(z::GPS_P + i, i)] = 1.0;
            h[(z::GPS_V + i, 3 + i)] = 1.0;
            h[(z::IMU_P + i, i)] = 1.0;
            h[(z::ROLL + i, 6 + i)] = 1.0;
        }
        h[(z::BARO, 2)] = -1.0;
        h
    }
    fn residual(&self, z: &Vector<NZ>, zp: &Vector<NZ>) -> Vector<NZ> {
        wrap_attitude(z, zp)
    }
}

impl Nav<9> for PaperModel {
    fn process_noise(&self, _x: &Vector<9>, _u: &Vector<NU>) -> Matrix<9, 9> {
        self.q
    }
    fn variances(&self) -> &[f64; NZ] {
        &self.r
    }
    fn update_form(&self) -> CovarianceUpdate {
        CovarianceUpdate::Standard
    }
}

/// Where the optional states of a principled filter sit.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Augmentation {
    /// Index of the barometer-drift state (random walk), if carried.
    pub baro_drift: Option<usize>,
    /// First index of each velocity clone, oldest first: clone 0 holds v at t − L when the
    /// GPS velocity of t arrives; after the update every clone moves up one and the newest
    /// takes v_k.
    pub clones: Vec<usize>,
    /// Compensate the barometer delay D by predicting −z(t − D) from the current state.
    pub baro_delay_s: Option<f64>,
}

/// The principled total-state EKF model: the IMU is the input (v̇ = R(Θ) f + g, or R(Θ) a for
/// the seed's gravity-subtracted output; Θ̇ = T(Θ) ω), Q from the IMU noise, R from the
/// sensor values, only the real sensors, Joseph update; optionally augmented.
#[derive(Clone, Debug, PartialEq)]
pub struct Principled<const NX: usize> {
    /// Δt.
    pub dt: f64,
    /// The IMU's accelerometer channel.
    pub imu: ImuOutput,
    /// g (NED).
    pub g: Vector<3>,
    /// Accelerometer white variance per sample (already scaled).
    pub accel_var: Vector<3>,
    /// Gyro white variance per sample.
    pub gyro_var: Vector<3>,
    /// Barometer drift random-walk variance per step (with a drift state).
    pub baro_drift_var: f64,
    /// R_ii per component (0 = unused).
    pub r: [f64; NZ],
    /// Optional states.
    pub aug: Augmentation,
    /// Steps between GPS epochs (clone shifts happen there).
    pub gps_period: usize,
}

impl<const NX: usize> Principled<NX> {
    fn nav_accel(&self, x: &Vector<NX>, u: &Vector<NU>) -> Vector<3> {
        let f = u.fixed_rows::<3>(0).into_owned();
        let ra = rotation(&att(x)) * f;
        match self.imu {
            ImuOutput::SpecificForce => ra + self.g,
            ImuOutput::GravitySubtracted => ra,
        }
    }
}

impl<const NX: usize> Model<NX, NU, NZ> for Principled<NX> {
    fn dt_s(&self) -> f64 {
        self.dt
    }
    fn propagate(&self, x: &Vector<NX>, u: &Vector<NU>) -> Vector<NX> {
        let dt = self.dt;
        let a = self.nav_accel(x, u);
        let w = u.fixed_rows::<3>(3).into_owned();
        let de = rate_transform(&att(x)) * w * dt;
        let mut y = *x;
        for i in 0..3 {
            y[i] += x[3 + i] * dt + 0.5 * a[i] * dt * dt;
            y[3 + i] += a[i] * dt;
            y[6 + i] += de[i];
        }
        y
    }
    fn transition_jacobian(&self, x: &Vector<NX>, u: &Vector<NU>) -> Matrix<NX, NX> {
        let dt = self.dt;
        let e = att(x);
        let f = u.fixed_rows::<3>(0).into_owned();
        let w = u.fixed_rows::<3>(3).into_owned();
        let dra = d_rotation_times(&e, &f);
        let mut m = Matrix::<NX, NX>::identity();
        for i in 0..3 {
            m[(i, 3 + i)] = dt;
        }
        m.fixed_view_mut::<3, 3>(0, 6)
            .copy_from(&(dra * (0.5 * dt * dt)));
        m.fixed_view_mut::<3, 3>(3, 6).copy_from(&(dra * dt));
        m.fixed_view_mut::<3, 3>(6, 6)
            .copy_from(&(Matrix::<3, 3>::identity() + d_rate_transform_times(&e, &w) * dt));
        m
    }
    fn measure(&self, x: &Vector<NX>, u: &Vector<NU>) -> Vector<NZ> {
        let mut h = Vector::<NZ>::zeros();
        let v0 = self.aug.clones.first().copied().unwrap_or(3);
        for i in 0..3 {
            h[z::GPS_P + i] = x[i];
            h[z::GPS_V + i] = x[v0 + i];
        }
        let mut alt = -x[2];
        if let Some(d) = self.aug.baro_delay_s {
            // z(t − D) ≈ z − D v_z + ½ D² a_z with this step's acceleration.
            alt = -(x[2] - d * x[5] + 0.5 * d * d * self.nav_accel(x, u)[2]);
        }
        if let Some(b) = self.aug.baro_drift {
            alt += x[b];
        }
        h[z::BARO] = alt;
        h
    }
    fn measurement_jacobian(&self, x: &Vector<NX>, u: &Vector<NU>) -> Matrix<NZ, NX> {
        let mut h = Matrix::<NZ, NX>::zeros();
        let v0 = self.aug.clones.first().copied().unwrap_or(3);
        for i in 0..3 {
            h[(z::GPS_P + i, i)] = 1.0;
            h[(z::GPS_V + i, v0 + i)] = 1.0;
        }
        h[(z::BARO, 2)] = -1.0;
        if let Some(d) = self.aug.baro_delay_s {
            h[(z::BARO, 5)] = d;
            let f = u.fixed_rows::<3>(0).into_owned();
            let da = d_rotation_times(&att(x), &f);
            for j in 0..3 {
                h[(z::BARO, 6 + j)] = -0.5 * d * d * da[(2, j)];
            }
        }
        if let Some(b) = self.aug.baro_drift {
            h[(z::BARO, b)] = 1.0;
        }
        h
    }
}

impl<const NX: usize> Nav<NX> for Principled<NX> {
    fn process_noise(&self, x: &Vector<NX>, _u: &Vector<NU>) -> Matrix<NX, NX> {
        let dt = self.dt;
        // Accelerometer white noise n_a enters as R n_a: δv = R n_a Δt, δp = ½ R n_a Δt²;
        // gyro noise as δΘ = T n_g Δt.
        let e = att(x);
        let r = rotation(&e);
        let t = rate_transform(&e);
        let qa = r * Matrix::<3, 3>::from_diagonal(&self.accel_var) * r.transpose();
        let qg = t * Matrix::<3, 3>::from_diagonal(&self.gyro_var) * t.transpose();
        let mut q = Matrix::<NX, NX>::zeros();
        q.fixed_view_mut::<3, 3>(0, 0)
            .copy_from(&(qa * (dt.powi(4) / 4.0)));
        q.fixed_view_mut::<3, 3>(0, 3)
            .copy_from(&(qa * (dt.powi(3) / 2.0)));
        q.fixed_view_mut::<3, 3>(3, 0)
            .copy_from(&(qa * (dt.powi(3) / 2.0)));
        q.fixed_view_mut::<3, 3>(3, 3).copy_from(&(qa * (dt * dt)));
        q.fixed_view_mut::<3, 3>(6, 6).copy_from(&(qg * (dt * dt)));
        if let Some(b) = self.aug.baro_drift {
            q[(b, b)] = self.baro_drift_var;
        }
        q
    }
    fn variances(&self) -> &[f64; NZ] {
        &self.r
    }
    fn update_form(&self) -> CovarianceUpdate {
        CovarianceUpdate::Joseph
    }
    fn augment(&self, available: Availability) -> Option<Matrix<NX, NX>> {
        if self.aug.clones.is_empty() || !available.has(z::GPS_V) {
            return None;
        }
        let mut j = Matrix::<NX, NX>::identity();
        let c = &self.aug.clones;
        for w in 0..c.len() {
            let src = if w + 1 < c.len() { c[w + 1] } else { 3 };
            for i in 0..3 {
                j[(c[w] + i, c[w] + i)] = 0.0;
                j[(c[w] + i, src + i)] = 1.0;
            }
        }
        Some(j)
    }
}

/// The initial clone layout: every clone a copy of v (the drone hovers before t = 0, so the
/// velocities of the past are the present one).
pub fn clone_prior<const NX: usize>(
    aug: &Augmentation,
    x: &mut Vector<NX>,
    p: &mut Matrix<NX, NX>,
) {
    if aug.clones.is_empty() {
        return;
    }
    let mut j = Matrix::<NX, NX>::identity();
    for &c in &aug.clones {
        for i in 0..3 {
            j[(c + i, c + i)] = 0.0;
            j[(c + i, 3 + i)] = 1.0;
        }
    }
    *x = j * *x;
    *p = j * *p * j.transpose();
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::filter::Ekf;

    fn paper() -> PaperModel {
        let mut r = [0.0; NZ];
        for (i, v) in r.iter_mut().enumerate() {
            *v = 0.1 + 0.05 * i as f64;
        }
        PaperModel {
            dt: 0.01,
            imu: ImuOutput::GravitySubtracted,
            g: Vector::<3>::new(0.0, 0.0, 9.81),
            q: Matrix::<9, 9>::from_diagonal(&Vector::<9>::from_fn(|i, _| {
                [1e-2, 1e-1, 1e-3][i / 3]
            })),
            r,
        }
    }

    #[test]
    fn sequential_updates_equal_the_joint_update() {
        // The generic EKF's joint update over the same rows is the independent reference.
        let m = paper();
        let x0 = Vector::<9>::from_fn(|i, _| 0.1 * i as f64 - 0.3);
        let p0 = Matrix::<9, 9>::from_fn(|i, j| if i == j { 1.0 + 0.1 * i as f64 } else { 0.05 });
        let u = Vector::<6>::new(0.5, -0.2, 0.1, 0.01, 0.02, -0.03);
        let zm = Measurement {
            z: Vector::<NZ>::from_fn(|i, _| 0.2 * i as f64 - 1.0),
            available: Availability(0b1_0111_1100_0111),
        };
        let seq = SeqEkf;
        let mut a = Filter::<9, NU, NZ, PaperModel>::init(&seq, &m, &x0, &p0, &zm);
        seq.predict(&m, &mut a, &u).unwrap();
        let inn = seq.update(&m, &mut a, &u, &zm).unwrap().unwrap();
        let joint = Ekf {
            q: m.q,
            r: Matrix::<NZ, NZ>::from_diagonal(&Vector::<NZ>::from(m.r)),
            update_form: CovarianceUpdate::Standard,
        };
        let mut b = Filter::<9, NU, NZ, PaperModel>::init(&joint, &m, &x0, &p0, &zm);
        joint.predict(&m, &mut b, &u).unwrap();
        let inn_b = joint.update(&m, &mut b, &u, &zm).unwrap().unwrap();
        assert!((a.x - b.x).amax() < 1e-12, "{}", (a.x - b.x).amax());
        assert!((a.p - b.p).amax() < 1e-12);
        assert!((inn.nis - inn_b.nis).abs() < 1e-10);
        assert_eq!(inn.dof, zm.available.count());
        let ea = Filter::<9, NU, NZ, PaperModel>::error_transition(&seq, &a).unwrap();
        let eb = Filter::<9, NU, NZ, PaperModel>::error_transition(&joint, &b).unwrap();
        assert!((ea - eb).amax() < 1e-12);
    }

    #[test]
    fn clone_shift_moves_velocities_up_at_gps_epochs() {
        let m = Principled::<15> {
            dt: 0.01,
            imu: ImuOutput::SpecificForce,
            g: Vector::<3>::new(0.0, 0.0, 9.81),
            accel_var: Vector::<3>::repeat(0.5),
            gyro_var: Vector::<3>::repeat(0.005),
            baro_drift_var: 0.0,
            r: [0.0; NZ],
            aug: Augmentation {
                clones: vec![9, 12],
                ..Default::default()
            },
            gps_period: 10,
        };
        let mut x = Vector::<15>::zeros();
        for i in 0..3 {
            x[3 + i] = 1.0 + i as f64;
            x[9 + i] = 10.0 + i as f64;
            x[12 + i] = 20.0 + i as f64;
        }
        let j = m.augment(Availability(1 << z::GPS_V)).unwrap();
        let y = j * x;
        assert_eq!(y[9], 20.0);
        assert_eq!(y[12], 1.0);
        assert_eq!(y[14], 3.0);
        assert!(m.augment(Availability(1 << z::BARO)).is_none());
    }
}
