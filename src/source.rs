//! Where frames come from: a TUM RGB-D folder or a generated ([`crate::synth`]) sequence, behind
//! one interface (used by `rgbid slam`, `rgbid demo` and the viewer).

use std::path::PathBuf;
use std::sync::Arc;

use crate::camera::PinholeCamera;
use crate::gpu::ComputeBackend;
use crate::image::RgbdFrame;
use crate::io::tum::{OpenOptions, TumSequence};
use crate::io::{IoError, Layout};
use crate::synth::{
    CameraModel, RenderBackend, Scene, Sequence, SequenceConfig, SynthError, Trajectory,
    TrajectoryKind,
};
use crate::trajectory::TimedPose;

/// Errors of [`FrameSource`].
#[derive(Debug, thiserror::Error)]
pub enum SourceError {
    /// Reading the TUM folder (or the camera file) failed.
    #[error(transparent)]
    Io(#[from] IoError),
    /// Building or rendering the generated sequence failed.
    #[error(transparent)]
    Synth(#[from] SynthError),
    /// The description itself is unusable.
    #[error("{0}")]
    Invalid(String),
}

/// What to open: a description that can be sent to another thread and reopened.
#[derive(Clone, Debug, PartialEq)]
pub enum SourceSpec {
    /// An RGB-D sequence folder: TUM RGB-D (rgb.txt + depth.txt or associations.txt) or
    /// another [`Layout`] (ETH3D, 7-Scenes, Replica).
    Tum {
        /// The folder.
        dir: PathBuf,
        /// Its layout; `None` detects it from the folder's content.
        format: Option<Layout>,
        /// Camera preset or calibration file (see `rgbid odometry --help`); `None` = the
        /// folder's `calib.txt`, else the default preset.
        camera: Option<String>,
        /// Only the first N frames.
        max_frames: Option<usize>,
    },
    /// A generated sequence `SCENE:TRAJECTORY` (e.g. `office:loop`) seen by a pinhole camera
    /// with the Kinect's field of view (fx = 525 px at 640 wide).
    Synth {
        /// `SCENE:TRAJECTORY` (`SCENE` alone means `SCENE:loop`).
        spec: String,
        /// Number of frames (30 per second).
        frames: usize,
        /// Image width in pixels (the height is 3/4 of it).
        width: u32,
        /// Seed of the scene, trajectory and noise.
        seed: u64,
        /// Session of the scene (0 = as generated; k > 0 moves, removes and adds objects, and
        /// the sensor noise seed changes with it).
        session: u32,
        /// Duration of the trajectory in seconds (one lap of a loop, which then repeats);
        /// `None` = the sequence's duration.
        lap_seconds: Option<f64>,
    },
}

impl SourceSpec {
    /// A short label (for titles and logs).
    pub fn label(&self) -> String {
        match self {
            SourceSpec::Tum { dir, .. } => dir.display().to_string(),
            SourceSpec::Synth {
                spec,
                frames,
                width,
                ..
            } => format!("synth {spec} ({frames} frames, {width} px)"),
        }
    }
}

/// The options that describe a generated sequence, shared by `rgbid slam`, `rgbid demo` and
/// the viewer (with the `clap` feature, a `clap::Args` group: `--synth`, `--frames`, `--laps`,
/// `--width`, `--seed`).
#[derive(Clone, Debug, PartialEq)]
#[cfg_attr(feature = "clap", derive(clap::Args))]
pub struct SynthOptions {
    /// Generate the sequence instead of reading a folder: `SCENE:TRAJECTORY` (e.g.
    /// `office:loop`; `rgbid synth --help` lists the names). `rgbid demo` uses `office:loop`
    /// when it is not given.
    #[cfg_attr(feature = "clap", arg(long, value_name = "SCENE:TRAJECTORY"))]
    pub synth: Option<String>,
    /// Frames of the generated sequence, at 30 per second (>= 1).
    #[cfg_attr(feature = "clap", arg(long, value_parser = ranges::frames, default_value_t = SynthOptions::default().frames))]
    pub frames: usize,
    /// Laps of a `loop` trajectory over the frames (> 0; the same closed path again, so a
    /// second lap revisits every place of the first: 1.3 revisits the start for the last
    /// 30 % of the frames). Other trajectories ignore it.
    #[cfg_attr(feature = "clap", arg(long, value_parser = ranges::laps, default_value_t = SynthOptions::default().laps))]
    pub laps: f64,
    /// Image width of the generated sequence in pixels (the height is 3/4 of it), 16 to
    /// 16384.
    #[cfg_attr(feature = "clap", arg(long, value_parser = ranges::width, default_value_t = SynthOptions::default().width))]
    pub width: u32,
    /// Seed of the generated scene, trajectory and sensor noise (any whole number, 0 to
    /// 2^64-1).
    #[cfg_attr(feature = "clap", arg(long, value_parser = ranges::seed, default_value_t = SynthOptions::default().seed))]
    pub seed: u64,
}

/// Value parsers of [`SynthOptions`]' command-line options: a bad value is a usage error
/// that names the valid range (clap names the option).
#[cfg(feature = "clap")]
mod ranges {
    pub(super) fn frames(s: &str) -> Result<usize, String> {
        match s.trim().parse::<usize>() {
            Ok(v) if v >= 1 => Ok(v),
            _ => Err("must be a whole number >= 1".into()),
        }
    }

    pub(super) fn laps(s: &str) -> Result<f64, String> {
        match s.trim().parse::<f64>() {
            Ok(v) if v.is_finite() && v > 0.0 => Ok(v),
            _ => Err("must be a finite number > 0".into()),
        }
    }

    pub(super) fn width(s: &str) -> Result<u32, String> {
        match s.trim().parse::<u32>() {
            Ok(v) if (16..=16384).contains(&v) => Ok(v),
            _ => Err("must be a whole number in 16 to 16384".into()),
        }
    }

    pub(super) fn seed(s: &str) -> Result<u64, String> {
        s.trim()
            .parse()
            .map_err(|_| "not a whole number in 0 to 18446744073709551615".into())
    }
}

impl Default for SynthOptions {
    /// 390 frames (13 s) of 1.3 laps at 320 x 240, seed 7: the demo's closed loop, which
    /// runs in about a minute on two cores without a GPU.
    fn default() -> Self {
        SynthOptions {
            synth: None,
            frames: 390,
            laps: 1.3,
            width: 320,
            seed: 7,
        }
    }
}

impl SynthOptions {
    /// The generated sequence when none is named (`rgbid demo`, the viewer's button).
    pub const DEFAULT_SPEC: &'static str = "office:loop";

    /// The generated sequence these options describe, or `None` without `--synth`.
    /// `max_frames` caps the frames; `session` is the scene's session (0 = as generated).
    pub fn spec(
        &self,
        session: u32,
        max_frames: Option<usize>,
    ) -> Result<Option<SourceSpec>, SourceError> {
        match &self.synth {
            Some(spec) => self.spec_of(spec, session, max_frames).map(Some),
            None => Ok(None),
        }
    }

    /// The sequence `spec` (`SCENE:TRAJECTORY`) with these frames, laps, width and seed.
    pub fn spec_of(
        &self,
        spec: &str,
        session: u32,
        max_frames: Option<usize>,
    ) -> Result<SourceSpec, SourceError> {
        let frames = max_frames.unwrap_or(self.frames).min(self.frames);
        if frames == 0 {
            return Err(SourceError::Invalid("--frames must be >= 1".into()));
        }
        if !(self.laps.is_finite() && self.laps > 0.0) {
            return Err(SourceError::Invalid(format!(
                "--laps must be > 0 (got {})",
                self.laps
            )));
        }
        let traj = spec.split_once(':').map_or("loop", |(_, t)| t);
        let lap_seconds = if TrajectoryKind::from_name(traj)? == TrajectoryKind::Loop {
            Some(
                SequenceConfig {
                    frames,
                    ..Default::default()
                }
                .duration()
                    / self.laps,
            )
        } else {
            None
        };
        Ok(SourceSpec::Synth {
            spec: spec.to_string(),
            frames,
            width: self.width,
            seed: self.seed,
            session,
            lap_seconds,
        })
    }
}

/// An opened source of frames.
pub enum FrameSource {
    /// A TUM folder, streamed from disk.
    Tum(TumSequence),
    /// A generated sequence, rendered frame by frame, and its camera.
    Synth(Box<Sequence>, PinholeCamera),
}

impl FrameSource {
    /// Opens `spec`; generated sequences render on `backend` with the Kinect-like sensor
    /// model ([`crate::synth::SensorModel::kinect`]).
    pub fn open(spec: &SourceSpec, backend: &ComputeBackend) -> Result<FrameSource, SourceError> {
        Self::open_with_sensor(spec, backend, None)
    }

    /// Opens `spec`; generated sequences render on `backend` with `sensor` (`None` = the
    /// Kinect-like default; ignored for TUM folders).
    pub fn open_with_sensor(
        spec: &SourceSpec,
        backend: &ComputeBackend,
        sensor: Option<crate::synth::SensorModel>,
    ) -> Result<FrameSource, SourceError> {
        match spec {
            SourceSpec::Synth {
                spec,
                frames,
                width,
                seed,
                session,
                lap_seconds,
            } => {
                let (scene_name, traj) = spec.split_once(':').unwrap_or((spec.as_str(), "loop"));
                if *width < 16 || *frames == 0 {
                    return Err(SourceError::Invalid(
                        "a generated sequence needs width >= 16 and at least one frame".into(),
                    ));
                }
                let (w, h) = (*width, *width * 3 / 4);
                let f = 525.0 * f64::from(w) / 640.0;
                let cam = PinholeCamera::new(
                    f,
                    f,
                    (f64::from(w) - 1.0) / 2.0,
                    (f64::from(h) - 1.0) / 2.0,
                    w,
                    h,
                );
                let base = Scene::preset(scene_name, *seed)?;
                let scene = Arc::new(if *session > 0 {
                    base.session(*session)
                } else {
                    base
                });
                let kind = TrajectoryKind::from_name(traj)?;
                let mut config = SequenceConfig {
                    frames: *frames,
                    seed: seed + u64::from(*session) * 1000,
                    ..Default::default()
                };
                if let Some(sensor) = sensor {
                    config.sensor = sensor;
                }
                let seconds = lap_seconds.unwrap_or(config.duration());
                if !(seconds.is_finite() && seconds > 0.0) {
                    return Err(SourceError::Invalid(format!(
                        "the trajectory duration must be > 0 s (got {seconds})"
                    )));
                }
                let trajectory = Trajectory::new(kind, &scene, seconds, *seed)?;
                let rb = match backend {
                    ComputeBackend::Cpu => RenderBackend::Cpu,
                    ComputeBackend::Gpu(g) => RenderBackend::Gpu(g.clone()),
                };
                let seq = Sequence::new(scene, CameraModel::Pinhole(cam), trajectory, config, &rb)?;
                Ok(FrameSource::Synth(Box::new(seq), cam))
            }
            SourceSpec::Tum {
                dir,
                format,
                camera,
                max_frames,
            } => {
                let mut opts = OpenOptions {
                    max_frames: *max_frames,
                    layout: *format,
                    ..Default::default()
                };
                if let Some(c) = camera {
                    opts.camera = Some(c.parse()?);
                }
                Ok(FrameSource::Tum(TumSequence::open(dir, &opts)?))
            }
        }
    }

    /// Number of frames.
    pub fn len(&self) -> usize {
        match self {
            FrameSource::Tum(s) => s.len(),
            FrameSource::Synth(s, _) => s.len(),
        }
    }

    /// A warning about the input found when it was opened (a depth factor that does not fit
    /// the sensor's range, see [`TumSequence::depth_range_warning`]); generated sequences
    /// have none.
    pub fn input_warning(&self) -> Option<&str> {
        match self {
            FrameSource::Tum(s) => s.depth_range_warning(),
            FrameSource::Synth(..) => None,
        }
    }

    /// True when there are no frames.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The (undistorted pinhole) camera of the frames.
    pub fn camera(&self) -> PinholeCamera {
        match self {
            FrameSource::Tum(s) => s.camera,
            FrameSource::Synth(_, c) => *c,
        }
    }

    /// Frame `i` (intensity 0-255, inverse depth 1/m).
    pub fn load(&mut self, i: usize) -> Result<RgbdFrame, SourceError> {
        match self {
            FrameSource::Tum(s) => Ok(s.load(i)?),
            FrameSource::Synth(s, _) => {
                let f = s.render_frame(i)?;
                Ok(f.frame.to_rgbd_frame(f.timestamp))
            }
        }
    }

    /// Ground truth (`world_from_camera` per time stamp), if there is any (a TUM folder's
    /// `groundtruth.txt` that cannot be read counts as none).
    pub fn groundtruth(&self) -> Option<Vec<TimedPose>> {
        match self {
            FrameSource::Tum(s) => s.ground_truth().ok().flatten(),
            FrameSource::Synth(s, _) => Some(s.ground_truth()),
        }
    }
}
