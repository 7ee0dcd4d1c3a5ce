//! `rgbid slam`: the full RGB-ID SLAM system on a TUM folder or a generated sequence.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use rgbid::camera::PinholeCamera;
use rgbid::eval::{evaluate, EvalOptions};
use rgbid::gpu::{select_backend, BackendChoice, ComputeBackend};
use rgbid::io::run_folder::{FrameRow, KeyframeTimingRow, LoopRow, RunFolderWriter, RunSummary};
use rgbid::place::Vocabulary;
use rgbid::slam::{build_model, FrameStatus, Map, ModelParams, Slam, SlamConfig, SlamResult};
use rgbid::source::{FrameSource, SourceSpec};
use rgbid::synth::{SequenceConfig, TrajectoryKind};
use rgbid::trajectory::TimedPose;

/// Arguments of `rgbid slam`.
#[derive(clap::Args)]
pub struct Args {
    /// TUM RGB-D folder (rgb.txt + depth.txt or associations.txt). Not needed with --synth.
    pub sequence: Option<PathBuf>,
    /// Generate the sequence instead: `SCENE:TRAJECTORY` (e.g. `office:loop`), see
    /// `rgbid synth --help` for the names.
    #[arg(long)]
    pub synth: Option<String>,
    /// Frames of a generated sequence (30 per second).
    #[arg(long, default_value_t = 600)]
    pub frames: usize,
    /// Image width of a generated sequence (height is 3/4 of it).
    #[arg(long, default_value_t = 320)]
    pub width: u32,
    /// Seed of a generated sequence.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Laps of a generated `loop` trajectory over the sequence (the same closed path again,
    /// so that the second lap revisits every place of the first).
    #[arg(long, default_value_t = 1.0)]
    pub laps: f64,
    /// Session of a generated scene (0 = reference arrangement; others move objects).
    #[arg(long, default_value_t = 0)]
    pub session: u32,
    /// Output folder: trajectory.txt (every frame), keyframes.txt, odometry.txt, loops.csv,
    /// model.ply, timing.csv, keyframe_timing.csv, summary.json.
    #[arg(long, default_value = "slam-out")]
    pub out: PathBuf,
    /// Camera preset or calibration file for a TUM folder (see `rgbid odometry --help`).
    #[arg(long)]
    pub camera: Option<String>,
    /// Only the first N frames.
    #[arg(long)]
    pub max_frames: Option<usize>,
    /// Load this map first: the session relocalises in it and extends it.
    #[arg(long)]
    pub map_in: Option<PathBuf>,
    /// Save the map here at the end.
    #[arg(long)]
    pub map_out: Option<PathBuf>,
    /// Feed frames at this rate (frames per second) as a live camera would: frames that
    /// arrive while the system is busy are dropped and counted.
    #[arg(long)]
    pub realtime: Option<f64>,
    /// Disable the superjut / neg-entropy masks in place recognition.
    #[arg(long)]
    pub no_masks: bool,
    /// Keyframe covisibility threshold.
    #[arg(long, default_value_t = 0.7)]
    pub keyframe_covisibility: f64,
    /// A frame whose motion since the last posed frame is faster than this (m/s) is treated as
    /// a tracking failure (lost, then relocalised) instead of keeping a wrong pose. The default
    /// suits handheld and worn cameras; raise it for vehicles, `inf` disables it.
    #[arg(long, default_value_t = SlamConfig::default().lost_max_speed)]
    pub max_speed: f64,
    /// The same for the rotation rate (rad/s).
    #[arg(long, default_value_t = SlamConfig::default().lost_max_angular_speed)]
    pub max_angular_speed: f64,
    /// Do not write model.ply.
    #[arg(long)]
    pub no_model: bool,
    /// Voxel size of the model filter, metres.
    #[arg(long, default_value_t = 0.01)]
    pub voxel: f64,
    /// Vocabulary file (default: the embedded one).
    #[arg(long)]
    pub vocabulary: Option<PathBuf>,
    /// Compute backend.
    #[arg(long, value_enum, default_value_t = BackendChoice::Auto)]
    pub backend: BackendChoice,
    /// GPU adapter name filter.
    #[arg(long)]
    pub adapter: Option<String>,
}

/// The source the arguments name (a TUM folder, or `--synth` with `--laps` laps of a loop).
#[allow(clippy::too_many_arguments)]
pub fn source_spec(
    sequence: Option<&Path>,
    synth: Option<&str>,
    camera: Option<&str>,
    max_frames: Option<usize>,
    frames: usize,
    width: u32,
    seed: u64,
    session: u32,
    laps: f64,
) -> Result<SourceSpec> {
    if let Some(spec) = synth {
        let frames = max_frames.unwrap_or(frames).min(frames);
        if !(laps.is_finite() && laps > 0.0) {
            bail!("--laps must be > 0");
        }
        let traj = spec.split_once(':').map_or("loop", |(_, t)| t);
        let lap_seconds = if TrajectoryKind::from_name(traj)? == TrajectoryKind::Loop {
            Some(
                SequenceConfig {
                    frames,
                    ..Default::default()
                }
                .duration()
                    / laps,
            )
        } else {
            None
        };
        return Ok(SourceSpec::Synth {
            spec: spec.to_string(),
            frames,
            width,
            seed,
            session,
            lap_seconds,
        });
    }
    let Some(dir) = sequence else {
        bail!("give a TUM folder or --synth SCENE:TRAJECTORY");
    };
    Ok(SourceSpec::Tum {
        dir: dir.to_path_buf(),
        camera: camera.map(str::to_string),
        max_frames,
    })
}

fn peak_rss_mb() -> Option<f64> {
    let s = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = s.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb / 1024.0)
}

fn median(v: &mut [f64]) -> f64 {
    crate::cli::bench::median(v)
}

/// Runs the subcommand.
pub fn run(a: Args) -> Result<()> {
    let backend = select_backend(a.backend, a.adapter.as_deref())?;
    let spec = source_spec(
        a.sequence.as_deref(),
        a.synth.as_deref(),
        a.camera.as_deref(),
        a.max_frames,
        a.frames,
        a.width,
        a.seed,
        a.session,
        a.laps,
    )?;
    let mut source = FrameSource::open(&spec, &backend)?;
    if source.is_empty() {
        bail!("the sequence has no frames");
    }
    let vocabulary = match &a.vocabulary {
        Some(p) => Vocabulary::load(p)?,
        None => Vocabulary::embedded_default()?,
    };
    let map = match &a.map_in {
        Some(p) => Some(Map::load(p)?),
        None => None,
    };
    let mut config = SlamConfig {
        masks: !a.no_masks,
        keyframe_covisibility: a.keyframe_covisibility,
        lost_max_speed: a.max_speed,
        lost_max_angular_speed: a.max_angular_speed,
        ..Default::default()
    };
    if a.realtime.is_some() {
        config.queue = 2;
    }
    // Per-frame rows are appended and flushed as they come (see `rgbid::io::run_folder`).
    let writer = RunFolderWriter::create(&a.out).with_context(|| format!("{}", a.out.display()))?;
    let outcome = run_slam(&a, &mut source, config, &backend, vocabulary, map, writer);
    match outcome {
        Ok(()) => Ok(()),
        Err(e) => Err(e.context(format!(
            "(whatever was computed before the error is in {})",
            a.out.display()
        ))),
    }
}

fn run_slam(
    a: &Args,
    source: &mut FrameSource,
    config: SlamConfig,
    backend: &ComputeBackend,
    vocabulary: Vocabulary,
    map: Option<Map>,
    mut writer: RunFolderWriter,
) -> Result<()> {
    let camera = source.camera();
    let n = source.len();
    println!(
        "slam: {n} frames {}x{}, backend {}, masks {}{}",
        camera.width,
        camera.height,
        backend.name(),
        if config.masks { "on" } else { "off" },
        match &map {
            Some(m) => format!(", map with {} keyframes", m.keyframes.len()),
            None => String::new(),
        }
    );
    let t0 = Instant::now();
    let mut slam = Slam::new(config, camera, backend, vocabulary, map)?;
    let bar = ProgressBar::new(n as u64);
    bar.set_style(
        ProgressStyle::with_template("{bar:40} {pos}/{len} frames {per_sec} eta {eta} {msg}")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    let mut error: Option<anyhow::Error> = None;
    let mut dropped = 0usize;
    let mut lost = 0usize;
    let mut load_ms = Vec::new();
    let mut i = 0usize;
    let start = Instant::now();
    while i < n {
        if let Some(fps) = a.realtime {
            // The newest frame a live camera would have delivered by now.
            let available = (start.elapsed().as_secs_f64() * fps).floor() as usize;
            if available > i {
                let newest = available.min(n - 1);
                dropped += newest - i;
                bar.inc((newest - i) as u64);
                i = newest;
            }
        }
        let tl = Instant::now();
        let frame = match source.load(i) {
            Ok(f) => f,
            Err(e) => {
                error = Some(anyhow::Error::new(e).context(format!("frame {i}")));
                break;
            }
        };
        load_ms.push(tl.elapsed().as_secs_f64() * 1e3);
        match slam.process(&frame) {
            Ok(r) => {
                if let Err(e) = write_frame(&mut writer, &slam, &r.record) {
                    error = Some(e.context(format!("frame {i}")));
                    break;
                }
                if r.status == FrameStatus::Lost {
                    lost += 1;
                }
                bar.set_message(format!(
                    "kf {} loops {} lost {lost}{}",
                    r.keyframes,
                    r.loops,
                    if a.realtime.is_some() {
                        format!(" dropped {dropped}")
                    } else {
                        String::new()
                    }
                ));
            }
            Err(e) => {
                error = Some(anyhow::Error::new(e).context(format!("frame {i}")));
                break;
            }
        }
        bar.inc(1);
        i += 1;
        if let Some(fps) = a.realtime {
            // Wait for the next frame to arrive.
            let due = i as f64 / fps;
            let now = start.elapsed().as_secs_f64();
            if due > now {
                std::thread::sleep(std::time::Duration::from_secs_f64(due - now));
            }
        }
    }
    bar.finish_and_clear();
    let processed = slam.frames();
    let result = slam.finish()?;
    let wall = t0.elapsed().as_secs_f64();
    write_outputs(
        a,
        writer,
        source,
        &camera,
        &result,
        &mut load_ms,
        dropped,
        processed,
        wall,
    )?;
    if let Some(e) = error {
        return Err(e);
    }
    Ok(())
}

/// Appends a frame's row, its front-end pose and the loops checked since the last call.
fn write_frame(
    writer: &mut RunFolderWriter,
    slam: &Slam,
    record: &rgbid::slam::FrameRecord,
) -> Result<()> {
    writer.frame(&FrameRow::from(record))?;
    if let Some(p) = record.frontworld_from_camera {
        writer.odometry_pose(&TimedPose {
            timestamp: record.timestamp,
            world_from_camera: p,
        })?;
    }
    for l in slam.loops_since(writer.loops_written()) {
        writer.loop_checked(&LoopRow::from(&l))?;
    }
    Ok(())
}

#[allow(clippy::too_many_arguments)]
fn write_outputs(
    a: &Args,
    mut writer: RunFolderWriter,
    source: &FrameSource,
    camera: &PinholeCamera,
    r: &SlamResult,
    load_ms: &mut [f64],
    dropped: usize,
    processed: usize,
    wall: f64,
) -> Result<()> {
    let out = &a.out;
    writer.trajectory(&r.trajectory)?;
    let kf_traj: Vec<TimedPose> = r
        .keyframes()
        .iter()
        .zip(r.keyframe_poses.iter())
        .map(|(k, p)| TimedPose {
            timestamp: k.timestamp,
            world_from_camera: *p,
        })
        .collect();
    writer.keyframes(&kf_traj)?;
    // Loops the back-end found after the last frame's call.
    for l in r.loops.iter().skip(writer.loops_written()) {
        writer.loop_checked(&LoopRow::from(l))?;
    }
    for t in &r.timings {
        writer.keyframe_timing(&KeyframeTimingRow::from(t))?;
    }
    let mut model_points = 0;
    if !a.no_model {
        let params = ModelParams {
            voxel: a.voxel,
            ..Default::default()
        };
        let filtered = build_model(r.keyframes(), &r.keyframe_poses, camera, &params);
        model_points = filtered.len();
        writer.model(&filtered)?;
    }
    if let Some(p) = &a.map_out {
        r.map.save(p)?;
        println!(
            "map: {} keyframes, {:.2} MB per keyframe, saved to {}",
            r.map.keyframes.len(),
            r.map.bytes_per_keyframe() / 1e6,
            p.display()
        );
    }
    // Tables 6.2 / 6.3 analogues.
    let col = |g: &dyn Fn(&rgbid::slam::FrameRecord) -> f64| {
        let mut v: Vec<f64> = r
            .frames
            .iter()
            .filter(|f| f.frontworld_from_camera.is_some())
            .map(g)
            .collect();
        median(&mut v)
    };
    let tracked = r
        .frames
        .iter()
        .filter(|f| f.frontworld_from_camera.is_some())
        .count();
    let lost = r
        .frames
        .iter()
        .filter(|f| f.status == FrameStatus::Lost)
        .count();
    let reloc = r
        .frames
        .iter()
        .filter(|f| f.status == FrameStatus::Relocalised)
        .count();
    let accepted = r
        .loops
        .iter()
        .filter(|l| l.accepted && !l.relocalisation)
        .count();
    println!(
        "frames {processed} (dropped {dropped}), tracked {tracked}, lost {lost}, relocalised {reloc}; \
         keyframes {} ({} new), loops {accepted} accepted of {} detected; wall {wall:.1} s",
        r.keyframes().len(),
        r.timings.len(),
        r.loops.iter().filter(|l| !l.relocalisation).count()
    );
    println!("front-end per frame (median ms): load {:.1} | pyramid {:.1} | scale {:.1} | reduce {:.1} | solve {:.2} | covisibility {:.1} | fusion {:.1} | total {:.1}",
        median(load_ms),
        col(&|f| f.times.pyramid_ms),
        col(&|f| f.times.scale_ms),
        col(&|f| f.times.reduce_ms),
        col(&|f| f.times.solve_ms),
        col(&|f| f.times.covisibility_ms),
        col(&|f| f.fusion_ms),
        col(&|f| f.frontend_ms));
    let kcol = |g: &dyn Fn(&rgbid::slam::KeyframeTiming) -> f64| {
        let mut v: Vec<f64> = r.timings.iter().map(g).collect();
        median(&mut v)
    };
    let mut loop_align: Vec<f64> = r
        .timings
        .iter()
        .filter(|t| t.align_ms > 0.0)
        .map(|t| t.align_ms)
        .collect();
    let mut opt: Vec<f64> = r
        .timings
        .iter()
        .filter(|t| t.optimise_ms > 0.0)
        .map(|t| t.optimise_ms)
        .collect();
    // Loop clusters still open at the end are optimised by the final pass only.
    let per_opt = if opt.is_empty() {
        "none during the run".to_string()
    } else {
        format!("{:.1} ({})", median(&mut opt), opt.len())
    };
    println!("back-end per keyframe (median ms): segment {:.1} | ORB+BoW {:.1} | query+verify {:.1} | total {:.1}; per loop: dense align {:.1}; per optimisation {}; final {:.1}",
        kcol(&|t| t.segment_ms),
        kcol(&|t| t.describe_ms),
        kcol(&|t| t.query_ms),
        kcol(&|t| t.total_ms),
        median(&mut loop_align),
        per_opt,
        r.final_optimise_ms);
    let rss = peak_rss_mb();
    if let Some(m) = rss {
        println!(
            "peak resident memory {m:.0} MB; map {:.2} MB per keyframe",
            r.map.bytes_per_keyframe() / 1e6
        );
    }
    // The instance's own account (what this `Slam` held), beside the process figure.
    let peak = &r.memory.peak;
    let mb = |b: usize| b as f64 / 1e6;
    println!(
        "instance peak {:.1} MB: keyframes {:.1} | place recognition {:.1} | pose graph {:.2} | segmenter {:.1} | odometry {:.1} | fusion {:.1} | records {:.2} | gpu {:.1}",
        mb(peak.total()),
        mb(peak.keyframes),
        mb(peak.place_recognition),
        mb(peak.pose_graph),
        mb(peak.segmenter),
        mb(peak.odometry),
        mb(peak.fusion),
        mb(peak.records),
        mb(peak.gpu)
    );
    let mut summary = RunSummary {
        frames: processed,
        dropped,
        tracked,
        lost,
        relocalised: reloc,
        keyframes: r.keyframes().len(),
        loops_accepted: accepted,
        wall_s: wall,
        model_points,
        peak_rss_mb: rss,
        ..Default::default()
    };
    summary.extra.insert(
        "instance_peak_bytes".into(),
        serde_json::json!(r.memory.peak_bytes()),
    );
    summary.extra.insert(
        "instance_peak_breakdown_bytes".into(),
        serde_json::to_value(peak)?,
    );
    if let Some(gt) = source.groundtruth() {
        writer.groundtruth(&gt)?;
        let opts = EvalOptions::default();
        for (name, est) in [("slam", &r.trajectory), ("odometry", &r.odometry)] {
            if est.len() < 2 {
                continue;
            }
            match evaluate(&gt, est, &opts) {
                Ok(m) => {
                    let rpe = m
                        .rpe
                        .as_ref()
                        .map(|x| x.translation_m.rmse)
                        .unwrap_or(f64::NAN);
                    println!(
                        "{name:<9} ATE rmse {:.4} m (max {:.4}), RPE {:.4} m/s over {} poses",
                        m.ate.translation.rmse, m.ate.translation.max, rpe, m.matched
                    );
                    let (ate, rpe_slot) = if name == "slam" {
                        (&mut summary.slam_ate_rmse, &mut summary.slam_rpe_rmse)
                    } else {
                        (
                            &mut summary.odometry_ate_rmse,
                            &mut summary.odometry_rpe_rmse,
                        )
                    };
                    *ate = Some(m.ate.translation.rmse);
                    *rpe_slot = Some(rpe);
                }
                Err(e) => println!("{name}: evaluation failed: {e}"),
            }
        }
    }
    writer.finish(summary)?;
    println!("wrote {}", out.display());
    Ok(())
}
