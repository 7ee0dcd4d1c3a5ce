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

/// A deterministic textured frame for kernel tests: intensity from a few sinusoids plus
/// hashed noise, inverse depth of a slanted plane with a bump, and holes (0) in a corner and
/// on a sparse grid (so the validity logic is exercised).
pub fn textured_frame(w: usize, h: usize, seed: u32) -> rgbid::image::RgbdFrame {
    use rgbid::image::{ImageF32, RgbdFrame};
    let hash = |x: u32, y: u32| {
        let mut v =
            x.wrapping_mul(374761393) ^ y.wrapping_mul(668265263) ^ seed.wrapping_mul(2246822519);
        v = (v ^ (v >> 13)).wrapping_mul(1274126177);
        (v ^ (v >> 16)) as f32 / u32::MAX as f32
    };
    let mut i = Vec::with_capacity(w * h);
    let mut r = Vec::with_capacity(w * h);
    for y in 0..h {
        for x in 0..w {
            let (fx, fy) = (x as f32 / w as f32, y as f32 / h as f32);
            let v = 128.0
                + 50.0 * (fx * 23.0).sin() * (fy * 17.0).cos()
                + 30.0 * (fx * 7.0 + fy * 11.0).sin()
                + 20.0 * hash((x / 3) as u32, (y / 3) as u32);
            i.push(v.clamp(0.0, 255.0));
            let hole = (x < w / 8 && y < h / 8) || (x % 17 == 0 && y % 13 == 0);
            let bump = 0.3 * (-((fx - 0.6).powi(2) + (fy - 0.4).powi(2)) * 20.0).exp();
            r.push(if hole {
                0.0
            } else {
                1.0 / (1.2 + 0.8 * fx + 0.3 * fy - bump)
            });
        }
    }
    RgbdFrame {
        timestamp: 0.0,
        intensity: ImageF32::from_vec(w, h, i).expect("size"),
        inverse_depth: ImageF32::from_vec(w, h, r).expect("size"),
    }
}
