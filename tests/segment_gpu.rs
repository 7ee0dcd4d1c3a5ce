//! GPU/CPU parity of the image-domain normal kernel (`shaders/normals.wgsl`).
//!
//! Runs on any wgpu adapter (lavapipe included): a GPU test, ignored by default (see
//! `rgbid::gpu::test_gpu`).

use rand::{Rng, SeedableRng};
use rgbid::camera::PinholeCamera;
use rgbid::gpu::ComputeBackend;
use rgbid::image::ImageF32;
use rgbid::segment::{normal_kernels, normals_cpu, NormalParams};

/// A sphere in front of a slanted wall, with holes and depth noise: planes, curved surface,
/// depth discontinuities, invalid pixels and image borders all occur.
fn scene(w: usize, h: usize, cam: &PinholeCamera, seed: u64) -> ImageF32 {
    let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
    let mut img = ImageF32::filled(w, h, 0.0);
    for v in 0..h {
        for u in 0..w {
            let d = [
                (u as f64 - cam.cx) / cam.fx,
                (v as f64 - cam.cy) / cam.fy,
                1.0,
            ];
            // Wall 0.3 x + z = 3 -> z = 3 / (0.3 dx + 1).
            let mut z = 3.0 / (0.3 * d[0] + 1.0);
            let c = [0.1, -0.05, 1.4];
            let a = d[0] * d[0] + d[1] * d[1] + 1.0;
            let b = -2.0 * (d[0] * c[0] + d[1] * c[1] + c[2]);
            let cc = c[0] * c[0] + c[1] * c[1] + c[2] * c[2] - 0.35 * 0.35;
            let disc = b * b - 4.0 * a * cc;
            if disc >= 0.0 {
                z = z.min((-b - disc.sqrt()) / (2.0 * a));
            }
            if rng.random_range(0.0..1.0) < 0.03 {
                continue; // hole
            }
            let noise: f64 = rng.random_range(-0.004..0.004);
            img.data_mut()[v * w + u] = (1.0 / (z * (1.0 + noise))) as f32;
        }
    }
    img
}

#[test]
#[ignore = "needs a GPU adapter"]
fn gpu_normals_match_the_cpu_mirror() {
    let Some(ctx) = rgbid::gpu::test_gpu("gpu_normals_match_the_cpu_mirror") else {
        return;
    };
    let mut kernel = normal_kernels(&ComputeBackend::Gpu(ctx)).unwrap();
    for (w, h, step) in [(160usize, 120usize, 1u32), (203, 97, 2), (640, 480, 2)] {
        let cam = PinholeCamera::new(
            0.8 * w as f64,
            0.8 * w as f64,
            (w as f64 - 1.0) / 2.0,
            (h as f64 - 1.0) / 2.0,
            w as u32,
            h as u32,
        );
        let rho = scene(w, h, &cam, w as u64);
        let params = NormalParams {
            step,
            jump_tolerance: 0.02,
            ..Default::default()
        };
        let cpu = normals_cpu(&rho, &cam, &params);
        let gpu = kernel.compute(&rho, &cam, &params).unwrap();
        assert_eq!((gpu.width, gpu.height), (w, h));
        let mut valid_mismatch = 0;
        let mut max_err = 0.0f32;
        let mut over = 0;
        for i in 0..w * h {
            if cpu.is_valid(i) != gpu.is_valid(i) {
                valid_mismatch += 1;
                continue;
            }
            let e = (0..3)
                .map(|k| (cpu.data[i][k] - gpu.data[i][k]).abs())
                .fold(0.0f32, f32::max);
            if e > 1e-3 {
                // A near-tie in the discontinuity test can pick the other one-sided difference.
                over += 1;
            } else {
                max_err = max_err.max(e);
            }
        }
        let valid = cpu.valid_count();
        println!("{w}x{h} step {step}: {valid} valid normals, max |gpu-cpu| {max_err:.2e}, {over} over 1e-3, {valid_mismatch} validity mismatches");
        assert!(valid > w * h / 2);
        assert_eq!(valid_mismatch, 0);
        assert!(
            over * 10_000 <= w * h,
            "{over} pixels differ by more than 1e-3"
        );
        assert!(max_err < 1e-4, "max error {max_err}");
    }
}
