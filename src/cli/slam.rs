//! `rgbid slam`: the full RGB-ID SLAM system on a TUM folder or a generated sequence.

use std::path::PathBuf;
use std::time::Instant;

use anyhow::{bail, Result};
use indicatif::{ProgressBar, ProgressStyle};
use rgbid::camera::PinholeCamera;
use rgbid::eval::{evaluate, EvalOptions};
use rgbid::gpu::{select_backend, ComputeBackend};
use rgbid::image::RgbdFrame;
use rgbid::io::run_folder::{
    FrameRow, KeyframeTimingRow, LoopRow, RunFolderWriter, RunStatus, RunSummary,
};
use rgbid::io::settings::Provenance;
use rgbid::io::CalibFormat;
use rgbid::io::Layout;
use rgbid::live::{LiveInput, LiveOptions, LiveSpec};
use rgbid::place::Vocabulary;
use rgbid::slam::{
    build_coloured_model, build_volume, FrameStatus, Map, ModelParams, Slam, SlamConfig, SlamResult,
};
use rgbid::source::{FrameSource, RgbdStream, SourceError, SourceSpec, SynthOptions};
use rgbid::trajectory::TimedPose;
use rgbid::tsdf::TsdfParams;

use super::ahead::ReadAhead;
use super::options::{range, BackendArgs, ConfigArgs, OdometryOptions};

/// Arguments of `rgbid slam`.
#[derive(clap::Args)]
pub struct Args {
    /// TUM RGB-D folder (rgb.txt + depth.txt or associations.txt). Not needed with --synth.
    pub sequence: Option<PathBuf>,
    #[command(flatten)]
    pub source: SynthOptions,
    /// Session of a generated scene (0 = reference arrangement; others move objects) (0 to 1000).
    #[arg(long, value_parser = crate::cli::options::range::session, default_value_t = 0)]
    pub session: u32,
    /// Output folder: trajectory.txt (every frame), keyframes.txt, odometry.txt, loops.csv,
    /// model.ply, mesh.ply and volume.tsdf (with --mesh), timing.csv, keyframe_timing.csv, summary.json
    /// (figures, and the configuration, version, backend and command line under
    /// `provenance`).
    #[arg(long, default_value = "slam-out")]
    pub out: PathBuf,
    /// Camera preset or calibration file for a sequence folder (see `rgbid odometry --help`).
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
    /// Layout of the sequence folder [default: detected from its content].
    #[arg(long, value_enum)]
    pub format: Option<Layout>,
    /// Only the first N frames (N >= 1).
    #[arg(long, value_parser = range::at_least_one)]
    pub max_frames: Option<usize>,
    /// Load this map first: the session relocalises in it and extends it.
    #[arg(long)]
    pub map_in: Option<PathBuf>,
    /// Save the map here at the end.
    #[arg(long)]
    pub map_out: Option<PathBuf>,
    /// Live input instead of a folder: `openni2` (the first OpenNI2 device; needs the
    /// `openni2` build feature), `openni2:URI`, or `replay:FOLDER[@FPS]` (a simulated camera
    /// playing a folder at FPS frames per second of wall time, default 30). Frames that arrive
    /// while tracking is busy are dropped and counted; Ctrl-C ends the run and writes every
    /// output. `--camera` sets the intrinsics (OpenNI2 default: the `default` preset).
    #[arg(long, conflicts_with_all = ["sequence", "realtime", "max_frames"])]
    pub live: Option<String>,
    /// With --live: record every frame the camera delivers (also the dropped ones) as a TUM
    /// RGB-D folder here (rgb/, depth/ at 5000 per metre, the lists, calib.txt with the
    /// undistorted camera); `rgbid slam DIR` on it replays the session.
    #[arg(long, requires = "live")]
    pub record: Option<PathBuf>,
    /// Feed frames at this rate (frames per second) as a live camera would: frames that
    /// arrive while the system is busy are dropped and counted (sets `queue = 2`); 0.001 to
    /// 10000 frames per second.
    #[arg(long, value_parser = range::frame_rate)]
    pub realtime: Option<f64>,
    /// Disable the superjut / neg-entropy masks in place recognition (`masks = false`).
    #[arg(long)]
    pub no_masks: bool,
    /// Keyframe covisibility threshold in [0, 1] (`keyframe_covisibility`)
    /// [default: 0.7].
    #[arg(long, value_parser = range::unit)]
    pub keyframe_covisibility: Option<f64>,
    /// A frame whose motion since the last posed frame is faster than this (m/s) is treated as
    /// a tracking failure (lost, then relocalised) instead of keeping a wrong pose
    /// (`lost_max_speed`). The default suits handheld and worn cameras; raise it for
    /// vehicles, `inf` disables it; > 0 [default: 3].
    #[arg(long, value_parser = range::positive_or_inf)]
    pub max_speed: Option<f64>,
    /// The same for the rotation rate, rad/s (`lost_max_angular_speed`); > 0, `inf` disables
    /// it [default: 4].
    #[arg(long, value_parser = range::positive_or_inf)]
    pub max_angular_speed: Option<f64>,
    /// Seconds of input (frame time stamps) between checkpoints: trajectory.txt (the
    /// estimate so far), keyframes.txt and summary.json (`status: running`) are replaced
    /// atomically, so a run killed later leaves them readable; > 0 [default: 5].
    #[arg(long, value_parser = range::positive, default_value_t = super::outputs::CHECKPOINT_EVERY_S)]
    pub checkpoint_every: f64,
    /// Do not write model.ply.
    #[arg(long)]
    pub no_model: bool,
    /// Voxel size of the model filter and of the mesh (--mesh), metres, >= 0 (0 = no
    /// filter; the mesh needs > 0).
    #[arg(long, value_parser = range::non_negative, default_value_t = ModelParams::default().voxel)]
    pub voxel: f64,
    /// Also write mesh.ply: a TSDF of every keyframe's fused inverse depth at its final
    /// (optimised) pose, built after the run on the compute backend, so loop closures move
    /// the surface; vertices carry normals and the keyframes' colour (grey from the
    /// intensity when the input has no colour).
    #[arg(long)]
    pub mesh: bool,
    /// With --mesh: most voxel blocks kept on the GPU while integrating (>= 1; a block is
    /// 8^3 voxels, 6144 bytes); the blocks farthest from the keyframe being integrated move
    /// to host memory and back, the mesh is the same. Default: unbounded. The CPU backend
    /// ignores it.
    #[arg(long, value_parser = range::at_least_one, value_name = "BLOCKS", requires = "mesh")]
    pub mesh_device_blocks: Option<usize>,
    /// Vocabulary file (default: the embedded one).
    #[arg(long)]
    pub vocabulary: Option<PathBuf>,
    /// Also log the run to rerun: `save:FILE.rrd` writes a recording, `connect` streams to a
    /// running viewer at 127.0.0.1:9876, `connect=HOST:PORT` (or a `rerun+http://` URL)
    /// elsewhere. Camera poses and pinhole, images (depth in metres), keyframe points, loop
    /// edges and the per-frame figures, on the timelines `frame` (index) and `time` (time
    /// stamp, s). Needs the `rerun` build feature.
    #[arg(long, value_name = "save:FILE.rrd|connect[=ADDR]", value_parser = super::rerun::parse_spec)]
    pub rerun: Option<super::rerun::RerunSpec>,
    /// Configuration: a `SlamConfig` file (`rgbid config dump --command slam`).
    #[command(flatten)]
    pub config: ConfigArgs,
    #[command(flatten)]
    pub odometry: OdometryOptions,
    #[command(flatten)]
    pub backend: BackendArgs,
}

impl Args {
    /// Arguments with every option at its default (no sequence named).
    pub fn new(out: PathBuf) -> Self {
        Args {
            sequence: None,
            source: SynthOptions::default(),
            session: 0,
            out,
            camera: None,
            calib_format: CalibFormat::Auto,
            format: None,
            max_frames: None,
            map_in: None,
            map_out: None,
            live: None,
            record: None,
            realtime: None,
            no_masks: false,
            keyframe_covisibility: None,
            max_speed: None,
            max_angular_speed: None,
            checkpoint_every: super::outputs::CHECKPOINT_EVERY_S,
            no_model: false,
            voxel: ModelParams::default().voxel,
            mesh: false,
            mesh_device_blocks: None,
            vocabulary: None,
            rerun: None,
            config: ConfigArgs::default(),
            odometry: OdometryOptions::default(),
            backend: BackendArgs::default(),
        }
    }

    /// The SLAM configuration: defaults, `--config`, the flags, `--set`.
    pub fn slam_config(&self) -> Result<SlamConfig> {
        let config = self.config.resolve(SlamConfig::default(), |c| {
            if self.no_masks {
                c.masks = false;
            }
            if let Some(v) = self.keyframe_covisibility {
                c.keyframe_covisibility = v;
            }
            if let Some(v) = self.max_speed {
                c.lost_max_speed = v;
            }
            if let Some(v) = self.max_angular_speed {
                c.lost_max_angular_speed = v;
            }
            if self.realtime.is_some() || self.live.is_some() {
                c.queue = 2;
            }
            self.odometry.apply(&mut c.odometry);
            Ok(())
        })?;
        config.validate()?;
        Ok(config)
    }

    /// The source the arguments name (a TUM folder, or `--synth` with `--laps` laps of a
    /// loop).
    pub fn source_spec(&self) -> Result<SourceSpec> {
        if let Some(spec) = self.source.spec(self.session, self.max_frames)? {
            return Ok(spec);
        }
        let Some(dir) = &self.sequence else {
            bail!("give a TUM folder or --synth SCENE:TRAJECTORY");
        };
        Ok(SourceSpec::Tum {
            dir: dir.clone(),
            format: self.format,
            camera: super::options::camera_spec(self.camera.as_deref(), self.calib_format),
            max_frames: self.max_frames,
        })
    }
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

/// Where a run's frames come from.
enum Input {
    /// A folder or generated sequence, read by index; a folder's frames are decoded on a
    /// reader thread ahead of the tracking unless frames are dropped to keep a real-time pace.
    Source(
        FrameSource,
        Option<ReadAhead<Result<RgbdFrame, SourceError>>>,
    ),
    /// A live camera (or a replayed folder) on its own thread.
    Live(LiveInput),
}

impl Input {
    fn camera(&self) -> PinholeCamera {
        match self {
            Input::Source(s, _) => s.camera(),
            Input::Live(l) => l.camera(),
        }
    }

    /// Frames to come, when known.
    fn len(&self) -> Option<usize> {
        match self {
            Input::Source(s, _) => Some(s.len()),
            Input::Live(_) => None,
        }
    }

    fn input_warning(&self) -> Option<&str> {
        match self {
            Input::Source(s, _) => s.input_warning(),
            Input::Live(_) => None,
        }
    }

    /// Frame `i` of a source; the next frame of a live input (`i` counts them). With the
    /// frame, the time its decoding took (ms) when a reader thread decoded it.
    fn frame(&mut self, i: usize) -> Option<Result<(RgbdFrame, Option<f64>), SourceError>> {
        match self {
            Input::Source(s, None) => (i < s.len()).then(|| s.load(i).map(|f| (f, None))),
            Input::Source(s, Some(ahead)) => (i < s.len()).then(|| match ahead.get(i) {
                Ok((loaded, ms)) => loaded.map(|f| (f, Some(ms))),
                Err(e) => Err(SourceError::Invalid(e.to_string())),
            }),
            Input::Live(l) => l.next_frame().map(|r| r.map(|f| (f, None))),
        }
    }

    fn groundtruth(&self) -> Option<Vec<TimedPose>> {
        match self {
            Input::Source(s, _) => s.groundtruth(),
            Input::Live(l) => l.groundtruth(),
        }
    }
}

/// What a run reads before its first frame.
struct Inputs {
    backend: ComputeBackend,
    source: Input,
    vocabulary: Vocabulary,
    map: Option<Map>,
    provenance: Provenance,
    rerun: Option<super::rerun::Recorder>,
}

impl Inputs {
    fn open(a: &Args, config: &SlamConfig) -> Result<Self> {
        let backend = select_backend(a.backend.backend, a.backend.adapter.as_deref())?;
        let source = match &a.live {
            Some(live) => {
                let spec: LiveSpec = live.parse()?;
                if a.calib_format == CalibFormat::Droid {
                    bail!("--calib-format droid reads the image size from a sequence folder, not --live input");
                }
                if let Some(r) = &a.record {
                    super::outputs::output_folder(r, None)?;
                }
                let options = LiveOptions {
                    camera: a.camera.clone(),
                    record: a.record.clone(),
                    queue: 2,
                };
                Input::Live(LiveInput::open(&spec, &options)?)
            }
            None => {
                let spec = a.source_spec()?;
                let source = FrameSource::open(&spec, &backend)?;
                if source.is_empty() {
                    bail!("the sequence has no frames");
                }
                // Only a folder is decoded ahead: a generated sequence renders on the
                // backend the tracking uses.
                let ahead = match (&source, a.realtime) {
                    (FrameSource::Tum(seq), None) => Some(ReadAhead::spawn(source.len(), {
                        let seq = seq.clone();
                        move |i| seq.load(i).map_err(SourceError::from)
                    })?),
                    _ => None,
                };
                Input::Source(source, ahead)
            }
        };
        let vocabulary = match &a.vocabulary {
            Some(p) => Vocabulary::load(p)?,
            None => Vocabulary::embedded_default()?,
        };
        let map = match &a.map_in {
            Some(p) => Some(Map::load(p)?),
            None => None,
        };
        let provenance = Provenance::new(config, &backend)?;
        let rerun = match &a.rerun {
            Some(spec) => Some(super::rerun::Recorder::open(spec, "rgbid slam")?),
            None => None,
        };
        Ok(Inputs {
            backend,
            source,
            vocabulary,
            map,
            provenance,
            rerun,
        })
    }
}

/// Runs the subcommand.
pub fn run(a: Args) -> Result<()> {
    let config = a.slam_config()?;
    let mesh_params = TsdfParams {
        voxel_size: a.voxel,
        device_blocks: a.mesh_device_blocks,
        ..Default::default()
    };
    if a.mesh {
        mesh_params.validate()?;
    }
    // Every output location is checked (and the folder locked) before any work.
    super::outputs::output_folder(&a.out, a.sequence.as_deref())?;
    if let Some(p) = &a.map_out {
        let inputs: Vec<&std::path::Path> = a.map_in.iter().map(|p| p.as_path()).collect();
        super::outputs::output_file(p, "--map-out", &inputs)?;
    }
    if let Some(p) = a.rerun.as_ref().and_then(|r| r.file()) {
        let inputs: Vec<&std::path::Path> = a.map_in.iter().map(|p| p.as_path()).collect();
        super::outputs::output_file(p, "--rerun", &inputs)?;
    }
    let writer = RunFolderWriter::create(&a.out)?;
    let out = a.out.clone();
    let stop = super::outputs::Stop::install(move || super::outputs::mark_interrupted(&out))?;
    let Inputs {
        backend,
        mut source,
        vocabulary,
        map,
        provenance,
        rerun,
    } = match Inputs::open(&a, &config) {
        Ok(s) => s,
        Err(e) => {
            // Nothing ran: the folder says why, and the error is reported once, as it is.
            let status = RunStatus::Failed(super::outcome::message(&e));
            writer.end(RunSummary::default(), status)?;
            return Err(e);
        }
    };
    // Frame rows are appended and flushed as they come (see `rgbid::io::run_folder`).
    run_slam(
        &a,
        &mut source,
        config,
        &backend,
        vocabulary,
        map,
        &provenance,
        writer,
        &stop,
        rerun,
    )
}

#[allow(clippy::too_many_arguments)]
fn run_slam(
    a: &Args,
    source: &mut Input,
    config: SlamConfig,
    backend: &ComputeBackend,
    vocabulary: Vocabulary,
    map: Option<Map>,
    provenance: &Provenance,
    mut writer: RunFolderWriter,
    stop: &super::outputs::Stop,
    mut rerun: Option<super::rerun::Recorder>,
) -> Result<()> {
    let camera = source.camera();
    let total = source.len();
    let n = total.unwrap_or(usize::MAX);
    // Said now, so that a long run can be stopped, and again with the outcome (exit code 3).
    let input_warning = source.input_warning().map(str::to_owned);
    if let Some(w) = &input_warning {
        log::warn!("{w}");
    }
    println!(
        "slam: {} {}x{}, backend {}, masks {}{}",
        match (total, &a.live) {
            (Some(n), _) => format!("{n} frames"),
            (None, live) => format!("live input `{}`", live.as_deref().unwrap_or("?")),
        },
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
    let mut slam = match Slam::new(config, camera, backend, vocabulary, map) {
        Ok(s) => s,
        Err(e) => {
            let e = anyhow::Error::new(e);
            writer.end(
                RunSummary::default(),
                RunStatus::Failed(super::outcome::message(&e)),
            )?;
            return Err(e);
        }
    };
    if let Some(r) = rerun.as_mut() {
        r.attach(&slam, &camera);
    }
    let bar = match total {
        Some(n) => {
            let bar = ProgressBar::new(n as u64);
            bar.set_style(
                ProgressStyle::with_template(
                    "{bar:40} {pos}/{len} frames {per_sec} eta {eta} {msg}",
                )
                .unwrap_or_else(|_| ProgressStyle::default_bar()),
            );
            bar
        }
        None => {
            let bar = ProgressBar::new_spinner();
            bar.set_style(
                ProgressStyle::with_template("{spinner} {pos} frames {per_sec} {msg}")
                    .unwrap_or_else(|_| ProgressStyle::default_spinner()),
            );
            bar
        }
    };
    let mut error: Option<anyhow::Error> = None;
    let mut interrupted = false;
    let mut dropped = 0usize;
    let mut lost = 0usize;
    let mut skips = super::outputs::Skips::default();
    let mut checkpoints = super::outputs::Checkpoints::new(a.checkpoint_every);
    // The estimate so far, for the checkpoints: every posed frame as corrected by the loops
    // known when it was tracked, and each new keyframe's pose then.
    let mut corrected: Vec<TimedPose> = Vec::new();
    let mut keyframe_poses: Vec<TimedPose> = Vec::new();
    let provenance_value = serde_json::to_value(provenance)?;
    let mut load_ms = Vec::new();
    let mut i = 0usize;
    let start = Instant::now();
    while i < n {
        if stop.requested() {
            interrupted = true;
            break;
        }
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
        let frame = match source.frame(i) {
            // The end of a live stream.
            None => break,
            Some(Ok((f, decode_ms))) => {
                load_ms.push(decode_ms.unwrap_or_else(|| tl.elapsed().as_secs_f64() * 1e3));
                f
            }
            Some(Err(e)) if frame_content_error(&e) => {
                if let Some(stop) = skips.skip(i, anyhow::Error::new(e)) {
                    error = Some(stop);
                    break;
                }
                bar.inc(1);
                i += 1;
                continue;
            }
            Some(Err(e)) => {
                error = Some(anyhow::Error::new(e).context(format!("frame {i}")));
                break;
            }
        };
        match slam.process(&frame) {
            Ok(r) => {
                if let Some(rr) = rerun.as_mut() {
                    rr.slam_frame(&frame, &r);
                }
                if let Err(e) = write_frame(&mut writer, &slam, &r.record) {
                    error = Some(e.context(format!("frame {i}")));
                    break;
                }
                if r.status == FrameStatus::Lost {
                    lost += 1;
                }
                if let Some(p) = r.world_from_camera {
                    let pose = TimedPose {
                        timestamp: r.record.timestamp,
                        world_from_camera: p,
                    };
                    corrected.push(pose);
                    if r.status == FrameStatus::NewKeyframe {
                        keyframe_poses.push(pose);
                    }
                }
                if checkpoints.due(r.record.timestamp) {
                    let mut summary = RunSummary {
                        frames: slam.frames(),
                        dropped,
                        skipped_frames: skips.count,
                        tracked: corrected.len(),
                        lost,
                        keyframes: slam.map_keyframes() + keyframe_poses.len(),
                        wall_s: t0.elapsed().as_secs_f64(),
                        warnings: input_warning.iter().cloned().collect(),
                        ..Default::default()
                    };
                    summary
                        .extra
                        .insert("provenance".into(), provenance_value.clone());
                    if let Err(e) = writer.checkpoint(&corrected, &keyframe_poses, summary) {
                        // The files hold the previous checkpoint (each is replaced whole).
                        error = Some(anyhow::Error::new(e).context(format!(
                            "checkpoint after frame {i} (the previous checkpoint is kept)"
                        )));
                        break;
                    }
                }
                bar.set_message(format!(
                    "kf {} loops {} lost {lost}{}",
                    r.keyframes,
                    r.loops,
                    if let Input::Live(l) = &*source {
                        format!(" dropped {}", l.dropped())
                    } else if a.realtime.is_some() {
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
            // Wait for the next frame to arrive (`--realtime` is range-checked, so the wait
            // is finite and representable).
            let due = i as f64 / fps;
            let now = start.elapsed().as_secs_f64();
            if let Ok(wait) = std::time::Duration::try_from_secs_f64(due - now) {
                std::thread::sleep(wait);
            }
        }
    }
    bar.finish_and_clear();
    if let Input::Live(live) = source {
        match live.finish() {
            Ok(s) => {
                dropped += s.dropped as usize;
                println!(
                    "live: {} frames received, {} dropped while tracking was busy{}",
                    s.received,
                    s.dropped,
                    match &a.record {
                        Some(d) => format!(", {} recorded in {}", s.recorded, d.display()),
                        None => String::new(),
                    }
                );
            }
            Err(e) => {
                let e = anyhow::Error::new(e).context("live input");
                error = Some(match error.take() {
                    Some(first) => first.context(format!("and then: {e:#}")),
                    None => e,
                });
            }
        }
    }
    let processed = slam.frames();
    let result = match slam.finish() {
        Ok(r) => r,
        Err(e) => {
            // The back-end's own error, reported once; the per-frame files hold every frame
            // processed before it and the summary says the run failed.
            let e = match error {
                // The same cause (a lost device) stops the back-end too: said once.
                Some(first)
                    if super::outcome::message(&first)
                        .contains(e.to_string().trim_end_matches([':', ' '])) =>
                {
                    first
                }
                Some(first) => anyhow::anyhow!(
                    "{}; and then finishing failed: {e}",
                    super::outcome::message(&first)
                ),
                None => anyhow::Error::new(e),
            };
            let summary = RunSummary {
                frames: processed,
                dropped,
                skipped_frames: skips.count,
                wall_s: t0.elapsed().as_secs_f64(),
                ..Default::default()
            };
            writer.end(summary, RunStatus::Failed(super::outcome::message(&e)))?;
            return Err(e.context(format!(
                "the {processed} frames processed before the error are in {}",
                a.out.display()
            )));
        }
    };
    let wall = t0.elapsed().as_secs_f64();
    let status = match (&error, interrupted) {
        (Some(e), _) => RunStatus::Failed(super::outcome::message(e)),
        (None, true) => RunStatus::Interrupted,
        (None, false) => RunStatus::Complete,
    };
    let mut warnings: Vec<String> = input_warning.into_iter().collect();
    if let Some(Err(e)) = rerun.map(|r| r.slam_finish(&result)) {
        warnings.push(e.to_string());
    }
    if let Some(w) = skips.warning() {
        warnings.push(format!("{w} (counted in summary.json)"));
    }
    let warnings = write_outputs(
        a,
        writer,
        source,
        &camera,
        backend,
        &result,
        &mut load_ms,
        (dropped, skips.count),
        processed,
        wall,
        provenance,
        status,
        warnings,
    )
    .map_err(|e| final_write_failed(e, error.take(), &a.out))?;
    if let Some(e) = error {
        return Err(if processed > 0 {
            e.context(format!(
                "the {processed} frames processed before the error are in {}",
                a.out.display()
            ))
        } else {
            e
        });
    }
    if interrupted {
        return Err(super::outcome::Interrupted {
            out: Some(a.out.clone()),
        }
        .into());
    }
    super::outcome::warnings(warnings)
}

/// The error of a run whose final outputs could not be written (a full disk, a folder gone),
/// after `first` stopped it or not: the files of the last checkpoint are what remains.
fn final_write_failed(
    e: anyhow::Error,
    first: Option<anyhow::Error>,
    out: &std::path::Path,
) -> anyhow::Error {
    let kept = format!("{} keeps the files of the last checkpoint", out.display());
    match first {
        Some(first) => first.context(format!(
            "the final outputs could not be written either ({}); {kept}",
            super::outcome::message(&e)
        )),
        None => e.context(format!("writing the final outputs; {kept}")),
    }
}

/// Whether a frame's load error concerns that frame's content alone (see
/// [`super::outputs::frame_content_error`]).
fn frame_content_error(e: &rgbid::source::SourceError) -> bool {
    matches!(e, rgbid::source::SourceError::Io(io) if super::outputs::frame_content_error(io))
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
    source: &Input,
    camera: &PinholeCamera,
    backend: &ComputeBackend,
    r: &SlamResult,
    load_ms: &mut [f64],
    (dropped, skipped): (usize, usize),
    processed: usize,
    wall: f64,
    provenance: &Provenance,
    status: RunStatus,
    mut warnings: Vec<String>,
) -> Result<Vec<String>> {
    let out = &a.out;
    writer.trajectory(&r.trajectory)?;
    let kf_traj: Vec<TimedPose> = r.keyframe_trajectory();
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
        let filtered = build_coloured_model(r.keyframes(), &r.keyframe_poses, camera, &params);
        model_points = filtered.len();
        writer.model_coloured(&filtered)?;
    }
    let mut mesh_summary = None;
    if a.mesh {
        let t = Instant::now();
        // The keyframes at their optimised poses, as `SlamResult::volume` integrates them,
        // with the device budget.
        let mesh_params = TsdfParams {
            voxel_size: a.voxel,
            device_blocks: a.mesh_device_blocks,
            ..Default::default()
        };
        let volume = build_volume(
            r.keyframes(),
            &r.keyframe_poses,
            camera,
            &mesh_params,
            ModelParams::default().min_weight,
            backend,
        )?;
        let mesh = volume.extract_mesh()?;
        let path = out.join(rgbid::io::run_folder::files::MESH);
        mesh.write_ply(&path)?;
        let seconds = t.elapsed().as_secs_f64();
        let volume_path = out.join(rgbid::io::run_folder::files::VOLUME);
        volume.save(&volume_path)?;
        mesh_summary = Some(serde_json::json!({
            "seconds": seconds,
            "vertices": mesh.vertices.len(),
            "triangles": mesh.triangles.len(),
            "blocks": volume.block_count(),
        }));
        println!(
            "mesh: {} keyframes integrated at their optimised poses, {} vertices, {} \
             triangles, {:.2} s -> {} (volume: {})",
            r.keyframes().len(),
            mesh.vertices.len(),
            mesh.triangles.len(),
            seconds,
            path.display(),
            volume_path.display()
        );
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
        .filter(|l| l.verdict.is_accepted() && !l.relocalisation)
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
        skipped_frames: skipped,
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
    summary
        .extra
        .insert("provenance".into(), serde_json::to_value(provenance)?);
    if let Some(m) = mesh_summary {
        // Built after the last frame: not part of `wall_s`.
        summary.extra.insert("mesh".into(), m);
    }
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
                Err(e) => warnings.push(format!("{name} trajectory not evaluated: {e}")),
            }
        }
    }
    summary.warnings = warnings.clone();
    writer.end(summary, status)?;
    println!("wrote {}", out.display());
    Ok(warnings)
}
