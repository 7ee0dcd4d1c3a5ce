//! TUM sequence reading: tiny sequences written to a temp dir and read back; association;
//! undistortion; loose frame pairs. Real data in the ignored test at the end.

use std::path::{Path, PathBuf};

use rgbid::camera::{BrownConrady, PinholeCamera};
use rgbid::image::rgb_to_intensity;
use rgbid::io::tum::associate;
use rgbid::io::{
    load_pair_frame, read_pose_file, CameraConfig, OpenOptions, TumSequence, UndistortMap,
};

const W: u32 = 32;
const H: u32 = 24;

fn colour(i: usize, x: u32, y: u32) -> [u8; 3] {
    [(x * 7 + i as u32) as u8, (y * 9) as u8, ((x + y) * 3) as u8]
}

fn raw_depth(i: usize, x: u32, y: u32) -> u16 {
    if (x + y).is_multiple_of(5) {
        0
    } else {
        (5000 + 100 * i as u32 + 20 * x + 10 * y) as u16
    }
}

fn write_frame(dir: &Path, i: usize, rgb_name: &str, depth_name: &str) {
    let rgb = image::RgbImage::from_fn(W, H, |x, y| image::Rgb(colour(i, x, y)));
    rgb.save(dir.join(rgb_name)).unwrap();
    let d = image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_fn(W, H, |x, y| {
        image::Luma([raw_depth(i, x, y)])
    });
    d.save(dir.join(depth_name)).unwrap();
}

/// Writes `n` frames with rgb/depth lists; depth stamps lag colour by `lag` seconds.
fn write_sequence(dir: &Path, n: usize, lag: f64) {
    std::fs::create_dir_all(dir.join("rgb")).unwrap();
    std::fs::create_dir_all(dir.join("depth")).unwrap();
    let mut rgb_txt = String::from("# colour images\n# timestamp filename\n");
    let mut depth_txt = String::from("# depth images\n\n");
    for i in 0..n {
        let t = 1.0 + i as f64 / 30.0;
        let (r, d) = (
            format!("rgb/{t:.6}.png"),
            format!("depth/{:.6}.png", t + lag),
        );
        write_frame(dir, i, &r, &d);
        rgb_txt += &format!("{t:.6} {r}\n");
        depth_txt += &format!("{:.6} {d}\n", t + lag);
    }
    std::fs::write(dir.join("rgb.txt"), rgb_txt).unwrap();
    std::fs::write(dir.join("depth.txt"), depth_txt).unwrap();
}

fn small_camera() -> CameraConfig {
    CameraConfig {
        camera: PinholeCamera::new(30.0, 30.0, 15.5, 11.5, W, H),
        depth_factor: 5000.0,
        source: "test".into(),
    }
}

fn opts() -> OpenOptions {
    OpenOptions {
        camera: Some(small_camera()),
        ..Default::default()
    }
}

#[test]
fn tiny_sequence_round_trip() {
    let tmp = tempfile::tempdir().unwrap();
    write_sequence(tmp.path(), 4, 0.005);
    std::fs::write(tmp.path().join("groundtruth.txt"), "1.0 0 0 0 0 0 0 1\n").unwrap();
    let seq = TumSequence::open(tmp.path(), &opts()).unwrap();
    assert_eq!(seq.len(), 4);
    assert!(!seq.is_empty());
    assert_eq!(
        seq.groundtruth.as_deref(),
        Some(tmp.path().join("groundtruth.txt").as_path())
    );
    for i in 0..4 {
        let e = &seq.entries[i];
        assert!((e.timestamp - (1.0 + i as f64 / 30.0)).abs() < 1e-6);
        assert!(e
            .depth
            .to_string_lossy()
            .contains(&format!("{:.6}", e.timestamp + 0.005)));
        let f = seq.load(i).unwrap();
        assert_eq!((f.width(), f.height()), (W as usize, H as usize));
        assert_eq!(f.timestamp(), e.timestamp);
        for (x, y) in [(0u32, 0u32), (5, 7), (31, 23), (17, 3)] {
            let c = colour(i, x, y);
            let want = rgb_to_intensity(c[0], c[1], c[2]);
            assert_eq!(f.intensity().at(x as usize, y as usize), want);
            let d = raw_depth(i, x, y);
            let want_inv = if d == 0 { 0.0 } else { 5000.0 / f32::from(d) };
            assert_eq!(
                f.inverse_depth().at(x as usize, y as usize),
                want_inv,
                "({x},{y})"
            );
        }
    }
    assert!(seq.load(4).is_err());

    let seq = TumSequence::open(
        tmp.path(),
        &OpenOptions {
            max_frames: Some(2),
            ..opts()
        },
    )
    .unwrap();
    assert_eq!(seq.len(), 2);
}

#[test]
fn association_tolerance_is_respected() {
    let tmp = tempfile::tempdir().unwrap();
    write_sequence(tmp.path(), 3, 0.015);
    assert_eq!(TumSequence::open(tmp.path(), &opts()).unwrap().len(), 3);
    let tight = OpenOptions {
        max_time_difference: 0.01,
        ..opts()
    };
    let e = TumSequence::open(tmp.path(), &tight)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("no colour/depth pairs within 0.01 s") && e.contains("0.015"),
        "{e}"
    );
}

#[test]
fn association_is_greedy_one_to_one() {
    // Colour 1 (0.01) is closest to depth 0 (0.008) and takes it; colour 0 then gets depth 1,
    // which is exactly at the tolerance. Each stamp is used once.
    let a = [0.0, 0.01, 0.5];
    let b = [0.008, 0.02, 0.9];
    assert_eq!(associate(&a, &b, 0.02), vec![(0, 1), (1, 0)]);
    assert_eq!(associate(&a, &b, 0.005), vec![(1, 0)]);
    assert!(associate(&a, &b, 0.001).is_empty());
    // Unsorted input lists are handled.
    assert_eq!(
        associate(&[0.5, 0.0], &[0.49, 0.01], 0.02),
        vec![(1, 1), (0, 0)]
    );
}

#[test]
fn associations_file_takes_precedence_and_calib_txt_is_used() {
    let tmp = tempfile::tempdir().unwrap();
    write_sequence(tmp.path(), 3, 0.0);
    // Only frames 2 and 0, pairing colour 0 with depth 1 on purpose.
    let a = "# assoc\n1.066667 rgb/1.066667.png 1.066667 depth/1.066667.png\n1.000000 rgb/1.000000.png 1.033333 depth/1.033333.png\n";
    std::fs::write(tmp.path().join("associations.txt"), a).unwrap();
    std::fs::write(tmp.path().join("calib.txt"), "30 30 15.5 11.5 5000 32 24\n").unwrap();
    let seq = TumSequence::open(tmp.path(), &OpenOptions::default()).unwrap();
    assert_eq!(seq.len(), 2);
    assert!(seq.camera_source.ends_with("calib.txt"));
    assert_eq!(seq.camera.fx, 30.0);
    assert!((seq.entries[0].timestamp - 1.0).abs() < 1e-9);
    assert!(seq.entries[0].depth.ends_with("depth/1.033333.png"));
    let f = seq.load(0).unwrap();
    let d = raw_depth(1, 3, 4);
    assert_eq!(f.inverse_depth().at(3, 4), 5000.0 / f32::from(d));
}

#[test]
fn distorted_camera_is_undistorted_on_load() {
    let tmp = tempfile::tempdir().unwrap();
    write_sequence(tmp.path(), 1, 0.0);
    let mut cfg = small_camera();
    cfg.camera.distortion = BrownConrady {
        k1: 0.25,
        k2: -0.9,
        p1: -0.005,
        p2: 0.003,
        k3: 1.1,
    };
    let seq = TumSequence::open(
        tmp.path(),
        &OpenOptions {
            camera: Some(cfg.clone()),
            ..Default::default()
        },
    )
    .unwrap();
    let f = seq.load(0).unwrap();
    let plain = TumSequence::open(tmp.path(), &opts())
        .unwrap()
        .load(0)
        .unwrap();
    let map = UndistortMap::new(&cfg.camera);
    assert_eq!(f.intensity(), &map.intensity(plain.intensity()).unwrap());
    assert_eq!(
        f.inverse_depth(),
        &map.inverse_depth(plain.inverse_depth()).unwrap()
    );
    assert_ne!(f.intensity(), plain.intensity());
    assert!(seq.undistorted_camera().distortion.is_zero());
}

#[test]
fn jpeg_colour_and_loose_pairs() {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path();
    let rgb = image::RgbImage::from_fn(W, H, |_, _| image::Rgb([100, 150, 200]));
    rgb.save(dir.join("c.jpg")).unwrap();
    let d =
        image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_fn(W, H, |_, _| image::Luma([2000]));
    d.save(dir.join("d.png")).unwrap();
    let cam = small_camera().camera;
    let f = load_pair_frame(&dir.join("c.jpg"), &dir.join("d.png"), &cam, 1000.0).unwrap();
    let want = rgb_to_intensity(100, 150, 200);
    assert!(
        f.intensity().data().iter().all(|v| (v - want).abs() < 3.0),
        "JPEG is lossy but close"
    );
    assert!(f.inverse_depth().data().iter().all(|&v| v == 0.5));

    std::fs::write(
        dir.join("pose.txt"),
        "1.3303 0.6256 1.6464 0.6579 0.6161 -0.2932 -0.3189\n",
    )
    .unwrap();
    let p = read_pose_file(&dir.join("pose.txt")).unwrap();
    assert!((p.translation.x - 1.3303).abs() < 1e-12);
    assert!((p.rotation.length() - 1.0).abs() < 1e-12);
}

#[test]
fn camera_flag_parses_presets_and_files() {
    let c: CameraConfig = "tum_fr1".parse().unwrap();
    assert_eq!(c.camera.fx, 517.3);
    let tmp = tempfile::tempdir().unwrap();
    let p = tmp.path().join("cam.cfg");
    std::fs::write(&p, "preset = tum_fr3\nwidth = 320\n").unwrap();
    let c: CameraConfig = p.to_str().unwrap().parse().unwrap();
    assert_eq!((c.camera.fx, c.camera.width), (535.4, 320));
    let e = "no_such_camera"
        .parse::<CameraConfig>()
        .unwrap_err()
        .to_string();
    assert!(e.contains("no_such_camera") && e.contains("tum_fr1"), "{e}");
}

fn data_dir() -> PathBuf {
    PathBuf::from(concat!(env!("CARGO_MANIFEST_DIR"), "/../shared/data/rgbd"))
}

#[test]
#[ignore = "needs ../shared/data"]
fn real_data_redkitchen_and_tum_pair() {
    let seq = TumSequence::open(
        &data_dir().join("redkitchen_0_299"),
        &OpenOptions::default(),
    )
    .unwrap();
    assert_eq!(seq.len(), 300);
    assert_eq!(
        (seq.camera.fx, seq.camera.cx, seq.depth_factor),
        (585.0, 320.0, 5000.0)
    );
    assert!(seq.groundtruth.is_some());
    for i in [0, 150, 299] {
        let f = seq.load(i).unwrap();
        assert_eq!((f.width(), f.height()), (640, 480));
        let mut inv: Vec<f32> = f
            .inverse_depth()
            .data()
            .iter()
            .copied()
            .filter(|&d| d > 0.0)
            .collect();
        assert!(inv.len() > 100_000, "frame {i}: {} valid depths", inv.len());
        inv.sort_by(f32::total_cmp);
        let median_m = 1.0 / inv[inv.len() / 2];
        assert!((0.4..5.0).contains(&median_m), "median depth {median_m} m");
        let mean_i = f.intensity().data().iter().sum::<f32>() / f.intensity().data().len() as f32;
        assert!((20.0..235.0).contains(&mean_i));
    }

    let pairs = data_dir().join("tum_pairs");
    let cam = rgbid::io::read_intrinsic_matrix(&pairs.join("kinect_params.txt"), 640, 480).unwrap();
    assert_eq!(
        (cam.fx, cam.fy, cam.cx, cam.cy),
        (525.0, 525.0, 319.5, 239.5)
    );
    let case = pairs.join("case_1");
    let f = load_pair_frame(
        &case.join("img_prev.png"),
        &case.join("dep_prev.png"),
        &cam,
        5000.0,
    )
    .unwrap();
    assert_eq!((f.width(), f.height()), (640, 480));
    assert!(
        f.inverse_depth()
            .data()
            .iter()
            .filter(|&&d| d > 0.0)
            .count()
            > 100_000
    );
    let prev = read_pose_file(&case.join("pose_prev.txt")).unwrap();
    let curr = read_pose_file(&case.join("pose_curr.txt")).unwrap();
    let prev_from_curr = prev.inverse() * curr;
    // data README: true motion 21.6 mm, 1.38 deg.
    assert!((prev_from_curr.translation.length() - 0.0216).abs() < 0.0005);
    assert!((prev_from_curr.angle().to_degrees() - 1.38).abs() < 0.01);
}
