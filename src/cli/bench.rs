//! `rgbid bench`: speed benchmarks that print medians per frame and per stage (and, for real
//! sequences, the peers' figures measured in the same run).

use std::time::Instant;

use anyhow::Result;
use rgbid::camera::PinholeCamera;
use rgbid::geometry::Se3;
use rgbid::gpu::{select_backend, BackendChoice, ComputeBackend};
use rgbid::image::test_pattern;
use rgbid::io::CalibFormat;
use std::path::PathBuf;

use anyhow::Context;
use indicatif::{ProgressBar, ProgressStyle};
use rgbid::io::trajectory::write_tum;
use rgbid::io::tum::{OpenOptions, TumSequence};
use rgbid::odometry::{Odometry, OdometryConfig, OdometryError};
use rgbid::trajectory::TimedPose;

use super::options::{ConfigArgs, OdometryOptions};

/// Subcommands of `rgbid bench`.
#[derive(clap::Subcommand)]
pub enum Command {
    /// Odometry kernels on generated frames (no data needed): pyramid, scale estimation,
    /// normal equations, solve per backend and image size, and the CPU undistortion of a
    /// frame (TUM fr1 distortion, as the I/O thread runs it).
    Kernels(Box<KernelBench>),
    /// Odometry speed and accuracy per backend on a TUM sequence, against OpenCV / Open3D run
    /// on the same data by `../shared/eval/peer_odometry.py`.
    Odometry(Box<OdometryBench>),
    /// TSDF integration speed per backend (with the frames' colour, and depth only) and mesh
    /// accuracy on a generated room with exact geometry, against Open3D's VoxelBlockGrid on
    /// the same frames (`scripts/tsdf_open3d.py`).
    Tsdf(Box<super::mesh::TsdfBench>),
    /// SLAM under load on generated frames (CPU backend): memory over a long run (bytes per
    /// keyframe, growth per frame beyond the map) and two sessions on two threads against the
    /// same two run one after the other.
    Load(Box<super::load::LoadBench>),
}

/// Arguments of `rgbid bench kernels`.
#[derive(clap::Args)]
pub struct KernelBench {
    /// Backends to measure, comma-separated: cpu, gpu.
    #[arg(long, default_value = "cpu,gpu")]
    pub backends: String,
    /// Image sizes, comma-separated WxH.
    #[arg(long, default_value = "640x480,320x240")]
    pub sizes: String,
    /// Repetitions (the median is reported), >= 1.
    #[arg(long, value_parser = crate::cli::options::range::at_least_one, default_value_t = 15)]
    pub repeat: usize,
    /// GPU adapter name filter.
    #[arg(long)]
    pub adapter: Option<String>,
    /// Also write the results as JSON (machine, commit, command and every row) to this file.
    #[arg(long, value_name = "FILE")]
    pub json: Option<PathBuf>,
}

/// One row of `rgbid bench kernels`' alignment table.
#[derive(serde::Serialize)]
struct KernelRow {
    backend: String,
    width: u32,
    height: u32,
    /// Median of one alignment: pyramids of both frames + coarse-to-fine Gauss-Newton, ms.
    align_ms: f64,
    /// Median per stage, ms (the pyramid is for both frames).
    pyramid_ms: f64,
    scale_ms: f64,
    reduce_ms: f64,
    solve_ms: f64,
    /// Gauss-Newton iterations over all levels.
    iterations: usize,
}

/// One row of `rgbid bench kernels`' keyframe fusion and ray casting table.
#[derive(serde::Serialize)]
struct FrameKernelRow {
    backend: String,
    width: u32,
    height: u32,
    /// Median ms to fuse one frame into a resident keyframe (upload, kernel, counts read-back).
    fuse_ms: f64,
    /// Median ms to ray-cast one frame of the office scene (kernel and read-back; no sensor
    /// model).
    raycast_ms: f64,
}

/// One row of `rgbid bench kernels`' undistortion table.
#[derive(serde::Serialize)]
struct UndistortRow {
    backend: String,
    width: u32,
    height: u32,
    /// Median ms of one frame: intensity bilinear + inverse depth nearest (GPU: upload and
    /// read-back included).
    undistort_ms: f64,
}

/// Median of a sample (NaN when empty).
pub fn median(v: &mut [f64]) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Runs the subcommand.
pub fn run(c: Command) -> Result<()> {
    match c {
        Command::Kernels(a) => kernels(*a),
        Command::Odometry(a) => odometry(*a),
        Command::Tsdf(a) => super::mesh::bench(*a),
        Command::Load(a) => super::load::run(*a),
    }
}

fn backend_named(name: &str, adapter: Option<&str>) -> Result<Option<ComputeBackend>> {
    Ok(match name {
        "cpu" => Some(ComputeBackend::Cpu),
        "gpu" => match select_backend(BackendChoice::Gpu, adapter) {
            Ok(b) => Some(b),
            Err(e) => {
                println!("backend gpu: unavailable ({e})");
                None
            }
        },
        other => anyhow::bail!("unknown backend '{other}' (cpu or gpu)"),
    })
}

fn kernels(a: KernelBench) -> Result<()> {
    let mut backends = Vec::new();
    for name in a
        .backends
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
    {
        if let Some(b) = backend_named(name, a.adapter.as_deref())? {
            backends.push(b);
        }
    }
    let sizes = a
        .sizes
        .split(',')
        .map(|size| {
            size.split_once('x')
                .and_then(|(w, h)| {
                    Some((w.trim().parse::<u32>().ok()?, h.trim().parse::<u32>().ok()?))
                })
                .ok_or_else(|| anyhow::anyhow!("bad size '{size}' (expected WxH)"))
        })
        .collect::<Result<Vec<_>>>()?;
    let mut rows = Vec::new();
    println!("| backend | size | align ms (median) | pyramid ms | scale ms | reduce ms | solve ms | GN iterations |");
    println!("|---|---|---|---|---|---|---|---|");
    for backend in &backends {
        for &(w, h) in &sizes {
            let f = 525.0 * f64::from(w) / 640.0;
            let cam = PinholeCamera::new(
                f,
                f,
                (f64::from(w) - 1.0) / 2.0,
                (f64::from(h) - 1.0) / 2.0,
                w,
                h,
            );
            let frame_a = test_pattern(w as usize, h as usize, 1);
            let frame_b = test_pattern(w as usize, h as usize, 1);
            let mut odo = Odometry::new(OdometryConfig::default(), cam, backend)?;
            let guess = Se3::exp(&[0.01, 0.0, 0.0, 0.0, 0.005, 0.0]);
            let mut totals = Vec::new();
            let mut stages: [Vec<f64>; 4] = Default::default();
            let mut iterations = 0;
            // One warm-up run (pipeline compilation on first dispatch), then the measured ones.
            odo.align(&frame_a, &frame_b, guess)?;
            for _ in 0..a.repeat.max(1) {
                let t = Instant::now();
                let r = odo.align(&frame_a, &frame_b, guess)?;
                totals.push(t.elapsed().as_secs_f64() * 1e3);
                let s = r.times;
                for (k, v) in [s.pyramid_ms, s.scale_ms, s.reduce_ms, s.solve_ms]
                    .into_iter()
                    .enumerate()
                {
                    stages[k].push(v);
                }
                iterations = r.levels.iter().map(|l| l.iterations).sum();
            }
            let row = KernelRow {
                backend: backend.name(),
                width: w,
                height: h,
                align_ms: median(&mut totals),
                pyramid_ms: median(&mut stages[0]),
                scale_ms: median(&mut stages[1]),
                reduce_ms: median(&mut stages[2]),
                solve_ms: median(&mut stages[3]),
                iterations,
            };
            println!(
                "| {} | {w}x{h} | {:.2} | {:.2} | {:.2} | {:.2} | {:.3} | {iterations} |",
                row.backend,
                row.align_ms,
                row.pyramid_ms,
                row.scale_ms,
                row.reduce_ms,
                row.solve_ms
            );
            rows.push(row);
        }
    }
    println!("(align = pyramids of both frames + coarse-to-fine Gauss-Newton; the pyramid column is for both frames)");
    let frame_rows = fusion_and_raycast(&backends, &sizes, a.repeat)?;
    let undistort = undistortion(&sizes, a.repeat)?;
    if let Some(path) = &a.json {
        let adapters = backends
            .iter()
            .filter_map(|b| match b {
                ComputeBackend::Gpu(ctx) => Some(ctx.adapter_info().name.clone()),
                ComputeBackend::Cpu => None,
            })
            .collect();
        let body = serde_json::json!({
            "repeat": a.repeat.max(1),
            "rows": rows,
            "frame_rows": frame_rows,
            "undistort_rows": undistort,
        });
        super::report::write(path, "kernels", &super::report::meta(adapters), &body)?;
    }
    Ok(())
}

/// Times keyframe fusion (one frame into a resident keyframe) and ray casting (one frame of
/// a generated scene) per backend and size.
fn fusion_and_raycast(
    backends: &[ComputeBackend],
    sizes: &[(u32, u32)],
    repeat: usize,
) -> Result<Vec<FrameKernelRow>> {
    use rgbid::slam::{FusionParams, KeyframeFuser};
    use rgbid::synth::{CameraModel, RenderBackend, Renderer, Scene};
    let scene = std::sync::Arc::new(Scene::preset("office", 1)?);
    let mut rows = Vec::new();
    println!();
    println!("| backend | size | fuse ms (median) | ray cast ms (median) |");
    println!("|---|---|---|---|");
    for backend in backends {
        for &(w, h) in sizes {
            let f = 525.0 * f64::from(w) / 640.0;
            let (cx, cy) = ((f64::from(w) - 1.0) / 2.0, (f64::from(h) - 1.0) / 2.0);
            let cam = PinholeCamera::new(f, f, cx, cy, w, h);
            let keyframe = test_pattern(w as usize, h as usize, 1);
            let frame = test_pattern(w as usize, h as usize, 2);
            let cur_from_kf = Se3::exp(&[0.01, 0.0, 0.0, 0.0, 0.005, 0.0]);
            let mut fuser = KeyframeFuser::new(cam, FusionParams::default(), backend)?;
            fuser.start(keyframe.inverse_depth())?;
            // No odometry here: sigma_W 0 makes the fuser use its fixed tolerance.
            fuser.fuse(frame.inverse_depth(), &cur_from_kf, 0.0)?; // warm-up
            let mut fuse = Vec::new();
            for _ in 0..repeat.max(1) {
                let t = Instant::now();
                fuser.fuse(frame.inverse_depth(), &cur_from_kf, 0.0)?;
                fuse.push(t.elapsed().as_secs_f64() * 1e3);
            }
            let render = match backend {
                ComputeBackend::Cpu => RenderBackend::Cpu,
                ComputeBackend::Gpu(ctx) => RenderBackend::Gpu(ctx.clone()),
            };
            let mut renderer = Renderer::new(scene.clone(), CameraModel::Pinhole(cam), &render)?;
            let centre = scene.free_area().center();
            let world_from_camera = Se3::new(
                glam::DQuat::from_rotation_x(-std::f64::consts::FRAC_PI_2),
                glam::DVec3::new(centre.x, centre.y, 1.5),
            );
            renderer.cast(&world_from_camera)?; // warm-up
            let mut cast = Vec::new();
            for _ in 0..repeat.max(1) {
                let t = Instant::now();
                renderer.cast(&world_from_camera)?;
                cast.push(t.elapsed().as_secs_f64() * 1e3);
            }
            let row = FrameKernelRow {
                backend: backend.name(),
                width: w,
                height: h,
                fuse_ms: median(&mut fuse),
                raycast_ms: median(&mut cast),
            };
            println!(
                "| {} | {w}x{h} | {:.2} | {:.2} |",
                row.backend, row.fuse_ms, row.raycast_ms
            );
            rows.push(row);
        }
    }
    Ok(rows)
}

/// Times the undistortion of one frame (TUM fr1 distortion) per size: the CPU remap on one
/// thread, as the I/O thread runs it beside the tracking.
fn undistortion(sizes: &[(u32, u32)], repeat: usize) -> Result<Vec<UndistortRow>> {
    let mut rows = Vec::new();
    println!();
    println!(
        "| backend | size | undistort ms (median; intensity bilinear + inverse depth nearest) |"
    );
    println!("|---|---|---|");
    {
        for &(w, h) in sizes {
            // The TUM fr1 preset's intrinsics and distortion, scaled to the size.
            let fr1 = rgbid::io::CameraConfig::preset("tum_fr1")
                .ok_or_else(|| anyhow::anyhow!("the tum_fr1 camera preset is missing"))?
                .camera;
            let (sx, sy) = (f64::from(w) / 640.0, f64::from(h) / 480.0);
            let mut cam =
                PinholeCamera::new(fr1.fx * sx, fr1.fy * sy, fr1.cx * sx, fr1.cy * sy, w, h);
            cam.distortion = fr1.distortion;
            let map = rgbid::io::UndistortMap::new(&cam);
            let f = test_pattern(w as usize, h as usize, 1);
            let (raw_i, raw_d) = (&f.intensity().data(), &f.inverse_depth().data());
            let mut times = Vec::new();
            let (mut oi, mut od) = (vec![0.0; raw_i.len()], vec![0.0; raw_d.len()]);
            for _ in 0..repeat.max(1) {
                let t = Instant::now();
                map.remap_bilinear(raw_i, &mut oi);
                map.remap_nearest(raw_d, &mut od);
                times.push(t.elapsed().as_secs_f64() * 1e3);
            }
            let row = UndistortRow {
                backend: "cpu (one thread)".into(),
                width: w,
                height: h,
                undistort_ms: median(&mut times),
            };
            println!("| {} | {w}x{h} | {:.2} |", row.backend, row.undistort_ms);
            rows.push(row);
        }
    }
    Ok(rows)
}

/// Arguments of `rgbid bench odometry`.
#[derive(clap::Args)]
pub struct OdometryBench {
    /// TUM-layout sequence folder (with groundtruth.txt for accuracy figures).
    pub sequence: PathBuf,
    /// Backends to measure, comma-separated: cpu, gpu.
    #[arg(long, default_value = "cpu,gpu")]
    pub backends: String,
    /// Process at most this many frames (>= 1).
    #[arg(long, value_parser = crate::cli::options::range::at_least_one)]
    pub max_frames: Option<usize>,
    /// Peer methods of `../shared/eval/peer_odometry.py` to run in the same benchmark
    /// (comma-separated; empty for none).
    #[arg(long, default_value = "cv_rgbd,o3dt_hybrid")]
    pub peers: String,
    /// The peer script.
    #[arg(long, default_value = "../shared/eval/peer_odometry.py")]
    pub peer_script: PathBuf,
    /// Python interpreter with numpy, scipy, opencv and open3d.
    #[arg(long, default_value = "python3")]
    pub python: String,
    /// Folder for the trajectories written by the benchmark.
    #[arg(long, default_value = "bench-out")]
    pub out: PathBuf,
    /// Camera preset or config file (default: calib.txt beside the sequence).
    #[arg(long)]
    pub camera: Option<String>,
    /// How --camera FILE is read: `auto` (by the file: `calib.txt` is rgbid's `fx fy cx cy
    /// [depth_factor [width height]]`, `.yaml`/`.yml` OpenCV / ORB-SLAM, else `key = value`
    /// lines) or `droid` (DROID-SLAM's calib.txt: one line `fx fy cx cy [k1 k2 p1 p2 [k3]]`,
    /// pixels; the image size is taken from the sequence's first image, the depth factor is
    /// the layout's: TUM and ETH3D 5000 per metre, 7-Scenes and ScanNet 1000, Replica
    /// 6553.5).
    #[arg(long, value_enum, default_value_t = CalibFormat::Auto, requires = "camera")]
    pub calib_format: CalibFormat,
    /// Also write the results as JSON (machine, commit, command and every row) to this file,
    /// e.g. `docs/results/odometry_redkitchen.json` for `scripts/results.py`.
    #[arg(long, value_name = "FILE")]
    pub json: Option<PathBuf>,
    /// Configuration: an `OdometryConfig` file (`rgbid config dump --command odometry`).
    #[command(flatten)]
    pub config: ConfigArgs,
    #[command(flatten)]
    pub odometry: OdometryOptions,
    /// Use the GPU adapter whose name contains this (case-insensitive).
    #[arg(long)]
    pub adapter: Option<String>,
}

/// One row of the result table (and of the `--json` report).
#[derive(Debug, Clone, serde::Serialize)]
struct Row {
    /// `rgbid cpu`, `rgbid gpu`, or the peer script's method name (`cv_rgbd`, ...).
    method: String,
    /// True for rows measured by the peer script.
    peer: bool,
    /// The compute backend in words (rgbid rows).
    backend: Option<String>,
    /// Frames with a pose.
    frames: usize,
    /// Median compute time per frame, ms (decoding excluded).
    ms_median: f64,
    /// 90th percentile of the time per frame, ms.
    ms_p90: f64,
    /// ATE RMSE after rigid alignment, m.
    ate_rmse_m: Option<f64>,
    /// Translational RPE RMSE over 1 s windows, m/s (TUM `evaluate_rpe` semantics).
    rpe_m_per_s: Option<f64>,
    /// Rotational RPE RMSE over 1 s windows, deg/s.
    rpe_deg_per_s: Option<f64>,
    /// Per-stage medians (rgbid rows).
    stages_ms: Option<Stages>,
    /// Median decoding time per frame, ms (not counted in `ms_median`).
    decode_ms_median: Option<f64>,
    /// Resident memory after 10 frames, MiB.
    rss_mib_after_10: Option<f64>,
    /// Resident memory at the end of this row's run, MiB.
    rss_mib_end: Option<f64>,
    /// Peak resident memory of the process so far (it includes the rows run before), MiB.
    peak_rss_mib: Option<f64>,
    /// Speed-up against every peer row of the same run: the peer's median time over this
    /// row's (> 1: this row is faster).
    speedup_vs: std::collections::BTreeMap<String, f64>,
}

/// Median milliseconds per frame of each odometry stage.
#[derive(Debug, Clone, Copy, serde::Serialize)]
struct Stages {
    pyramid: f64,
    scale: f64,
    reduce: f64,
    solve: f64,
    covisibility: f64,
    covariance: f64,
}

/// The `--json` report of `rgbid bench odometry` (besides `meta`).
#[derive(serde::Serialize)]
struct OdometryReport<'a> {
    /// The sequence folder as given.
    sequence: String,
    /// Its folder name.
    sequence_name: String,
    /// Frames in the sequence (after `--max-frames`).
    sequence_frames: usize,
    /// `--camera` as given (None: calib.txt beside the sequence, else the default camera).
    camera: Option<&'a str>,
    /// The odometry configuration every rgbid row used.
    config: &'a OdometryConfig,
    /// Versions of the peers' libraries, from the peer interpreter.
    peer_versions: std::collections::BTreeMap<String, String>,
    rows: &'a [Row],
}

fn percentile(v: &mut [f64], p: f64) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    v[((v.len() - 1) as f64 * p).round() as usize]
}

/// Peak and current resident memory in MiB, from /proc/self/status (Linux).
fn rss_mib() -> (Option<f64>, Option<f64>) {
    let Ok(s) = std::fs::read_to_string("/proc/self/status") else {
        return (None, None);
    };
    let field = |name: &str| {
        s.lines()
            .find(|l| l.starts_with(name))
            .and_then(|l| l.split_whitespace().nth(1))
            .and_then(|v| v.parse::<f64>().ok())
            .map(|kib| kib / 1024.0)
    };
    (field("VmHWM:"), field("VmRSS:"))
}

fn odometry(a: OdometryBench) -> Result<()> {
    let config = a.odometry.config(&a.config)?;
    let mut opts = OpenOptions {
        max_frames: a.max_frames,
        ..Default::default()
    };
    super::options::set_camera(&mut opts, a.camera.as_deref(), a.calib_format)?;
    let seq = TumSequence::open(&a.sequence, &opts)?;
    std::fs::create_dir_all(&a.out).with_context(|| format!("{}", a.out.display()))?;
    let gt = seq.ground_truth()?;
    let mut rows = Vec::new();
    let mut adapters = Vec::new();
    for name in a
        .backends
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
    {
        let backend = match name {
            "cpu" => ComputeBackend::Cpu,
            "gpu" => match select_backend(BackendChoice::Gpu, a.adapter.as_deref()) {
                Ok(b) => b,
                Err(e) => {
                    println!("backend gpu: unavailable ({e})");
                    continue;
                }
            },
            other => anyhow::bail!("unknown backend '{other}' (cpu or gpu)"),
        };
        let label = backend.name();
        if let ComputeBackend::Gpu(ctx) = &backend {
            adapters.push(ctx.adapter_info().name.clone());
        }
        let mut odo = Odometry::new(config.clone(), seq.camera, &backend)?;
        if let (Some(gt), Some(e)) = (&gt, seq.entries.first()) {
            if let Some(near) = gt.iter().min_by(|x, y| {
                (x.timestamp - e.timestamp)
                    .abs()
                    .total_cmp(&(y.timestamp - e.timestamp).abs())
            }) {
                odo.set_initial_pose(near.world_from_camera);
            }
        }
        let bar = ProgressBar::new(seq.len() as u64);
        bar.set_style(
            ProgressStyle::with_template("{msg} {bar:30} {pos}/{len}")
                .unwrap_or_else(|_| ProgressStyle::default_bar()),
        );
        bar.set_message(label.clone());
        let mut totals = Vec::new();
        let mut stages: [Vec<f64>; 6] = Default::default();
        let mut load_ms = Vec::new();
        let mut poses = Vec::new();
        let mut rss_early = None;
        for i in 0..seq.len() {
            let t = std::time::Instant::now();
            let frame = seq.load(i)?;
            load_ms.push(t.elapsed().as_secs_f64() * 1e3);
            let r = match odo.track(&frame) {
                Ok(r) => r,
                Err(OdometryError::TrackingFailed(m)) => {
                    log::warn!("frame {i}: {m}");
                    continue;
                }
                Err(e) => return Err(e.into()),
            };
            poses.push(TimedPose {
                timestamp: frame.timestamp(),
                world_from_camera: r.world_from_camera,
            });
            if i > 0 {
                let s = r.stats.times;
                totals.push(s.total_ms);
                for (k, v) in [
                    s.pyramid_ms,
                    s.scale_ms,
                    s.reduce_ms,
                    s.solve_ms,
                    s.covisibility_ms,
                    s.covariance_ms,
                ]
                .into_iter()
                .enumerate()
                {
                    stages[k].push(v);
                }
            }
            if i == 10 {
                rss_early = rss_mib().1;
            }
            bar.inc(1);
        }
        bar.finish_and_clear();
        let (peak, rss_end) = rss_mib();
        let path = a.out.join(format!("rgbid_{name}.txt"));
        write_tum(&path, &poses)?;
        let (ate, rpe, rpe_rot) = accuracy(gt.as_deref(), &poses);
        let st = Stages {
            pyramid: median(&mut stages[0]),
            scale: median(&mut stages[1]),
            reduce: median(&mut stages[2]),
            solve: median(&mut stages[3]),
            covisibility: median(&mut stages[4]),
            covariance: median(&mut stages[5]),
        };
        let decode = median(&mut load_ms);
        println!(
            "rgbid {label}: per-frame median {:.2} ms (pyramid {:.2}, scale {:.2}, reduce {:.2}, solve {:.2}, covisibility {:.2}, covariance {:.2}); decode {decode:.2} ms/frame (not counted)",
            median(&mut totals.clone()),
            st.pyramid,
            st.scale,
            st.reduce,
            st.solve,
            st.covisibility,
            st.covariance,
        );
        if let (Some(e), Some(l)) = (rss_early, rss_end) {
            println!("  resident memory: {e:.0} MiB after 10 frames, {l:.0} MiB at the end, peak {:.0} MiB", peak.unwrap_or(f64::NAN));
        }
        rows.push(Row {
            method: format!("rgbid {name}"),
            peer: false,
            backend: Some(label),
            frames: poses.len(),
            ms_median: median(&mut totals.clone()),
            ms_p90: percentile(&mut totals, 0.9),
            ate_rmse_m: ate,
            rpe_m_per_s: rpe,
            rpe_deg_per_s: rpe_rot,
            stages_ms: Some(st),
            decode_ms_median: Some(decode),
            rss_mib_after_10: rss_early,
            rss_mib_end: rss_end,
            peak_rss_mib: peak,
            speedup_vs: Default::default(),
        });
    }
    if !a.peers.trim().is_empty() {
        match run_peers(&a, &seq) {
            Ok(mut peers) => rows.append(&mut peers),
            Err(e) => println!("peers not measured: {e:#}"),
        }
    }
    add_speedups(&mut rows);
    print_table(&rows);
    if let Some(path) = &a.json {
        let mut peer_versions = std::collections::BTreeMap::new();
        if rows.iter().any(|r| r.peer) {
            let peers = a.peers.to_lowercase();
            for (prefix, module, label) in [("cv_", "cv2", "opencv"), ("o3d", "open3d", "open3d")] {
                if peers.split(',').any(|m| m.trim().starts_with(prefix)) {
                    if let Some(v) = super::report::python_module_version(&a.python, module) {
                        peer_versions.insert(label.to_string(), v);
                    }
                }
            }
        }
        let report = OdometryReport {
            sequence: a.sequence.display().to_string(),
            sequence_name: a
                .sequence
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default(),
            sequence_frames: seq.len(),
            camera: a.camera.as_deref(),
            config: &config,
            peer_versions,
            rows: &rows,
        };
        super::report::write(path, "odometry", &super::report::meta(adapters), &report)?;
    }
    Ok(())
}

/// Fills every row's speed-up against each peer row (other than itself).
fn add_speedups(rows: &mut [Row]) {
    let peers: Vec<(String, f64)> = rows
        .iter()
        .filter(|r| r.peer)
        .map(|r| (r.method.clone(), r.ms_median))
        .collect();
    for r in rows.iter_mut() {
        for (method, ms) in &peers {
            if *method != r.method && ms.is_finite() && r.ms_median > 0.0 {
                r.speedup_vs.insert(method.clone(), ms / r.ms_median);
            }
        }
    }
}

/// ATE RMSE (m), translational RPE RMSE (m/s) and rotational RPE RMSE (deg/s) of `est`.
fn accuracy(
    gt: Option<&[TimedPose]>,
    est: &[TimedPose],
) -> (Option<f64>, Option<f64>, Option<f64>) {
    let Some(gt) = gt else {
        return (None, None, None);
    };
    match rgbid::eval::evaluate(gt, est, &rgbid::eval::EvalOptions::default()) {
        Ok(r) => (
            Some(r.ate.translation.rmse),
            r.rpe.as_ref().map(|x| x.translation_m_per_s.rmse),
            r.rpe.as_ref().map(|x| x.rotation_deg_per_s.rmse),
        ),
        Err(e) => {
            log::warn!("evaluation failed: {e}");
            (None, None, None)
        }
    }
}

fn run_peers(a: &OdometryBench, seq: &TumSequence) -> Result<Vec<Row>> {
    use rgbid::experiments::peers::{run_odometry_peers, OdometryPeerOptions};
    let opts = OdometryPeerOptions {
        python: &a.python,
        script: &a.peer_script,
        methods: &a.peers,
        max_frames: a.max_frames,
    };
    let runs = run_odometry_peers(&opts, &seq.root, &a.out.join("peers"))?;
    let gt = seq.ground_truth()?;
    let mut rows = Vec::new();
    for run in runs {
        // Re-evaluate the peers' trajectories with rgbid's own metrics, like rgbid's rows.
        let est = rgbid::io::trajectory::read_tum(&run.trajectory).ok();
        let (ate, rpe, rpe_rot) = match (&gt, &est) {
            (Some(g), Some(e)) => accuracy(Some(g), e),
            _ => (run.ate_rmse_m, run.rpe_m_per_s, None),
        };
        rows.push(Row {
            method: run.method,
            peer: true,
            backend: None,
            frames: run.frames,
            ms_median: run.ms_median,
            ms_p90: run.ms_p90,
            ate_rmse_m: ate,
            rpe_m_per_s: rpe,
            rpe_deg_per_s: rpe_rot,
            stages_ms: None,
            decode_ms_median: None,
            rss_mib_after_10: None,
            rss_mib_end: None,
            peak_rss_mib: None,
            speedup_vs: Default::default(),
        });
    }
    Ok(rows)
}

fn print_table(rows: &[Row]) {
    let reference = rows
        .iter()
        .find(|r| r.method == "cv_rgbd")
        .map(|r| r.ms_median);
    println!("\n| method | frames | ATE RMSE m | RPE m/s | RPE deg/s | median ms/frame | p90 ms | speed-up vs OpenCV RGB_DEPTH |");
    println!("|---|---|---|---|---|---|---|---|");
    for r in rows {
        let f = |v: Option<f64>| v.map(|x| format!("{x:.4}")).unwrap_or_else(|| "-".into());
        let ratio = reference
            .map(|p| format!("{:.2}x", p / r.ms_median))
            .unwrap_or_else(|| "-".into());
        println!(
            "| {} | {} | {} | {} | {} | {:.1} | {:.1} | {} |",
            r.method,
            r.frames,
            f(r.ate_rmse_m),
            f(r.rpe_m_per_s),
            f(r.rpe_deg_per_s),
            r.ms_median,
            r.ms_p90,
            ratio
        );
    }
}
