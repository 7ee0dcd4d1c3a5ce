//! Headless tests of the viewer: the SLAM worker on a generated sequence, and snapshots of the
//! main panels rendered offscreen with wgpu (egui_kittest), compared against the PNGs in
//! `tests/snapshots/` with a tolerance. `UPDATE_SNAPSHOTS=1` rewrites the references.
//!
//! The tests that render need a GPU adapter: they are named `gpu_*` and ignored by default,
//! and CI runs them on lavapipe with `RGBID_REQUIRE_GPU=1` (see `rgbid::gpu::test_gpu`).

use std::path::PathBuf;
use std::time::{Duration, Instant};

use egui_kittest::{Harness, SnapshotOptions, SnapshotResults};
use rgbid::gpu::BackendChoice;
use rgbid_viewer::scene3d;
use rgbid_viewer::source::SourceSpec;
use rgbid_viewer::state::ViewerState;
use rgbid_viewer::worker::{Command, RunConfig, Update, Worker};
use rgbid_viewer::ViewerApp;

const FRAMES: usize = 30;

fn small_run(autoplay: bool) -> RunConfig {
    let mut cfg = RunConfig::new(SourceSpec::Synth {
        spec: "office:loop".into(),
        frames: FRAMES,
        width: 160,
        seed: 1,
        // A 20 s lap: the 30 frames walk its first second.
        session: 0,
        lap_seconds: Some(20.0),
    });
    cfg.backend = BackendChoice::Cpu;
    cfg.autoplay = autoplay;
    cfg
}

/// Runs the small generated sequence to the end and returns the state it produced.
fn finished_state() -> ViewerState {
    let mut app = ViewerApp::new(ViewerState::default(), Some(small_run(true)));
    app.speed = 0.0;
    app.send_speed();
    app.wait_until_finished();
    assert!(app.state.error.is_none(), "{:?}", app.state.error);
    app.state
}

#[test]
fn worker_streams_frames_keyframes_and_finishes_accurately() {
    let state = finished_state();
    let start = state.start.as_ref().expect("Started message");
    assert_eq!(start.frames, FRAMES);
    assert!(start.backend.starts_with("cpu"), "{}", start.backend);
    assert_eq!(state.frames_processed, FRAMES);
    assert_eq!(state.stages.len(), FRAMES);
    assert!(!state.live_keyframes.is_empty());
    let first_points = state.live_keyframes[0].1.len();
    // 160x120 with step 2: 4800 pixels, nearly all with depth in the office scene.
    assert!(first_points > 3000, "{first_points} live points");
    assert!(
        state.panels.superjuts.is_some(),
        "superjut image of the keyframe"
    );
    assert!(state.panels.neg_entropy.is_some());
    let kp = &state.panels.keypoints;
    assert!(kp.len() > 50, "{} keypoints", kp.len());
    assert!(kp
        .iter()
        .all(|k| k.x >= 0.0 && k.x < 160.0 && k.y >= 0.0 && k.y < 120.0));
    // Residuals of the last frame against its reference at the pose found: most reference
    // pixels warp into the frame, and on a static scene most keep a high IRLS weight.
    let res = state.panels.residuals.as_ref().expect("residual images");
    assert!(
        res.photometric_coverage() > 0.5,
        "{}",
        res.photometric_coverage()
    );
    assert!(
        res.mean_photometric_weight() > 0.6,
        "{}",
        res.mean_photometric_weight()
    );
    assert!(
        res.mean_geometric_weight() > 0.6,
        "{}",
        res.mean_geometric_weight()
    );
    assert!(
        state
            .stages
            .iter()
            .filter(|r| r.sigma_photo.is_some_and(|s| s > 0.0 && s.is_finite()))
            .count()
            >= FRAMES - 1
    );
    let run = state.finished.as_ref().expect("finished");
    assert_eq!(run.trajectory.len(), FRAMES);
    assert!(!run.model.is_empty());
    assert!(!run.keyframes.is_empty());
    // Ground truth exists for generated sequences; one second of odometry drifts little.
    let worst = state
        .position_error
        .iter()
        .map(|e| e[1])
        .fold(0.0, f64::max);
    assert_eq!(state.position_error.len(), FRAMES);
    assert!(worst < 0.05, "position error up to {worst} m");
}

#[test]
fn step_processes_exactly_one_frame_while_paused() {
    let w = Worker::spawn(small_run(false)).expect("spawn");
    let next = |timeout: Duration| w.updates.recv_timeout(timeout).ok();
    match next(Duration::from_secs(60)) {
        Some(Update::Started(_)) => {}
        other => panic!("expected Started, got {other:?}"),
    }
    // Paused: nothing comes.
    assert!(next(Duration::from_millis(400)).is_none());
    w.send(Command::Step);
    match next(Duration::from_secs(30)) {
        Some(Update::Frame(f)) => assert_eq!(f.index, 0),
        other => panic!("expected frame 0, got {other:?}"),
    }
    // The first frame starts a keyframe; after that, nothing more until the next command.
    let mut more = Vec::new();
    while let Some(u) = next(Duration::from_millis(400)) {
        more.push(u);
    }
    assert!(
        more.iter().all(|u| matches!(u, Update::Keyframe(_))),
        "only the keyframe of frame 0 may follow: {more:?}"
    );
    w.send(Command::Step);
    match next(Duration::from_secs(30)) {
        Some(Update::Frame(f)) => assert_eq!(f.index, 1),
        other => panic!("expected frame 1, got {other:?}"),
    }
    w.send(Command::Finish);
    let t = Instant::now();
    loop {
        match next(Duration::from_secs(30)) {
            Some(Update::Finished(r)) => {
                assert_eq!(r.trajectory.len(), 2);
                break;
            }
            Some(_) => {}
            None => panic!("no Finished after {:?}", t.elapsed()),
        }
    }
}

/// A wgpu render state for kittest in the GPU test `test`: `None` after
/// [`rgbid::gpu::test_gpu`]'s skip line when there is no adapter (a failure with
/// `RGBID_REQUIRE_GPU=1`).
fn gpu_render_state(test: &str) -> Option<egui_wgpu::RenderState> {
    rgbid::gpu::test_gpu(test)?;
    let made = std::panic::catch_unwind(|| {
        egui_kittest::wgpu::create_render_state(
            egui_kittest::wgpu::default_wgpu_setup(),
            egui_wgpu::RendererOptions::PREDICTABLE,
        )
    });
    match made {
        Ok(rs) => Some(rs),
        Err(_) => {
            rgbid::gpu::no_test_gpu(test, "egui_kittest could not create a render state");
            None
        }
    }
}

fn snapshot_options() -> SnapshotOptions {
    SnapshotOptions::new()
        .output_path(PathBuf::from(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/tests/snapshots"
        )))
        // Per-pixel colour distance tolerated, and how many pixels may exceed it (0.5 % of a
        // 1200x800 image): rayon's reduction order moves a few points by a pixel.
        .threshold(2.0)
        .max_failed_pixels(4800)
}

fn harness<'a>(
    rs: egui_wgpu::RenderState,
    size: egui::Vec2,
    app: ViewerApp,
    ui: impl FnMut(&mut egui::Ui, &mut ViewerApp) + 'a,
) -> Harness<'a, ViewerApp> {
    scene3d::install(&rs, 1);
    Harness::builder()
        .with_size(size)
        .with_pixels_per_point(1.0)
        .with_accessibility_check(false)
        .renderer(egui_kittest::wgpu::WgpuTestRenderer::from_render_state(rs))
        .build_ui_state(ui, app)
}

/// The state of the small run with the stage times replaced by a fixed pattern (times are
/// measurements and differ on every run; the snapshot checks drawing, not speed).
fn deterministic_state() -> ViewerState {
    let mut s = finished_state();
    for r in &mut s.stages {
        let i = r.index as f64;
        r.pyramid_ms = 0.5 + 0.1 * (i * 0.7).sin();
        r.scale_ms = 0.3;
        r.reduce_ms = 2.0 + 0.5 * (i * 0.3).cos();
        r.solve_ms = 0.1;
        r.covisibility_ms = 0.4;
        r.fusion_ms = 1.0 + 0.2 * (i * 0.5).sin();
        r.frontend_ms = r.pyramid_ms + r.scale_ms + r.reduce_ms + r.solve_ms + r.covisibility_ms;
    }
    s
}

fn background_fraction(img: &image::RgbaImage, bg: [u8; 3]) -> f64 {
    let n = img.pixels().filter(|p| p.0[..3] == bg).count();
    n as f64 / (img.width() * img.height()) as f64
}

#[test]
#[ignore = "needs a GPU adapter"]
fn gpu_panel_snapshots() {
    let Some(rs) = gpu_render_state("gpu_panel_snapshots") else {
        return;
    };
    let base = deterministic_state();
    let state = base.clone();
    let run = state.finished.clone().expect("finished");
    let mut app = ViewerApp::new(state, None);
    app.has_3d = true;
    app.show_timing = false;
    let mut h = harness(rs, egui::Vec2::new(1200.0, 800.0), app, |ui, app| {
        app.show(ui)
    });
    h.run_steps(3);
    let opts = snapshot_options();
    let mut results = SnapshotResults::new();
    h.snapshot_options("viewer_full", &opts);
    results.extend_harness(&mut h);

    // The 3D view alone: the model must be drawn (not just the background).
    let state = ViewerState::from_run(run.clone());
    let mut app = ViewerApp::new(state, None);
    app.has_3d = true;
    let rs = gpu_render_state("3d").expect("adapter seen above");
    let mut h3 = harness(rs, egui::Vec2::new(640.0, 480.0), app, |ui, app| {
        egui::CentralPanel::default().show(ui, |ui| app.scene_ui(ui));
    });
    h3.run_steps(3);
    let img = h3.render().expect("render");
    // Offscreen background (0.07, 0.07, 0.09) -> (18, 18, 23) in 8 bits.
    let bg = background_fraction(&img, [18, 18, 23]);
    assert!(
        bg > 0.2 && bg < 0.98,
        "background covers {bg} of the 3D view"
    );
    h3.snapshot_options("scene3d", &opts);
    results.extend_harness(&mut h3);

    // Image panels and plots alone.
    let rs = gpu_render_state("images").expect("adapter seen above");
    let mut hi = harness(
        rs,
        egui::Vec2::new(360.0, 1000.0),
        ViewerApp::new(base.clone(), None),
        |ui, app| {
            egui::CentralPanel::default().show(ui, |ui| app.images_ui(ui));
        },
    );
    hi.run_steps(2);
    hi.snapshot_options("images", &opts);
    results.extend_harness(&mut hi);
    let rs = gpu_render_state("plots").expect("adapter seen above");
    let mut hp = harness(
        rs,
        egui::Vec2::new(1000.0, 260.0),
        ViewerApp::new(base.clone(), None),
        |ui, app| {
            egui::CentralPanel::default().show(ui, |ui| app.plots_ui(ui));
        },
    );
    hp.run_steps(2);
    hp.snapshot_options("plots", &opts);
    results.extend_harness(&mut hp);
    results.unwrap();
}

/// One 6 s lap of the generated office (180 frames) and its first 2 s again: the revisit
/// closes loops.
fn loop_run() -> RunConfig {
    let mut cfg = RunConfig::new(SourceSpec::Synth {
        spec: "office:loop".into(),
        frames: 240,
        width: 160,
        seed: 1,
        session: 0,
        lap_seconds: Some(6.0),
    });
    cfg.backend = BackendChoice::Cpu;
    cfg
}

/// The viewer state after SLAM on [`loop_run`].
fn closed_loop_state() -> ViewerState {
    let mut app = ViewerApp::new(ViewerState::default(), Some(loop_run()));
    app.speed = 0.0;
    app.send_speed();
    app.wait_until_finished();
    assert!(app.state.error.is_none(), "{:?}", app.state.error);
    app.state.clone()
}

/// The loop panels after SLAM on [`loop_run`]: the latest accepted loop's inlier matches lie
/// on ORB keypoints of the two keyframe images (as the back-end extracts them), the drawn
/// lines join exactly those points, and the two keyframes see the same place (ground truth).
#[test]
fn loop_panels_show_the_inlier_matches_of_a_closed_loop() {
    let state = closed_loop_state();
    let l = state
        .panels
        .loop_accepted
        .as_ref()
        .expect("an accepted loop on the revisit");
    assert!(!l.relocalisation && l.accepted && l.reason.is_empty());
    assert!(l.query > l.candidate, "{} -> {}", l.query, l.candidate);
    assert!(l.inliers >= 10, "{} inliers", l.inliers);
    assert_eq!(l.matches.len(), l.inliers);
    let (q, c) = (
        l.query_image.as_ref().expect("query keyframe image"),
        l.candidate_image
            .as_ref()
            .expect("candidate keyframe image"),
    );
    assert_eq!(
        (q.width(), q.height(), c.width(), c.height()),
        (160, 120, 160, 120)
    );
    // Every match end is an ORB keypoint of its keyframe image.
    let orb = rgbid::slam::SlamConfig::default().detector.orb;
    let keypoints = |img: &rgbid::image::ImageF32| -> Vec<[f32; 2]> {
        rgbid::place::extract_orb(img, None, &orb)
            .expect("orb")
            .keypoints
            .iter()
            .map(|k| [k.uv.x as f32, k.uv.y as f32])
            .collect()
    };
    let (kq, kc) = (keypoints(q), keypoints(c));
    for (a, b) in &l.matches {
        assert!(kq.contains(a), "query match {a:?} is not a keypoint");
        assert!(kc.contains(b), "candidate match {b:?} is not a keypoint");
    }
    // The drawn lines join those points (candidate image below the query's).
    let dy = (q.height() + rgbid_viewer::images::LOOP_GAP) as f32;
    let segments = rgbid_viewer::images::loop_match_segments(&l.matches, q.height());
    for ((a, b), (s, e)) in l.matches.iter().zip(&segments) {
        assert_eq!((a, [b[0], b[1] + dy]), (s, *e));
    }
    // A true revisit: the keyframes' ground-truth positions are close.
    let run = state.finished.as_ref().expect("finished");
    let gt = state.groundtruth.as_ref().expect("ground truth");
    let gt_at = |kf: usize| {
        let t = run.keyframes[kf].timestamp;
        gt.iter()
            .min_by(|x, y| (x.timestamp - t).abs().total_cmp(&(y.timestamp - t).abs()))
            .expect("gt pose")
            .world_from_camera
            .translation
    };
    let d = (gt_at(l.query) - gt_at(l.candidate)).length();
    assert!(d < 0.5, "loop keyframes {d} m apart");
    eprintln!(
        "loop {} -> {}: {} inliers; rejected: {:?}",
        l.query,
        l.candidate,
        l.inliers,
        state
            .panels
            .loop_rejected
            .as_ref()
            .map(|r| (r.query, r.candidate, r.reason.clone()))
    );
}

/// The loop panels after SLAM on [`loop_run`], compared against `tests/snapshots/loops.png`.
#[test]
#[ignore = "needs a GPU adapter"]
fn gpu_loop_panel_snapshot() {
    let Some(rs) = gpu_render_state("gpu_loop_panel_snapshot") else {
        return;
    };
    let state = closed_loop_state();
    let mut h = harness(
        rs,
        egui::Vec2::new(360.0, 380.0),
        ViewerApp::new(state, None),
        |ui, app| {
            egui::CentralPanel::default().show(ui, |ui| app.loops_ui(ui));
        },
    );
    h.run_steps(2);
    let mut results = SnapshotResults::new();
    h.snapshot_options("loops", &snapshot_options());
    results.extend_harness(&mut h);
    results.unwrap();
}

/// Frame time of the whole UI (egui layout + tessellation + wgpu render + read-back) with a
/// 1M-point cloud in the 3D view. A measurement, not an assertion on speed: run with
/// `cargo test -p rgbid-viewer --test panels -- --ignored --nocapture ui_frame_time`. Manual
/// (`manual_*`): not run by CI.
#[test]
#[ignore = "benchmark: prints figures; needs a GPU adapter"]
fn manual_ui_frame_time_with_a_million_points() {
    let Some(_) = gpu_render_state("manual_ui_frame_time_with_a_million_points") else {
        return;
    };
    for (points, budget) in [(0, None), (1_000_000, None), (1_000_000, Some(250_000u32))] {
        let rs = gpu_render_state("ui_frame_time").expect("adapter seen above");
        let adapter = rs.adapter.get_info().name;
        let mut state = ViewerState::default();
        state.add_bench_points(points);
        let mut app = ViewerApp::new(state, None);
        app.has_3d = true;
        app.point_budget = budget;
        let mut h = harness(rs, egui::Vec2::new(1280.0, 800.0), app, |ui, app| {
            app.camera.orbit(2.0, 0.0);
            app.show(ui);
        });
        h.run_steps(2);
        let _ = h.render();
        let mut times = Vec::new();
        for _ in 0..15 {
            let t = Instant::now();
            h.step();
            let _ = h.render().expect("render");
            times.push(t.elapsed().as_secs_f64() * 1e3);
        }
        times.sort_by(f64::total_cmp);
        println!(
            "UI frame with {points} points, budget {:?}, 1280x800 on {adapter}: median {:.1} ms, min {:.1} ms",
            budget,
            times[times.len() / 2],
            times[0]
        );
    }
}

/// Writes `viewer/screenshot.png` (the README's picture): the full UI after SLAM on one lap
/// of the generated office loop. Run with
/// `cargo test -p rgbid-viewer --test panels -- --ignored readme_screenshot`. Manual
/// (`manual_*`): not run by CI.
#[test]
#[ignore = "writes viewer/screenshot.png; needs a GPU adapter"]
fn manual_readme_screenshot() {
    let Some(rs) = gpu_render_state("manual_readme_screenshot") else {
        return;
    };
    let mut cfg = RunConfig::new(SourceSpec::Synth {
        spec: "office:loop".into(),
        frames: 300,
        width: 320,
        seed: 1,
        session: 0,
        lap_seconds: Some(10.0),
    });
    cfg.backend = BackendChoice::Cpu;
    let mut app = ViewerApp::new(ViewerState::default(), Some(cfg));
    app.speed = 0.0;
    app.send_speed();
    app.wait_until_finished();
    assert!(app.state.error.is_none(), "{:?}", app.state.error);
    app.has_3d = true;
    app.show_timing = false;
    let mut h = harness(rs, egui::Vec2::new(1400.0, 900.0), app, |ui, app| {
        app.show(ui)
    });
    h.run_steps(3);
    let img = h.render().expect("render");
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/screenshot.png");
    img.save(path).expect("save");
    println!("wrote {path}");
}

#[test]
fn exports_reopen_as_an_output_folder() {
    let state = finished_state();
    let run = state.finished.clone().expect("finished");
    let dir = std::env::temp_dir().join(format!("rgbid-viewer-out-{}", std::process::id()));
    let mut app = ViewerApp::new(state, None);
    app.export_dir = dir.clone();
    let traj = app.export_trajectory().expect("trajectory");
    let ply = app.export_ply().expect("ply");
    assert_eq!(traj, dir.join("trajectory.txt"));
    assert_eq!(ply, dir.join("model.ply"));
    rgbid::io::trajectory::write_tum(&dir.join("keyframes.txt"), &run.keyframes).expect("kf");
    let gt = app.state.groundtruth.clone().expect("ground truth");
    rgbid::io::trajectory::write_tum(&dir.join("groundtruth.txt"), &gt).expect("gt");

    let mut reopened = ViewerApp::new(ViewerState::default(), None);
    reopened.open(&dir).expect("open output folder");
    let r = reopened.state.finished.as_ref().expect("shown as finished");
    assert_eq!(r.trajectory.len(), run.trajectory.len());
    assert_eq!(r.keyframes.len(), run.keyframes.len());
    assert_eq!(r.model.len(), run.model.len());
    for (a, b) in r.model.iter().zip(&run.model) {
        assert!((a.0 - b.0).length() < 1e-5 && a.1 == b.1);
    }
    // Ground truth is matched again and the trajectory error is as small as live.
    assert_eq!(reopened.state.position_error.len(), run.trajectory.len());
    assert!(reopened.state.position_error.iter().all(|e| e[1] < 0.05));
    assert_eq!(reopened.state.point_count(), run.model.len());
    // An output folder keeps no loop matches or images: the loop panel says so.
    assert!(reopened.state.panels.loop_accepted.is_none());
    let note = reopened.state.panels.loop_note.as_deref().unwrap_or("");
    assert!(note.contains("no inlier matches"), "{note}");
    // Not a folder of rgbid: a clear error, no panic.
    assert!(reopened.open(&dir.join("missing")).is_err());
    std::fs::remove_dir_all(&dir).ok();
}

#[test]
fn saved_map_opens_with_its_keyframes_and_model() {
    use rgbid::slam::{Slam, SlamConfig};
    let backend = rgbid::gpu::ComputeBackend::Cpu;
    let spec = match small_run(true).source {
        s @ SourceSpec::Synth { .. } => s,
        other => panic!("{other:?}"),
    };
    let mut source = rgbid_viewer::source::FrameSource::open(&spec, &backend).expect("source");
    let mut slam = Slam::new(
        SlamConfig::default(),
        source.camera(),
        &backend,
        rgbid::place::Vocabulary::embedded_default().expect("vocabulary"),
        None,
    )
    .expect("slam");
    for i in 0..source.len() {
        slam.process(&source.load(i).expect("frame"))
            .expect("process");
    }
    let result = slam.finish().expect("finish");
    let path = std::env::temp_dir().join(format!("rgbid-viewer-{}.map", std::process::id()));
    result.map.save(&path).expect("save map");
    let mut app = ViewerApp::new(ViewerState::default(), None);
    app.open(&path).expect("open map");
    let run = app.state.finished.as_ref().expect("map shown");
    assert_eq!(run.keyframes.len(), result.keyframes().len());
    assert!(run.model.len() > 1000, "{} model points", run.model.len());
    assert_eq!(app.state.point_count(), run.model.len());
    // A file that is not a map: an error, not a panic.
    std::fs::write(&path, b"not a map").expect("write");
    assert!(app.open(&path).is_err());
    std::fs::remove_file(&path).ok();
}

#[test]
#[ignore = "needs a GPU adapter"]
fn gpu_dragging_orbits_and_scrolling_zooms_the_3d_view() {
    let Some(rs) = gpu_render_state("gpu_dragging_orbits_and_scrolling_zooms_the_3d_view") else {
        return;
    };
    let mut state = ViewerState::default();
    state.add_bench_points(10_000);
    let mut app = ViewerApp::new(state, None);
    app.has_3d = true;
    let mut h = harness(rs, egui::Vec2::new(640.0, 480.0), app, |ui, app| {
        egui::CentralPanel::default().show(ui, |ui| app.scene_ui(ui));
    });
    h.run_steps(2);
    let before = h.state().camera;
    let at = egui::pos2(320.0, 260.0);
    let button = |pos, pressed| egui::Event::PointerButton {
        pos,
        button: egui::PointerButton::Primary,
        pressed,
        modifiers: Default::default(),
    };
    h.event(egui::Event::PointerMoved(at));
    h.event(button(at, true));
    h.step();
    for k in 1..=6 {
        h.event(egui::Event::PointerMoved(
            at + egui::vec2(10.0 * k as f32, 0.0),
        ));
        h.step();
    }
    h.event(button(at + egui::vec2(60.0, 0.0), false));
    h.step();
    let orbited = h.state().camera;
    assert!(
        (orbited.yaw - before.yaw).abs() > 0.2,
        "{before:?} -> {orbited:?}"
    );
    assert_eq!(orbited.distance, before.distance);
    h.event(egui::Event::MouseWheel {
        unit: egui::MouseWheelUnit::Point,
        delta: egui::vec2(0.0, 200.0),
        phase: egui::TouchPhase::Move,
        source: egui::MouseWheelSource::Unknown,
        modifiers: Default::default(),
    });
    h.run_steps(20);
    let zoomed = h.state().camera;
    assert!(
        zoomed.distance < 0.9 * orbited.distance,
        "{orbited:?} -> {zoomed:?}"
    );
}
