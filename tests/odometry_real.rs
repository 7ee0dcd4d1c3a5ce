//! Odometry on real data from `../shared/data` (ignored by default: run with `--ignored`).

mod common;

use glam::{DQuat, DVec3};
use rgbid::camera::PinholeCamera;
use rgbid::geometry::Se3;
use rgbid::gpu::ComputeBackend;
use rgbid::image::{rgb_to_intensity, ImageF32, RgbdFrame};
use rgbid::odometry::{Odometry, OdometryConfig};

fn load(rgb: &std::path::Path, depth: &std::path::Path, factor: f32) -> RgbdFrame {
    let c = image::open(rgb).unwrap().to_rgb8();
    let d = image::open(depth).unwrap().to_luma16();
    let (w, h) = (c.width() as usize, c.height() as usize);
    let intensity = c
        .pixels()
        .map(|p| rgb_to_intensity(p[0], p[1], p[2]))
        .collect();
    let inv = d
        .pixels()
        .map(|p| {
            if p[0] == 0 {
                0.0
            } else {
                factor / f32::from(p[0])
            }
        })
        .collect();
    RgbdFrame {
        timestamp: 0.0,
        intensity: ImageF32::from_vec(w, h, intensity).unwrap(),
        inverse_depth: ImageF32::from_vec(w, h, inv).unwrap(),
    }
}

fn pose(path: &std::path::Path) -> Se3 {
    let v: Vec<f64> = std::fs::read_to_string(path)
        .unwrap()
        .split_whitespace()
        .map(|s| s.parse().unwrap())
        .collect();
    Se3::new(
        DQuat::from_xyzw(v[3], v[4], v[5], v[6]),
        DVec3::new(v[0], v[1], v[2]),
    )
}

#[test]
#[ignore = "needs ../shared/data"]
fn real_data_tum_pairs_cpu() {
    let _ = env_logger::builder().is_test(true).try_init();
    let cam = PinholeCamera::new(525.0, 525.0, 319.5, 239.5, 640, 480);
    let mut failures = 0;
    for case in ["case_1", "case_2"] {
        let dir = common::shared_data().join("rgbd/tum_pairs").join(case);
        let prev = load(&dir.join("img_prev.png"), &dir.join("dep_prev.png"), 5000.0);
        let cur = load(&dir.join("img_curr.png"), &dir.join("dep_curr.png"), 5000.0);
        let world_from_prev = pose(&dir.join("pose_prev.txt"));
        let world_from_cur = pose(&dir.join("pose_curr.txt"));
        let truth_prev_from_cur = world_from_prev.inverse() * world_from_cur;
        if std::env::var("RGBID_EXPLORE").is_ok() {
            use rgbid::odometry::*;
            let variants: Vec<(&str, OdometryConfig)> = vec![
                (
                    "iters 10/10/20",
                    OdometryConfig {
                        iterations: vec![10, 10, 20],
                        ..Default::default()
                    },
                ),
                (
                    "iters 20/20/30",
                    OdometryConfig {
                        iterations: vec![20, 20, 30],
                        ..Default::default()
                    },
                ),
                (
                    "huber",
                    OdometryConfig {
                        estimator: Estimator::Huber,
                        iterations: vec![20, 20, 30],
                        ..Default::default()
                    },
                ),
                (
                    "photo",
                    OdometryConfig {
                        terms: Terms::Photometric,
                        iterations: vec![20, 20, 30],
                        ..Default::default()
                    },
                ),
                (
                    "geo",
                    OdometryConfig {
                        terms: Terms::Geometric,
                        iterations: vec![20, 20, 30],
                        ..Default::default()
                    },
                ),
                (
                    "4 levels",
                    OdometryConfig {
                        levels: 4,
                        iterations: vec![10, 10, 20, 30],
                        ..Default::default()
                    },
                ),
                (
                    "mad",
                    OdometryConfig {
                        scale: ScaleMethod::Mad,
                        iterations: vec![20, 20, 30],
                        ..Default::default()
                    },
                ),
                (
                    "fixed",
                    OdometryConfig {
                        scale: ScaleMethod::Fixed,
                        iterations: vec![20, 20, 30],
                        ..Default::default()
                    },
                ),
            ];
            for (name, cfg) in variants {
                let mut odo = Odometry::new(cfg, cam, &ComputeBackend::Cpu).unwrap();
                let a = odo.align(&prev, &cur, Se3::IDENTITY).unwrap();
                let err = truth_prev_from_cur.inverse() * a.cur_from_ref.inverse();
                let its: Vec<usize> = a.levels.iter().map(|l| l.iterations).collect();
                println!(
                    "  {case} {name}: {:.2} mm {:.3} deg its {its:?} nu {:.2}",
                    err.translation.length() * 1e3,
                    err.angle().to_degrees(),
                    a.levels.last().unwrap().nu_photo
                );
            }
        }
        let mut odo = Odometry::new(OdometryConfig::default(), cam, &ComputeBackend::Cpu).unwrap();
        let a = odo.align(&prev, &cur, Se3::IDENTITY).unwrap();
        let est_prev_from_cur = a.cur_from_ref.inverse();
        let err = truth_prev_from_cur.inverse() * est_prev_from_cur;
        println!(
            "{case}: true {:.1} mm {:.2} deg; error {:.2} mm {:.3} deg; {:?}",
            truth_prev_from_cur.translation.length() * 1e3,
            truth_prev_from_cur.angle().to_degrees(),
            err.translation.length() * 1e3,
            err.angle().to_degrees(),
            a.levels
        );
        println!("  times {:?}", a.times);
        // OpenCV 5 RGB_DEPTH reaches 5.7 / 5.2 mm and 0.158 / 0.158 deg on these pairs (data
        // README). rgbid's translation is better; its rotation error is still ~10 % above
        // OpenCV's (0.177 / 0.164 deg when these bounds were set). The bounds are what rgbid
        // achieves now, not the goal (OpenCV's figures); see the issue notes.
        let (t_max, r_max) = if case == "case_1" {
            (0.0057, 0.19)
        } else {
            (0.0052, 0.18)
        };
        failures +=
            usize::from(!(err.translation.length() < t_max && err.angle().to_degrees() < r_max));
    }
    assert_eq!(failures, 0, "pairs outside the bounds");
}
