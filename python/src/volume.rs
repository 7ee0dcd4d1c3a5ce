//! `TsdfVolume`: dense TSDF reconstruction (integrate, ray cast, extract a mesh, save, load).

use std::path::PathBuf;
use std::sync::Mutex;

use numpy::ndarray::{Array2, Array3};
use numpy::{IntoPyArray, PyArray2, PyReadonlyArray2, PyUntypedArray, PyUntypedArrayMethods};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyTuple};
use rgbid::io::UndistortMap;
use rgbid::tsdf::{TsdfError, TsdfParams};

use crate::convert::{backend_from, pose_from_matrix, runtime, value};
use crate::frames::{Camera, FrameIn};

/// The lock of the volume; a panic inside the library while it was held poisons it.
fn locked<T>(m: &Mutex<T>) -> PyResult<std::sync::MutexGuard<'_, T>> {
    m.lock()
        .map_err(|_| crate::RgbidError::new_err("a previous call panicked inside rgbid"))
}

/// Bad parameters and frames are the caller's (`ValueError`); the rest is rgbid's.
fn tsdf_err(e: TsdfError) -> PyErr {
    match e {
        TsdfError::InvalidParameter { .. }
        | TsdfError::FrameSize { .. }
        | TsdfError::OutOfRange
        | TsdfError::NonFinitePose
        | TsdfError::Image(_) => value(e),
        other => runtime(other),
    }
}

/// A sparse TSDF volume in the world frame (blocks of 8^3 voxels; thesis 4.5.5): integrate
/// RGB-D frames at known poses, ray cast depth / normals / colour from any pose, extract a
/// coloured triangle mesh, save and load.
///
/// ``TsdfVolume(camera, voxel=0.01, min_depth=0.3, max_depth=4.0, backend="auto",
/// device_blocks=None)``: ``voxel`` is the voxel edge in metres, depths outside
/// ``[min_depth, max_depth]`` metres are not integrated; ``backend`` is ``"auto"`` (a hardware
/// GPU, else the CPU), ``"gpu"`` (any adapter, lavapipe included) or ``"cpu"``;
/// ``device_blocks`` (>= 1, ``None`` = unbounded) is the most voxel blocks (6144 bytes each)
/// kept on the GPU, the blocks farthest from the camera moving to host memory and back (same
/// mesh; the CPU backend ignores it). Frames of a camera with distortion are undistorted
/// first.
#[pyclass(module = "rgbid")]
pub struct TsdfVolume {
    inner: Mutex<rgbid::tsdf::TsdfVolume>,
    camera: Camera,
    map: Option<UndistortMap>,
    backend: String,
}

#[pymethods]
impl TsdfVolume {
    #[new]
    #[pyo3(signature = (camera, voxel = 0.01, min_depth = 0.3, max_depth = 4.0, backend = "auto", device_blocks = None))]
    fn py_new(
        py: Python<'_>,
        camera: Camera,
        voxel: f64,
        min_depth: f64,
        max_depth: f64,
        backend: &str,
        device_blocks: Option<usize>,
    ) -> PyResult<Self> {
        let params = TsdfParams {
            voxel_size: voxel,
            min_depth,
            max_depth,
            device_blocks,
            ..Default::default()
        };
        params.validate().map_err(value)?;
        let compute = backend_from(backend)?;
        let cam = camera.undistorted();
        let volume = py
            .detach(|| rgbid::tsdf::TsdfVolume::new(params, cam, &compute))
            .map_err(tsdf_err)?;
        Ok(Self {
            inner: Mutex::new(volume),
            map: camera.undistort_map(),
            camera,
            backend: compute.name(),
        })
    }

    /// Loads a volume saved by :meth:`save` (or by ``rgbid mesh --save-volume`` / ``rgbid slam
    /// --mesh``'s ``volume.tsdf``). Frames integrated later are of ``camera`` when given, else
    /// of the saved (undistorted) camera. A missing, truncated, corrupt or other-version file
    /// raises ``RgbidError`` naming the file and the cause.
    #[staticmethod]
    #[pyo3(signature = (path, camera = None, backend = "auto"))]
    fn load(
        py: Python<'_>,
        path: PathBuf,
        camera: Option<Camera>,
        backend: &str,
    ) -> PyResult<Self> {
        let compute = backend_from(backend)?;
        let cam = camera.as_ref().map(|c| c.undistorted());
        let volume = py
            .detach(|| rgbid::tsdf::TsdfVolume::load(&path, cam, &compute))
            .map_err(runtime)?;
        let camera = match camera {
            Some(c) => c,
            None => Camera {
                camera: *volume.camera(),
                depth_factor: None,
            },
        };
        Ok(Self {
            inner: Mutex::new(volume),
            map: camera.undistort_map(),
            camera,
            backend: compute.name(),
        })
    }

    /// Saves the volume to ``path`` (rgbid's binary ``.tsdf`` format, replaced atomically).
    fn save(&self, py: Python<'_>, path: PathBuf) -> PyResult<()> {
        let inner = &self.inner;
        py.detach(|| -> PyResult<()> { locked(inner)?.save(&path).map_err(runtime) })
    }

    /// Integrates one frame seen from ``world_from_camera`` (``float64[4, 4]``, metres).
    /// ``depth``: ``uint16[H, W]`` in units of ``1 / depth_factor`` metres (0 = no
    /// measurement; ``depth_factor`` defaults to the camera preset's) or ``float32[H, W]``
    /// metres with ``depth_factor=None``; ``image``: ``uint8[H, W, 3]`` RGB colours the
    /// surface (``uint8[H, W]`` grey or ``None``: depth only, colour unchanged). Arrays must
    /// be C-contiguous. Returns the blocks the frame touched.
    #[pyo3(signature = (depth, depth_factor, world_from_camera, image = None))]
    fn integrate<'py>(
        &self,
        py: Python<'py>,
        depth: &Bound<'py, PyAny>,
        depth_factor: Option<f64>,
        world_from_camera: PyReadonlyArray2<'py, f64>,
        image: Option<&Bound<'py, PyAny>>,
    ) -> PyResult<usize> {
        let pose = pose_from_matrix(world_from_camera)?;
        if !pose.is_finite() {
            return Err(PyValueError::new_err("world_from_camera is not finite"));
        }
        let placeholder;
        let image = match image {
            Some(i) if !i.is_none() => i,
            _ => {
                let shape = depth
                    .cast::<PyUntypedArray>()
                    .map_err(|_| {
                        PyValueError::new_err(format!(
                            "depth must be a numpy array (uint16[H, W] or float32[H, W]), got {}",
                            depth.get_type()
                        ))
                    })?
                    .shape()
                    .to_vec();
                let [h, w] = shape[..] else {
                    return Err(PyValueError::new_err(format!(
                        "depth must be 2-D (H, W), got shape {shape:?}"
                    )));
                };
                placeholder = numpy::PyArray2::<u8>::zeros(py, [h, w], false).into_any();
                &placeholder
            }
        };
        let input = FrameIn::new(py, image, depth, depth_factor, self.camera.depth_factor)?;
        let buffers = input.buffers()?;
        let (map, inner) = (self.map.as_ref(), &self.inner);
        py.detach(|| -> PyResult<usize> {
            let frame = buffers.frame(0.0, map).map_err(value)?;
            let times = locked(inner)?.integrate(&frame, &pose).map_err(tsdf_err)?;
            Ok(times.active_blocks)
        })
    }

    /// What the volume shows from ``world_from_camera`` (``float64[4, 4]``) through
    /// ``camera`` (default: the volume's): a dict of ``depth`` (``float32[H, W]``, metres
    /// along the optical axis, 0 where no surface), ``normals`` (``float32[H, W, 3]``, unit,
    /// camera frame, facing the camera; 0 where no surface, or where a neighbouring voxel is
    /// unobserved) and ``colour``
    /// (``uint8[H, W, 3]`` RGB).
    #[pyo3(signature = (world_from_camera, camera = None))]
    fn ray_cast<'py>(
        &self,
        py: Python<'py>,
        world_from_camera: PyReadonlyArray2<'py, f64>,
        camera: Option<Camera>,
    ) -> PyResult<Bound<'py, PyDict>> {
        let pose = pose_from_matrix(world_from_camera)?;
        let cam = camera.unwrap_or_else(|| self.camera.clone()).undistorted();
        let inner = &self.inner;
        let r = py
            .detach(|| -> PyResult<_> { locked(inner)?.ray_cast(&cam, &pose).map_err(tsdf_err) })?;
        let (w, h) = (cam.width as usize, cam.height as usize);
        let depth = Array2::from_shape_vec((h, w), r.depth.data().to_vec()).map_err(value)?;
        let normals = Array3::from_shape_vec(
            (h, w, 3),
            r.normals.iter().flatten().copied().collect::<Vec<f32>>(),
        )
        .map_err(value)?;
        let colour = Array3::from_shape_vec(
            (h, w, 3),
            r.colours.iter().flatten().copied().collect::<Vec<u8>>(),
        )
        .map_err(value)?;
        let d = PyDict::new(py);
        d.set_item("depth", depth.into_pyarray(py))?;
        d.set_item("normals", normals.into_pyarray(py))?;
        d.set_item("colour", colour.into_pyarray(py))?;
        Ok(d)
    }

    /// The surface as a triangle mesh: ``(vertices, triangles, normals, colours)`` with
    /// vertices ``float32[N, 3]`` (metres, world frame), triangles ``uint32[M, 3]`` (vertex
    /// indices, counter-clockwise seen from the front), unit normals ``float32[N, 3]`` and
    /// colours ``uint8[N, 3]`` RGB.
    fn extract_mesh<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyTuple>> {
        let inner = &self.inner;
        let m = py.detach(|| -> PyResult<_> { locked(inner)?.extract_mesh().map_err(runtime) })?;
        fn rows<'py, T: Copy + numpy::Element, const K: usize>(
            py: Python<'py>,
            v: &[[T; K]],
        ) -> PyResult<Bound<'py, PyArray2<T>>> {
            let flat: Vec<T> = v.iter().flatten().copied().collect();
            Ok(Array2::from_shape_vec((v.len(), K), flat)
                .map_err(value)?
                .into_pyarray(py))
        }
        let out = (
            rows(py, &m.vertices)?,
            rows(py, &m.triangles)?,
            rows(py, &m.normals)?,
            rows(py, &m.colours)?,
        );
        out.into_pyobject(py)
    }

    /// The volume's parameters (``voxel_size``, ``min_depth``, ``max_depth`` in metres;
    /// ``rho_sigma`` in 1/m; ``trunc_min_voxels``; ``trunc_sigmas``; ``max_weight``).
    #[getter]
    fn params<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let p = *locked(&self.inner)?.params();
        crate::convert::to_python(py, &p)
    }

    /// Allocated blocks (8^3 voxels each).
    /// Where the blocks are: ``resident_blocks`` (device slots; every block on the CPU
    /// backend), ``host_blocks`` (paged out to host memory), ``peak_resident_blocks``,
    /// ``page_outs`` and ``page_ins`` (blocks moved so far).
    #[getter]
    fn paging<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, pyo3::types::PyDict>> {
        let st = locked(&self.inner)?.paging();
        let d = pyo3::types::PyDict::new(py);
        d.set_item("resident_blocks", st.resident_blocks)?;
        d.set_item("host_blocks", st.host_blocks)?;
        d.set_item("peak_resident_blocks", st.peak_resident_blocks)?;
        d.set_item("page_outs", st.page_outs)?;
        d.set_item("page_ins", st.page_ins)?;
        Ok(d)
    }

    #[getter]
    fn block_count(&self) -> PyResult<usize> {
        Ok(locked(&self.inner)?.block_count())
    }

    /// Frames integrated so far (saved with the volume).
    #[getter]
    fn frames(&self) -> PyResult<usize> {
        Ok(locked(&self.inner)?.frames())
    }

    /// The compute backend in use (adapter name or ``"cpu"``).
    #[getter]
    fn backend(&self) -> String {
        self.backend.clone()
    }

    /// The camera of the integrated frames.
    #[getter]
    fn camera(&self) -> Camera {
        self.camera.clone()
    }

    fn __repr__(&self) -> String {
        match locked(&self.inner) {
            Ok(v) => format!(
                "TsdfVolume(voxel={}, blocks={}, frames={}, backend={:?})",
                v.params().voxel_size,
                v.block_count(),
                v.frames(),
                self.backend
            ),
            Err(_) => "TsdfVolume(<poisoned>)".into(),
        }
    }
}
