use std::ops::Mul;

use glam::{DMat3, DMat4, DQuat, DVec3};

use super::so3::{skew, so3_exp, so3_log};

/// A rigid transform `a_from_b` in SE(3): `p_a = rotation * p_b + translation`.
///
/// Translation in metres. The rotation is a unit quaternion.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Se3 {
    /// Rotation part (unit quaternion).
    pub rotation: DQuat,
    /// Translation part, in metres, expressed in frame `a`.
    pub translation: DVec3,
}

impl Default for Se3 {
    fn default() -> Self {
        Self::IDENTITY
    }
}

impl Se3 {
    /// The identity transform.
    pub const IDENTITY: Se3 = Se3 {
        rotation: DQuat::IDENTITY,
        translation: DVec3::ZERO,
    };

    /// Builds a transform from a rotation and a translation (metres).
    pub fn new(rotation: DQuat, translation: DVec3) -> Self {
        Self {
            rotation: rotation.normalize(),
            translation,
        }
    }

    /// The inverse transform `b_from_a`.
    pub fn inverse(&self) -> Se3 {
        let r = self.rotation.conjugate();
        Se3 {
            rotation: r,
            translation: -(r * self.translation),
        }
    }

    /// Applies the transform to a point: `p_a = a_from_b * p_b`.
    pub fn transform_point(&self, p: DVec3) -> DVec3 {
        self.rotation * p + self.translation
    }

    /// Applies only the rotation to a direction vector.
    pub fn transform_vector(&self, v: DVec3) -> DVec3 {
        self.rotation * v
    }

    /// The rotation as a 3x3 matrix.
    pub fn rotation_matrix(&self) -> DMat3 {
        DMat3::from_quat(self.rotation)
    }

    /// The homogeneous 4x4 matrix.
    pub fn to_mat4(&self) -> DMat4 {
        DMat4::from_rotation_translation(self.rotation, self.translation)
    }

    /// Builds a transform from a homogeneous matrix (the rotation block is re-orthonormalised
    /// through the quaternion conversion).
    pub fn from_mat4(m: &DMat4) -> Se3 {
        let (_, r, t) = m.to_scale_rotation_translation();
        Se3::new(r, t)
    }

    /// Exponential map of se(3) for the twist `[v; w]` (metres, radians).
    pub fn exp(twist: &[f64; 6]) -> Se3 {
        let v = DVec3::new(twist[0], twist[1], twist[2]);
        let w = DVec3::new(twist[3], twist[4], twist[5]);
        let rotation = so3_exp(w);
        Se3 {
            rotation,
            translation: left_jacobian(w) * v,
        }
    }

    /// Logarithm map: the twist `[v; w]` with `Se3::exp(&t.log()) == t`.
    pub fn log(&self) -> [f64; 6] {
        let w = so3_log(self.rotation);
        let v = left_jacobian_inverse(w) * self.translation;
        [v.x, v.y, v.z, w.x, w.y, w.z]
    }

    /// Rotation angle in radians, in `[0, pi]`.
    pub fn angle(&self) -> f64 {
        so3_log(self.rotation).length()
    }

    /// The 6x6 adjoint (row-major) for twists ordered `[v; w]`:
    /// `exp(Ad * xi) = T * exp(xi) * T^-1`.
    pub fn adjoint(&self) -> [[f64; 6]; 6] {
        let r = self.rotation_matrix();
        let tr = skew(self.translation) * r;
        let mut a = [[0.0; 6]; 6];
        for i in 0..3 {
            for j in 0..3 {
                a[i][j] = r.col(j)[i];
                a[i + 3][j + 3] = r.col(j)[i];
                a[i][j + 3] = tr.col(j)[i];
            }
        }
        a
    }

    /// True when every component is finite.
    pub fn is_finite(&self) -> bool {
        self.rotation.is_finite() && self.translation.is_finite()
    }
}

impl Mul for Se3 {
    type Output = Se3;
    /// Composition: `a_from_b * b_from_c = a_from_c`.
    fn mul(self, rhs: Se3) -> Se3 {
        Se3 {
            rotation: (self.rotation * rhs.rotation).normalize(),
            translation: self.rotation * rhs.translation + self.translation,
        }
    }
}

impl Mul<DVec3> for Se3 {
    type Output = DVec3;
    fn mul(self, rhs: DVec3) -> DVec3 {
        self.transform_point(rhs)
    }
}

/// Left Jacobian of SO(3), `V` in `t = V v`.
fn left_jacobian(w: DVec3) -> DMat3 {
    let theta2 = w.length_squared();
    let k = skew(w);
    let (a, b) = if theta2 < 1e-10 {
        (0.5 - theta2 / 24.0, 1.0 / 6.0 - theta2 / 120.0)
    } else {
        let t = theta2.sqrt();
        ((1.0 - t.cos()) / theta2, (t - t.sin()) / (theta2 * t))
    };
    DMat3::IDENTITY + k * a + k * k * b
}

fn left_jacobian_inverse(w: DVec3) -> DMat3 {
    let theta2 = w.length_squared();
    let k = skew(w);
    let c = if theta2 < 1e-10 {
        1.0 / 12.0 + theta2 / 720.0
    } else {
        let t = theta2.sqrt();
        (1.0 - t * t.sin() / (2.0 * (1.0 - t.cos()))) / theta2
    };
    DMat3::IDENTITY - k * 0.5 + k * k * c
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exp_log_round_trip() {
        let xi = [0.3, -0.1, 0.05, 0.2, -0.4, 0.1];
        let back = Se3::exp(&xi).log();
        for k in 0..6 {
            assert!((back[k] - xi[k]).abs() < 1e-10);
        }
    }

    #[test]
    fn inverse_composes_to_identity() {
        let t = Se3::exp(&[0.3, -0.1, 0.05, 0.2, -0.4, 0.1]);
        let i = t * t.inverse();
        assert!(i.translation.length() < 1e-12 && i.angle() < 1e-12);
    }

    #[test]
    fn adjoint_matches_conjugation() {
        let t = Se3::exp(&[0.3, -0.1, 0.05, 0.2, -0.4, 0.1]);
        let xi = [0.01, 0.02, -0.03, 0.004, -0.002, 0.003];
        let ad = t.adjoint();
        let mut axi = [0.0; 6];
        for i in 0..6 {
            for j in 0..6 {
                axi[i] += ad[i][j] * xi[j];
            }
        }
        let lhs = Se3::exp(&axi);
        let rhs = t * Se3::exp(&xi) * t.inverse();
        assert!((lhs.translation - rhs.translation).length() < 1e-12);
        assert!((lhs.rotation.dot(rhs.rotation).abs() - 1.0).abs() < 1e-12);
    }
}
