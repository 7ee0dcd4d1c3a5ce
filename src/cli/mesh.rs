//! `rgbid mesh SEQ --poses TRAJ`: TSDF integration of every frame of a TUM sequence at given
//! poses, and `rgbid bench tsdf`: speed and accuracy on a generated scene against Open3D.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use anyhow::{bail, Context, Result};
use glam::DVec3;
use indicatif::{ProgressBar, ProgressStyle};
use rgbid::camera::PinholeCamera;
use rgbid::eval::associate;
use rgbid::gpu::{select_backend, BackendChoice, ComputeBackend};
use rgbid::image::RgbdFrame;
use rgbid::io::trajectory::read_tum;
use rgbid::io::tum::{OpenOptions, TumSequence};
use rgbid::io::CalibFormat;
use rgbid::synth::tum_export::TumWriter;
use rgbid::synth::{
    CameraModel, RenderBackend, Scene, Sequence, SequenceConfig, Trajectory, TrajectoryKind,
};
use rgbid::trajectory::TimedPose;
use rgbid::tsdf::{mesh_accuracy, thin_points, MeshAccuracy, TsdfParams, TsdfVolume};

use super::bench::median;

/// Arguments of `rgbid mesh`.
#[derive(clap::Args)]
#[command(group(clap::ArgGroup::new("input").required(true).multiple(true).args(["sequence", "volume"])))]
pub struct Args {
    /// TUM-layout sequence folder (rgb/, depth/, associations or rgb.txt + depth.txt). May be
    /// left out with --volume (a mesh of the saved volume alone).
    #[arg(requires = "poses")]
    pub sequence: Option<PathBuf>,
    /// Trajectory (TUM format, `world_from_camera`); frames are matched to poses by time
    /// stamp within `--max-diff` seconds, unmatched frames are skipped. Needed with a
    /// sequence.
    #[arg(long, requires = "sequence")]
    pub poses: Option<PathBuf>,
    /// Start from this saved volume (`--save-volume`, `rgbid slam --mesh`'s volume.tsdf)
    /// instead of an empty one: its voxel size and depth range apply, and the sequence's
    /// frames, if any, are integrated into it.
    #[arg(long, value_name = "FILE")]
    pub volume: Option<PathBuf>,
    /// Also save the volume after integration (rgbid's binary .tsdf format, for --volume and
    /// `rgbid.TsdfVolume.load`).
    #[arg(long, value_name = "FILE")]
    pub save_volume: Option<PathBuf>,
    /// Voxel edge, metres (blocks are 8 voxels along each side) (> 0). Not with --volume.
    #[arg(long, value_parser = crate::cli::options::range::positive, default_value_t = 0.01, conflicts_with = "volume")]
    pub voxel: f64,
    /// Output mesh, binary PLY with normals, colours and faces.
    #[arg(long, default_value = "mesh.ply")]
    pub out: PathBuf,
    /// Largest pose/frame time-stamp difference, seconds (> 0).
    #[arg(long, value_parser = crate::cli::options::range::positive, default_value_t = 0.02)]
    pub max_diff: f64,
    /// Farthest depth integrated, metres (> 0). Not with --volume.
    #[arg(long, value_parser = crate::cli::options::range::positive, default_value_t = 4.0, conflicts_with = "volume")]
    pub max_depth: f64,
    /// Camera: a preset (default, tum_fr1, tum_fr2, tum_fr3, icl_nuim, 7scenes, replica) or a
    /// camera file (calib.txt, OpenCV / ORB-SLAM .yaml, or `key = value` lines). Default:
    /// calib.txt beside the sequence, else `default`. Frames are undistorted with it.
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
    /// Integrate only the first this many frames (>= 1).
    #[arg(long, value_parser = crate::cli::options::range::at_least_one)]
    pub max_frames: Option<usize>,
    /// Where the integration runs: auto (hardware GPU, else CPU), gpu (any adapter, lavapipe
    /// included), cpu (rayon).
    #[arg(long, value_enum, default_value_t = BackendChoice::Auto)]
    pub backend: BackendChoice,
    /// Most voxel blocks kept on the GPU (>= 1; a block is 8^3 voxels, 6144 bytes): beyond
    /// it, the blocks farthest from the camera that a frame does not touch move to host
    /// memory and back when needed; the mesh and the saved volume are the same as without
    /// it. Default: unbounded. The CPU backend ignores it.
    #[arg(long, value_parser = crate::cli::options::range::at_least_one, value_name = "BLOCKS")]
    pub device_blocks: Option<usize>,
}

fn progress(n: usize) -> ProgressBar {
    let bar = ProgressBar::new(n as u64);
    bar.set_style(
        ProgressStyle::with_template("{bar:40} {pos}/{len} frames {elapsed} ({eta} left)")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    bar
}

/// Runs `rgbid mesh`.
pub fn run(args: Args) -> Result<()> {
    let inputs: Vec<&std::path::Path> = [&args.sequence, &args.poses, &args.volume]
        .into_iter()
        .flatten()
        .map(|p| p.as_path())
        .collect();
    super::outputs::output_file(&args.out, "--out", &inputs)?;
    if let Some(p) = &args.save_volume {
        super::outputs::output_file(p, "--save-volume", &inputs)?;
        if p == &args.out {
            bail!("--save-volume and --out are the same file {}", p.display());
        }
    }
    let backend = select_backend(args.backend, None)?;
    let mut integrated = None;
    let vol = match (&args.sequence, &args.poses) {
        (Some(sequence), Some(poses)) => {
            let t = Instant::now();
            let (vol, stats) = integrate_sequence(&args, sequence, poses, &backend)?;
            integrated = Some((t.elapsed().as_secs_f64(), stats));
            vol
        }
        _ => {
            let Some(path) = &args.volume else {
                bail!("give a sequence with --poses, or --volume");
            };
            let mut vol = load_volume(path, None, &backend)?;
            vol.set_device_blocks(args.device_blocks)?;
            vol
        }
    };
    let t = Instant::now();
    let mesh = vol.extract_mesh()?;
    mesh.write_ply(&args.out)?;
    let extract_s = t.elapsed().as_secs_f64();
    // Surface area of the mesh, for the memory per square metre.
    let area: f64 = mesh
        .triangles
        .iter()
        .map(|t| {
            let p = t.map(|i| {
                let v = mesh.vertices[i as usize];
                DVec3::new(f64::from(v[0]), f64::from(v[1]), f64::from(v[2]))
            });
            0.5 * (p[1] - p[0]).cross(p[2] - p[0]).length()
        })
        .sum();
    let voxel_bytes = vol.block_count() * rgbid::tsdf::BLOCK_VOXELS * 12;
    println!(
        "{} frames, {} blocks ({:.1} MB of voxels, {:.2} MB per square metre of surface), {} \
         vertices, {} triangles, {:.1} m^2, extracted in {:.2} s -> {}",
        vol.frames(),
        vol.block_count(),
        voxel_bytes as f64 / 1e6,
        if area > 0.0 {
            voxel_bytes as f64 / 1e6 / area
        } else {
            0.0
        },
        mesh.vertices.len(),
        mesh.triangles.len(),
        area,
        extract_s,
        args.out.display()
    );
    // Where the voxels are: device slots and host-held (paged-out) blocks on the GPU backend,
    // host memory on the CPU backend.
    let block_mb = (rgbid::tsdf::BLOCK_VOXELS * 12) as f64 / 1e6;
    let st = vol.paging();
    let per_m2 = |mb: f64| if area > 0.0 { mb / area } else { 0.0 };
    let mut peak_device = None;
    if let Some((seconds, s)) = integrated {
        let n = s.frames.max(1) as f64;
        println!(
            "integration: {:.1} ms per frame (allocation {:.1} ms, kernel and paging {:.1} ms; \
             {:.1} ms with reading the frames), {} blocks per frame at most",
            1e3 * (s.allocate_s + s.kernel_s) / n,
            1e3 * s.allocate_s / n,
            1e3 * s.kernel_s / n,
            1e3 * seconds / n,
            s.most_active
        );
        peak_device = Some((s.peak_device_blocks, s.peak_device_bytes));
    }
    if matches!(backend, ComputeBackend::Gpu(_)) {
        let resident = st.resident_blocks as f64 * block_mb;
        let host = st.host_blocks as f64 * block_mb;
        println!(
            "device: {:.1} MB of voxels resident ({} blocks, {:.2} MB per square metre of \
             surface); host: {:.1} MB of paged-out voxels ({} blocks, {:.2} MB per square \
             metre); {} page-outs, {} page-ins",
            resident,
            st.resident_blocks,
            per_m2(resident),
            host,
            st.host_blocks,
            per_m2(host),
            st.page_outs,
            st.page_ins
        );
        if let Some((blocks, bytes)) = peak_device {
            println!(
                "device peak while integrating: {:.1} MB of voxel storage ({} blocks), {:.1} MB \
                 in all (frame buffers included)",
                blocks as f64 * block_mb,
                blocks,
                bytes as f64 / 1e6
            );
        }
    }
    if let Some(p) = &args.save_volume {
        let t = Instant::now();
        vol.save(p)?;
        let bytes = std::fs::metadata(p).map(|m| m.len()).unwrap_or(0);
        println!(
            "volume: {:.1} MB saved in {:.2} s -> {}",
            bytes as f64 / 1e6,
            t.elapsed().as_secs_f64(),
            p.display()
        );
    }
    Ok(())
}

/// Totals of the integration of a sequence.
#[derive(Default)]
struct IntegrationStats {
    /// Frames integrated.
    frames: usize,
    /// Seconds of block allocation and of the kernel (with paging), summed over frames.
    allocate_s: f64,
    kernel_s: f64,
    /// Most blocks one frame touched.
    most_active: usize,
    /// Peak voxel storage on the device (blocks) and peak device bytes in all.
    peak_device_blocks: usize,
    peak_device_bytes: usize,
}

/// Integrates the frames of `sequence` that have a pose in `poses` into a new volume, or
/// into the one of `--volume`.
fn integrate_sequence(
    args: &Args,
    sequence: &std::path::Path,
    poses: &std::path::Path,
    backend: &ComputeBackend,
) -> Result<(TsdfVolume, IntegrationStats)> {
    let mut opts = OpenOptions {
        max_frames: args.max_frames,
        ..Default::default()
    };
    super::options::set_camera(&mut opts, args.camera.as_deref(), args.calib_format)?;
    let seq = TumSequence::open(sequence, &opts)?;
    let poses_path = poses;
    let poses = read_tum(poses_path).context("reading --poses")?;
    let stamps: Vec<TimedPose> = seq
        .entries
        .iter()
        .map(|e| TimedPose {
            timestamp: e.timestamp,
            world_from_camera: rgbid::geometry::Se3::IDENTITY,
        })
        .collect();
    let pairs = associate(&stamps, &poses, args.max_diff);
    if pairs.is_empty() {
        bail!(
            "no frame of {} has a pose within {} s in {}",
            sequence.display(),
            args.max_diff,
            poses_path.display()
        );
    }
    let mut vol = match &args.volume {
        Some(path) => {
            let mut vol = load_volume(path, Some(seq.undistorted_camera()), backend)?;
            vol.set_device_blocks(args.device_blocks)?;
            vol
        }
        None => {
            let params = TsdfParams {
                voxel_size: args.voxel,
                max_depth: args.max_depth,
                device_blocks: args.device_blocks,
                ..Default::default()
            };
            TsdfVolume::new(params, seq.undistorted_camera(), backend)?
        }
    };
    let mut stats = IntegrationStats {
        peak_device_blocks: vol.device_block_capacity(),
        peak_device_bytes: vol.memory_bytes().1,
        ..Default::default()
    };
    log::info!(
        "integrating {} of {} frames on {}",
        pairs.len(),
        seq.len(),
        backend.name()
    );
    let bar = progress(pairs.len());
    for (i, j) in &pairs {
        let frame = seq.load(*i)?;
        let t = vol.integrate(&frame, &poses[*j].world_from_camera)?;
        stats.frames += 1;
        stats.allocate_s += t.allocate_s;
        stats.kernel_s += t.kernel_s;
        stats.most_active = stats.most_active.max(t.active_blocks);
        stats.peak_device_blocks = stats.peak_device_blocks.max(vol.device_block_capacity());
        stats.peak_device_bytes = stats.peak_device_bytes.max(vol.memory_bytes().1);
        bar.inc(1);
    }
    bar.finish_and_clear();
    Ok((vol, stats))
}

/// Arguments of `rgbid bench tsdf`.
#[derive(clap::Args)]
pub struct TsdfBench {
    /// Scene preset of the generated room.
    #[arg(long, default_value = "office")]
    pub scene: String,
    /// Seed of the scene, trajectory and noise (any whole number, 0 to 2^64-1).
    #[arg(long, value_parser = crate::cli::options::range::seed, default_value_t = 1)]
    pub seed: u64,
    /// Frames (30 per second along a handheld path; every frame is integrated) (>= 1).
    #[arg(long, value_parser = crate::cli::options::range::at_least_one, default_value_t = 150)]
    pub frames: usize,
    /// Image width, pixels (a Kinect's 525 px focal length at 640 wide, scaled) (16 to 16384 pixels).
    #[arg(long, value_parser = crate::cli::options::range::image_side, default_value_t = 640)]
    pub width: u32,
    /// Image height, pixels (16 to 16384 pixels).
    #[arg(long, value_parser = crate::cli::options::range::image_side, default_value_t = 480)]
    pub height: u32,
    /// Voxel edge, metres (> 0).
    #[arg(long, value_parser = crate::cli::options::range::positive, default_value_t = 0.02)]
    pub voxel: f64,
    /// Backends to measure, comma-separated: cpu, gpu.
    #[arg(long, default_value = "cpu,gpu")]
    pub backends: String,
    /// Python interpreter with open3d for the peer (empty: no peer).
    #[arg(long, default_value = "/work/.venv-peers/bin/python")]
    pub python: String,
    /// The peer script.
    #[arg(long, default_value = "scripts/tsdf_open3d.py")]
    pub peer_script: PathBuf,
    /// Also write the results as JSON (machine, commit, command and every row) to this file.
    #[arg(long, value_name = "FILE")]
    pub json: Option<PathBuf>,
}

/// One row of `rgbid bench tsdf`.
#[derive(serde::Serialize)]
struct TsdfRow {
    method: String,
    /// Whether colour was integrated (rgbid rows measure both; Open3D integrates colour).
    colour: bool,
    /// Median ms to integrate one frame (allocation + kernel; Open3D: block coordinates +
    /// integration).
    integrate_ms: f64,
    /// Median ms of the host block allocation (rgbid only).
    allocate_ms: Option<f64>,
    /// Median ms of the integration kernel (rgbid only).
    kernel_ms: Option<f64>,
    /// Median blocks a frame touched (rgbid only).
    active_blocks: Option<f64>,
    /// Seconds to extract the mesh (the first extraction).
    extract_s: f64,
    /// Median ms of three extractions of the finished volume's mesh (rgbid only; the GPU
    /// backend's per-cube kernel with its read-back, then the host's vertex sharing and
    /// normals).
    extract_ms: Option<f64>,
    /// Median ms of a ray cast of the finished volume (depth, normals and colour at the
    /// frames' size) from every tenth frame's pose (rgbid only).
    cast_ms: Option<f64>,
    /// Open3D's median integration time over this method's.
    open3d_ratio: Option<f64>,
    #[serde(flatten)]
    accuracy: MeshAccuracy,
}

/// Runs `rgbid bench tsdf`.
pub fn bench(a: TsdfBench) -> Result<()> {
    let work = std::env::temp_dir().join(format!("rgbid-bench-tsdf-{}", std::process::id()));
    let result = bench_in(&a, &work);
    // The rendered frames are only needed by this run.
    let _ = std::fs::remove_dir_all(&work);
    result
}

fn bench_in(a: &TsdfBench, work: &std::path::Path) -> Result<()> {
    let scene = Arc::new(Scene::preset(&a.scene, a.seed)?);
    let f = 525.0 * f64::from(a.width) / 640.0;
    let cam = PinholeCamera::new(
        f,
        f,
        (f64::from(a.width) - 1.0) / 2.0,
        (f64::from(a.height) - 1.0) / 2.0,
        a.width,
        a.height,
    );
    let duration = a.frames as f64 / 30.0;
    let traj = Trajectory::new(TrajectoryKind::Handheld, &scene, duration, a.seed)?;
    let mut sensor = rgbid::synth::SensorModel::kinect();
    sensor.focal_px = Some(525.0);
    let config = SequenceConfig {
        frames: a.frames,
        seed: a.seed,
        sensor,
        ..Default::default()
    };
    let seq = Sequence::new(
        scene.clone(),
        CameraModel::Pinhole(cam),
        traj,
        config,
        &RenderBackend::Cpu,
    )?;
    let folder = work.join("seq");
    println!(
        "rendering {} frames of '{}' at {}x{} to {}",
        a.frames,
        a.scene,
        a.width,
        a.height,
        folder.display()
    );
    let mut writer = TumWriter::create(&folder, &CameraModel::Pinhole(cam))?;
    let mut seen = Vec::new();
    let bar = progress(a.frames);
    for f in seq {
        let f = f?;
        let w = cam.width as usize;
        let rho = f.frame.inverse_depth.data();
        for (i, &z) in f.frame.true_depth.data().iter().enumerate() {
            if z > 0.0 && rho[i] > 0.0 {
                let (u, v, z) = ((i % w) as f64, (i / w) as f64, f64::from(z));
                let p = DVec3::new((u - cam.cx) / cam.fx * z, (v - cam.cy) / cam.fy * z, z);
                seen.push(f.world_from_camera.transform_point(p));
            }
        }
        seen = thin_points(&seen, 0.01);
        writer.write_frame(f.timestamp, &f.world_from_camera, &f.frame)?;
        bar.inc(1);
    }
    bar.finish_and_clear();
    writer.finish("rgbid bench tsdf", &[])?;
    let reference = seen;
    let tum = TumSequence::open(&folder, &OpenOptions::default())?;
    let gt = read_tum(&folder.join("groundtruth.txt"))?;
    let distance = |p: DVec3| scene.surface_distance(p);
    let params = TsdfParams {
        voxel_size: a.voxel,
        ..Default::default()
    };
    let mut rows = Vec::new();
    let mut adapters = Vec::new();
    for name in a.backends.split(',').map(str::trim) {
        let backend = match name {
            "cpu" => ComputeBackend::Cpu,
            "gpu" => match select_backend(BackendChoice::Gpu, None) {
                Ok(b) => b,
                Err(e) => {
                    println!("backend gpu: unavailable ({e})");
                    continue;
                }
            },
            other => bail!("unknown backend '{other}' (cpu, gpu)"),
        };
        if let ComputeBackend::Gpu(ctx) = &backend {
            adapters.push(ctx.adapter_info().name.clone());
        }
        // With the frames' colour, then depth only (the same frames without their colour).
        for colour in [true, false] {
            let mut vol = TsdfVolume::new(params, cam, &backend)?;
            let (mut total, mut alloc, mut kernel) = (Vec::new(), Vec::new(), Vec::new());
            let mut blocks = Vec::new();
            for i in 0..tum.len() {
                let mut frame = tum.load(i)?;
                if !colour {
                    let t = frame.timestamp();
                    let (intensity, rho) = frame.into_images();
                    frame = RgbdFrame::new(t, intensity, rho)?;
                }
                let pose = gt
                    .get(i)
                    .context("ground truth shorter than the sequence")?
                    .world_from_camera;
                let t = Instant::now();
                let s = vol.integrate(&frame, &pose)?;
                total.push(t.elapsed().as_secs_f64() * 1e3);
                alloc.push(s.allocate_s * 1e3);
                kernel.push(s.kernel_s * 1e3);
                blocks.push(s.active_blocks as f64);
            }
            let t = Instant::now();
            let mesh = vol.extract_mesh()?;
            let extract_s = t.elapsed().as_secs_f64();
            let mut extract = vec![extract_s * 1e3];
            for _ in 0..2 {
                let t = Instant::now();
                vol.extract_mesh()?;
                extract.push(t.elapsed().as_secs_f64() * 1e3);
            }
            let mut cast = Vec::new();
            for p in gt.iter().take(tum.len()).step_by(10) {
                let t = Instant::now();
                vol.ray_cast(&cam, &p.world_from_camera)?;
                cast.push(t.elapsed().as_secs_f64() * 1e3);
            }
            rows.push(TsdfRow {
                method: format!(
                    "rgbid {}{}",
                    backend.name(),
                    if colour { "" } else { ", no colour" }
                ),
                colour,
                integrate_ms: median(&mut total),
                allocate_ms: Some(median(&mut alloc)),
                kernel_ms: Some(median(&mut kernel)),
                active_blocks: Some(median(&mut blocks)),
                extract_s,
                extract_ms: Some(median(&mut extract)),
                cast_ms: Some(median(&mut cast)),
                open3d_ratio: None,
                accuracy: mesh_accuracy(&mesh.vertices, distance, &reference, 0.02),
            });
        }
    }
    if !a.python.is_empty() {
        let mesh_path = work.join("open3d.ply");
        let json_path = work.join("open3d.json");
        let status = std::process::Command::new(&a.python)
            .arg(&a.peer_script)
            .arg(&folder)
            .arg("--voxel")
            .arg(a.voxel.to_string())
            .arg("--depth-max")
            .arg(params.max_depth.to_string())
            .arg("--mesh")
            .arg(&mesh_path)
            .arg("--json")
            .arg(&json_path)
            .status();
        match status {
            Ok(s) if s.success() => {
                let doc: serde_json::Value =
                    serde_json::from_str(&std::fs::read_to_string(&json_path)?)?;
                let mut ms: Vec<f64> = doc["integrate_ms"]
                    .as_array()
                    .map(|v| v.iter().filter_map(|x| x.as_f64()).collect())
                    .unwrap_or_default();
                let verts: Vec<[f32; 3]> = rgbid::io::ply::read_ply(&mesh_path)?
                    .iter()
                    .map(|(p, _)| [p.x as f32, p.y as f32, p.z as f32])
                    .collect();
                let o3d_ms = median(&mut ms);
                for r in &mut rows {
                    r.open3d_ratio = Some(o3d_ms / r.integrate_ms);
                }
                rows.push(TsdfRow {
                    method: format!(
                        "Open3D {} VoxelBlockGrid (CPU)",
                        doc["open3d"].as_str().unwrap_or("?")
                    ),
                    colour: true,
                    integrate_ms: o3d_ms,
                    allocate_ms: None,
                    kernel_ms: None,
                    active_blocks: None,
                    extract_s: doc["extract_s"].as_f64().unwrap_or(f64::NAN),
                    extract_ms: None,
                    cast_ms: None,
                    open3d_ratio: Some(1.0),
                    accuracy: mesh_accuracy(&verts, distance, &reference, 0.02),
                });
            }
            // The script's status for "open3d cannot be imported".
            Ok(s) if s.code() == Some(3) => {
                println!(
                    "peer Open3D: skipped (open3d is not importable by {})",
                    a.python
                )
            }
            Ok(s) => println!("peer Open3D: failed ({s})"),
            Err(e) => println!("peer Open3D: could not run {} ({e})", a.python),
        }
    }
    println!(
        "{} frames {}x{}, voxel {} m, scene '{}' seed {}, ground-truth poses, every frame integrated",
        a.frames, a.width, a.height, a.voxel, a.scene, a.seed
    );
    println!(
        "{:<44} {:>9} {:>9} {:>9} {:>7} {:>9} {:>10} {:>8} {:>9} {:>8} {:>8} {:>7} {:>8}",
        "method",
        "int. ms",
        "alloc ms",
        "kern. ms",
        "blocks",
        "extract s",
        "extract ms",
        "cast ms",
        "vertices",
        "mean mm",
        "p90 mm",
        "compl.",
        "O3D/x"
    );
    let opt = |v: Option<f64>, p: usize| v.map_or("-".to_string(), |x| format!("{x:.p$}"));
    for r in &rows {
        println!(
            "{:<44} {:>9.2} {:>9} {:>9} {:>7} {:>9.2} {:>10} {:>8} {:>9} {:>8.2} {:>8.2} {:>7.3} {:>8}",
            r.method,
            r.integrate_ms,
            opt(r.allocate_ms, 2),
            opt(r.kernel_ms, 2),
            opt(r.active_blocks, 0),
            r.extract_s,
            opt(r.extract_ms, 1),
            opt(r.cast_ms, 1),
            r.accuracy.vertices,
            r.accuracy.mean_m * 1e3,
            r.accuracy.p90_m * 1e3,
            r.accuracy.completeness,
            opt(r.open3d_ratio, 2)
        );
    }
    if let Some(path) = &a.json {
        let body = serde_json::json!({
            "scene": a.scene,
            "seed": a.seed,
            "frames": a.frames,
            "width": a.width,
            "height": a.height,
            "voxel_m": a.voxel,
            "rows": rows,
        });
        super::report::write(path, "tsdf", &super::report::meta(adapters), &body)?;
    }
    Ok(())
}

/// A saved volume (see [`TsdfVolume::load`]), its size and load time logged.
fn load_volume(
    path: &std::path::Path,
    camera: Option<PinholeCamera>,
    backend: &ComputeBackend,
) -> Result<TsdfVolume> {
    let t = Instant::now();
    let v = TsdfVolume::load(path, camera, backend)?;
    log::info!(
        "loaded {} ({} frames, {} blocks) in {:.2} s",
        path.display(),
        v.frames(),
        v.block_count(),
        t.elapsed().as_secs_f64()
    );
    Ok(v)
}
