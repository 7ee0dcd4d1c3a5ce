//! `rgbid demo`: the main job on an embedded default, with no files needed. Renders a
//! procedural office in memory along a closed loop that comes back past its start, runs the
//! full RGB-ID SLAM on it (tracking, keyframe fusion, loop closure, pose graph), and reports
//! ATE / RPE of SLAM and of odometry alone against the exact ground truth.

use std::path::PathBuf;

use anyhow::Result;
use rgbid::gpu::BackendChoice;

/// Arguments of `rgbid demo`.
#[derive(clap::Args)]
pub struct Args {
    /// Output folder (trajectories, loops, model.ply, timings, summary.json).
    #[arg(long, default_value = "demo-out")]
    pub out: PathBuf,
    /// Scene preset (office, kitchen, corridor, lab, home).
    #[arg(long, default_value = "office")]
    pub scene: String,
    /// Trajectory (loop, handheld, slow, fast, walk-head, walk-chest, stairs, robot).
    #[arg(long, default_value = "loop")]
    pub trajectory: String,
    /// Number of frames (30 per second).
    #[arg(long, default_value_t = 390)]
    pub frames: usize,
    /// Laps of the loop over the frames (1.3: the last 90 frames revisit the start).
    #[arg(long, default_value_t = 1.3)]
    pub laps: f64,
    /// Image width in pixels (height is 3/4 of it). 320 keeps the default run around a
    /// minute on a 2-core machine without a GPU.
    #[arg(long, default_value_t = 320)]
    pub width: u32,
    /// Random seed of the scene, trajectory and sensor noise.
    #[arg(long, default_value_t = 7)]
    pub seed: u64,
    /// Compute backend for rendering, odometry and fusion.
    #[arg(long, value_enum, default_value_t = BackendChoice::Auto)]
    pub backend: BackendChoice,
    /// GPU adapter name filter.
    #[arg(long)]
    pub adapter: Option<String>,
}

/// Runs the subcommand.
pub fn run(a: Args) -> Result<()> {
    println!(
        "demo: RGB-ID SLAM on a generated '{}' scene, '{}' trajectory ({} laps), {} frames",
        a.scene, a.trajectory, a.laps, a.frames
    );
    crate::cli::slam::run(crate::cli::slam::Args {
        sequence: None,
        synth: Some(format!("{}:{}", a.scene, a.trajectory)),
        frames: a.frames,
        width: a.width,
        seed: a.seed,
        laps: a.laps,
        session: 0,
        out: a.out,
        camera: None,
        max_frames: None,
        map_in: None,
        map_out: None,
        realtime: None,
        no_masks: false,
        keyframe_covisibility: 0.7,
        max_speed: rgbid::slam::SlamConfig::default().lost_max_speed,
        max_angular_speed: rgbid::slam::SlamConfig::default().lost_max_angular_speed,
        no_model: false,
        voxel: 0.01,
        vocabulary: None,
        backend: a.backend,
        adapter: a.adapter,
    })
}
