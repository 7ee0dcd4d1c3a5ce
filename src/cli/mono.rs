//! `rgbid mono`: monocular EKF SLAM (thesis ch. 2) on an image-only sequence or a generated
//! one; `--bench` prints ms/frame and per-stage medians, `--table21` the FI / Rm / Rf table
//! for warped vs plain patches at ZNCC thresholds 0.8 / 0.9 / 0.95.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{bail, Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use rgbid::camera::UnifiedCamera;
use rgbid::eval::ate::ate;
use rgbid::experiments::mono::{render, run as run_synthetic, SyntheticCamera, SyntheticSpec};
use rgbid::gpu::ComputeBackend;
use rgbid::io::trajectory::{read_tum, write_tum};
use rgbid::mono::{load_camera, FrameReport, ImageSequence, MonoConfig, MonoSlam, PatchMode};
use rgbid::trajectory::TimedPose;

use super::bench::median;
use super::options::{write_sidecar, ConfigArgs};

/// Patch modes of `--patch`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum PatchArg {
    /// Warped for the predicted view (catadioptric cameras).
    Warped,
    /// As seen at initialisation.
    Plain,
}

/// Synthetic cameras of `--synthetic`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum SynthArg {
    /// Pinhole (xi = 0).
    Pinhole,
    /// Catadioptric (xi = 0.9).
    Omni,
}

/// Arguments of `rgbid mono`.
#[derive(clap::Args)]
pub struct Args {
    /// Sequence folder: an EuRoC / TUM-VI camera folder (`data.csv`, `data/`, `sensor.yaml`;
    /// also as SEQ/cam0 or SEQ/mav0/cam0), rgb.txt (TUM style) or images named by their time
    /// stamp.
    seq: Option<PathBuf>,
    /// Camera file (JSON camera model as written by `rgbid synth`, or a line
    /// `xi gamma cx cy width height [fov_radius [inner_radius]]`); default: the folder's
    /// sensor.yaml (images resampled onto its undistorted camera), else SEQ/camera.json.
    #[arg(long)]
    camera: Option<PathBuf>,
    /// Output trajectory (TUM format, world_from_camera, filter world = first camera, scale
    /// unknown).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Patch mode (default: warped for xi > 0, plain for pinhole cameras).
    #[arg(long, value_enum)]
    patch: Option<PatchArg>,
    /// ZNCC threshold of a match, in (-1, 1) (`zncc_threshold`) [default: 0.8].
    #[arg(long, value_parser = crate::cli::options::range::open_signed_unit)]
    zncc: Option<f64>,
    /// Landmarks the system keeps predicted visible (`target_visible`); >= 1 [default: 40].
    #[arg(long, value_parser = crate::cli::options::range::at_least_one)]
    target_visible: Option<usize>,
    /// Most landmarks in the filter state, at least --target-visible (`max_landmarks`)
    /// [default: 120].
    #[arg(long, value_parser = crate::cli::options::range::at_least_one)]
    max_landmarks: Option<usize>,
    /// Initial inverse depth of new landmarks, 1/m; sets the map's nominal scale
    /// (`initial_inverse_depth`); > 0 [default: 0.5].
    #[arg(long, value_parser = crate::cli::options::range::positive)]
    inverse_depth: Option<f64>,
    /// Configuration: a `MonoConfig` file (`rgbid config dump --command mono`).
    #[command(flatten)]
    config: ConfigArgs,
    /// Run on a generated sequence (in memory, CPU renderer) instead of SEQ and report the
    /// Sim(3)-aligned error against its ground truth.
    #[arg(long, value_enum)]
    synthetic: Option<SynthArg>,
    /// Frames of the synthetic sequence (>= 1).
    #[arg(long, value_parser = crate::cli::options::range::at_least_one, default_value_t = 150)]
    frames: usize,
    /// Synthetic image width (default 320 pinhole, 400 omni) (16 to 16384 pixels).
    #[arg(long, value_parser = crate::cli::options::range::image_side)]
    width: Option<u32>,
    /// Synthetic image height (default 240 pinhole, 400 omni) (16 to 16384 pixels).
    #[arg(long, value_parser = crate::cli::options::range::image_side)]
    height: Option<u32>,
    /// Synthetic scene preset.
    #[arg(long, default_value = "office")]
    scene: String,
    /// Synthetic trajectory.
    #[arg(long, default_value = "handheld")]
    trajectory: String,
    /// Seed of the synthetic sequence (any whole number, 0 to 2^64-1).
    #[arg(long, value_parser = crate::cli::options::range::seed, default_value_t = 7)]
    seed: u64,
    /// Print the median ms/frame and per-stage medians.
    #[arg(long)]
    bench: bool,
    /// Print the thesis' table 2.1 (FI, Rm, Rf, ATE) for warped vs plain patches at ZNCC
    /// thresholds 0.8 / 0.9 / 0.95 on a synthetic catadioptric sequence.
    #[arg(long)]
    table21: bool,
}

fn progress(len: usize, what: &str) -> ProgressBar {
    let bar = ProgressBar::new(len as u64);
    if let Ok(style) = ProgressStyle::with_template(
        "{msg} [{elapsed_precise}] {wide_bar} {pos}/{len} ({per_sec}, eta {eta})",
    ) {
        bar.set_style(style);
    }
    bar.set_message(what.to_string());
    bar
}

/// The configuration: defaults (patch mode by the camera), `--config`, the flags, `--set`.
fn config(args: &Args, camera: &UnifiedCamera) -> Result<MonoConfig> {
    let base = MonoConfig {
        patch_mode: if camera.xi > 0.0 {
            PatchMode::Warped
        } else {
            PatchMode::Plain
        },
        ..MonoConfig::default()
    };
    let cfg = args.config.resolve(base, |c| {
        match args.patch {
            Some(PatchArg::Warped) => c.patch_mode = PatchMode::Warped,
            Some(PatchArg::Plain) => c.patch_mode = PatchMode::Plain,
            None => {}
        }
        if let Some(v) = args.zncc {
            c.zncc_threshold = v;
        }
        if let Some(v) = args.target_visible {
            c.target_visible = v;
            c.max_landmarks = c.max_landmarks.max(v);
        }
        if let Some(v) = args.max_landmarks {
            c.max_landmarks = v.max(c.target_visible);
        }
        if let Some(v) = args.inverse_depth {
            c.initial_inverse_depth = v;
        }
        Ok(())
    })?;
    cfg.validate()?;
    Ok(cfg)
}

fn synthetic_spec(args: &Args, kind: SynthArg) -> SyntheticSpec {
    let (camera, w, h) = match kind {
        SynthArg::Pinhole => (SyntheticCamera::Pinhole, 320, 240),
        SynthArg::Omni => (SyntheticCamera::Catadioptric, 400, 400),
    };
    let mut spec = SyntheticSpec::new(
        camera,
        args.width.unwrap_or(w),
        args.height.unwrap_or(h),
        args.frames,
    );
    spec.scene = args.scene.clone();
    spec.trajectory = args.trajectory.clone();
    spec.seed = args.seed;
    spec
}

/// Runs the subcommand.
pub fn run(args: Args) -> Result<()> {
    if args.table21 {
        return table21(&args);
    }
    if let Some(kind) = args.synthetic {
        return synthetic(&args, kind);
    }
    let Some(seq_dir) = args.seq.clone() else {
        bail!("give a sequence folder SEQ (or --synthetic pinhole|omni, or --table21)");
    };
    let seq = ImageSequence::open(&seq_dir)?;
    let camera = match (&args.camera, seq.camera) {
        (Some(path), Some(_)) => bail!(
            "{} has a sensor.yaml whose camera its images are resampled onto; --camera {} \
             would disagree with them (remove one of the two)",
            seq_dir.display(),
            path.display()
        ),
        (Some(path), None) => {
            load_camera(path).with_context(|| format!("camera file {}", path.display()))?
        }
        (None, Some(camera)) => camera,
        (None, None) => {
            let path = seq_dir.join("camera.json");
            load_camera(&path).with_context(|| format!("camera file {}", path.display()))?
        }
    };
    let cfg = config(&args, &camera)?;
    let mut slam = MonoSlam::new(camera, cfg.clone())?;
    let bar = progress(seq.len(), "mono");
    let mut reports = Vec::with_capacity(seq.len());
    let mut load_ms = Vec::with_capacity(seq.len());
    for i in 0..seq.len() {
        let t0 = Instant::now();
        let Some(frame) = seq.load(i) else { break };
        let (t, img) = frame?;
        load_ms.push(t0.elapsed().as_secs_f64() * 1e3);
        reports.push(slam.process(t, &img)?);
        bar.inc(1);
    }
    bar.finish_and_clear();
    let estimate: Vec<TimedPose> = reports
        .iter()
        .map(|r| TimedPose {
            timestamp: r.timestamp,
            world_from_camera: r.world_from_camera,
        })
        .collect();
    if let Some(out) = &args.out {
        write_tum(out, &estimate)?;
        write_sidecar(out, &cfg, &ComputeBackend::Cpu)?;
        println!("wrote {} poses to {}", estimate.len(), out.display());
    }
    summary(&reports, &slam, cfg.patch_mode);
    let gt_path = seq_dir.join("groundtruth.txt");
    if gt_path.is_file() {
        let gt = read_tum(&gt_path)?;
        let pairs = rgbid::eval::associate(&estimate, &gt, 0.02);
        let e: Vec<TimedPose> = pairs.iter().map(|p| estimate[p.0]).collect();
        let g: Vec<TimedPose> = pairs.iter().map(|p| gt[p.1]).collect();
        match ate(&g, &e, true) {
            Ok(a) => println!(
                "ATE after Sim(3) alignment ({} poses): rmse {:.4} m, median {:.4} m, scale {:.4}",
                pairs.len(),
                a.translation.rmse,
                a.translation.median,
                a.alignment.scale
            ),
            Err(e) => println!("ATE not computed: {e}"),
        }
    }
    if args.bench {
        print_bench(&reports, Some(&mut load_ms));
    }
    Ok(())
}

fn summary(reports: &[FrameReport], slam: &MonoSlam, mode: PatchMode) {
    let s = slam.stats();
    let n = reports.len().max(1) as f64;
    let avg = |f: fn(&FrameReport) -> usize| reports.iter().map(|r| f(r) as f64).sum::<f64>() / n;
    println!(
        "{} frames, patch {:?}: visible {:.1}, matched {:.1}, inliers {:.1} + rescued {:.1} per frame; \
         FI {}, Rm {:.2}, Rf {:.3}, fixed map {} points, {} rays dropped",
        reports.len(),
        mode,
        avg(|r| r.visible),
        avg(|r| r.matched),
        avg(|r| r.inliers),
        avg(|r| r.rescued),
        s.features_initialised,
        s.rm(),
        s.rf(slam.points_in_state()),
        slam.fixed_map().len(),
        s.rays_dropped
    );
}

fn print_bench(reports: &[FrameReport], load_ms: Option<&mut Vec<f64>>) {
    // The first frame only initialises features; leave it out.
    let r = if reports.len() > 1 {
        &reports[1..]
    } else {
        reports
    };
    let col = |f: fn(&FrameReport) -> f64| {
        let mut v: Vec<f64> = r.iter().map(f).collect();
        median(&mut v)
    };
    println!(
        "ms/frame (median over {} frames): total {:.2} | predict {:.3}, search {:.2}, ransac {:.2}, update {:.2}, manage {:.2}{}",
        r.len(),
        col(|x| x.times.total()),
        col(|x| x.times.predict),
        col(|x| x.times.search),
        col(|x| x.times.ransac),
        col(|x| x.times.update),
        col(|x| x.times.manage),
        load_ms.map_or(String::new(), |v| format!(" (+ image loading {:.2})", median(v)))
    );
    println!(
        "tracked per frame (median): visible {:.0}, matched {:.0}, landmarks in state {:.0}; \
         max ms/frame {:.2}; threads {}",
        col(|x| x.visible as f64),
        col(|x| (x.inliers + x.rescued) as f64),
        col(|x| x.landmarks as f64),
        r.iter().map(|x| x.times.total()).fold(0.0, f64::max),
        rayon::current_num_threads()
    );
}

fn synthetic(args: &Args, kind: SynthArg) -> Result<()> {
    let spec = synthetic_spec(args, kind);
    let t0 = Instant::now();
    let frames = render(&spec)?;
    println!(
        "rendered {} frames {}x{} ({:?}, {} / {}) in {:.1} s",
        spec.frames,
        spec.width,
        spec.height,
        spec.camera,
        spec.scene,
        spec.trajectory,
        t0.elapsed().as_secs_f64()
    );
    let cfg = config(args, &frames.camera)?;
    let r = run_synthetic(&frames, &cfg)?;
    if let Some(out) = &args.out {
        write_tum(out, &r.estimate)?;
        write_sidecar(out, &cfg, &ComputeBackend::Cpu)?;
        println!("wrote {} poses to {}", r.estimate.len(), out.display());
    }
    let n = r.reports.len().max(1) as f64;
    println!(
        "patch {:?}, zncc {}: path {:.2} m; ATE after Sim(3) alignment rmse {:.4} m ({:.2} % of the path), \
         median {:.4} m, scale {:.3}; FI {}, Rm {:.2}, Rf {:.3}; matched/frame {:.1}",
        cfg.patch_mode,
        cfg.zncc_threshold,
        r.path_length,
        r.ate.translation.rmse,
        100.0 * r.ate.translation.rmse / r.path_length.max(1e-12),
        r.ate.translation.median,
        r.ate.alignment.scale,
        r.stats.features_initialised,
        r.stats.rm(),
        r.stats.rf(r.points_in_state),
        r.reports
            .iter()
            .map(|x| (x.inliers + x.rescued) as f64)
            .sum::<f64>()
            / n
    );
    if args.bench {
        print_bench(&r.reports, None);
    }
    Ok(())
}

fn table21(args: &Args) -> Result<()> {
    let spec = synthetic_spec(args, args.synthetic.unwrap_or(SynthArg::Omni));
    let t0 = Instant::now();
    let frames = render(&spec)?;
    println!(
        "table 2.1 on a synthetic {:?} sequence: {} frames {}x{}, {} / {}, seed {} (rendered in {:.1} s)",
        spec.camera,
        spec.frames,
        spec.width,
        spec.height,
        spec.scene,
        spec.trajectory,
        spec.seed,
        t0.elapsed().as_secs_f64()
    );
    println!(
        "FI = features initialised, Rm = matches per feature, Rf = 3D map features per feature"
    );
    println!(
        "{:<8} {:>6} {:>6} {:>7} {:>7} {:>10} {:>8}",
        "patch", "zncc", "FI", "Rm", "Rf", "ATE [m]", "ms/frame"
    );
    let base = config(args, &frames.camera)?;
    let bar = progress(6, "table 2.1");
    let mut rows = Vec::new();
    for zncc in [0.8, 0.9, 0.95] {
        for mode in [PatchMode::Warped, PatchMode::Plain] {
            let cfg = MonoConfig {
                patch_mode: mode,
                zncc_threshold: zncc,
                ..base.clone()
            };
            let line = match run_synthetic(&frames, &cfg) {
                Ok(r) => {
                    let mut t: Vec<f64> =
                        r.reports.iter().skip(1).map(|x| x.times.total()).collect();
                    format!(
                        "{:<8} {:>6.2} {:>6} {:>7.2} {:>7.3} {:>10.4} {:>8.2}",
                        format!("{mode:?}").to_lowercase(),
                        zncc,
                        r.stats.features_initialised,
                        r.stats.rm(),
                        r.stats.rf(r.points_in_state),
                        r.ate.translation.rmse,
                        median(&mut t)
                    )
                }
                Err(e) => format!(
                    "{:<8} {:>6.2} failed: {e}",
                    format!("{mode:?}").to_lowercase(),
                    zncc
                ),
            };
            rows.push(line);
            bar.inc(1);
        }
    }
    bar.finish_and_clear();
    for r in rows {
        println!("{r}");
    }
    Ok(())
}
