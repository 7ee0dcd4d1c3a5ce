//! Sequences: a trajectory rendered frame by frame, streamed in memory as an iterator of
//! [`SequenceFrame`] (time stamp, ground-truth `world_from_camera`, rendered frame), so
//! callers need no files.

use std::sync::Arc;

use super::raycast::pcg_hash;
use super::render::{finish_frame, CameraModel, RenderBackend, RenderedFrame, Renderer};
use super::scene::Scene;
use super::sensor::SensorModel;
use super::trajectory::Trajectory;
use super::SynthError;
use crate::geometry::Se3;
use crate::trajectory::TimedPose;

/// How a sequence is sampled and sensed.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SequenceConfig {
    /// Number of frames.
    pub frames: usize,
    /// Frame rate, frames per second.
    pub fps: f64,
    /// Time stamp of the first frame, seconds.
    pub start_time: f64,
    /// Sensor model.
    pub sensor: SensorModel,
    /// Seed of the sensor noise (each frame derives its own).
    pub seed: u64,
    /// Vary the exposure gain smoothly between frames (auto-exposure), +-20%.
    pub exposure_changes: bool,
    /// Motion blur: number of sub-frame renders averaged over the exposure (0 or 1 = off).
    pub motion_blur: usize,
    /// Exposure time for motion blur, seconds.
    pub exposure_time: f64,
}

impl Default for SequenceConfig {
    fn default() -> Self {
        SequenceConfig {
            frames: 300,
            fps: 30.0,
            start_time: 0.0,
            sensor: SensorModel::kinect(),
            seed: 0,
            exposure_changes: false,
            motion_blur: 0,
            exposure_time: 1.0 / 60.0,
        }
    }
}

impl SequenceConfig {
    /// Duration covered by the frames, seconds (`frames / fps`, the last frame at
    /// `(frames - 1) / fps`).
    pub fn duration(&self) -> f64 {
        self.frames.max(1) as f64 / self.fps
    }
}

/// One frame of a sequence.
#[derive(Clone, Debug)]
pub struct SequenceFrame {
    /// Frame index from 0.
    pub index: usize,
    /// Time stamp, seconds.
    pub timestamp: f64,
    /// Ground-truth pose of the camera, `world_from_camera`.
    pub world_from_camera: Se3,
    /// The rendered frame.
    pub frame: RenderedFrame,
}

/// A sequence being rendered: iterate it to get the frames in order.
pub struct Sequence {
    renderer: Renderer,
    trajectory: Trajectory,
    config: SequenceConfig,
    next: usize,
}

impl Sequence {
    /// Prepares a sequence of `scene` seen through `camera` along `trajectory`.
    pub fn new(
        scene: Arc<Scene>,
        camera: CameraModel,
        trajectory: Trajectory,
        config: SequenceConfig,
        backend: &RenderBackend,
    ) -> Result<Sequence, SynthError> {
        if !(config.fps.is_finite() && config.fps > 0.0) {
            return Err(SynthError::InvalidParameter {
                name: "fps",
                why: format!("{} must be > 0", config.fps),
            });
        }
        let renderer = Renderer::new(scene, camera, backend)?;
        Ok(Sequence {
            renderer,
            trajectory,
            config,
            next: 0,
        })
    }

    /// The configuration.
    pub fn config(&self) -> &SequenceConfig {
        &self.config
    }
    /// The trajectory.
    pub fn trajectory(&self) -> &Trajectory {
        &self.trajectory
    }
    /// The renderer (camera, scene, backend).
    pub fn renderer(&self) -> &Renderer {
        &self.renderer
    }
    /// Number of frames.
    pub fn len(&self) -> usize {
        self.config.frames
    }
    /// True when the sequence has no frames.
    pub fn is_empty(&self) -> bool {
        self.config.frames == 0
    }

    /// Time (from the trajectory's start) of frame `index`.
    fn local_time(&self, index: usize) -> f64 {
        index as f64 / self.config.fps
    }

    /// The ground truth of every frame (`world_from_camera` with time stamps).
    pub fn ground_truth(&self) -> Vec<TimedPose> {
        (0..self.config.frames)
            .map(|i| TimedPose {
                timestamp: self.config.start_time + self.local_time(i),
                world_from_camera: self.trajectory.pose_at(self.local_time(i)),
            })
            .collect()
    }

    /// Exposure gain of frame `index`.
    pub fn gain(&self, index: usize) -> f64 {
        if !self.config.exposure_changes {
            return self.config.sensor.gain;
        }
        let t = self.local_time(index);
        self.config.sensor.gain
            * (1.0
                + 0.15 * (std::f64::consts::TAU * t / 7.0).sin()
                + 0.05 * (std::f64::consts::TAU * t / 2.3).sin())
    }

    /// Renders frame `index` (any order).
    pub fn render_frame(&mut self, index: usize) -> Result<SequenceFrame, SynthError> {
        let t = self.local_time(index);
        let pose = self.trajectory.pose_at(t);
        let mut samples = self.renderer.cast(&pose)?;
        let blur = self.config.motion_blur;
        if blur > 1 {
            // Average the colour over the exposure; depth comes from the mid-exposure pose.
            let mut acc: Vec<[f32; 3]> = samples.iter().map(|s| s.rgb).collect();
            for k in 0..blur {
                let dt = self.config.exposure_time * ((k as f64 + 0.5) / blur as f64 - 0.5);
                let sub = self.renderer.cast(&self.trajectory.pose_at(t + dt))?;
                for (a, s) in acc.iter_mut().zip(&sub) {
                    for c in 0..3 {
                        a[c] += s.rgb[c];
                    }
                }
            }
            let n = (blur + 1) as f32;
            for (s, a) in samples.iter_mut().zip(&acc) {
                s.rgb = [a[0] / n, a[1] / n, a[2] / n];
            }
        }
        let mut sensor = self.config.sensor.clone();
        sensor.gain = self.gain(index);
        let seed = self.config.seed
            ^ (u64::from(pcg_hash(index as u32 ^ 0x51ed_270b)) << 32)
            ^ index as u64;
        let cam = *self.renderer.camera();
        let frame = finish_frame(
            self.renderer.scene(),
            &samples,
            cam.width(),
            cam.height(),
            &sensor,
            cam.focal_px(),
            seed,
        );
        Ok(SequenceFrame {
            index,
            timestamp: self.config.start_time + t,
            world_from_camera: pose,
            frame,
        })
    }
}

impl Iterator for Sequence {
    type Item = Result<SequenceFrame, SynthError>;

    fn next(&mut self) -> Option<Self::Item> {
        if self.next >= self.config.frames {
            return None;
        }
        let i = self.next;
        self.next += 1;
        Some(self.render_frame(i))
    }

    fn size_hint(&self) -> (usize, Option<usize>) {
        let left = self.config.frames - self.next;
        (left, Some(left))
    }
}
