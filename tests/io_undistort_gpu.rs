//! GPU/CPU parity of the undistortion kernel (`shaders/undistort.wgsl`) and of a TUM sequence
//! loaded with it. Runs on any wgpu adapter (lavapipe in CI): GPU tests, ignored by default
//! (see `rgbid::gpu::test_gpu`).

use rand::{Rng, SeedableRng};
use rgbid::camera::PinholeCamera;
use rgbid::io::{CameraConfig, GpuUndistort, OpenOptions, TumSequence, UndistortMap};

/// The TUM fr1 preset (strong barrel distortion with tangential terms), scaled to any size.
fn fr1_like(w: u32, h: u32) -> PinholeCamera {
    let fr1 = CameraConfig::preset("tum_fr1").unwrap().camera;
    let (sx, sy) = (f64::from(w) / 640.0, f64::from(h) / 480.0);
    let mut c = PinholeCamera::new(fr1.fx * sx, fr1.fy * sy, fr1.cx * sx, fr1.cy * sy, w, h);
    c.distortion = fr1.distortion;
    c
}

#[test]
#[ignore = "needs a GPU adapter"]
fn gpu_undistortion_matches_the_cpu_mirror() {
    let Some(ctx) = rgbid::gpu::test_gpu("gpu_undistortion_matches_the_cpu_mirror") else {
        return;
    };
    let mut rng = rand_pcg::Pcg64::seed_from_u64(7);
    // Odd sizes (partial workgroups), a one-row and a one-column image (the kernel's
    // neighbour steps collapse there), and the full Kinect size.
    for (w, h) in [(640u32, 480u32), (203, 97), (17, 1), (1, 13)] {
        let cam = fr1_like(w, h);
        let map = UndistortMap::new(&cam);
        let gpu = GpuUndistort::new(ctx.clone(), &map).unwrap();
        let n = (w * h) as usize;
        let intensity: Vec<f32> = (0..n).map(|_| rng.random_range(0.0..255.0)).collect();
        // Inverse depth with holes (0) and jumps: nearest sampling must copy, never blend.
        let rho: Vec<f32> = (0..n)
            .map(|i| {
                if rng.random_range(0.0..1.0) < 0.1 {
                    0.0
                } else if (i % w as usize) < w as usize / 2 {
                    rng.random_range(0.2..0.3)
                } else {
                    rng.random_range(1.0..2.0)
                }
            })
            .collect();
        let (gi, gd) = gpu.remap(&intensity, &rho).unwrap();
        let mut ci = vec![0.0; n];
        let mut cd = vec![0.0; n];
        map.remap_bilinear(&intensity, &mut ci);
        map.remap_nearest(&rho, &mut cd);
        let worst = gi
            .iter()
            .zip(&ci)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        assert!(worst < 1e-3, "{w}x{h}: intensity differs by {worst}");
        assert_eq!(
            gd, cd,
            "{w}x{h}: nearest inverse depth must be bit-identical"
        );
        // The distortion moves pixels: the remap is not the identity.
        if w > 100 {
            assert!(ci.iter().zip(&intensity).filter(|(a, b)| a != b).count() > n / 2);
            assert!(cd.iter().filter(|&&v| v == 0.0).count() > n / 10 + 100);
        }
    }
    // A frame of another size is an error naming both sizes, not a panic.
    let map = UndistortMap::new(&fr1_like(64, 48));
    let gpu = GpuUndistort::new(ctx, &map).unwrap();
    let e = gpu.remap(&[0.0; 10], &[0.0; 10]).unwrap_err().to_string();
    assert!(e.contains("64 x 48") && e.contains("10"), "{e}");
}

#[test]
#[ignore = "needs a GPU adapter"]
fn gpu_sequence_undistorted_on_the_gpu_equals_the_cpu_load() {
    let Some(ctx) = rgbid::gpu::test_gpu("gpu_sequence_undistorted_on_the_gpu_equals_the_cpu_load")
    else {
        return;
    };
    let (w, h) = (80u32, 60u32);
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    std::fs::create_dir_all(dir.join("rgb")).unwrap();
    std::fs::create_dir_all(dir.join("depth")).unwrap();
    let rgb = image::RgbImage::from_fn(w, h, |x, y| {
        image::Rgb([(x * 3 + y) as u8, (y * 4) as u8, ((x ^ y) * 5) as u8])
    });
    rgb.save(dir.join("rgb/1.0.png")).unwrap();
    let d = image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_fn(w, h, |x, y| {
        image::Luma([if (x + y) % 7 == 0 {
            0
        } else {
            (4000 + 40 * x + 25 * y) as u16
        }])
    });
    d.save(dir.join("depth/1.0.png")).unwrap();
    std::fs::write(dir.join("rgb.txt"), "1.0 rgb/1.0.png\n").unwrap();
    std::fs::write(dir.join("depth.txt"), "1.0 depth/1.0.png\n").unwrap();
    let cfg = CameraConfig {
        camera: fr1_like(w, h),
        depth_factor: 5000.0,
        source: "test".into(),
    };
    let opts = OpenOptions {
        camera: Some(cfg),
        ..Default::default()
    };
    let cpu = TumSequence::open(dir, &opts).unwrap();
    let mut gpu = cpu.clone();
    assert!(!gpu.undistorts_on_gpu());
    assert!(gpu.undistort_on_gpu(ctx.clone()).unwrap());
    assert!(gpu.undistorts_on_gpu());
    let (a, b) = (cpu.load(0).unwrap(), gpu.load(0).unwrap());
    assert_eq!(a.inverse_depth, b.inverse_depth);
    let worst = a
        .intensity
        .data
        .iter()
        .zip(&b.intensity.data)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0f32, f32::max);
    assert!(worst < 1e-3, "intensity differs by {worst}");
    // Without distortion there is nothing to move to the GPU.
    let plain = CameraConfig {
        camera: PinholeCamera::new(60.0, 60.0, 39.5, 29.5, w, h),
        depth_factor: 5000.0,
        source: "test".into(),
    };
    let mut seq = TumSequence::open(
        dir,
        &OpenOptions {
            camera: Some(plain),
            ..Default::default()
        },
    )
    .unwrap();
    assert!(!seq.undistort_on_gpu(ctx).unwrap());
    assert!(!seq.undistorts_on_gpu());
}
