//! Helpers shared by the integration tests.
#![allow(dead_code)]

use std::path::PathBuf;

use rgbid::gpu::{any_gpu, GpuContext};
use std::sync::Arc;

/// `../shared/data` beside the checkout.
pub fn shared_data() -> PathBuf {
    PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../shared/data"))
}

/// A GPU context for parity tests. Without an adapter: panics when `RGBID_REQUIRE_GPU=1`
/// (CI, which installs lavapipe), otherwise prints a loud skip line and returns `None`.
pub fn gpu_or_skip(test: &str) -> Option<Arc<GpuContext>> {
    match any_gpu() {
        Some(g) => Some(g),
        None => {
            if std::env::var("RGBID_REQUIRE_GPU").as_deref() == Ok("1") {
                panic!(
                    "{test}: RGBID_REQUIRE_GPU=1 but no GPU adapter (install mesa-vulkan-drivers)"
                );
            }
            eprintln!("SKIPPED {test}: no GPU adapter (install mesa-vulkan-drivers for lavapipe)");
            None
        }
    }
}

/// See [`rgbid::image::test_pattern`].
pub fn textured_frame(w: usize, h: usize, seed: u32) -> rgbid::image::RgbdFrame {
    rgbid::image::test_pattern(w, h, seed)
}
