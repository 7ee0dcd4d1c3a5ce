use glam::{DMat3, DQuat, DVec3};

/// The skew-symmetric (cross-product) matrix of `v`: `skew(v) * x == v.cross(x)`.
pub fn skew(v: DVec3) -> DMat3 {
    DMat3::from_cols(
        DVec3::new(0.0, v.z, -v.y),
        DVec3::new(-v.z, 0.0, v.x),
        DVec3::new(v.y, -v.x, 0.0),
    )
}

/// Exponential map of so(3): the rotation by angle `|w|` (radians) about axis `w / |w|`.
pub fn so3_exp(w: DVec3) -> DQuat {
    let theta = w.length();
    if theta < 1e-12 {
        // Second-order accurate near zero, then normalised.
        DQuat::from_xyzw(0.5 * w.x, 0.5 * w.y, 0.5 * w.z, 1.0).normalize()
    } else {
        DQuat::from_axis_angle(w / theta, theta)
    }
}

/// Logarithm map of SO(3): the rotation vector (radians) with angle in `[0, pi]`.
pub fn so3_log(q: DQuat) -> DVec3 {
    let q = if q.w < 0.0 { -q } else { q };
    let v = DVec3::new(q.x, q.y, q.z);
    let s = v.length();
    if s < 1e-12 {
        return 2.0 * v;
    }
    let angle = 2.0 * s.atan2(q.w);
    v * (angle / s)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exp_log_round_trip() {
        for w in [
            DVec3::new(0.1, -0.2, 0.3),
            DVec3::new(1e-9, 0.0, 2e-9),
            DVec3::new(3.0, 0.1, -0.05),
        ] {
            let back = so3_log(so3_exp(w));
            assert!((back - w).length() < 1e-9, "{w:?} -> {back:?}");
        }
    }

    #[test]
    fn skew_is_cross() {
        let a = DVec3::new(0.3, -1.0, 2.0);
        let b = DVec3::new(-0.7, 0.2, 0.9);
        assert!((skew(a) * b - a.cross(b)).length() < 1e-12);
    }
}
