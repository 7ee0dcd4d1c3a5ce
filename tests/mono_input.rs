//! Image-only input for monocular SLAM: sequence folders (rgb.txt or time-stamped file
//! names), camera files, bad input (missing folder, corrupt image, bad lists) and the
//! `rgbid mono` command end to end on a folder written from a synthetic sequence.

use std::path::Path;
use std::process::Command;

use image::{GrayImage, Luma};
use rgbid::camera::UnifiedCamera;
use rgbid::experiments::mono::{render, SyntheticCamera, SyntheticSpec};
use rgbid::image::ImageF32;
use rgbid::io::trajectory::{read_tum, write_tum};
use rgbid::mono::{load_grey, ImageSequence, MonoConfig, MonoError, MonoSlam};

fn save_grey(path: &Path, img: &ImageF32) {
    let g = GrayImage::from_fn(img.width() as u32, img.height() as u32, |x, y| {
        Luma([img.at(x as usize, y as usize).round().clamp(0.0, 255.0) as u8])
    });
    g.save(path).expect("save png");
}

/// Writes `camera` as a one-line camera file (`xi gamma cx cy width height`).
fn write_camera_line(path: &Path, c: &UnifiedCamera) {
    std::fs::write(
        path,
        format!(
            "{} {} {} {} {} {}\n",
            c.xi, c.gamma, c.cx, c.cy, c.width, c.height
        ),
    )
    .unwrap();
}

#[test]
fn bad_folders_and_files_give_errors() {
    let tmp = tempfile::tempdir().unwrap();
    let missing = tmp.path().join("nope");
    assert!(matches!(
        ImageSequence::open(&missing),
        Err(MonoError::File { .. })
    ));
    let empty = tmp.path().join("empty");
    std::fs::create_dir(&empty).unwrap();
    std::fs::write(empty.join("notes.txt"), "hello").unwrap();
    assert!(matches!(
        ImageSequence::open(&empty),
        Err(MonoError::NoImages { .. })
    ));
    // rgb.txt with a bad time stamp, with too few fields, with repeated time stamps.
    let bad = tmp.path().join("bad");
    std::fs::create_dir(&bad).unwrap();
    for (text, what) in [
        ("# c\n1.0 rgb/a.png\nx rgb/b.png\n", "number"),
        ("1.0\n", "fields"),
        ("1.0 a.png\n1.0 b.png\n", "time"),
    ] {
        std::fs::write(bad.join("rgb.txt"), text).unwrap();
        let e = ImageSequence::open(&bad).expect_err(what);
        match what {
            "time" => assert!(matches!(e, MonoError::NonIncreasingTime { .. }), "{e}"),
            _ => assert!(
                matches!(
                    e,
                    MonoError::Parse { line: 2.., .. } | MonoError::Parse { line: 1, .. }
                ),
                "{e}"
            ),
        }
    }
    // A corrupt image: listed fine, fails to decode with the path in the message.
    let corrupt = tmp.path().join("corrupt");
    std::fs::create_dir(&corrupt).unwrap();
    std::fs::write(corrupt.join("0.500000.png"), b"\x89PNG\r\n\x1a\nnot really").unwrap();
    let seq = ImageSequence::open(&corrupt).unwrap();
    assert_eq!(seq.len(), 1);
    let e = seq.load(0).unwrap().expect_err("corrupt");
    assert!(matches!(e, MonoError::Decode { .. }));
    assert!(e.to_string().contains("0.500000.png"));
    assert!(seq.load(1).is_none());
    assert!(matches!(
        load_grey(&corrupt.join("missing.png")),
        Err(MonoError::File { .. })
    ));
}

#[test]
fn filter_rejects_wrong_sizes_and_time_going_backwards() {
    let cam = UnifiedCamera::new(0.0, 200.0, 79.5, 59.5, 160, 120);
    let mut slam = MonoSlam::new(cam, MonoConfig::default()).unwrap();
    let img = ImageF32::filled(160, 120, 100.0);
    assert!(matches!(
        slam.process(0.0, &ImageF32::filled(100, 120, 0.0)),
        Err(MonoError::ImageSize { .. })
    ));
    slam.process(1.0, &img).unwrap();
    assert!(matches!(
        slam.process(1.0, &img),
        Err(MonoError::NonIncreasingTime { .. })
    ));
    assert!(matches!(
        slam.process(f64::NAN, &img),
        Err(MonoError::InvalidConfig { .. })
    ));
    let bad = MonoConfig {
        zncc_threshold: 1.5,
        ..MonoConfig::default()
    };
    assert!(matches!(
        MonoSlam::new(cam, bad),
        Err(MonoError::InvalidConfig { .. })
    ));
    let bad_cam = UnifiedCamera::new(0.5, -1.0, 0.0, 0.0, 10, 10);
    assert!(matches!(
        MonoSlam::new(bad_cam, MonoConfig::default()),
        Err(MonoError::Camera(_))
    ));
}

/// Writes a synthetic pinhole sequence as a folder of time-stamped PNGs with a camera text
/// file, runs `rgbid mono` on it, and checks the trajectory it writes; then the same images
/// through an rgb.txt list; then a missing folder.
#[test]
fn cli_runs_on_an_image_only_folder() {
    let spec = SyntheticSpec::new(SyntheticCamera::Pinhole, 320, 240, 45);
    let frames = render(&spec).expect("render");
    let tmp = tempfile::tempdir().unwrap();
    let seq = tmp.path().join("seq");
    std::fs::create_dir_all(seq.join("images")).unwrap();
    let mut list = String::from("# timestamp filename\n");
    for (t, img) in &frames.images {
        save_grey(&seq.join(format!("{t:.6}.png")), img);
        save_grey(&seq.join("images").join(format!("{t:.6}.png")), img);
        list.push_str(&format!("{t:.6} images/{t:.6}.png\n"));
    }
    let cam_file = tmp.path().join("camera.txt");
    write_camera_line(&cam_file, &frames.camera);
    write_tum(&seq.join("groundtruth.txt"), &frames.ground_truth).unwrap();
    let exe = env!("CARGO_BIN_EXE_rgbid");
    let out = tmp.path().join("traj.txt");
    let o = Command::new(exe)
        .args(["mono", seq.to_str().unwrap(), "--camera"])
        .arg(&cam_file)
        .arg("--out")
        .arg(&out)
        .arg("--bench")
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(
        o.status.success(),
        "{stdout}{}",
        String::from_utf8_lossy(&o.stderr)
    );
    assert!(stdout.contains("ATE after Sim(3) alignment"), "{stdout}");
    assert!(stdout.contains("ms/frame"), "{stdout}");
    let traj = read_tum(&out).unwrap();
    assert_eq!(traj.len(), frames.images.len());
    assert!((traj[0].world_from_camera.translation).length() < 1e-12);
    // The camera moved in the estimate too.
    let last = traj.last().unwrap().world_from_camera.translation;
    assert!(last.length() > 1e-3);

    // The same images listed in rgb.txt (the folder's own PNGs are then ignored).
    std::fs::write(seq.join("rgb.txt"), list).unwrap();
    let s = ImageSequence::open(&seq).unwrap();
    assert_eq!(s.len(), frames.images.len());
    assert!(s.frames[0]
        .1
        .ends_with(format!("images/{:.6}.png", frames.images[0].0)));
    let o = Command::new(exe)
        .args(["mono", seq.to_str().unwrap(), "--camera"])
        .arg(&cam_file)
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    assert!(o.status.success());
    assert_eq!(read_tum(&out).unwrap().len(), frames.images.len());

    // --walker-height on a 1.5 s handheld clip: no walking, so no scale. The run finishes
    // with a warning (exit 3) and keeps the filter's trajectory and the report.
    let metric = tmp.path().join("m").join("metric.txt");
    let json = tmp.path().join("m").join("metric.json");
    let o = Command::new(exe)
        .args(["mono", seq.to_str().unwrap(), "--camera"])
        .arg(&cam_file)
        .args(["--walker-height", "1.75", "--out"])
        .arg(&metric)
        .arg("--json")
        .arg(&json)
        .output()
        .unwrap();
    let (stdout, stderr) = (
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr),
    );
    assert_eq!(o.status.code(), Some(3), "{stdout}{stderr}");
    assert!(stderr.contains("no metric trajectory"), "{stderr}");
    assert!(stdout.contains("unscaled (EKF)"), "{stdout}");
    assert!(!metric.exists());
    let unscaled = tmp.path().join("m").join("metric_unscaled.txt");
    assert_eq!(read_tum(&unscaled).unwrap().len(), frames.images.len());
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    assert_eq!(report["benchmark"], "mono-metric");
    assert_eq!(report["frames"], frames.images.len());
    assert!(report["unscaled"]["mean_pct"].as_f64().unwrap() >= 0.0);
    // A rigid alignment has less freedom than a similarity, so it cannot fit the filter's
    // trajectory better than the Sim(3) alignment does (same poses, same path length).
    let rigid = report["unscaled"]["rigid_ate_pct"].as_f64().unwrap();
    let sim3 = report["ekf_sim3_ate_pct"].as_f64().unwrap();
    assert!(rigid.is_finite() && rigid >= sim3 - 1e-9, "{rigid} {sim3}");
    assert_eq!(report["warnings"].as_array().unwrap().len(), 1);
    let o = Command::new(exe)
        .args(["mono", "--synthetic", "pinhole", "--walker-height", "3.5"])
        .output()
        .unwrap();
    assert_eq!(o.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&o.stderr).contains("(0, 3]"));

    let o = Command::new(exe)
        .args(["mono", tmp.path().join("missing").to_str().unwrap()])
        .output()
        .unwrap();
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("missing"));
}

/// An EuRoC-layout folder (`mav0/cam0/data.csv`, `data/`, `sensor.yaml`) of a synthetic pinhole
/// sequence runs without `--camera` and gives the trajectory of the same images in a plain
/// folder with the camera given (no distortion: the resampling is the identity).
#[test]
fn cli_runs_on_an_euroc_folder_with_its_sensor_yaml() {
    let spec = SyntheticSpec::new(SyntheticCamera::Pinhole, 320, 240, 30);
    let frames = render(&spec).expect("render");
    let c = frames.camera;
    let tmp = tempfile::tempdir().unwrap();
    let (plain, euroc) = (tmp.path().join("plain"), tmp.path().join("euroc"));
    let cam0 = euroc.join("mav0").join("cam0");
    std::fs::create_dir_all(cam0.join("data")).unwrap();
    std::fs::create_dir_all(&plain).unwrap();
    let mut csv = String::from("#timestamp [ns],filename\n");
    for (t, img) in &frames.images {
        let ns = (t * 1e9).round() as u64;
        save_grey(&cam0.join("data").join(format!("{ns}.png")), img);
        save_grey(&plain.join(format!("{:.9}.png", ns as f64 * 1e-9)), img);
        csv.push_str(&format!("{ns},{ns}.png\n"));
    }
    std::fs::write(cam0.join("data.csv"), csv).unwrap();
    std::fs::write(
        cam0.join("sensor.yaml"),
        format!(
            "sensor_type: camera\ncomment: synthetic\nrate_hz: 30\nresolution: [{}, {}]\n\
             camera_model: pinhole\nintrinsics: [{g}, {g}, {}, {}]\n\
             distortion_model: radial-tangential\ndistortion_coefficients: [0.0, 0.0, 0.0, 0.0]\n",
            c.width,
            c.height,
            c.cx,
            c.cy,
            g = c.gamma
        ),
    )
    .unwrap();
    let s = ImageSequence::open(&euroc).unwrap();
    assert_eq!(s.len(), frames.images.len());
    let cam = s.camera.expect("the sensor.yaml camera");
    assert_eq!((cam.xi, cam.gamma, cam.width), (0.0, c.gamma, c.width));
    assert!((s.frames[1].0 - frames.images[1].0).abs() < 1e-6);

    let cam_file = tmp.path().join("camera.txt");
    let line = format!(
        "{} {} {} {} {} {}\n",
        c.xi, c.gamma, c.cx, c.cy, c.width, c.height
    );
    std::fs::write(&cam_file, line).unwrap();
    let exe = env!("CARGO_BIN_EXE_rgbid");
    let run = |seq: &Path, camera: Option<&Path>, out: &Path| {
        let mut cmd = Command::new(exe);
        cmd.arg("mono").arg(seq).arg("--out").arg(out);
        if let Some(c) = camera {
            cmd.arg("--camera").arg(c);
        }
        cmd.output().unwrap()
    };
    let (a, b) = (tmp.path().join("a.txt"), tmp.path().join("b.txt"));
    let o = run(&euroc, None, &a);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let o = run(&plain, Some(&cam_file), &b);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let (ta, tb) = (read_tum(&a).unwrap(), read_tum(&b).unwrap());
    assert_eq!(ta.len(), tb.len());
    for (p, q) in ta.iter().zip(&tb) {
        let d = p.world_from_camera.translation - q.world_from_camera.translation;
        assert!(d.length() < 1e-6, "{}: {} m apart", p.timestamp, d.length());
    }
    // The folder's camera and a camera file together are refused.
    let o = run(&euroc, Some(&cam_file), &a);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("sensor.yaml"));
}

/// A folder of `frames` generated pinhole images named by their time stamps, its camera file
/// and the names of the images in order.
fn pinhole_folder(dir: &Path, frames: usize) -> (std::path::PathBuf, Vec<std::path::PathBuf>) {
    let spec = SyntheticSpec::new(SyntheticCamera::Pinhole, 320, 240, frames);
    let r = render(&spec).expect("render");
    let seq = dir.join("seq");
    std::fs::create_dir_all(&seq).unwrap();
    let mut names = Vec::new();
    for (t, img) in &r.images {
        let p = seq.join(format!("{t:.6}.png"));
        save_grey(&p, img);
        names.push(p);
    }
    let cam_file = dir.join("camera.txt");
    write_camera_line(&cam_file, &r.camera);
    (cam_file, names)
}

/// Unreadable frames: one is skipped and counted (exit code 3, every other frame has its
/// pose); when most frames are unreadable the run stops with an error (exit code 1) that
/// says where the poses of the frames before it went, and those poses are written.
#[test]
fn mono_skips_a_bad_frame_and_keeps_the_poses_before_a_fatal_one() {
    let tmp = tempfile::tempdir().unwrap();
    let (cam_file, names) = pinhole_folder(tmp.path(), 45);
    let seq = tmp.path().join("seq");
    let out = tmp.path().join("traj.txt");
    let exe = env!("CARGO_BIN_EXE_rgbid");
    let run = || {
        Command::new(exe)
            .args(["mono", seq.to_str().unwrap(), "--camera"])
            .arg(&cam_file)
            .arg("--out")
            .arg(&out)
            .output()
            .unwrap()
    };
    std::fs::write(&names[10], b"not a png").unwrap();
    let o = run();
    let all = format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
    assert_eq!(o.status.code(), Some(3), "{all}");
    assert!(all.contains("1 frames skipped"), "{all}");
    let bad = names[10]
        .file_name()
        .unwrap()
        .to_string_lossy()
        .into_owned();
    assert!(all.contains(&bad), "{all}");
    assert_eq!(read_tum(&out).unwrap().len(), 44);

    for name in &names[20..] {
        std::fs::write(name, b"not a png").unwrap();
    }
    let o = run();
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{stderr}");
    assert!(stderr.contains("could not be used"), "{stderr}");
    assert!(
        stderr.contains("frames processed before the error are in"),
        "{stderr}"
    );
    // Frames 0-19 but the damaged frame 10.
    assert_eq!(read_tum(&out).unwrap().len(), 19);
}

/// `rgbid mono --walker-height` checkpoints the filter's trajectory while it runs, and on
/// SIGINT stops reading frames, writes its outputs and exits with code 130.
#[test]
fn interrupted_mono_keeps_the_trajectory_so_far() {
    use std::process::Stdio;
    use std::time::{Duration, Instant};
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("t.txt");
    let unscaled = tmp.path().join("t_unscaled.txt");
    let frames = 900;
    let mut child = Command::new(env!("CARGO_BIN_EXE_rgbid"))
        .args([
            "mono",
            "--synthetic",
            "pinhole",
            "--width",
            "160",
            "--height",
            "120",
        ])
        .args(["--frames", &frames.to_string(), "--walker-height", "1.75"])
        .args(["--checkpoint-every", "0.2", "--out"])
        .arg(&out)
        .env("RUST_LOG", "warn")
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let start = Instant::now();
    while !std::fs::metadata(&unscaled).is_ok_and(|m| m.len() > 0) {
        assert!(
            start.elapsed() < Duration::from_secs(300),
            "no checkpoint written"
        );
        assert!(child.try_wait().unwrap().is_none(), "exited early");
        std::thread::sleep(Duration::from_millis(20));
    }
    let checkpoint = read_tum(&unscaled).expect("a checkpoint parses");
    assert!(!checkpoint.is_empty());
    let kill = Command::new("kill")
        .args(["-INT", &child.id().to_string()])
        .status()
        .unwrap();
    assert!(kill.success());
    let o = child.wait_with_output().unwrap();
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(130), "{stderr}");
    assert!(stderr.contains("interrupted"), "{stderr}");
    let kept = read_tum(&unscaled).unwrap();
    assert!(
        kept.len() >= checkpoint.len() && kept.len() < frames,
        "{} poses",
        kept.len()
    );
}
