//! Where frames come from: a dataset folder or a generated ([`crate::synth`]) sequence, behind
//! one interface (used by `rgbid slam`, `rgbid demo` and the viewer), and [`RgbdStream`], the
//! streaming form any input can take, including frames pushed from user code ([`pushed`]).

use std::path::PathBuf;
use std::sync::Arc;

use crate::camera::PinholeCamera;
use crate::gpu::ComputeBackend;
use crate::image::RgbdFrame;
use crate::io::config::DROID_PREFIX;
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
    /// A pushed stream's receiving end is gone (its consumer stopped).
    #[error("the frame stream was closed")]
    Closed,
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
        /// Camera preset or calibration file (see `rgbid odometry --help`), or
        /// `droid:FILE` for a DROID-SLAM `calib.txt` (sized by the first frame, see
        /// [`OpenOptions::droid_calib`]); `None` = the layout's camera, the folder's
        /// `calib.txt`, else the default preset.
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
                match camera.as_deref().map(|c| (c, c.strip_prefix(DROID_PREFIX))) {
                    Some((_, Some(file))) => opts.droid_calib = Some(file.into()),
                    Some((c, None)) => opts.camera = Some(c.parse()?),
                    None => {}
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

/// A stream of RGB-D frames: what a SLAM or odometry loop consumes, whatever the frames come
/// from (a dataset folder, a generated sequence, a live camera, frames pushed from user code).
/// Implement it for your own input; [`Frames`] adapts an opened [`FrameSource`] and
/// [`pushed`] makes one fed from another thread. `Send`, so a loop can run on its own thread.
pub trait RgbdStream: Send {
    /// The undistorted pinhole camera of the frames (pixels).
    fn camera(&self) -> PinholeCamera;
    /// Number of frames still to come when known (datasets), `None` for live input.
    fn len_hint(&self) -> Option<usize>;
    /// The next frame; `None` at the end of the stream. A frame that cannot be read is an
    /// error for that frame only: the stream goes on with the next one.
    fn next_frame(&mut self) -> Option<Result<RgbdFrame, SourceError>>;
    /// Ground truth (`world_from_camera` per time stamp, seconds) when the input has some.
    fn groundtruth(&self) -> Option<Vec<TimedPose>> {
        None
    }
}

/// An opened [`FrameSource`] read in order as an [`RgbdStream`]; frames stay available by
/// index through [`Frames::source`].
pub struct Frames {
    source: FrameSource,
    next: usize,
}

impl Frames {
    /// Streams `source` from its first frame.
    pub fn new(source: FrameSource) -> Frames {
        Frames { source, next: 0 }
    }

    /// The underlying source (random access by index).
    pub fn source(&mut self) -> &mut FrameSource {
        &mut self.source
    }
}

impl RgbdStream for Frames {
    fn camera(&self) -> PinholeCamera {
        self.source.camera()
    }
    fn len_hint(&self) -> Option<usize> {
        Some(self.source.len().saturating_sub(self.next))
    }
    fn next_frame(&mut self) -> Option<Result<RgbdFrame, SourceError>> {
        if self.next >= self.source.len() {
            return None;
        }
        let i = self.next;
        self.next += 1;
        Some(self.source.load(i))
    }
    fn groundtruth(&self) -> Option<Vec<TimedPose>> {
        self.source.groundtruth()
    }
}

/// The sending end of [`pushed`]: user code (a camera callback, a ROS subscriber, another
/// thread) hands frames to the stream. Dropping every sender ends the stream.
#[derive(Clone)]
pub struct FrameSender {
    tx: std::sync::mpsc::SyncSender<RgbdFrame>,
    camera: PinholeCamera,
    dropped: Arc<std::sync::atomic::AtomicU64>,
}

impl FrameSender {
    /// Queues `frame`, waiting while the queue is full (for recorded input, where no frame
    /// may be lost). Errors when the frame's size is not the stream's camera's or the
    /// receiving end is gone.
    pub fn push(&self, frame: RgbdFrame) -> Result<(), SourceError> {
        self.check(&frame)?;
        self.tx.send(frame).map_err(|_| SourceError::Closed)
    }

    /// Queues `frame` unless the queue is full, in which case the frame is dropped and
    /// counted (for live input, where the consumer must not fall behind the camera).
    /// Returns whether the frame was queued.
    pub fn try_push(&self, frame: RgbdFrame) -> Result<bool, SourceError> {
        self.check(&frame)?;
        match self.tx.try_send(frame) {
            Ok(()) => Ok(true),
            Err(std::sync::mpsc::TrySendError::Full(_)) => {
                self.dropped
                    .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                Ok(false)
            }
            Err(std::sync::mpsc::TrySendError::Disconnected(_)) => Err(SourceError::Closed),
        }
    }

    /// Frames dropped by [`Self::try_push`] so far.
    pub fn dropped(&self) -> u64 {
        self.dropped.load(std::sync::atomic::Ordering::Relaxed)
    }

    fn check(&self, frame: &RgbdFrame) -> Result<(), SourceError> {
        let (w, h) = (frame.width(), frame.height());
        if w != self.camera.width as usize || h != self.camera.height as usize {
            return Err(SourceError::Invalid(format!(
                "pushed frame at {} s is {w} x {h} pixels, the stream's camera {} x {}",
                frame.timestamp, self.camera.width, self.camera.height
            )));
        }
        Ok(())
    }
}

/// The receiving end of [`pushed`], an [`RgbdStream`] of the frames pushed so far, in order.
pub struct PushedFrames {
    rx: std::sync::mpsc::Receiver<RgbdFrame>,
    camera: PinholeCamera,
    dropped: Arc<std::sync::atomic::AtomicU64>,
}

impl PushedFrames {
    /// Frames the senders dropped because the queue was full.
    pub fn dropped(&self) -> u64 {
        self.dropped.load(std::sync::atomic::Ordering::Relaxed)
    }
}

impl RgbdStream for PushedFrames {
    fn camera(&self) -> PinholeCamera {
        self.camera
    }
    fn len_hint(&self) -> Option<usize> {
        None
    }
    /// Waits for the next pushed frame; `None` once every sender is dropped and the queue is
    /// empty.
    fn next_frame(&mut self) -> Option<Result<RgbdFrame, SourceError>> {
        self.rx.recv().ok().map(Ok)
    }
}

/// A stream fed from user code: frames of `camera` pushed through the returned
/// [`FrameSender`] (clone it for several producers) come out of the [`PushedFrames`] in
/// order. At most `capacity` frames (>= 1) wait in between.
pub fn pushed(camera: PinholeCamera, capacity: usize) -> (FrameSender, PushedFrames) {
    let (tx, rx) = std::sync::mpsc::sync_channel(capacity.max(1));
    let dropped = Arc::new(std::sync::atomic::AtomicU64::new(0));
    (
        FrameSender {
            tx,
            camera,
            dropped: dropped.clone(),
        },
        PushedFrames {
            rx,
            camera,
            dropped,
        },
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::odometry::{Odometry, OdometryConfig};

    fn generated(frames: usize) -> FrameSource {
        let spec = SourceSpec::Synth {
            spec: "office:handheld".into(),
            frames,
            width: 160,
            seed: 3,
            session: 0,
            lap_seconds: None,
        };
        FrameSource::open(&spec, &ComputeBackend::Cpu).expect("generated sequence")
    }

    fn track_all(stream: &mut dyn RgbdStream) -> Vec<crate::geometry::Se3> {
        let mut odo = Odometry::new(
            OdometryConfig::default(),
            stream.camera(),
            &ComputeBackend::Cpu,
        )
        .expect("odometry");
        let mut poses = Vec::new();
        while let Some(frame) = stream.next_frame() {
            let frame = frame.expect("frame");
            poses.push(odo.track(&frame).expect("tracked").world_from_camera);
        }
        poses
    }

    /// Frames pushed from another thread give the same trajectory as the source read
    /// directly, in order, and the end of the producer ends the stream.
    #[test]
    fn pushed_frames_track_like_the_source() {
        let n = 12;
        let mut direct = Frames::new(generated(n));
        assert_eq!(direct.len_hint(), Some(n));
        let expected = track_all(&mut direct);
        assert_eq!(direct.len_hint(), Some(0));

        let mut source = generated(n);
        let (tx, mut rx) = pushed(source.camera(), 2);
        let producer = std::thread::spawn(move || {
            for i in 0..source.len() {
                tx.push(source.load(i).expect("frame")).expect("pushed");
            }
        });
        assert_eq!(rx.len_hint(), None);
        let got = track_all(&mut rx);
        producer.join().expect("producer");
        assert_eq!(got.len(), n);
        for (a, b) in got.iter().zip(&expected) {
            assert!((a.translation - b.translation).length() < 1e-12);
        }
        assert_eq!(rx.dropped(), 0);
    }

    /// A full queue drops and counts with `try_push`; a frame of the wrong size is refused
    /// with both sizes in the message; a closed stream is an error.
    #[test]
    fn try_push_drops_and_counts_and_sizes_are_checked() {
        let mut source = generated(3);
        let frame = source.load(0).expect("frame");
        let (tx, rx) = pushed(source.camera(), 1);
        assert!(tx.try_push(frame.clone()).expect("queued"));
        assert!(!tx.try_push(frame.clone()).expect("dropped"));
        assert_eq!((tx.dropped(), rx.dropped()), (1, 1));
        let mut small = source.camera();
        small.width /= 2;
        let (tx2, _rx2) = pushed(small, 1);
        let e = tx2.push(frame.clone()).expect_err("wrong size").to_string();
        assert!(e.contains("160 x 120") && e.contains("80 x 120"), "{e}");
        drop(rx);
        assert!(tx.push(frame).is_err());
    }
}
