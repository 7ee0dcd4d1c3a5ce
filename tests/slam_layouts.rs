//! `rgbid slam` on one generated sequence written in every dataset layout: each folder is
//! detected without `--format`, runs to the end, and is scored against the ground truth its own
//! layout carries (TUM/ETH3D `groundtruth.txt`, 7-Scenes and ScanNet pose files, Replica's
//! `traj.txt`), as `summary.json` records it. The folders hold the same frames, so their
//! figures agree with the TUM folder's within what the layouts change: depth quantisation
//! (TUM and ETH3D 0.2 mm steps, 7-Scenes and ScanNet 1 mm, Replica 0.15 mm) and colour coding
//! (ScanNet and Replica JPEG; ScanNet's colour also upsampled and resampled back).

#[path = "common/cli.rs"]
#[allow(dead_code)]
mod cli;

use std::path::Path;

use cli::text;
use rgbid::camera::PinholeCamera;
use rgbid::io::run_folder::RunFolder;
use rgbid::io::Layout;
use rgbid::synth::layout_export::LayoutWriter;
use rgbid::synth::{
    CameraModel, RenderBackend, Scene, SensorModel, Sequence, SequenceConfig, Trajectory,
    TrajectoryKind,
};

const FRAMES: usize = 60;
const WIDTH: u32 = 160;
/// Every layout's ATE RMSE against its own ground truth stays below this (metres): the TUM
/// folder of these frames tracks to a few millimetres, so this catches a layout whose poses
/// or depth scale are read wrongly (a wrong depth factor or transposed poses give decimetres).
const ATE_BOUND_M: f64 = 0.03;
/// The most a layout's ATE may differ from the TUM folder's (metres): the same frames, with
/// only depth quantisation and colour coding changed.
const AGREEMENT_M: f64 = 0.01;

fn camera() -> PinholeCamera {
    let s = f64::from(WIDTH) / 640.0;
    let h = WIDTH * 3 / 4;
    PinholeCamera::new(
        525.0 * s,
        525.0 * s,
        f64::from(WIDTH) * 0.5 - 0.5,
        f64::from(h) * 0.5 - 0.5,
        WIDTH,
        h,
    )
}

/// Renders the sequence once and writes it into `root/<layout>` for each of `layouts`.
fn write_all(root: &Path, layouts: &[Layout]) {
    let scene = std::sync::Arc::new(Scene::preset("office", 5).unwrap());
    let config = SequenceConfig {
        frames: FRAMES,
        fps: 30.0,
        start_time: 0.0,
        sensor: SensorModel::kinect(),
        seed: 5,
        exposure_changes: false,
        motion_blur: 0,
        exposure_time: 1.0 / 60.0,
    };
    let traj = Trajectory::new(TrajectoryKind::Handheld, &scene, config.duration(), 5).unwrap();
    let cam = camera();
    let seq = Sequence::new(
        scene,
        CameraModel::Pinhole(cam),
        traj,
        config,
        &RenderBackend::Cpu,
    )
    .unwrap();
    let mut writers: Vec<LayoutWriter> = layouts
        .iter()
        .map(|&l| LayoutWriter::create(&root.join(l.name()), l, &cam).unwrap())
        .collect();
    for f in seq {
        let f = f.unwrap();
        for w in &mut writers {
            w.write_frame(f.timestamp, &f.world_from_camera, &f.frame)
                .unwrap();
        }
    }
    for w in writers {
        w.finish("generated for tests/slam_layouts.rs\n", &[])
            .unwrap();
    }
}

/// Runs `rgbid ARGS` with info logging (which names the detected layout).
fn run(args: &[String]) -> (std::process::Output, String) {
    let o = std::process::Command::new(env!("CARGO_BIN_EXE_rgbid"))
        .args(args)
        .env("RUST_LOG", "info")
        .output()
        .expect("running rgbid");
    let log = text(&o);
    (o, log)
}

#[test]
fn slam_runs_on_every_layout_against_its_own_ground_truth() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    write_all(
        root,
        &[
            Layout::Tum,
            Layout::Eth3d,
            Layout::SevenScenes,
            Layout::ScanNet,
            Layout::Replica,
        ],
    );
    let mut ates = Vec::new();
    for layout in Layout::NAMES {
        let dir = root.join(layout);
        assert_eq!(Layout::detect(&dir).name(), layout);
        let out = root.join(format!("run-{layout}"));
        let calib = dir.join("calib.txt");
        let mut args = vec![
            "slam".to_string(),
            dir.display().to_string(),
            "--out".into(),
            out.display().to_string(),
            "--backend".into(),
            "cpu".into(),
        ];
        // 7-Scenes and Replica folders carry no camera of their own (their presets are the
        // datasets' cameras, not this one): the writer leaves a DROID-SLAM calib.txt.
        if matches!(layout, "7scenes" | "replica") {
            args.extend([
                "--camera".into(),
                calib.display().to_string(),
                "--calib-format".into(),
                "droid".into(),
            ]);
        }
        let (o, log) = run(&args);
        assert!(o.status.success(), "{layout}: {log}");
        assert!(
            log.contains(&format!("{layout} layout, camera from")),
            "{layout} not detected: {log}"
        );
        let run = RunFolder::read(&out).unwrap();
        let s = run.summary.as_ref().expect("summary.json");
        assert_eq!(s.frames, FRAMES, "{layout}");
        assert!(s.keyframes >= 1, "{layout}");
        let ate = s
            .slam_ate_rmse
            .unwrap_or_else(|| panic!("{layout}: no ATE in summary.json"));
        assert!(ate < ATE_BOUND_M, "{layout}: ATE {ate} m");
        ates.push((layout, ate));
    }
    eprintln!("ATE RMSE per layout (m): {ates:?}");
    let tum = ates[0].1;
    for (layout, ate) in &ates {
        assert!(
            (ate - tum).abs() < AGREEMENT_M,
            "{layout}: ATE {ate} m, the TUM folder's {tum} m ({ates:?})"
        );
    }
}

/// `keyframe_colour = false` from the command line keeps the keyframes grey: the same
/// keyframes, and `model.ply` is grey where the coloured run's is not. (The memory it saves is
/// checked in `slam_system.rs`: the run folder records only the account's peak, whose moment
/// depends on the back-end thread.)
#[test]
fn keyframe_colour_off_keeps_keyframes_grey() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    write_all(root, &[Layout::Tum]);
    let dir = root.join("tum").display().to_string();
    let mut runs = Vec::new();
    for (name, colour) in [("on", "true"), ("off", "false")] {
        let out = root.join(name);
        let args: Vec<String> = [
            "slam",
            &dir,
            "--out",
            &out.display().to_string(),
            "--backend",
            "cpu",
            "--voxel",
            "0",
            "--set",
            &format!("keyframe_colour={colour}"),
        ]
        .map(String::from)
        .to_vec();
        let (o, log) = run(&args);
        assert!(o.status.success(), "{name}: {log}");
        let summary = RunFolder::read(&out)
            .unwrap()
            .summary
            .expect("summary.json");
        let model = rgbid::io::ply::read_ply(&out.join("model.ply")).unwrap();
        assert!(!model.is_empty(), "{name}");
        let coloured = model
            .iter()
            .filter(|(_, c)| c[0] != c[1] || c[1] != c[2])
            .count();
        runs.push((summary.keyframes, coloured, model.len()));
    }
    let (on, off) = (runs[0], runs[1]);
    // The colour switch leaves tracking alone: the same keyframes.
    assert_eq!(on.0, off.0, "{runs:?}");
    assert!(on.1 * 10 > on.2, "the coloured model is grey: {runs:?}");
    assert_eq!(off.1, 0, "grey keyframes gave coloured points: {runs:?}");
}

/// `--calib-format droid` on another command (`rgbid odometry`): the DROID-SLAM file is read
/// with the first frame's size, a broken one is an error naming file and line, and the flag
/// alone (without --camera) is a usage error.
#[test]
fn droid_calibration_reads_on_odometry_and_names_bad_lines() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path();
    write_all(root, &[Layout::Tum]);
    let dir = root.join("tum");
    let c = camera();
    let good = root.join("droid.txt");
    std::fs::write(
        &good,
        format!("{} {} {} {} 0 0 0 0\n", c.fx, c.fy, c.cx, c.cy),
    )
    .unwrap();
    let out = root.join("odo.txt");
    let args = |calib: &Path| -> Vec<String> {
        [
            "odometry",
            &dir.display().to_string(),
            "--out",
            &out.display().to_string(),
            "--backend",
            "cpu",
            "--camera",
            &calib.display().to_string(),
            "--calib-format",
            "droid",
        ]
        .map(String::from)
        .to_vec()
    };
    let (o, log) = run(&args(&good));
    assert!(o.status.success(), "{log}");
    assert!(log.contains("(DROID-SLAM calib) at 160 x 120"), "{log}");
    let bad = root.join("bad.txt");
    std::fs::write(&bad, "# fx fy cx cy\n100 100 x 60\n").unwrap();
    let (o, log) = run(&args(&bad));
    assert!(!o.status.success(), "{log}");
    assert!(
        log.contains("bad.txt:2:") && log.contains("'x' is not a number"),
        "{log}"
    );
    let (o, log) = run(&[
        "odometry".into(),
        dir.display().to_string(),
        "--calib-format".into(),
        "droid".into(),
    ]);
    assert_eq!(o.status.code(), Some(2), "{log}");
    assert!(log.contains("--camera"), "{log}");
}
