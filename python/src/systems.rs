//! `Odometry`, `Slam`, its result and its event stream.

use std::sync::Mutex;
use std::time::Instant;

use numpy::ndarray::{Array2, Array3};
use numpy::{IntoPyArray, PyArray2, PyArray3, PyReadonlyArray2};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyDict;
use rgbid::geometry::Se3;
use rgbid::io::run_folder::LoopRow;
use rgbid::io::UndistortMap;
use rgbid::odometry::{
    ModelOdometry, ModelParams as TrackingModelParams, ModelTimes, OdometryConfig, OdometryError,
    TrackResult,
};
use rgbid::place::Vocabulary;
use rgbid::slam::{
    build_coloured_model, FrameStatus, KeyframeLink, Map, ModelParams, SlamConfig, SlamEvent,
    SlamEvents,
};
use rgbid::trajectory::TimedPose;

use crate::convert::{
    backend_from, config_from, pose_from_matrix, pose_matrix, runtime, to_python, trajectory_array,
    value,
};
use crate::frames::{Camera, FrameIn};

/// The lock of a system; a panic inside the library while it was held poisons it.
fn locked<T>(m: &Mutex<T>) -> PyResult<std::sync::MutexGuard<'_, T>> {
    m.lock()
        .map_err(|_| crate::RgbidError::new_err("a previous call panicked inside rgbid"))
}

/// What an [`Odometry`] aligns each frame to.
enum Tracker {
    /// Frame-to-reference (the default).
    Reference(rgbid::odometry::Odometry),
    /// Frame-to-model: the intensity and inverse depth ray cast from a TSDF of the frames.
    Model(Box<ModelOdometry>),
}

impl Tracker {
    fn set_initial_pose(&mut self, world_from_camera: Se3) {
        match self {
            Tracker::Reference(o) => o.set_initial_pose(world_from_camera),
            Tracker::Model(o) => o.set_initial_pose(world_from_camera),
        }
    }

    /// The tracking result and, frame-to-model, the model's stage times.
    fn track(
        &mut self,
        frame: &rgbid::image::RgbdFrame,
    ) -> Result<(TrackResult, Option<ModelTimes>), OdometryError> {
        match self {
            Tracker::Reference(o) => Ok((o.track(frame)?, None)),
            Tracker::Model(o) => o.track(frame).map(|r| (r.track, Some(r.model))),
        }
    }
}

/// The model's options from the ``model`` dict: ``voxel`` (metres), ``cast_level`` and
/// ``fill_holes``, each optional; any other key is an error.
fn model_params(model: &Bound<'_, PyDict>) -> PyResult<TrackingModelParams> {
    let mut p = TrackingModelParams::default();
    for (k, v) in model.iter() {
        let key: String = k.extract()?;
        match key.as_str() {
            "voxel" => p.tsdf.voxel_size = v.extract()?,
            "cast_level" => p.cast_level = v.extract()?,
            "fill_holes" => p.fill_holes = v.extract()?,
            other => {
                return Err(PyValueError::new_err(format!(
                    "model: unknown key {other:?} (known: voxel, cast_level, fill_holes)"
                )))
            }
        }
    }
    Ok(p)
}

/// Dense RGB-D odometry with inverse depth (thesis ch. 4, 6.3) over a stream of frames.
///
/// ``Odometry(camera, config=None, backend="auto", model=None)``: ``config`` is a dict with
/// the keys of an ``OdometryConfig`` TOML file (``rgbid config dump --command odometry``; any
/// subset, unknown keys are an error) or a path to such a file; ``backend`` is ``"auto"`` (a
/// hardware GPU, else the CPU), ``"gpu"`` (any adapter, lavapipe included) or ``"cpu"``.
/// ``model``: ``None`` aligns each frame to a reference frame; a dict (``{}`` for the
/// defaults) aligns it to the intensity and inverse depth ray cast from a TSDF model of the
/// frames tracked so far, as ``rgbid odometry --reference model`` does, with the keys
/// ``voxel`` (TSDF voxel edge, metres, default 0.02), ``cast_level`` (pyramid level of the
/// cast, default 1) and ``fill_holes`` (the previous frame fills what the cast misses,
/// default ``True``).
#[pyclass(module = "rgbid")]
pub struct Odometry {
    inner: Mutex<Tracker>,
    camera: Camera,
    map: Option<UndistortMap>,
    backend: String,
}

#[pymethods]
impl Odometry {
    #[new]
    #[pyo3(signature = (camera, config = None, backend = "auto", model = None))]
    fn py_new(
        py: Python<'_>,
        camera: Camera,
        config: Option<&Bound<'_, PyAny>>,
        backend: &str,
        model: Option<&Bound<'_, PyDict>>,
    ) -> PyResult<Self> {
        let config: OdometryConfig = config_from(py, config)?;
        config.validate().map_err(value)?;
        let compute = backend_from(backend)?;
        let cam = camera.undistorted();
        let params = model.map(model_params).transpose()?;
        let odo = py
            .detach(|| match params {
                None => {
                    rgbid::odometry::Odometry::new(config, cam, &compute).map(Tracker::Reference)
                }
                Some(p) => ModelOdometry::new(config, p, cam, &compute)
                    .map(|m| Tracker::Model(Box::new(m))),
            })
            .map_err(|e| match e {
                OdometryError::InvalidConfig(_)
                | OdometryError::TooManyLevels { .. }
                | OdometryError::Model(rgbid::tsdf::TsdfError::InvalidParameter { .. }) => value(e),
                other => runtime(other),
            })?;
        Ok(Self {
            inner: Mutex::new(odo),
            map: camera.undistort_map(),
            camera,
            backend: compute.name(),
        })
    }

    /// Sets the pose of the first frame, ``world_from_camera`` as ``float64[4, 4]`` (metres);
    /// the default is the identity.
    fn set_initial_pose(&self, world_from_camera: PyReadonlyArray2<'_, f64>) -> PyResult<()> {
        let pose = pose_from_matrix(world_from_camera)?;
        locked(&self.inner)?.set_initial_pose(pose);
        Ok(())
    }

    /// Tracks one frame. ``image``: ``uint8[H, W]`` grey or ``uint8[H, W, 3]`` RGB (an OpenCV
    /// BGR image must be converted first); ``depth``: ``uint16[H, W]`` in units of
    /// ``1 / depth_factor`` metres (0 = no measurement), or ``float32[H, W]`` metres with
    /// ``depth_factor=None``; ``depth_factor`` defaults to the camera preset's;
    /// ``timestamp`` in seconds. Arrays must be C-contiguous; they are read in place.
    ///
    /// Returns a dict: ``world_from_camera`` (``float64[4, 4]``, or ``None`` when tracking
    /// failed, ``status`` then ``"tracking_failed"`` and ``message`` says why),
    /// ``cur_from_ref`` (``float64[4, 4]``), ``covariance`` (``float64[6, 6]`` of the
    /// alignment, twist ``[v; w]`` in m and rad, or ``None``), ``status`` (``"ok"``),
    /// ``stats`` (iterations, sigma_photo, sigma_geo, nu, covisibility, condition_number,
    /// new_reference, times in ms), ``model_ms`` (frame-to-model: ``ray_cast`` and
    /// ``integrate`` times in ms, else ``None``) and ``rust_ms`` (time spent in the library for
    /// this call: building the frame and tracking it).
    #[pyo3(signature = (image, depth, depth_factor = None, timestamp = 0.0))]
    fn track<'py>(
        &self,
        py: Python<'py>,
        image: &Bound<'py, PyAny>,
        depth: &Bound<'py, PyAny>,
        depth_factor: Option<f64>,
        timestamp: f64,
    ) -> PyResult<Bound<'py, PyDict>> {
        let input = FrameIn::new(py, image, depth, depth_factor, self.camera.depth_factor)?;
        let buffers = input.buffers()?;
        let (map, inner) = (self.map.as_ref(), &self.inner);
        let (outcome, rust_ms) = py.detach(|| {
            let t0 = Instant::now();
            let outcome =
                (|| -> PyResult<Result<(TrackResult, Option<ModelTimes>), OdometryError>> {
                    let frame = buffers.frame(timestamp, map).map_err(value)?;
                    Ok(locked(inner)?.track(&frame))
                })();
            (outcome, t0.elapsed().as_secs_f64() * 1e3)
        });
        let tracked = outcome?;
        let d = PyDict::new(py);
        match tracked {
            Ok((r, model)) => {
                d.set_item("world_from_camera", pose_matrix(py, &r.world_from_camera))?;
                d.set_item("cur_from_ref", pose_matrix(py, &r.cur_from_ref))?;
                let cov = r.covariance.map(|c| covariance_array(py, c.rows()));
                d.set_item("covariance", cov)?;
                d.set_item("status", "ok")?;
                d.set_item("stats", to_python(py, &r.stats)?)?;
                match model {
                    Some(m) => {
                        let times = PyDict::new(py);
                        times.set_item("ray_cast", m.ray_cast_ms)?;
                        times.set_item("integrate", m.integrate_ms)?;
                        d.set_item("model_ms", times)?;
                    }
                    None => d.set_item("model_ms", py.None())?,
                }
            }
            Err(OdometryError::TrackingFailed(m)) => {
                d.set_item("world_from_camera", py.None())?;
                d.set_item("cur_from_ref", py.None())?;
                d.set_item("covariance", py.None())?;
                d.set_item("status", "tracking_failed")?;
                d.set_item("message", m)?;
                d.set_item("stats", py.None())?;
                d.set_item("model_ms", py.None())?;
            }
            Err(e @ OdometryError::FrameSize { .. }) => return Err(value(e)),
            Err(e) => return Err(runtime(e)),
        }
        d.set_item("timestamp", timestamp)?;
        d.set_item("rust_ms", rust_ms)?;
        Ok(d)
    }

    /// The compute backend in use (adapter name or ``"cpu"``).
    #[getter]
    fn backend(&self) -> String {
        self.backend.clone()
    }

    /// The camera.
    #[getter]
    fn camera(&self) -> Camera {
        self.camera.clone()
    }
}

fn covariance_array<'py>(py: Python<'py>, rows: &[[f64; 6]; 6]) -> Bound<'py, PyArray2<f64>> {
    let mut m = Array2::<f64>::zeros((6, 6));
    for (i, row) in rows.iter().enumerate() {
        for (j, v) in row.iter().enumerate() {
            m[[i, j]] = *v;
        }
    }
    m.into_pyarray(py)
}

/// `world_from_x` poses as `float64[K, 4, 4]`.
fn pose_stack<'py>(py: Python<'py>, poses: &[Se3]) -> Bound<'py, PyArray3<f64>> {
    let mut m = Array3::<f64>::zeros((poses.len(), 4, 4));
    for (k, p) in poses.iter().enumerate() {
        let r = glam::DMat3::from_quat(p.rotation);
        for row in 0..3 {
            for col in 0..3 {
                m[[k, row, col]] = r.col(col)[row];
            }
        }
        m[[k, 0, 3]] = p.translation.x;
        m[[k, 1, 3]] = p.translation.y;
        m[[k, 2, 3]] = p.translation.z;
        m[[k, 3, 3]] = 1.0;
    }
    m.into_pyarray(py)
}

fn status_name(s: FrameStatus) -> &'static str {
    match s {
        FrameStatus::Tracking => "tracking",
        FrameStatus::NewKeyframe => "new_keyframe",
        FrameStatus::Lost => "lost",
        FrameStatus::Relocalised => "relocalised",
    }
}

/// RGB-ID SLAM (thesis ch. 6): tracking, keyframe fusion, loop closure on a back-end thread,
/// pose graph.
///
/// ``Slam(camera, config=None, backend="auto", map_path=None, vocabulary=None)``: ``config``
/// is a dict with the keys of a ``SlamConfig`` TOML file (``rgbid config dump --command
/// slam``) or a path to one; ``map_path`` a map saved by ``SlamResult.save_map`` to
/// relocalise in and extend; ``vocabulary`` a vocabulary file (default: the embedded one).
#[pyclass(module = "rgbid")]
pub struct Slam {
    inner: Mutex<Option<rgbid::slam::Slam>>,
    camera: Camera,
    map: Option<UndistortMap>,
    backend: String,
}

impl Slam {
    fn finished() -> PyErr {
        PyValueError::new_err("this Slam has finished; start a new one")
    }
}

#[pymethods]
impl Slam {
    #[new]
    #[pyo3(signature = (camera, config = None, backend = "auto", map_path = None, vocabulary = None))]
    fn py_new(
        py: Python<'_>,
        camera: Camera,
        config: Option<&Bound<'_, PyAny>>,
        backend: &str,
        map_path: Option<std::path::PathBuf>,
        vocabulary: Option<std::path::PathBuf>,
    ) -> PyResult<Self> {
        let config: SlamConfig = config_from(py, config)?;
        config.validate().map_err(value)?;
        let compute = backend_from(backend)?;
        let cam = camera.undistorted();
        let slam = py.detach(|| -> PyResult<rgbid::slam::Slam> {
            let vocabulary = match &vocabulary {
                Some(p) => Vocabulary::load(p).map_err(runtime)?,
                None => Vocabulary::embedded_default().map_err(runtime)?,
            };
            let map = match &map_path {
                Some(p) => Some(Map::load(p).map_err(runtime)?),
                None => None,
            };
            rgbid::slam::Slam::new(config, cam, &compute, vocabulary, map).map_err(runtime)
        })?;
        Ok(Self {
            inner: Mutex::new(Some(slam)),
            map: camera.undistort_map(),
            camera,
            backend: compute.name(),
        })
    }

    /// Processes one frame (inputs as ``Odometry.track``). Returns a dict:
    /// ``world_from_camera`` (``float64[4, 4]`` corrected by the loops so far, ``None`` while
    /// lost), ``frontworld_from_camera`` (the odometry's pose), ``status`` (``"tracking"``,
    /// ``"new_keyframe"``, ``"lost"``, ``"relocalised"``), ``index``, ``keyframes``, ``loops``
    /// (accepted so far), ``covisibility``, ``keyframe_covisibility``, ``frontend_ms`` and
    /// ``rust_ms`` (time in the library for this call).
    #[pyo3(signature = (image, depth, depth_factor = None, timestamp = 0.0))]
    fn process<'py>(
        &self,
        py: Python<'py>,
        image: &Bound<'py, PyAny>,
        depth: &Bound<'py, PyAny>,
        depth_factor: Option<f64>,
        timestamp: f64,
    ) -> PyResult<Bound<'py, PyDict>> {
        let input = FrameIn::new(py, image, depth, depth_factor, self.camera.depth_factor)?;
        let buffers = input.buffers()?;
        let (map, inner) = (self.map.as_ref(), &self.inner);
        let (report, rust_ms) = py.detach(|| {
            let t0 = Instant::now();
            let report = (|| -> PyResult<rgbid::slam::FrameReport> {
                let frame = buffers.frame(timestamp, map).map_err(value)?;
                let mut guard = locked(inner)?;
                let slam = guard.as_mut().ok_or_else(Self::finished)?;
                slam.process(&frame).map_err(runtime)
            })();
            (report, t0.elapsed().as_secs_f64() * 1e3)
        });
        let r = report?;
        let d = PyDict::new(py);
        d.set_item(
            "world_from_camera",
            r.world_from_camera.map(|p| pose_matrix(py, &p)),
        )?;
        d.set_item(
            "frontworld_from_camera",
            r.record.frontworld_from_camera.map(|p| pose_matrix(py, &p)),
        )?;
        d.set_item("status", status_name(r.status))?;
        d.set_item("index", r.record.index)?;
        d.set_item("timestamp", r.record.timestamp)?;
        d.set_item("keyframes", r.keyframes)?;
        d.set_item("loops", r.loops)?;
        d.set_item("covisibility", r.record.covisibility)?;
        d.set_item("keyframe_covisibility", r.record.keyframe_covisibility)?;
        d.set_item("frontend_ms", r.record.frontend_ms)?;
        d.set_item("rust_ms", rust_ms)?;
        Ok(d)
    }

    /// The event stream (keyframes created and described, loops checked, graph optimisations,
    /// lost, relocalised). Events are recorded from the first call on; a reader that lags
    /// loses the oldest events (counted in ``EventStream.dropped``), the system never waits.
    fn events(&self) -> PyResult<EventStream> {
        let guard = locked(&self.inner)?;
        let slam = guard.as_ref().ok_or_else(Self::finished)?;
        Ok(EventStream {
            inner: Mutex::new(slam.events()),
        })
    }

    /// Frames processed so far.
    #[getter]
    fn frames(&self) -> PyResult<usize> {
        let guard = locked(&self.inner)?;
        Ok(guard.as_ref().map_or(0, |s| s.frames()))
    }

    /// The compute backend in use.
    #[getter]
    fn backend(&self) -> String {
        self.backend.clone()
    }

    /// Ends the run: the last optimisations (keyframes, then all frames) and the map.
    /// ``voxel`` is the model's voxel filter size in metres (0 = none). Returns a
    /// ``SlamResult``; the ``Slam`` cannot process frames afterwards.
    #[pyo3(signature = (voxel = ModelParams::default().voxel))]
    fn finish(&self, py: Python<'_>, voxel: f64) -> PyResult<SlamResult> {
        if !(voxel >= 0.0 && voxel.is_finite()) {
            return Err(PyValueError::new_err(format!(
                "voxel must be >= 0 metres, got {voxel}"
            )));
        }
        let slam = locked(&self.inner)?.take().ok_or_else(Self::finished)?;
        let camera = self.camera.undistorted();
        py.detach(move || {
            let r = slam.finish().map_err(runtime)?;
            let params = ModelParams {
                voxel,
                ..Default::default()
            };
            let points = build_coloured_model(r.keyframes(), &r.keyframe_poses, &camera, &params);
            let keyframes = r.keyframe_trajectory();
            let statuses = r.frames.iter().map(|f| status_name(f.status)).collect();
            Ok(SlamResult {
                trajectory: r.trajectory,
                odometry: r.odometry,
                keyframes,
                loops: r.loops.iter().map(LoopRow::from).collect(),
                points,
                statuses,
                map: r.map,
            })
        })
    }
}

/// What a finished ``Slam`` produced.
#[pyclass(frozen, module = "rgbid")]
pub struct SlamResult {
    trajectory: Vec<TimedPose>,
    odometry: Vec<TimedPose>,
    keyframes: Vec<TimedPose>,
    loops: Vec<LoopRow>,
    points: Vec<(glam::DVec3, [u8; 3])>,
    statuses: Vec<&'static str>,
    map: Map,
}

#[pymethods]
impl SlamResult {
    /// ``float64[N, 8]``, TUM columns ``t tx ty tz qx qy qz qw`` (``world_from_camera``,
    /// seconds and metres): every tracked frame after the final optimisation.
    #[getter]
    fn trajectory<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<f64>> {
        trajectory_array(py, &self.trajectory)
    }
    /// ``float64[N, 8]``: the front-end (odometry-only) poses of the tracked frames.
    #[getter]
    fn odometry<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<f64>> {
        trajectory_array(py, &self.odometry)
    }
    /// ``float64[K, 8]``: the optimised keyframe poses, TUM columns.
    #[getter]
    fn keyframes<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<f64>> {
        trajectory_array(py, &self.keyframes)
    }
    /// Loops checked (accepted and rejected), one dict each with the columns of
    /// ``loops.csv`` of ``rgbid slam``.
    #[getter]
    fn loops<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        to_python(py, &self.loops)
    }
    /// ``float64[N, 3]``: the model's points in the world frame, metres (keyframe points
    /// not seen by the previous keyframe, voxel-filtered).
    #[getter]
    fn points<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<f64>> {
        let mut m = Array2::<f64>::zeros((self.points.len(), 3));
        for (i, (p, _)) in self.points.iter().enumerate() {
            m[[i, 0]] = p.x;
            m[[i, 1]] = p.y;
            m[[i, 2]] = p.z;
        }
        m.into_pyarray(py)
    }
    /// ``uint8[N, 3]``: the points' RGB, the mean colour of the keyframe pixels in each
    /// voxel. Keyframes keep the RGB of their reference frame when the frames had colour
    /// (and the configuration's ``keyframe_colour`` is on); otherwise the three channels are
    /// the same grey value, the intensity.
    #[getter]
    fn colors<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<u8>> {
        let mut m = Array2::<u8>::zeros((self.points.len(), 3));
        for (i, (_, rgb)) in self.points.iter().enumerate() {
            for (c, v) in rgb.iter().enumerate() {
                m[[i, c]] = *v;
            }
        }
        m.into_pyarray(py)
    }
    /// Per-frame status (``"tracking"``, ``"new_keyframe"``, ``"lost"``, ``"relocalised"``),
    /// one per processed frame.
    #[getter]
    fn statuses(&self) -> Vec<&'static str> {
        self.statuses.clone()
    }
    /// Saves the map (keyframes, descriptors, graph) to ``path`` in rgbid's versioned binary
    /// format, for ``Slam(..., map_path=path)``.
    fn save_map(&self, py: Python<'_>, path: std::path::PathBuf) -> PyResult<()> {
        py.detach(|| self.map.save(&path)).map_err(runtime)
    }
    fn __repr__(&self) -> String {
        format!(
            "SlamResult({} poses, {} keyframes, {} loops checked, {} points)",
            self.trajectory.len(),
            self.keyframes.len(),
            self.loops.len(),
            self.points.len()
        )
    }
}

/// The events of a ``Slam``: iterating yields the events waiting now (one dict each, with
/// ``kind``) and stops when none is left; iterate again later for newer ones. After
/// ``Slam.finish`` everything the run produced is waiting.
#[pyclass(module = "rgbid")]
pub struct EventStream {
    inner: Mutex<SlamEvents>,
}

#[pymethods]
impl EventStream {
    fn __iter__(slf: PyRef<'_, Self>) -> PyRef<'_, Self> {
        slf
    }

    fn __next__<'py>(&self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyDict>>> {
        let next = locked(&self.inner)?.try_recv().ok();
        next.map(|e| event_dict(py, e)).transpose()
    }

    /// Events lost because the reader lagged: ``{"images": n, "events": m}``.
    #[getter]
    fn dropped<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let d = locked(&self.inner)?.dropped();
        let out = PyDict::new(py);
        out.set_item("images", d.images)?;
        out.set_item("events", d.events)?;
        Ok(out)
    }
}

fn event_dict(py: Python<'_>, e: SlamEvent) -> PyResult<Bound<'_, PyDict>> {
    let d = PyDict::new(py);
    match e {
        SlamEvent::KeyframeCreated {
            id,
            frame_index,
            timestamp,
            world_from_keyframe,
            link,
        } => {
            d.set_item("kind", "keyframe_created")?;
            d.set_item("id", id)?;
            d.set_item("frame_index", frame_index)?;
            d.set_item("timestamp", timestamp)?;
            d.set_item("world_from_keyframe", pose_matrix(py, &world_from_keyframe))?;
            d.set_item(
                "link",
                match link {
                    KeyframeLink::First => "first",
                    KeyframeLink::Odometry { .. } => "odometry",
                    KeyframeLink::Relocalised { .. } => "relocalised",
                },
            )?;
        }
        SlamEvent::KeyframeDescribed(k) => {
            d.set_item("kind", "keyframe_described")?;
            d.set_item("id", k.id)?;
            d.set_item("superjuts", k.neg_entropy.len())?;
            d.set_item("neg_entropy", k.neg_entropy)?;
            d.set_item("keypoints", k.keypoints.len())?;
            d.set_item("segment_ms", k.segment_ms)?;
            d.set_item("describe_ms", k.describe_ms)?;
        }
        SlamEvent::LoopChecked(l) => {
            d.set_item("kind", "loop_checked")?;
            d.set_item("loop", to_python(py, &LoopRow::from(&l))?)?;
            d.set_item("accepted", l.verdict.is_accepted())?;
        }
        SlamEvent::GraphOptimised {
            world_from_keyframe,
            loops,
            optimise_ms,
        } => {
            d.set_item("kind", "graph_optimised")?;
            d.set_item("world_from_keyframe", pose_stack(py, &world_from_keyframe))?;
            d.set_item("loops", loops)?;
            d.set_item("optimise_ms", optimise_ms)?;
        }
        SlamEvent::Lost {
            frame_index,
            timestamp,
        } => {
            d.set_item("kind", "lost")?;
            d.set_item("frame_index", frame_index)?;
            d.set_item("timestamp", timestamp)?;
        }
        SlamEvent::Relocalised {
            frame_index,
            timestamp,
            keyframe,
            new_keyframe,
            world_from_camera,
        } => {
            d.set_item("kind", "relocalised")?;
            d.set_item("frame_index", frame_index)?;
            d.set_item("timestamp", timestamp)?;
            d.set_item("keyframe", keyframe)?;
            d.set_item("new_keyframe", new_keyframe)?;
            d.set_item("world_from_camera", pose_matrix(py, &world_from_camera))?;
        }
        // Variants added later come through by their debug text.
        #[allow(unreachable_patterns)]
        other => {
            d.set_item("kind", "other")?;
            d.set_item("debug", format!("{other:?}"))?;
        }
    }
    Ok(d)
}
