//! RGB-ID SLAM (thesis ch. 6): a front-end that tracks every frame with the dense odometry
//! and fuses frames into keyframes (GPU or CPU), and a back-end thread that, per keyframe,
//! segments superjuts, describes the keyframe with ORB + masked bags of words, detects and
//! verifies loops, refines them by dense alignment and optimises the keyframe pose graph
//! when a loop cluster closes. At the end all frames are optimised with the keyframes fixed.
//!
//! ```no_run
//! # use rgbid::{slam::*, camera::PinholeCamera, gpu::*, place::Vocabulary};
//! # fn f(frames: Vec<rgbid::image::RgbdFrame>) -> Result<(), SlamError> {
//! let backend = select_backend(BackendChoice::Auto, None)?;
//! let camera = PinholeCamera::new(525.0, 525.0, 319.5, 239.5, 640, 480);
//! let mut slam = Slam::new(SlamConfig::default(), camera, &backend, Vocabulary::embedded_default()?, None)?;
//! for f in &frames {
//!     let report = slam.process(f)?;
//!     println!("{:?} {:?}", report.status, report.world_from_camera);
//! }
//! let result = slam.finish()?;
//! println!("{} keyframes, {} loops", result.keyframes().len(), result.loops.len());
//! # Ok(()) }
//! ```

mod backend;
pub mod events;
pub(crate) mod fusion;
#[cfg(test)]
mod fusion_tests;
pub(crate) mod keyframe;
pub(crate) mod map;
mod memory;
pub(crate) mod model;
mod rows;
mod system;

pub use backend::{KeyframeTiming, LoopRecord, LoopVerdict};
pub use events::{
    EventDrops, EventOptions, KeyframeDescribed, SlamEvent, SlamEvents, SuperjutLabels,
};
#[doc(hidden)]
pub use fusion::KeyframeFuser;
pub use fusion::{FusionCounts, FusionParams};
pub use keyframe::{Keyframe, KeyframeLink};
pub use map::{Map, MapError, MAP_VERSION};
pub use memory::{MemoryBreakdown, MemoryReport};
pub use model::{
    build_coloured_model, build_mesh, build_model, build_volume, voxel_filter, ModelParams,
};
pub use system::{FrameRecord, FrameReport, FrameStatus, OdometryDiagnostics, Slam, SlamResult};

use crate::odometry::OdometryConfig;
use crate::place::LoopDetectorParams;
use crate::segment::SegmentConfig;

/// Errors of the SLAM system.
#[derive(Debug, thiserror::Error)]
pub enum SlamError {
    /// The odometry failed in a way that is not a tracking loss (configuration, device).
    #[error("odometry: {0}")]
    Odometry(#[from] crate::odometry::OdometryError),
    /// GPU failure (device lost, shader, timeout).
    #[error("gpu: {0}")]
    Gpu(#[from] crate::gpu::GpuError),
    /// Place recognition failed.
    #[error("place recognition: {0}")]
    Place(#[from] crate::place::PlaceError),
    /// Segmentation failed.
    #[error("segmentation: {0}")]
    Segment(#[from] crate::segment::SegmentError),
    /// Pose-graph optimisation failed.
    #[error("pose graph: {0}")]
    Graph(#[from] crate::graph::GraphError),
    /// Map file problem.
    #[error("map: {0}")]
    Map(#[from] MapError),
    /// A frame does not match the camera.
    #[error("frame {index}: size {got_w}x{got_h}, the camera is {want_w}x{want_h}")]
    FrameSize {
        /// Frame index.
        index: usize,
        /// Frame width.
        got_w: usize,
        /// Frame height.
        got_h: usize,
        /// Camera width.
        want_w: usize,
        /// Camera height.
        want_h: usize,
    },
    /// An invalid configuration value.
    #[error("invalid configuration: {0}")]
    InvalidConfig(String),
    /// The back-end thread stopped (it panicked or returned an error earlier).
    #[error("back-end thread stopped: {0}")]
    BackendStopped(String),
    /// An internal inconsistency (a bug): please report it.
    #[error("internal: {0}")]
    Internal(String),
}

/// Configuration of the SLAM system (defaults as the thesis where it gives a value).
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SlamConfig {
    /// Dense odometry (frame-to-reference tracking, reference switch at covisibility 0.9).
    pub odometry: OdometryConfig,
    /// A new keyframe is made when the current keyframe's covisibility with the frame drops
    /// below this (0.7).
    pub keyframe_covisibility: f64,
    /// Keyframe inverse-depth fusion.
    #[serde(with = "FusionParamsDef")]
    pub fusion: FusionParams,
    /// Most frames buffered since the last keyframe and fused into the next one.
    pub buffer_frames: usize,
    /// When the buffered frames are fused into a new keyframe.
    pub buffered_fusion: BufferedFusion,
    /// Tracking is declared lost when the covisibility with the reference falls below this.
    pub lost_covisibility: f64,
    /// Tracking is declared lost when the Hessian condition number exceeds this.
    pub lost_condition: f64,
    /// Tracking is declared lost when the camera would have moved faster than this (m/s)
    /// since the last tracked frame: a wrong convergence of the alignment (e.g. 12 cm per
    /// frame at 30 fps on a walk at 0.95 m/s) keeps a high covisibility, so this physical
    /// bound is what catches it. `f64::INFINITY` disables it.
    pub lost_max_speed: f64,
    /// Same for the rotation rate (rad/s).
    pub lost_max_angular_speed: f64,
    /// Bounded queue of finished keyframes between front-end and back-end.
    pub queue: usize,
    /// Superjut segmentation and neg-entropy masks in the back-end.
    pub masks: bool,
    /// Neg-entropy thresholds of the masks (one BoW histogram each, plus the unmasked one).
    pub mask_thresholds: Vec<f64>,
    /// Segmentation parameters.
    pub segment: SegmentConfig,
    /// Place recognition (ORB, database query, verification).
    pub detector: LoopDetectorParams,
    /// Loops whose query keyframes are within this many keyframes form one cluster; the graph
    /// is optimised when the cluster closes, or after it has been open for twice this many.
    pub loop_cluster_gap: usize,
    /// A loop is rejected when the dense refinement moves the RANSAC pose by more than this
    /// (metres) ...
    pub loop_max_refine_translation: f64,
    /// ... or this (radians).
    pub loop_max_refine_rotation: f64,
    /// A loop is rejected when the dense covisibility of the two keyframes is below this.
    pub loop_min_covisibility: f64,
    /// While lost, relocalisation is tried on every n-th frame.
    pub relocalise_every: usize,
    /// Information of the frame-level pose graph that places every frame between the
    /// optimised keyframes at the end of a run (thesis eq. 6.28).
    pub frame_edges: FrameEdges,
    /// Keep the RGB of each keyframe's reference frame when the input has colour (3 bytes per
    /// pixel on top of the keyframe's 4: coloured `model.ply`, meshes and map colours);
    /// `false` keeps keyframes grey, and every model built from them takes its colour from
    /// the intensity.
    pub keyframe_colour: bool,
}

/// When a new keyframe takes in the frames buffered since the previous one (thesis 6.24-6.25:
/// the frames between two keyframes are fused into both).
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum BufferedFusion {
    /// All of them when the keyframe starts: the keyframe's first frame pays for every
    /// buffered frame's fusion at once.
    AtStart,
    /// The thesis' schedule: one buffered frame (the newest not yet fused) with each incoming
    /// frame, so every frame pays at most two fusions; frames still waiting when the keyframe
    /// ends are fused then. The keyframe takes in the same frames in another order, and its
    /// covisibility with incoming frames is measured before all of them are in. The default:
    /// the same accuracy on the real sequences (docs/notes.md) without the keyframe's
    /// first frame taking several fusions' time.
    OnePerFrame,
}

/// Information of the edges of the frame-level pose graph (thesis eq. 6.28): frame to
/// keyframe, and frame to previous frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum FrameEdges {
    /// Fixed diagonal sigmas: 2 mm and 2 mrad between consecutive frames, and
    /// `0.002 sqrt(1 + n)` to the keyframe for the n-th frame since it.
    Fixed,
    /// The thesis' formulation: the odometry covariances (eq. 6.22-6.23). A frame's edge to
    /// its keyframe carries the covariance composed along the odometry references since the
    /// keyframe; the edge to the previous frame the alignment covariance of the frame (its
    /// reference is the previous frame) or, when both frames were aligned to the same
    /// reference, the sum of both alignments' covariances (first order, correlation ignored).
    /// Frames without a covariance fall back to [`FrameEdges::Fixed`]'s sigmas. The default:
    /// the thesis' formulation, not worse than the fixed sigmas on either real sequence
    /// (docs/notes.md).
    Odometry,
}

/// The serde form of [`FusionParams`] in a configuration: every key optional, unknown keys
/// rejected.
#[derive(serde::Serialize, serde::Deserialize)]
#[serde(remote = "FusionParams", default, deny_unknown_fields)]
struct FusionParamsDef {
    tol_abs: f32,
    tol_rel: f32,
    new_weight: f32,
    max_weight: f32,
    tol_sigmas: f32,
    occlusion: bool,
    both_directions: bool,
}

impl Default for FusionParamsDef {
    fn default() -> Self {
        let d = FusionParams::default();
        FusionParamsDef {
            tol_abs: d.tol_abs,
            tol_rel: d.tol_rel,
            new_weight: d.new_weight,
            max_weight: d.max_weight,
            tol_sigmas: d.tol_sigmas,
            occlusion: d.occlusion,
            both_directions: d.both_directions,
        }
    }
}

impl Default for SlamConfig {
    fn default() -> Self {
        let mut detector = LoopDetectorParams::default();
        detector.query.min_separation = 8;
        // Each level's strongest corners (OpenCV's selection), not the place-recognition
        // default's grid: with the grid, relocalisation after a covered sensor failed on the
        // generated `office` loop (tests/slam_system.rs), with this it succeeds.
        detector.orb.distribute = false;
        // The odometry's defaults: four pyramid levels (a wide basin for fast motion: the
        // generated `lab` loop at 0.95 m/s diverged with three) and no level wider than 320.
        let odometry = OdometryConfig::default();
        SlamConfig {
            odometry,
            keyframe_covisibility: 0.7,
            fusion: FusionParams::default(),
            buffer_frames: 30,
            buffered_fusion: BufferedFusion::OnePerFrame,
            lost_covisibility: 0.25,
            lost_condition: 1e9,
            // A handheld or head-worn camera: walking is < 2 m/s, fast head turns < 4 rad/s.
            lost_max_speed: 3.0,
            lost_max_angular_speed: 4.0,
            queue: 8,
            masks: true,
            mask_thresholds: vec![0.5],
            segment: SegmentConfig::default(),
            detector,
            loop_cluster_gap: 10,
            loop_max_refine_translation: 0.15,
            loop_max_refine_rotation: 0.15,
            loop_min_covisibility: 0.3,
            relocalise_every: 1,
            frame_edges: FrameEdges::Odometry,
            keyframe_colour: true,
        }
    }
}

impl SlamConfig {
    /// Checks the values.
    pub fn validate(&self) -> Result<(), SlamError> {
        self.odometry.validate()?;
        let in01 = |v: f64| (0.0..=1.0).contains(&v);
        if !in01(self.keyframe_covisibility) || !in01(self.lost_covisibility) {
            return Err(SlamError::InvalidConfig(
                "covisibility thresholds must be in [0, 1]".into(),
            ));
        }
        if self.queue == 0 {
            return Err(SlamError::InvalidConfig("queue must be >= 1".into()));
        }
        if !(self.lost_max_speed > 0.0 && self.lost_max_angular_speed > 0.0) {
            return Err(SlamError::InvalidConfig(
                "lost_max_speed and lost_max_angular_speed must be > 0 (infinity disables)".into(),
            ));
        }
        if self.masks {
            self.segment.validate()?;
        }
        Ok(())
    }
}

/// The information matrix of `covariance` as the pose graph takes it (row-major); a fallback
/// diagonal (`sigma_t` metres, `sigma_r` radians) when it is missing or not positive definite.
pub(crate) fn information_from(
    covariance: Option<&crate::geometry::Covariance6>,
    sigma_t: f64,
    sigma_r: f64,
) -> Vec<f64> {
    let fallback = || {
        let mut m = vec![0.0; 36];
        for i in 0..6 {
            let s = if i < 3 { sigma_t } else { sigma_r };
            m[i * 6 + i] = 1.0 / (s * s);
        }
        m
    };
    match covariance.and_then(|c| c.information()) {
        Some(info) => info.iter().flatten().copied().collect(),
        None => fallback(),
    }
}
