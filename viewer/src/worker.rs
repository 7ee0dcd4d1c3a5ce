//! The background thread that runs SLAM: it opens the source, feeds frames to
//! [`rgbid::slam::Slam`] at the requested pace and sends owned per-frame snapshots to the UI
//! through a bounded channel (the UI applies back-pressure by draining it once per repaint).

use std::collections::HashMap;
use std::sync::mpsc::{channel, sync_channel, Receiver, RecvTimeoutError, Sender, SyncSender};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use anyhow::{Context, Result};
use glam::DVec3;
use rgbid::camera::PinholeCamera;
use rgbid::gpu::{select_backend, BackendChoice};
use rgbid::image::{ImageF32, RgbdFrame};
use rgbid::io::ply::PlyMesh;
use rgbid::live::{LiveInput, LiveOptions, LiveSpec, LiveSummary};
use rgbid::odometry::{residual_images, OdometryConfig, ResidualImages, RobustScales};
use rgbid::place::{PixelMatch, Vocabulary};
use rgbid::segment::label_colour;
use rgbid::slam::{
    build_coloured_model, EventOptions, FrameReport, FrameStatus, KeyframeDescribed, LoopRecord,
    ModelParams, Slam, SlamConfig, SlamEvent, SlamEvents,
};
use rgbid::source::{RgbdStream, SourceError};
use rgbid::trajectory::TimedPose;

use crate::source::{FrameSource, SourceSpec};

/// World points (metres) with their 8-bit RGB colour (grey, red = green = blue, for runs
/// without colour).
pub type Cloud = Vec<(DVec3, [u8; 3])>;

/// Where the frames of a run come from.
#[derive(Clone, Debug)]
pub enum RunSource {
    /// A folder or generated sequence, read frame by frame at the pace the UI asks for.
    Sequence(SourceSpec),
    /// A live camera (or a folder replayed at camera rate, [`LiveSpec::Replay`]) on its own
    /// thread: frames that arrive while SLAM is busy (or paused) are dropped and counted.
    Live {
        /// Which camera.
        spec: LiveSpec,
        /// Camera file and recording folder ([`LiveOptions`]).
        options: LiveOptions,
    },
}

/// Settings of a run, chosen before it starts.
#[derive(Clone, Debug)]
pub struct RunConfig {
    /// What to open.
    pub source: RunSource,
    /// Compute backend of the odometry, fusion and rendering of generated sequences.
    pub backend: BackendChoice,
    /// Keyframe covisibility threshold (`SlamConfig::keyframe_covisibility`).
    pub keyframe_covisibility: f64,
    /// Superjut / neg-entropy masks in place recognition.
    pub masks: bool,
    /// Receive the superjut label image of every keyframe the back-end describes, for the
    /// superjut and neg-entropy panels (the back-end segments keyframes only with masks on).
    pub segment_keyframes: bool,
    /// Every n-th pixel of a new keyframe becomes a live point.
    pub point_step: usize,
    /// Voxel size of the final model, metres.
    pub voxel: f64,
    /// Start playing at once (otherwise paused on the first frame).
    pub autoplay: bool,
    /// Compute residual and weight images of every frame (a CPU pass over one pyramid
    /// level, a few ms per frame).
    pub residuals: bool,
    /// At the end, also build a TSDF mesh of the keyframes with this voxel size (metres;
    /// [`rgbid::slam::build_mesh`]); `None` = no mesh.
    pub mesh_voxel: Option<f64>,
}

impl RunConfig {
    /// Defaults for the sequence `source`.
    pub fn new(source: SourceSpec) -> Self {
        Self::with_source(RunSource::Sequence(source))
    }

    /// Defaults for live input from `spec` (a queue of two frames, as `rgbid slam --live`).
    pub fn live(
        spec: LiveSpec,
        camera: Option<String>,
        record: Option<std::path::PathBuf>,
    ) -> Self {
        Self::with_source(RunSource::Live {
            spec,
            options: LiveOptions {
                camera,
                record,
                queue: 2,
            },
        })
    }

    fn with_source(source: RunSource) -> Self {
        RunConfig {
            source,
            backend: BackendChoice::Auto,
            keyframe_covisibility: SlamConfig::default().keyframe_covisibility,
            masks: true,
            segment_keyframes: true,
            point_step: 2,
            voxel: ModelParams::default().voxel,
            autoplay: true,
            residuals: true,
            mesh_voxel: None,
        }
    }
}

/// Commands from the UI.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Command {
    /// Run continuously.
    Play,
    /// Stop after the current frame.
    Pause,
    /// Process one frame, then pause.
    Step,
    /// Pace: multiple of the sequence frame rate (30 fps); 0 = as fast as possible (live
    /// input keeps the camera's rate).
    Speed(f64),
    /// Stop feeding frames and finish (final optimisation, model).
    Finish,
}

/// Camera intrinsics + metadata sent when the run starts.
#[derive(Clone, Debug)]
pub struct StartInfo {
    /// Frames in the sequence (`None` for live input).
    pub frames: Option<usize>,
    /// The camera.
    pub camera: PinholeCamera,
    /// Name of the compute backend.
    pub backend: String,
    /// Ground truth, if any.
    pub groundtruth: Option<Vec<TimedPose>>,
}

/// One processed frame.
#[derive(Clone, Debug)]
pub struct FrameUpdate {
    /// Frame index.
    pub index: usize,
    /// Intensity 0-255.
    pub intensity: ImageF32,
    /// Inverse depth 1/m (0 = invalid).
    pub inverse_depth: ImageF32,
    /// What SLAM said.
    pub report: FrameReport,
    /// Residuals and IRLS weights against the odometry reference at the pose SLAM found
    /// (finest optimised level); `None` for the first frame, lost frames, or when
    /// [`RunConfig::residuals`] is off.
    pub residuals: Option<ResidualImages>,
    /// Wall time of loading the frame, milliseconds.
    pub load_ms: f64,
}

/// A new keyframe (sent with the frame that started it).
#[derive(Clone, Debug)]
pub struct KeyframeUpdate {
    /// Frame index that started the keyframe.
    pub frame_index: usize,
    /// `world_from_camera` of the keyframe (front-end estimate at creation).
    pub world_from_keyframe: rgbid::geometry::Se3,
    /// Points in world coordinates with the frame's colour (grey from the intensity when it
    /// has none), from the frame's inverse depth.
    pub points: Cloud,
    /// Whether the frame had colour.
    pub coloured: bool,
}

/// What the SLAM back-end found in a keyframe when it described it for place recognition
/// ([`SlamEvent::KeyframeDescribed`]); it arrives some frames after the keyframe started.
#[derive(Clone, Debug)]
pub struct KeyframeDescription {
    /// Keyframe id.
    pub id: usize,
    /// The keyframe's intensity (0-255) as the back-end keeps it, if the worker has it.
    pub intensity: Option<ImageF32>,
    /// Superjut colours (RGB8, row-major), when the back-end segmented the keyframe (masks
    /// on) and the label image was received.
    pub superjuts: Option<(usize, usize, Vec<u8>)>,
    /// Neg-entropy of each pixel's superjut, with the superjut colours.
    pub neg_entropy: Option<ImageF32>,
    /// The back-end's ORB keypoints: level-0 pixel `(x, y)`, patch diameter (pixels), and
    /// whether the first neg-entropy mask keeps it.
    pub keypoints: Vec<KeypointMark>,
    /// The back-end's segmentation and masks time, milliseconds.
    pub segment_ms: f64,
}

impl KeyframeDescription {
    /// The panel images of `d`, with the keyframe's intensity from `keyframes`.
    pub fn new(d: &KeyframeDescribed, keyframes: &KeyframeImages) -> Self {
        // mask_flags[0] is the whole image; [1] the first neg-entropy threshold.
        let kept = d.mask_flags.get(1);
        let keypoints = d
            .keypoints
            .iter()
            .enumerate()
            .map(|(i, k)| KeypointMark {
                x: k.uv.x as f32,
                y: k.uv.y as f32,
                size: k.size,
                kept: kept.is_none_or(|m| m.get(i).copied().unwrap_or(false)),
            })
            .collect();
        KeyframeDescription {
            id: d.id,
            intensity: keyframes.get(d.id),
            superjuts: d.labels.as_ref().map(|l| {
                let rgb = l.labels.iter().flat_map(|&s| label_colour(s)).collect();
                (l.width, l.height, rgb)
            }),
            neg_entropy: d.neg_entropy_image(),
            keypoints,
            segment_ms: d.segment_ms,
        }
    }
}

/// One ORB keypoint for the keyframe panel.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct KeypointMark {
    /// Level-0 pixel coordinates.
    pub x: f32,
    /// Level-0 pixel coordinates.
    pub y: f32,
    /// Descriptor patch diameter, pixels.
    pub size: f32,
    /// Kept by the first neg-entropy mask threshold (or no mask configured).
    pub kept: bool,
}

/// A loop the back-end verified (accepted, or rejected by the dense checks after it), with
/// the images of both sides and the inlier matches of the verification.
#[derive(Clone, Debug)]
pub struct LoopUpdate {
    /// Query keyframe id (the newer one; for relocalisation the id the relocalised frame's
    /// keyframe gets).
    pub query: usize,
    /// Candidate (older) keyframe id.
    pub candidate: usize,
    /// RANSAC inliers of the verification.
    pub inliers: usize,
    /// Whether it became a graph edge (or, for relocalisation, was used).
    pub accepted: bool,
    /// Why it was rejected (empty when accepted).
    pub reason: String,
    /// True when it came from relocalisation rather than loop detection.
    pub relocalisation: bool,
    /// Intensity (0-255) of the query side: keyframe `query`, or the relocalised frame;
    /// `None` when the worker does not have it.
    pub query_image: Option<ImageF32>,
    /// Intensity (0-255) of keyframe `candidate`; `None` when the worker does not have it.
    pub candidate_image: Option<ImageF32>,
    /// Inlier pairs: level-0 pixel `(x, y)` in the query image and in the candidate image
    /// ([`LoopRecord::matches`]).
    pub matches: Vec<PixelMatch>,
}

impl LoopUpdate {
    /// The update of `record`, with keyframe images from `keyframes` (id -> intensity) and,
    /// for relocalisation, `frame` (the frame being relocalised) as the query image.
    pub fn new(record: &LoopRecord, keyframes: &KeyframeImages, frame: Option<&ImageF32>) -> Self {
        let query_image = if record.relocalisation {
            frame.cloned()
        } else {
            keyframes.get(record.query)
        };
        LoopUpdate {
            query: record.query,
            candidate: record.candidate,
            inliers: record.inliers,
            accepted: record.verdict.is_accepted(),
            reason: record.verdict.reason(),
            relocalisation: record.relocalisation,
            query_image,
            candidate_image: keyframes.get(record.candidate),
            matches: record.matches.clone(),
        }
    }
}

/// What a finished run produced.
#[derive(Clone, Debug, Default)]
pub struct FinishedRun {
    /// Final (optimised) trajectory of every tracked frame.
    pub trajectory: Vec<TimedPose>,
    /// Optimised keyframe poses.
    pub keyframes: Vec<TimedPose>,
    /// Accepted loops as (query keyframe, candidate keyframe) indices into `keyframes`.
    pub loops: Vec<(usize, usize)>,
    /// Voxel-filtered model: world points (metres) with RGB colour (grey when the run had
    /// no colour).
    pub model: Cloud,
    /// Whether the model's colours come from colour images (false: grey from intensity).
    pub coloured: bool,
    /// TSDF mesh of the run, world frame (`mesh.ply` of a run folder, or built at the end
    /// with [`RunConfig::mesh_voxel`]).
    pub mesh: Option<std::sync::Arc<PlyMesh>>,
    /// Milliseconds of the final optimisation.
    pub final_optimise_ms: f64,
}

/// Counts of live input so far.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct LiveCounts {
    /// Frames the camera delivered so far (tracked, dropped or waiting in the queue).
    pub received: u64,
    /// Frames dropped because SLAM was busy (or paused).
    pub dropped: u64,
    /// Frames written to the recording: known once the camera stopped (`None` before, or
    /// when nothing is recorded).
    pub recorded: Option<u64>,
    /// Whether the camera has stopped and these are the final counts.
    pub finished: bool,
}

/// Messages to the UI.
#[derive(Debug)]
pub enum Update {
    /// The source is open and SLAM is ready.
    Started(Box<StartInfo>),
    /// A frame was processed.
    Frame(Box<FrameUpdate>),
    /// The frame just sent started a keyframe.
    Keyframe(Box<KeyframeUpdate>),
    /// The back-end described a keyframe (superjuts, neg-entropy, keypoints).
    KeyframeDescribed(Box<KeyframeDescription>),
    /// The back-end verified a loop (sent in the order they were found).
    Loop(Box<LoopUpdate>),
    /// Live input counts (after every frame of a live run, and once when it stops).
    Live(LiveCounts),
    /// The run finished.
    Finished(Box<FinishedRun>),
    /// The run stopped with an error.
    Error(String),
}

/// Handle of a running worker: commands in, updates out.
pub struct Worker {
    /// Commands to the thread.
    pub commands: Sender<Command>,
    /// Updates from the thread.
    pub updates: Receiver<Update>,
    handle: Option<JoinHandle<()>>,
}

impl Worker {
    /// Starts a run in a new thread.
    pub fn spawn(config: RunConfig) -> Result<Worker> {
        let (ctx, crx) = channel();
        let (utx, urx) = sync_channel(16);
        let handle = std::thread::Builder::new()
            .name("rgbid-viewer-slam".into())
            .spawn(move || {
                if let Err(e) = run(&config, &crx, &utx) {
                    let _ = utx.send(Update::Error(format!("{e:#}")));
                }
            })
            .context("starting the SLAM thread")?;
        Ok(Worker {
            commands: ctx,
            updates: urx,
            handle: Some(handle),
        })
    }

    /// Sends a command (ignored when the thread has ended).
    pub fn send(&self, c: Command) {
        let _ = self.commands.send(c);
    }
}

impl Drop for Worker {
    fn drop(&mut self) {
        // Ask the thread to finish and stop consuming; it ends when its next send fails.
        let _ = self.commands.send(Command::Finish);
        if let Some(h) = self.handle.take() {
            // Draining lets a blocked send return; dropping the receiver afterwards unblocks the rest.
            while !h.is_finished() {
                match self.updates.recv_timeout(Duration::from_millis(20)) {
                    Ok(_) | Err(RecvTimeoutError::Timeout) => {}
                    Err(RecvTimeoutError::Disconnected) => break,
                }
            }
            let _ = h.join();
        }
    }
}

/// Points of a frame in world coordinates with their colour (grey from the intensity when
/// the frame has no colour), every `step`-th pixel with inverse depth.
pub fn frame_points(
    frame: &RgbdFrame,
    camera: &PinholeCamera,
    world_from_camera: &rgbid::geometry::Se3,
    step: usize,
) -> Cloud {
    let step = step.max(1);
    let colour = frame.colour();
    let (w, h) = (frame.width(), frame.height());
    let mut out = Vec::with_capacity((w / step + 1) * (h / step + 1));
    for y in (0..h).step_by(step) {
        for x in (0..w).step_by(step) {
            let i = y * w + x;
            let rho = frame.inverse_depth().data()[i];
            if rho > 0.0 && rho.is_finite() {
                let z = 1.0 / f64::from(rho);
                let p = DVec3::new(
                    (x as f64 - camera.cx) / camera.fx * z,
                    (y as f64 - camera.cy) / camera.fy * z,
                    z,
                );
                let c = match colour {
                    Some(c) => c.at(x, y),
                    None => [frame.intensity().data()[i].round().clamp(0.0, 255.0) as u8; 3],
                };
                out.push((world_from_camera.transform_point(p), c));
            }
        }
    }
    out
}

/// Residual images of `frame` against the odometry `reference` (frame and front-end pose) at
/// the pose the front-end found, on the finest level the odometry optimises.
fn frame_residuals(
    frame: &RgbdFrame,
    report: &FrameReport,
    reference: Option<&(RgbdFrame, rgbid::geometry::Se3)>,
    camera: &PinholeCamera,
    odometry: &OdometryConfig,
) -> Option<ResidualImages> {
    let (ref_frame, frontworld_from_ref) = reference?;
    let frontworld_from_cur = report.record.frontworld_from_camera?;
    let d = &report.record.diagnostics;
    let level = odometry.finest_level(camera.width as usize);
    let scales = RobustScales {
        sigma_photo: d.sigma_photo,
        sigma_geo: d.sigma_geo,
        nu: d.nu,
    };
    let cur_from_ref = frontworld_from_cur.inverse() * *frontworld_from_ref;
    residual_images(
        ref_frame,
        frame,
        camera,
        &cur_from_ref,
        odometry,
        scales,
        level,
    )
    .map_err(|e| log::debug!("residual images of frame {}: {e}", report.record.index))
    .ok()
}

/// Keyframe intensities by keyframe id, as the back-end keeps them: rounded to 8 bits (as
/// [`rgbid::slam::Keyframe::pack`]), so keypoints found on them are the back-end's, and one
/// byte per pixel.
#[derive(Clone, Debug, Default)]
pub struct KeyframeImages {
    images: HashMap<usize, (usize, usize, Vec<u8>)>,
}

impl KeyframeImages {
    /// Keeps `intensity` (0-255) as keyframe `id`'s image.
    pub fn insert(&mut self, id: usize, intensity: &ImageF32) {
        let bytes = intensity
            .data()
            .iter()
            .map(|&v| v.round().clamp(0.0, 255.0) as u8)
            .collect();
        self.images
            .insert(id, (intensity.width(), intensity.height(), bytes));
    }

    /// Keyframe `id`'s intensity (0-255), if kept.
    pub fn get(&self, id: usize) -> Option<ImageF32> {
        self.images.get(&id).and_then(|(w, h, bytes)| {
            ImageF32::from_vec(*w, *h, bytes.iter().map(|&v| f32::from(v)).collect())
        })
    }
}

/// The UI messages of the SLAM events queued so far: keyframe descriptions and checked loops
/// (relocalisation attempts show `frame`, the frame being relocalised, as their query side).
fn backend_updates(
    events: &SlamEvents,
    keyframes: &KeyframeImages,
    frame: Option<&ImageF32>,
) -> Vec<Update> {
    events
        .try_iter()
        .filter_map(|e| match e {
            SlamEvent::KeyframeDescribed(d) => Some(Update::KeyframeDescribed(Box::new(
                KeyframeDescription::new(&d, keyframes),
            ))),
            SlamEvent::LoopChecked(l) => Some(Update::Loop(Box::new(LoopUpdate::new(
                &l, keyframes, frame,
            )))),
            _ => None,
        })
        .collect()
}

enum Pace {
    Paused,
    Playing,
    Stepping,
}

/// The open input of a run: a sequence read by index, or a live camera.
enum Input {
    Sequence { source: FrameSource, next: usize },
    Live(LiveInput),
}

impl Input {
    fn open(source: &RunSource, backend: &rgbid::gpu::ComputeBackend) -> Result<Input> {
        Ok(match source {
            RunSource::Sequence(spec) => Input::Sequence {
                source: FrameSource::open(spec, backend)?,
                next: 0,
            },
            RunSource::Live { spec, options } => {
                Input::Live(LiveInput::open(spec, options).context("opening the live input")?)
            }
        })
    }

    fn camera(&self) -> PinholeCamera {
        match self {
            Input::Sequence { source, .. } => source.camera(),
            Input::Live(l) => l.camera(),
        }
    }

    fn len(&self) -> Option<usize> {
        match self {
            Input::Sequence { source, .. } => Some(source.len()),
            Input::Live(_) => None,
        }
    }

    fn groundtruth(&self) -> Option<Vec<TimedPose>> {
        match self {
            Input::Sequence { source, .. } => source.groundtruth(),
            Input::Live(l) => l.groundtruth(),
        }
    }

    /// The next frame; `None` at the end of the sequence or of the live stream.
    fn next_frame(&mut self) -> Option<Result<RgbdFrame, SourceError>> {
        match self {
            Input::Sequence { source, next } => {
                let i = *next;
                (i < source.len()).then(|| {
                    *next += 1;
                    source.load(i)
                })
            }
            Input::Live(l) => l.next_frame(),
        }
    }
}

/// The mesh of `result`'s keyframes at their optimised poses (as `rgbid slam --mesh`).
fn keyframe_mesh(
    result: &rgbid::slam::SlamResult,
    camera: &PinholeCamera,
    voxel: f64,
    backend: &rgbid::gpu::ComputeBackend,
) -> Result<PlyMesh> {
    let mesh = result
        .mesh(camera, voxel, backend)
        .context("building the mesh")?;
    Ok(PlyMesh {
        vertices: mesh
            .vertices
            .iter()
            .zip(&mesh.colours)
            .map(|(p, c)| {
                (
                    DVec3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2])),
                    *c,
                )
            })
            .collect(),
        triangles: mesh.triangles,
    })
}

fn run(config: &RunConfig, commands: &Receiver<Command>, tx: &SyncSender<Update>) -> Result<()> {
    let backend = select_backend(config.backend, None).context("choosing the backend")?;
    let mut input = Input::open(&config.source, &backend)?;
    let recording =
        matches!(&config.source, RunSource::Live { options, .. } if options.record.is_some());
    let camera = input.camera();
    let mut slam_config = SlamConfig {
        keyframe_covisibility: config.keyframe_covisibility,
        masks: config.masks,
        ..Default::default()
    };
    if !config.masks {
        slam_config.mask_thresholds.clear();
    }
    let odometry_config = slam_config.odometry.clone();
    let mut reference: Option<(RgbdFrame, rgbid::geometry::Se3)> = None;
    // Keyframe images by id as the back-end keeps them (intensity rounded to 8 bits), for
    // the keyframe and loop panels.
    let mut keyframe_images = KeyframeImages::default();
    let mut slam = Slam::new(
        slam_config,
        camera,
        &backend,
        Vocabulary::embedded_default()?,
        None,
    )?;
    // The panels show what the back-end did: its keyframe descriptions and loop checks. A
    // few label images are enough (the panels show the latest); without the superjut panels
    // none are kept.
    let events = slam.events_with(EventOptions {
        images: if config.segment_keyframes { 4 } else { 0 },
        ..EventOptions::default()
    });
    let send = |u: Update| tx.send(u).map_err(|_| anyhow::anyhow!("the viewer closed"));
    send(Update::Started(Box::new(StartInfo {
        frames: input.len(),
        camera,
        backend: backend.name(),
        groundtruth: input.groundtruth(),
    })))?;
    let mut pace = if config.autoplay {
        Pace::Playing
    } else {
        Pace::Paused
    };
    let mut speed = 0.0_f64;
    let mut next_due = Instant::now();
    let mut i = 0;
    'frames: loop {
        // Commands: block while paused, otherwise drain what is there.
        loop {
            let cmd = match pace {
                Pace::Paused => match commands.recv() {
                    Ok(c) => c,
                    Err(_) => break 'frames,
                },
                _ => match commands.try_recv() {
                    Ok(c) => c,
                    Err(_) => break,
                },
            };
            match cmd {
                Command::Play => pace = Pace::Playing,
                Command::Pause => pace = Pace::Paused,
                Command::Step => pace = Pace::Stepping,
                Command::Speed(s) => speed = s.max(0.0),
                Command::Finish => break 'frames,
            }
        }
        // A live camera sets its own rate.
        if speed > 0.0 && matches!(input, Input::Sequence { .. }) {
            let now = Instant::now();
            if next_due > now {
                std::thread::sleep(next_due - now);
            }
            next_due = Instant::now().max(next_due) + Duration::from_secs_f64(1.0 / (30.0 * speed));
        }
        let t0 = Instant::now();
        let Some(frame) = input.next_frame() else {
            break;
        };
        let frame = frame.with_context(|| format!("frame {i}"))?;
        let load_ms = t0.elapsed().as_secs_f64() * 1e3;
        let report = slam.process(&frame)?;
        if matches!(
            report.status,
            FrameStatus::NewKeyframe | FrameStatus::Relocalised
        ) {
            if let Some((id, _)) = report.record.keyframe {
                keyframe_images.insert(id, frame.intensity());
            }
        }
        let backend_updates = backend_updates(&events, &keyframe_images, Some(frame.intensity()));
        let residuals = if config.residuals {
            frame_residuals(
                &frame,
                &report,
                reference.as_ref(),
                &camera,
                &odometry_config,
            )
        } else {
            None
        };
        if report.record.diagnostics.new_reference
            || (reference.is_none() && report.record.frontworld_from_camera.is_some())
        {
            reference = report
                .record
                .frontworld_from_camera
                .map(|pose| (frame.clone(), pose));
        } else if report.record.frontworld_from_camera.is_none() {
            reference = None;
        }
        let keyframe = if report.status == FrameStatus::NewKeyframe {
            report
                .world_from_camera
                .map(|world_from_keyframe| KeyframeUpdate {
                    frame_index: i,
                    world_from_keyframe,
                    points: frame_points(&frame, &camera, &world_from_keyframe, config.point_step),
                    coloured: frame.colour().is_some(),
                })
        } else {
            None
        };
        let (intensity, inverse_depth) = frame.into_images();
        send(Update::Frame(Box::new(FrameUpdate {
            index: i,
            intensity,
            inverse_depth,
            report,
            residuals,
            load_ms,
        })))?;
        if let Some(k) = keyframe {
            send(Update::Keyframe(Box::new(k)))?;
        }
        for u in backend_updates {
            send(u)?;
        }
        if let Input::Live(l) = &input {
            let dropped = l.dropped();
            send(Update::Live(LiveCounts {
                received: i as u64 + 1 + dropped,
                dropped,
                recorded: None,
                finished: false,
            }))?;
        }
        if matches!(pace, Pace::Stepping) {
            pace = Pace::Paused;
        }
        i += 1;
    }
    if let Input::Live(live) = &mut input {
        // Stop the camera first: what it received is then final, and the recording complete.
        match live.finish() {
            Ok(LiveSummary {
                received,
                dropped,
                recorded,
            }) => send(Update::Live(LiveCounts {
                received,
                dropped,
                recorded: recording.then_some(recorded),
                finished: true,
            }))?,
            Err(e) => send(Update::Error(format!("live input: {e}")))?,
        }
    }
    let result = slam.finish()?;
    // The last keyframes' descriptions and loops, from the back-end's finish.
    for u in backend_updates(&events, &keyframe_images, None) {
        send(u)?;
    }
    let keyframes: Vec<TimedPose> = result.keyframe_trajectory();
    let index_of = |id: usize| result.keyframes().iter().position(|k| k.id == id);
    let loops = result
        .loops
        .iter()
        .filter(|l| l.verdict.is_accepted() && !l.relocalisation)
        .filter_map(|l| Some((index_of(l.query)?, index_of(l.candidate)?)))
        .collect();
    let model = build_coloured_model(
        result.keyframes(),
        &result.keyframe_poses,
        &camera,
        &ModelParams {
            voxel: config.voxel,
            ..ModelParams::default()
        },
    );
    let coloured = result.keyframes().iter().any(|k| k.colour.is_some());
    let mesh = match config.mesh_voxel {
        Some(v) => Some(std::sync::Arc::new(keyframe_mesh(
            &result, &camera, v, &backend,
        )?)),
        None => None,
    };
    send(Update::Finished(Box::new(FinishedRun {
        trajectory: result.trajectory,
        keyframes,
        loops,
        model,
        coloured,
        mesh,
        final_optimise_ms: result.final_optimise_ms,
    })))?;
    Ok(())
}
