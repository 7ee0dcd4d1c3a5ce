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
    let a = align_umeyama(&re, &rg, with_scale).map_err(|e| ScaleError::InvalidParameter {
        name: "alignment",
        why: e.to_string(),
    })?;
    let curve: Vec<(f64, f64)> = rg
        .iter()
        .zip(&re)
        .enumerate()
        .map(|(k, (g, e))| (k as f64 / (samples - 1) as f64, (*g - a.apply(*e)).length()))
        .collect();
    let mean = curve.iter().map(|c| c.1).sum::<f64>() / samples as f64;
    let max = curve.iter().fold(0.0f64, |m, c| m.max(c.1));
    Ok(ArcLengthError {
        mean,
        max,
        relative: mean / lg,
        gt_length: lg,
        est_length: le * a.scale,
        curve,
    })
}
