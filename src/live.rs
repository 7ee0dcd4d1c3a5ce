//! Live RGB-D input: a camera running on its own thread and feeding a bounded
//! [`crate::source::pushed`] stream. When the consumer (tracking) falls behind, the frames it
//! is not ready for are dropped and counted, never queued without bound. Every frame the
//! camera delivers can be recorded as a TUM RGB-D folder, and [`LiveSpec::Replay`] plays a
//! folder at camera rate through the same path (a simulated device): replaying a recording
//! gives the same frames the live run received.
//!
//! Sources: OpenNI2 devices (the Kinect / Xtion family; the `openni2` feature, which needs
//! Debian's `libopenni2-dev` and `OPENNI2_REDIST64=/usr/lib/x86_64-linux-gnu` at build time)
//! and the simulated device. Another driver (e.g. librealsense) follows the same pattern: open
//! the device on the producer thread, report the camera, then hand frames to this module's
//! delivery loop (`deliver`), which drops, counts and records them.

use std::path::PathBuf;
use std::str::FromStr;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{channel, sync_channel, Receiver, Sender, SyncSender};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use crate::camera::PinholeCamera;
use crate::image::RgbdFrame;
use crate::io::{CameraConfig, IoError};
use crate::source::{pushed, FrameSender, PushedFrames, RgbdStream, SourceError};
use crate::synth::tum_export::TumWriter;
use crate::synth::CameraModel;
use crate::trajectory::TimedPose;

/// Depth units per metre of recorded depth images (TUM's).
const RECORD_DEPTH_FACTOR: f32 = 5000.0;

/// Errors of live input.
#[derive(Debug, thiserror::Error)]
pub enum LiveError {
    /// The source description is not understood.
    #[error("live source `{0}`: expected `openni2`, `openni2:URI` or `replay:FOLDER[@FPS]`")]
    Spec(String),
    /// The source needs a feature this build does not have.
    #[error(
        "live source `{0}` needs rgbid built with the `{0}` feature \
         (cargo build --release --features {0})"
    )]
    NotBuilt(&'static str),
    /// The OpenNI2 driver failed (no device, a stream that cannot start, ...).
    #[error("OpenNI2: {0}")]
    OpenNi2(String),
    /// Reading the replayed folder failed.
    #[error(transparent)]
    Source(#[from] SourceError),
    /// Writing the recording (or reading a camera file) failed.
    #[error(transparent)]
    Io(#[from] IoError),
    /// The camera or recorder thread stopped without a result.
    #[error("the {0} thread stopped unexpectedly")]
    Thread(&'static str),
}

/// Which live source to open.
#[derive(Clone, Debug, PartialEq)]
pub enum LiveSpec {
    /// An OpenNI2 device: the first one found, or the one at `uri` (a device URI, or an
    /// `.oni` recording file).
    OpenNi2 {
        /// Device URI; `None` = the default device.
        uri: Option<String>,
    },
    /// A simulated device: a dataset folder played at `fps` frames per second of wall
    /// time, with the folder's own time stamps.
    Replay {
        /// The folder (any layout `rgbid slam` reads).
        dir: PathBuf,
        /// Frames per second (> 0).
        fps: f64,
    },
}

impl FromStr for LiveSpec {
    type Err = LiveError;
    /// `openni2`, `openni2:URI` or `replay:FOLDER[@FPS]` (30 frames per second by default).
    fn from_str(s: &str) -> Result<Self, LiveError> {
        if s == "openni2" {
            return Ok(LiveSpec::OpenNi2 { uri: None });
        }
        if let Some(uri) = s.strip_prefix("openni2:") {
            return Ok(LiveSpec::OpenNi2 {
                uri: Some(uri.to_string()),
            });
        }
        if let Some(rest) = s.strip_prefix("replay:") {
            let (dir, fps) = match rest.rsplit_once('@') {
                Some((d, f)) => match f.parse::<f64>() {
                    Ok(fps) if fps.is_finite() && fps > 0.0 => (d, fps),
                    _ => return Err(LiveError::Spec(s.to_string())),
                },
                None => (rest, 30.0),
            };
            if dir.is_empty() {
                return Err(LiveError::Spec(s.to_string()));
            }
            return Ok(LiveSpec::Replay {
                dir: PathBuf::from(dir),
                fps,
            });
        }
        Err(LiveError::Spec(s.to_string()))
    }
}

/// How to open a live source.
#[derive(Clone, Debug, Default)]
pub struct LiveOptions {
    /// The camera (a preset or a camera file, as `--camera` takes); `None` = the replayed
    /// folder's own camera, or the `default` preset (525 px at 640 x 480) for OpenNI2.
    pub camera: Option<String>,
    /// Record every frame the camera delivers (also those dropped for tracking) as a TUM
    /// RGB-D folder here: `rgb/`, `depth/` (5000 per metre), the lists and `calib.txt`.
    pub record: Option<PathBuf>,
    /// Frames waiting for the consumer before new ones are dropped (>= 1; 0 means 1).
    pub queue: usize,
}

/// What a live run received.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct LiveSummary {
    /// Frames the camera delivered.
    pub received: u64,
    /// Frames dropped because the consumer was not ready for them.
    pub dropped: u64,
    /// Frames written to the recording.
    pub recorded: u64,
}

/// An open live source: an [`RgbdStream`] of the frames the consumer was ready for.
/// [`LiveInput::finish`] stops the camera and returns the counts.
pub struct LiveInput {
    frames: PushedFrames,
    stop: Arc<AtomicBool>,
    producer: Option<JoinHandle<Result<(u64, u64), LiveError>>>,
    groundtruth: Option<Vec<TimedPose>>,
}

/// What the producer thread reports once its device is open.
type Setup = Result<(PushedFrames, Option<Vec<TimedPose>>), LiveError>;

impl LiveInput {
    /// Opens `spec` and starts its camera thread; returns once the device is open (or
    /// failed to open, with its error).
    pub fn open(spec: &LiveSpec, options: &LiveOptions) -> Result<LiveInput, LiveError> {
        let camera = options
            .camera
            .as_deref()
            .map(CameraConfig::from_name_or_path)
            .transpose()?;
        let stop = Arc::new(AtomicBool::new(false));
        let (setup_tx, setup_rx) = sync_channel::<Setup>(1);
        let queue = options.queue.max(1);
        let record = options.record.clone();
        let stop_thread = stop.clone();
        let spec = spec.clone();
        let producer = std::thread::Builder::new()
            .name("rgbid-live".into())
            .spawn(move || match spec {
                LiveSpec::Replay { dir, fps } => {
                    replay(&dir, fps, camera, queue, record, &stop_thread, setup_tx)
                }
                LiveSpec::OpenNi2 { uri } => {
                    openni2_run(uri, camera, queue, record, &stop_thread, setup_tx)
                }
            })
            .map_err(|_| LiveError::Thread("camera"))?;
        match setup_rx.recv() {
            Ok(Ok((frames, groundtruth))) => Ok(LiveInput {
                frames,
                stop,
                producer: Some(producer),
                groundtruth,
            }),
            Ok(Err(e)) => {
                let _ = producer.join();
                Err(e)
            }
            Err(_) => match producer.join() {
                Ok(Err(e)) => Err(e),
                _ => Err(LiveError::Thread("camera")),
            },
        }
    }

    /// Frames dropped so far because the consumer was not ready for them.
    pub fn dropped(&self) -> u64 {
        self.frames.dropped()
    }

    /// Stops the camera, waits for the recording to be complete and returns the counts (all
    /// zero when called again).
    pub fn finish(&mut self) -> Result<LiveSummary, LiveError> {
        self.stop.store(true, Ordering::Relaxed);
        let Some(producer) = self.producer.take() else {
            return Ok(LiveSummary::default());
        };
        let (received, recorded) = match producer.join() {
            Ok(r) => r?,
            Err(_) => return Err(LiveError::Thread("camera")),
        };
        let dropped = self.frames.dropped();
        Ok(LiveSummary {
            received,
            dropped,
            recorded,
        })
    }
}

impl Drop for LiveInput {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
    }
}

impl RgbdStream for LiveInput {
    fn camera(&self) -> PinholeCamera {
        self.frames.camera()
    }
    fn len_hint(&self) -> Option<usize> {
        None
    }
    fn next_frame(&mut self) -> Option<Result<RgbdFrame, SourceError>> {
        self.frames.next_frame()
    }
    fn groundtruth(&self) -> Option<Vec<TimedPose>> {
        self.groundtruth.clone()
    }
}

/// The recorder thread's input and handle (its result: the frames written).
type Recorder = (Sender<RgbdFrame>, JoinHandle<Result<u64, LiveError>>);

/// The recorder thread: writes every frame it is sent, in order, and finishes the folder
/// when the sender is dropped.
fn start_recorder(dir: PathBuf, camera: PinholeCamera) -> Result<Recorder, LiveError> {
    let mut writer = TumWriter::create_recording(&dir, &CameraModel::Pinhole(camera))?;
    let (tx, rx): (Sender<RgbdFrame>, Receiver<RgbdFrame>) = channel();
    let handle = std::thread::Builder::new()
        .name("rgbid-record".into())
        .spawn(move || {
            let mut n = 0u64;
            for frame in rx {
                let (rgb, depth) = recorded_buffers(&frame);
                writer.write_images(
                    frame.timestamp(),
                    frame.width() as u32,
                    frame.height() as u32,
                    rgb,
                    depth,
                    None,
                )?;
                n += 1;
            }
            writer.finish(
                "Frames recorded by rgbid from live input (rgbid slam --live ... --record).\n\
                 depth: 16-bit, 5000 per metre; calib.txt: the undistorted pinhole camera.\n",
                &[],
            )?;
            Ok(n)
        })
        .map_err(|_| LiveError::Thread("recorder"))?;
    Ok((tx, handle))
}

/// A frame's images as a TUM folder stores them: RGB bytes (grey repeated when the frame
/// has no colour) and depth at 5000 per metre (0 where there is none or beyond 13.1 m).
/// Depth read at 1000 or 5000 units per metre comes back to the same inverse depth.
pub(crate) fn recorded_buffers(frame: &RgbdFrame) -> (Vec<u8>, Vec<u16>) {
    let rgb = match frame.colour() {
        Some(c) => c.rgb().to_vec(),
        None => frame
            .intensity()
            .data()
            .iter()
            .flat_map(|&v| [crate::image::intensity_byte(v); 3])
            .collect(),
    };
    let depth = frame
        .inverse_depth()
        .data()
        .iter()
        .map(|&rho| {
            let d = (RECORD_DEPTH_FACTOR / rho).round();
            if rho > 0.0 && d.is_finite() && d <= f32::from(u16::MAX - 1) {
                d as u16
            } else {
                0
            }
        })
        .collect();
    (rgb, depth)
}

/// Hands one frame the camera delivered to the recorder and, when the consumer is ready, to
/// the stream (else it is dropped and counted). Returns false when the consumer is gone.
pub(crate) fn deliver(
    frame: RgbdFrame,
    tx: &FrameSender,
    recorder: Option<&Sender<RgbdFrame>>,
) -> Result<bool, LiveError> {
    if let Some(r) = recorder {
        r.send(frame.clone())
            .map_err(|_| LiveError::Thread("recorder"))?;
    }
    match tx.try_push(frame) {
        Ok(_) => Ok(true),
        Err(SourceError::Closed) => Ok(false),
        Err(e) => Err(e.into()),
    }
}

/// Ends a producer: closes the recorder and returns `(received, recorded)`.
fn close(received: u64, recorder: Option<Recorder>) -> Result<(u64, u64), LiveError> {
    let recorded = match recorder {
        Some((tx, handle)) => {
            drop(tx);
            handle.join().map_err(|_| LiveError::Thread("recorder"))??
        }
        None => 0,
    };
    Ok((received, recorded))
}

/// The simulated device: plays `dir` at `fps` frames per second of wall time.
fn replay(
    dir: &std::path::Path,
    fps: f64,
    camera: Option<CameraConfig>,
    queue: usize,
    record: Option<PathBuf>,
    stop: &AtomicBool,
    setup: SyncSender<Setup>,
) -> Result<(u64, u64), LiveError> {
    let opened = (|| {
        let opts = crate::io::tum::OpenOptions {
            camera,
            ..Default::default()
        };
        let seq = crate::io::tum::TumSequence::open(dir, &opts)?;
        let recorder = record.map(|d| start_recorder(d, seq.camera)).transpose()?;
        Ok::<_, LiveError>((seq, recorder))
    })();
    let (seq, recorder) = match opened {
        Ok(v) => v,
        Err(e) => {
            let _ = setup.send(Err(e));
            return Ok((0, 0));
        }
    };
    let (tx, frames) = pushed(seq.camera, queue);
    let groundtruth = seq.ground_truth().ok().flatten();
    if setup.send(Ok((frames, groundtruth))).is_err() {
        return close(0, recorder);
    }
    let start = Instant::now();
    let mut received = 0u64;
    for i in 0..seq.len() {
        if stop.load(Ordering::Relaxed) {
            break;
        }
        let due = start + Duration::from_secs_f64(i as f64 / fps);
        if let Some(wait) = due.checked_duration_since(Instant::now()) {
            std::thread::sleep(wait);
        }
        let frame = match seq.load(i) {
            Ok(f) => f,
            Err(e) => {
                // A camera delivers no unreadable frames: skip it as a driver would.
                log::warn!("replay: frame {i} skipped: {e}");
                continue;
            }
        };
        received += 1;
        if !deliver(frame, &tx, recorder.as_ref().map(|(s, _)| s))? {
            break;
        }
    }
    close(received, recorder)
}

#[cfg(not(feature = "openni2"))]
fn openni2_run(
    _uri: Option<String>,
    _camera: Option<CameraConfig>,
    _queue: usize,
    _record: Option<PathBuf>,
    _stop: &AtomicBool,
    setup: SyncSender<Setup>,
) -> Result<(u64, u64), LiveError> {
    let _ = setup.send(Err(LiveError::NotBuilt("openni2")));
    Ok((0, 0))
}

#[cfg(feature = "openni2")]
fn openni2_run(
    uri: Option<String>,
    camera: Option<CameraConfig>,
    queue: usize,
    record: Option<PathBuf>,
    stop: &AtomicBool,
    setup: SyncSender<Setup>,
) -> Result<(u64, u64), LiveError> {
    use openni2::{
        Device, ImageRegistrationMode, OniDepthPixel, OniRGB888Pixel, PixelFormat, SensorType,
        Status, VideoMode,
    };
    let oni = |what: &str, s: Status| LiveError::OpenNi2(format!("{what}: {s:?}"));
    let fail = |e: LiveError| {
        let _ = setup.send(Err(e));
        Ok((0, 0))
    };
    if let Err(s) = openni2::init() {
        return fail(oni("initialisation", s));
    }
    let device = match uri.as_deref() {
        Some(u) => Device::open_uri(u),
        None => Device::open_default(),
    };
    let device = match device {
        Ok(d) => d,
        Err(s) => {
            return fail(LiveError::OpenNi2(format!(
                "no device ({}): {s:?}; is the camera plugged in and its udev rule installed?",
                uri.as_deref().unwrap_or("the default device")
            )))
        }
    };
    let config = camera.unwrap_or_else(|| CameraConfig {
        camera: PinholeCamera::new(525.0, 525.0, 319.5, 239.5, 640, 480),
        depth_factor: 1000.0,
        source: "preset default (OpenNI2 depth in millimetres)".into(),
    });
    let (w, h) = (config.camera.width, config.camera.height);
    // Before the streams borrow the device: depth and colour frames come in pairs.
    let mut device = device;
    let _ = device.enable_color_depth_sync(true);
    fn start(
        device: &Device,
        w: u32,
        h: u32,
    ) -> Result<(openni2::Stream<'_>, openni2::Stream<'_>), LiveError> {
        let oni = |what: &str, s: Status| LiveError::OpenNi2(format!("{what}: {s:?}"));
        let depth = device
            .create_stream(SensorType::DEPTH)
            .map_err(|s| oni("depth stream", s))?;
        let colour = device
            .create_stream(SensorType::COLOR)
            .map_err(|s| oni("colour stream", s))?;
        let mode = |pixel_format| VideoMode {
            pixel_format,
            resolution_x: w as i32,
            resolution_y: h as i32,
            fps: 30,
        };
        depth
            .set_video_mode(mode(PixelFormat::DEPTH_1_MM))
            .map_err(|s| oni(&format!("depth mode {w} x {h} at 30 Hz, 1 mm"), s))?;
        colour
            .set_video_mode(mode(PixelFormat::RGB888))
            .map_err(|s| oni(&format!("colour mode {w} x {h} at 30 Hz, RGB"), s))?;
        if device.is_image_registration_mode_supported(ImageRegistrationMode::DEPTH_TO_COLOR) {
            device
                .set_image_registration(true)
                .map_err(|s| oni("depth-to-colour registration", s))?;
        }
        depth.start().map_err(|s| oni("starting depth", s))?;
        colour.start().map_err(|s| oni("starting colour", s))?;
        Ok((depth, colour))
    }
    let streams = start(&device, w, h);
    let (depth, colour) = match streams {
        Ok(v) => v,
        Err(e) => return fail(e),
    };
    let recorder = match record.map(|d| start_recorder(d, config.camera)).transpose() {
        Ok(r) => r,
        Err(e) => return fail(e),
    };
    let (tx, frames) = pushed(config.camera, queue);
    if setup.send(Ok((frames, None))).is_err() {
        return close(0, recorder);
    }
    let mut received = 0u64;
    let mut result = Ok(());
    while !stop.load(Ordering::Relaxed) {
        // The modes were set above; a stream that reports another pixel format would make
        // the driver's frame accessor panic, so it is checked first.
        let modes_ok = matches!(
            (depth.get_video_mode(), colour.get_video_mode()),
            (Ok(d), Ok(c)) if matches!(d.pixel_format, PixelFormat::DEPTH_1_MM)
                && matches!(c.pixel_format, PixelFormat::RGB888)
        );
        if !modes_ok {
            result = Err(LiveError::OpenNi2(
                "the device changed its pixel formats during the run".into(),
            ));
            break;
        }
        let d = match depth.read_frame::<OniDepthPixel>() {
            Ok(f) => f,
            Err(s) => {
                result = Err(oni("reading depth", s));
                break;
            }
        };
        let c = match colour.read_frame::<OniRGB888Pixel>() {
            Ok(f) => f,
            Err(s) => {
                result = Err(oni("reading colour", s));
                break;
            }
        };
        if d.dimensions() != (w as u16, h as u16) || c.dimensions() != (w as u16, h as u16) {
            log::warn!(
                "OpenNI2: frame {}x{} / {}x{} instead of {w}x{h}, skipped",
                d.width(),
                d.height(),
                c.width(),
                c.height()
            );
            continue;
        }
        let rgb: Vec<u8> = c.pixels().iter().flat_map(|p| [p.r, p.g, p.b]).collect();
        let frame = crate::image::RgbdFrame::from_buffers(
            d.timestamp() as f64 * 1e-6,
            w as usize,
            h as usize,
            crate::image::ImageBuffer::Rgb(&rgb),
            crate::image::DepthBuffer::U16 {
                data: d.pixels(),
                factor: config.depth_factor,
            },
        );
        let frame = match frame {
            Ok(f) => f,
            Err(e) => {
                log::warn!("OpenNI2: frame skipped: {e}");
                continue;
            }
        };
        received += 1;
        match deliver(frame, &tx, recorder.as_ref().map(|(s, _)| s)) {
            Ok(true) => {}
            Ok(false) => break,
            Err(e) => {
                result = Err(e);
                break;
            }
        }
    }
    depth.stop();
    colour.stop();
    let counts = close(received, recorder)?;
    result.map(|()| counts)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gpu::ComputeBackend;
    use crate::source::{FrameSource, Frames, SourceSpec};

    fn spec_err(s: &str) {
        assert!(
            matches!(s.parse::<LiveSpec>(), Err(LiveError::Spec(_))),
            "{s}"
        );
    }

    #[test]
    fn specs_parse_and_bad_ones_are_named() {
        assert_eq!(
            "openni2".parse::<LiveSpec>().ok(),
            Some(LiveSpec::OpenNi2 { uri: None })
        );
        assert_eq!(
            "openni2:file.oni".parse::<LiveSpec>().ok(),
            Some(LiveSpec::OpenNi2 {
                uri: Some("file.oni".into())
            })
        );
        assert_eq!(
            "replay:/data/seq@15".parse::<LiveSpec>().ok(),
            Some(LiveSpec::Replay {
                dir: "/data/seq".into(),
                fps: 15.0
            })
        );
        assert_eq!(
            "replay:seq".parse::<LiveSpec>().ok(),
            Some(LiveSpec::Replay {
                dir: "seq".into(),
                fps: 30.0
            })
        );
        for bad in [
            "",
            "kinect",
            "replay:",
            "replay:seq@0",
            "replay:seq@nan",
            "replay:s@-3",
        ] {
            spec_err(bad);
        }
        let e = "kinect".parse::<LiveSpec>().unwrap_err().to_string();
        assert!(e.contains("`kinect`") && e.contains("replay:FOLDER"), "{e}");
    }

    #[cfg(not(feature = "openni2"))]
    #[test]
    fn openni2_without_the_feature_says_how_to_build_it() {
        let e = LiveInput::open(&LiveSpec::OpenNi2 { uri: None }, &LiveOptions::default())
            .err()
            .map(|e| e.to_string())
            .unwrap_or_default();
        assert!(e.contains("--features openni2"), "{e}");
    }

    /// Without a device the driver's error says there is none (CI builds the feature on a
    /// machine without a camera).
    #[cfg(feature = "openni2")]
    #[test]
    fn openni2_without_a_device_says_so() {
        let e = LiveInput::open(&LiveSpec::OpenNi2 { uri: None }, &LiveOptions::default())
            .err()
            .map(|e| e.to_string())
            .unwrap_or_default();
        assert!(e.contains("no device"), "{e}");
    }

    fn write_folder(dir: &std::path::Path, frames: usize) {
        let spec = SourceSpec::Synth {
            spec: "office:handheld".into(),
            frames,
            width: 160,
            seed: 5,
            session: 0,
            lap_seconds: None,
        };
        let FrameSource::Synth(mut seq, cam) =
            FrameSource::open(&spec, &ComputeBackend::Cpu).expect("generated")
        else {
            panic!("a generated source");
        };
        let mut w = TumWriter::create(dir, &CameraModel::Pinhole(cam)).expect("writer");
        for i in 0..seq.len() {
            let f = seq.render_frame(i).expect("render");
            let pose = seq.ground_truth()[i].world_from_camera;
            w.write_frame(f.timestamp, &pose, &f.frame).expect("write");
        }
        w.finish("test\n", &[]).expect("finish");
    }

    fn all_frames(stream: &mut dyn RgbdStream) -> Vec<RgbdFrame> {
        let mut v = Vec::new();
        while let Some(f) = stream.next_frame() {
            v.push(f.expect("frame"));
        }
        v
    }

    /// The simulated device delivers every frame of a folder (a queue as long as the folder,
    /// so none is dropped) and records them; the recording replays to the same frames, bit
    /// for bit, as the folder read directly.
    #[test]
    fn replay_records_the_frames_it_delivers() {
        let tmp = tempfile::tempdir().expect("tmp");
        let (folder, rec) = (tmp.path().join("seq"), tmp.path().join("rec"));
        write_folder(&folder, 6);
        let direct = {
            let spec = SourceSpec::Tum {
                dir: folder.clone(),
                format: None,
                camera: None,
                max_frames: None,
            };
            all_frames(&mut Frames::new(
                FrameSource::open(&spec, &ComputeBackend::Cpu).expect("folder"),
            ))
        };
        let options = LiveOptions {
            camera: None,
            record: Some(rec.clone()),
            queue: 16,
        };
        let live_spec = LiveSpec::Replay {
            dir: folder.clone(),
            fps: 200.0,
        };
        let mut live = LiveInput::open(&live_spec, &options).expect("replay");
        assert!(live.groundtruth().is_some_and(|g| g.len() == 6));
        let got = all_frames(&mut live);
        let summary = live.finish().expect("finish");
        assert_eq!(
            summary,
            LiveSummary {
                received: 6,
                dropped: 0,
                recorded: 6
            }
        );
        let replayed = {
            let opts = LiveOptions {
                queue: 16,
                ..Default::default()
            };
            let mut l = LiveInput::open(
                &LiveSpec::Replay {
                    dir: rec.clone(),
                    fps: 200.0,
                },
                &opts,
            )
            .expect("replay of the recording");
            let v = all_frames(&mut l);
            l.finish().expect("finish");
            v
        };
        assert_eq!(got.len(), direct.len());
        assert_eq!(replayed.len(), direct.len());
        for ((a, b), c) in direct.iter().zip(&got).zip(&replayed) {
            assert_eq!(a.timestamp(), c.timestamp());
            for f in [b, c] {
                assert_eq!(a.intensity().data(), f.intensity().data());
                assert_eq!(a.inverse_depth().data(), f.inverse_depth().data());
            }
        }
    }

    /// A consumer slower than the camera gets fewer frames; the rest are counted as dropped
    /// and still recorded.
    #[test]
    fn a_slow_consumer_drops_and_counts() {
        let tmp = tempfile::tempdir().expect("tmp");
        let (folder, rec) = (tmp.path().join("seq"), tmp.path().join("rec"));
        write_folder(&folder, 8);
        let options = LiveOptions {
            camera: None,
            record: Some(rec.clone()),
            queue: 1,
        };
        let mut live = LiveInput::open(
            &LiveSpec::Replay {
                dir: folder,
                fps: 100.0,
            },
            &options,
        )
        .expect("replay");
        let mut consumed = 0u64;
        while let Some(f) = live.next_frame() {
            f.expect("frame");
            consumed += 1;
            std::thread::sleep(Duration::from_millis(60));
        }
        let s = live.finish().expect("finish");
        assert_eq!(s.received, 8);
        assert_eq!(s.recorded, 8);
        assert!(s.dropped > 0, "{s:?}");
        assert_eq!(consumed + s.dropped, s.received, "{s:?}");
        let list = std::fs::read_to_string(rec.join("rgb.txt")).expect("rgb.txt");
        assert_eq!(list.lines().filter(|l| !l.starts_with('#')).count(), 8);
    }
}
