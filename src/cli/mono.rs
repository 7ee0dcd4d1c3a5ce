//! `rgbid mono`: monocular EKF SLAM (thesis ch. 2) on an image-only sequence or a generated
//! one; `--bench` prints ms/frame and per-stage medians, `--table21` the FI / Rm / Rf table
//! for every patch mode at ZNCC thresholds 0.8 / 0.9 / 0.95.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use rgbid::camera::UnifiedCamera;
use rgbid::eval::ate::ate;
use rgbid::experiments::mono::{
    loops as synthetic_loops, render, run as run_synthetic, LoopTruth, SyntheticCamera,
    SyntheticSpec,
};
use rgbid::experiments::patches::{run_patch_sweeps, PatchSweepSpec};
use rgbid::gpu::ComputeBackend;
use rgbid::image::ImageF32;
use rgbid::io::trajectory::{read_tum, write_tum};
use rgbid::mono::{
    load_camera, FrameReport, ImageSequence, LoopScaleParams, LoopingMono, MetricMono, MonoConfig,
    MonoLoopParams, MonoSlam, PatchMode,
};
use rgbid::place::Vocabulary;
use rgbid::scale::{
    arc_length_error_from_start, time_matched_error_from_start, DynScaleConfig, WalkingModel,
};
use rgbid::trajectory::TimedPose;

use super::bench::median;
use super::options::{write_sidecar, ConfigArgs};

/// Patch modes of `--patch`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum PatchArg {
    /// Rotated by the change of polar angle, scaled by the ratio of the mirror's local
    /// magnifications times the estimated distance ratio.
    Warped,
    /// Rotated, scaled by the ratio of projected image lengths from r_im- (thesis eq.
    /// 2.63-2.67), the distance ratio only once the depth has converged.
    Thesis,
    /// As thesis, with separate radial and tangential scales.
    Anisotropic,
    /// Each pixel carried through the predicted relative pose onto the plane through the
    /// feature perpendicular to its first ray (at infinity until its depth has converged).
    Projective,
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
    /// Output trajectory (TUM format, world_from_camera, filter world = first camera). Scale
    /// unknown, or metres with --walker-height (then the EKF's own trajectory goes to
    /// NAME_unscaled.txt and each frame's causal metric pose to NAME_causal.txt beside it;
    /// with --synthetic also the ground truth, to NAME_groundtruth.txt). With --walker-height
    /// and --loops: the loop-corrected metric trajectory, the one without loops (dynScale
    /// alone) to NAME_dynscale.txt, and each frame's causal pose corrected by the loops found
    /// up to it to NAME_causal_loops.txt.
    #[arg(long)]
    out: Option<PathBuf>,
    /// Height of the person wearing the camera, metres, in (0, 3]: runs the metric scale
    /// estimation from the step frequency (thesis 3.4, Algorithm 1) beside the filter, with
    /// the up axis found online and the `rgbid scale` defaults for everything else; reports
    /// the eq. 3.36 errors when there is ground truth.
    #[arg(long, value_parser = crate::cli::options::range::walker_height)]
    walker_height: Option<f64>,
    /// With --walker-height: a JSON report of the run (errors, sections, per-frame times;
    /// `scripts/mono_walks.sh` collects them into docs/results).
    #[arg(long, requires = "walker_height")]
    json: Option<PathBuf>,
    /// Patch mode (default: projective for xi > 0, plain for pinhole cameras; chosen by
    /// `scripts/mono_patch_modes.sh`).
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
    /// Detect loops from the images (thesis 3.3.2): keyframes from the filter stream (when
    /// fewer than half of the landmarks tracked at the last keyframe are still tracked, at most
    /// 2 s and at least 0.25 s apart), ORB + bag of words (the embedded vocabulary) with the
    /// mirror's blind areas masked, candidates at least 10 s older than the query, and an
    /// essential matrix fitted by RANSAC to the matched bearings (0.01 rad). Prints the loops;
    /// with --synthetic also precision and recall against the ground truth (a true loop: true
    /// camera positions within 1.5 m, optical axes within 90 degrees). With --walker-height:
    /// each loop's relative similarity (the scale ratio of eq. 3.10 from the keyframes' local
    /// triangulations) corrects the metric trajectory through optimSim3 with the walking scale
    /// of each section as a prior, and the eq. 3.36 errors are reported with and without it.
    #[arg(long, conflicts_with = "table21")]
    loops: bool,
    /// With --loops: a JSON report (loops, every keyframe's candidates and checks, and with
    /// --synthetic precision / recall over a grid of thresholds). Not with --walker-height,
    /// whose --json report has the loops' figures.
    #[arg(long, requires = "loops", conflicts_with = "walker_height")]
    loops_json: Option<PathBuf>,
    /// With --loops: smallest normalised bag-of-words score (score against the candidate over
    /// score against the previous keyframe) of a candidate that is verified, >= 0 [default: 0.3].
    #[arg(long, requires = "loops", value_parser = crate::cli::options::range::non_negative)]
    loop_score: Option<f64>,
    /// With --loops: fewest essential-matrix inliers of a verified loop, >= 8 [default: 30].
    #[arg(long, requires = "loops", value_parser = crate::cli::options::range::at_least_eight)]
    loop_inliers: Option<usize>,
    /// With --loops and --walker-height: seconds over which the online output
    /// (NAME_causal_loops.txt) moves to a new loop's correction instead of jumping to it,
    /// >= 0 (0 = at once).
    #[arg(long, requires = "loops", requires = "walker_height", value_parser = crate::cli::options::range::non_negative, default_value_t = LoopScaleParams::default().correction_blend)]
    loop_blend: f64,
    /// Print the thesis' table 2.1 (FI, Rm, Rf, ATE) for every patch mode (plain, warped,
    /// thesis, anisotropic, projective) at ZNCC thresholds 0.8 / 0.9 / 0.95 on a synthetic
    /// catadioptric sequence.
    #[arg(long)]
    table21: bool,
    /// The decoupled matching experiment of thesis 2.6.1 (figs. 2.8-2.12), written as JSON to
    /// this file: features of a generated catadioptric image (--scene, --seed, --width,
    /// --height [default 400 x 400]) found again after a rotation about the vertical (0-180
    /// degrees), a translation along the floor (0-2 m) and a change of distance (factors
    /// 0.5-2), by ZNCC in a 13 x 13 pixel window around the true projection, with every patch
    /// mode; prints the share within 1 / 2 pixels of the truth per step.
    #[arg(long, conflicts_with_all = ["table21", "loops", "walker_height"])]
    patch_sweeps: Option<PathBuf>,
    /// Seconds of input (frame time stamps) between checkpoints on a sequence folder: with
    /// --out, the trajectory so far (the --out file; with --walker-height NAME_unscaled.txt,
    /// NAME_causal.txt and with --loops NAME_causal_loops.txt) is replaced atomically, so a
    /// run killed later leaves it readable.
    /// Ctrl-C (or SIGTERM) stops reading frames and writes every output; a second one exits
    /// at once with the last checkpoint's files; > 0 [default: 5].
    #[arg(long, value_parser = crate::cli::options::range::positive, default_value_t = super::outputs::CHECKPOINT_EVERY_S)]
    checkpoint_every: f64,
}

/// A frame loop over a sequence that keeps what it computed whatever stops it: an unreadable
/// frame is skipped and counted (when most frames are, the run stops), Ctrl-C stops reading,
/// and an error of the filter stops the run; in each case the frames processed so far have
/// their outputs written before the cause is returned (see [`FrameLoop::end`]).
struct FrameLoop {
    stop: super::outputs::Stop,
    skips: super::outputs::Skips,
    checkpoints: super::outputs::Checkpoints,
    error: Option<anyhow::Error>,
    interrupted: bool,
    processed: usize,
}

impl FrameLoop {
    fn new(args: &Args) -> Result<Self> {
        Ok(FrameLoop {
            stop: super::outputs::Stop::install(|| {})?,
            skips: super::outputs::Skips::default(),
            checkpoints: super::outputs::Checkpoints::new(args.checkpoint_every),
            error: None,
            interrupted: false,
            processed: 0,
        })
    }

    /// The next usable frame `(index, time stamp, image)`, or `None` when the input ended,
    /// a stop was asked for, or too many frames could not be read.
    fn next<I>(&mut self, frames: &mut I, bar: &ProgressBar) -> Option<(usize, f64, ImageF32)>
    where
        I: Iterator<Item = (usize, Result<(f64, ImageF32), rgbid::mono::MonoError>)>,
    {
        if self.error.is_some() {
            return None;
        }
        for (i, frame) in frames.by_ref() {
            if self.stop.requested() {
                self.interrupted = true;
                return None;
            }
            match frame {
                Ok((t, img)) => return Some((i, t, img)),
                Err(e) => {
                    bar.inc(1);
                    if let Some(fatal) = self.skips.skip(i, e.into()) {
                        self.error = Some(fatal);
                        return None;
                    }
                }
            }
        }
        None
    }

    /// A frame stamped `t` (seconds) was processed; whether a checkpoint is due.
    fn done(&mut self, t: f64, bar: &ProgressBar) -> bool {
        self.processed += 1;
        bar.inc(1);
        self.checkpoints.due(t)
    }

    /// The filter failed on frame `i` (time stamp `t`): the run stops there.
    fn failed(&mut self, i: usize, t: f64, e: rgbid::mono::MonoError) {
        self.error = Some(anyhow::Error::new(e).context(format!("frame {i} ({t:.3} s)")));
    }

    /// Writes a checkpoint; a failure keeps the previous one and is logged, not fatal.
    fn checkpoint(files: &[(PathBuf, &[TimedPose])]) {
        for (path, poses) in files {
            if let Err(e) = write_tum(path, poses) {
                log::warn!(
                    "checkpoint of {} failed (its previous checkpoint is kept): {e}",
                    path.display()
                );
            }
        }
    }

    /// After every output was written: the error that stopped the run (saying where the
    /// frames before it went), the interruption (exit code 130), or `warnings` with the
    /// skipped frames' warning (exit code 3 when there are any).
    fn end(self, out: Option<&Path>, mut warnings: Vec<String>) -> Result<()> {
        if let Some(e) = self.error {
            return Err(match out {
                Some(o) if self.processed > 0 => e.context(format!(
                    "the {} frames processed before the error are in {} (and the files \
                     beside it)",
                    self.processed,
                    o.display()
                )),
                _ => e,
            });
        }
        if self.interrupted {
            return Err(super::outcome::Interrupted {
                out: out.map(Path::to_path_buf),
            }
            .into());
        }
        warnings.extend(self.skips.warning());
        super::outcome::warnings(warnings)
    }
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
            PatchMode::Projective
        } else {
            PatchMode::Plain
        },
        ..MonoConfig::default()
    };
    let cfg = args.config.resolve(base, |c| {
        match args.patch {
            Some(PatchArg::Warped) => c.patch_mode = PatchMode::Warped,
            Some(PatchArg::Thesis) => c.patch_mode = PatchMode::Thesis,
            Some(PatchArg::Anisotropic) => c.patch_mode = PatchMode::Anisotropic,
            Some(PatchArg::Projective) => c.patch_mode = PatchMode::Projective,
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
    if let Some(json) = &args.json {
        let inputs: Vec<&Path> = args.seq.iter().map(PathBuf::as_path).collect();
        super::outputs::output_file(json, "--json", &inputs)?;
    }
    if let Some(json) = &args.loops_json {
        let inputs: Vec<&Path> = args.seq.iter().map(PathBuf::as_path).collect();
        super::outputs::output_file(json, "--loops-json", &inputs)?;
    }
    if let Some(out) = &args.out {
        let inputs: Vec<&Path> = args.seq.iter().map(PathBuf::as_path).collect();
        super::outputs::output_file(out, "--out", &inputs)?;
        if args.walker_height.is_some() {
            for suffix in [
                "unscaled",
                "causal",
                "causal_loops",
                "groundtruth",
                "dynscale",
            ] {
                super::outputs::output_file(&beside(out, suffix), "--out", &inputs)?;
            }
        }
    }
    if args.table21 {
        return table21(&args);
    }
    if let Some(path) = &args.patch_sweeps {
        super::outputs::output_file(path, "--patch-sweeps", &[])?;
        return patch_sweeps(&args, path);
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
    if let Some(height) = args.walker_height {
        let gt_path = seq_dir.join("groundtruth.txt");
        let gt = if gt_path.is_file() {
            Some(read_tum(&gt_path)?)
        } else {
            None
        };
        let frames = (0..seq.len()).map_while(|i| seq.load(i).map(|f| (i, f)));
        return metric(
            &args,
            camera,
            &cfg,
            height,
            seq.len(),
            frames,
            gt.as_deref(),
        );
    }
    if args.loops {
        let frames = (0..seq.len()).map_while(|i| seq.load(i).map(|f| (i, f)));
        return loops_on_sequence(&args, camera, &cfg, seq.len(), frames);
    }
    let mut slam = MonoSlam::new(camera, cfg.clone())?;
    let bar = progress(seq.len(), "mono");
    let mut reports = Vec::with_capacity(seq.len());
    let mut estimate: Vec<TimedPose> = Vec::with_capacity(seq.len());
    let mut load_ms = Vec::with_capacity(seq.len());
    let mut run = FrameLoop::new(&args)?;
    let mut t0 = Instant::now();
    let mut frames = (0..seq.len()).map_while(|i| seq.load(i).map(|f| (i, f)));
    while let Some((i, t, img)) = run.next(&mut frames, &bar) {
        load_ms.push(t0.elapsed().as_secs_f64() * 1e3);
        match slam.process(t, &img) {
            Ok(r) => {
                estimate.push(TimedPose {
                    timestamp: r.timestamp,
                    world_from_camera: r.world_from_camera,
                });
                reports.push(r);
            }
            Err(e) => {
                run.failed(i, t, e);
                break;
            }
        }
        if let (true, Some(out)) = (run.done(t, &bar), &args.out) {
            FrameLoop::checkpoint(&[(out.clone(), &estimate)]);
        }
        t0 = Instant::now();
    }
    bar.finish_and_clear();
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
    run.end(args.out.as_deref(), Vec::new())
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
    if let Some(height) = args.walker_height {
        let images = frames
            .images
            .iter()
            .enumerate()
            .map(|(i, (t, img))| (i, Ok((*t, img.clone()))));
        return metric(
            args,
            frames.camera,
            &cfg,
            height,
            frames.images.len(),
            images,
            Some(&frames.ground_truth),
        );
    }
    if args.loops {
        return loops_synthetic(args, &spec, &frames, &cfg);
    }
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

fn patch_sweeps(args: &Args, path: &Path) -> Result<()> {
    let spec = PatchSweepSpec {
        width: args.width.unwrap_or(400),
        height: args.height.unwrap_or(400),
        scene: args.scene.clone(),
        seed: args.seed,
        ..PatchSweepSpec::default()
    };
    let t0 = Instant::now();
    let report = run_patch_sweeps(&spec)?;
    println!(
        "decoupled matching (thesis 2.6.1): {} features of a {}x{} {} image (seed {}), {:.1} s",
        report.reference_features,
        spec.width,
        spec.height,
        spec.scene,
        spec.seed,
        t0.elapsed().as_secs_f64()
    );
    println!(
        "{:<12} {:>7} {:<12} {:>5} {:>7} {:>7} {:>9} {:>7}",
        "sweep", "step", "patch", "n", "<=1px%", "<=2px%", "matched%", "zncc"
    );
    for r in &report.rows {
        println!(
            "{:<12} {:>7.3} {:<12} {:>5} {:>7.1} {:>7.1} {:>9.1} {:>7.3}",
            r.sweep,
            r.step,
            r.mode,
            r.features,
            r.within_1px_pct,
            r.within_2px_pct,
            r.matched_pct,
            r.mean_score
        );
    }
    super::report::write(
        path,
        "patch-sweeps",
        &super::report::meta(Vec::new()),
        &report,
    )?;
    println!("wrote {}", path.display());
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
        "{:<11} {:>6} {:>6} {:>7} {:>7} {:>10} {:>8}",
        "patch", "zncc", "FI", "Rm", "Rf", "ATE [m]", "ms/frame"
    );
    let base = config(args, &frames.camera)?;
    let modes = [
        PatchMode::Plain,
        PatchMode::Warped,
        PatchMode::Thesis,
        PatchMode::Anisotropic,
        PatchMode::Projective,
    ];
    let zncc_thresholds = [0.8, 0.9, 0.95];
    let bar = progress(modes.len() * zncc_thresholds.len(), "table 2.1");
    let mut rows = Vec::new();
    for zncc in zncc_thresholds {
        for mode in modes {
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
                        "{:<11} {:>6.2} {:>6} {:>7.2} {:>7.3} {:>10.4} {:>8.2}",
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
                    "{:<11} {:>6.2} failed: {e}",
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

/// `path` with `_suffix` added to its file stem (`traj.txt` -> `traj_unscaled.txt`).
fn beside(path: &Path, suffix: &str) -> PathBuf {
    let stem = path.file_stem().map_or_else(
        || "trajectory".to_string(),
        |s| s.to_string_lossy().into_owned(),
    );
    let ext = path
        .extension()
        .map_or(String::new(), |e| format!(".{}", e.to_string_lossy()));
    path.with_file_name(format!("{stem}_{suffix}{ext}"))
}

/// `--walker-height`: the filter with the metric scale estimation beside it.
fn metric<I>(
    args: &Args,
    camera: UnifiedCamera,
    cfg: &MonoConfig,
    height: f64,
    len: usize,
    frames: I,
    gt: Option<&[TimedPose]>,
) -> Result<()>
where
    I: Iterator<Item = (usize, Result<(f64, ImageF32), rgbid::mono::MonoError>)>,
{
    let scale_cfg = DynScaleConfig {
        model: WalkingModel {
            height,
            ..super::scale::defaults().model
        },
        ..super::scale::defaults()
    };
    let loop_params = if args.loops {
        Some(loop_params(args)?)
    } else {
        None
    };
    let mut system = match &loop_params {
        Some(p) => MetricMono::with_loops(
            camera,
            cfg.clone(),
            scale_cfg.clone(),
            Vocabulary::embedded_default()?,
            p.clone(),
            LoopScaleParams {
                correction_blend: args.loop_blend,
                ..LoopScaleParams::default()
            },
        )?,
        None => MetricMono::new(camera, cfg.clone(), scale_cfg.clone())?,
    };
    let bar = progress(len, "mono + scale");
    let (mut ekf_ms, mut scale_ms) = (Vec::with_capacity(len), Vec::with_capacity(len));
    let mut keyframe_ms = Vec::new();
    let mut first_scaled = None;
    let mut frame_loop = FrameLoop::new(args)?;
    let mut frames = frames;
    while let Some((i, t, img)) = frame_loop.next(&mut frames, &bar) {
        let r = match system.process(t, &img) {
            Ok(r) => r,
            Err(e) => {
                frame_loop.failed(i, t, e);
                break;
            }
        };
        ekf_ms.push(r.report.times.total());
        scale_ms.push(r.scale_ms);
        if r.keyframe.is_some() {
            keyframe_ms.push(r.loop_ms);
        }
        if first_scaled.is_none() && r.metric.is_some() {
            first_scaled = Some(t);
        }
        if let (true, Some(out)) = (frame_loop.done(t, &bar), &args.out) {
            let mut files = vec![
                (beside(out, "unscaled"), system.unscaled()),
                (beside(out, "causal"), system.causal()),
            ];
            if args.loops {
                files.push((beside(out, "causal_loops"), system.causal_looped()));
            }
            FrameLoop::checkpoint(&files);
        }
    }
    bar.finish_and_clear();
    let run = system.finish();
    // The first frame only initialises features; leave it out of the timing.
    let (ekf, sc) = (
        median(&mut ekf_ms[1.min(ekf_ms.len())..].to_vec()),
        median(&mut scale_ms[1.min(scale_ms.len())..].to_vec()),
    );
    println!(
        "ms/frame (median): filter {ekf:.3}, scale estimation {sc:.4} ({:.2} % of the filter)",
        100.0 * sc / ekf.max(1e-12)
    );
    let mut warnings = Vec::new();
    let mut report = serde_json::json!({
        "sequence": match args.synthetic {
            Some(_) => format!("{} / {} ({} frames, seed {})", args.scene, args.trajectory, args.frames, args.seed),
            None => args.seq.as_ref().map_or(String::new(), |p| p.display().to_string()),
        },
        "walker_height_m": height,
        "frames": run.unscaled.len(),
        "filter_ms": ekf,
        "scale_ms": sc,
        "sections": run.scaled.as_ref().map_or(0, |r| r.sections.len()),
        "walking_sections": run.scaled.as_ref().map_or(0, |r| r.sections.iter().filter(|s| s.walking).count()),
        "first_metric_s": first_scaled,
    });
    match &run.scaled {
        Ok(r) => {
            let walking = r.sections.iter().filter(|s| s.walking).count();
            let u = r.up;
            println!(
                "{} frames; up [{:.3} {:.3} {:.3}] found online; {} of {} sections walking; \
                 first metric pose at {}",
                run.unscaled.len(),
                u[0],
                u[1],
                u[2],
                walking,
                r.sections.len(),
                first_scaled.map_or("none".to_string(), |t| format!("{t:.2} s"))
            );
            warnings.extend(super::scale::walking_warning(walking, r.sections.len(), u));
        }
        Err(e) => warnings.push(format!(
            "no metric trajectory: {e}; the filter's own trajectory is kept (unscaled)"
        )),
    }
    let looped = match &run.looped {
        Some(Ok(l)) => Some(l),
        Some(Err(e)) => {
            warnings.push(format!("no loop-corrected trajectory: {e}"));
            None
        }
        None => None,
    };
    if let Some(l) = looped {
        let used = l.loops.iter().filter(|x| x.similarity.is_some()).count();
        println!(
            "{} keyframes ({:.1} ms per keyframe, median), {} loops verified, {} with a similarity \
             used by optimSim3",
            l.keyframe_frames.len(),
            median(&mut keyframe_ms),
            l.loops.len(),
            used
        );
        report["keyframes"] = l.keyframe_frames.len().into();
        report["loops_verified"] = l.loops.len().into();
        report["loops_used"] = used.into();
        if let Some(gt) = gt {
            let truth = LoopTruth::default();
            let (mut correct, mut t_err, mut s_err) = (0, Vec::new(), Vec::new());
            for lp in &l.loops {
                let (a, b) = (l.keyframe_frames[lp.candidate], l.keyframe_frames[lp.query]);
                let (Some(ga), Some(gb)) = (gt.get(a), gt.get(b)) else {
                    continue;
                };
                correct += usize::from(truth.judge(ga, gb).2);
                if let (Some(sim), Ok(r)) = (&lp.similarity, &run.scaled) {
                    // The similarity carried into metres by the section scales, against the
                    // true relative translation.
                    let true_t =
                        (ga.world_from_camera.inverse() * gb.world_from_camera).translation;
                    let ci = r.scale_at(ga.timestamp);
                    let cj = r.scale_at(gb.timestamp);
                    t_err.push((ci * sim.candidate_from_query.translation - true_t).length());
                    // Metric scale ratio of the constraint: 1 when the two sections' scales
                    // and the measurement agree.
                    s_err.push((sim.candidate_from_query.scale * ci / cj).ln().abs());
                }
            }
            let (mt, ms) = (median(&mut t_err), median(&mut s_err));
            println!(
                "loops true by the ground truth: {correct} of {}; used loops' translation error \
                 median {mt:.3} m, |ln metric scale ratio| median {ms:.3}",
                l.loops.len()
            );
            report["loops_true"] = correct.into();
            report["loop_translation_error_m"] = mt.into();
            report["loop_log_scale_ratio"] = ms.into();
        }
    }
    if let Some(out) = &args.out {
        if let Ok(r) = &run.scaled {
            match looped {
                Some(l) => {
                    write_tum(out, &l.trajectory)?;
                    write_tum(&beside(out, "dynscale"), &r.scaled)?;
                }
                None => write_tum(out, &r.scaled)?,
            }
        }
        write_tum(&beside(out, "unscaled"), &run.unscaled)?;
        write_tum(&beside(out, "causal"), &run.causal)?;
        if args.loops {
            write_tum(&beside(out, "causal_loops"), &run.causal_looped)?;
        }
        write_sidecar(
            out,
            &serde_json::json!({ "mono": cfg, "scale": scale_cfg }),
            &ComputeBackend::Cpu,
        )?;
        println!(
            "wrote {} ({}), {} ({} poses), {} ({} poses)",
            out.display(),
            run.scaled
                .as_ref()
                .map_or("not written: no scale".to_string(), |r| {
                    format!("{} metric poses", r.scaled.len())
                }),
            beside(out, "unscaled").display(),
            run.unscaled.len(),
            beside(out, "causal").display(),
            run.causal.len()
        );
    }
    if let (Some(out), Some(gt), true) = (&args.out, gt, args.synthetic.is_some()) {
        write_tum(&beside(out, "groundtruth"), gt)?;
    }
    if let Some(gt) = gt {
        println!("eq. 3.36, placed on the ground truth at the first pose, never rescaled:");
        // (printed name, JSON key, trajectory)
        let mut rows = vec![
            ("unscaled (EKF)", "unscaled", &run.unscaled),
            ("causal metric", "causal", &run.causal),
        ];
        if args.loops {
            rows.push(("loops + causal", "causal_loops", &run.causal_looped));
        }
        if let Ok(r) = &run.scaled {
            rows.push(("final metric", "final", &r.scaled));
        }
        if let Some(l) = looped {
            rows.push(("loops + final metric", "loops", &l.trajectory));
        }
        for (name, key, est) in rows {
            let pairs = rgbid::eval::associate(est, gt, 0.02);
            let e: Vec<TimedPose> = pairs.iter().map(|p| est[p.0]).collect();
            let g: Vec<TimedPose> = pairs.iter().map(|p| gt[p.1]).collect();
            let result = arc_length_error_from_start(&g, &e, 1000);
            // The same placement compared at equal times: free of how the estimate spends
            // its arc length (a loop correction's jump lengthens the path).
            let at_time = time_matched_error_from_start(&g, &e)
                .map_or(f64::NAN, |(mean, length)| 100.0 * mean / length);
            // The positions' RMSE after the rigid motion that fits them best (no scale): the
            // metric shape and scale without the start placement, which carries the filter's
            // attitude error at every later pose along the whole walk.
            let rigid = ate(&g, &e, false).map_or(f64::NAN, |a| {
                100.0 * a.translation.rmse / path_length(&g).max(1e-12)
            });
            if let Ok(a) = &result {
                let end = a.curve.last().map_or(f64::NAN, |c| c.1);
                report[key] = serde_json::json!({
                    "mean_pct": 100.0 * a.relative,
                    "end_pct": 100.0 * end / a.gt_length,
                    "time_matched_pct": at_time,
                    "rigid_ate_pct": rigid,
                    "path_m": a.gt_length,
                    "length_ratio": a.est_length / a.gt_length,
                    "poses": pairs.len(),
                });
            }
            match result {
                Ok(a) => println!(
                    "  {name:<20} mean {:.3} m ({:.2} % of {:.1} m), end {:.3} m ({:.2} %), \
                     length ratio {:.3} over {} poses; at equal times {:.2} %; \
                     rigidly aligned ATE {:.2} %",
                    a.mean,
                    100.0 * a.relative,
                    a.gt_length,
                    a.curve.last().map_or(f64::NAN, |c| c.1),
                    100.0 * a.curve.last().map_or(f64::NAN, |c| c.1) / a.gt_length,
                    a.est_length / a.gt_length,
                    pairs.len(),
                    at_time,
                    rigid
                ),
                Err(err) => println!("  {name:<20} not computed: {err}"),
            }
        }
        let pairs = rgbid::eval::associate(&run.unscaled, gt, 0.02);
        let e: Vec<TimedPose> = pairs.iter().map(|p| run.unscaled[p.0]).collect();
        let g: Vec<TimedPose> = pairs.iter().map(|p| gt[p.1]).collect();
        if let Ok(a) = ate(&g, &e, true) {
            let pct = 100.0 * a.translation.rmse / path_length(&g).max(1e-12);
            println!(
                "EKF ATE after Sim(3) alignment: rmse {:.4} m ({pct:.2} % of the path), scale {:.4}",
                a.translation.rmse, a.alignment.scale
            );
            report["ekf_sim3_ate_pct"] = pct.into();
            report["ekf_sim3_scale"] = a.alignment.scale.into();
        }
    }
    if let Some(path) = &args.json {
        report["warnings"] = serde_json::json!(warnings);
        super::report::write(
            path,
            "mono-metric",
            &super::report::meta(Vec::new()),
            &report,
        )?;
    }
    frame_loop.end(args.out.as_deref(), warnings)
}

fn path_length(p: &[TimedPose]) -> f64 {
    p.windows(2)
        .map(|w| (w[1].world_from_camera.translation - w[0].world_from_camera.translation).length())
        .sum()
}

/// Loop-detection parameters: defaults and the `--loop-*` flags.
fn loop_params(args: &Args) -> Result<MonoLoopParams> {
    let mut p = MonoLoopParams::default();
    if let Some(v) = args.loop_score {
        p.min_normalised_score = v;
    }
    if let Some(v) = args.loop_inliers {
        p.min_inliers = v;
    }
    p.validate()?;
    Ok(p)
}

/// `--loops` on a sequence folder: prints the verified loops.
fn loops_on_sequence(
    args: &Args,
    camera: UnifiedCamera,
    cfg: &MonoConfig,
    len: usize,
    mut frames: impl Iterator<Item = (usize, Result<(f64, ImageF32), rgbid::mono::MonoError>)>,
) -> Result<()> {
    let params = loop_params(args)?;
    let slam = MonoSlam::new(camera, cfg.clone())?;
    let mut sys = LoopingMono::new(slam, Vocabulary::embedded_default()?, params.clone())?;
    let bar = progress(len, "mono --loops");
    let mut queries = Vec::new();
    let mut estimate = Vec::with_capacity(len);
    let mut run = FrameLoop::new(args)?;
    while let Some((i, t, img)) = run.next(&mut frames, &bar) {
        let r = match sys.process(t, &img) {
            Ok(r) => r,
            Err(e) => {
                run.failed(i, t, e);
                break;
            }
        };
        estimate.push(TimedPose {
            timestamp: t,
            world_from_camera: r.filter.world_from_camera,
        });
        queries.extend(r.keyframe);
        if let (true, Some(out)) = (run.done(t, &bar), &args.out) {
            FrameLoop::checkpoint(&[(out.clone(), &estimate)]);
        }
    }
    bar.finish_and_clear();
    if let Some(out) = &args.out {
        write_tum(out, &estimate)?;
        write_sidecar(out, cfg, &ComputeBackend::Cpu)?;
        println!("wrote {} poses to {}", estimate.len(), out.display());
    }
    let kfs = sys.detector().keyframes();
    let mut found = Vec::new();
    for q in &queries {
        if let Some(c) = q.best(
            params.min_normalised_score,
            params.min_inliers,
            params.min_inlier_ratio,
        ) {
            let (a, b) = (&kfs[q.keyframe], &kfs[c.keyframe]);
            println!(
                "loop: keyframe {} (frame {}, {:.2} s) -> keyframe {} (frame {}, {:.2} s): normalised score {:.2}, {} of {} matches inliers, parallax {:.1} deg",
                q.keyframe, a.frame, a.timestamp, c.keyframe, b.frame, b.timestamp,
                c.normalised_score, c.inliers, c.matches, c.parallax_deg
            );
            found.push(*c);
        }
    }
    println!("{} keyframes, {} loops verified", kfs.len(), found.len());
    if let Some(path) = &args.loops_json {
        let doc = serde_json::json!({
            "params": params,
            "keyframe_frames": kfs.iter().map(|k| k.frame).collect::<Vec<_>>(),
            "queries": queries,
        });
        super::report::write(path, "mono-loops", &super::report::meta(Vec::new()), &doc)?;
    }
    run.end(args.out.as_deref(), Vec::new())
}

/// `--loops --synthetic`: loops scored against the ground truth.
fn loops_synthetic(
    args: &Args,
    spec: &SyntheticSpec,
    frames: &rgbid::experiments::mono::SyntheticFrames,
    cfg: &MonoConfig,
) -> Result<()> {
    let params = loop_params(args)?;
    let truth = LoopTruth::default();
    let t0 = Instant::now();
    let e = synthetic_loops(
        frames,
        cfg,
        Vocabulary::embedded_default()?,
        &params,
        &truth,
    )?;
    let secs = t0.elapsed().as_secs_f64();
    for l in &e.loops {
        println!(
            "loop: keyframe {} (frame {}) -> keyframe {} (frame {}): normalised score {:.2}, {} of {} matches inliers, parallax {:.1} deg; truth {:.2} m apart, axes {:.0} deg -> {}",
            l.query, l.query_frame, l.candidate, l.candidate_frame, l.normalised_score,
            l.inliers, l.matches, l.parallax_deg, l.true_distance_m, l.true_axis_angle_deg,
            if l.correct { "true" } else { "FALSE" }
        );
    }
    let s = &e.score;
    println!(
        "{} frames ({:.1} m), {} keyframes: {} loops, {} true; {} keyframes have a true loop \
         partner >= {} s older -> precision {:.3}, recall {:.3} (score >= {}, inliers >= {}, ratio >= {}); \
         filter {:.2} ms/frame, loops {:.1} ms/keyframe (median); EKF Sim(3) ATE {:.3} m; {:.1} s",
        e.frames, e.path_length, e.keyframe_frames.len(), s.detected, s.true_positives,
        s.loop_queries, params.min_time_separation, s.precision, s.recall,
        s.min_normalised_score, s.min_inliers, s.min_inlier_ratio, e.filter_ms, e.keyframe_ms,
        e.ate_rmse, secs
    );
    println!(
        "{} checked candidates are not true loops; the most inliers among them: {}{}",
        e.false_candidates,
        e.false_candidate_max_inliers,
        e.false_candidate_max_truth
            .map_or(String::new(), |(d, a)| format!(
                " (true positions {d:.2} m apart, optical axes {a:.0} deg)"
            ))
    );
    println!("sweep (normalised score, inliers, inlier ratio: loops / true -> precision, recall):");
    for w in &e.sweep {
        println!(
            "  {:>4.2} {:>3} {:>4.2}: {:>3} / {:>3} -> {:.3}, {:.3}",
            w.min_normalised_score,
            w.min_inliers,
            w.min_inlier_ratio,
            w.detected,
            w.true_positives,
            w.precision,
            w.recall
        );
    }
    if let Some(path) = &args.loops_json {
        let doc = serde_json::json!({
            "sequence": format!("{} / {} ({} frames, seed {})", spec.scene, spec.trajectory, spec.frames, spec.seed),
            "width": spec.width,
            "height": spec.height,
            "evaluation": e,
        });
        super::report::write(path, "mono-loops", &super::report::meta(Vec::new()), &doc)?;
    }
    Ok(())
}
