//! Helpers shared by the integration tests.
#![allow(dead_code)]

use std::path::PathBuf;

/// `../shared/data` beside the checkout.
pub fn shared_data() -> PathBuf {
    PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../shared/data"))
}

/// See [`rgbid::image::test_pattern`].
pub fn textured_frame(w: usize, h: usize, seed: u32) -> rgbid::image::RgbdFrame {
    rgbid::image::test_pattern(w, h, seed)
}
