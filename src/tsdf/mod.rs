//! Dense surface reconstruction: a sparse truncated signed distance field (TSDF) of voxel
//! blocks (thesis 4.5.5, 5.3.1), integration of RGB-D frames, ray casting and meshes.
//!
//! * Storage: blocks of 8^3 voxels, found through a hash map from integer block coordinates to
//!   a block slot on the host (as Open3D's `VoxelBlockGrid` and InfiniTAM, without the moving
//!   volume of the thesis: a sparse grid bounds memory by the observed surface, not by a
//!   region of space). Each voxel holds the truncated signed distance in metres, its weight and
//!   an RGB colour.
//! * Block allocation is done by the host from each frame's depth before integration (the
//!   band `z +- mu(z)` along every pixel's ray), so no kernel needs a GPU hash table or float
//!   atomics; the kernel then updates exactly the blocks the frame touches.
//! * Integration (`integrate.rs`): one kernel interface with the rayon CPU mirror and the WGSL
//!   kernel `shaders/tsdf.wgsl` (same f32 operations in the same order).
//! * Noise model: a Kinect-like sensor has constant inverse-depth noise `sigma_rho` (1/m,
//!   the odometry's geometric scale), so depth noise grows as `sigma_z = sigma_rho z^2`. The
//!   truncation is `mu(z) = max(trunc_min, trunc_sigmas sigma_z)` and a measurement's weight
//!   is its inverse depth variance relative to a measurement at 1 m, `(1 m / z)^4`.
//! * Meshes (`mesh.rs`): marching tetrahedra (six tetrahedra per voxel cube); the per-cube
//!   work is the CPU mirror of `shaders/tsdf_mesh.wgsl`, vertices shared between faces,
//!   per-vertex normals and colours on the host.
//! * Ray casting (`raycast.rs`): depth, normals and colour from any pose, the CPU mirror of
//!   `shaders/tsdf_cast.wgsl`.
//!
//! Frames: the volume lives in the world frame; frames are integrated at `world_from_camera`.
//! Units: metres; inverse depth in 1/m with 0 = no measurement.

mod accuracy;
mod gpu;
mod integrate;
mod mesh;
mod paging;
mod persist;
mod raycast;
mod volume;

pub use accuracy::{mesh_accuracy, thin_points, MeshAccuracy};
pub use mesh::Mesh;
pub use paging::PagingStats;
pub use raycast::RayCastImages;
pub use volume::{IntegrateTimes, TsdfParams, TsdfVolume};

/// Voxels along one side of a block.
pub const BLOCK_SIDE: usize = 8;
/// Voxels in a block.
pub const BLOCK_VOXELS: usize = BLOCK_SIDE * BLOCK_SIDE * BLOCK_SIDE;

/// Errors of the TSDF volume.
#[derive(Debug, thiserror::Error)]
pub enum TsdfError {
    /// A parameter is out of range.
    #[error("invalid TSDF parameter {name}: {why}")]
    InvalidParameter {
        /// Parameter name.
        name: &'static str,
        /// What is wrong.
        why: String,
    },
    /// The frame's size differs from the camera's.
    #[error("frame is {got_w}x{got_h}, the volume's camera is {want_w}x{want_h}")]
    FrameSize {
        /// Frame width, pixels.
        got_w: usize,
        /// Frame height, pixels.
        got_h: usize,
        /// Camera width, pixels.
        want_w: u32,
        /// Camera height, pixels.
        want_h: u32,
    },
    /// A block lies farther from the world origin than block keys reach (2^20 blocks along
    /// an axis).
    #[error("a measured point lies beyond the volume's coordinate range")]
    OutOfRange,
    /// The pose is not finite.
    #[error("world_from_camera is not finite")]
    NonFinitePose,
    /// An image given to the volume is malformed (e.g. a colour image of another size).
    #[error(transparent)]
    Image(#[from] crate::image::ImageError),
    /// Writing a file failed.
    #[error(transparent)]
    Io(#[from] crate::io::IoError),
    /// The GPU backend failed.
    #[error(transparent)]
    Gpu(#[from] crate::gpu::GpuError),
}
