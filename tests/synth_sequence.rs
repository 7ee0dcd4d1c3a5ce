//! Sequences, trajectories, sessions and the TUM writer.

use std::sync::Arc;

use rgbid::camera::PinholeCamera;
use rgbid::io::trajectory::read_tum;
use rgbid::synth::trajectory::{TrajectoryKind, WalkingParams, TRAJECTORIES};
use rgbid::synth::tum_export::TumWriter;
use rgbid::synth::{
    CameraModel, RenderBackend, Scene, SensorModel, Sequence, SequenceConfig, Trajectory, PRESETS,
};

fn small_camera() -> CameraModel {
    CameraModel::Pinhole(PinholeCamera::new(131.25, 131.25, 79.5, 59.5, 160, 120))
}

#[test]
fn trajectories_stay_inside_and_loops_close() {
    for name in PRESETS {
        let scene = Scene::preset(name, 5).unwrap();
        let area = scene.free_area();
        for t in TRAJECTORIES {
            let kind = TrajectoryKind::from_name(t).unwrap();
            let traj = match Trajectory::new(kind, &scene, 20.0, 3) {
                Ok(t) => t,
                // Flat walks are refused where they would reach a staircase.
                Err(e) if scene.params().staircase.is_some() => {
                    assert!(e.to_string().contains("staircase"), "{name}/{t}: {e}");
                    continue;
                }
                Err(e) => panic!("{name}/{t}: {e}"),
            };
            let mut prev = traj.pose_at(0.0);
            let mut max_step = 0.0f64;
            for i in 0..=200 {
                let p = traj.pose_at(i as f64 * 0.1);
                let e = p.translation;
                assert!(p.is_finite());
                assert!(
                    e.x > area.min.x - 0.5
                        && e.x < area.max.x + 0.5
                        && e.y > area.min.y - 0.5
                        && e.y < area.max.y + 0.5,
                    "{name}/{t}: eye {e} outside the free area {area:?}"
                );
                // The stairs trajectory climbs 2 m above the floor it started on (no stair geometry).
                let top = if kind == TrajectoryKind::Stairs {
                    area.ceiling + 2.1
                } else {
                    area.ceiling - 0.05
                };
                assert!(e.z > 0.2 && e.z < top, "{name}/{t}: eye height {}", e.z);
                max_step = max_step.max((p.translation - prev.translation).length());
                prev = p;
            }
            // A `loop` makes one lap of the free area in the duration: around the long
            // open-route presets that is far faster than a person, and they are not walked so.
            let lap = kind == TrajectoryKind::Loop && scene.params().open_route;
            assert!(max_step < 0.25 || lap, "{name}/{t}: {max_step} m in 0.1 s");
            if kind == TrajectoryKind::Loop {
                let d = traj.pose_at(0.0).inverse() * traj.pose_at(20.0);
                assert!(
                    d.translation.length() < 1e-6 && d.angle() < 1e-6,
                    "{name}: loop does not close"
                );
                let mid = traj.pose_at(0.0).inverse() * traj.pose_at(10.0);
                assert!(
                    mid.translation.length() > 0.5,
                    "{name}: loop does not go anywhere"
                );
            }
            if kind == TrajectoryKind::Robot {
                for i in 0..50 {
                    let p = traj.pose_at(i as f64 * 0.4);
                    assert!((p.translation.z - 0.4).abs() < 1e-9);
                    // Camera y (down) stays along -z: pure planar motion.
                    assert!((p.transform_vector(glam::DVec3::Y) + glam::DVec3::Z).length() < 1e-9);
                }
            }
        }
    }
}

#[test]
fn walking_speed_and_bob_follow_the_step_frequency() {
    let scene = Scene::preset("lab", 1).unwrap();
    let params = WalkingParams::default();
    let traj = Trajectory::walking(&scene, params.clone(), 19.0, 2);
    // Distance walked in the steady part of each pace segment matches V = alpha f^beta H.
    for (t0, t1, f) in [
        (1.5, 5.5, 1.6),
        (7.5, 10.5, 2.0),
        (12.5, 12.9, 0.0),
        (14.5, 18.5, 1.3),
    ] {
        let (s0, _) = traj.walking_state(t0).unwrap();
        let (s1, _) = traj.walking_state(t1).unwrap();
        let v = (s1 - s0) / (t1 - t0);
        assert!(
            (v - params.speed(f)).abs() < 1e-3,
            "f {f}: v {v} vs {}",
            params.speed(f)
        );
    }
    // Vertical oscillation at the step frequency while walking at 1.6 Hz: count the maxima of height.
    let mut z = Vec::new();
    for i in 0..400 {
        z.push(traj.pose_at(1.5 + i as f64 * 0.01).translation.z);
    }
    let peaks = (1..z.len() - 1)
        .filter(|&i| z[i] > z[i - 1] && z[i] >= z[i + 1])
        .count();
    assert!(
        (5..=8).contains(&peaks),
        "{peaks} height maxima in 4 s at 1.6 steps/s"
    );
    // Standing still: no motion at all.
    let a = traj.pose_at(12.5);
    let b = traj.pose_at(12.9);
    assert!((a.translation - b.translation).length() < 1e-3);
    // Stairs: climbs 12 x 0.17 m.
    let stairs = Trajectory::new(TrajectoryKind::Stairs, &scene, 30.0, 2).unwrap();
    let rise = stairs.pose_at(29.0).translation.z - stairs.pose_at(1.0).translation.z;
    assert!((rise - 12.0 * 0.17).abs() < 0.08, "rise {rise}");
}

#[test]
fn sequence_streams_frames_with_ground_truth() {
    let scene = Arc::new(Scene::preset("corridor", 3).unwrap());
    let traj = Trajectory::new(TrajectoryKind::Handheld, &scene, 1.0, 3).unwrap();
    let config = SequenceConfig {
        frames: 4,
        fps: 30.0,
        start_time: 10.0,
        exposure_changes: true,
        ..Default::default()
    };
    let seq = Sequence::new(
        scene,
        small_camera(),
        traj.clone(),
        config,
        &RenderBackend::Cpu,
    )
    .unwrap();
    let gt = seq.ground_truth();
    let gains: Vec<f64> = (0..4).map(|i| seq.gain(i)).collect();
    let frames: Vec<_> = seq.map(|f| f.unwrap()).collect();
    assert_eq!(frames.len(), 4);
    for (f, g) in frames.iter().zip(&gt) {
        assert_eq!(f.timestamp, g.timestamp);
        assert_eq!(f.world_from_camera, g.world_from_camera);
        let p = traj.pose_at(f.timestamp - 10.0);
        assert!((f.world_from_camera.translation - p.translation).length() < 1e-9);
        assert!((f.world_from_camera.rotation.dot(p.rotation).abs() - 1.0).abs() < 1e-12);
        assert!(f.frame.moved_mask.is_none());
        let rgbd = f.frame.to_rgbd_frame(f.timestamp);
        assert_eq!((rgbd.width(), rgbd.height()), (160, 120));
    }
    assert!(gains.windows(2).all(|w| w[0] != w[1]));
    assert_ne!(frames[0].frame.rgb, frames[1].frame.rgb);
}

#[test]
fn sessions_move_objects_and_masks_mark_them() {
    let base = Scene::preset("office", 8).unwrap();
    let s1 = base.session(1);
    let again = base.session(1);
    assert_eq!(s1.packed().prims, again.packed().prims);
    assert!(!s1.changed_objects().is_empty());
    // Static structure is identical.
    let structure = |s: &Scene| {
        s.objects()
            .iter()
            .filter(|o| !o.movable)
            .map(|o| o.prims.clone())
            .collect::<Vec<_>>()
    };
    assert_eq!(structure(&base), structure(&s1));
    assert_ne!(base.packed().prims, s1.packed().prims);
    // Masks: across a set of views, some pixels see moved objects, and every masked pixel sees a changed object.
    let cam = PinholeCamera::new(131.25, 131.25, 79.5, 59.5, 160, 120);
    let mut masked = 0;
    for k in 0..8 {
        let c = s1.free_area().center();
        let pose = rgbid::synth::trajectory::camera_pose(
            glam::DVec3::new(c.x, c.y, 1.5),
            k as f64 * 0.785,
            -0.45,
            0.0,
        );
        let f = rgbid::synth::render_pinhole(&s1, &cam, &pose, &SensorModel::noiseless(), 0);
        let mask = f.moved_mask.expect("sessions > 0 have masks");
        for (m, o) in mask.iter().zip(&f.object_ids) {
            assert_eq!(*m, s1.changed_objects().binary_search(o).is_ok());
            masked += usize::from(*m);
        }
        assert!(
            rgbid::synth::render_pinhole(&base, &cam, &pose, &SensorModel::noiseless(), 0)
                .moved_mask
                .is_none()
        );
    }
    assert!(masked > 50, "only {masked} masked pixels over 8 views");
}

fn write_folder(dir: &std::path::Path, session: u32) {
    let scene = Arc::new(Scene::preset("kitchen", 4).unwrap().session(session));
    let traj = Trajectory::new(TrajectoryKind::Loop, &scene, 0.2, 4).unwrap();
    let config = SequenceConfig {
        frames: 3,
        seed: 4,
        ..Default::default()
    };
    let cam = small_camera();
    let seq = Sequence::new(scene, cam, traj, config, &RenderBackend::Cpu).unwrap();
    let mut w = TumWriter::create(dir, &cam).unwrap();
    for f in seq {
        let f = f.unwrap();
        w.write_frame(f.timestamp, &f.world_from_camera, &f.frame)
            .unwrap();
    }
    w.finish(
        "readme\n",
        &[("session.txt", format!("session {session}\n"))],
    )
    .unwrap();
}

#[test]
fn tum_folder_is_complete_and_byte_identical() {
    let a = tempfile::tempdir().unwrap();
    let b = tempfile::tempdir().unwrap();
    write_folder(a.path(), 1);
    write_folder(b.path(), 1);
    let mut files = Vec::new();
    for sub in ["", "rgb", "depth", "masks"] {
        for e in std::fs::read_dir(a.path().join(sub)).unwrap() {
            let p = e.unwrap().path();
            if p.is_file() {
                files.push(p.strip_prefix(a.path()).unwrap().to_path_buf());
            }
        }
    }
    files.sort();
    for f in &files {
        assert_eq!(
            std::fs::read(a.path().join(f)).unwrap(),
            std::fs::read(b.path().join(f)).unwrap(),
            "{f:?} differs"
        );
    }
    for name in [
        "rgb.txt",
        "depth.txt",
        "associations.txt",
        "groundtruth.txt",
        "calib.txt",
        "camera.json",
        "README.txt",
        "masks.txt",
    ] {
        assert!(a.path().join(name).exists(), "{name} missing");
    }
    assert_eq!(std::fs::read_dir(a.path().join("rgb")).unwrap().count(), 3);
    assert_eq!(
        std::fs::read_to_string(a.path().join("calib.txt"))
            .unwrap()
            .trim(),
        "131.25 131.25 79.5 59.5 5000 160 120"
    );
    let gt = read_tum(&a.path().join("groundtruth.txt")).unwrap();
    assert_eq!(gt.len(), 3);
    let assoc = std::fs::read_to_string(a.path().join("associations.txt")).unwrap();
    let first = assoc.lines().next().unwrap();
    let parts: Vec<&str> = first.split_whitespace().collect();
    assert_eq!(parts.len(), 4);
    // Depth PNG round trip equals the in-memory inverse depth.
    let depth = image::open(a.path().join(parts[3])).unwrap().into_luma16();
    let scene = Arc::new(Scene::preset("kitchen", 4).unwrap().session(1));
    let traj = Trajectory::new(TrajectoryKind::Loop, &scene, 0.2, 4).unwrap();
    let mut seq = Sequence::new(
        scene,
        small_camera(),
        traj,
        SequenceConfig {
            frames: 3,
            seed: 4,
            ..Default::default()
        },
        &RenderBackend::Cpu,
    )
    .unwrap();
    let f0 = seq.next().unwrap().unwrap();
    let mut valid = 0;
    for (i, px) in depth.pixels().enumerate() {
        let inv = f0.frame.inverse_depth.data()[i];
        if px.0[0] == 0 {
            assert_eq!(inv, 0.0);
        } else {
            valid += 1;
            assert!((5000.0 / f64::from(px.0[0]) - f64::from(inv)).abs() < 1e-6);
        }
    }
    assert!(valid > 1000);
    let rgb = image::open(a.path().join(parts[1])).unwrap().into_rgb8();
    assert_eq!(rgb.as_raw(), &f0.frame.rgb);
}

/// The `home` preset has soft objects (sphere clusters, movable), and its sessions add soft
/// objects rather than piles; the other presets have none (their scenes are unchanged).
#[test]
fn home_preset_has_soft_objects_that_sessions_change() {
    use rgbid::synth::ObjectKind;
    let soft = |s: &Scene| {
        s.objects()
            .iter()
            .filter(|o| o.kind == ObjectKind::Soft)
            .map(|o| o.id)
            .collect::<Vec<_>>()
    };
    let home = Scene::preset("home", 3).unwrap();
    let ids = soft(&home);
    assert_eq!(ids.len(), home.params().soft_objects);
    assert!(ids.len() >= 5);
    for o in home.objects().iter().filter(|o| o.kind == ObjectKind::Soft) {
        assert!(o.movable);
        assert!(o.prims.len() >= 8, "{} spheres", o.prims.len());
        assert!(o
            .prims
            .iter()
            .all(|p| matches!(p.shape, rgbid::synth::Shape::Sphere { .. })));
    }
    let s1 = home.session(1);
    let added: Vec<u32> = soft(&s1)
        .into_iter()
        .filter(|id| !ids.contains(id))
        .collect();
    assert!(!added.is_empty(), "session 1 adds soft objects");
    assert!(added.iter().all(|id| s1.changed_objects().contains(id)));
    for name in ["office", "kitchen", "corridor", "lab"] {
        assert!(soft(&Scene::preset(name, 3).unwrap()).is_empty(), "{name}");
    }
}
