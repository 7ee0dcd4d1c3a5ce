//! The one GPU-test helper of the crate and the viewer.
//!
//! Tests that need a GPU adapter are named `gpu_*` and marked
//! `#[ignore = "needs a GPU adapter"]`, so a machine without an adapter reports them ignored,
//! never passed. CI runs them on lavapipe with `cargo test --workspace --tests -- --ignored gpu_`
//! and `RGBID_REQUIRE_GPU=1`, where a missing adapter is a failure (`tests/ci_stages.rs` keeps
//! the names, the ignore reasons and the CI stages consistent).

use std::sync::Arc;

use super::backend::{select_backend, BackendChoice, ComputeBackend};
use super::context::{GpuContext, GpuError};

/// The environment variable that turns a missing adapter in a GPU test into a failure.
#[doc(hidden)]
pub const REQUIRE_GPU_ENV: &str = "RGBID_REQUIRE_GPU";

/// A context on any adapter (lavapipe included) for the GPU test `test`. Without one: panics
/// when `RGBID_REQUIRE_GPU=1`, otherwise prints `SKIPPED test: no GPU adapter` and returns
/// `None` (the test then returns early).
#[doc(hidden)]
pub fn test_gpu(test: &str) -> Option<Arc<GpuContext>> {
    match select_backend(BackendChoice::Gpu, None) {
        Ok(ComputeBackend::Gpu(g)) => Some(g),
        Ok(ComputeBackend::Cpu) => {
            no_test_gpu(test, "the GPU backend resolved to the CPU");
            None
        }
        Err(GpuError::NoGpuAdapter { .. }) => {
            no_test_gpu(
                test,
                "wgpu found none; `apt-get install mesa-vulkan-drivers` gives lavapipe",
            );
            None
        }
        Err(e) => {
            no_test_gpu(test, &e.to_string());
            None
        }
    }
}

/// What a GPU test does when it finds no adapter (also for helpers that create their own
/// device, such as the viewer's egui render state): panics when `RGBID_REQUIRE_GPU=1`,
/// otherwise prints a loud `SKIPPED` line.
#[doc(hidden)]
pub fn no_test_gpu(test: &str, why: &str) {
    if std::env::var(REQUIRE_GPU_ENV).as_deref() == Ok("1") {
        panic!("{test}: {REQUIRE_GPU_ENV}=1 but no GPU adapter ({why})");
    }
    eprintln!("SKIPPED {test}: no GPU adapter ({why}); {REQUIRE_GPU_ENV}=1 makes this a failure");
}
