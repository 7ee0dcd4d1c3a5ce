//! GPU/CPU parity of the WGSL ray caster (`shaders/raycast.wgsl`) against its CPU mirror.
//! Runs on any adapter (lavapipe in CI): a GPU test, ignored by default (see
//! `rgbid::gpu::test_gpu`).

use std::sync::Arc;

use glam::DVec3;
use rgbid::camera::{PinholeCamera, UnifiedCamera};
use rgbid::synth::trajectory::camera_pose;
use rgbid::synth::{CameraModel, RenderBackend, Renderer, Scene, SensorModel, NO_OBJECT};

#[test]
#[ignore = "needs a GPU adapter"]
fn gpu_ray_caster_matches_cpu() {
    let Some(ctx) = rgbid::gpu::test_gpu("gpu_ray_caster_matches_cpu") else {
        return;
    };
    let cams = [
        CameraModel::Pinhole(PinholeCamera::new(262.5, 262.5, 159.5, 119.5, 320, 240)),
        CameraModel::Unified(UnifiedCamera::catadioptric(240, 240)),
    ];
    for (name, yaw) in [
        ("office", 0.4),
        ("kitchen", 2.0),
        ("corridor", 0.1),
        ("lab", 4.0),
    ] {
        let scene = Arc::new(Scene::preset(name, 9).unwrap().session(1));
        let c = scene.free_area().center();
        let pose = camera_pose(DVec3::new(c.x, c.y, 1.45), yaw, -0.2, 0.05);
        for cam in cams {
            let mut cpu = Renderer::new(scene.clone(), cam, &RenderBackend::Cpu).unwrap();
            let mut gpu =
                Renderer::new(scene.clone(), cam, &RenderBackend::Gpu(ctx.clone())).unwrap();
            let a = cpu.cast(&pose).unwrap();
            let b = gpu.cast(&pose).unwrap();
            assert_eq!(a.len(), b.len());
            let hits = a.iter().filter(|s| s.object != NO_OBJECT).count();
            assert!(hits > a.len() / 3, "{name}: too few hits ({hits})");
            let mut same_object = 0usize;
            let mut depth_bad = 0usize;
            let mut color_bad = 0usize;
            let mut max_color = 0.0f32;
            for (x, y) in a.iter().zip(&b) {
                if x.object != y.object {
                    continue;
                }
                same_object += 1;
                if x.object == NO_OBJECT {
                    continue;
                }
                if (x.z - y.z).abs() > 1e-4 * x.z.max(1.0) {
                    depth_bad += 1;
                }
                let dc = (0..3)
                    .map(|k| (x.rgb[k] - y.rgb[k]).abs())
                    .fold(0.0f32, f32::max);
                if dc > 2.0 / 255.0 {
                    color_bad += 1;
                }
                max_color = max_color.max(dc);
            }
            let n = a.len() as f64;
            // Objects differ only where a ray grazes an edge (f32 rounding in different order).
            assert!(
                same_object as f64 > 0.998 * n,
                "{name} {cam:?}: object ids agree on {same_object}/{n}"
            );
            assert!(
                depth_bad as f64 <= 0.001 * n,
                "{name}: {depth_bad} depth mismatches"
            );
            // Colour may differ at texture discontinuities (checker edges, poster shapes).
            assert!(
                color_bad as f64 <= 0.003 * n,
                "{name}: {color_bad} colour mismatches (max {max_color})"
            );
            // After the (shared) sensor model the frames agree just as well.
            let sensor = SensorModel::kinect();
            let fa = cpu.render(&pose, &sensor, 3).unwrap();
            let fb = gpu.render(&pose, &sensor, 3).unwrap();
            let dv = fa
                .inverse_depth
                .data()
                .iter()
                .zip(fb.inverse_depth.data())
                .filter(|(p, q)| (**p - **q).abs() > 1e-3)
                .count();
            assert!(
                dv as f64 <= 0.004 * n,
                "{name}: {dv} inverse-depth mismatches after the sensor model"
            );
        }
    }
}
