//! `rgbid demo`: the main job on an embedded default, with no files needed. Renders a
//! procedural office in memory along a closed loop that comes back past its start, runs the
//! full RGB-ID SLAM on it (tracking, keyframe fusion, loop closure, pose graph), and reports
//! ATE / RPE of SLAM and of odometry alone against the exact ground truth.

use std::path::PathBuf;

use anyhow::Result;
use rgbid::source::SynthOptions;

use super::options::{BackendArgs, ConfigArgs, OdometryOptions};

/// Arguments of `rgbid demo`.
#[derive(clap::Args)]
pub struct Args {
    /// Output folder (trajectories, loops, model.ply, timings, summary.json).
    #[arg(long, default_value = "demo-out")]
    pub out: PathBuf,
    #[command(flatten)]
    pub source: SynthOptions,
    /// Configuration: a `SlamConfig` file (`rgbid config dump --command slam`).
    #[command(flatten)]
    pub config: ConfigArgs,
    #[command(flatten)]
    pub odometry: OdometryOptions,
    #[command(flatten)]
    pub backend: BackendArgs,
}

/// Runs the subcommand.
pub fn run(a: Args) -> Result<()> {
    let mut source = a.source;
    let spec = source
        .synth
        .get_or_insert_with(|| SynthOptions::DEFAULT_SPEC.to_string())
        .clone();
    let (scene, trajectory) = spec.split_once(':').unwrap_or((spec.as_str(), "loop"));
    println!(
        "demo: RGB-ID SLAM on a generated '{scene}' scene, '{trajectory}' trajectory ({} laps), {} frames",
        source.laps, source.frames
    );
    crate::cli::slam::run(crate::cli::slam::Args {
        source,
        config: a.config,
        odometry: a.odometry,
        backend: a.backend,
        ..crate::cli::slam::Args::new(a.out)
    })
}
