//! Monocular EKF SLAM for any central camera (thesis ch. 2, app. A).
//!
//! A single camera, conventional, fisheye or catadioptric, described by the unified sphere
//! model ([`crate::camera::UnifiedCamera`]; pinhole is `xi = 0`), tracked by an extended
//! Kalman filter over a sparse map of anchored inverse-depth landmarks (Civera, Davison and
//! Montiel 2008), with active search inside the 95 % innovation ellipse, ZNCC patch
//! correlation, 1-point RANSAC (Civera et al. 2010), map management and, for catadioptric
//! images, patch warping ([`PatchMode`]: the change of polar angle with the thesis' scale
//! rules, or a projective map through the predicted relative pose).
//!
//! Frames and units. The filter's world frame `w` is the first camera's frame (x right,
//! y down, z forward at time 0); the camera state is `world_from_camera` (position in
//! metres, rotation as a unit quaternion whose error state lives in so(3) in the world frame,
//! `R = exp([dtheta]x) R_hat`), the linear velocity (m/s, world frame) and the angular
//! velocity (rad/s, world frame). Monocular SLAM has no metric scale: positions are metres
//! only up to one unknown factor, fixed loosely by the landmarks' initial inverse depth
//! ([`MonoConfig::initial_inverse_depth`]); evaluate with a similarity (Sim(3)) alignment.
//! Pixel coordinates: integer values at pixel centres; intensity in `[0, 255]`.
//!
//! Parts: [`CameraState`] (camera state, constant-velocity motion model with its closed-form
//! discrete error model), [`InverseDepthLandmark`] (inverse-depth parametrisation, measurement
//! model and Jacobians, initialisation with covariance), FAST-9 corners, ZNCC and catadioptric
//! patch warping ([`PatchMode`]), [`MonoSlam`] (the SLAM loop: prediction, active search,
//! 1-point RANSAC, update, map management, statistics), [`MetricMono`] (the filter with the
//! metric scale from walking beside it, thesis 3.4), [`LoopingMono`] (the filter with loop
//! detection from images beside it, thesis 3.3.2: [`KeyframeSelector`], [`MonoLoopDetector`]),
//! [`ImageSequence`] and [`load_camera`]
//! (image-only sequences and camera files). Runs on generated sequences with ground truth are in
//! `rgbid::experiments::mono` (feature `experiments`).

pub(crate) mod asl;
pub(crate) mod fast;
pub(crate) mod filter;
pub(crate) mod input;
pub(crate) mod landmark;
pub(crate) mod loops;
pub(crate) mod metric;
pub(crate) mod patch;
pub(crate) mod state;

use std::path::PathBuf;

pub use filter::{FrameReport, MonoSlam, MonoStats, StageTimes};
pub use input::{load_camera, load_grey, unified_from_model, ImageSequence};
pub use landmark::InverseDepthLandmark;
pub use loops::{
    CandidateCheck, KeyframePolicy, KeyframeQuery, KeyframeSelector, LoopScaleParams,
    LoopSimilarity, LoopingMono, LoopingReport, MonoKeyframe, MonoLoopDetector, MonoLoopParams,
};
pub use metric::{LoopedRun, MetricLoop, MetricMono, MetricReport, MetricRun};
pub use patch::PatchMode;
pub use state::CameraState;

/// Errors of monocular SLAM and its inputs.
#[derive(Debug, thiserror::Error)]
pub enum MonoError {
    /// A file or folder could not be read.
    #[error("{path}: {source}")]
    File {
        /// The path concerned.
        path: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
    /// The sequence folder has no frames: no ASL `data.csv` rows, no `rgb.txt` list and no
    /// images named by time stamp.
    #[error("{path}: no frames (an EuRoC / TUM-VI data.csv, an rgb.txt, or images named by their time stamp)")]
    NoImages {
        /// The folder.
        path: PathBuf,
    },
    /// A line of a list or camera file could not be parsed.
    #[error("{path}:{line}: {message}")]
    Parse {
        /// The file.
        path: PathBuf,
        /// Line number (1-based; 0 for the whole file).
        line: usize,
        /// What is wrong.
        message: String,
    },
    /// An image file could not be decoded.
    #[error("{path}: cannot decode image: {message}")]
    Decode {
        /// The image file.
        path: PathBuf,
        /// The decoder's message.
        message: String,
    },
    /// An image's size differs from the camera's.
    #[error(
        "{what}: image is {width}x{height}, the camera expects {expected_width}x{expected_height}"
    )]
    ImageSize {
        /// Which image.
        what: String,
        /// Its width, pixels.
        width: usize,
        /// Its height, pixels.
        height: usize,
        /// The camera's width, pixels.
        expected_width: usize,
        /// The camera's height, pixels.
        expected_height: usize,
    },
    /// The camera model is invalid or not usable here (e.g. a distorted pinhole camera).
    #[error("camera: {0}")]
    Camera(String),
    /// A configuration value is out of range.
    #[error("invalid configuration {name}: {why}")]
    InvalidConfig {
        /// The parameter.
        name: &'static str,
        /// What is wrong.
        why: String,
    },
    /// Time stamps do not increase.
    #[error("time stamp {timestamp} s is not after the previous one ({previous} s)")]
    NonIncreasingTime {
        /// The new time stamp, seconds.
        timestamp: f64,
        /// The previous one, seconds.
        previous: f64,
    },
    /// The filter's covariance lost positive definiteness or became non-finite.
    #[error("filter diverged: {0}")]
    Diverged(String),
    /// The synthetic generator failed.
    #[error(transparent)]
    Synth(#[from] crate::synth::SynthError),
    /// Trajectory evaluation failed.
    #[error(transparent)]
    Eval(#[from] crate::eval::EvalError),
    /// Place recognition on a keyframe failed ([`MonoLoopDetector`]).
    #[error("place recognition: {0}")]
    Place(#[from] crate::place::PlaceError),
    /// The metric scale estimation beside the filter failed ([`MetricMono`]).
    #[error("scale: {0}")]
    Scale(#[from] crate::scale::ScaleError),
}

/// Parameters of [`MonoSlam`].
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MonoConfig {
    /// Standard deviation of the linear acceleration noise, m/s^2 (white, continuous time).
    pub sigma_linear_acceleration: f64,
    /// Standard deviation of the angular acceleration noise, rad/s^2.
    pub sigma_angular_acceleration: f64,
    /// Standard deviation of the image measurement noise, pixels.
    pub sigma_pixel: f64,
    /// Initial inverse depth of new landmarks, 1/m (fixes the map's nominal scale).
    pub initial_inverse_depth: f64,
    /// Standard deviation of the initial inverse depth, 1/m.
    pub sigma_inverse_depth: f64,
    /// Most landmarks kept in the filter state.
    pub max_landmarks: usize,
    /// Landmarks the system tries to have predicted visible in each frame; new ones are
    /// initialised in sparsely populated image cells while fewer are visible.
    pub target_visible: usize,
    /// Most new landmarks initialised per frame.
    pub max_new_per_frame: usize,
    /// Half size of the correlation patch, pixels (the patch is `2 h + 1` wide).
    pub patch_half: usize,
    /// Half size of the big patch stored at initialisation for warping, pixels.
    pub big_patch_half: usize,
    /// ZNCC threshold for a match, in `[-1, 1]`.
    pub zncc_threshold: f64,
    /// Patch mode: plain, or one of the catadioptric warps (see [`PatchMode`]). The default,
    /// plain, suits pinhole cameras; for catadioptric ones `PatchMode::Projective` tracks best
    /// on the generated walks (docs/results.md), and `rgbid mono` picks it when `xi > 0`.
    pub patch_mode: PatchMode,
    /// Limit of the warp's scale factors `k` (`1 / k_lim <= k <= k_lim`, eq. 2.67); at most
    /// `big_patch_half / (sqrt(2) patch_half)` keeps the warped patch inside the big patch.
    pub k_lim: f64,
    /// [`PatchMode::Thesis`] and [`PatchMode::Anisotropic`] scale a patch by the landmark's
    /// distance ratio only when its inverse depth has converged: standard deviation over value,
    /// `sigma_rho / rho`, at most this (> 0). At 0.1 a one-sigma error of the inverse depth
    /// moves the distance ratio of a landmark approached by half its distance by about 10 %,
    /// within what an 11 x 11 ZNCC patch tolerates; the ray-like landmarks of a fresh
    /// initialisation (`sigma_rho / rho = 1` with the defaults) keep their scale.
    pub depth_converged_ratio: f64,
    /// Largest half-size of a search region, pixels (bigger ellipses are clipped to it).
    pub max_search_half: f64,
    /// FAST intensity threshold, intensity units.
    pub fast_threshold: f32,
    /// Grid of cells (columns, rows) used to find sparsely populated image areas.
    pub grid: (usize, usize),
    /// Smallest distance between a new feature and any predicted one, pixels.
    pub min_feature_distance: f64,
    /// Inlier threshold of 1-point RANSAC, pixels.
    pub ransac_threshold: f64,
    /// Probability that 1-point RANSAC draws at least one all-inlier hypothesis.
    pub ransac_confidence: f64,
    /// Consecutive frames a landmark may go unmatched (while predicted visible or not)
    /// before it is moved out of the state into the fixed map.
    pub max_unmatched_frames: usize,
    /// A landmark counts as a 3D point (bounded depth) rather than a ray (depth still
    /// compatible with infinity) when `rho > point_sigmas * sigma_rho`; 2 is the 95 % bound.
    pub point_sigmas: f64,
    /// Seed of the RANSAC sampling.
    pub seed: u64,
}

impl Default for MonoConfig {
    fn default() -> Self {
        MonoConfig {
            sigma_linear_acceleration: 2.0,
            sigma_angular_acceleration: 4.0,
            sigma_pixel: 1.0,
            initial_inverse_depth: 0.5,
            sigma_inverse_depth: 0.5,
            max_landmarks: 120,
            target_visible: 40,
            max_new_per_frame: 6,
            patch_half: 5,
            big_patch_half: 15,
            zncc_threshold: 0.8,
            patch_mode: PatchMode::Plain,
            k_lim: 2.0,
            depth_converged_ratio: 0.1,
            max_search_half: 30.0,
            fast_threshold: 20.0,
            grid: (4, 4),
            min_feature_distance: 12.0,
            ransac_threshold: 2.0,
            ransac_confidence: 0.99,
            max_unmatched_frames: 15,
            point_sigmas: 2.0,
            seed: 1,
        }
    }
}

impl MonoConfig {
    /// Checks the values.
    pub fn validate(&self) -> Result<(), MonoError> {
        let pos = |name: &'static str, v: f64| {
            if v.is_finite() && v > 0.0 {
                Ok(())
            } else {
                Err(MonoError::InvalidConfig {
                    name,
                    why: format!("{v} must be finite and > 0"),
                })
            }
        };
        pos("sigma_linear_acceleration", self.sigma_linear_acceleration)?;
        pos(
            "sigma_angular_acceleration",
            self.sigma_angular_acceleration,
        )?;
        pos("sigma_pixel", self.sigma_pixel)?;
        pos("initial_inverse_depth", self.initial_inverse_depth)?;
        pos("sigma_inverse_depth", self.sigma_inverse_depth)?;
        pos("max_search_half", self.max_search_half)?;
        pos("ransac_threshold", self.ransac_threshold)?;
        pos("min_feature_distance", self.min_feature_distance)?;
        pos("point_sigmas", self.point_sigmas)?;
        pos("depth_converged_ratio", self.depth_converged_ratio)?;
        if !(self.k_lim.is_finite() && self.k_lim >= 1.0) {
            return Err(MonoError::InvalidConfig {
                name: "k_lim",
                why: format!("{} must be >= 1", self.k_lim),
            });
        }
        if !(self.zncc_threshold > -1.0 && self.zncc_threshold < 1.0) {
            return Err(MonoError::InvalidConfig {
                name: "zncc_threshold",
                why: format!("{} must be in (-1, 1)", self.zncc_threshold),
            });
        }
        if !(self.ransac_confidence > 0.0 && self.ransac_confidence < 1.0) {
            return Err(MonoError::InvalidConfig {
                name: "ransac_confidence",
                why: format!("{} must be in (0, 1)", self.ransac_confidence),
            });
        }
        if self.patch_half == 0 || self.big_patch_half < self.patch_half {
            return Err(MonoError::InvalidConfig {
                name: "patch_half",
                why: "patch_half must be >= 1 and big_patch_half >= patch_half".into(),
            });
        }
        if self.max_landmarks == 0 || self.grid.0 == 0 || self.grid.1 == 0 {
            return Err(MonoError::InvalidConfig {
                name: "max_landmarks/grid",
                why: "must be non-zero".into(),
            });
        }
        Ok(())
    }
}
