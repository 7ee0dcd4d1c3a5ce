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
use rgbid_viewer::worker::{Command, RunConfig, RunSource, Update, Worker};
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
    assert_eq!(start.frames, Some(FRAMES));
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
        RunSource::Sequence(s @ SourceSpec::Synth { .. }) => s,
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

/// The small run's points carry the generated images' colour; the intensity toggle makes
/// them grey (their luma), and back.
#[test]
fn points_are_coloured_and_the_toggle_makes_them_grey() {
    use rgbid_viewer::state::{intensity_of, PointColours};
    let mut state = finished_state();
    assert!(state.live_coloured, "the generated frames have colour");
    // The geometry of the finished run (the UI rebuilds it when it draws).
    state.rebuild_geometry();
    let run = state.finished.as_ref().expect("finished");
    assert!(run.coloured);
    assert!(rgbid_viewer::output::is_coloured(&run.model));
    let model = run.model.clone();
    assert!(state.has_colour());
    assert_eq!(state.point_colours(), PointColours::Colour);
    let coloured = |g: &rgbid_viewer::scene3d::Geometry| {
        g.points
            .iter()
            .filter(|v| v.colour[0] != v.colour[1] || v.colour[1] != v.colour[2])
            .count()
    };
    // Most points of the office have some hue (walls, floor and furniture are coloured).
    let n = state.geometry.points.len();
    assert_eq!(n, model.len());
    assert!(
        coloured(&state.geometry) > n / 2,
        "{} of {n}",
        coloured(&state.geometry)
    );
    // The drawn colours are the model's colours (in the interleaved order).
    let mut drawn: Vec<[u8; 3]> = state
        .geometry
        .points
        .iter()
        .map(|v| [v.colour[0], v.colour[1], v.colour[2]])
        .collect();
    let mut expected: Vec<[u8; 3]> = model.iter().map(|p| p.1).collect();
    drawn.sort();
    expected.sort();
    assert_eq!(drawn, expected);

    state.set_point_colours(PointColours::Intensity);
    assert!(state.rebuild_geometry());
    assert_eq!(coloured(&state.geometry), 0);
    let mut grey: Vec<u8> = state.geometry.points.iter().map(|v| v.colour[0]).collect();
    let mut expected: Vec<u8> = model.iter().map(|p| intensity_of(p.1)).collect();
    grey.sort();
    expected.sort();
    assert_eq!(grey, expected);
    state.set_point_colours(PointColours::Colour);
    assert!(state.rebuild_geometry());
    assert!(coloured(&state.geometry) > n / 2);
}

/// A grey model (a run without colour images) is shown as having no colour.
#[test]
fn a_grey_run_folder_has_no_colour() {
    let tmp = tempfile_dir("grey");
    let w = rgbid::io::run_folder::RunFolderWriter::create(&tmp).expect("writer");
    let pose = rgbid::trajectory::TimedPose {
        timestamp: 0.0,
        world_from_camera: rgbid::geometry::Se3::default(),
    };
    w.trajectory(&[pose]).expect("trajectory");
    w.model(&[
        (glam::DVec3::new(0.0, 0.0, 1.0), 90),
        (glam::DVec3::ONE, 200),
    ])
    .expect("model");
    w.finish(Default::default()).expect("finish");
    let state = ViewerState::from_output(rgbid_viewer::output::load_output(&tmp).expect("load"));
    assert!(!state.has_colour());
    assert!(state.geometry.mesh.is_none());
    let greys: Vec<[u8; 4]> = state.geometry.points.iter().map(|v| v.colour).collect();
    assert!(greys.contains(&[90, 90, 90, 255]) && greys.contains(&[200, 200, 200, 255]));
    std::fs::remove_dir_all(&tmp).ok();
}

/// A fresh folder under the system's temporary folder (removed first if it exists).
fn tempfile_dir(what: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("rgbid-viewer-{what}-{}", std::process::id()));
    std::fs::remove_dir_all(&dir).ok();
    dir
}

/// Writes a TUM RGB-D folder of `frames` generated 160x120 frames of the office (colour,
/// depth, ground truth).
fn tum_folder(dir: &std::path::Path, frames: usize) {
    use rgbid::synth::tum_export::TumWriter;
    use rgbid::synth::{
        CameraModel, RenderBackend, Scene, Sequence, SequenceConfig, Trajectory, TrajectoryKind,
    };
    use std::sync::Arc;
    let scene = Arc::new(Scene::preset("office", 1).expect("scene"));
    // A 20 s lap: the frames walk its first second, as the small run does.
    let traj = Trajectory::new(TrajectoryKind::Loop, &scene, 20.0, 1).expect("trajectory");
    let camera = rgbid::camera::PinholeCamera::new(131.25, 131.25, 79.5, 59.5, 160, 120);
    let config = SequenceConfig {
        frames,
        seed: 1,
        ..Default::default()
    };
    let camera = CameraModel::Pinhole(camera);
    let seq = Sequence::new(scene, camera, traj, config, &RenderBackend::Cpu).expect("sequence");
    let mut w = TumWriter::create(dir, &camera).expect("writer");
    for f in seq {
        let f = f.expect("frame");
        w.write_frame(f.timestamp, &f.world_from_camera, &f.frame)
            .expect("write");
    }
    w.finish("generated\n", &[]).expect("finish");
}

/// `--live replay:DIR@FPS --record REC` in the viewer: the worker tracks the frames the
/// simulated camera delivers, the status line counts received / dropped / recorded, and the
/// recording holds every frame delivered.
#[test]
fn live_replay_counts_frames_and_records_them() {
    let tmp = tempfile_dir("live");
    let (seq, rec) = (tmp.join("seq"), tmp.join("rec"));
    tum_folder(&seq, 20);
    let spec: rgbid::live::LiveSpec = format!("replay:{}@10", seq.display())
        .parse()
        .expect("spec");
    let mut cfg = RunConfig::live(spec, None, Some(rec.clone()));
    cfg.backend = BackendChoice::Cpu;
    let mut app = ViewerApp::new(ViewerState::default(), Some(cfg));
    app.show_timing = false;
    app.wait_until_finished();
    assert!(app.state.error.is_none(), "{:?}", app.state.error);
    let counts = app.state.live.expect("live counts");
    assert!(counts.finished);
    assert_eq!(counts.received, 20);
    assert_eq!(counts.recorded, Some(20));
    assert_eq!(app.state.frames_processed as u64 + counts.dropped, 20);
    assert!(app.state.frames_processed >= 10, "{counts:?}");
    assert_eq!(app.state.start.as_ref().and_then(|s| s.frames), None);
    assert!(app.state.has_colour());
    let status = app.status_text();
    assert!(
        status.contains(&format!(
            "live: 20 received, {} dropped, 20 recorded",
            counts.dropped
        )),
        "{status}"
    );
    let rgb_list = std::fs::read_to_string(rec.join("rgb.txt")).expect("recorded rgb.txt");
    let lines = rgb_list.lines().filter(|l| !l.starts_with('#')).count();
    assert_eq!(lines, 20, "{rgb_list}");
    std::fs::remove_dir_all(&tmp).ok();
}

/// Without the `openni2` feature, `--live openni2` fails with the library's error naming
/// the feature; a malformed spec is the library's parse error.
#[cfg(not(feature = "openni2"))]
#[test]
fn live_openni2_without_the_feature_names_it() {
    let spec: rgbid::live::LiveSpec = "openni2".parse().expect("spec");
    let mut cfg = RunConfig::live(spec, None, None);
    cfg.backend = BackendChoice::Cpu;
    let mut app = ViewerApp::new(ViewerState::default(), Some(cfg));
    app.wait_until_finished();
    let e = app.state.error.clone().expect("an error");
    assert!(e.contains("--features openni2"), "{e}");
    let e = "replay:"
        .parse::<rgbid::live::LiveSpec>()
        .unwrap_err()
        .to_string();
    assert!(e.contains("replay:FOLDER[@FPS]"), "{e}");
}

/// A run folder as `rgbid slam --out DIR --mesh` writes it (trajectory, keyframes, coloured
/// model, mesh.ply), from SLAM on the sequence of `run` (the small generated run by default).
fn mesh_run_folder(dir: &std::path::Path) {
    mesh_run_folder_of(dir, small_run(true));
}

fn mesh_run_folder_of(dir: &std::path::Path, run: RunConfig) {
    use rgbid::slam::{build_coloured_model, build_mesh, ModelParams, Slam, SlamConfig};
    let backend = rgbid::gpu::ComputeBackend::Cpu;
    let RunSource::Sequence(spec) = run.source else {
        panic!("a sequence");
    };
    let mut source = rgbid_viewer::source::FrameSource::open(&spec, &backend).expect("source");
    let camera = source.camera();
    let mut slam = Slam::new(
        SlamConfig::default(),
        camera,
        &backend,
        rgbid::place::Vocabulary::embedded_default().expect("vocabulary"),
        None,
    )
    .expect("slam");
    for i in 0..source.len() {
        slam.process(&source.load(i).expect("frame"))
            .expect("process");
    }
    let r = slam.finish().expect("finish");
    let w = rgbid::io::run_folder::RunFolderWriter::create(dir).expect("writer");
    w.trajectory(&r.trajectory).expect("trajectory");
    w.keyframes(&r.keyframe_trajectory()).expect("keyframes");
    let params = ModelParams::default();
    w.model_coloured(&build_coloured_model(
        r.keyframes(),
        &r.keyframe_poses,
        &camera,
        &params,
    ))
    .expect("model");
    let tsdf = rgbid::tsdf::TsdfParams {
        voxel_size: 0.02,
        ..Default::default()
    };
    let mesh = build_mesh(
        r.keyframes(),
        &r.keyframe_poses,
        &camera,
        &tsdf,
        params.min_weight,
        &backend,
    )
    .expect("mesh");
    mesh.write_ply(&dir.join(rgbid_viewer::output::MESH_FILE))
        .expect("mesh.ply");
    w.finish(Default::default()).expect("finish");
}

/// A run folder with `mesh.ply`: the viewer reads the mesh with its colours, shows it by
/// default and hands it to the 3D view.
#[test]
fn run_folder_mesh_is_read_and_shown() {
    let dir = tempfile_dir("mesh");
    mesh_run_folder(&dir);
    let folder = rgbid_viewer::output::load_output(&dir).expect("load");
    let mesh = folder.run.mesh.clone().expect("mesh.ply read");
    assert!(
        mesh.triangles.len() > 1000,
        "{} triangles",
        mesh.triangles.len()
    );
    assert!(rgbid_viewer::output::is_coloured(&mesh.vertices));
    let n = mesh.vertices.len() as u32;
    assert!(mesh.triangles.iter().flatten().all(|&i| i < n));
    let app = ViewerApp::new(ViewerState::from_output(folder), None);
    let g = app.state.geometry.mesh.as_ref().expect("mesh geometry");
    assert_eq!(g.triangles.len(), mesh.triangles.len());
    assert_eq!(g.vertices.len(), mesh.vertices.len());
    assert!(app.shows_mesh());
    assert!(app
        .status_text()
        .contains(&format!("mesh {} triangles", mesh.triangles.len())));
    std::fs::remove_dir_all(&dir).ok();
}

/// `--mesh-voxel`: the worker builds the keyframes' mesh at the end of a live run.
#[test]
fn worker_builds_the_mesh_when_asked() {
    let mut cfg = small_run(true);
    cfg.mesh_voxel = Some(0.02);
    let mut app = ViewerApp::new(ViewerState::default(), Some(cfg));
    app.speed = 0.0;
    app.send_speed();
    app.wait_until_finished();
    assert!(app.state.error.is_none(), "{:?}", app.state.error);
    let run = app.state.finished.as_ref().expect("finished");
    let mesh = run.mesh.as_ref().expect("mesh");
    assert!(
        mesh.triangles.len() > 1000,
        "{} triangles",
        mesh.triangles.len()
    );
    app.state.rebuild_geometry();
    assert!(app.shows_mesh());
}

/// The 3D view of a run folder with a mesh: shaded coloured triangles (compared against
/// `tests/snapshots/mesh3d.png`), and the points instead when toggled.
#[test]
#[ignore = "needs a GPU adapter"]
fn gpu_mesh_snapshot() {
    let Some(rs) = gpu_render_state("gpu_mesh_snapshot") else {
        return;
    };
    let dir = tempfile_dir("mesh-gpu");
    mesh_run_folder(&dir);
    let state = ViewerState::from_output(rgbid_viewer::output::load_output(&dir).expect("load"));
    std::fs::remove_dir_all(&dir).ok();
    let mut app = ViewerApp::new(state, None);
    app.has_3d = true;
    let mut h = harness(rs, egui::Vec2::new(640.0, 480.0), app, |ui, app| {
        egui::CentralPanel::default().show(ui, |ui| app.scene_ui(ui));
    });
    h.run_steps(3);
    let mesh_img = h.render().expect("render");
    let bg = background_fraction(&mesh_img, [18, 18, 23]);
    assert!(
        bg > 0.2 && bg < 0.95,
        "background covers {bg} of the 3D view"
    );
    // Shaded and coloured: many distinct colours, some with a hue.
    let mut distinct: Vec<[u8; 3]> = mesh_img
        .pixels()
        .map(|p| [p.0[0], p.0[1], p.0[2]])
        .filter(|c| c[0] != c[1] || c[1] != c[2])
        .collect();
    distinct.sort();
    distinct.dedup();
    assert!(
        distinct.len() > 200,
        "{} distinct coloured pixels",
        distinct.len()
    );
    h.snapshot_options("mesh3d", &snapshot_options());
    // The points instead: a different picture.
    h.state_mut().surface = Some(rgbid_viewer::app::Surface::Points);
    h.run_steps(2);
    let points_img = h.render().expect("render");
    let differ = mesh_img
        .pixels()
        .zip(points_img.pixels())
        .filter(|(a, b)| a != b)
        .count();
    assert!(
        differ > 5000,
        "{differ} pixels differ between mesh and points"
    );
}

/// Writes `docs/viewer_mesh.png`: the whole viewer showing the mesh of a run folder written
/// as `rgbid slam --mesh` writes it. Run with
/// `cargo test -p rgbid-viewer --test panels -- --ignored manual_mesh_screenshot`. Manual
/// (`manual_*`): not run by CI.
#[test]
#[ignore = "writes docs/viewer_mesh.png; needs a GPU adapter"]
fn manual_mesh_screenshot() {
    let Some(rs) = gpu_render_state("manual_mesh_screenshot") else {
        return;
    };
    let dir = tempfile_dir("mesh-doc");
    // One lap of the generated office.
    let mut cfg = RunConfig::new(SourceSpec::Synth {
        spec: "office:loop".into(),
        frames: 150,
        width: 320,
        seed: 1,
        session: 0,
        lap_seconds: Some(5.0),
    });
    cfg.backend = BackendChoice::Cpu;
    mesh_run_folder_of(&dir, cfg);
    let state = ViewerState::from_output(rgbid_viewer::output::load_output(&dir).expect("load"));
    std::fs::remove_dir_all(&dir).ok();
    let mut app = ViewerApp::new(state, None);
    app.has_3d = true;
    app.show_timing = false;
    let mut h = harness(rs, egui::Vec2::new(1000.0, 700.0), app, |ui, app| {
        egui::CentralPanel::default().show(ui, |ui| app.scene_ui(ui));
    });
    h.run_steps(3);
    // Closer than "frame all", which also frames stray far points.
    h.state_mut().camera.zoom(0.6);
    h.run_steps(2);
    let img = h.render().expect("render");
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../docs/viewer_mesh.png");
    img.save(path).expect("save");
    println!("wrote {path}");
}
