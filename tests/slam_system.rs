//! The SLAM system end to end on generated sequences (CPU backend): tracking and keyframes,
//! map files (round trip, truncated, foreign), relocalisation of a second session in a saved
//! map of a changed scene.

use std::sync::Arc;

use rgbid::camera::PinholeCamera;
use rgbid::eval::{evaluate, EvalOptions};
use rgbid::geometry::Se3;
use rgbid::gpu::ComputeBackend;
use rgbid::image::RgbdFrame;
use rgbid::place::Vocabulary;
use rgbid::slam::{
    build_mesh, BufferedFusion, EventOptions, FrameReport, FrameStatus, KeyframeLink, Map,
    MapError, Slam, SlamConfig, SlamError, SlamEvent, SlamResult,
};
use rgbid::synth::{
    CameraModel, RenderBackend, Scene, Sequence, SequenceConfig, Trajectory, TrajectoryKind,
};
use rgbid::trajectory::TimedPose;
use rgbid::tsdf::{mesh_accuracy, TsdfParams};

fn camera(w: u32) -> PinholeCamera {
    let h = w * 3 / 4;
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

fn sequence(
    scene: Scene,
    kind: TrajectoryKind,
    frames: usize,
    seed: u64,
    cam: PinholeCamera,
) -> Sequence {
    sequence_with_noise(scene, kind, frames, frames, seed, seed, cam)
}

/// `frames` frames at 30 fps of a trajectory lasting `trajectory_frames / 30` seconds.
fn sequence_with_noise(
    scene: Scene,
    kind: TrajectoryKind,
    frames: usize,
    trajectory_frames: usize,
    seed: u64,
    noise_seed: u64,
    cam: PinholeCamera,
) -> Sequence {
    let config = SequenceConfig {
        frames,
        seed: noise_seed,
        ..Default::default()
    };
    let traj = Trajectory::new(kind, &scene, trajectory_frames as f64 / 30.0, seed).unwrap();
    Sequence::new(
        Arc::new(scene),
        CameraModel::Pinhole(cam),
        traj,
        config,
        &RenderBackend::Cpu,
    )
    .unwrap()
}

/// Runs SLAM over `seq`; `modify(i, frame)` may alter frame `i` before it is processed.
/// Returns the finished result and every frame's report.
fn run(
    seq: &mut Sequence,
    cam: PinholeCamera,
    config: SlamConfig,
    map: Option<Map>,
    modify: impl FnMut(usize, &mut RgbdFrame),
) -> (SlamResult, Vec<FrameReport>) {
    let (r, reports, _) = run_observed(seq, cam, config, map, modify);
    (r, reports)
}

/// [`run`] with the event stream on, read after every frame and to its end after `finish`
/// (so nothing may be dropped).
fn run_observed(
    seq: &mut Sequence,
    cam: PinholeCamera,
    config: SlamConfig,
    map: Option<Map>,
    mut modify: impl FnMut(usize, &mut RgbdFrame),
) -> (SlamResult, Vec<FrameReport>, Vec<SlamEvent>) {
    let mut slam = Slam::new(
        config,
        cam,
        &ComputeBackend::Cpu,
        Vocabulary::embedded_default().unwrap(),
        map,
    )
    .unwrap();
    // Bounds no run here reaches: a reader after every frame must lose nothing.
    let events = slam.events_with(EventOptions {
        capacity: 1 << 20,
        images: 1 << 20,
    });
    let mut got = Vec::new();
    let mut reports = Vec::new();
    for i in 0..seq.len() {
        let f = seq.render_frame(i).unwrap();
        let mut frame = f.frame.to_rgbd_frame(f.timestamp);
        modify(i, &mut frame);
        reports.push(slam.process(&frame).unwrap());
        got.extend(events.try_iter());
    }
    let r = slam.finish().unwrap();
    got.extend(events.clone());
    assert_eq!(
        events.dropped().total(),
        0,
        "a reader after every frame lost events"
    );
    (r, reports, got)
}

/// SLAM over the same rendered frames of `seq` once per configuration (CPU backend).
fn finish_each<const N: usize>(
    seq: &mut Sequence,
    cam: PinholeCamera,
    configs: [SlamConfig; N],
) -> Vec<SlamResult> {
    let frames: Vec<RgbdFrame> = (0..seq.len())
        .map(|i| {
            let f = seq.render_frame(i).unwrap();
            f.frame.to_rgbd_frame(f.timestamp)
        })
        .collect();
    configs
        .into_iter()
        .map(|config| {
            let vocabulary = Vocabulary::embedded_default().unwrap();
            let mut slam = Slam::new(config, cam, &ComputeBackend::Cpu, vocabulary, None).unwrap();
            for f in &frames {
                slam.process(f).unwrap();
            }
            slam.finish().unwrap()
        })
        .collect()
}

/// One keyframe-created and one keyframe-described event per keyframe, in id order, that
/// agree with the keyframes of the result.
fn check_keyframe_events(r: &SlamResult, events: &[SlamEvent], thresholds: usize) {
    let created: Vec<_> = events
        .iter()
        .filter_map(|e| match e {
            SlamEvent::KeyframeCreated {
                id,
                frame_index,
                timestamp,
                world_from_keyframe,
                ..
            } => Some((*id, *frame_index, *timestamp, *world_from_keyframe)),
            _ => None,
        })
        .collect();
    assert_eq!(created.len(), r.keyframes().len());
    for ((id, frame_index, timestamp, pose), kf) in created.iter().zip(r.keyframes()) {
        assert_eq!(
            (*id, *frame_index, *timestamp),
            (kf.id, kf.frame_index, kf.timestamp)
        );
        assert!(pose.is_finite());
    }
    let described: Vec<_> = events
        .iter()
        .filter_map(|e| match e {
            SlamEvent::KeyframeDescribed(d) => Some(d),
            _ => None,
        })
        .collect();
    assert_eq!(described.len(), r.keyframes().len());
    for (d, kf) in described.iter().zip(r.keyframes()) {
        assert_eq!(d.id, kf.id);
        let labels = d.labels.as_ref().expect("label image");
        assert_eq!(labels.labels.len(), kf.width * kf.height);
        assert!(!d.neg_entropy.is_empty() && !d.keypoints.is_empty());
        assert_eq!(d.mask_flags.len(), 1 + thresholds);
        assert!(d.mask_flags.iter().all(|f| f.len() == d.keypoints.len()));
        assert_eq!(d.mask_flags, r.map.mask_flags[kf.id]);
        let img = d.neg_entropy_image().unwrap();
        assert!(img.data().iter().any(|v| v.is_finite()));
    }
}

/// The loop-checked events are the result's loop records, in order.
fn check_loop_events(r: &SlamResult, events: &[SlamEvent]) {
    let checked: Vec<_> = events
        .iter()
        .filter_map(|e| match e {
            SlamEvent::LoopChecked(l) => Some(l),
            _ => None,
        })
        .collect();
    assert_eq!(checked.len(), r.loops.len());
    for (a, b) in checked.iter().zip(&r.loops) {
        assert_eq!(
            (a.query, a.candidate, a.inliers, a.relocalisation, a.verdict),
            (b.query, b.candidate, b.inliers, b.relocalisation, b.verdict)
        );
        assert_eq!(a.verdict.reason().is_empty(), a.verdict.is_accepted());
    }
}

fn statuses(reports: &[FrameReport]) -> Vec<FrameStatus> {
    reports.iter().map(|r| r.status).collect()
}

#[test]
fn slam_tracks_a_generated_sequence_with_keyframes_and_a_map_file() {
    let cam = camera(192);
    let scene = Scene::preset("office", 3).unwrap();
    let mut seq = sequence(scene, TrajectoryKind::Handheld, 90, 3, cam);
    let gt = seq.ground_truth();
    let (r, reports) = run(&mut seq, cam, SlamConfig::default(), None, |_, _| {});
    let status = statuses(&reports);
    assert!(status.iter().all(|s| *s != FrameStatus::Lost), "{status:?}");
    assert_eq!(r.trajectory.len(), 90);
    // Every tracked frame after the first carries the odometry's diagnostics.
    for rep in &reports[1..] {
        let d = rep.record.diagnostics;
        assert!(
            d.iterations > 0 && d.sigma_photo > 0.0 && d.sigma_geo > 0.0,
            "frame {}: {d:?}",
            rep.record.index
        );
        assert!(d.condition_number.is_finite() && d.condition_number >= 1.0);
    }
    assert!(
        r.keyframes().len() >= 2,
        "{} keyframes",
        r.keyframes().len()
    );
    assert_eq!(r.timings.len(), r.keyframes().len());
    let m = evaluate(&gt, &r.trajectory, &EvalOptions::default()).unwrap();
    assert!(
        m.ate.translation.rmse < 0.03,
        "ATE {}",
        m.ate.translation.rmse
    );
    // Keyframe fusion keeps most of the depth and raises the weights above 1.
    let kf = &r.keyframes()[0];
    assert!(kf.weight.iter().filter(|&&w| w >= 2).count() > kf.weight.len() / 3);

    // Map round trip.
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("a.rgbmap");
    r.map.save(&path).unwrap();
    let back = Map::load(&path).unwrap();
    assert_eq!(back.keyframes.len(), r.map.keyframes.len());
    assert_eq!(back.keyframes[1].intensity, r.map.keyframes[1].intensity);
    assert_eq!(
        back.keyframes[1].inverse_depth,
        r.map.keyframes[1].inverse_depth
    );
    assert_eq!(back.features[1].descriptors, r.map.features[1].descriptors);
    assert_eq!(back.mask_flags, r.map.mask_flags);
    assert_eq!(back.edges.len(), r.map.edges.len());
    let d =
        back.keyframes[1].world_from_keyframe.inverse() * r.map.keyframes[1].world_from_keyframe;
    assert!(d.translation.length() < 1e-12);

    // Truncated, foreign and future files are clear errors.
    let bytes = std::fs::read(&path).unwrap();
    let cut = dir.path().join("cut.rgbmap");
    std::fs::write(&cut, &bytes[..bytes.len() * 2 / 3]).unwrap();
    assert!(matches!(Map::load(&cut), Err(MapError::Corrupt { .. })));
    let foreign = dir.path().join("f.rgbmap");
    std::fs::write(&foreign, b"PK\x03\x04 not a map").unwrap();
    assert!(matches!(Map::load(&foreign), Err(MapError::Foreign(_))));
    let mut future = bytes.clone();
    future[8] = 99;
    let fut = dir.path().join("v.rgbmap");
    std::fs::write(&fut, &future).unwrap();
    let e = Map::load(&fut).unwrap_err();
    assert!(matches!(e, MapError::Version { found: 99, .. }), "{e}");
    assert!(e.to_string().contains("v.rgbmap"));
}

/// Each `Slam` keeps its own memory account: two instances in one process, one fed three
/// times the frames of the other, report their own keyframes, descriptions, records and
/// segmentation buffers; the account grows with the keyframes, its peak never falls and is
/// never below what is held, and one instance stopping frees none of the other's buffers.
#[test]
fn two_instances_account_their_own_memory() {
    let cam = camera(192);
    let pixels = 192 * 144;
    let scene = Scene::preset("office", 3).unwrap();
    let mut seq = sequence(scene, TrajectoryKind::Handheld, 90, 3, cam);
    let new_slam = || {
        Slam::new(
            SlamConfig::default(),
            cam,
            &ComputeBackend::Cpu,
            Vocabulary::embedded_default().unwrap(),
            None,
        )
        .unwrap()
    };
    let (mut a, mut b) = (new_slam(), new_slam());
    let b_frames = 30;
    let mut accounts = Vec::new();
    let mut a_keyframes = 0;
    for i in 0..seq.len() {
        let f = seq.render_frame(i).unwrap();
        let frame = f.frame.to_rgbd_frame(f.timestamp);
        if a.process(&frame).unwrap().status == FrameStatus::NewKeyframe {
            a_keyframes += 1;
        }
        if i < b_frames {
            b.process(&frame).unwrap();
        }
        let m = a.memory();
        assert!(m.peak_bytes() >= m.now.total(), "frame {i}: {m:?}");
        accounts.push(m);
    }
    for (i, w) in accounts.windows(2).enumerate() {
        let (before, after) = (&w[0], &w[1]);
        assert!(after.peak_bytes() >= before.peak_bytes(), "frame {i}");
        // Keyframes are only ever added; one more frame record each frame.
        assert!(after.now.keyframes >= before.now.keyframes, "frame {i}");
        assert!(after.now.records >= before.now.records, "frame {i}");
    }
    let last = accounts.last().unwrap();
    assert!(last.now.odometry > 0 && last.now.fusion > 0, "{last:?}");
    assert_eq!(last.now.gpu, 0, "CPU backend");
    // Once A's back-end has segmented a keyframe (it got one when the second started), B
    // stopping (its back-end frees its segmentation buffers) leaves A's alone.
    assert!(a_keyframes >= 2, "{a_keyframes} keyframes");
    let t = std::time::Instant::now();
    while a.memory().now.segmenter == 0 && t.elapsed().as_secs() < 120 {
        std::thread::sleep(std::time::Duration::from_millis(10));
    }
    let rb = b.finish().unwrap();
    assert!(a.memory().now.segmenter >= 100 * pixels);
    let ra = a.finish().unwrap();
    assert!(ra.keyframes().len() > rb.keyframes().len());
    for r in [&ra, &rb] {
        let m = r.memory;
        // This instance's keyframe images (4 bytes per pixel, and 3 of RGB: the generated
        // frames have colour) and no other's.
        let images: usize = r
            .keyframes()
            .iter()
            .map(|k| {
                k.intensity.len()
                    + 2 * k.inverse_depth.len()
                    + k.weight.len()
                    + k.colour.as_ref().map_or(0, |c| c.rgb().len())
            })
            .sum();
        assert_eq!(images, 7 * pixels * r.keyframes().len());
        assert!(
            m.now.keyframes >= images && m.now.keyframes < images + 64 * 1024,
            "{} keyframe bytes for {} keyframes",
            m.now.keyframes,
            r.keyframes().len()
        );
        // The back-end freed its segmentation buffers when it stopped; the peak held them.
        assert_eq!(m.now.segmenter, 0);
        assert!(m.peak.segmenter >= 100 * pixels, "{m:?}");
        assert!(m.peak_bytes() >= m.now.total());
        assert!(m.now.place_recognition > 0 && m.now.pose_graph > 0);
    }
    let (ma, mb) = (ra.memory, rb.memory);
    assert!(ma.now.keyframes > mb.now.keyframes);
    assert!(ma.now.place_recognition > mb.now.place_recognition);
    assert!(ma.now.records > mb.now.records);
    assert!(ma.peak_bytes() > mb.peak_bytes());
}

#[test]
fn wrong_frame_size_is_an_error_not_a_panic() {
    let cam = camera(160);
    let mut slam = Slam::new(
        SlamConfig::default(),
        cam,
        &ComputeBackend::Cpu,
        Vocabulary::embedded_default().unwrap(),
        None,
    )
    .unwrap();
    let f = rgbid::image::test_pattern(64, 48, 1);
    let e = slam.process(&f).unwrap_err();
    assert!(matches!(e, SlamError::FrameSize { got_w: 64, .. }), "{e}");
}

/// Second session of a changed scene (objects moved) starts lost in the saved map of the
/// first session and must relocalise; its poses are then in the map's frame.
#[test]
fn second_session_relocalises_in_the_saved_map() {
    let cam = camera(192);
    let scene = Scene::preset("office", 5).unwrap();
    let session1 = scene.session(1);
    // One lap takes 300 frames (10 s); session 0 maps the first 120 frames of it.
    let mut s0 = sequence_with_noise(scene, TrajectoryKind::Loop, 120, 300, 5, 5, cam);
    let gt0 = s0.ground_truth();
    let (r0, _) = run(&mut s0, cam, SlamConfig::default(), None, |_, _| {});
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("office.rgbmap");
    r0.map.save(&path).unwrap();
    let map = Map::load(&path).unwrap();
    let n_map = map.keyframes.len();

    // Same path, other session (moved objects), other sensor noise; only the first 40 frames.
    let mut s1 = sequence_with_noise(session1, TrajectoryKind::Loop, 40, 300, 5, 77, cam);
    let gt1 = s1.ground_truth();
    let (r1, reports) = run(&mut s1, cam, SlamConfig::default(), Some(map), |_, _| {});
    let first_reloc = reports
        .iter()
        .position(|r| r.status == FrameStatus::Relocalised);
    let i = first_reloc.expect("the second session never relocalised in the map");
    assert!(i < 10, "relocalised only at frame {i}");
    assert!(r1.keyframes().len() > n_map);
    // Map frame = first camera of session 0: map_from_world = inv(gt0[0]).
    let map_from_world = gt0[0].world_from_camera.inverse();
    let est: Vec<TimedPose> = r1.trajectory.clone();
    let mut worst: f64 = 0.0;
    for e in &est {
        let g = gt1
            .iter()
            .min_by(|a, b| {
                (a.timestamp - e.timestamp)
                    .abs()
                    .total_cmp(&(b.timestamp - e.timestamp).abs())
            })
            .unwrap();
        let want: Se3 = map_from_world * g.world_from_camera;
        worst = worst.max((want.translation - e.world_from_camera.translation).length());
    }
    assert!(
        worst < 0.08,
        "worst position error in the map frame {worst} m"
    );
}

/// The sensor is covered for a few frames: those frames are reported lost (no pose), then
/// the system relocalises against its own keyframes and goes on in the same map.
#[test]
fn lost_tracking_is_reported_and_relocalised() {
    let cam = camera(192);
    let scene = Scene::preset("office", 9).unwrap();
    let mut seq = sequence_with_noise(scene, TrajectoryKind::Loop, 60, 300, 9, 9, cam);
    let gt = seq.ground_truth();
    let covered = 30..34;
    let (r, reports, events) =
        run_observed(&mut seq, cam, SlamConfig::default(), None, |i, frame| {
            if covered.contains(&i) {
                // Covered sensor: black image, no depth.
                frame
                    .intensity_mut()
                    .data_mut()
                    .iter_mut()
                    .for_each(|v| *v = 0.0);
                frame
                    .inverse_depth_mut()
                    .data_mut()
                    .iter_mut()
                    .for_each(|v| *v = 0.0);
            }
        });
    for i in covered.clone() {
        assert!(
            reports[i].world_from_camera.is_none(),
            "frame {i} kept a pose while covered"
        );
    }
    let status = statuses(&reports);
    assert!(
        status[30..34].iter().all(|s| *s == FrameStatus::Lost),
        "{status:?}"
    );
    let back = status[34..]
        .iter()
        .position(|s| *s == FrameStatus::Relocalised);
    assert!(
        back.is_some_and(|k| k < 5),
        "no relocalisation soon after: {status:?}"
    );
    assert_eq!(r.trajectory.len(), 60 - 4 - back.unwrap());
    // Events: lost once at the first covered frame, relocalised where the report says, with
    // a keyframe started there and linked to the keyframe it relocalised against.
    let lost: Vec<usize> = events
        .iter()
        .filter_map(|e| match e {
            SlamEvent::Lost { frame_index, .. } => Some(*frame_index),
            _ => None,
        })
        .collect();
    assert_eq!(lost, vec![30]);
    let reloc: Vec<_> = events
        .iter()
        .filter_map(|e| match e {
            SlamEvent::Relocalised {
                frame_index,
                keyframe,
                new_keyframe,
                world_from_camera,
                ..
            } => Some((*frame_index, *keyframe, *new_keyframe, *world_from_camera)),
            _ => None,
        })
        .collect();
    assert_eq!(reloc.len(), 1, "{reloc:?}");
    let (frame, against, new_kf, pose) = reloc[0];
    assert_eq!(frame, 34 + back.unwrap());
    let reported = reports[frame].world_from_camera.unwrap();
    assert!((reported.inverse() * pose).translation.length() < 1e-9);
    assert!(events.iter().any(|e| matches!(
        e,
        SlamEvent::KeyframeCreated { id, frame_index, link: KeyframeLink::Relocalised { from, .. }, .. }
            if *id == new_kf && *frame_index == frame && *from == against
    )));
    check_loop_events(&r, &events);
    // Same map frame before and after the loss.
    let m = evaluate(&gt, &r.trajectory, &EvalOptions::default()).unwrap();
    assert!(
        m.ate.translation.rmse < 0.03,
        "ATE {}",
        m.ate.translation.rmse
    );
}

/// Two laps of a closed loop: the second lap revisits the first, loops are detected,
/// verified, refined and close the graph; SLAM's ATE must be at most half of odometry's.
#[test]
fn loop_closure_halves_the_odometry_error_on_two_laps() {
    let cam = camera(192);
    let scene = Scene::preset("kitchen", 2).unwrap();
    // 240 frames per lap (8 s), two laps.
    let mut seq = sequence_with_noise(scene, TrajectoryKind::Loop, 480, 240, 2, 2, cam);
    let gt = seq.ground_truth();
    let (r, reports, events) = run_observed(&mut seq, cam, SlamConfig::default(), None, |_, _| {});
    assert!(statuses(&reports).iter().all(|s| *s != FrameStatus::Lost));
    check_keyframe_events(&r, &events, SlamConfig::default().mask_thresholds.len());
    check_loop_events(&r, &events);
    // The graph is optimised once a loop is accepted, over every keyframe made by then.
    let first_accepted = events
        .iter()
        .position(|e| matches!(e, SlamEvent::LoopChecked(l) if l.verdict.is_accepted()))
        .expect("an accepted loop event");
    let optimised: Vec<(usize, usize)> = events[first_accepted..]
        .iter()
        .filter_map(|e| match e {
            SlamEvent::GraphOptimised {
                world_from_keyframe,
                loops,
                ..
            } => Some((world_from_keyframe.len(), *loops)),
            _ => None,
        })
        .collect();
    assert!(
        !optimised.is_empty(),
        "no graph-optimised event after a loop"
    );
    for (n, loops) in optimised {
        assert!(
            n >= 2 && n <= r.keyframes().len() && loops >= 1,
            "{n} {loops}"
        );
    }
    let accepted = r.loops.iter().filter(|l| l.verdict.is_accepted()).count();
    assert!(
        accepted >= 3,
        "only {accepted} loops accepted: {:?}",
        r.loops
    );
    let slam = evaluate(&gt, &r.trajectory, &EvalOptions::default()).unwrap();
    let odo = evaluate(&gt, &r.odometry, &EvalOptions::default()).unwrap();
    let (a, b) = (slam.ate.translation.rmse, odo.ate.translation.rmse);
    eprintln!("two laps: SLAM ATE {a:.4} m, odometry {b:.4} m, {accepted} loops");
    assert!(
        a <= 0.5 * b,
        "SLAM ATE {a} not at most half of odometry {b}"
    );

    // The TSDF mesh of the keyframes re-integrated at their optimised poses lies closer to
    // the true surface than the one at their odometry poses (what integration without
    // re-integration after the loop closures keeps: the second lap's copy of each wall is
    // displaced by the drift). Both are anchored to the ground truth at the
    // first keyframe.
    let scene = Scene::preset("kitchen", 2).unwrap();
    let kfs = r.keyframes();
    assert!(
        kfs.iter().all(|k| k.colour.is_some()),
        "keyframes without colour"
    );
    let params = TsdfParams {
        voxel_size: 0.02,
        ..Default::default()
    };
    let mean_distance = |poses: Vec<Se3>| {
        let true_from_map = gt[kfs[0].frame_index].world_from_camera * poses[0].inverse();
        let poses: Vec<Se3> = poses.iter().map(|p| true_from_map * *p).collect();
        let mesh = build_mesh(kfs, &poses, &cam, &params, 2, &ComputeBackend::Cpu).unwrap();
        let acc = mesh_accuracy(&mesh.vertices, |p| scene.surface_distance(p), &[], 0.04);
        assert!(acc.vertices > 1000, "{} vertices", acc.vertices);
        // The keyframes keep the generated frames' colour, so the mesh is coloured.
        let coloured = mesh
            .colours
            .iter()
            .filter(|c| c[0] != c[1] || c[1] != c[2])
            .count();
        assert!(
            2 * coloured > mesh.colours.len(),
            "{coloured} of {} vertices coloured",
            mesh.colours.len()
        );
        acc.mean_m
    };
    let optimised = mean_distance(r.keyframe_poses.clone());
    // The odometry-only pose of each keyframe's frame: the surface without loop closure.
    let tracked: Vec<Se3> = kfs
        .iter()
        .map(|k| {
            r.odometry
                .iter()
                .find(|p| (p.timestamp - k.timestamp).abs() < 1e-6)
                .map(|p| p.world_from_camera)
                .expect("an odometry pose per keyframe")
        })
        .collect();
    let front_end = mean_distance(tracked);
    eprintln!(
        "two laps: mesh {:.1} mm from the true surface re-integrated, {:.1} mm as tracked",
        optimised * 1e3,
        front_end * 1e3
    );
    assert!(
        optimised < front_end,
        "re-integrated mesh {optimised} m not closer than the tracked one {front_end} m"
    );
}

/// A one-second lap of the office (about 10 m/s, far beyond a handheld camera): the dense
/// alignment converges to wrong poses with high covisibility. With the default speed bounds
/// those frames are reported lost instead of keeping a wrong pose; without them (the bounds
/// disabled) the same frames keep poses that are decimetres off, so the scenario is real.
#[test]
fn implausibly_fast_motion_is_lost_not_a_wrong_pose() {
    let cam = camera(320);
    let worst_error = |config: SlamConfig| {
        let scene = Scene::preset("office", 1).unwrap();
        let mut seq = sequence_with_noise(scene, TrajectoryKind::Loop, 8, 30, 1, 1, cam);
        let gt = seq.ground_truth();
        let (_, reports) = run(&mut seq, cam, config, None, |_, _| {});
        let origin = gt[0].world_from_camera.inverse();
        let mut worst: f64 = 0.0;
        for (i, r) in reports.iter().enumerate() {
            if let Some(p) = r.world_from_camera {
                let truth = origin * gt[i].world_from_camera;
                worst = worst.max((truth.translation - p.translation).length());
            }
        }
        (worst, statuses(&reports))
    };
    let unbounded = SlamConfig {
        lost_max_speed: f64::INFINITY,
        lost_max_angular_speed: f64::INFINITY,
        ..SlamConfig::default()
    };
    let (worst_unbounded, _) = worst_error(unbounded);
    assert!(
        worst_unbounded > 0.2,
        "the scenario should diverge without the bound: worst error {worst_unbounded} m"
    );
    let (worst, status) = worst_error(SlamConfig::default());
    assert!(
        status.contains(&FrameStatus::Lost),
        "no frame declared lost: {status:?}"
    );
    assert!(
        worst < 0.05,
        "a frame kept a pose {worst} m off: {status:?}"
    );
}

/// A consumer that never reads neither blocks nor slows the run: with tiny bounds the queue
/// drops label images and then whole events, and counts them.
#[test]
fn events_never_block_a_run_whose_consumer_does_not_read() {
    let cam = camera(192);
    let scene = Scene::preset("office", 3).unwrap();
    let mut seq = sequence(scene, TrajectoryKind::Handheld, 60, 3, cam);
    let mut slam = Slam::new(
        SlamConfig::default(),
        cam,
        &ComputeBackend::Cpu,
        Vocabulary::embedded_default().unwrap(),
        None,
    )
    .unwrap();
    let events = slam.events_with(EventOptions {
        capacity: 1,
        images: 0,
    });
    for i in 0..seq.len() {
        let f = seq.render_frame(i).unwrap();
        slam.process(&f.frame.to_rgbd_frame(f.timestamp)).unwrap();
    }
    let r = slam.finish().unwrap();
    assert!(r.keyframes().len() >= 2);
    let dropped = events.dropped();
    assert!(dropped.events > 0, "{dropped:?}");
    assert_eq!(dropped.images as usize, r.keyframes().len(), "{dropped:?}");
    // The one event left, then the end of the stream.
    assert!(events.try_recv().is_ok());
    assert!(matches!(
        events.try_recv(),
        Err(std::sync::mpsc::TryRecvError::Disconnected)
    ));
}

/// `keyframe_colour = false` keeps keyframes grey: the same keyframes at the same poses, no
/// RGB in them, and the account holds 4 bytes per keyframe pixel instead of 7.
#[test]
fn keyframes_without_colour_hold_four_bytes_per_pixel() {
    let cam = camera(160);
    let pixels = 160 * 120;
    let mut seq = sequence(
        Scene::preset("office", 3).unwrap(),
        TrajectoryKind::Handheld,
        40,
        3,
        cam,
    );
    let runs = finish_each(
        &mut seq,
        cam,
        [true, false].map(|keyframe_colour| SlamConfig {
            keyframe_colour,
            ..SlamConfig::default()
        }),
    );
    let (on, off) = (&runs[0], &runs[1]);
    let n = on.keyframes().len();
    assert!(
        n >= 2 && off.keyframes().len() == n,
        "{n} / {}",
        off.keyframes().len()
    );
    for (a, b) in on.keyframes().iter().zip(off.keyframes()) {
        assert_eq!(
            a.world_from_keyframe.translation,
            b.world_from_keyframe.translation
        );
        assert!(a.colour.is_some() && b.colour.is_none());
    }
    for (run, bytes) in [(on, 7), (off, 4)] {
        let held = run.memory.now.keyframes;
        let images = bytes * pixels * n;
        assert!(
            held >= images && held < images + 64 * 1024,
            "{held} keyframe bytes for {n} keyframes, {bytes} bytes per pixel"
        );
    }
}

/// The thesis' schedule (one buffered frame fused with each incoming frame, the rest when the
/// keyframe ends) takes the same frames into each keyframe as fusing them all at its start:
/// same keyframes, and the keyframes' fusion weights (one per consistent fusion) add up to
/// the same within the order's effect on the consistency test. A frame left unfused would
/// remove its whole weight.
#[test]
fn buffered_frames_fused_one_per_frame_reach_the_same_keyframes() {
    let cam = camera(160);
    let mut seq = sequence(
        Scene::preset("office", 3).unwrap(),
        TrajectoryKind::Handheld,
        60,
        5,
        cam,
    );
    let runs = finish_each(
        &mut seq,
        cam,
        [BufferedFusion::AtStart, BufferedFusion::OnePerFrame].map(|buffered_fusion| SlamConfig {
            buffered_fusion,
            ..SlamConfig::default()
        }),
    );
    let weights = |r: &SlamResult| -> Vec<u64> {
        r.keyframes()
            .iter()
            .map(|k| k.weight.iter().map(|&w| u64::from(w)).sum())
            .collect()
    };
    let (at_start, per_frame) = (weights(&runs[0]), weights(&runs[1]));
    let n = at_start.len();
    assert!(
        n >= 3 && per_frame.len() == n,
        "{n} / {} keyframes",
        per_frame.len()
    );
    // Weight beyond each keyframe's own frame (one per pixel with depth).
    let own = |r: &SlamResult| -> Vec<u64> {
        r.keyframes()
            .iter()
            .map(|k| k.weight.iter().filter(|&&w| w > 0).count() as u64)
            .collect()
    };
    let fused = |w: &[u64], o: &[u64]| -> u64 { w.iter().zip(o).map(|(a, b)| a - b).sum() };
    let (a, b) = (
        fused(&at_start, &own(&runs[0])),
        fused(&per_frame, &own(&runs[1])),
    );
    assert!(a > 0, "no fused weight");
    let ratio = b as f64 / a as f64;
    assert!(
        (ratio - 1.0).abs() < 0.03,
        "fused weight one per frame {b} against {a} at the keyframe start"
    );
}
