//! Dense RGB-D visual odometry with photometric and inverse-depth geometric error
//! (thesis ch. 4 and 6.3).
//!
//! For each pixel of a *reference* frame with a valid inverse depth, the point is warped into
//! the *current* frame by `cur_from_ref` ("reverse warping", eq. 6.5-6.9: bilinear intensity,
//! nearest inverse depth). Two residuals are formed: photometric `I_cur(w(x)) - I_ref(x)` and
//! geometric `rho_cur(w(x)) - 1/z'` in inverse depth (or in depth, for comparison). Their
//! Jacobians (6.12, 6.13) feed an IRLS Gauss-Newton solve (6.14) with Student-t (default), Huber,
//! Tukey or least-squares weights; scales come from maximum likelihood (6.15, 6.16), MAD (4.25)
//! or, for Huber and Tukey, a Gaussian-consistent M-scale, on a systematic sample of at most 19200 pixels. Coarse-to-fine over an image pyramid, with a
//! constant-velocity initial guess and the reference frame switched when the dense covisibility
//! ratio (6.10) drops below a threshold (6.4.1).
//!
//! Frames: `cur_from_ref` maps points from the reference camera to the current camera; poses
//! are `world_from_camera`. The Gauss-Newton increments are twists `[v; w]` (m, rad) of
//! `cur_from_ref` applied on the left, which is the library's right perturbation of
//! `ref_from_cur` ([`crate::geometry`]); covariances leave this module in that convention.
//!
//! The algorithm is written once against a kernel interface implemented by the WGSL kernels
//! (`shaders/pyramid.wgsl`, `shaders/odometry.wgsl`) and by their rayon CPU mirror;
//! [`Odometry`] picks one at run time from a [`crate::gpu::ComputeBackend`].

mod backend;
mod config;
mod cpu;
mod gpu;
mod inspect;
mod kernel;
mod model;
#[cfg(test)]
mod oracle;
#[cfg(test)]
mod parity_tests;
mod robust;
mod rolling_shutter;
mod rows;
mod solver;
mod tracker;

/// Whether the CPU has AVX2 (the lane loops' condition; they also run with the feature
/// enabled per function, so the build needs no target flags).
pub(crate) fn avx2() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::is_x86_feature_detected!("avx2")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// Runs `f` on a worker of rayon's global pool (at once when the caller is one). The
/// parallel passes inside it then fork from a worker; called from another thread, each of
/// them would queue its job into the pool and put the caller to sleep until the job ends,
/// a pair of context switches per pass. `f` must not wait for other work on the pool: with
/// every worker busy (one worker, say) that work would never run.
pub(crate) fn in_pool<R: Send>(f: impl FnOnce() -> R + Send) -> R {
    if rayon::current_thread_index().is_some() {
        f()
    } else {
        rayon::scope(|_| f())
    }
}

pub use config::{
    CovarianceGradients, CovisibilityTest, GeometricParam, GeometricSampling, Linearisation,
    Location, OdometryConfig, Terms, OCCLUSION_SIGMAS,
};
pub use inspect::{residual_images, ResidualImages, RobustScales};
pub use model::{model_reference, ModelOdometry, ModelParams, ModelTimes, ModelTrackResult};
pub use robust::{Estimator, ScaleMethod};
pub use tracker::{
    Alignment, FrameStats, LevelStats, Odometry, PreparedFrame, StageTimes, TrackResult,
};

use crate::gpu::GpuError;

/// Errors of the odometry.
#[derive(Debug, thiserror::Error)]
pub enum OdometryError {
    /// The GPU failed (device lost, validation error...).
    #[error(transparent)]
    Gpu(#[from] GpuError),
    /// A frame's size differs from the camera's.
    #[error("frame is {got_w}x{got_h} but the camera is {want_w}x{want_h}")]
    FrameSize {
        /// Camera width.
        want_w: usize,
        /// Camera height.
        want_h: usize,
        /// Frame width.
        got_w: usize,
        /// Frame height.
        got_h: usize,
    },
    /// The configuration is inconsistent.
    #[error("invalid odometry configuration: {0}")]
    InvalidConfig(String),
    /// The image is too small for the requested number of pyramid levels.
    #[error("image {width}x{height} is too small for {levels} pyramid levels")]
    TooManyLevels {
        /// Width.
        width: usize,
        /// Height.
        height: usize,
        /// Requested levels.
        levels: usize,
    },
    /// A prepared frame was given to an odometry on the other backend.
    #[error("the frame was prepared by an odometry on the other backend")]
    OtherBackend,
    /// No level had enough valid residuals to estimate the motion (no overlap or no depth).
    #[error("tracking failed: {0}")]
    TrackingFailed(String),
    /// The model of frame-to-model tracking failed (integration or ray cast).
    #[error("frame-to-model tracking: {0}")]
    Model(#[from] crate::tsdf::TsdfError),
    /// An image built for frame-to-model tracking is malformed.
    #[error(transparent)]
    Image(#[from] crate::image::ImageError),
}
