//! `rgbid eval GT EST`: ATE and RPE of an estimated trajectory against ground truth (TUM, KITTI
//! or EuRoC files, detected), and a plot of both.

use std::path::PathBuf;

use anyhow::Context;
use rgbid::eval::{associate, evaluate, EvalOptions, RpeDelta, RpeResult, TrajectoryMetrics};
use rgbid::io::trajectory::read_trajectory;
use rgbid::trajectory::TimedPose;

use super::plot::{write_png, Panel, Series, BLUE, DARK};

/// Arguments of `rgbid eval`.
#[derive(clap::Args)]
pub struct Args {
    /// Ground-truth trajectory, `world_from_camera`: TUM, KITTI (with `times.txt` beside) or
    /// EuRoC CSV, detected from the file.
    pub gt: PathBuf,
    /// Estimated trajectory (any of the same formats).
    pub est: PathBuf,
    /// Seconds added to the estimate's time stamps before matching (a clock offset) (any finite number).
    #[arg(long, value_parser = crate::cli::options::range::finite, default_value_t = 0.0, allow_negative_numbers = true)]
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
    /// Output: a PNG with a top view of both trajectories (the estimate aligned as for the ATE)
    /// and the position error of each matched pose against time.
    #[arg(long, value_name = "PNG")]
    pub plot: Option<PathBuf>,
    /// The plane of the top view: the two world axes of the ground truth's largest extent
    /// (`auto`), or `xy`, `xz`, `yz`.
    #[arg(long, value_enum, default_value_t = Plane::Auto)]
    pub plot_plane: Plane,
}

/// The plane of `rgbid eval --plot`'s top view.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Plane {
    /// The two axes along which the ground truth extends most.
    Auto,
    /// x horizontal, y vertical.
    Xy,
    /// x horizontal, z vertical.
    Xz,
    /// y horizontal, z vertical.
    Yz,
}

impl Plane {
    /// Axis indices `(horizontal, vertical)`.
    fn axes(self, gt: &[TimedPose]) -> (usize, usize) {
        match self {
            Plane::Xy => (0, 1),
            Plane::Xz => (0, 2),
            Plane::Yz => (1, 2),
            Plane::Auto => {
                let extent = |k: usize| {
                    let v = gt.iter().map(|p| p.world_from_camera.translation[k]);
                    let (lo, hi) = v.fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), x| {
                        (a.min(x), b.max(x))
                    });
                    hi - lo
                };
                let mut k = [0usize, 1, 2];
                k.sort_by(|&a, &b| extent(b).total_cmp(&extent(a)));
                (k[0].min(k[1]), k[0].max(k[1]))
            }
        }
    }
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
    if let Some(path) = &args.plot {
        plot(path, &gt, &est, &m, args.max_diff, args.plot_plane)?;
    }
    if args.json {
        println!("{}", serde_json::to_string(&m)?);
        return Ok(());
    }
    print_metrics(&m, args.scale, args.delta);
    Ok(())
}

/// Writes the `--plot` figure: the top view of ground truth and aligned estimate, and the ATE
/// position error of each matched pose against time since the first match.
fn plot(
    path: &std::path::Path,
    gt: &[TimedPose],
    est: &[TimedPose],
    m: &TrajectoryMetrics,
    max_diff: f64,
    plane: Plane,
) -> anyhow::Result<()> {
    let sorted = |t: &[TimedPose]| {
        let mut v = t.to_vec();
        v.sort_by(|a, b| a.timestamp.total_cmp(&b.timestamp));
        v
    };
    let (gt, est) = (sorted(gt), sorted(est));
    let align = &m.ate.alignment;
    let (h, v) = plane.axes(&gt);
    let top = |p: glam::DVec3| (p[h], p[v]);
    let gt_xy: Vec<(f64, f64)> = gt
        .iter()
        .map(|p| top(p.world_from_camera.translation))
        .collect();
    let est_xy: Vec<(f64, f64)> = est
        .iter()
        .map(|p| top(align.apply(p.world_from_camera.translation)))
        .collect();
    let pairs = associate(&est, &gt, max_diff);
    let t0 = pairs.first().map_or(0.0, |&(_, j)| gt[j].timestamp);
    let errors: Vec<(f64, f64)> = pairs
        .iter()
        .map(|&(i, j)| {
            let e = align.apply(est[i].world_from_camera.translation)
                - gt[j].world_from_camera.translation;
            (gt[j].timestamp - t0, e.length())
        })
        .collect();
    let axis = |k: usize| format!("{} (m)", ["x", "y", "z"][k]);
    let series = |label: &str, points, color| Series {
        label: label.into(),
        points,
        color,
        dots: false,
    };
    let aligned = if m.ate.alignment.scale != 1.0 {
        "estimate (Sim(3)-aligned)"
    } else {
        "estimate (aligned)"
    };
    let panels = [
        Panel {
            title: format!("top view, {} matched poses", m.matched),
            x_label: axis(h),
            y_label: axis(v),
            series: vec![
                series("ground truth", gt_xy, DARK),
                series(aligned, est_xy, BLUE),
            ],
            equal_axes: true,
        },
        Panel {
            title: format!("position error, ATE rmse {:.4} m", m.ate.translation.rmse),
            x_label: "time since the first match (s)".into(),
            y_label: "error (m)".into(),
            series: vec![series("", errors, BLUE)],
            equal_axes: false,
        },
    ];
    write_png(path, &panels, (1, 2), (1600, 700))
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
