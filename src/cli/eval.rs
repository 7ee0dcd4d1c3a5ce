//! `rgbid eval GT EST`: ATE and RPE of an estimated trajectory against ground truth (TUM, KITTI
//! or EuRoC files, detected).

use std::path::PathBuf;

use anyhow::Context;
use rgbid::eval::{evaluate, EvalOptions, RpeDelta, RpeResult};
use rgbid::io::trajectory::read_trajectory;
use rgbid::trajectory::TimedPose;

/// Arguments of `rgbid eval`.
#[derive(clap::Args)]
pub struct Args {
    /// Ground-truth trajectory, `world_from_camera`: TUM, KITTI (with `times.txt` beside) or
    /// EuRoC CSV, detected from the file.
    pub gt: PathBuf,
    /// Estimated trajectory (any of the same formats).
    pub est: PathBuf,
    /// Seconds added to the estimate's time stamps before matching (a clock offset).
    #[arg(long, default_value_t = 0.0, allow_negative_numbers = true)]
    pub t_offset: f64,
    /// Print one JSON line instead of a table.
    #[arg(long)]
    pub json: bool,
    /// Largest time difference of a matched pose pair, seconds, > 0.
    #[arg(long, value_parser = crate::cli::options::range::positive, default_value_t = 0.02)]
    pub max_diff: f64,
    /// RPE interval, seconds, > 0.
    #[arg(long, value_parser = crate::cli::options::range::positive, default_value_t = 1.0)]
    pub delta: f64,
    /// Align with a similarity (estimate scale too), for monocular trajectories.
    #[arg(long)]
    pub scale: bool,
}

/// Runs the subcommand.
pub fn run(args: Args) -> anyhow::Result<()> {
    if !args.t_offset.is_finite() {
        anyhow::bail!("--t-offset must be a finite number of seconds");
    }
    let gt = read_trajectory(&args.gt).context("reading ground truth")?;
    let mut est = read_trajectory(&args.est).context("reading estimate")?;
    for p in &mut est {
        p.timestamp += args.t_offset;
    }
    let opts = EvalOptions {
        max_time_difference: args.max_diff,
        delta: RpeDelta::Seconds(args.delta),
        with_scale: args.scale,
    };
    let m = evaluate(&gt, &est, &opts)?;
    if args.json {
        println!("{}", serde_json::to_string(&m)?);
        return Ok(());
    }
    print_metrics(&m, args.scale, args.delta);
    Ok(())
}

/// Reads two TUM trajectories and prints ATE / RPE with the default options.
pub fn print_against(g: &[TimedPose], est: &std::path::Path) -> anyhow::Result<()> {
    let e = read_trajectory(est).with_context(|| format!("reading estimate {}", est.display()))?;
    let m = evaluate(g, &e, &EvalOptions::default())?;
    print_metrics(&m, false, 1.0);
    Ok(())
}

/// Prints the metrics table.
pub fn print_metrics(m: &rgbid::eval::TrajectoryMetrics, scale: bool, delta: f64) {
    let a = &m.ate.translation;
    println!(
        "matched poses      {} of {} estimated ({} ground truth)",
        m.matched, m.est_poses, m.gt_poses
    );
    println!(
        "path length        {:.3} m over {:.2} s",
        m.path_length_m, m.duration_s
    );
    if scale {
        println!("alignment scale    {:.6}", m.ate.alignment.scale);
    }
    println!(
        "{:<18} {:>10} {:>10} {:>10} {:>10} {:>6}",
        "metric", "rmse", "mean", "median", "max", "n"
    );
    println!(
        "{:<18} {:>10.6} {:>10.6} {:>10.6} {:>10.6} {:>6}",
        "ATE m", a.rmse, a.mean, a.median, a.max, a.count
    );
    let rows = |name: &str, r: &Option<RpeResult>| {
        if let Some(r) = r {
            for (unit, s) in [
                ("m", &r.translation_m),
                ("deg", &r.rotation_deg),
                ("m/s", &r.translation_m_per_s),
                ("deg/s", &r.rotation_deg_per_s),
            ] {
                let label = format!("{name} {unit}");
                println!(
                    "{label:<18} {:>10.6} {:>10.6} {:>10.6} {:>10.6} {:>6}",
                    s.rmse, s.mean, s.median, s.max, s.count
                );
            }
        } else {
            println!("{name:<18} no pose pairs span the interval");
        }
    };
    rows(&format!("RPE {delta}s"), &m.rpe);
    rows("RPE 1fr", &m.rpe_frame);
}
