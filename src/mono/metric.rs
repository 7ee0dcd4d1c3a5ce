//! Metric monocular SLAM of a walking person (thesis 3.4, Algorithm 1): the EKF
//! ([`MonoSlam`]) with the dynamic scale estimation ([`LiveDynScale`]) fed one pose per frame
//! beside it. Every `t_upd` seconds the scale estimation closes a section and scales it by the
//! walker's step frequency; the causal metric pose of each frame is available as it is
//! processed, and [`MetricMono::finish`] gives the final trajectory, each section scaled with
//! the scale known at its end.
//!
//! The scale estimation runs on the EKF's thread: its work per pose and per update does not
//! grow with the trajectory ([`LiveDynScale`]), and [`MetricReport::scale_ms`] reports it so
//! the share it adds to a frame can be measured.

use std::time::Instant;

use super::{FrameReport, MonoConfig, MonoError, MonoSlam};
use crate::camera::UnifiedCamera;
use crate::image::ImageF32;
use crate::scale::{DynScaleConfig, DynScaleResult, LiveDynScale, ScaleError, Section};
use crate::trajectory::TimedPose;

/// One processed frame of [`MetricMono`].
#[derive(Clone, Debug)]
pub struct MetricReport {
    /// The EKF's report (pose in SLAM units, filter world = first camera).
    pub report: FrameReport,
    /// The frame's pose in metres with the scale known now (causal, eq. 3.31-3.32); `None`
    /// until the first walking window has given a scale.
    pub metric: Option<TimedPose>,
    /// The scale in effect now, metres per SLAM unit.
    pub scale: Option<f64>,
    /// Sections closed by this frame (usually none; one every `t_upd` seconds).
    pub closed: Vec<Section>,
    /// Milliseconds spent in the scale estimation for this frame.
    pub scale_ms: f64,
}

/// The trajectories of a finished [`MetricMono`] run (`world_from_camera`, filter world =
/// first camera).
#[derive(Debug)]
pub struct MetricRun {
    /// The EKF's trajectory, SLAM units.
    pub unscaled: Vec<TimedPose>,
    /// Each frame's causal metric pose, metres, from the first frame that had a scale on.
    pub causal: Vec<TimedPose>,
    /// The final output, metres: sections, up axis and the scaled trajectory (each section
    /// scaled with the scale at its end; those before the first estimate with the first).
    /// An error when the scale was unobservable (no section detected as walking); the
    /// trajectories above are kept either way.
    pub scaled: Result<DynScaleResult, ScaleError>,
}

/// Monocular EKF SLAM with metric scale from walking.
pub struct MetricMono {
    slam: MonoSlam,
    scale: LiveDynScale,
    unscaled: Vec<TimedPose>,
    causal: Vec<TimedPose>,
}

impl MetricMono {
    /// The EKF on `camera` with `mono` settings, and the scale estimation with `scale`
    /// settings (their walking model carries the walker's height; `UpAxis::Auto` finds the
    /// up axis online and then holds it, as a monocular world frame is arbitrary).
    pub fn new(
        camera: UnifiedCamera,
        mono: MonoConfig,
        scale: DynScaleConfig,
    ) -> Result<MetricMono, MonoError> {
        Ok(MetricMono {
            slam: MonoSlam::new(camera, mono)?,
            scale: LiveDynScale::new(scale)?,
            unscaled: Vec::new(),
            causal: Vec::new(),
        })
    }

    /// The EKF.
    pub fn slam(&self) -> &MonoSlam {
        &self.slam
    }

    /// The scale estimation.
    pub fn scale(&self) -> &LiveDynScale {
        &self.scale
    }

    /// Processes one grey image (intensity in `[0, 255]`) taken at `timestamp` seconds
    /// (strictly increasing).
    pub fn process(&mut self, timestamp: f64, image: &ImageF32) -> Result<MetricReport, MonoError> {
        let report = self.slam.process(timestamp, image)?;
        let pose = TimedPose {
            timestamp: report.timestamp,
            world_from_camera: report.world_from_camera,
        };
        let t0 = Instant::now();
        let closed = self.scale.push(pose)?;
        let metric = self.scale.scaled_pose();
        let scale_ms = t0.elapsed().as_secs_f64() * 1e3;
        self.unscaled.push(pose);
        if let Some(m) = metric {
            self.causal.push(m);
        }
        Ok(MetricReport {
            report,
            metric,
            scale: self.scale.scale(),
            closed,
            scale_ms,
        })
    }

    /// Ends the run: closes the last sections and scales the whole trajectory.
    pub fn finish(mut self) -> MetricRun {
        let scaled = self.scale.finish(&self.unscaled);
        MetricRun {
            unscaled: self.unscaled,
            causal: self.causal,
            scaled,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scale::{UpAxis, WalkingModel};

    #[test]
    fn a_blank_sequence_has_no_scale_keeps_its_poses_and_says_no_walking() {
        let camera = UnifiedCamera::new(0.0, 100.0, 31.5, 23.5, 64, 48);
        let cfg = DynScaleConfig {
            model: WalkingModel::grieve(1.8),
            up: UpAxis::Auto,
            ..DynScaleConfig::default()
        };
        let mut m = MetricMono::new(camera, MonoConfig::default(), cfg).unwrap();
        let img = ImageF32::filled(64, 48, 128.0);
        for k in 0..20 {
            let r = m.process(k as f64 / 30.0, &img).unwrap();
            assert!(r.metric.is_none() && r.scale.is_none() && r.closed.is_empty());
        }
        let run = m.finish();
        assert_eq!((run.unscaled.len(), run.causal.len()), (20, 0));
        let e = run.scaled.unwrap_err().to_string();
        assert!(e.contains("walking"), "{e}");
    }
}
