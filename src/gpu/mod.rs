//! Shared GPU plumbing: the headless `wgpu` context, backend selection, shader assembly,
//! buffer helpers and read-back.
//!
//! Kernels live in `shaders/*.wgsl` and are embedded at compile time. Each algorithm keeps its
//! own host code next to it (`odometry/gpu.rs`); this module only holds what they share.
//! Buffers are f32; reductions produce per-workgroup partial sums that the CPU finishes in f64.

mod backend;
mod context;
pub(crate) mod shaders;
mod testing;

pub use backend::{describe_adapters, select_backend, BackendChoice, ComputeBackend};
#[doc(hidden)]
pub use context::LOSE_DEVICE_ENV;
pub use context::{GpuContext, GpuError};
#[cfg(test)]
pub(crate) use testing::{host_layout, layout_mismatches};
#[doc(hidden)]
pub use testing::{no_test_gpu, test_gpu, REQUIRE_GPU_ENV};
