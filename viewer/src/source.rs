//! Where frames come from: a TUM RGB-D folder or a generated (`rgbid::synth`) sequence. The
//! same opening rules as `rgbid slam` (see `src/cli/slam.rs` of the library).

use std::path::PathBuf;
use std::sync::Arc;

use anyhow::{bail, Context, Result};
use rgbid::camera::PinholeCamera;
use rgbid::gpu::ComputeBackend;
use rgbid::image::RgbdFrame;
use rgbid::io::trajectory::{read_tum, TimedPose};
use rgbid::io::tum::{OpenOptions, TumSequence};
use rgbid::synth::{
    CameraModel, RenderBackend, Scene, Sequence, SequenceConfig, Trajectory, TrajectoryKind,
};

/// What to open: a description that can be sent to the worker thread and reopened.
#[derive(Clone, Debug, PartialEq)]
pub enum SourceSpec {
    /// A TUM RGB-D folder (rgb.txt + depth.txt or associations.txt).
    Tum {
        /// The folder.
        dir: PathBuf,
        /// Camera preset or calibration file (see `rgbid odometry --help`).
        camera: Option<String>,
        /// Only the first N frames.
        max_frames: Option<usize>,
    },
    /// A generated sequence `SCENE:TRAJECTORY` (e.g. `office:loop`).
    Synth {
        /// `SCENE:TRAJECTORY`.
        spec: String,
        /// Number of frames (30 per second).
        frames: usize,
        /// Image width (height is 3/4 of it).
        width: u32,
        /// Seed of the scene, trajectory and noise.
        seed: u64,
        /// Duration of the whole trajectory (a loop: one lap), seconds; `None` = the
        /// sequence's duration. Longer than the sequence plays only the start of it.
        trajectory_seconds: Option<f64>,
    },
}

impl SourceSpec {
    /// A short label for the title bar.
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

/// An opened source of frames.
pub enum Source {
    /// A TUM folder.
    Tum(TumSequence),
    /// A generated sequence.
    Synth(Box<Sequence>, PinholeCamera),
}

impl Source {
    /// Opens `spec`; generated sequences render on `backend`.
    pub fn open(spec: &SourceSpec, backend: &ComputeBackend) -> Result<Source> {
        match spec {
            SourceSpec::Synth {
                spec,
                frames,
                width,
                seed,
                trajectory_seconds,
            } => {
                let (scene_name, traj) = spec.split_once(':').unwrap_or((spec.as_str(), "loop"));
                if *width < 16 || *frames == 0 {
                    bail!("a generated sequence needs width >= 16 and at least one frame");
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
                let scene = Arc::new(Scene::preset(scene_name, *seed)?);
                let kind = TrajectoryKind::from_name(traj)?;
                let config = SequenceConfig {
                    frames: *frames,
                    seed: *seed,
                    ..Default::default()
                };
                let seconds = trajectory_seconds.unwrap_or(config.duration());
                if !(seconds.is_finite() && seconds > 0.0) {
                    bail!("the trajectory duration must be > 0 s");
                }
                let trajectory = Trajectory::new(kind, &scene, seconds, *seed)?;
                let rb = match backend {
                    ComputeBackend::Cpu => RenderBackend::Cpu,
                    ComputeBackend::Gpu(g) => RenderBackend::Gpu(g.clone()),
                };
                let seq = Sequence::new(scene, CameraModel::Pinhole(cam), trajectory, config, &rb)?;
                Ok(Source::Synth(Box::new(seq), cam))
            }
            SourceSpec::Tum {
                dir,
                camera,
                max_frames,
            } => {
                let mut opts = OpenOptions {
                    max_frames: *max_frames,
                    ..Default::default()
                };
                if let Some(c) = camera {
                    opts.camera = Some(c.parse().with_context(|| format!("camera '{c}'"))?);
                }
                Ok(Source::Tum(TumSequence::open(dir, &opts)?))
            }
        }
    }

    /// Number of frames.
    pub fn len(&self) -> usize {
        match self {
            Source::Tum(s) => s.len(),
            Source::Synth(s, _) => s.len(),
        }
    }

    /// True when there are no frames.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The (undistorted pinhole) camera.
    pub fn camera(&self) -> PinholeCamera {
        match self {
            Source::Tum(s) => s.camera,
            Source::Synth(_, c) => *c,
        }
    }

    /// Frame `i`.
    pub fn load(&mut self, i: usize) -> Result<RgbdFrame> {
        match self {
            Source::Tum(s) => Ok(s.load(i)?),
            Source::Synth(s, _) => {
                let f = s.render_frame(i)?;
                Ok(f.frame.to_rgbd_frame(f.timestamp))
            }
        }
    }

    /// Ground truth (`world_from_camera` per time stamp), if there is any.
    pub fn groundtruth(&self) -> Option<Vec<TimedPose>> {
        match self {
            Source::Tum(s) => s.groundtruth.as_ref().and_then(|p| read_tum(p).ok()),
            Source::Synth(s, _) => Some(s.ground_truth()),
        }
    }
}
