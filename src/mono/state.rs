//! The camera state and its constant-velocity motion model (thesis eq. 2.29-2.32, app. A).
//!
//! State: position `r` (m, world), orientation `q` (`world_from_camera`), linear velocity
//! `v` (m/s, world) and angular velocity `w` (rad/s, world). The error state is 12-dimensional,
//! `[dr, dtheta, dv, dw]`, with the rotation error in so(3) on the left (world frame):
//! `R = exp([dtheta]x) R_hat`.
//!
//! Motion: `r' = r + v dt`, `q' = exp(w dt) q`, `v' = v`, `w' = w`, driven by white linear and
//! angular accelerations (`sigma_a`, `sigma_alpha`). The error dynamics are
//! `d(dr)/dt = dv`, `d(dtheta)/dt = w x dtheta + dw`, `d(dv)/dt = n_a`, `d(dw)/dt = n_alpha`,
//! whose exact transition over `dt` is
//! `F = [[I, 0, dt I, 0], [0, R_dt, 0, dt J_l(w dt)], [0, 0, I, 0], [0, 0, 0, I]]`
//! (`R_dt = exp([w dt]x)`, `J_l` the left Jacobian of SO(3)), and the discrete noise
//! `Q = integral_0^dt Phi(s) G Q_c G^T Phi(s)^T ds`: for the translation part
//! `sigma_a^2 [[dt^3/3, dt^2/2], [dt^2/2, dt]] (x) I`, for the rotation part
//! `Q_tt = sigma_alpha^2 dt^3 / 3 I`, `Q_tw = sigma_alpha^2 (dt^2/2 I + dt^3/6 [w]x)`,
//! `Q_ww = sigma_alpha^2 dt I` (the S integrals in closed form to second order in `|w| dt`;
//! the first-order terms of `Q_tt` cancel exactly).

use glam::{DMat3, DQuat, DVec3};
use nalgebra::SMatrix;

use crate::geometry::{skew, so3_exp, Se3};

/// Size of the camera error state.
pub const CAMERA_DIM: usize = 12;

/// A 12x12 matrix over the camera error state.
pub type Mat12 = SMatrix<f64, 12, 12>;

/// The camera part of the filter state.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CameraState {
    /// Position of the camera centre in the filter world frame, metres (up to scale).
    pub position: DVec3,
    /// Orientation `world_from_camera` (unit quaternion).
    pub rotation: DQuat,
    /// Linear velocity, world frame, m/s.
    pub velocity: DVec3,
    /// Angular velocity, world frame, rad/s.
    pub angular_velocity: DVec3,
}

impl Default for CameraState {
    fn default() -> Self {
        CameraState {
            position: DVec3::ZERO,
            rotation: DQuat::IDENTITY,
            velocity: DVec3::ZERO,
            angular_velocity: DVec3::ZERO,
        }
    }
}

/// Left Jacobian of SO(3) at rotation vector `phi` (radians).
pub fn so3_left_jacobian(phi: DVec3) -> DMat3 {
    let t = phi.length();
    let k = skew(phi);
    if t < 1e-6 {
        return DMat3::IDENTITY + 0.5 * k + (1.0 / 6.0) * k * k;
    }
    let t2 = t * t;
    DMat3::IDENTITY + ((1.0 - t.cos()) / t2) * k + ((t - t.sin()) / (t2 * t)) * k * k
}

impl CameraState {
    /// The pose `world_from_camera`.
    pub fn world_from_camera(&self) -> Se3 {
        Se3::new(self.rotation, self.position)
    }

    /// The state after `dt` seconds of constant velocity.
    pub fn predicted(&self, dt: f64) -> CameraState {
        CameraState {
            position: self.position + self.velocity * dt,
            rotation: (so3_exp(self.angular_velocity * dt) * self.rotation).normalize(),
            velocity: self.velocity,
            angular_velocity: self.angular_velocity,
        }
    }

    /// Applies an error-state correction `[dr, dtheta, dv, dw]` (rotation on the manifold).
    pub fn corrected(&self, dx: &[f64]) -> CameraState {
        let v = |i: usize| DVec3::new(dx[i], dx[i + 1], dx[i + 2]);
        CameraState {
            position: self.position + v(0),
            rotation: (so3_exp(v(3)) * self.rotation).normalize(),
            velocity: self.velocity + v(6),
            angular_velocity: self.angular_velocity + v(9),
        }
    }

    /// The error-state transition `F` over `dt` seconds, evaluated at this (prior) state.
    pub fn transition(&self, dt: f64) -> Mat12 {
        let mut f = Mat12::identity();
        let phi = self.angular_velocity * dt;
        let r = DMat3::from_quat(so3_exp(phi));
        let j = so3_left_jacobian(phi) * dt;
        for a in 0..3 {
            f[(a, 6 + a)] = dt;
            for b in 0..3 {
                f[(3 + a, 3 + b)] = r.col(b)[a];
                f[(3 + a, 9 + b)] = j.col(b)[a];
            }
        }
        f
    }

    /// The discrete process noise `Q` over `dt` seconds (see the module docs).
    pub fn process_noise(&self, dt: f64, sigma_a: f64, sigma_alpha: f64) -> Mat12 {
        let mut q = Mat12::zeros();
        let (sa, sw) = (sigma_a * sigma_a, sigma_alpha * sigma_alpha);
        let (dt2, dt3) = (dt * dt, dt * dt * dt);
        let wx = skew(self.angular_velocity);
        for a in 0..3 {
            q[(a, a)] = sa * dt3 / 3.0;
            q[(a, 6 + a)] = sa * dt2 / 2.0;
            q[(6 + a, a)] = sa * dt2 / 2.0;
            q[(6 + a, 6 + a)] = sa * dt;
            q[(3 + a, 3 + a)] = sw * dt3 / 3.0;
            q[(9 + a, 9 + a)] = sw * dt;
            for b in 0..3 {
                let i = if a == b { 1.0 } else { 0.0 };
                let tw = sw * (dt2 / 2.0 * i + dt3 / 6.0 * wx.col(b)[a]);
                q[(3 + a, 9 + b)] = tw;
                q[(9 + b, 3 + a)] = tw;
            }
        }
        q
    }
}

#[cfg(test)]
/// Error-state difference `b - a` (`[dr, dtheta, dv, dw]`, rotation on the left), the
/// inverse of [`CameraState::corrected`].
pub fn error_between(a: &CameraState, b: &CameraState) -> [f64; 12] {
    let dr = b.position - a.position;
    let dth = crate::geometry::so3_log(b.rotation * a.rotation.conjugate());
    let dv = b.velocity - a.velocity;
    let dw = b.angular_velocity - a.angular_velocity;
    let mut out = [0.0; 12];
    for k in 0..3 {
        out[k] = dr[k];
        out[3 + k] = dth[k];
        out[6 + k] = dv[k];
        out[9 + k] = dw[k];
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn state() -> CameraState {
        CameraState {
            position: DVec3::new(0.3, -0.1, 0.5),
            rotation: so3_exp(DVec3::new(0.2, -0.4, 0.1)),
            velocity: DVec3::new(0.4, 0.1, -0.2),
            angular_velocity: DVec3::new(0.8, -1.5, 0.6),
        }
    }

    #[test]
    fn transition_matches_finite_differences() {
        let x = state();
        let dt = 0.1;
        let f = x.transition(dt);
        let base = x.predicted(dt);
        let h = 1e-6;
        for k in 0..12 {
            let mut d = [0.0; 12];
            d[k] = h;
            let p = x.corrected(&d).predicted(dt);
            d[k] = -h;
            let m = x.corrected(&d).predicted(dt);
            let ep = error_between(&base, &p);
            let em = error_between(&base, &m);
            for r in 0..12 {
                let num = (ep[r] - em[r]) / (2.0 * h);
                assert!(
                    (num - f[(r, k)]).abs() < 1e-6,
                    "F[{r},{k}] = {} vs {num}",
                    f[(r, k)]
                );
            }
        }
    }

    #[test]
    fn process_noise_is_symmetric_positive_definite_and_grows_with_dt() {
        let x = state();
        let q1 = x.process_noise(1.0 / 30.0, 2.0, 4.0);
        let q2 = x.process_noise(2.0 / 30.0, 2.0, 4.0);
        assert!((q1 - q1.transpose()).norm() < 1e-15);
        assert!(q1.cholesky().is_some());
        assert!(q2.trace() > q1.trace());
        // Position variance of a random walk in velocity: sigma^2 dt^3 / 3.
        let dt: f64 = 1.0 / 30.0;
        assert!((q1[(0, 0)] - 4.0 * dt.powi(3) / 3.0).abs() < 1e-15);
    }

    /// The closed-form rotation block of Q against numerical quadrature of the integral
    /// `int_0^dt s^2 J_l(w s) J_l(w s)^T ds` and `int_0^dt s J_l(w s) ds`.
    #[test]
    fn rotation_noise_matches_quadrature() {
        let x = state();
        let dt = 1.0 / 30.0;
        let q = x.process_noise(dt, 1.0, 1.0);
        let n = 2000;
        let mut tt = DMat3::ZERO;
        let mut tw = DMat3::ZERO;
        for i in 0..n {
            let s = (i as f64 + 0.5) / n as f64 * dt;
            let j = so3_left_jacobian(x.angular_velocity * s) * s;
            tt += j * j.transpose() * (dt / n as f64);
            tw += j * (dt / n as f64);
        }
        for a in 0..3 {
            for b in 0..3 {
                let rel = |num: f64, an: f64, scale: f64| (num - an).abs() / scale;
                assert!(rel(tt.col(b)[a], q[(3 + a, 3 + b)], dt.powi(3) / 3.0) < 1e-3);
                assert!(rel(tw.col(b)[a], q[(3 + a, 9 + b)], dt * dt / 2.0) < 1e-3);
            }
        }
    }
}
