//! True metric scale for a walking person wearing a monocular camera (thesis ch. 3).
//!
//! A monocular trajectory (TUM file, or the output of the monocular EKF) has no metric scale
//! and its scale drifts. For a camera worn on the head or the chest the vertical oscillation of
//! the body happens at the step frequency `f` (steps per second), and walking speed follows
//! `V = alpha f^beta H` (eq. 3.11, Grieve: `alpha = 0.2896`, `beta = 1.7544`, `H` the height
//! in metres). Comparing that metric speed with the trajectory's own (unscaled) speed over a
//! sliding window gives the scale, which a particle filter over `(V_SLAM, log10 s)` tracks as
//! it drifts (eq. 3.20-3.30); the trajectory is then rescaled section by section
//! (eq. 3.31-3.33, Algorithm 1).
//!
//! - [`StepAnalysis`]: offset removal, second-order high-pass at 0.7 Hz, PSD by FFT, step
//!   frequency peak in 1-3 Hz, Parseval power and walking / standing detection (3.15-3.19).
//! - [`WalkingModel`]: the speed model and its calibration by a power fit ([`calibrate`];
//!   3.11, 3.4.1).
//! - [`ScaleFilter`]: the particle filter over `(V_SLAM, log10 s)`.
//! - [`DynScale`]: Algorithm 1 (sliding window `t_DFT`, update every `t_upd`), recursive
//!   section scaling of positions, velocities and landmarks (3.31-3.35).
//! - [`LiveDynScale`]: the same on a live stream, with bounded work per update and the up
//!   axis found online.
//! - [`emulate_monocular`]: an emulator of monocular SLAM output (pose noise + drifting scale)
//!   from a ground-truth trajectory, for experiments.
//! - [`optim_sim3`]: Sim(3) loop closure (`optimSim3`) through [`crate::graph::PoseGraphSim3`],
//!   on emulated loops; [`optim_sim3_with`]: the same graph on measured relative similarities.
//! - [`arc_length_error`]: position error against ground truth by normalised arc length (3.36).
//! - [`arc_length_error_from_start`]: the same, placed on the ground truth at the first pose and
//!   never rescaled (how the thesis scores a walk); [`time_matched_error_from_start`]: the
//!   same placement, compared at equal times.
//!
//! Frames: trajectories are `world_from_camera` in the trajectory's own world frame (for a
//! monocular SLAM output, usually the first camera: x right, y down, z forward). Units: seconds,
//! Hz (steps per second), metres for metric quantities, "SLAM units" for unscaled ones. The
//! scale `s` maps SLAM units to metres: `p_metric = s p_slam`.

pub(crate) mod drift;
pub(crate) mod dynscale;
pub(crate) mod live;
pub(crate) mod loops;
pub(crate) mod metric;
pub(crate) mod particle;
pub(crate) mod spectrum;
pub(crate) mod walking;

pub use drift::{emulate_monocular, DriftModel, EmulatedRun};
pub use dynscale::{
    check_trajectory, interpolate_position, DynScale, DynScaleConfig, DynScaleResult, Section,
    UpAxis,
};
pub use live::{LiveDynScale, SectionTransform};
pub use loops::{
    detect_loops_from_ground_truth, optim_sim3, optim_sim3_with, LoopConfig, SimilarityConstraint,
};
pub use metric::{
    arc_length_error, arc_length_error_from_start, time_matched_error_from_start, ArcLengthError,
};
pub use particle::{FilterUpdate, ParticleConfig, ScaleFilter};
pub use spectrum::{HighPass, SpectrumConfig, StepAnalysis};
pub use walking::{calibrate, CalibrationSample, WalkingModel, GRIEVE_ALPHA, GRIEVE_BETA};

/// Errors of the scale estimation.
#[derive(Debug, thiserror::Error)]
pub enum ScaleError {
    /// The trajectory has no poses, or too few for one analysis window.
    #[error("trajectory too short: {have} poses over {seconds:.2} s, need {need}")]
    TooShort {
        /// Number of poses given.
        have: usize,
        /// Time span of the poses, seconds.
        seconds: f64,
        /// What is needed.
        need: String,
    },
    /// Time stamps that are not finite or not increasing.
    #[error("time stamps must be finite and increasing: {0}")]
    BadTimestamps(String),
    /// A parameter outside its valid range.
    #[error("invalid parameter {name}: {why}")]
    InvalidParameter {
        /// Parameter name.
        name: &'static str,
        /// Why it is invalid.
        why: String,
    },
    /// Calibration data that cannot determine alpha and beta.
    #[error("calibration: {0}")]
    Calibration(String),
    /// The up axis cannot be determined from the trajectory.
    #[error("cannot determine the up axis: {0}")]
    UpAxis(String),
    /// No window of the trajectory looked like walking: the scale is unobservable.
    #[error("no walking detected in {windows} analysis windows: the scale is unobservable")]
    NoWalking {
        /// Number of windows analysed.
        windows: usize,
    },
    /// Non-finite values in the input.
    #[error("non-finite value in {0}")]
    NonFinite(String),
    /// The monocular estimator (rendering or the EKF) failed.
    #[error("monocular estimate: {0}")]
    Monocular(String),
    /// The Sim(3) pose-graph optimisation failed.
    #[error("pose graph: {0}")]
    Graph(#[from] crate::graph::GraphError),
    /// A run file of the experiment cache could not be read or written.
    #[error("run cache {path}: {message}")]
    Cache {
        /// The cache file.
        path: std::path::PathBuf,
        /// What went wrong (with the line number for parse errors).
        message: String,
    },
}

pub(crate) fn check_param(
    name: &'static str,
    ok: bool,
    why: impl FnOnce() -> String,
) -> Result<(), ScaleError> {
    if ok {
        Ok(())
    } else {
        Err(ScaleError::InvalidParameter { name, why: why() })
    }
}
