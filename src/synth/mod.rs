//! Synthetic RGB-D and omnidirectional sequences with exact ground truth.
//!
//! * [`Scene`]: procedural indoor scenes from a seed (presets `office`, `kitchen`,
//!   `corridor`, `lab`, `home`, or full [`SceneParams`]), and "sessions" of the same scene with
//!   movable objects moved, removed or added ([`Scene::session`]).
//! * Rendering by per-pixel ray casting through any central camera ([`CameraModel`]: pinhole
//!   with optional distortion, or the unified sphere model) on the CPU ([`render_pinhole`],
//!   [`render`]) or the GPU ([`Renderer`] with [`RenderBackend::Gpu`], kernel
//!   `shaders/raycast.wgsl`), followed by a Kinect-like [`SensorModel`].
//! * [`trajectory`]: handheld splines, loops, walking head/chest cameras, planar robots.
//! * [`Sequence`]: streams `(timestamp, world_from_camera, frame)` in memory.
//!
//! Conventions: world frame z up with the floor at z = 0; camera frame x right, y down,
//! z forward; poses are `world_from_camera`; metres, radians, seconds; inverse depth in 1/m
//! with 0 = no measurement; intensity in `[0, 255]`.

mod bvh;
mod distance;
mod gpu;
pub mod layout_export;
pub(crate) mod raycast;
mod render;
mod scene;
mod sensor;
pub(crate) mod sequence;
pub mod trajectory;
pub mod tum_export;

pub use bvh::Aabb;
pub use raycast::NO_OBJECT;
pub use render::{render, render_pinhole, CameraModel, RenderBackend, RenderedFrame, Renderer};
pub use scene::{
    FreeArea, FurnitureStyle, Layout, ObjectKind, Primitive, Scene, SceneObject, SceneParams,
    Shape, Staircase, PRESETS,
};
pub use sensor::{SensorModel, DEPTH_FACTOR};
pub use sequence::{Sequence, SequenceConfig, SequenceFrame};
pub use trajectory::{Trajectory, TrajectoryKind};

/// Errors of the synthetic data generator.
#[derive(Debug, thiserror::Error)]
pub enum SynthError {
    /// The preset name is not known.
    #[error("unknown scene preset '{name}' (known: {known})")]
    UnknownPreset {
        /// The name asked for.
        name: String,
        /// The known names.
        known: String,
    },
    /// The trajectory name is not known.
    #[error("unknown trajectory '{name}' (known: {known})")]
    UnknownTrajectory {
        /// The name asked for.
        name: String,
        /// The known names.
        known: String,
    },
    /// A generator or sensor parameter is out of range.
    #[error("invalid parameter {name}: {why}")]
    InvalidParameter {
        /// Parameter name.
        name: &'static str,
        /// What is wrong.
        why: String,
    },
    /// The camera parameters are invalid.
    #[error(transparent)]
    Camera(#[from] crate::camera::CameraError),
    /// The GPU ray caster failed.
    #[error(transparent)]
    Gpu(#[from] crate::gpu::GpuError),
}
