//! Lie-group types for pose graphs: [`Se2`], [`Sim3`], the [`Manifold`] trait implemented for
//! them, for [`Se3`] and for plain points (`DVec2`, `DVec3`), and small dense helpers.
//!
//! Conventions: a transform `a_from_b` maps `p_a = a_from_b * p_b`. Perturbations of poses
//! are applied on the right (in the body frame of the transform):
//! SE(2) is parametrised additively in `(x, y, theta)` (as g2o does),
//! SE(3) as `R <- R Exp(w)`, `t <- t + R v` with tangent `[v; w]`,
//! Sim(3) as SE(3) plus `s <- s exp(sigma)` with tangent `[v; w; sigma]`.

use glam::{DMat3, DQuat, DVec2, DVec3};

use crate::geometry::{skew, so3_exp, Se3};

/// A variable the solver can update: a point of a manifold with a `DIM`-dimensional
/// tangent space and a retraction.
pub trait Manifold: Clone + Send + Sync + 'static {
    /// Dimension of the tangent space (number of solver unknowns per variable).
    const DIM: usize;
    /// Applies the tangent increment `delta` (length `DIM`) and returns the new value.
    fn retract(&self, delta: &[f64]) -> Self;
    /// True when every component is finite.
    fn is_finite(&self) -> bool;
}

/// A rigid transform `a_from_b` in SE(2): `p_a = R(theta) p_b + (x, y)`. Metres, radians.
#[derive(Clone, Copy, Debug, PartialEq, Default)]
pub struct Se2 {
    /// Translation x (metres, frame `a`).
    pub x: f64,
    /// Translation y (metres, frame `a`).
    pub y: f64,
    /// Rotation angle (radians), kept in `(-pi, pi]` by the constructors.
    pub theta: f64,
}

/// Wraps an angle (radians) to `(-pi, pi]`.
pub fn wrap_angle(a: f64) -> f64 {
    let two_pi = std::f64::consts::TAU;
    let mut r = a % two_pi;
    if r <= -std::f64::consts::PI {
        r += two_pi;
    } else if r > std::f64::consts::PI {
        r -= two_pi;
    }
    r
}

impl Se2 {
    /// The identity transform.
    pub const IDENTITY: Se2 = Se2 {
        x: 0.0,
        y: 0.0,
        theta: 0.0,
    };
    /// Builds a transform from a translation (metres) and an angle (radians, wrapped).
    pub fn new(x: f64, y: f64, theta: f64) -> Self {
        Se2 {
            x,
            y,
            theta: wrap_angle(theta),
        }
    }
    /// The translation as a vector.
    pub fn translation(&self) -> DVec2 {
        DVec2::new(self.x, self.y)
    }
    /// Applies the transform to a point.
    pub fn transform_point(&self, p: DVec2) -> DVec2 {
        let (s, c) = self.theta.sin_cos();
        DVec2::new(c * p.x - s * p.y + self.x, s * p.x + c * p.y + self.y)
    }
    /// The inverse transform `b_from_a`.
    pub fn inverse(&self) -> Se2 {
        let (s, c) = self.theta.sin_cos();
        Se2 {
            x: -(c * self.x + s * self.y),
            y: -(-s * self.x + c * self.y),
            theta: -self.theta,
        }
    }
    /// Composition `self * rhs` (`a_from_b * b_from_c = a_from_c`).
    pub fn compose(&self, rhs: &Se2) -> Se2 {
        let t = self.transform_point(rhs.translation());
        Se2::new(t.x, t.y, self.theta + rhs.theta)
    }
    /// Embeds the transform in SE(3) (rotation about z).
    pub fn to_se3(&self) -> Se3 {
        Se3::new(
            DQuat::from_rotation_z(self.theta),
            DVec3::new(self.x, self.y, 0.0),
        )
    }
}

impl std::ops::Mul for Se2 {
    type Output = Se2;
    fn mul(self, rhs: Se2) -> Se2 {
        self.compose(&rhs)
    }
}

impl Manifold for Se2 {
    const DIM: usize = 3;
    fn retract(&self, d: &[f64]) -> Self {
        Se2::new(self.x + d[0], self.y + d[1], self.theta + d[2])
    }
    fn is_finite(&self) -> bool {
        self.x.is_finite() && self.y.is_finite() && self.theta.is_finite()
    }
}

impl Manifold for Se3 {
    const DIM: usize = 6;
    fn retract(&self, d: &[f64]) -> Self {
        let v = DVec3::new(d[0], d[1], d[2]);
        let w = DVec3::new(d[3], d[4], d[5]);
        Se3 {
            rotation: (self.rotation * so3_exp(w)).normalize(),
            translation: self.translation + self.rotation * v,
        }
    }
    fn is_finite(&self) -> bool {
        Se3::is_finite(self)
    }
}

/// A similarity `a_from_b` in Sim(3): `p_a = s R p_b + t` (Strasdat et al. 2010).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Sim3 {
    /// Rotation (unit quaternion).
    pub rotation: DQuat,
    /// Translation (metres, frame `a`).
    pub translation: DVec3,
    /// Scale factor (> 0, unitless).
    pub scale: f64,
}

impl Default for Sim3 {
    fn default() -> Self {
        Sim3::IDENTITY
    }
}

impl Sim3 {
    /// The identity similarity.
    pub const IDENTITY: Sim3 = Sim3 {
        rotation: DQuat::IDENTITY,
        translation: DVec3::ZERO,
        scale: 1.0,
    };
    /// Builds a similarity (the quaternion is normalised).
    pub fn new(rotation: DQuat, translation: DVec3, scale: f64) -> Self {
        Sim3 {
            rotation: rotation.normalize(),
            translation,
            scale,
        }
    }
    /// A rigid transform as a similarity of scale 1.
    pub fn from_se3(t: &Se3) -> Self {
        Sim3 {
            rotation: t.rotation,
            translation: t.translation,
            scale: 1.0,
        }
    }
    /// The rigid part (rotation, translation), dropping the scale.
    pub fn to_se3(&self) -> Se3 {
        Se3::new(self.rotation, self.translation)
    }
    /// Applies the similarity to a point.
    pub fn transform_point(&self, p: DVec3) -> DVec3 {
        self.scale * (self.rotation * p) + self.translation
    }
    /// The inverse similarity `b_from_a`.
    pub fn inverse(&self) -> Sim3 {
        let r = self.rotation.conjugate();
        let s = 1.0 / self.scale;
        Sim3 {
            rotation: r,
            translation: -(s * (r * self.translation)),
            scale: s,
        }
    }
    /// Composition `self * rhs`.
    pub fn compose(&self, rhs: &Sim3) -> Sim3 {
        Sim3 {
            rotation: (self.rotation * rhs.rotation).normalize(),
            translation: self.scale * (self.rotation * rhs.translation) + self.translation,
            scale: self.scale * rhs.scale,
        }
    }
}

impl std::ops::Mul for Sim3 {
    type Output = Sim3;
    fn mul(self, rhs: Sim3) -> Sim3 {
        self.compose(&rhs)
    }
}

impl Manifold for Sim3 {
    const DIM: usize = 7;
    fn retract(&self, d: &[f64]) -> Self {
        let v = DVec3::new(d[0], d[1], d[2]);
        let w = DVec3::new(d[3], d[4], d[5]);
        Sim3 {
            rotation: (self.rotation * so3_exp(w)).normalize(),
            translation: self.translation + self.rotation * v,
            scale: self.scale * d[6].exp(),
        }
    }
    fn is_finite(&self) -> bool {
        self.rotation.is_finite() && self.translation.is_finite() && self.scale.is_finite()
    }
}

impl Manifold for DVec2 {
    const DIM: usize = 2;
    fn retract(&self, d: &[f64]) -> Self {
        *self + DVec2::new(d[0], d[1])
    }
    fn is_finite(&self) -> bool {
        DVec2::is_finite(*self)
    }
}

impl Manifold for DVec3 {
    const DIM: usize = 3;
    fn retract(&self, d: &[f64]) -> Self {
        *self + DVec3::new(d[0], d[1], d[2])
    }
    fn is_finite(&self) -> bool {
        DVec3::is_finite(*self)
    }
}

/// Inverse of the right Jacobian of SO(3) at the rotation vector `phi` (radians):
/// `Log(Exp(phi) Exp(d)) ~ phi + Jr^-1(phi) d`.
pub fn so3_right_jacobian_inverse(phi: DVec3) -> DMat3 {
    let theta2 = phi.length_squared();
    let k = skew(phi);
    let c = if theta2 < 1e-8 {
        1.0 / 12.0 + theta2 / 720.0
    } else {
        let t = theta2.sqrt();
        1.0 / theta2 - (1.0 + t.cos()) / (2.0 * t * t.sin())
    };
    DMat3::IDENTITY + k * 0.5 + k * k * c
}

/// Lower Cholesky factor `L` (row-major, `n x n`) with `m = L L^T`, or `None` when `m`
/// (row-major, symmetric) is not positive definite or not finite.
pub fn cholesky_lower(m: &[f64], n: usize) -> Option<Vec<f64>> {
    let mut l = vec![0.0; n * n];
    for i in 0..n {
        for j in 0..=i {
            let mut s = m[i * n + j];
            for k in 0..j {
                s -= l[i * n + k] * l[j * n + k];
            }
            if i == j {
                if !(s > 0.0) || !s.is_finite() {
                    return None;
                }
                l[i * n + i] = s.sqrt();
            } else {
                l[i * n + j] = s / l[j * n + j];
            }
        }
    }
    Some(l)
}

/// Inverse of a symmetric positive-definite matrix (row-major), `None` if not SPD.
pub fn spd_inverse(m: &[f64], n: usize) -> Option<Vec<f64>> {
    let l = cholesky_lower(m, n)?;
    let mut inv = vec![0.0; n * n];
    for col in 0..n {
        // Solve L y = e_col, then L^T x = y.
        let mut y = vec![0.0; n];
        for i in 0..n {
            let mut s = if i == col { 1.0 } else { 0.0 };
            for k in 0..i {
                s -= l[i * n + k] * y[k];
            }
            y[i] = s / l[i * n + i];
        }
        for i in (0..n).rev() {
            let mut s = y[i];
            for k in i + 1..n {
                s -= l[k * n + i] * inv[k * n + col];
            }
            inv[i * n + col] = s / l[i * n + i];
        }
    }
    Some(inv)
}

/// Projects a 3x3 matrix to the nearest rotation (Frobenius norm) through its SVD.
pub fn project_to_so3(m: DMat3) -> DMat3 {
    let a = nalgebra::Matrix3::from_fn(|r, c| m.col(c)[r]);
    let svd = a.svd(true, true);
    let (Some(u), Some(vt)) = (svd.u, svd.v_t) else {
        return DMat3::IDENTITY;
    };
    let mut d = nalgebra::Matrix3::identity();
    if (u * vt).determinant() < 0.0 {
        d[(2, 2)] = -1.0;
    }
    let r = u * d * vt;
    DMat3::from_cols_array(&[
        r[(0, 0)],
        r[(1, 0)],
        r[(2, 0)],
        r[(0, 1)],
        r[(1, 1)],
        r[(2, 1)],
        r[(0, 2)],
        r[(1, 2)],
        r[(2, 2)],
    ])
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::so3_log;

    #[test]
    fn se2_inverse_and_compose() {
        let a = Se2::new(1.0, -2.0, 0.7);
        let b = Se2::new(-0.3, 0.5, -2.9);
        let i = a * a.inverse();
        assert!(i.x.abs() < 1e-12 && i.y.abs() < 1e-12 && i.theta.abs() < 1e-12);
        let p = DVec2::new(0.3, 0.9);
        let lhs = (a * b).transform_point(p);
        let rhs = a.transform_point(b.transform_point(p));
        assert!((lhs - rhs).length() < 1e-12);
    }

    #[test]
    fn sim3_inverse_and_compose() {
        let a = Sim3::new(DQuat::from_rotation_y(0.4), DVec3::new(1.0, 2.0, -1.0), 1.7);
        let b = Sim3::new(
            DQuat::from_rotation_x(-1.1),
            DVec3::new(0.1, -0.2, 0.3),
            0.6,
        );
        let p = DVec3::new(0.3, -0.4, 2.0);
        assert!(
            ((a * b).transform_point(p) - a.transform_point(b.transform_point(p))).length() < 1e-12
        );
        assert!(((a * a.inverse()).transform_point(p) - p).length() < 1e-12);
    }

    #[test]
    fn right_jacobian_inverse_matches_finite_differences() {
        let phi = DVec3::new(0.4, -0.9, 1.3);
        let jr_inv = so3_right_jacobian_inverse(phi);
        let r = so3_exp(phi);
        let h = 1e-6;
        for k in 0..3 {
            let mut d = DVec3::ZERO;
            d[k] = h;
            let fd = (so3_log(r * so3_exp(d)) - phi) / h;
            assert!(
                (fd - jr_inv.col(k)).length() < 1e-5,
                "{fd:?} vs {:?}",
                jr_inv.col(k)
            );
        }
    }

    #[test]
    fn spd_helpers() {
        let m = [4.0, 1.0, 0.5, 1.0, 3.0, 0.2, 0.5, 0.2, 2.0];
        let inv = spd_inverse(&m, 3).unwrap();
        for i in 0..3 {
            for j in 0..3 {
                let s: f64 = (0..3).map(|k| m[i * 3 + k] * inv[k * 3 + j]).sum();
                assert!((s - if i == j { 1.0 } else { 0.0 }).abs() < 1e-12);
            }
        }
        assert!(cholesky_lower(&[1.0, 2.0, 2.0, 1.0], 2).is_none());
        assert!(cholesky_lower(&[f64::NAN, 0.0, 0.0, 1.0], 2).is_none());
    }

    #[test]
    fn projection_to_so3() {
        let r = DMat3::from_quat(DQuat::from_rotation_z(0.3) * DQuat::from_rotation_x(1.0));
        let noisy = r + DMat3::from_cols_array(&[0.01, 0.0, 0.02, -0.01, 0.0, 0.0, 0.0, 0.03, 0.0]);
        let p = project_to_so3(noisy);
        assert!((p.determinant() - 1.0).abs() < 1e-12);
        assert!(
            (p - r)
                .to_cols_array()
                .iter()
                .map(|x| x.abs())
                .fold(0.0, f64::max)
                < 0.05
        );
    }
}
