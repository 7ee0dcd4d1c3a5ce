//! Position error against ground truth by normalised arc length (thesis eq. 3.36, natural
//! formulation).
//!
//! Both trajectories are resampled at `samples` points equally spaced in their own normalised
//! arc length `u = l / L` in `[0, 1]` (so the comparison does not depend on timing), the
//! estimate is aligned to the ground truth (rigidly, i.e. keeping its metric scale, or with a
//! similarity for a shape-only comparison) by Umeyama over those points, and the error at `u`
//! is `e(u) = |p_gt(u) - A p_est(u)|`. Reported: mean and max of `e` (metres) and the relative
//! error `mean(e) / L_gt` (fraction of the distance walked).

use glam::DVec3;

use super::ScaleError;
use crate::eval::ate::align_umeyama;
use crate::trajectory::TimedPose;

/// Errors by normalised arc length.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ArcLengthError {
    /// Mean position error, metres.
    pub mean: f64,
    /// Largest position error, metres.
    pub max: f64,
    /// `mean / gt_length` (unitless fraction).
    pub relative: f64,
    /// Ground-truth path length, metres.
    pub gt_length: f64,
    /// Estimated path length after alignment, metres.
    pub est_length: f64,
    /// `(u, e(u))` samples, `u` in [0, 1], `e` metres.
    pub curve: Vec<(f64, f64)>,
}

fn resample_by_arc_length(p: &[DVec3], samples: usize) -> (f64, Vec<DVec3>) {
    let mut cum = Vec::with_capacity(p.len());
    let mut l = 0.0;
    cum.push(0.0);
    for w in p.windows(2) {
        l += (w[1] - w[0]).length();
        cum.push(l);
    }
    let out = (0..samples)
        .map(|k| {
            let target = l * k as f64 / (samples - 1) as f64;
            let i = cum.partition_point(|&c| c < target).clamp(1, p.len() - 1);
            let seg = cum[i] - cum[i - 1];
            let a = if seg > 0.0 {
                ((target - cum[i - 1]) / seg).clamp(0.0, 1.0)
            } else {
                0.0
            };
            p[i - 1].lerp(p[i], a)
        })
        .collect();
    (l, out)
}

/// Error of `est` against `gt` by normalised arc length (`samples >= 3` points); with
/// `with_scale` the alignment is a similarity (shape only), otherwise rigid (metric).
pub fn arc_length_error(
    gt: &[TimedPose],
    est: &[TimedPose],
    samples: usize,
    with_scale: bool,
) -> Result<ArcLengthError, ScaleError> {
    compare(gt, est, samples, |re, rg| {
        let a = align_umeyama(re, rg, with_scale).map_err(|e| ScaleError::InvalidParameter {
            name: "alignment",
            why: e.to_string(),
        })?;
        Ok((a.scale, Box::new(move |p| a.apply(p))))
    })
}

/// Eq. 3.36 as the thesis scores a walk: the estimate is placed on the ground truth at its
/// first pose (the rigid transform `gt[0] * est[0]^-1`, so the start agrees in position and
/// orientation) and never rescaled, then compared by normalised arc length (`samples >= 3`).
/// Scale errors, heading drift and the error of the first pose's orientation all show, as
/// they would for a walker who only knows where they started. The error at the end of the
/// walk is `curve.last()`.
pub fn arc_length_error_from_start(
    gt: &[TimedPose],
    est: &[TimedPose],
    samples: usize,
) -> Result<ArcLengthError, ScaleError> {
    let (Some(g0), Some(e0)) = (gt.first(), est.first()) else {
        return Err(ScaleError::TooShort {
            have: 0,
            seconds: 0.0,
            need: "2 poses in both trajectories".into(),
        });
    };
    let gt_from_est = g0.world_from_camera * e0.world_from_camera.inverse();
    compare(gt, est, samples, move |_, _| {
        Ok((1.0, Box::new(move |p| gt_from_est.transform_point(p))))
    })
}

/// The position error at equal times, placed as [`arc_length_error_from_start`] places the
/// estimate (the rigid transform `gt[0] * est[0]^-1`, never rescaled): the mean of
/// `|p_gt(t_i) - A p_est(t_i)|` over the pairs `(gt[i], est[i])`, which must be associated
/// in time (equal lengths, `>= 2`). Returned as `(mean error, ground-truth path length)`,
/// metres. Unlike eq. 3.36 it does not depend on how the estimate spends its arc length, so
/// a jump, which lengthens the path, counts only for the distance it leaves.
pub fn time_matched_error_from_start(
    gt: &[TimedPose],
    est: &[TimedPose],
) -> Result<(f64, f64), ScaleError> {
    if gt.len() != est.len() {
        return Err(ScaleError::InvalidParameter {
            name: "trajectory",
            why: format!(
                "{} ground-truth poses for {} estimated poses: the pairs must be associated \
                 in time",
                gt.len(),
                est.len()
            ),
        });
    }
    if gt.len() < 2 {
        return Err(ScaleError::TooShort {
            have: gt.len().min(est.len()),
            seconds: 0.0,
            need: "2 or more time-associated pose pairs".into(),
        });
    }
    let gt_from_est = gt[0].world_from_camera * est[0].world_from_camera.inverse();
    let mut sum = 0.0;
    let mut length = 0.0;
    for (i, (g, e)) in gt.iter().zip(est).enumerate() {
        let pg = g.world_from_camera.translation;
        let pe = gt_from_est.transform_point(e.world_from_camera.translation);
        if !(pg.is_finite() && pe.is_finite()) {
            return Err(ScaleError::NonFinite("trajectory positions".into()));
        }
        sum += (pg - pe).length();
        if i > 0 {
            length += (pg - gt[i - 1].world_from_camera.translation).length();
        }
    }
    if !(length > 0.0) {
        return Err(ScaleError::InvalidParameter {
            name: "trajectory",
            why: "zero path length".into(),
        });
    }
    Ok((sum / gt.len() as f64, length))
}

/// A map from the estimate's world frame into the ground truth's, with its scale.
type Align = (f64, Box<dyn Fn(DVec3) -> DVec3>);

fn compare(
    gt: &[TimedPose],
    est: &[TimedPose],
    samples: usize,
    align: impl FnOnce(&[DVec3], &[DVec3]) -> Result<Align, ScaleError>,
) -> Result<ArcLengthError, ScaleError> {
    if gt.len() < 2 || est.len() < 2 {
        return Err(ScaleError::TooShort {
            have: gt.len().min(est.len()),
            seconds: 0.0,
            need: "2 poses in both trajectories".into(),
        });
    }
    let samples = samples.max(3);
    let pg: Vec<DVec3> = gt.iter().map(|p| p.world_from_camera.translation).collect();
    let pe: Vec<DVec3> = est
        .iter()
        .map(|p| p.world_from_camera.translation)
        .collect();
    if pg.iter().chain(&pe).any(|p| !p.is_finite()) {
        return Err(ScaleError::NonFinite("trajectory positions".into()));
    }
    let (lg, rg) = resample_by_arc_length(&pg, samples);
    let (le, re) = resample_by_arc_length(&pe, samples);
    if !(lg > 0.0 && le > 0.0) {
        return Err(ScaleError::InvalidParameter {
            name: "trajectory",
            why: "zero path length".into(),
        });
    }
    let (scale, apply) = align(&re, &rg)?;
    let curve: Vec<(f64, f64)> = rg
        .iter()
        .zip(&re)
        .enumerate()
        .map(|(k, (g, e))| (k as f64 / (samples - 1) as f64, (*g - apply(*e)).length()))
        .collect();
    let mean = curve.iter().map(|c| c.1).sum::<f64>() / samples as f64;
    let max = curve.iter().fold(0.0f64, |m, c| m.max(c.1));
    Ok(ArcLengthError {
        mean,
        max,
        relative: mean / lg,
        gt_length: lg,
        est_length: le * scale,
        curve,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::Se3;
    use glam::DQuat;

    /// An L-shaped walk: 10 m along x, then 5 m along y, one pose per 10 cm.
    fn walk() -> Vec<TimedPose> {
        let mut p = Vec::new();
        for k in 0..=150 {
            let s = k as f64 * 0.1;
            let xy = if s <= 10.0 {
                DVec3::new(s, 0.0, 0.0)
            } else {
                DVec3::new(10.0, s - 10.0, 0.0)
            };
            p.push(TimedPose {
                timestamp: k as f64,
                world_from_camera: Se3::new(DQuat::from_rotation_z(0.3), xy),
            });
        }
        p
    }

    /// `gt` expressed in another world frame (`other_from_gt`).
    fn in_frame(other_from_gt: &Se3, gt: &[TimedPose]) -> Vec<TimedPose> {
        gt.iter()
            .map(|p| TimedPose {
                timestamp: p.timestamp,
                world_from_camera: *other_from_gt * p.world_from_camera,
            })
            .collect()
    }

    #[test]
    fn start_alignment_keeps_the_scale_error_that_a_rigid_fit_spreads_out() {
        let gt = walk();
        // The estimate in another world frame: exact up to where it started.
        let other_from_gt = Se3::new(DQuat::from_rotation_y(1.0), DVec3::new(3.0, -2.0, 1.0));
        let moved = in_frame(&other_from_gt, &gt);
        let e = arc_length_error_from_start(&gt, &moved, 301).unwrap();
        assert!(e.max < 1e-9, "{}", e.max);
        assert!((e.est_length - 15.0).abs() < 1e-9);
        // 10 % too long: the error grows from 0 at the start to 10 % of the distance from
        // the start at the end (|(10, 5)| = 11.18 m), and is never rescaled away.
        let long: Vec<TimedPose> = moved
            .iter()
            .map(|p| {
                let t = p.world_from_camera.translation;
                let o = moved[0].world_from_camera.translation;
                TimedPose {
                    timestamp: p.timestamp,
                    world_from_camera: Se3::new(p.world_from_camera.rotation, o + 1.1 * (t - o)),
                }
            })
            .collect();
        let e = arc_length_error_from_start(&gt, &long, 301).unwrap();
        let end = e.curve.last().unwrap().1;
        assert!((end - 0.1 * 125f64.sqrt()).abs() < 1e-6, "{end}");
        assert!(e.curve[0].1 < 1e-9);
        assert!((e.est_length / e.gt_length - 1.1).abs() < 1e-9);
        // A rigid best fit moves the start to share the error out, so its end error is smaller.
        let rigid = arc_length_error(&gt, &long, 301, false).unwrap();
        assert!(rigid.curve.last().unwrap().1 < end && rigid.curve[0].1 > 0.1);
    }

    #[test]
    fn the_time_matched_error_counts_a_jump_by_its_distance_not_by_its_length() {
        let gt = walk();
        let other_from_gt = Se3::new(DQuat::from_rotation_x(0.4), DVec3::new(1.0, 2.0, 3.0));
        let moved = in_frame(&other_from_gt, &gt);
        let (mean, length) = time_matched_error_from_start(&gt, &moved).unwrap();
        assert!(
            mean < 1e-9 && (length - 15.0).abs() < 1e-9,
            "{mean} {length}"
        );
        // One pose 1 m off to the side: 1 m of error over 151 poses, while the arc length
        // grows by 1.8 m.
        let mut jumped = moved.clone();
        let side = other_from_gt.transform_vector(DVec3::new(0.0, 0.0, 1.0));
        jumped[40].world_from_camera.translation += side;
        let (mean, _) = time_matched_error_from_start(&gt, &jumped).unwrap();
        assert!((mean - 1.0 / 151.0).abs() < 1e-9, "{mean}");
        let arc = arc_length_error_from_start(&gt, &jumped, 301).unwrap();
        assert!(
            arc.est_length > 16.7 && arc.mean > 10.0 * mean,
            "{} {}",
            arc.est_length,
            arc.mean
        );
        assert!(time_matched_error_from_start(&gt, &moved[1..]).is_err());
    }
}
