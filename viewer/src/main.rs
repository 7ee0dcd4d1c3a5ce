//! `rgbid-viewer`: the native viewer of rgbid.
//!
//! ```text
//! rgbid-viewer SEQ                      # TUM RGB-D folder: run SLAM live
//! rgbid-viewer --synth office:loop      # generated sequence
//! rgbid-viewer --output slam-out        # a finished `rgbid slam` output folder
//! rgbid-viewer --map office.map         # a saved map
//! rgbid-viewer --live openni2 --record rec   # live camera (feature `openni2`), recorded
//! rgbid-viewer --live replay:SEQ@30      # a folder played at camera rate
//! rgbid-viewer --bench-points 1000000 --headless   # offscreen 3D frame time, no window
//! ```

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{bail, Context, Result};
use clap::Parser;
use egui_wgpu::wgpu;
use rgbid::gpu::BackendChoice;
use rgbid::live::LiveSpec;
use rgbid_viewer::output::{load_map, load_output};
use rgbid_viewer::scene3d::{self, OrbitCamera, SceneRenderer};
use rgbid_viewer::source::{SourceSpec, SynthOptions};
use rgbid_viewer::state::ViewerState;
use rgbid_viewer::worker::RunConfig;
use rgbid_viewer::ViewerApp;

#[derive(Parser)]
#[command(
    version,
    about = "Native viewer of rgbid: live SLAM, image panels, 3D view, plots"
)]
struct Args {
    /// TUM RGB-D folder (or an `rgbid slam` output folder, detected by its trajectory.txt).
    sequence: Option<PathBuf>,
    #[command(flatten)]
    source: SynthOptions,
    /// Camera preset or calibration file for a TUM folder or live input (default: the
    /// folder's own camera; for OpenNI2 the `default` preset, 525 px at 640 x 480).
    #[arg(long)]
    camera: Option<String>,
    /// Only the first N frames of a TUM folder.
    #[arg(long)]
    max_frames: Option<usize>,
    /// Show a finished `rgbid slam` output folder.
    #[arg(long)]
    output: Option<PathBuf>,
    /// Show a saved map.
    #[arg(long)]
    map: Option<PathBuf>,
    /// Live input instead of a folder: `openni2` (the first OpenNI2 device; needs the
    /// viewer built with `--features openni2`), `openni2:URI` (a device URI or an .oni file)
    /// or `replay:FOLDER[@FPS]` (a dataset folder played at FPS frames per second of wall
    /// time, default 30, as a simulated camera). Frames that arrive while SLAM is busy or
    /// paused are dropped and counted in the status line.
    #[arg(long, value_name = "SPEC", conflicts_with_all = ["output", "map", "sequence"])]
    live: Option<String>,
    /// With --live: record every frame the camera delivers (also the dropped ones) as a TUM
    /// RGB-D folder (depth 5000 per metre) here.
    #[arg(long, value_name = "DIR", requires = "live")]
    record: Option<PathBuf>,
    /// At the end of a run, build a TSDF mesh of the keyframes with this voxel size (metres,
    /// > 0; as `rgbid slam --mesh --voxel`) and draw it. Default: no mesh.
    #[arg(long, value_name = "METRES", value_parser = positive_metres)]
    mesh_voxel: Option<f64>,
    /// Compute backend of the SLAM run.
    #[arg(long, value_enum, default_value_t = BackendChoice::Auto)]
    backend: BackendChoice,
    /// Start paused (use Step / Play).
    #[arg(long)]
    paused: bool,
    /// Add this many synthetic points to the 3D view (frame-time checks).
    #[arg(long)]
    bench_points: Option<usize>,
    /// With --bench-points: render the 3D view offscreen this many times and print frame times,
    /// without opening a window.
    #[arg(long)]
    headless: bool,
    /// Frames of the headless benchmark.
    #[arg(long, default_value_t = 200)]
    bench_frames: usize,
    /// Point budget of the headless benchmark (points drawn per frame; default all).
    #[arg(long)]
    bench_budget: Option<u32>,
}

/// A length in metres that must be positive and finite.
fn positive_metres(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if v.is_finite() && v > 0.0 => Ok(v),
        _ => Err(format!("`{s}` is not a positive length in metres")),
    }
}

fn main() -> Result<()> {
    env_logger::Builder::from_env(env_logger::Env::default().default_filter_or("warn")).init();
    let a = Args::parse();
    if a.headless {
        return bench_headless(
            a.bench_points.unwrap_or(1_000_000),
            a.bench_frames,
            a.bench_budget.unwrap_or(u32::MAX),
        );
    }
    let mut state = ViewerState::default();
    let mut run = None;
    if let Some(dir) = &a.output {
        state = ViewerState::from_output(load_output(dir)?);
    } else if let Some(map) = &a.map {
        state = ViewerState::from_run(load_map(map, rgbid::slam::ModelParams::default().voxel)?);
    } else if let Some(live) = &a.live {
        let spec: LiveSpec = live.parse()?;
        run = Some(RunConfig::live(spec, a.camera.clone(), a.record.clone()));
    } else if let Some(spec) = a.source.spec(0, None)? {
        run = Some(RunConfig::new(spec));
    } else if let Some(seq) = &a.sequence {
        if rgbid::io::run_folder::RunFolder::is_run_folder(seq) {
            state = ViewerState::from_output(load_output(seq)?);
        } else {
            run = Some(RunConfig::new(SourceSpec::Tum {
                dir: seq.clone(),
                format: None,
                camera: a.camera.clone(),
                max_frames: a.max_frames,
            }));
        }
    }
    if let Some(r) = &mut run {
        r.backend = a.backend;
        r.autoplay = !a.paused;
        r.mesh_voxel = a.mesh_voxel;
    }
    let bench_points = a.bench_points;
    let options = eframe::NativeOptions {
        viewport: egui::ViewportBuilder::default()
            .with_inner_size([1400.0, 900.0])
            .with_title("rgbid-viewer"),
        renderer: eframe::Renderer::Wgpu,
        ..Default::default()
    };
    eframe::run_native(
        "rgbid-viewer",
        options,
        Box::new(move |cc| {
            let mut app = ViewerApp::new(state, run);
            app.frame_bench = rgbid_viewer::app::FrameBench::from_env();
            if let Some(rs) = &cc.wgpu_render_state {
                scene3d::install(rs, 1);
                app.has_3d = true;
                // Software adapters (lavapipe): keep the view fluid (see the constant).
                if rs.adapter.get_info().device_type == wgpu::DeviceType::Cpu {
                    app.point_budget = Some(scene3d::SOFTWARE_POINT_BUDGET);
                }
            }
            if let Some(n) = bench_points {
                app.state.add_bench_points(n);
            }
            Ok(Box::new(app))
        }),
    )
    .map_err(|e| anyhow::anyhow!("the window could not be opened: {e}"))
}

/// Renders `points` synthetic points into a 1280x720 offscreen target `frames` times (camera
/// orbiting) and prints upload and per-frame times.
fn bench_headless(points: usize, frames: usize, budget: u32) -> Result<()> {
    let instance = wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle());
    let adapter = pollster::block_on(instance.request_adapter(&wgpu::RequestAdapterOptions {
        power_preference: wgpu::PowerPreference::HighPerformance,
        ..Default::default()
    }))
    .context("no wgpu adapter (install a Vulkan driver or Mesa lavapipe)")?;
    let info = adapter.get_info();
    let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
        label: Some("rgbid-viewer bench"),
        required_limits: adapter.limits(),
        ..Default::default()
    }))
    .context("creating the device")?;
    let mut state = ViewerState::default();
    state.add_bench_points(points);
    let mut r = SceneRenderer::new(&device, wgpu::TextureFormat::Rgba8Unorm, 1, None);
    let size = [1280u32, 720];
    let t = Instant::now();
    r.upload(&device, &state.geometry);
    r.set_point_budget(budget);
    let mut cam = OrbitCamera::default();
    if let Some(b) = state.geometry.bounds() {
        cam.frame_bounds(b);
    }
    let render_once = |r: &mut SceneRenderer, cam: &OrbitCamera| -> Result<()> {
        let mut enc = device.create_command_encoder(&Default::default());
        r.render(
            &device,
            &queue,
            &mut enc,
            cam.clip_from_world(16.0 / 9.0),
            size,
            [0.0; 3],
        );
        queue.submit([enc.finish()]);
        device
            .poll(wgpu::PollType::wait_indefinitely())
            .context("waiting for the GPU")?;
        Ok(())
    };
    render_once(&mut r, &cam)?;
    let first_ms = t.elapsed().as_secs_f64() * 1e3;
    if r.counts().0 as usize != points {
        bail!("uploaded {} points, expected {points}", r.counts().0);
    }
    let mut times = Vec::with_capacity(frames);
    for _ in 0..frames {
        cam.orbit(3.0, 0.0);
        let t = Instant::now();
        render_once(&mut r, &cam)?;
        times.push(t.elapsed().as_secs_f64() * 1e3);
    }
    times.sort_by(f64::total_cmp);
    let mean = times.iter().sum::<f64>() / times.len().max(1) as f64;
    let pct = |q: f64| {
        times
            .get(((times.len() as f64 - 1.0) * q) as usize)
            .copied()
            .unwrap_or(0.0)
    };
    println!(
        "adapter: {} ({:?}, {:?})",
        info.name, info.device_type, info.backend
    );
    println!(
        "{points} points (budget {}), {}x{} offscreen: upload + first frame {first_ms:.1} ms; {} frames: mean {mean:.2} ms, median {:.2} ms, p95 {:.2} ms ({:.0} fps)",
        if budget == u32::MAX { "all".to_string() } else { budget.to_string() },
        size[0],
        size[1],
        times.len(),
        pct(0.5),
        pct(0.95),
        1e3 / pct(0.5).max(1e-9)
    );
    Ok(())
}
