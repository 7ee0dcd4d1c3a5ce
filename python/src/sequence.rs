//! Frames as stored: TUM folders and generated sequences, as numpy arrays.

use std::path::PathBuf;
use std::sync::{Arc, Mutex};

use numpy::ndarray::{Array2, Array3};
use numpy::IntoPyArray;
use pyo3::exceptions::{PyIndexError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyTuple;
use rgbid::camera::PinholeCamera;
use rgbid::io::tum::{OpenOptions, RawPixels, TumSequence};
use rgbid::io::CameraConfig;
use rgbid::synth::tum_export::TumWriter;
use rgbid::synth::{
    CameraModel, RenderBackend, Scene, SensorModel, SequenceConfig, Trajectory, TrajectoryKind,
    DEPTH_FACTOR, PRESETS,
};
use rgbid::trajectory::TimedPose;

use crate::convert::{runtime, trajectory_array, value};
use crate::frames::Camera;

enum Source {
    Tum(Box<TumSequence>),
    Synth(Box<Mutex<rgbid::synth::Sequence>>),
}

/// A sequence of frames as stored: ``len(seq)``, ``seq[i]`` and iteration give
/// ``(timestamp, image, depth, depth_factor)`` with ``image`` ``uint8[H, W, 3]`` RGB or
/// ``uint8[H, W]`` grey (as stored, not undistorted), ``depth`` the raw ``uint16[H, W]``
/// (units of ``1 / depth_factor`` metres, 0 = no measurement), ``timestamp`` in seconds.
#[pyclass(frozen, module = "rgbid")]
pub struct Sequence {
    source: Source,
    camera: Camera,
    depth_factor: f64,
    groundtruth: Option<Vec<TimedPose>>,
    timestamps: Vec<f64>,
    path: Option<PathBuf>,
}

#[pymethods]
impl Sequence {
    fn __len__(&self) -> usize {
        self.timestamps.len()
    }

    fn __getitem__<'py>(&self, py: Python<'py>, index: isize) -> PyResult<Bound<'py, PyTuple>> {
        let n = self.timestamps.len() as isize;
        let i = if index < 0 { index + n } else { index };
        if i < 0 || i >= n {
            return Err(PyIndexError::new_err(format!(
                "frame {index} of a sequence of {n}"
            )));
        }
        let i = i as usize;
        let (timestamp, pixels, depth, (w, h)) = py.detach(|| self.load(i))?;
        let image = match pixels {
            RawPixels::Gray(g) => Array2::from_shape_vec((h, w), g)
                .map_err(value)?
                .into_pyarray(py)
                .into_any(),
            RawPixels::Rgb(c) => Array3::from_shape_vec((h, w, 3), c)
                .map_err(value)?
                .into_pyarray(py)
                .into_any(),
        };
        let depth = Array2::from_shape_vec((h, w), depth)
            .map_err(value)?
            .into_pyarray(py);
        PyTuple::new(
            py,
            [
                timestamp.into_pyobject(py)?.into_any(),
                image,
                depth.into_any(),
                self.depth_factor.into_pyobject(py)?.into_any(),
            ],
        )
    }

    /// The camera of the frames (with the distortion of the calibration, if any).
    #[getter]
    fn camera(&self) -> Camera {
        self.camera.clone()
    }

    /// Depth units per metre.
    #[getter]
    fn depth_factor(&self) -> f64 {
        self.depth_factor
    }

    /// Time stamps of the frames, seconds, ``float64[N]``.
    #[getter]
    fn timestamps(&self) -> Vec<f64> {
        self.timestamps.clone()
    }

    /// Ground truth as ``float64[M, 8]`` TUM columns, or ``None``.
    #[getter]
    fn groundtruth<'py>(&self, py: Python<'py>) -> Option<Bound<'py, numpy::PyArray2<f64>>> {
        self.groundtruth.as_ref().map(|g| trajectory_array(py, g))
    }

    /// The folder the frames are read from (``None`` for frames generated in memory).
    #[getter]
    fn path(&self) -> Option<PathBuf> {
        self.path.clone()
    }

    fn __repr__(&self) -> String {
        let c = &self.camera.camera;
        format!(
            "Sequence({} frames, {}x{}, {})",
            self.timestamps.len(),
            c.width,
            c.height,
            self.path
                .as_ref()
                .map_or("generated".into(), |p| p.display().to_string())
        )
    }
}

type Loaded = (f64, RawPixels, Vec<u16>, (usize, usize));

impl Sequence {
    fn load(&self, i: usize) -> PyResult<Loaded> {
        match &self.source {
            Source::Tum(s) => {
                let f = s.load_raw(i).map_err(runtime)?;
                Ok((f.timestamp, f.pixels, f.depth, (f.width, f.height)))
            }
            Source::Synth(s) => {
                let mut s = s
                    .lock()
                    .map_err(|_| crate::RgbidError::new_err("a previous render panicked"))?;
                let f = s.render_frame(i).map_err(runtime)?;
                let (w, h) = (f.frame.width(), f.frame.height());
                let depth = f.frame.depth_u16();
                Ok((f.timestamp, RawPixels::Rgb(f.frame.rgb), depth, (w, h)))
            }
        }
    }

    fn open_tum(
        path: PathBuf,
        camera: Option<CameraConfig>,
        max_frames: Option<usize>,
    ) -> PyResult<Self> {
        let opts = OpenOptions {
            camera,
            max_frames,
            ..Default::default()
        };
        let seq = TumSequence::open(&path, &opts).map_err(runtime)?;
        let groundtruth = seq.ground_truth().map_err(runtime)?;
        Ok(Self {
            camera: Camera::new_checked(seq.camera, Some(seq.depth_factor))?,
            depth_factor: seq.depth_factor,
            timestamps: seq.entries.iter().map(|e| e.timestamp).collect(),
            groundtruth,
            source: Source::Tum(Box::new(seq)),
            path: Some(path),
        })
    }
}

/// Opens a sequence folder in any layout ``rgbid odometry`` and ``rgbid slam`` read: TUM RGB-D
/// (``rgb.txt`` + ``depth.txt`` or ``associations.txt``, optional ``groundtruth.txt`` and
/// ``calib.txt``), ETH3D, a 7-Scenes ``seq-NN`` folder, a ScanNet export or Replica as
/// rendered for NICE-SLAM, detected from the content. ``camera``: a ``Camera``, a preset name
/// or a calibration file (default: the layout's own, else ``calib.txt`` beside the frames, else
/// the ``default`` preset); ``max_frames`` keeps the first frames only. Images are returned as
/// stored (a ScanNet colour image at its own size).
#[pyfunction]
#[pyo3(signature = (path, camera = None, max_frames = None))]
pub fn read_sequence(
    py: Python<'_>,
    path: PathBuf,
    camera: Option<&Bound<'_, PyAny>>,
    max_frames: Option<usize>,
) -> PyResult<Sequence> {
    let camera = match camera {
        None => None,
        Some(c) if c.is_none() => None,
        Some(c) => Some(match c.extract::<Camera>() {
            Ok(cam) => CameraConfig {
                camera: cam.camera,
                depth_factor: cam.depth_factor.unwrap_or(DEPTH_FACTOR),
                source: "the given Camera".into(),
            },
            Err(_) => {
                let name: String = c.extract().map_err(|_| {
                    PyValueError::new_err("camera must be a Camera, a preset name or a file path")
                })?;
                CameraConfig::from_name_or_path(&name).map_err(value)?
            }
        }),
    };
    py.detach(|| Sequence::open_tum(path, camera, max_frames))
}

/// A generated sequence (exact ground truth, Kinect-like sensor noise): ``scene`` (one of
/// ``office``, ``corridor``, ... as ``rgbid synth --help`` lists), ``trajectory`` (``loop``,
/// ``handheld``, ...), ``frames`` at 30 per second, ``seed``, ``width`` pixels (height 3/4 of
/// it; fx = 525 px at 640 wide). ``out``: write a TUM folder there (what ``rgbid synth
/// --out`` writes) and read it back; ``None``: render frames on demand in memory.
#[pyfunction]
#[pyo3(signature = (scene, trajectory, frames, seed, width = 320, out = None, noise = true))]
#[allow(clippy::too_many_arguments)]
pub fn synth_render(
    py: Python<'_>,
    scene: &str,
    trajectory: &str,
    frames: usize,
    seed: u64,
    width: u32,
    out: Option<PathBuf>,
    noise: bool,
) -> PyResult<Sequence> {
    if !PRESETS.contains(&scene) {
        return Err(PyValueError::new_err(format!(
            "unknown scene '{scene}' (known: {})",
            PRESETS.join(", ")
        )));
    }
    if frames == 0 || width < 16 {
        return Err(PyValueError::new_err(
            "a generated sequence needs frames >= 1 and width >= 16",
        ));
    }
    let kind = TrajectoryKind::from_name(trajectory).map_err(value)?;
    let (w, h) = (width, width * 3 / 4);
    let f = 525.0 * f64::from(w) / 640.0;
    let cam = PinholeCamera::new(
        f,
        f,
        (f64::from(w) - 1.0) / 2.0,
        (f64::from(h) - 1.0) / 2.0,
        w,
        h,
    );
    py.detach(|| {
        let scene_arc = Arc::new(Scene::preset(scene, seed).map_err(value)?);
        let config = SequenceConfig {
            frames,
            seed,
            sensor: if noise {
                SensorModel::kinect()
            } else {
                SensorModel::noiseless()
            },
            ..Default::default()
        };
        let traj = Trajectory::new(kind, &scene_arc, config.duration(), seed).map_err(runtime)?;
        let mut seq = rgbid::synth::Sequence::new(
            scene_arc,
            CameraModel::Pinhole(cam),
            traj,
            config,
            &RenderBackend::Cpu,
        )
        .map_err(runtime)?;
        let Some(dir) = out else {
            let groundtruth = Some(seq.ground_truth());
            let timestamps = groundtruth.iter().flatten().map(|p| p.timestamp).collect();
            return Ok(Sequence {
                camera: Camera::new_checked(cam, Some(DEPTH_FACTOR))?,
                depth_factor: DEPTH_FACTOR,
                groundtruth,
                timestamps,
                source: Source::Synth(Box::new(Mutex::new(seq))),
                path: None,
            });
        };
        let model = CameraModel::Pinhole(cam);
        let mut writer = TumWriter::create(&dir, &model).map_err(runtime)?;
        for i in 0..frames {
            let f = seq.render_frame(i).map_err(runtime)?;
            writer
                .write_frame(f.timestamp, &f.world_from_camera, &f.frame)
                .map_err(runtime)?;
        }
        let readme = format!(
            "Synthetic sequence rendered by rgbid.synth.render (exact ground truth).\n\
             scene {scene:?}, trajectory {trajectory}, {frames} frames at 30 fps, seed {seed}, \
             {w}x{h}, sensor noise {noise}.\n\
             groundtruth.txt holds world_from_camera in TUM format. Depth PNGs: 16-bit, \
             5000 per metre, 0 = no measurement.\n"
        );
        writer.finish(&readme, &[]).map_err(runtime)?;
        Sequence::open_tum(dir, None, None)
    })
}
