//! Relative pose error, TUM `evaluate_rpe` semantics.

use super::{ErrorStats, EvalError};
use crate::trajectory::TimedPose;

/// The interval between the two poses of an RPE pair.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub enum RpeDelta {
    /// Pairs `(i, k)` with `t_k` the first time stamp `>= t_i + delta` (seconds).
    Seconds(f64),
    /// Pairs `(i, i + n)` (frames).
    Frames(usize),
}

/// RPE statistics over all pairs.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct RpeResult {
    /// The interval used.
    pub delta: RpeDelta,
    /// Number of pose pairs.
    pub pairs: usize,
    /// Translation error of the relative motion, metres per pair (TUM `evaluate_rpe`).
    pub translation_m: ErrorStats,
    /// Rotation error of the relative motion, degrees per pair.
    pub rotation_deg: ErrorStats,
    /// Translation error divided by each pair's time span, m/s.
    pub translation_m_per_s: ErrorStats,
    /// Rotation error divided by each pair's time span, deg/s.
    pub rotation_deg_per_s: ErrorStats,
}

/// RPE of matched pose lists (`gt[i]` and `est[i]` at the same time, sorted by time). `None`
/// when no pair spans the interval.
pub fn rpe(
    gt: &[TimedPose],
    est: &[TimedPose],
    delta: RpeDelta,
) -> Result<Option<RpeResult>, EvalError> {
    let n = gt.len().min(est.len());
    let mut pairs = Vec::new();
    match delta {
        RpeDelta::Seconds(d) => {
            if !(d > 0.0 && d.is_finite()) {
                return Err(EvalError::InvalidOption {
                    name: "delta",
                    value: d,
                    why: "must be finite and > 0 seconds",
                });
            }
            for i in 0..n {
                let target = est[i].timestamp + d;
                let k = est[..n].partition_point(|p| p.timestamp < target);
                if k >= n {
                    break;
                }
                pairs.push((i, k));
            }
        }
        RpeDelta::Frames(f) => {
            if f == 0 {
                return Err(EvalError::InvalidOption {
                    name: "delta",
                    value: 0.0,
                    why: "must be >= 1 frame",
                });
            }
            pairs.extend((0..n.saturating_sub(f)).map(|i| (i, i + f)));
        }
    }
    if pairs.is_empty() {
        return Ok(None);
    }
    let (mut tm, mut rd, mut tms, mut rds) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    for &(i, k) in &pairs {
        let dg = gt[i].world_from_camera.inverse() * gt[k].world_from_camera;
        let de = est[i].world_from_camera.inverse() * est[k].world_from_camera;
        let err = dg.inverse() * de;
        let t = err.translation.length();
        let r = err.angle().to_degrees();
        let dt = est[k].timestamp - est[i].timestamp;
        tm.push(t);
        rd.push(r);
        if dt > 0.0 {
            tms.push(t / dt);
            rds.push(r / dt);
        }
    }
    Ok(Some(RpeResult {
        delta,
        pairs: pairs.len(),
        translation_m: ErrorStats::from_errors(&tm),
        rotation_deg: ErrorStats::from_errors(&rd),
        translation_m_per_s: ErrorStats::from_errors(&tms),
        rotation_deg_per_s: ErrorStats::from_errors(&rds),
    }))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::Se3;
    use glam::{DQuat, DVec3};

    #[test]
    fn known_drift_gives_known_rpe() {
        // Ground truth moves 1 m/s along x without rotating; the estimate moves 1.1 m/s along x
        // and yaws at 2 deg/s. Frames every 0.125 s (exact in binary, so pairs are (i, i + 8)).
        // The closed form of each pair's error is below.
        let rate = 2f64.to_radians();
        let mk = |t: f64, v: f64, w: f64| TimedPose {
            timestamp: t,
            world_from_camera: Se3::new(DQuat::from_rotation_z(w * t), DVec3::new(v * t, 0.0, 0.0)),
        };
        let gt: Vec<_> = (0..41).map(|i| mk(i as f64 * 0.125, 1.0, 0.0)).collect();
        let est: Vec<_> = (0..41).map(|i| mk(i as f64 * 0.125, 1.1, rate)).collect();
        let r = rpe(&gt, &est, RpeDelta::Seconds(1.0)).unwrap().unwrap();
        assert_eq!(r.pairs, 33);
        // Relative estimate from i to k: R_i^T (1.1 (t_k - t_i) x), rotation rate*(t_k - t_i).
        // Error translation = est_rel.t - gt_rel.t (gt rotation identity) = R(-w t_i)*(1.1 dt x) - dt x.
        let mut expect = Vec::new();
        for i in 0..r.pairs {
            let ti = i as f64 * 0.125;
            let dt = 1.0;
            let rel = DQuat::from_rotation_z(-rate * ti) * DVec3::new(1.1 * dt, 0.0, 0.0);
            expect.push((rel - DVec3::new(dt, 0.0, 0.0)).length());
        }
        let e = ErrorStats::from_errors(&expect);
        assert!(
            (r.translation_m.rmse - e.rmse).abs() < 1e-6,
            "{} vs {}",
            r.translation_m.rmse,
            e.rmse
        );
        assert!(
            (r.rotation_deg.rmse - 2.0).abs() < 1e-9 && (r.rotation_deg.max - 2.0).abs() < 1e-9
        );
        assert!((r.translation_m_per_s.rmse - e.rmse).abs() < 1e-6);

        // Frame mode: each step the estimate goes 0.1375 m vs 0.125 m and yaws 0.25 deg.
        let f = rpe(&gt, &est, RpeDelta::Frames(1)).unwrap().unwrap();
        assert_eq!(f.pairs, 40);
        assert!((f.rotation_deg.mean - 0.25).abs() < 1e-9);
        assert!((f.rotation_deg_per_s.mean - 2.0).abs() < 1e-7);
        assert!(f.translation_m.min >= 0.0125 - 1e-9);
    }

    #[test]
    fn identical_trajectories_have_zero_rpe_and_bad_delta_is_rejected() {
        let gt: Vec<_> = (0..10)
            .map(|i| TimedPose {
                timestamp: i as f64,
                world_from_camera: Se3::exp(&[
                    0.1 * i as f64,
                    0.0,
                    0.2,
                    0.01,
                    0.02,
                    0.03 * i as f64,
                ]),
            })
            .collect();
        let r = rpe(&gt, &gt, RpeDelta::Seconds(2.0)).unwrap().unwrap();
        assert!(r.translation_m.max < 1e-12 && r.rotation_deg.max < 1e-6);
        assert!(rpe(&gt, &gt, RpeDelta::Seconds(100.0)).unwrap().is_none());
        assert!(matches!(
            rpe(&gt, &gt, RpeDelta::Seconds(-1.0)),
            Err(EvalError::InvalidOption { .. })
        ));
        assert!(matches!(
            rpe(&gt, &gt, RpeDelta::Frames(0)),
            Err(EvalError::InvalidOption { .. })
        ));
    }
}
