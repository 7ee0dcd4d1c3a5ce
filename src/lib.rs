//! # rgbid
//!
//! GPU-portable implementations of the localisation and mapping systems of the thesis
//! *Real-time Metric Localisation with Wearable Vision Systems* (Gutiérrez-Gómez, 2016):
//! dense RGB-D odometry with inverse depth ([`odometry`]), RGB-ID SLAM ([`slam`]), pose-graph
//! and curve-graph optimisation ([`graph`]), place recognition ([`place`]), superjut
//! segmentation ([`segment`]), monocular EKF SLAM ([`mono`]) and metric scale from walking
//! ([`scale`]).
//!
//! Features: `cli` (default) builds the `rgbid` program and enables `experiments` (the thesis'
//! experiment harnesses on generated data) and `clap` (`clap::ValueEnum` on the option enums).
//! With `default-features = false` the library has none of the command line's dependencies.
//!
//! Conventions (see `ARCHITECTURE.md`): transforms are named `a_from_b` (`p_a = a_from_b * p_b`);
//! metres, radians, seconds; inverse depth in 1/m with 0 = no measurement; intensity in
//! `[0, 255]`; camera frame x right, y down, z forward; integer pixel coordinates are pixel
//! centres. Pixel work runs as WGSL compute kernels through `wgpu`, each with a rayon CPU
//! mirror that is both the test oracle and the `--backend cpu` implementation.
#![warn(missing_docs)]
// `!(x > 0.0)` is used on purpose: it also rejects NaN, which input can contain.
#![allow(clippy::neg_cmp_op_on_partial_ord)]
// Kernel mirrors index arrays the way the WGSL does, so the two read alike.
#![allow(clippy::needless_range_loop)]

// Modules by layer; each imports only from its own layer (without cycles) and the layers
// above it in this list (ARCHITECTURE.md; enforced by tests/layers.rs).
// Foundation.
pub mod camera;
pub mod geometry;
pub mod image;
pub mod trajectory;
// Plumbing and formats.
pub mod eval;
pub mod gpu;
pub mod io;
// Algorithms.
pub mod graph;
pub mod live;
pub mod odometry;
pub mod place;
pub mod segment;
pub mod source;
pub mod synth;
pub mod tsdf;
// Systems.
pub mod mono;
pub mod scale;
pub mod slam;
// Experiments.
#[cfg(feature = "experiments")]
pub mod experiments;

/// Internal stages for the repository's own profiling examples (feature `internals`); not a
/// stable API.
#[cfg(feature = "internals")]
#[doc(hidden)]
pub mod internals {
    pub use crate::segment::features as segment_features;
    pub use crate::segment::graph as segment_graph;
}
