//! Monocular SLAM on generated sequences with exact ground truth (`crate::synth`): renders
//! the grey images once, runs [`MonoSlam`] and scores the trajectory after a similarity
//! (Sim(3)) alignment, since monocular SLAM has no metric scale.

use std::sync::Arc;

use crate::camera::{PinholeCamera, UnifiedCamera};
use crate::eval::ate::{ate, AteResult};
use crate::image::ImageF32;
use crate::mono::filter::FrameReport;
use crate::mono::{MonoConfig, MonoError, MonoSlam, MonoStats};
use crate::synth::{
    CameraModel, RenderBackend, Scene, SensorModel, Sequence, SequenceConfig, Trajectory,
    TrajectoryKind,
};
use crate::trajectory::TimedPose;

/// Which synthetic camera.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
pub enum SyntheticCamera {
    /// Pinhole with `f = 525 * width / 640` pixels (unified model with `xi = 0`).
    Pinhole,
    /// Catadioptric camera ([`UnifiedCamera::catadioptric`]).
    Catadioptric,
}

/// A synthetic sequence to render.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct SyntheticSpec {
    /// Camera kind.
    pub camera: SyntheticCamera,
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
    /// Frames.
    pub frames: usize,
    /// Frame rate, frames per second.
    pub fps: f64,
    /// Scene preset (`office`, `kitchen`, `corridor`, `lab`, `home`).
    pub scene: String,
    /// Trajectory name (`handheld`, `slow`, ...).
    pub trajectory: String,
    /// Seed of scene, trajectory and sensor noise.
    pub seed: u64,
    /// Add the sensor's image noise.
    pub noise: bool,
}

impl SyntheticSpec {
    /// A short sequence: `frames` frames at 30 fps of the office scene, handheld.
    pub fn new(camera: SyntheticCamera, width: u32, height: u32, frames: usize) -> Self {
        SyntheticSpec {
            camera,
            width,
            height,
            frames,
            fps: 30.0,
            scene: "office".into(),
            trajectory: "handheld".into(),
            seed: 7,
            noise: true,
        }
    }

    /// The camera model used for rendering and for the filter.
    pub fn camera_model(&self) -> (CameraModel, UnifiedCamera) {
        match self.camera {
            SyntheticCamera::Pinhole => {
                let f = 525.0 * f64::from(self.width) / 640.0;
                let (cx, cy) = (
                    f64::from(self.width) * 0.5 - 0.5,
                    f64::from(self.height) * 0.5 - 0.5,
                );
                (
                    CameraModel::Pinhole(PinholeCamera::new(f, f, cx, cy, self.width, self.height)),
                    UnifiedCamera::new(0.0, f, cx, cy, self.width, self.height),
                )
            }
            SyntheticCamera::Catadioptric => {
                let c = UnifiedCamera::catadioptric(self.width, self.height);
                (CameraModel::Unified(c), c)
            }
        }
    }
}

/// Rendered grey frames with their ground truth.
#[derive(Clone, Debug)]
pub struct SyntheticFrames {
    /// The camera (unified model).
    pub camera: UnifiedCamera,
    /// `(timestamp, intensity)` per frame.
    pub images: Vec<(f64, ImageF32)>,
    /// Ground truth `world_from_camera` per frame (metres, synth world frame).
    pub ground_truth: Vec<TimedPose>,
}

/// Renders a synthetic sequence on the CPU.
pub fn render(spec: &SyntheticSpec) -> Result<SyntheticFrames, MonoError> {
    let scene = Arc::new(Scene::preset(&spec.scene, spec.seed)?);
    let kind = TrajectoryKind::from_name(&spec.trajectory)?;
    let config = SequenceConfig {
        frames: spec.frames,
        fps: spec.fps,
        start_time: 0.0,
        sensor: if spec.noise {
            SensorModel::kinect()
        } else {
            SensorModel::noiseless()
        },
        seed: spec.seed,
        exposure_changes: false,
        motion_blur: 0,
        exposure_time: 1.0 / 60.0,
    };
    let trajectory = Trajectory::new(kind, &scene, config.duration(), spec.seed)?;
    let (model, camera) = spec.camera_model();
    let mut seq = Sequence::new(scene, model, trajectory, config, &RenderBackend::Cpu)?;
    let mut images = Vec::with_capacity(spec.frames);
    let mut ground_truth = Vec::with_capacity(spec.frames);
    for i in 0..spec.frames {
        let f = seq.render_frame(i)?;
        images.push((f.timestamp, f.frame.intensity));
        ground_truth.push(TimedPose {
            timestamp: f.timestamp,
            world_from_camera: f.world_from_camera,
        });
    }
    Ok(SyntheticFrames {
        camera,
        images,
        ground_truth,
    })
}

/// The outcome of a run with ground truth.
#[derive(Clone, Debug)]
pub struct RunResult {
    /// Estimated `world_from_camera` per frame (filter world frame, unknown scale).
    pub estimate: Vec<TimedPose>,
    /// Per-frame reports.
    pub reports: Vec<FrameReport>,
    /// ATE after a Sim(3) alignment (metres of the ground truth).
    pub ate: AteResult,
    /// Length of the ground-truth path, metres.
    pub path_length: f64,
    /// Run statistics.
    pub stats: MonoStats,
    /// Landmarks in the state that are 3D points at the end.
    pub points_in_state: usize,
}

/// Runs the filter over rendered frames and scores it against their ground truth.
pub fn run(frames: &SyntheticFrames, config: &MonoConfig) -> Result<RunResult, MonoError> {
    let mut slam = MonoSlam::new(frames.camera, config.clone())?;
    let mut estimate = Vec::with_capacity(frames.images.len());
    let mut reports = Vec::with_capacity(frames.images.len());
    for (t, img) in &frames.images {
        let r = slam.process(*t, img)?;
        estimate.push(TimedPose {
            timestamp: *t,
            world_from_camera: r.world_from_camera,
        });
        reports.push(r);
    }
    let ate = ate(&frames.ground_truth, &estimate, true)?;
    let path_length = frames
        .ground_truth
        .windows(2)
        .map(|w| (w[1].world_from_camera.translation - w[0].world_from_camera.translation).length())
        .sum();
    Ok(RunResult {
        estimate,
        reports,
        ate,
        path_length,
        stats: *slam.stats(),
        points_in_state: slam.points_in_state(),
    })
}
