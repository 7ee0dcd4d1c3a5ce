//! Conversions between the library's types and Python's: errors, poses, trajectories,
//! configuration dicts, JSON-shaped results.

use glam::{DMat3, DQuat, DVec3};
use numpy::ndarray::Array2;
use numpy::{IntoPyArray, PyArray2, PyArrayMethods, PyReadonlyArray2, PyUntypedArrayMethods};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use rgbid::geometry::Se3;
use rgbid::gpu::{select_backend, BackendChoice, ComputeBackend};
use rgbid::trajectory::TimedPose;
use serde::de::DeserializeOwned;
use serde::Serialize;

use crate::RgbidError;

/// The error and its causes, `outer: inner: innermost`.
pub(crate) fn chain(e: &dyn std::error::Error) -> String {
    let mut s = e.to_string();
    let mut source = e.source();
    while let Some(inner) = source {
        let t = inner.to_string();
        // `#[error(transparent)]` and `{0}` wrappers repeat their source's text.
        if !s.ends_with(&t) {
            s.push_str(": ");
            s.push_str(&t);
        }
        source = inner.source();
    }
    s
}

/// A library failure as `rgbid.RgbidError`.
pub(crate) fn runtime(e: impl std::error::Error) -> PyErr {
    RgbidError::new_err(chain(&e))
}

/// Bad input as `ValueError`.
pub(crate) fn value(e: impl std::error::Error) -> PyErr {
    PyValueError::new_err(chain(&e))
}

/// `world_from_camera` as a `float64[4, 4]` homogeneous matrix.
pub(crate) fn pose_matrix<'py>(py: Python<'py>, pose: &Se3) -> Bound<'py, PyArray2<f64>> {
    let r = DMat3::from_quat(pose.rotation);
    let t = pose.translation;
    let mut m = Array2::<f64>::zeros((4, 4));
    for row in 0..3 {
        for col in 0..3 {
            m[[row, col]] = r.col(col)[row];
        }
    }
    m[[0, 3]] = t.x;
    m[[1, 3]] = t.y;
    m[[2, 3]] = t.z;
    m[[3, 3]] = 1.0;
    m.into_pyarray(py)
}

/// A `float64[4, 4]` rigid transform as `Se3`; the rotation block must be orthonormal with
/// determinant +1 (within 1e-6) and the last row `0 0 0 1`.
pub(crate) fn pose_from_matrix(m: PyReadonlyArray2<'_, f64>) -> PyResult<Se3> {
    if m.shape() != [4, 4] {
        return Err(PyValueError::new_err(format!(
            "a pose must be float64[4, 4], got shape {:?}",
            m.shape()
        )));
    }
    let a = m.as_array();
    let col = |c: usize| DVec3::new(a[[0, c]], a[[1, c]], a[[2, c]]);
    let r = DMat3::from_cols(col(0), col(1), col(2));
    let err = (r.transpose() * r - DMat3::IDENTITY)
        .to_cols_array()
        .iter()
        .fold(0.0f64, |acc, v| acc.max(v.abs()));
    let bottom = [a[[3, 0]], a[[3, 1]], a[[3, 2]], a[[3, 3]]];
    if !(err < 1e-6) || !((r.determinant() - 1.0).abs() < 1e-6) || bottom != [0.0, 0.0, 0.0, 1.0] {
        return Err(PyValueError::new_err(
            "a pose must be a rigid transform: orthonormal rotation (det +1) and last row 0 0 0 1",
        ));
    }
    Ok(Se3 {
        rotation: DQuat::from_mat3(&r).normalize(),
        translation: col(3),
    })
}

/// Poses as `float64[N, 8]` in TUM column order `t tx ty tz qx qy qz qw`.
pub(crate) fn trajectory_array<'py>(
    py: Python<'py>,
    poses: &[TimedPose],
) -> Bound<'py, PyArray2<f64>> {
    let mut m = Array2::<f64>::zeros((poses.len(), 8));
    for (i, p) in poses.iter().enumerate() {
        let (t, q) = (
            p.world_from_camera.translation,
            p.world_from_camera.rotation,
        );
        let row = [p.timestamp, t.x, t.y, t.z, q.x, q.y, q.z, q.w];
        for (k, v) in row.into_iter().enumerate() {
            m[[i, k]] = v;
        }
    }
    m.into_pyarray(py)
}

/// A `float64[N, 8]` TUM array (`t tx ty tz qx qy qz qw`) as poses; quaternions are
/// normalised, non-finite values and zero quaternions are rejected.
pub(crate) fn trajectory_from_array(a: &Bound<'_, PyAny>, what: &str) -> PyResult<Vec<TimedPose>> {
    let arr = a.cast::<PyArray2<f64>>().map_err(|_| {
        PyValueError::new_err(format!("{what} must be a float64[N, 8] numpy array"))
    })?;
    let ro = arr.readonly();
    if ro.shape()[1] != 8 {
        return Err(PyValueError::new_err(format!(
            "{what} must be float64[N, 8] (t tx ty tz qx qy qz qw), got shape {:?}",
            ro.shape()
        )));
    }
    let v = ro.as_array();
    let mut out = Vec::with_capacity(v.nrows());
    for (i, r) in v.rows().into_iter().enumerate() {
        if r.iter().any(|x| !x.is_finite()) {
            return Err(PyValueError::new_err(format!(
                "{what}: row {i} has a non-finite value"
            )));
        }
        let q = DQuat::from_xyzw(r[4], r[5], r[6], r[7]);
        if !(q.length() > 1e-12) {
            return Err(PyValueError::new_err(format!(
                "{what}: row {i} has a zero quaternion"
            )));
        }
        out.push(TimedPose {
            timestamp: r[0],
            world_from_camera: Se3 {
                rotation: q.normalize(),
                translation: DVec3::new(r[1], r[2], r[3]),
            },
        });
    }
    Ok(out)
}

/// `value` as Python objects (dicts, lists, floats...) through the `json` module.
pub(crate) fn to_python<'py, T: Serialize>(py: Python<'py>, v: &T) -> PyResult<Bound<'py, PyAny>> {
    let text = serde_json::to_string(v).map_err(runtime)?;
    py.import("json")?.call_method1("loads", (text,))
}

/// The configuration `T`: its defaults with the keys of `config` put over them. `config` is
/// `None`, a dict with the keys of the TOML files (any subset; an unknown key is an error that
/// names it), or a path to a TOML / JSON file.
pub(crate) fn config_from<T: Serialize + DeserializeOwned + Default>(
    py: Python<'_>,
    config: Option<&Bound<'_, PyAny>>,
) -> PyResult<T> {
    use rgbid::io::settings;
    let base = T::default();
    let Some(c) = config else {
        return Ok(base);
    };
    if c.is_none() {
        return Ok(base);
    }
    if c.cast::<pyo3::types::PyDict>().is_ok() {
        let text: String = py
            .import("json")?
            .call_method1("dumps", (c,))
            .map_err(|e| {
                PyValueError::new_err(format!("the configuration dict is not JSON-shaped: {e}"))
            })?
            .extract()?;
        let overlay: serde_json::Value = serde_json::from_str(&text).map_err(value)?;
        let mut tree = settings::to_tree(&base).map_err(value)?;
        settings::merge(&mut tree, overlay);
        return settings::from_tree(tree, "the configuration dict").map_err(value);
    }
    let path: std::path::PathBuf = c.extract().map_err(|_| {
        PyValueError::new_err("config must be None, a dict, or a path to a TOML / JSON file")
    })?;
    settings::load_file(&base, &path).map_err(value)
}

/// `"auto"`, `"gpu"` or `"cpu"` as a compute backend (see `rgbid odometry --help`).
pub(crate) fn backend_from(name: &str) -> PyResult<ComputeBackend> {
    let choice = match name {
        "auto" => BackendChoice::Auto,
        "gpu" => BackendChoice::Gpu,
        "cpu" => BackendChoice::Cpu,
        other => {
            return Err(PyValueError::new_err(format!(
                "backend must be 'auto', 'gpu' or 'cpu', got '{other}'"
            )))
        }
    };
    select_backend(choice, None).map_err(runtime)
}
