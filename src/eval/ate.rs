//! Absolute trajectory error after a Horn/Umeyama alignment.

use glam::{DMat3, DQuat, DVec3};

use super::{ErrorStats, EvalError};
use crate::trajectory::TimedPose;

/// The similarity `gt_from_est` that best maps estimated positions onto ground truth:
/// `p_gt ~ scale * rotation * p_est + translation`.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Alignment {
    /// Rotation as a unit quaternion `[x, y, z, w]`.
    pub rotation_xyzw: [f64; 4],
    /// Translation, metres (in the ground-truth world frame).
    pub translation: [f64; 3],
    /// Scale (1 for a rigid alignment).
    pub scale: f64,
}

impl Alignment {
    /// Maps a point of the estimate's world frame into the ground truth's.
    pub fn apply(&self, p: DVec3) -> DVec3 {
        let [x, y, z, w] = self.rotation_xyzw;
        self.scale * (DQuat::from_xyzw(x, y, z, w) * p) + DVec3::from_array(self.translation)
    }
}

/// ATE result: statistics of the per-pose position errors after alignment, metres.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct AteResult {
    /// Translation error statistics, metres.
    pub translation: ErrorStats,
    /// The alignment used.
    pub alignment: Alignment,
}

/// Least-squares similarity (Umeyama 1991) with `dst ~ c R src + t`; `c = 1` unless
/// `with_scale`. Needs at least 3 points; reflections are excluded.
pub fn align_umeyama(
    src: &[DVec3],
    dst: &[DVec3],
    with_scale: bool,
) -> Result<Alignment, EvalError> {
    let n = src.len().min(dst.len());
    if n < 3 {
        return Err(EvalError::TooFewMatches {
            matched: n,
            required: 3,
            max_time_difference: f64::NAN,
        });
    }
    let nf = n as f64;
    let ms = src[..n].iter().copied().sum::<DVec3>() / nf;
    let md = dst[..n].iter().copied().sum::<DVec3>() / nf;
    let mut cov = nalgebra::Matrix3::<f64>::zeros();
    let mut var_src = 0.0;
    for (s, d) in src[..n].iter().zip(&dst[..n]) {
        let (a, b) = (*s - ms, *d - md);
        var_src += a.length_squared();
        for r in 0..3 {
            for c in 0..3 {
                cov[(r, c)] += b[r] * a[c];
            }
        }
    }
    cov /= nf;
    var_src /= nf;
    if with_scale {
        // Positions that do not spread out (all within a nanometre of their mean) give a
        // scale of 0, or a meaningless one.
        let var_dst = dst[..n]
            .iter()
            .map(|d| (*d - md).length_squared())
            .sum::<f64>()
            / nf;
        if !(var_dst > 1e-18) {
            return Err(EvalError::StationaryGroundTruth);
        }
    }
    let svd = cov.svd(true, true);
    let (Some(u), Some(vt)) = (svd.u, svd.v_t) else {
        return Err(EvalError::DegenerateAlignment);
    };
    let sign = if (u * vt).determinant() < 0.0 {
        -1.0
    } else {
        1.0
    };
    let s = nalgebra::Matrix3::from_diagonal(&nalgebra::Vector3::new(1.0, 1.0, sign));
    let r = u * s * vt;
    let scale = if with_scale {
        if var_src.is_nan() || var_src <= 1e-300 {
            return Err(EvalError::DegenerateAlignment);
        }
        (svd.singular_values[0] + svd.singular_values[1] + sign * svd.singular_values[2]) / var_src
    } else {
        1.0
    };
    let rm = DMat3::from_cols_array(&[
        r[(0, 0)],
        r[(1, 0)],
        r[(2, 0)],
        r[(0, 1)],
        r[(1, 1)],
        r[(2, 1)],
        r[(0, 2)],
        r[(1, 2)],
        r[(2, 2)],
    ]);
    let q = DQuat::from_mat3(&rm).normalize();
    let t = md - scale * (rm * ms);
    Ok(Alignment {
        rotation_xyzw: [q.x, q.y, q.z, q.w],
        translation: t.to_array(),
        scale,
    })
}

/// ATE of matched pose lists (`gt[i]` and `est[i]` at the same time): aligns the estimated
/// positions to the ground-truth ones and takes the distances, metres.
pub fn ate(gt: &[TimedPose], est: &[TimedPose], with_scale: bool) -> Result<AteResult, EvalError> {
    let src: Vec<DVec3> = est
        .iter()
        .map(|p| p.world_from_camera.translation)
        .collect();
    let dst: Vec<DVec3> = gt.iter().map(|p| p.world_from_camera.translation).collect();
    let alignment = align_umeyama(&src, &dst, with_scale)?;
    let errors: Vec<f64> = src
        .iter()
        .zip(&dst)
        .map(|(s, d)| (alignment.apply(*s) - *d).length())
        .collect();
    Ok(AteResult {
        translation: ErrorStats::from_errors(&errors),
        alignment,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::Se3;

    fn points() -> Vec<DVec3> {
        (0..20)
            .map(|i| {
                let t = i as f64 * 0.3;
                DVec3::new(t.sin() * 2.0, t.cos() - 0.5 * t, 0.1 * t * t)
            })
            .collect()
    }

    #[test]
    fn recovers_a_known_similarity() {
        let src = points();
        let q = DQuat::from_axis_angle(DVec3::new(0.3, -0.5, 0.8).normalize(), 1.1);
        let t = DVec3::new(0.4, -2.0, 1.5);
        let dst: Vec<DVec3> = src.iter().map(|p| 2.5 * (q * *p) + t).collect();
        let a = align_umeyama(&src, &dst, true).unwrap();
        assert!((a.scale - 2.5).abs() < 1e-10, "{}", a.scale);
        for (s, d) in src.iter().zip(&dst) {
            assert!((a.apply(*s) - *d).length() < 1e-9);
        }
        // Rigid fit of the same data cannot reach zero error.
        let r = align_umeyama(&src, &dst, false).unwrap();
        assert_eq!(r.scale, 1.0);
        assert!(src
            .iter()
            .zip(&dst)
            .any(|(s, d)| (r.apply(*s) - *d).length() > 0.1));
    }

    #[test]
    fn translation_offset_gives_zero_ate() {
        let gt: Vec<TimedPose> = points()
            .into_iter()
            .enumerate()
            .map(|(i, p)| TimedPose {
                timestamp: i as f64 * 0.1,
                world_from_camera: Se3::new(DQuat::IDENTITY, p),
            })
            .collect();
        let est: Vec<TimedPose> = gt
            .iter()
            .map(|p| TimedPose {
                timestamp: p.timestamp,
                world_from_camera: Se3::new(
                    p.world_from_camera.rotation,
                    p.world_from_camera.translation + DVec3::new(1.0, -2.0, 3.0),
                ),
            })
            .collect();
        let r = ate(&gt, &est, false).unwrap();
        assert!(
            r.translation.rmse < 1e-12 && r.translation.max < 1e-12,
            "{:?}",
            r
        );
        assert!(
            (DVec3::from_array(r.alignment.translation) - DVec3::new(-1.0, 2.0, -3.0)).length()
                < 1e-12
        );
    }

    #[test]
    fn known_residual_after_alignment() {
        // Points on the unit circle in z = 0, errors +d along z at +-X and -d at +-Y: the error
        // pattern is quadratic (x^2 - y^2), which no rotation or translation can absorb, and by
        // symmetry the best rigid fit is the identity, so every error stays exactly d.
        let d = 0.05;
        let pts = [DVec3::X, -DVec3::X, DVec3::Y, -DVec3::Y];
        let gt: Vec<TimedPose> = pts
            .iter()
            .enumerate()
            .map(|(i, p)| TimedPose {
                timestamp: i as f64,
                world_from_camera: Se3::new(DQuat::IDENTITY, *p),
            })
            .collect();
        let est: Vec<TimedPose> = gt
            .iter()
            .enumerate()
            .map(|(i, p)| {
                let s = if i < 2 { d } else { -d };
                TimedPose {
                    timestamp: p.timestamp,
                    world_from_camera: Se3::new(
                        DQuat::IDENTITY,
                        p.world_from_camera.translation + DVec3::Z * s,
                    ),
                }
            })
            .collect();
        let r = ate(&gt, &est, false).unwrap();
        assert!((r.translation.rmse - d).abs() < 1e-6, "{:?}", r.translation);
    }
}
