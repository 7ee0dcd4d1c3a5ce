//! The camera and the frames that come in from numpy.

use numpy::ndarray::Array2;
use numpy::{
    IntoPyArray, PyArray2, PyArrayDescrMethods, PyArrayDyn, PyArrayMethods, PyReadonlyArrayDyn,
    PyUntypedArray, PyUntypedArrayMethods,
};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use rgbid::camera::{BrownConrady, PinholeCamera};
use rgbid::image::{DepthBuffer, ImageBuffer, ImageError, RgbdFrame};
use rgbid::io::{CameraConfig, UndistortMap};

use crate::convert::value;

/// A pinhole camera: focal lengths ``fx``, ``fy`` and principal point ``cx``, ``cy`` in pixels
/// (integer pixel coordinates are pixel centres, so TUM's ``cx = 319.5`` means the image
/// centre), image size ``width`` x ``height`` in pixels, and optional Brown-Conrady
/// ``distortion`` ``(k1, k2, p1, p2, k3)`` (OpenCV order). Frames of a camera with distortion
/// are undistorted before tracking (intensity bilinear, depth nearest). ``readout``: the
/// rolling shutter's readout time in seconds, first row to last (0 for a global shutter; the
/// odometry rectifies the intensity for it).
#[pyclass(frozen, from_py_object, module = "rgbid")]
#[derive(Clone)]
pub struct Camera {
    pub(crate) camera: PinholeCamera,
    /// Depth units per metre of the preset or calibration file this camera came from.
    pub(crate) depth_factor: Option<f64>,
}

impl Camera {
    pub(crate) fn new_checked(camera: PinholeCamera, depth_factor: Option<f64>) -> PyResult<Self> {
        camera.validate().map_err(value)?;
        Ok(Self {
            camera,
            depth_factor,
        })
    }

    /// The camera the systems see: without distortion (frames are undistorted first).
    pub(crate) fn undistorted(&self) -> PinholeCamera {
        let mut c = self.camera;
        c.distortion = BrownConrady::default();
        c
    }

    /// The undistortion map, when the camera has distortion.
    pub(crate) fn undistort_map(&self) -> Option<UndistortMap> {
        (!self.camera.distortion.is_zero()).then(|| UndistortMap::new(&self.camera))
    }
}

#[pymethods]
impl Camera {
    #[new]
    #[pyo3(signature = (fx, fy, cx, cy, width, height, distortion = None, readout = 0.0))]
    #[allow(clippy::too_many_arguments)]
    fn py_new(
        fx: f64,
        fy: f64,
        cx: f64,
        cy: f64,
        width: u32,
        height: u32,
        distortion: Option<[f64; 5]>,
        readout: f64,
    ) -> PyResult<Self> {
        let mut camera = PinholeCamera::new(fx, fy, cx, cy, width, height);
        camera.readout = readout;
        if let Some([k1, k2, p1, p2, k3]) = distortion {
            camera.distortion = BrownConrady { k1, k2, p1, p2, k3 };
        }
        Self::new_checked(camera, None)
    }

    /// A named camera: ``tum_fr1``, ``tum_fr2``, ``tum_fr3`` (TUM RGB-D, 640x480) or
    /// ``default`` (Kinect-like, 640x480), or a camera file (``calib.txt`` or a TOML / JSON
    /// camera config). ``depth_factor`` is the preset's depth units per metre.
    #[staticmethod]
    fn preset(name: &str) -> PyResult<Self> {
        let c = CameraConfig::from_name_or_path(name).map_err(value)?;
        Self::new_checked(c.camera, Some(c.depth_factor))
    }

    /// Focal length along x, pixels.
    #[getter]
    fn fx(&self) -> f64 {
        self.camera.fx
    }
    /// Focal length along y, pixels.
    #[getter]
    fn fy(&self) -> f64 {
        self.camera.fy
    }
    /// Principal point x, pixels (pixel centres at integers).
    #[getter]
    fn cx(&self) -> f64 {
        self.camera.cx
    }
    /// Principal point y, pixels.
    #[getter]
    fn cy(&self) -> f64 {
        self.camera.cy
    }
    /// Image width, pixels.
    #[getter]
    fn width(&self) -> u32 {
        self.camera.width
    }
    /// Image height, pixels.
    #[getter]
    fn height(&self) -> u32 {
        self.camera.height
    }
    /// ``(k1, k2, p1, p2, k3)``, zeros for none.
    #[getter]
    fn distortion(&self) -> (f64, f64, f64, f64, f64) {
        let d = self.camera.distortion;
        (d.k1, d.k2, d.p1, d.p2, d.k3)
    }
    /// Rolling-shutter readout, seconds from the first row to the last (0: global shutter).
    #[getter]
    fn readout(&self) -> f64 {
        self.camera.readout
    }
    /// Depth units per metre of the preset or file (``None`` for a camera built from numbers).
    #[getter]
    fn depth_factor(&self) -> Option<f64> {
        self.depth_factor
    }
    /// The intrinsic matrix ``K`` as ``float64[3, 3]``.
    #[getter]
    fn matrix<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray2<f64>> {
        let c = &self.camera;
        let mut k = Array2::<f64>::zeros((3, 3));
        k[[0, 0]] = c.fx;
        k[[1, 1]] = c.fy;
        k[[0, 2]] = c.cx;
        k[[1, 2]] = c.cy;
        k[[2, 2]] = 1.0;
        k.into_pyarray(py)
    }

    fn __repr__(&self) -> String {
        let c = &self.camera;
        format!(
            "Camera(fx={}, fy={}, cx={}, cy={}, width={}, height={}, distortion={:?})",
            c.fx,
            c.fy,
            c.cx,
            c.cy,
            c.width,
            c.height,
            self.distortion()
        )
    }
}

/// A numpy array checked for dtype `T`, C order and the number of dimensions.
fn checked<'py, T: numpy::Element>(
    py: Python<'py>,
    a: &Bound<'py, PyAny>,
    what: &str,
    want: &str,
) -> PyResult<PyReadonlyArrayDyn<'py, T>> {
    let untyped = a.cast::<PyUntypedArray>().map_err(|_| {
        PyValueError::new_err(format!(
            "{what} must be a numpy array ({want}), got {}",
            a.get_type()
        ))
    })?;
    let dtype = untyped.dtype();
    if !dtype.is_equiv_to(&numpy::dtype::<T>(py)) {
        return Err(PyValueError::new_err(format!(
            "{what} must be {want}, got dtype {dtype} (convert with .astype)"
        )));
    }
    if !untyped.is_c_contiguous() {
        return Err(PyValueError::new_err(format!(
            "{what} must be C-contiguous (a slice or transpose is not; use np.ascontiguousarray)"
        )));
    }
    Ok(a.cast::<PyArrayDyn<T>>()?.readonly())
}

/// The depth of a frame as it came in.
pub(crate) enum DepthIn<'py> {
    /// Raw 16-bit values with units per metre.
    U16(PyReadonlyArrayDyn<'py, u16>, f64),
    /// Metres.
    Metres(PyReadonlyArrayDyn<'py, f32>),
}

/// One frame's arrays, checked and borrowed (not copied).
pub(crate) struct FrameIn<'py> {
    image: PyReadonlyArrayDyn<'py, u8>,
    depth: DepthIn<'py>,
    width: usize,
    height: usize,
}

impl<'py> FrameIn<'py> {
    /// Checks `image` (``uint8[H, W]`` grey or ``uint8[H, W, 3]`` RGB) and `depth`
    /// (``uint16[H, W]`` with `depth_factor`, else `fallback_factor`, units per metre; or
    /// ``float32[H, W]`` metres with no factor).
    pub(crate) fn new(
        py: Python<'py>,
        image: &Bound<'py, PyAny>,
        depth: &Bound<'py, PyAny>,
        depth_factor: Option<f64>,
        fallback_factor: Option<f64>,
    ) -> PyResult<Self> {
        let image = checked::<u8>(py, image, "image", "uint8[H, W] or uint8[H, W, 3] RGB")?;
        let (height, width) = match image.shape() {
            [h, w] => (*h, *w),
            [h, w, 3] => (*h, *w),
            other => {
                return Err(PyValueError::new_err(format!(
                    "image must be uint8[H, W] (grey) or uint8[H, W, 3] (RGB), got shape {other:?}"
                )))
            }
        };
        let is_f32 = depth
            .cast::<PyUntypedArray>()
            .is_ok_and(|a| a.dtype().is_equiv_to(&numpy::dtype::<f32>(py)));
        let depth = if is_f32 {
            if depth_factor.is_some() {
                return Err(PyValueError::new_err(
                    "float32 depth is in metres: give depth_factor=None",
                ));
            }
            DepthIn::Metres(checked::<f32>(py, depth, "depth", "uint16[H, W]")?)
        } else {
            let factor = depth_factor.or(fallback_factor).ok_or_else(|| {
                PyValueError::new_err(
                    "uint16 depth needs depth_factor (units per metre; TUM: 5000, millimetres: 1000)",
                )
            })?;
            DepthIn::U16(
                checked::<u16>(py, depth, "depth", "uint16[H, W] (or float32 metres)")?,
                factor,
            )
        };
        let depth_shape = match &depth {
            DepthIn::U16(a, _) => a.shape().to_vec(),
            DepthIn::Metres(a) => a.shape().to_vec(),
        };
        if depth_shape != [height, width] {
            return Err(PyValueError::new_err(format!(
                "depth has shape {depth_shape:?} but the image is {height}x{width} (H x W)"
            )));
        }
        Ok(Self {
            image,
            depth,
            width,
            height,
        })
    }

    /// The borrowed buffers, to be used without the interpreter lock.
    pub(crate) fn buffers(&self) -> PyResult<Buffers<'_>> {
        let img = self.image.as_slice().map_err(value)?;
        let image = if self.image.ndim() == 3 {
            ImageBuffer::Rgb(img)
        } else {
            ImageBuffer::Gray(img)
        };
        let depth = match &self.depth {
            DepthIn::U16(a, factor) => DepthBuffer::U16 {
                data: a.as_slice().map_err(value)?,
                factor: *factor,
            },
            DepthIn::Metres(a) => DepthBuffer::Metres(a.as_slice().map_err(value)?),
        };
        Ok(Buffers {
            image,
            depth,
            width: self.width,
            height: self.height,
        })
    }
}

/// Borrowed frame buffers (`Send`: plain slices).
#[derive(Clone, Copy)]
pub(crate) struct Buffers<'a> {
    image: ImageBuffer<'a>,
    depth: DepthBuffer<'a>,
    width: usize,
    height: usize,
}

impl Buffers<'_> {
    /// The frame, undistorted by `map` when there is one. The colour is kept only without
    /// distortion (undistortion works on intensity and inverse depth).
    pub(crate) fn frame(
        &self,
        timestamp: f64,
        map: Option<&UndistortMap>,
    ) -> Result<RgbdFrame, ImageError> {
        let frame =
            RgbdFrame::from_buffers(timestamp, self.width, self.height, self.image, self.depth)?;
        let Some(map) = map else {
            return Ok(frame);
        };
        match (
            map.intensity(frame.intensity()),
            map.inverse_depth(frame.inverse_depth()),
        ) {
            (Some(i), Some(d)) => RgbdFrame::new(timestamp, i, d),
            // The map was built for the camera, whose size the systems check the frame against.
            _ => Ok(frame),
        }
    }
}
