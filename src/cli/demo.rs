//! `rgbid demo`: the main job on an embedded default, with no files needed. Renders a
//! procedural office in memory along a handheld trajectory, tracks it with the odometry, and
//! reports ATE / RPE against the exact ground truth.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Instant;

use anyhow::{Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use rgbid::camera::PinholeCamera;
use rgbid::gpu::{select_backend, BackendChoice, ComputeBackend};
use rgbid::io::trajectory::{write_tum, TimedPose};
use rgbid::odometry::{Odometry, OdometryConfig, OdometryError};
use rgbid::synth::{
    CameraModel, RenderBackend, Scene, Sequence, SequenceConfig, Trajectory, TrajectoryKind,
};

/// Arguments of `rgbid demo`.
#[derive(clap::Args)]
pub struct Args {
    /// Output folder for the estimated and ground-truth trajectories.
    #[arg(long, default_value = "demo-out")]
    pub out: PathBuf,
    /// Scene preset (office, kitchen, corridor, ...).
    #[arg(long, default_value = "office")]
    pub scene: String,
    /// Trajectory (handheld, slow, fast, loop, walk_head, walk_chest, stairs, robot).
    #[arg(long, default_value = "handheld")]
    pub trajectory: String,
    /// Number of frames (30 per second).
    #[arg(long, default_value_t = 150)]
    pub frames: usize,
    /// Image width in pixels (height is 3/4 of it). 320 keeps the default run well under two
    /// minutes on a 2-core machine without a GPU.
    #[arg(long, default_value_t = 320)]
    pub width: u32,
    /// Random seed of the scene, trajectory and sensor noise.
    #[arg(long, default_value_t = 7)]
    pub seed: u64,
    /// Compute backend for rendering and odometry.
    #[arg(long, value_enum, default_value_t = BackendChoice::Auto)]
    pub backend: BackendChoice,
    /// GPU adapter name filter.
    #[arg(long)]
    pub adapter: Option<String>,
}

/// Runs the subcommand.
pub fn run(a: Args) -> Result<()> {
    let t0 = Instant::now();
    let backend = select_backend(a.backend, a.adapter.as_deref())?;
    let (w, h) = (a.width, a.width * 3 / 4);
    let f = 525.0 * f64::from(w) / 640.0;
    let camera = PinholeCamera::new(
        f,
        f,
        (f64::from(w) - 1.0) / 2.0,
        (f64::from(h) - 1.0) / 2.0,
        w,
        h,
    );
    let scene = Arc::new(Scene::preset(&a.scene, a.seed)?);
    let kind = TrajectoryKind::from_name(&a.trajectory)?;
    let config = SequenceConfig {
        frames: a.frames,
        seed: a.seed,
        ..Default::default()
    };
    let trajectory = Trajectory::new(kind, &scene, config.duration(), a.seed)?;
    let render_backend = match &backend {
        ComputeBackend::Cpu => RenderBackend::Cpu,
        ComputeBackend::Gpu(g) => RenderBackend::Gpu(g.clone()),
    };
    let mut seq = Sequence::new(
        scene,
        CameraModel::Pinhole(camera),
        trajectory,
        config,
        &render_backend,
    )?;
    let gt = seq.ground_truth();
    println!(
        "demo: '{}' scene, '{}' trajectory, {} frames at {w}x{h}, backend {}",
        a.scene,
        a.trajectory,
        seq.len(),
        backend.name()
    );
    let mut odo = Odometry::new(OdometryConfig::default(), camera, &backend)?;
    if let Some(first) = gt.first() {
        odo.set_initial_pose(first.world_from_camera);
    }
    std::fs::create_dir_all(&a.out).with_context(|| format!("{}", a.out.display()))?;
    let bar = ProgressBar::new(seq.len() as u64);
    bar.set_style(
        ProgressStyle::with_template("{bar:40} {pos}/{len} frames {per_sec} {msg}")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let mut poses = Vec::with_capacity(seq.len());
    let mut render_ms = Vec::new();
    let mut track_ms = Vec::new();
    let mut outcome = Ok(());
    loop {
        let tr = Instant::now();
        let Some(item) = seq.next() else { break };
        let sf = match item {
            Ok(f) => f,
            Err(e) => {
                outcome = Err(anyhow::Error::new(e).context("rendering"));
                break;
            }
        };
        render_ms.push(tr.elapsed().as_secs_f64() * 1e3);
        let frame = sf.frame.to_rgbd_frame(sf.timestamp);
        match odo.track(&frame) {
            Ok(r) => {
                track_ms.push(r.stats.times.total_ms);
                poses.push(TimedPose {
                    timestamp: sf.timestamp,
                    world_from_camera: r.world_from_camera,
                });
            }
            Err(OdometryError::TrackingFailed(m)) => log::warn!("frame {}: {m}", sf.index),
            Err(e) => {
                outcome = Err(anyhow::Error::new(e).context(format!("frame {}", sf.index)));
                break;
            }
        }
        bar.inc(1);
    }
    bar.finish_and_clear();
    let est_path = a.out.join("trajectory.txt");
    let gt_path = a.out.join("groundtruth.txt");
    write_tum(&est_path, &poses)?;
    write_tum(&gt_path, &gt)?;
    outcome?;
    let med = |v: &mut Vec<f64>| crate::cli::bench::median(v);
    println!(
        "tracked {} frames: median {:.1} ms/frame odometry, {:.1} ms/frame rendering; total {:.1} s",
        poses.len(),
        med(&mut track_ms),
        med(&mut render_ms),
        t0.elapsed().as_secs_f64()
    );
    println!("wrote {} and {}", est_path.display(), gt_path.display());
    crate::cli::eval::print_against(&gt_path, &est_path)
}
