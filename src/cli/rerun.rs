//! `--rerun save:FILE.rrd | connect[=ADDR]` on `rgbid slam` and `rgbid odometry`: the run as
//! a [rerun](https://rerun.io) recording, frame by frame.
//!
//! Entities (poses `world_from_*`, metres; the camera frame is OpenCV's x right, y down,
//! z forward, which is rerun's default `RDF` for a pinhole):
//! - `world/camera`: the frame's `world_from_camera` (Transform3D) and the pinhole of the
//!   camera intrinsics; `world/camera/image` the intensity (8-bit grey) or, when the frame
//!   has colour, its RGB; `world/camera/depth` the depth, metres (f32, `meter = 1`, 0 = none);
//! - `world/keyframes/<id>`: each keyframe's `world_from_keyframe`, updated when the pose
//!   graph is optimised; `world/keyframes/<id>/points` its points in its own camera frame
//!   (coloured when the input has colour, grey from the intensity otherwise): the depth of
//!   the frame it was made from while the run goes on, its fused depth at the end;
//! - `world/loops` the accepted loop closures and `world/relocalisations` the accepted
//!   relocalisations, one line segment between the two keyframes' positions each;
//! - `frame/<name>`: the per-frame figures (the run folder's `timing.csv` row for `slam`,
//!   the `--csv` row for `odometry`), one scalar series each; `frame/status` a text line for
//!   every frame whose status is not plain tracking (`NewKeyframe`, `Lost`, `Relocalised`;
//!   `not tracked` in `odometry`).
//!
//! Everything is logged on two timelines: `frame` (the frame index, from 0) and `time` (the
//! frame's time stamp, as seconds since the Unix epoch: TUM stamps are that). Without the
//! `rerun` build feature the option is parsed and then refused with a message that says how
//! to build it. `connect` fails at the start when nothing listens at the viewer's address.
//! A later failure of the recording never stops the run: logging stops at the first one and
//! the run ends with it as a warning (exit code 3).

use std::path::PathBuf;
use std::str::FromStr;

#[cfg(feature = "rerun")]
use std::collections::BTreeMap;

use rgbid::camera::PinholeCamera;
#[cfg(feature = "rerun")]
use rgbid::geometry::Se3;
use rgbid::image::RgbdFrame;
use rgbid::odometry::{FrameStats, TrackResult};
use rgbid::slam::{FrameRecord, FrameReport, Slam, SlamResult};

/// Errors of `--rerun`.
#[derive(Debug, thiserror::Error)]
pub enum RerunError {
    /// The option's value is none of the accepted forms.
    #[error("--rerun `{0}`: expected `save:FILE.rrd`, `connect` or `connect=ADDR`")]
    Spec(String),
    /// This build has no rerun support.
    #[cfg_attr(feature = "rerun", allow(dead_code))]
    #[error(
        "--rerun needs rgbid built with the `rerun` feature \
         (cargo build --release --features rerun)"
    )]
    NotBuilt,
    /// The rerun SDK failed (opening the file, connecting, writing or flushing).
    #[cfg_attr(not(feature = "rerun"), allow(dead_code))]
    #[error("rerun recording: {0}")]
    Sdk(String),
}

/// Where `--rerun` sends the recording.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum RerunSpec {
    /// Write an `.rrd` file (`rerun FILE.rrd` opens it).
    Save(PathBuf),
    /// Stream to a running viewer (`rerun` started beforehand) over gRPC: at `url`, or at the
    /// viewer's default address `rerun+http://127.0.0.1:9876/proxy` when `None`.
    Connect(Option<String>),
}

impl FromStr for RerunSpec {
    type Err = RerunError;
    /// `save:FILE`, `connect`, or `connect=ADDR` where ADDR is `HOST:PORT` (the viewer's
    /// proxy at `rerun+http://HOST:PORT/proxy`) or a full `rerun+http://...` URL.
    fn from_str(s: &str) -> Result<Self, RerunError> {
        if let Some(file) = s.strip_prefix("save:") {
            if file.is_empty() {
                return Err(RerunError::Spec(s.to_string()));
            }
            return Ok(RerunSpec::Save(PathBuf::from(file)));
        }
        if s == "connect" {
            return Ok(RerunSpec::Connect(None));
        }
        if let Some(addr) = s.strip_prefix("connect=") {
            if addr.is_empty() || addr.chars().any(char::is_whitespace) {
                return Err(RerunError::Spec(s.to_string()));
            }
            let url = if addr.contains("://") {
                addr.to_string()
            } else {
                format!("rerun+http://{addr}/proxy")
            };
            return Ok(RerunSpec::Connect(Some(url)));
        }
        Err(RerunError::Spec(s.to_string()))
    }
}

impl RerunSpec {
    /// The `.rrd` file this writes, if any (checked with the other outputs before the run).
    pub fn file(&self) -> Option<&std::path::Path> {
        match self {
            RerunSpec::Save(p) => Some(p),
            RerunSpec::Connect(_) => None,
        }
    }
}

/// clap's parser of `--rerun` (the spec's own error as the message).
pub fn parse_spec(s: &str) -> Result<RerunSpec, String> {
    s.parse().map_err(|e: RerunError| e.to_string())
}

/// The per-frame figures of `rgbid odometry` (as its `--csv` columns), `(name, value)`.
#[cfg_attr(not(feature = "rerun"), allow(dead_code))]
fn odometry_scalars(s: &FrameStats) -> Vec<(&'static str, f64)> {
    let t = &s.times;
    vec![
        ("pyramid_ms", t.pyramid_ms),
        ("scale_ms", t.scale_ms),
        ("reduce_ms", t.reduce_ms),
        ("solve_ms", t.solve_ms),
        ("covisibility_ms", t.covisibility_ms),
        ("covariance_ms", t.covariance_ms),
        ("total_ms", t.total_ms),
        ("iterations", s.iterations as f64),
        ("sigma_photo", s.sigma_photo),
        ("sigma_geo", s.sigma_geo),
        ("nu", s.nu),
        ("covisibility", s.covisibility),
        ("condition_number", s.condition_number),
        ("new_reference", f64::from(u8::from(s.new_reference))),
    ]
}

/// The per-frame figures of `rgbid slam`: the numeric columns of its `timing.csv` row.
#[cfg_attr(not(feature = "rerun"), allow(dead_code))]
fn slam_scalars(record: &FrameRecord) -> Vec<(String, f64)> {
    let row = rgbid::io::run_folder::FrameRow::from(record);
    let Ok(serde_json::Value::Object(fields)) = serde_json::to_value(&row) else {
        return Vec::new();
    };
    fields
        .into_iter()
        .filter(|(k, _)| k != "index" && k != "timestamp")
        .filter_map(|(k, v)| v.as_f64().map(|v| (k, v)))
        .collect()
}

/// Points of an image on its camera's pixel grid, in the camera frame (metres), every
/// `step`-th pixel in x and y where `keep(i)` holds and the inverse depth `rho(i)` (1/m) is
/// positive, with the colour `rgb(i)`; `i = y * width + x`.
#[cfg_attr(not(feature = "rerun"), allow(dead_code))]
fn back_project(
    camera: &PinholeCamera,
    (width, height): (usize, usize),
    step: usize,
    rho: impl Fn(usize) -> f32,
    keep: impl Fn(usize) -> bool,
    rgb: impl Fn(usize) -> [u8; 3],
) -> (Vec<[f32; 3]>, Vec<[u8; 3]>) {
    let mut points = Vec::new();
    let mut colours = Vec::new();
    for y in (0..height).step_by(step.max(1)) {
        for x in (0..width).step_by(step.max(1)) {
            let i = y * width + x;
            let r = rho(i);
            if r > 0.0 && r.is_finite() && keep(i) {
                let z = 1.0 / f64::from(r);
                points.push([
                    ((x as f64 - camera.cx) / camera.fx * z) as f32,
                    ((y as f64 - camera.cy) / camera.fy * z) as f32,
                    z as f32,
                ]);
                colours.push(rgb(i));
            }
        }
    }
    (points, colours)
}

/// Grey of an intensity in [0, 255] (rounded, clamped).
#[cfg_attr(not(feature = "rerun"), allow(dead_code))]
fn grey(v: f32) -> u8 {
    v.round().clamp(0.0, 255.0) as u8
}

/// Every `POINT_STEP`-th pixel in x and y becomes a keyframe point: enough to see the
/// scene, and a long run's recording stays small (`model.ply` holds the dense points).
#[cfg_attr(not(feature = "rerun"), allow(dead_code))]
const POINT_STEP: usize = 4;

/// Timeline of frame indices.
#[cfg_attr(not(feature = "rerun"), allow(dead_code))]
const FRAME_TIMELINE: &str = "frame";

/// Timeline of frame time stamps.
#[cfg_attr(not(feature = "rerun"), allow(dead_code))]
const TIME_TIMELINE: &str = "time";

/// An open recording. Logging never fails the run: the first error stops it and
/// [`Recorder::finish`] returns it.
#[cfg(feature = "rerun")]
pub struct Recorder {
    rec: rerun::RecordingStream,
    /// The first error; nothing is logged after it.
    error: Option<RerunError>,
    camera: Option<PinholeCamera>,
    /// The SLAM system's events (keyframes, loops, optimisations).
    events: Option<rgbid::slam::SlamEvents>,
    /// Latest `world_from_keyframe` of every keyframe seen.
    keyframes: BTreeMap<usize, Se3>,
    /// Accepted loops, `(query, candidate)` keyframe ids.
    loops: Vec<(usize, usize)>,
    /// Accepted relocalisations, `(new keyframe, matched keyframe)` ids.
    relocalisations: Vec<(usize, usize)>,
    /// The last frame's index and time stamp (the time of what is logged after it).
    last: Option<(usize, f64)>,
    /// Streaming to a viewer (not writing a file).
    connected: bool,
}

/// Seconds [`Recorder::finish`] waits for a viewer to take what is still queued: an absent
/// viewer would otherwise keep the program from ending.
#[cfg(feature = "rerun")]
pub const CONNECT_FLUSH_S: u64 = 30;

/// An open recording (this build has no rerun support, so there is never one).
#[cfg(not(feature = "rerun"))]
pub struct Recorder {
    never: std::convert::Infallible,
}

#[cfg(not(feature = "rerun"))]
impl Recorder {
    /// Without the `rerun` feature: always [`RerunError::NotBuilt`].
    pub fn open(_spec: &RerunSpec, _application: &'static str) -> Result<Recorder, RerunError> {
        Err(RerunError::NotBuilt)
    }

    /// See the `rerun` build.
    pub fn attach(&mut self, _slam: &Slam, _camera: &PinholeCamera) {
        match self.never {}
    }

    /// See the `rerun` build.
    pub fn slam_frame(&mut self, _frame: &RgbdFrame, _report: &FrameReport) {
        match self.never {}
    }

    /// See the `rerun` build.
    pub fn odometry_frame(
        &mut self,
        _index: usize,
        _frame: &RgbdFrame,
        _camera: &PinholeCamera,
        _result: Option<&TrackResult>,
    ) {
        match self.never {}
    }

    /// See the `rerun` build.
    pub fn slam_finish(self, _result: &SlamResult) -> Result<(), RerunError> {
        match self.never {}
    }

    /// See the `rerun` build.
    pub fn finish(self) -> Result<(), RerunError> {
        match self.never {}
    }
}

#[cfg(feature = "rerun")]
impl Recorder {
    /// Opens the recording of application `application` (the viewer's application id):
    /// creates the file, or connects to the viewer (the connection is made in the
    /// background; a viewer that is not there shows as an error at [`Recorder::finish`]).
    pub fn open(spec: &RerunSpec, application: &'static str) -> Result<Recorder, RerunError> {
        // `default_enabled(true)` with nothing else: the `RERUN=off` environment variable
        // still turns the recording off, as it does for every rerun program.
        if let RerunSpec::Connect(url) = spec {
            probe(url.as_deref().unwrap_or(rerun::DEFAULT_CONNECT_URL))?;
        }
        let builder = rerun::RecordingStreamBuilder::new(application).default_enabled(true);
        let rec = match spec {
            RerunSpec::Save(path) => builder.save(path),
            RerunSpec::Connect(None) => builder.connect_grpc(),
            RerunSpec::Connect(Some(url)) => builder.connect_grpc_opts(url.clone()),
        }
        .map_err(|e| RerunError::Sdk(e.to_string()))?;
        Ok(Recorder {
            rec,
            error: None,
            camera: None,
            events: None,
            keyframes: BTreeMap::new(),
            loops: Vec::new(),
            relocalisations: Vec::new(),
            last: None,
            connected: matches!(spec, RerunSpec::Connect(_)),
        })
    }

    /// Follows the SLAM system's keyframes, loops and pose-graph optimisations (turns its
    /// event stream on, without label images) on camera `camera`.
    pub fn attach(&mut self, slam: &Slam, camera: &PinholeCamera) {
        self.set_camera(camera);
        self.events = Some(slam.events_with(rgbid::slam::EventOptions {
            capacity: 1024,
            images: 0,
        }));
    }

    /// Logs one frame of `rgbid slam`: pose, images, figures, and what the system did since
    /// the last frame (new keyframes with the points of their frame, loops, optimised
    /// keyframe poses).
    pub fn slam_frame(&mut self, frame: &RgbdFrame, report: &FrameReport) {
        let r = &report.record;
        self.set_time(r.index, r.timestamp);
        let status = match report.status {
            rgbid::slam::FrameStatus::Tracking => None,
            s => Some(format!("{s:?}")),
        };
        let scalars = slam_scalars(r);
        let scalars: Vec<(&str, f64)> = scalars.iter().map(|(k, v)| (k.as_str(), *v)).collect();
        self.frame(frame, report.world_from_camera, &scalars, status.as_deref());
        self.drain_events(Some((r.index, frame)));
    }

    /// Logs one frame of `rgbid odometry` on camera `camera`: its pose and figures when it
    /// was tracked (`result`), its images either way.
    pub fn odometry_frame(
        &mut self,
        index: usize,
        frame: &RgbdFrame,
        camera: &PinholeCamera,
        result: Option<&TrackResult>,
    ) {
        self.set_camera(camera);
        self.set_time(index, frame.timestamp());
        match result {
            Some(r) => self.frame(
                frame,
                Some(r.world_from_camera),
                &odometry_scalars(&r.stats),
                None,
            ),
            None => self.frame(frame, None, &[], Some("not tracked")),
        }
    }

    /// Logs the end of a SLAM run: the system's last events, then every keyframe at its
    /// optimised pose with the points of its fused depth, and the loops between them, at
    /// the time of the last frame; then flushes. The first logging error of the run, if any.
    pub fn slam_finish(mut self, result: &SlamResult) -> Result<(), RerunError> {
        self.drain_events(None);
        if let Some((index, timestamp)) = self.last {
            self.set_time(index, timestamp);
        }
        let params = rgbid::slam::ModelParams::default();
        if let Some(camera) = self.camera {
            for (kf, pose) in result.keyframes().iter().zip(&result.keyframe_poses) {
                self.keyframes.insert(kf.id, *pose);
                self.log(&format!("world/keyframes/{}", kf.id), &transform(pose));
                let (points, colours) = back_project(
                    &camera,
                    (kf.width, kf.height),
                    POINT_STEP,
                    |i| kf.inverse_depth[i].to_f32(),
                    |i| kf.weight[i] >= params.min_weight,
                    |i| match &kf.colour {
                        Some(c) => {
                            let rgb = c.rgb();
                            [rgb[3 * i], rgb[3 * i + 1], rgb[3 * i + 2]]
                        }
                        None => [kf.intensity[i]; 3],
                    },
                );
                self.log(
                    &format!("world/keyframes/{}/points", kf.id),
                    &rerun::Points3D::new(points).with_colors(colours),
                );
            }
        }
        self.log_edges();
        self.finish()
    }

    /// Flushes the recording (waiting at most [`CONNECT_FLUSH_S`] for a viewer); the first
    /// logging error of the run, if any.
    pub fn finish(mut self) -> Result<(), RerunError> {
        let flushed = match self.connected {
            false => self.rec.flush_blocking(),
            true => self
                .rec
                .flush_with_timeout(std::time::Duration::from_secs(CONNECT_FLUSH_S)),
        };
        if let Err(e) = flushed {
            self.fail(RerunError::Sdk(format!(
                "{e} (the viewer did not take the whole recording)"
            )));
            // The SDK's sink thread waits for the viewer for as long as it takes, and
            // dropping the stream (or disconnecting it) joins that thread: what is still
            // queued is abandoned instead, so that the program can end.
            let error = self.error.take();
            std::mem::forget(self);
            return Err(error.unwrap_or(RerunError::Sdk("flush failed".into())));
        }
        match self.error.take() {
            Some(e) => Err(e),
            None => Ok(()),
        }
    }

    /// The camera of the frames (logged once, as static data).
    fn set_camera(&mut self, camera: &PinholeCamera) {
        if self.camera.is_some() {
            return;
        }
        self.camera = Some(*camera);
        // rerun's pixel coordinates put the centre of pixel (0, 0) at (0.5, 0.5); ours at
        // (0, 0) (TUM's cx = 319.5 is the middle of 640 pixels).
        let pinhole = rerun::Pinhole::from_focal_length_and_resolution(
            [camera.fx as f32, camera.fy as f32],
            [camera.width as f32, camera.height as f32],
        )
        .with_principal_point([(camera.cx + 0.5) as f32, (camera.cy + 0.5) as f32]);
        if self.error.is_none() {
            if let Err(e) = self.rec.log_static("world/camera", &pinhole) {
                self.fail(RerunError::Sdk(e.to_string()));
            }
        }
    }

    fn set_time(&mut self, index: usize, timestamp: f64) {
        self.last = Some((index, timestamp));
        self.rec.set_time_sequence(FRAME_TIMELINE, index as i64);
        if timestamp.is_finite() {
            self.rec
                .set_timestamp_secs_since_epoch(TIME_TIMELINE, timestamp);
        }
    }

    fn fail(&mut self, e: RerunError) {
        if self.error.is_none() {
            log::warn!("{e}; nothing more is logged to the recording");
            self.error = Some(e);
        }
    }

    fn log(&mut self, path: &str, what: &impl rerun::AsComponents) {
        if self.error.is_some() {
            return;
        }
        if let Err(e) = self.rec.log(path, what) {
            self.fail(RerunError::Sdk(format!("{path}: {e}")));
        }
    }

    /// Pose, images, figures and status of the current frame.
    fn frame(
        &mut self,
        frame: &RgbdFrame,
        world_from_camera: Option<Se3>,
        scalars: &[(&str, f64)],
        status: Option<&str>,
    ) {
        if let Some(p) = world_from_camera {
            self.log("world/camera", &transform(&p));
        }
        let (w, h) = (frame.width(), frame.height());
        let resolution = [w as u32, h as u32];
        let image = match frame.colour() {
            Some(c) => rerun::Image::from_rgb24(c.rgb().to_vec(), resolution),
            None => {
                let grey: Vec<u8> = frame.intensity().data().iter().map(|&v| grey(v)).collect();
                rerun::Image::from_l8(grey, resolution)
            }
        };
        self.log("world/camera/image", &image);
        let depth: Vec<f32> = frame
            .inverse_depth()
            .data()
            .iter()
            .map(|&r| {
                if r > 0.0 && r.is_finite() {
                    1.0 / r
                } else {
                    0.0
                }
            })
            .collect();
        let depth = rerun::DepthImage::from_data_type_and_bytes(
            bytemuck::cast_slice::<f32, u8>(&depth).to_vec(),
            resolution,
            rerun::ChannelDatatype::F32,
        )
        .with_meter(1.0);
        self.log("world/camera/depth", &depth);
        for (name, value) in scalars {
            if value.is_finite() {
                self.log(&format!("frame/{name}"), &rerun::Scalars::single(*value));
            }
        }
        if let Some(s) = status {
            self.log("frame/status", &rerun::TextLog::new(s));
        }
    }

    /// Logs the events the SLAM system queued; `current` is the frame just processed (its
    /// index and images), whose depth gives the points of a keyframe made from it.
    fn drain_events(&mut self, current: Option<(usize, &RgbdFrame)>) {
        let Some(events) = self.events.take() else {
            return;
        };
        let mut edges_changed = false;
        let next = || match current {
            Some(_) => events.try_recv().ok(),
            // After the system finished, the queue is closed: this reads it to its end.
            None => events.recv().ok(),
        };
        while let Some(event) = next() {
            use rgbid::slam::SlamEvent;
            match event {
                SlamEvent::KeyframeCreated {
                    id,
                    frame_index,
                    world_from_keyframe,
                    ..
                } => {
                    self.keyframes.insert(id, world_from_keyframe);
                    self.log(
                        &format!("world/keyframes/{id}"),
                        &transform(&world_from_keyframe),
                    );
                    if let (Some((index, frame)), Some(camera)) = (current, self.camera) {
                        if index == frame_index {
                            self.frame_points(id, frame, &camera);
                        }
                    }
                }
                SlamEvent::LoopChecked(l) if l.verdict.is_accepted() && !l.relocalisation => {
                    self.loops.push((l.query, l.candidate));
                    edges_changed = true;
                }
                SlamEvent::Relocalised {
                    keyframe,
                    new_keyframe,
                    ..
                } => {
                    self.relocalisations.push((new_keyframe, keyframe));
                    edges_changed = true;
                }
                SlamEvent::GraphOptimised {
                    world_from_keyframe,
                    ..
                } => {
                    for (id, pose) in world_from_keyframe.iter().enumerate() {
                        self.keyframes.insert(id, *pose);
                        self.log(&format!("world/keyframes/{id}"), &transform(pose));
                    }
                    edges_changed = true;
                }
                _ => {}
            }
        }
        self.events = Some(events);
        if edges_changed {
            self.log_edges();
        }
    }

    /// Points of keyframe `id` from the depth of the frame it was made from.
    fn frame_points(&mut self, id: usize, frame: &RgbdFrame, camera: &PinholeCamera) {
        let rho = frame.inverse_depth().data();
        let intensity = frame.intensity().data();
        let colour = frame.colour().map(|c| c.rgb());
        let (points, colours) = back_project(
            camera,
            (frame.width(), frame.height()),
            POINT_STEP,
            |i| rho[i],
            |_| true,
            |i| match colour {
                Some(rgb) => [rgb[3 * i], rgb[3 * i + 1], rgb[3 * i + 2]],
                None => [grey(intensity[i]); 3],
            },
        );
        self.log(
            &format!("world/keyframes/{id}/points"),
            &rerun::Points3D::new(points).with_colors(colours),
        );
    }

    /// The loop and relocalisation edges between the keyframes' current positions.
    fn log_edges(&mut self) {
        for (path, edges) in [
            ("world/loops", self.loops.clone()),
            ("world/relocalisations", self.relocalisations.clone()),
        ] {
            let strips: Vec<Vec<[f32; 3]>> = edges
                .iter()
                .filter_map(|(a, b)| {
                    let a = self.keyframes.get(a)?.translation;
                    let b = self.keyframes.get(b)?.translation;
                    Some(vec![position(a), position(b)])
                })
                .collect();
            if !strips.is_empty() {
                self.log(path, &rerun::LineStrips3D::new(strips));
            }
        }
    }
}

/// Checks that something listens at the viewer address of `url` (`SCHEME://HOST:PORT/...`):
/// the SDK would otherwise wait for it without end once its queue is full.
#[cfg(feature = "rerun")]
fn probe(url: &str) -> Result<(), RerunError> {
    use std::net::{TcpStream, ToSocketAddrs};
    let authority = url
        .split_once("://")
        .map_or(url, |(_, rest)| rest)
        .split('/')
        .next()
        .unwrap_or_default();
    let no_viewer = |why: String| {
        RerunError::Sdk(format!(
            "no rerun viewer at {url} ({why}); start one first (`rerun`)"
        ))
    };
    let addresses = authority
        .to_socket_addrs()
        .map_err(|e| no_viewer(format!("{authority}: {e}")))?;
    let mut last = None;
    for a in addresses {
        match TcpStream::connect_timeout(&a, std::time::Duration::from_secs(PROBE_S)) {
            Ok(_) => return Ok(()),
            Err(e) => last = Some(e),
        }
    }
    Err(no_viewer(
        last.map_or("no address".into(), |e| e.to_string()),
    ))
}

/// Seconds to wait for the viewer's port to answer.
#[cfg(feature = "rerun")]
const PROBE_S: u64 = 5;

/// A position as rerun takes it (rerun has its own glam: plain arrays cross over).
#[cfg(feature = "rerun")]
fn position(p: glam::DVec3) -> [f32; 3] {
    [p.x as f32, p.y as f32, p.z as f32]
}

/// `a_from_b` as a rerun transform of entity `b` in its parent `a`.
#[cfg(feature = "rerun")]
fn transform(a_from_b: &Se3) -> rerun::Transform3D {
    let q = a_from_b.rotation;
    rerun::Transform3D::from_translation_rotation(
        position(a_from_b.translation),
        rerun::Quaternion::from_xyzw([q.x as f32, q.y as f32, q.z as f32, q.w as f32]),
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::BTreeMap;

    #[test]
    fn specs_parse_and_bad_ones_are_named() {
        assert_eq!(
            "save:/tmp/x.rrd".parse::<RerunSpec>().ok(),
            Some(RerunSpec::Save("/tmp/x.rrd".into()))
        );
        assert_eq!(
            "connect".parse::<RerunSpec>().ok(),
            Some(RerunSpec::Connect(None))
        );
        assert_eq!(
            "connect=10.0.0.2:9877".parse::<RerunSpec>().ok(),
            Some(RerunSpec::Connect(Some(
                "rerun+http://10.0.0.2:9877/proxy".into()
            )))
        );
        assert_eq!(
            "connect=rerun+http://h:1/proxy".parse::<RerunSpec>().ok(),
            Some(RerunSpec::Connect(Some("rerun+http://h:1/proxy".into())))
        );
        for bad in [
            "",
            "save:",
            "save",
            "connect=",
            "connect:h",
            "spawn",
            "connect=a b",
        ] {
            let e = bad.parse::<RerunSpec>().err().map(|e| e.to_string());
            let e = e.unwrap_or_else(|| panic!("`{bad}` was accepted"));
            assert!(
                e.contains(&format!("`{bad}`")) && e.contains("save:FILE.rrd"),
                "{e}"
            );
        }
    }

    #[cfg(not(feature = "rerun"))]
    #[test]
    fn without_the_feature_says_how_to_build_it() {
        let e = Recorder::open(&RerunSpec::Connect(None), "rgbid")
            .err()
            .map(|e| e.to_string())
            .unwrap_or_default();
        assert!(e.contains("--features rerun"), "{e}");
    }

    #[test]
    fn back_projection_inverts_the_pinhole() {
        let camera = PinholeCamera::new(500.0, 400.0, 3.5, 2.5, 8, 6);
        // Inverse depth 0.5 (2 m) everywhere but pixel 9 (no depth).
        let (points, colours) = back_project(
            &camera,
            (8, 6),
            1,
            |i| if i == 9 { 0.0 } else { 0.5 },
            |i| i != 10,
            |i| [i as u8, 0, 0],
        );
        assert_eq!(points.len(), 8 * 6 - 2);
        assert_eq!(colours.len(), points.len());
        for (p, c) in points.iter().zip(&colours) {
            let i = c[0] as usize;
            let (x, y) = ((i % 8) as f64, (i / 8) as f64);
            assert!((p[2] - 2.0).abs() < 1e-6);
            // Projects back onto its own pixel.
            let u = camera.fx * f64::from(p[0]) / f64::from(p[2]) + camera.cx;
            let v = camera.fy * f64::from(p[1]) / f64::from(p[2]) + camera.cy;
            assert!(
                (u - x).abs() < 1e-4 && (v - y).abs() < 1e-4,
                "{u} {v} vs {x} {y}"
            );
        }
        let (every_other, _) = back_project(&camera, (8, 6), 2, |_| 1.0, |_| true, |_| [0; 3]);
        assert_eq!(every_other.len(), 4 * 3);
    }

    #[test]
    fn figures_are_the_numeric_columns_of_the_frame_rows() {
        let record = FrameRecord {
            index: 3,
            timestamp: 1.5,
            status: rgbid::slam::FrameStatus::NewKeyframe,
            frontworld_from_camera: None,
            keyframe: None,
            frontend_ms: 12.0,
            times: Default::default(),
            fusion_ms: 2.0,
            covisibility: 0.75,
            keyframe_covisibility: 0.5,
            diagnostics: rgbid::slam::OdometryDiagnostics {
                iterations: 17,
                ..Default::default()
            },
            odometry_covariance: None,
            keyframe_covariance: None,
        };
        let slam: BTreeMap<String, f64> = slam_scalars(&record).into_iter().collect();
        assert_eq!(slam.get("iterations"), Some(&17.0), "{slam:?}");
        assert_eq!(slam.get("covisibility"), Some(&0.75), "{slam:?}");
        assert_eq!(slam.get("frontend_ms"), Some(&12.0), "{slam:?}");
        // The index and the time stamp are the timelines; the status is text.
        for not in ["index", "timestamp", "status"] {
            assert!(!slam.contains_key(not), "{slam:?}");
        }
        let stats = FrameStats {
            iterations: 9,
            new_reference: true,
            ..Default::default()
        };
        let odometry: BTreeMap<&str, f64> = odometry_scalars(&stats).into_iter().collect();
        assert_eq!(odometry.get("iterations"), Some(&9.0));
        assert_eq!(odometry.get("new_reference"), Some(&1.0));
        assert_eq!(odometry.len(), 14);
    }
}
