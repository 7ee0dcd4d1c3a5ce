//! Keyframe fusion: the CPU mirror against noise and covisibility, and the WGSL kernel against
//! the mirror.
use super::fusion::{fuse_cpu, FusionParams, KeyframeFuser};
use crate::camera::PinholeCamera;
use crate::geometry::Se3;
use crate::gpu::ComputeBackend;
use crate::image::ImageF32;
use glam::{DQuat, DVec3};
use rand::{Rng, SeedableRng};

fn camera(w: u32, h: u32) -> PinholeCamera {
    let f = 525.0 * f64::from(w) / 640.0;
    PinholeCamera::new(
        f,
        f,
        (f64::from(w) - 1.0) / 2.0,
        (f64::from(h) - 1.0) / 2.0,
        w,
        h,
    )
}

/// Inverse depth of a slanted wall with a box in front, seen from `world_from_camera`,
/// with relative depth noise `noise` and 3 % holes.
fn render(cam: &PinholeCamera, world_from_camera: &Se3, noise: f64, seed: u64) -> ImageF32 {
    let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
    let (w, h) = (cam.width as usize, cam.height as usize);
    let mut img = ImageF32::filled(w, h, 0.0);
    for v in 0..h {
        for u in 0..w {
            let d = DVec3::new(
                (u as f64 - cam.cx) / cam.fx,
                (v as f64 - cam.cy) / cam.fy,
                1.0,
            );
            let o = world_from_camera.translation;
            let dir = world_from_camera.transform_vector(d);
            // Wall z = 3 + 0.2 x (world), box face z = 2 for |x| < 0.3, |y| < 0.3.
            let t_wall = (3.0 + 0.2 * o.x - o.z) / (dir.z - 0.2 * dir.x);
            let t_box = (2.0 - o.z) / dir.z;
            let hit_box = {
                let p = o + dir * t_box;
                t_box > 0.0 && p.x.abs() < 0.3 && p.y.abs() < 0.3
            };
            let t = if hit_box { t_box } else { t_wall };
            if t <= 0.0 || rng.random::<f64>() < 0.03 {
                continue;
            }
            // Depth along the camera z axis = t (d has z = 1 in the camera frame).
            let z = t * (1.0 + noise * (rng.random::<f64>() * 2.0 - 1.0) * 1.732);
            img.data_mut()[v * w + u] = (1.0 / z) as f32;
        }
    }
    img
}

fn pose(tx: f64, ty: f64, yaw: f64) -> Se3 {
    Se3::new(DQuat::from_rotation_y(yaw), DVec3::new(tx, ty, 0.0))
}

#[test]
fn fusion_averages_noise_and_counts_covisibility() {
    let cam = camera(160, 120);
    let kf_pose = pose(0.0, 0.0, 0.0);
    let truth = render(&cam, &kf_pose, 0.0, 1);
    let mut rho = render(&cam, &kf_pose, 0.01, 2).into_data();
    let mut weight: Vec<f32> = rho
        .iter()
        .map(|&r| if r > 0.0 { 1.0 } else { 0.0 })
        .collect();
    let err = |r: &[f32]| {
        let (mut s, mut n) = (0.0, 0);
        for (a, b) in r.iter().zip(truth.data().iter()) {
            if *a > 0.0 && *b > 0.0 {
                s += f64::from((1.0 / a - 1.0 / b).abs());
                n += 1;
            }
        }
        s / n as f64
    };
    let e0 = err(&rho);
    let params = fixed_params();
    let mut last = None;
    for k in 0..8u64 {
        let p = pose(0.02 * k as f64, -0.01 * k as f64, 0.01 * k as f64);
        let cur = render(&cam, &p, 0.01, 10 + k);
        let cur_from_kf = p.inverse() * kf_pose;
        last = Some(fuse_cpu(
            &mut rho,
            &mut weight,
            cur.data(),
            &cam,
            &cur_from_kf,
            0.0,
            &params,
        ));
    }
    let e1 = err(&rho);
    let c = last.unwrap();
    assert!(
        e1 < 0.6 * e0,
        "fusion did not reduce the depth error: {e0} -> {e1}"
    );
    assert!(c.covisibility() > 0.8, "covisibility {}", c.covisibility());
    assert!(c.fused as f64 > 0.7 * c.covisible as f64, "{c:?}");
    assert!(weight.iter().cloned().fold(0.0f32, f32::max) >= 8.0);

    // A frame that sees nothing of the keyframe: covisibility 0, nothing fused.
    let away = Se3::new(DQuat::from_rotation_y(std::f64::consts::PI), DVec3::ZERO);
    let cur = render(&cam, &away, 0.0, 3);
    let before = rho.clone();
    let c = fuse_cpu(
        &mut rho,
        &mut weight,
        cur.data(),
        &cam,
        &away.inverse(),
        0.0,
        &params,
    );
    assert_eq!(c.covisible, 0);
    assert_eq!(rho, before);
}

#[test]
#[ignore = "needs a GPU adapter"]
fn gpu_fusion_matches_cpu_mirror() {
    let Some(gpu) = crate::gpu::test_gpu("gpu_fusion_matches_cpu_mirror") else {
        return;
    };
    // The fixed tolerance without the occlusion test, and the thesis' parameters.
    let variants = [fixed_params(), thesis_params()];
    for ((w, h), params) in [(160u32, 120u32), (203, 97), (640, 480)]
        .into_iter()
        .flat_map(|s| variants.iter().map(move |p| (s, *p)))
    {
        let cam = camera(w, h);
        let kf = render(&cam, &Se3::IDENTITY, 0.01, 5);
        let mut cpu = KeyframeFuser::new(cam, params, &ComputeBackend::Cpu).unwrap();
        let mut gpu_f = KeyframeFuser::new(cam, params, &ComputeBackend::Gpu(gpu.clone())).unwrap();
        cpu.start(&kf).unwrap();
        gpu_f.start(&kf).unwrap();
        for k in 0..4u64 {
            let p = pose(0.03 * k as f64, 0.01 * k as f64, -0.02 * k as f64);
            let cur = render(&cam, &p, 0.01, 20 + k);
            let a = cpu.fuse(&cur, &p.inverse(), 0.004).unwrap();
            let b = gpu_f.fuse(&cur, &p.inverse(), 0.004).unwrap();
            let tol = |x: u64| (x as f64 * 0.002).max(3.0);
            assert_eq!(a.valid, b.valid, "{w}x{h} frame {k}");
            assert!(
                (a.covisible as f64 - b.covisible as f64).abs() <= tol(a.covisible),
                "{w}x{h} frame {k}: {a:?} vs {b:?}"
            );
            assert!(
                (a.fused as f64 - b.fused as f64).abs() <= tol(a.fused),
                "{w}x{h} frame {k}: {a:?} vs {b:?}"
            );
            assert_eq!(a.frame_valid, b.frame_valid, "{w}x{h} frame {k}");
            assert!(
                (a.frame_covisible as f64 - b.frame_covisible as f64).abs()
                    <= tol(a.frame_covisible),
                "{w}x{h} frame {k}: {a:?} vs {b:?}"
            );
            if params.both_directions {
                assert!(a.frame_valid > 0 && a.frame_covisible > 0, "{a:?}");
            }
        }
        let (rc, wc) = cpu.finish().unwrap();
        let (rg, wg) = gpu_f.finish().unwrap();
        let n = rc.data().len();
        let mut differ = 0;
        for i in 0..n {
            let (a, b) = (rc.data()[i], rg.data()[i]);
            if (a - b).abs() > 1e-5 * a.abs().max(1e-3) || wc.data()[i] != wg.data()[i] {
                differ += 1;
            }
        }
        assert!(
            (differ as f64) < 0.002 * n as f64 + 3.0,
            "{w}x{h}: {differ} of {n} pixels differ between GPU and CPU"
        );
    }
}

/// The fixed tolerance `0.004 + 0.03 rho`, every pixel on depth covisible, keyframe side only.
fn fixed_params() -> FusionParams {
    FusionParams {
        tol_sigmas: 0.0,
        occlusion: false,
        both_directions: false,
        ..FusionParams::default()
    }
}

/// The thesis' fusion (eq. 6.10, 6.24): 3 sigma_W, occlusion test, both directions.
fn thesis_params() -> FusionParams {
    FusionParams {
        tol_sigmas: 3.0,
        occlusion: true,
        both_directions: true,
        ..FusionParams::default()
    }
}

/// A constant inverse-depth image.
fn flat(cam: &PinholeCamera, rho: f32) -> ImageF32 {
    ImageF32::filled(cam.width as usize, cam.height as usize, rho)
}

#[test]
fn occlusion_test_excludes_occluding_pixels_from_covisibility() {
    let cam = camera(80, 60);
    // The keyframe sees a wall at 2 m; the frame at the same pose has an object at 1 m over
    // its left half.
    let kf = flat(&cam, 0.5);
    let mut cur = flat(&cam, 0.5);
    for v in 0..60 {
        for u in 0..40 {
            cur.data_mut()[v * 80 + u] = 1.0;
        }
    }
    let run = |params: &FusionParams| {
        let mut rho = kf.data().to_vec();
        let mut weight = vec![1.0f32; rho.len()];
        fuse_cpu(
            &mut rho,
            &mut weight,
            cur.data(),
            &cam,
            &Se3::IDENTITY,
            0.004,
            params,
        )
    };
    let plain = run(&fixed_params());
    assert_eq!(plain.covisibility(), 1.0, "{plain:?}");
    let thesis = run(&thesis_params());
    assert!(
        (thesis.covisibility() - 0.5).abs() < 1e-9,
        "the occluded half must not count: {thesis:?}"
    );
    assert_eq!(thesis.fused, plain.fused);
}

#[test]
fn both_directions_take_the_frame_side_minimum() {
    let cam = camera(80, 60);
    // The keyframe has depth on its right half only; the frame everywhere: every keyframe
    // pixel is seen, but only half of the frame's pixels land on keyframe depth.
    let mut kf = flat(&cam, 0.5);
    for v in 0..60 {
        for u in 0..40 {
            kf.data_mut()[v * 80 + u] = 0.0;
        }
    }
    let cur = flat(&cam, 0.5);
    let run = |params: &FusionParams| {
        let mut rho = kf.data().to_vec();
        let mut weight: Vec<f32> = rho.iter().map(|&r| f32::from(r > 0.0)).collect();
        fuse_cpu(
            &mut rho,
            &mut weight,
            cur.data(),
            &cam,
            &Se3::IDENTITY,
            0.004,
            params,
        )
    };
    let one_sided = run(&fixed_params());
    assert_eq!(one_sided.covisibility(), 1.0);
    assert_eq!(one_sided.frame_valid, 0);
    let both = run(&FusionParams {
        both_directions: true,
        ..fixed_params()
    });
    assert_eq!(both.frame_valid, 80 * 60);
    assert_eq!(both.frame_covisible, 40 * 60);
    assert!((both.covisibility() - 0.5).abs() < 1e-9, "{both:?}");
}

#[test]
fn sigma_tolerance_follows_the_given_scale() {
    let cam = camera(80, 60);
    // The frame measures the keyframe's wall 0.01 1/m further away.
    let kf = flat(&cam, 0.5);
    let cur = flat(&cam, 0.49);
    let fused = |sigma_geo: f64, params: &FusionParams| {
        let mut rho = kf.data().to_vec();
        let mut weight = vec![1.0f32; rho.len()];
        fuse_cpu(
            &mut rho,
            &mut weight,
            cur.data(),
            &cam,
            &Se3::IDENTITY,
            sigma_geo,
            params,
        )
        .fused
    };
    let sigma = FusionParams {
        tol_sigmas: 3.0,
        ..fixed_params()
    };
    // 3 sigma_W = 0.012 1/m accepts the offset, 0.006 1/m rejects it.
    assert_eq!(fused(0.004, &sigma), 80 * 60);
    assert_eq!(fused(0.002, &sigma), 0);
    // The fixed tolerance 0.004 + 0.03 * 0.5 = 0.019 1/m ignores the scale.
    assert_eq!(fused(0.002, &fixed_params()), 80 * 60);
    // The defaults are the thesis' tolerance.
    assert_eq!(FusionParams::default().tol_sigmas, 3.0);
}
