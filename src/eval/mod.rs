//! Trajectory evaluation with the TUM RGB-D benchmark's definitions.
//!
//! Both trajectories are `world_from_camera` poses with time stamps (seconds). Each estimated
//! pose is matched to the ground-truth pose nearest in time (within `max_time_difference`,
//! default 0.02 s); the metrics use the matched pairs only.
//!
//! - ATE ([`ate()`]): translation error after aligning the estimate to the ground truth with a
//!   rigid Horn/Umeyama fit (optionally a similarity, for monocular runs); metres.
//! - RPE ([`rpe()`]): error of the relative motion between poses `delta` apart, TUM
//!   `evaluate_rpe`: for each `i`, `k` is the first pose with `t_k >= t_i + delta`; the error is
//!   `(gt_i^-1 gt_k)^-1 (est_i^-1 est_k)`. Reported raw (metres, degrees) and per second of
//!   `t_k - t_i` (m/s, deg/s). A frame mode uses pairs `(i, i + n)`.

pub mod ate;
pub mod rpe;

pub use ate::{align_umeyama, ate, Alignment, AteResult};
pub use rpe::{rpe, RpeDelta, RpeResult};

use crate::trajectory::TimedPose;

/// Default largest time difference for matching estimated to ground-truth poses, seconds.
pub const DEFAULT_MAX_TIME_DIFFERENCE: f64 = 0.02;

/// Errors of the evaluation.
#[derive(Debug, thiserror::Error)]
pub enum EvalError {
    /// Too few estimated poses have a ground-truth pose within the time tolerance.
    #[error("only {matched} estimated poses have a ground-truth pose within {max_time_difference} s; at least {required} are needed")]
    TooFewMatches {
        /// Matched pairs found.
        matched: usize,
        /// The minimum.
        required: usize,
        /// The tolerance used, seconds.
        max_time_difference: f64,
    },
    /// The matched positions are degenerate for the alignment (all equal, so no scale).
    #[error("the estimated positions do not spread out: cannot estimate a scale")]
    DegenerateAlignment,
    /// The ground-truth positions of the matched poses do not spread out (a stationary
    /// camera): a scale aligned to them would be 0.
    #[error("the ground-truth positions do not spread out (a stationary camera): cannot estimate a scale; evaluate without it")]
    StationaryGroundTruth,
    /// Two or more poses of one trajectory share a time stamp; matching them would pair
    /// several poses with one and weight that time more.
    #[error("the estimated trajectory has {count} poses at time {timestamp} s; time stamps must be distinct")]
    DuplicateTimestamps {
        /// The time stamp, seconds.
        timestamp: f64,
        /// How many poses share it.
        count: usize,
    },
    /// An option is out of range.
    #[error("invalid option {name} = {value}: {why}")]
    InvalidOption {
        /// Option name.
        name: &'static str,
        /// Offending value.
        value: f64,
        /// What is required.
        why: &'static str,
    },
}

/// Summary statistics of a set of non-negative errors.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ErrorStats {
    /// Number of errors.
    pub count: usize,
    /// Root mean square.
    pub rmse: f64,
    /// Mean.
    pub mean: f64,
    /// Median (mean of the two middle values for an even count, as numpy).
    pub median: f64,
    /// Standard deviation (population).
    pub std: f64,
    /// Smallest.
    pub min: f64,
    /// Largest.
    pub max: f64,
}

impl ErrorStats {
    /// Statistics of `errors`; all zero for an empty slice.
    pub fn from_errors(errors: &[f64]) -> Self {
        let n = errors.len();
        if n == 0 {
            return Self::default();
        }
        let nf = n as f64;
        let mean = errors.iter().sum::<f64>() / nf;
        let ms = errors.iter().map(|e| e * e).sum::<f64>() / nf;
        let var = errors.iter().map(|e| (e - mean) * (e - mean)).sum::<f64>() / nf;
        let mut s = errors.to_vec();
        s.sort_by(f64::total_cmp);
        let median = if n % 2 == 1 {
            s[n / 2]
        } else {
            0.5 * (s[n / 2 - 1] + s[n / 2])
        };
        Self {
            count: n,
            rmse: ms.sqrt(),
            mean,
            median,
            std: var.sqrt(),
            min: s[0],
            max: s[n - 1],
        }
    }
}

/// Options of [`evaluate`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EvalOptions {
    /// Largest time difference of a matched pair, seconds (default 0.02).
    pub max_time_difference: f64,
    /// RPE interval (default 1 s).
    pub delta: RpeDelta,
    /// Align with a similarity (scale too), for monocular trajectories (default false).
    pub with_scale: bool,
}

impl Default for EvalOptions {
    fn default() -> Self {
        Self {
            max_time_difference: DEFAULT_MAX_TIME_DIFFERENCE,
            delta: RpeDelta::Seconds(1.0),
            with_scale: false,
        }
    }
}

/// All metrics of an estimated trajectory against ground truth.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct TrajectoryMetrics {
    /// Estimated poses matched to ground truth.
    pub matched: usize,
    /// Estimated poses in the file.
    pub est_poses: usize,
    /// Ground-truth poses in the file.
    pub gt_poses: usize,
    /// Length of the matched ground-truth path, metres.
    pub path_length_m: f64,
    /// Duration of the matched estimate, seconds.
    pub duration_s: f64,
    /// Absolute trajectory error.
    pub ate: AteResult,
    /// Relative pose error at the requested interval (`None` if no pair is that far apart).
    pub rpe: Option<RpeResult>,
    /// Frame-to-frame relative pose error (consecutive matched poses).
    pub rpe_frame: Option<RpeResult>,
}

/// For each estimated pose, the index of the ground-truth pose nearest in time, kept when within
/// `max_time_difference` (several estimates may share one ground-truth pose). Both slices must be
/// sorted by time (as [`crate::io::trajectory::read_tum`] returns them). Returns
/// `(est_index, gt_index)` pairs in estimate order.
pub fn associate(
    est: &[TimedPose],
    gt: &[TimedPose],
    max_time_difference: f64,
) -> Vec<(usize, usize)> {
    let mut out = Vec::new();
    if gt.is_empty() {
        return out;
    }
    for (i, e) in est.iter().enumerate() {
        let t = e.timestamp;
        let j = if gt.len() == 1 {
            0
        } else {
            let k = gt
                .partition_point(|g| g.timestamp < t)
                .clamp(1, gt.len() - 1);
            if (gt[k - 1].timestamp - t).abs() < (gt[k].timestamp - t).abs() {
                k - 1
            } else {
                k
            }
        };
        if (gt[j].timestamp - t).abs() <= max_time_difference {
            out.push((i, j));
        }
    }
    out
}

/// Matches, aligns and computes ATE, RPE at `opts.delta` and frame-to-frame RPE.
pub fn evaluate(
    gt: &[TimedPose],
    est: &[TimedPose],
    opts: &EvalOptions,
) -> Result<TrajectoryMetrics, EvalError> {
    if !(opts.max_time_difference >= 0.0 && opts.max_time_difference.is_finite()) {
        return Err(EvalError::InvalidOption {
            name: "max_time_difference",
            value: opts.max_time_difference,
            why: "must be finite and >= 0",
        });
    }
    let mut gt_sorted = gt.to_vec();
    gt_sorted.sort_by(|a, b| a.timestamp.total_cmp(&b.timestamp));
    let mut est_sorted = est.to_vec();
    est_sorted.sort_by(|a, b| a.timestamp.total_cmp(&b.timestamp));
    // Duplicated estimate times would be matched many-to-one with one ground-truth pose.
    if let Some(w) = est_sorted
        .windows(2)
        .find(|w| w[0].timestamp == w[1].timestamp)
    {
        let timestamp = w[0].timestamp;
        return Err(EvalError::DuplicateTimestamps {
            timestamp,
            count: est_sorted
                .iter()
                .filter(|p| p.timestamp == timestamp)
                .count(),
        });
    }
    let pairs = associate(&est_sorted, &gt_sorted, opts.max_time_difference);
    if pairs.len() < 3 {
        return Err(EvalError::TooFewMatches {
            matched: pairs.len(),
            required: 3,
            max_time_difference: opts.max_time_difference,
        });
    }
    let e: Vec<TimedPose> = pairs.iter().map(|&(i, _)| est_sorted[i]).collect();
    let g: Vec<TimedPose> = pairs.iter().map(|&(_, j)| gt_sorted[j]).collect();
    let ate = ate(&g, &e, opts.with_scale)?;
    let rpe_main = rpe(&g, &e, opts.delta)?;
    let rpe_frame = rpe(&g, &e, RpeDelta::Frames(1))?;
    let path_length_m = g
        .windows(2)
        .map(|w| (w[1].world_from_camera.translation - w[0].world_from_camera.translation).length())
        .sum();
    Ok(TrajectoryMetrics {
        matched: pairs.len(),
        est_poses: est.len(),
        gt_poses: gt.len(),
        path_length_m,
        duration_s: e[e.len() - 1].timestamp - e[0].timestamp,
        ate,
        rpe: rpe_main,
        rpe_frame,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::Se3;

    fn tp(t: f64) -> TimedPose {
        TimedPose {
            timestamp: t,
            world_from_camera: Se3::IDENTITY,
        }
    }

    #[test]
    fn association_nearest_within_tolerance() {
        let gt: Vec<_> = [0.0, 0.1, 0.2, 0.3].into_iter().map(tp).collect();
        let est: Vec<_> = [-0.5, 0.01, 0.14, 0.16, 0.29, 0.35]
            .into_iter()
            .map(tp)
            .collect();
        assert_eq!(associate(&est, &gt, 0.02), vec![(1, 0), (4, 3)]);
        assert_eq!(
            associate(&est, &gt, 0.06),
            vec![(1, 0), (2, 1), (3, 2), (4, 3), (5, 3)]
        );
        assert!(associate(&est, &[tp(0.0)], 0.02).len() == 1);
        assert!(associate(&est, &[], 0.02).is_empty());
    }

    fn moving(t: f64) -> TimedPose {
        TimedPose {
            timestamp: t,
            world_from_camera: Se3::new(
                glam::DQuat::IDENTITY,
                glam::DVec3::new(t, (3.0 * t).sin(), 0.5 * t * t),
            ),
        }
    }

    #[test]
    fn duplicated_estimate_times_are_an_error() {
        let gt: Vec<_> = (0..20).map(|i| moving(0.1 * i as f64)).collect();
        let mut est = gt.clone();
        est.push(moving(0.5));
        let e = evaluate(&gt, &est, &EvalOptions::default()).unwrap_err();
        assert!(
            matches!(e, EvalError::DuplicateTimestamps { count: 2, .. }),
            "{e}"
        );
        assert!(evaluate(&gt, &gt, &EvalOptions::default()).is_ok());
    }

    #[test]
    fn scale_against_a_stationary_ground_truth_is_an_error() {
        let gt: Vec<_> = (0..20).map(|i| tp(0.1 * i as f64)).collect();
        let est: Vec<_> = (0..20).map(|i| moving(0.1 * i as f64)).collect();
        let opts = EvalOptions {
            with_scale: true,
            ..Default::default()
        };
        let e = evaluate(&gt, &est, &opts).unwrap_err();
        assert!(matches!(e, EvalError::StationaryGroundTruth), "{e}");
        // Without a scale the same pair evaluates (the error is the motion itself).
        let m = evaluate(&gt, &est, &EvalOptions::default()).unwrap();
        assert!(m.ate.translation.rmse > 0.1);
    }

    #[test]
    fn stats() {
        let s = ErrorStats::from_errors(&[3.0, 4.0, 1.0, 2.0]);
        assert_eq!(
            (s.count, s.mean, s.median, s.min, s.max),
            (4, 2.5, 2.5, 1.0, 4.0)
        );
        assert!((s.rmse - 7.5f64.sqrt()).abs() < 1e-15);
    }
}
