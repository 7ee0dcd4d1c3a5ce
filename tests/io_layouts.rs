//! Dataset layouts other than TUM's lists (ETH3D, 7-Scenes, Replica): tiny folders written as
//! each dataset documents its files, from frames rendered with exact ground truth, then read
//! back through the same reader `rgbid odometry` and `rgbid slam` use, and tracked.

use std::path::Path;

use rgbid::camera::PinholeCamera;
use rgbid::eval::{evaluate, EvalOptions};
use rgbid::gpu::ComputeBackend;
use rgbid::io::{CameraConfig, IoError, Layout, OpenOptions, TumSequence};
use rgbid::odometry::{Odometry, OdometryConfig};
use rgbid::synth::{render_pinhole, Scene, SensorModel, Trajectory, TrajectoryKind};
use rgbid::trajectory::TimedPose;

const FRAMES: usize = 12;

/// `FRAMES` frames of a handheld path through the office scene at 30 Hz, rendered by
/// `camera`: poses, 8-bit RGB and depth in metres (0 = none).
fn render(camera: &PinholeCamera) -> Vec<(TimedPose, Vec<u8>, Vec<f32>)> {
    let scene = Scene::preset("office", 3).unwrap();
    let traj = Trajectory::new(TrajectoryKind::Handheld, &scene, 10.0, 3).unwrap();
    traj.sample(FRAMES, 30.0, 0.0)
        .into_iter()
        .enumerate()
        .map(|(i, p)| {
            let f = render_pinhole(
                &scene,
                camera,
                &p.world_from_camera,
                &SensorModel::noiseless(),
                i as u64,
            );
            let depth = f
                .inverse_depth
                .data()
                .iter()
                .map(|&r| if r > 0.0 { 1.0 / r } else { 0.0 })
                .collect();
            (p, f.rgb, depth)
        })
        .collect()
}

fn save_rgb(path: &Path, w: u32, h: u32, rgb: &[u8]) {
    image::RgbImage::from_raw(w, h, rgb.to_vec())
        .unwrap()
        .save(path)
        .unwrap();
}

/// Depth in metres as 16-bit PNG with `factor` units per metre; no measurement as `none`.
fn save_depth(path: &Path, w: u32, h: u32, depth: &[f32], factor: f64, none: u16) {
    let raw: Vec<u16> = depth
        .iter()
        .map(|&z| {
            if z > 0.0 {
                (f64::from(z) * factor).round().min(65534.0) as u16
            } else {
                none
            }
        })
        .collect();
    image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_raw(w, h, raw)
        .unwrap()
        .save(path)
        .unwrap();
}

/// Row-major 4x4 of `world_from_camera`.
fn matrix_rows(p: &rgbid::geometry::Se3) -> [f64; 16] {
    p.to_mat4().transpose().to_cols_array()
}

fn camera_of(name: &str) -> PinholeCamera {
    CameraConfig::preset(name).unwrap().camera
}

/// Tracks the opened sequence and returns the ATE RMSE (m) against its own ground truth.
fn track(seq: &TumSequence) -> f64 {
    let gt = seq.ground_truth().unwrap().expect("ground truth");
    assert_eq!(gt.len(), seq.len());
    let mut odo =
        Odometry::new(OdometryConfig::default(), seq.camera, &ComputeBackend::Cpu).unwrap();
    odo.set_initial_pose(gt[0].world_from_camera);
    let est: Vec<TimedPose> = (0..seq.len())
        .map(|i| {
            let f = seq.load(i).unwrap();
            TimedPose {
                timestamp: f.timestamp(),
                world_from_camera: odo.track(&f).unwrap().world_from_camera,
            }
        })
        .collect();
    evaluate(&gt, &est, &EvalOptions::default())
        .unwrap()
        .ate
        .translation
        .rmse
}

/// Ground truth read back equals the poses written (to the text precision).
fn assert_same_poses(read: &[TimedPose], written: &[(TimedPose, Vec<u8>, Vec<f32>)]) {
    assert_eq!(read.len(), written.len());
    for (r, (w, _, _)) in read.iter().zip(written) {
        let d = r.world_from_camera.inverse() * w.world_from_camera;
        assert!(d.translation.length() < 1e-6, "{:?}", d.translation);
        assert!(d.angle() < 1e-6, "{}", d.angle());
    }
}

#[test]
fn seven_scenes_folder_is_detected_read_and_tracked() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let cam = camera_of("7scenes");
    let frames = render(&cam);
    for (i, (p, rgb, depth)) in frames.iter().enumerate() {
        save_rgb(&d.join(format!("frame-{i:06}.color.png")), 640, 480, rgb);
        save_depth(
            &d.join(format!("frame-{i:06}.depth.png")),
            640,
            480,
            depth,
            1000.0,
            65535,
        );
        let rows: Vec<String> = matrix_rows(&p.world_from_camera)
            .chunks(4)
            .map(|r| {
                r.iter()
                    .map(|v| format!("{v:.9e}"))
                    .collect::<Vec<_>>()
                    .join("\t")
            })
            .collect();
        std::fs::write(
            d.join(format!("frame-{i:06}.pose.txt")),
            rows.join("\n") + "\n",
        )
        .unwrap();
    }
    assert_eq!(Layout::detect(d), Layout::SevenScenes);
    let seq = TumSequence::open(d, &OpenOptions::default()).unwrap();
    assert_eq!(seq.layout, Layout::SevenScenes);
    assert_eq!(seq.len(), FRAMES);
    assert_eq!(seq.depth_factor, 1000.0);
    assert!((seq.entries[3].timestamp - 0.1).abs() < 1e-12);
    // 65535 is no measurement, like 0.
    let f = seq.load(0).unwrap();
    let holes = frames[0].2.iter().filter(|&&z| z == 0.0).count();
    let zeros = f
        .inverse_depth()
        .data()
        .iter()
        .filter(|&&r| r == 0.0)
        .count();
    assert_eq!(zeros, holes);
    assert_same_poses(&seq.ground_truth().unwrap().unwrap(), &frames);
    let ate = track(&seq);
    assert!(ate < 0.01, "ATE {ate} m");
    // A gap ends the sequence at the last complete frame; a missing depth is named.
    std::fs::remove_file(d.join("frame-000005.depth.png")).unwrap();
    let e = TumSequence::open(d, &OpenOptions::default()).unwrap_err();
    assert!(
        matches!(&e, IoError::MissingFile { path, .. } if path.ends_with("frame-000005.depth.png")),
        "{e}"
    );
}

#[test]
fn eth3d_folder_takes_its_calibration_and_image_size() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let cam = PinholeCamera::new(300.0, 300.0, 159.5, 119.5, 320, 240);
    let frames = render(&cam);
    std::fs::create_dir_all(d.join("rgb")).unwrap();
    std::fs::create_dir_all(d.join("depth")).unwrap();
    let (mut rgb_txt, mut depth_txt, mut gt_txt) = (String::new(), String::new(), String::new());
    for (i, (p, rgb, depth)) in frames.iter().enumerate() {
        let t = 1000.0 + p.timestamp;
        save_rgb(&d.join(format!("rgb/{t:.6}.png")), 320, 240, rgb);
        save_depth(
            &d.join(format!("depth/{t:.6}.png")),
            320,
            240,
            depth,
            5000.0,
            0,
        );
        rgb_txt += &format!("{t:.6} rgb/{t:.6}.png\n");
        depth_txt += &format!("{t:.6} depth/{t:.6}.png\n");
        let q = p.world_from_camera.rotation;
        let x = p.world_from_camera.translation;
        gt_txt += &format!(
            "{t:.6} {:.9} {:.9} {:.9} {:.9} {:.9} {:.9} {:.9}\n",
            x.x, x.y, x.z, q.x, q.y, q.z, q.w
        );
        assert!(i < FRAMES);
    }
    std::fs::write(d.join("rgb.txt"), rgb_txt).unwrap();
    std::fs::write(d.join("depth.txt"), depth_txt).unwrap();
    std::fs::write(d.join("groundtruth.txt"), gt_txt).unwrap();
    std::fs::write(d.join("calibration.txt"), "300 300 159.5 119.5\n").unwrap();
    assert_eq!(Layout::detect(d), Layout::Eth3d);
    let seq = TumSequence::open(d, &OpenOptions::default()).unwrap();
    assert_eq!((seq.camera.width, seq.camera.height), (320, 240));
    assert_eq!(seq.camera.fx, 300.0);
    let ate = track(&seq);
    assert!(ate < 0.01, "ATE {ate} m");
    // A calibration line that is not `fx fy cx cy` is named with its line.
    std::fs::write(d.join("calibration.txt"), "# ETH3D\n300 300 159.5\n").unwrap();
    let e = TumSequence::open(d, &OpenOptions::default()).unwrap_err();
    assert!(matches!(&e, IoError::Parse { line: 2, .. }), "{e}");
}

#[test]
fn replica_folder_reads_its_trajectory_file() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    std::fs::create_dir_all(d.join("results")).unwrap();
    // Replica's own camera is 1200 x 680; a smaller render keeps the test fast, with the
    // camera given as a user would for their own rendering.
    let cam = PinholeCamera::new(200.0, 200.0, 159.5, 89.5, 320, 180);
    let frames = render(&cam);
    let mut traj = String::new();
    for (i, (p, rgb, depth)) in frames.iter().enumerate() {
        save_rgb(&d.join(format!("results/frame{i:06}.jpg")), 320, 180, rgb);
        save_depth(
            &d.join(format!("results/depth{i:06}.png")),
            320,
            180,
            depth,
            6553.5,
            0,
        );
        let r = matrix_rows(&p.world_from_camera);
        traj += &(r
            .iter()
            .map(|v| format!("{v:.12e}"))
            .collect::<Vec<_>>()
            .join(" ")
            + "\n");
    }
    std::fs::write(d.join("traj.txt"), traj).unwrap();
    assert_eq!(Layout::detect(d), Layout::Replica);
    let opts = OpenOptions {
        camera: Some(CameraConfig {
            camera: cam,
            depth_factor: 6553.5,
            source: "test".into(),
        }),
        ..Default::default()
    };
    let seq = TumSequence::open(d, &opts).unwrap();
    assert_eq!(seq.len(), FRAMES);
    assert_same_poses(&seq.ground_truth().unwrap().unwrap(), &frames);
    let ate = track(&seq);
    assert!(ate < 0.02, "ATE {ate} m");
    // Without a camera the layout's preset applies, and its size is checked against the images.
    let e = TumSequence::open(d, &OpenOptions::default()).unwrap_err();
    assert!(matches!(e, IoError::CameraSizeMismatch { .. }), "{e}");
}

#[test]
fn scannet_colour_is_resampled_onto_the_depth_camera() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    for sub in ["color", "depth", "pose", "intrinsic"] {
        std::fs::create_dir_all(d.join(sub)).unwrap();
    }
    // ScanNet's colour camera sees a wider, finer image than its depth camera; scaled down
    // here (colour 324 x 242, depth 160 x 120) to keep the test fast.
    let colour_cam = PinholeCamera::new(290.0, 290.0, 161.5, 120.5, 324, 242);
    let depth_cam = PinholeCamera::new(144.0, 144.0, 79.5, 59.5, 160, 120);
    let colour = render(&colour_cam);
    let depth = render(&depth_cam);
    let matrix = |c: &PinholeCamera| {
        format!(
            "{} 0 {} 0\n0 {} {} 0\n0 0 1 0\n0 0 0 1\n",
            c.fx, c.cx, c.fy, c.cy
        )
    };
    std::fs::write(d.join("intrinsic/intrinsic_color.txt"), matrix(&colour_cam)).unwrap();
    std::fs::write(d.join("intrinsic/intrinsic_depth.txt"), matrix(&depth_cam)).unwrap();
    for (i, ((p, rgb, _), (_, _, z))) in colour.iter().zip(&depth).enumerate() {
        save_rgb(&d.join(format!("color/{i}.jpg")), 324, 242, rgb);
        save_depth(&d.join(format!("depth/{i}.png")), 160, 120, z, 1000.0, 0);
        let rows: Vec<String> = if i == 4 {
            // The exporter writes -inf where the scan's tracking was lost.
            vec!["-inf -inf -inf -inf".to_string(); 4]
        } else {
            matrix_rows(&p.world_from_camera)
                .chunks(4)
                .map(|r| {
                    r.iter()
                        .map(|v| format!("{v:.9}"))
                        .collect::<Vec<_>>()
                        .join(" ")
                })
                .collect()
        };
        std::fs::write(d.join(format!("pose/{i}.txt")), rows.join("\n") + "\n").unwrap();
    }
    assert_eq!(Layout::detect(d), Layout::ScanNet);
    let seq = TumSequence::open(d, &OpenOptions::default()).unwrap();
    assert_eq!((seq.camera.width, seq.camera.height), (160, 120));
    assert_eq!(seq.camera.fx, 144.0);
    // The resampled intensity is the depth camera's view: compare with a render by it.
    let f = seq.load(0).unwrap();
    let direct = render_pinhole(
        &Scene::preset("office", 3).unwrap(),
        &depth_cam,
        &depth[0].0.world_from_camera,
        &SensorModel::noiseless(),
        0,
    );
    let diffs: Vec<f32> = f
        .intensity()
        .data()
        .iter()
        .zip(direct.intensity.data())
        .map(|(a, b)| (a - b).abs())
        .collect();
    let mean = diffs.iter().sum::<f32>() / diffs.len() as f32;
    assert!(mean < 6.0, "mean |resampled - direct| = {mean} grey levels");
    let gt = seq.ground_truth().unwrap().unwrap();
    assert_eq!(gt.len(), FRAMES - 1, "the -inf pose is left out");
    assert!(gt.iter().all(|p| (p.timestamp - 4.0 / 30.0).abs() > 1e-9));
}
