//! Trajectory files, evaluation, pose graphs, run folders, configuration defaults.

use std::path::PathBuf;

use numpy::ndarray::Array2;
use numpy::{IntoPyArray, PyArray2};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use pyo3::types::PyDict;
use rgbid::eval::{evaluate as eval_metrics, EvalOptions, RpeDelta};
use rgbid::graph::g2o::{read_g2o, LoadedGraph};
use rgbid::graph::isam::read_isam;
use rgbid::graph::{initialize_2d, initialize_3d, EdgeCost, InitMethod, SolverOptions};
use rgbid::io::run_folder::RunFolder;
use rgbid::io::trajectory::{read_tum, write_tum};
use rgbid::odometry::OdometryConfig;
use rgbid::slam::SlamConfig;

use crate::convert::{runtime, to_python, trajectory_array, trajectory_from_array, value};

/// Reads a TUM trajectory file (``t tx ty tz qx qy qz qw`` per line, ``world_from_camera``)
/// as ``float64[N, 8]``.
#[pyfunction]
pub fn read_trajectory(py: Python<'_>, path: PathBuf) -> PyResult<Bound<'_, PyArray2<f64>>> {
    let poses = py.detach(|| read_tum(&path)).map_err(runtime)?;
    Ok(trajectory_array(py, &poses))
}

/// Writes ``float64[N, 8]`` (TUM columns) to a TUM trajectory file.
#[pyfunction]
pub fn write_trajectory(
    py: Python<'_>,
    path: PathBuf,
    trajectory: &Bound<'_, PyAny>,
) -> PyResult<()> {
    let poses = trajectory_from_array(trajectory, "trajectory")?;
    py.detach(|| write_tum(&path, &poses)).map_err(runtime)
}

/// ATE and RPE (TUM definitions) of ``est`` against ``gt`` (both ``float64[N, 8]``): poses
/// matched by time within ``max_diff`` seconds, RPE over ``delta`` seconds, similarity
/// alignment with ``scale``. Returns the metrics as nested dicts (what ``rgbid eval --json``
/// prints).
#[pyfunction]
#[pyo3(signature = (gt, est, delta = 1.0, max_diff = 0.02, scale = false))]
pub fn evaluate<'py>(
    py: Python<'py>,
    gt: &Bound<'py, PyAny>,
    est: &Bound<'py, PyAny>,
    delta: f64,
    max_diff: f64,
    scale: bool,
) -> PyResult<Bound<'py, PyAny>> {
    if !(delta > 0.0 && delta.is_finite() && max_diff >= 0.0 && max_diff.is_finite()) {
        return Err(PyValueError::new_err(
            "delta must be > 0 seconds and max_diff >= 0 seconds",
        ));
    }
    let gt = trajectory_from_array(gt, "gt")?;
    let est = trajectory_from_array(est, "est")?;
    let opts = EvalOptions {
        max_time_difference: max_diff,
        delta: RpeDelta::Seconds(delta),
        with_scale: scale,
    };
    let m = py
        .detach(|| eval_metrics(&gt, &est, &opts))
        .map_err(value)?;
    to_python(py, &m)
}

/// Optimises the pose graph in ``path`` (g2o ``.g2o``, else iSAM text) the way ``rgbid graph
/// optimize`` does by default (SE(2) / SE(3) parametrisation, chordal / linear
/// initialisation, Levenberg-Marquardt). ``cost``: ``"geodesic"`` (whitened by the full
/// information, what chi2 is) or ``"sesync"`` (chordal). Returns ``(poses, summary)``:
/// ``poses`` ``float64[N, 3]`` (``x y theta``) for 2D graphs or ``float64[N, 7]`` (``tx ty tz
/// qx qy qz qw``) for 3D ones, in the file's vertex order; ``summary`` a dict with
/// ``initial_cost``, ``final_cost``, ``iterations``, ``time_s`` (solver),
/// ``init_time_s``, ``termination``, ``chi2``.
#[pyfunction]
#[pyo3(signature = (path, cost = "geodesic", max_iterations = None))]
pub fn graph_optimize<'py>(
    py: Python<'py>,
    path: PathBuf,
    cost: &str,
    max_iterations: Option<usize>,
) -> PyResult<(Bound<'py, PyArray2<f64>>, Bound<'py, PyDict>)> {
    let cost = match cost {
        "geodesic" => EdgeCost::Geodesic,
        "sesync" => EdgeCost::Chordal,
        other => {
            return Err(PyValueError::new_err(format!(
                "cost must be 'geodesic' or 'sesync', got '{other}'"
            )))
        }
    };
    let mut opts = SolverOptions {
        // With the chordal / linear initialisation the start is close: little damping.
        initial_lambda: 1e-9,
        ..Default::default()
    };
    if let Some(n) = max_iterations {
        opts.max_iterations = n;
    }
    let (poses, report, init_s, chi2) = py.detach(|| -> PyResult<_> {
        let file = if path.extension().is_some_and(|e| e == "g2o") {
            read_g2o(&path).map_err(runtime)?
        } else {
            read_isam(&path).map_err(runtime)?
        };
        let t = std::time::Instant::now();
        Ok(match file.graph {
            LoadedGraph::Se2(mut g) => {
                initialize_2d(&mut g, InitMethod::Auto).map_err(runtime)?;
                let init_s = t.elapsed().as_secs_f64();
                let report = g.optimize_with(&opts, cost).map_err(runtime)?;
                let mut m = Array2::<f64>::zeros((g.poses.len(), 3));
                for (i, p) in g.poses.iter().enumerate() {
                    m[[i, 0]] = p.x;
                    m[[i, 1]] = p.y;
                    m[[i, 2]] = p.theta;
                }
                (m, report, init_s, g.chi2())
            }
            LoadedGraph::Se3(mut g) => {
                initialize_3d(&mut g, InitMethod::Auto).map_err(runtime)?;
                let init_s = t.elapsed().as_secs_f64();
                let report = g.optimize_with(&opts, cost).map_err(runtime)?;
                let mut m = Array2::<f64>::zeros((g.poses.len(), 7));
                for (i, p) in g.poses.iter().enumerate() {
                    let (t, q) = (p.translation, p.rotation);
                    for (k, v) in [t.x, t.y, t.z, q.x, q.y, q.z, q.w].into_iter().enumerate() {
                        m[[i, k]] = v;
                    }
                }
                (m, report, init_s, g.chi2())
            }
        })
    })?;
    let summary = PyDict::new(py);
    summary.set_item("initial_cost", report.initial_cost)?;
    summary.set_item("final_cost", report.final_cost)?;
    summary.set_item("iterations", report.iterations)?;
    summary.set_item("time_s", report.seconds)?;
    summary.set_item("init_time_s", init_s)?;
    summary.set_item("termination", format!("{:?}", report.termination))?;
    summary.set_item("chi2", chi2)?;
    Ok((poses.into_pyarray(py), summary))
}

/// Reads a finished ``rgbid slam`` run folder. Returns a dict: ``trajectory``, ``odometry``,
/// ``keyframes``, ``groundtruth`` (``float64[N, 8]`` or ``None``), ``frames``, ``loops``,
/// ``keyframe_timings`` (lists of dicts with the CSV columns), ``summary`` (dict or
/// ``None``), ``points`` (``float64[N, 3]``, metres) and ``intensity`` (``uint8[N]``) of the
/// model, ``complete`` (whether the run finished).
#[pyfunction]
pub fn read_run(py: Python<'_>, folder: PathBuf) -> PyResult<Bound<'_, PyDict>> {
    let run = py.detach(|| RunFolder::read(&folder)).map_err(runtime)?;
    let d = PyDict::new(py);
    d.set_item("trajectory", trajectory_array(py, &run.trajectory))?;
    d.set_item("odometry", trajectory_array(py, &run.odometry))?;
    d.set_item("keyframes", trajectory_array(py, &run.keyframes))?;
    d.set_item(
        "groundtruth",
        run.groundtruth.as_ref().map(|g| trajectory_array(py, g)),
    )?;
    d.set_item("frames", to_python(py, &run.frames)?)?;
    d.set_item("loops", to_python(py, &run.loops)?)?;
    d.set_item("keyframe_timings", to_python(py, &run.keyframe_timings)?)?;
    d.set_item("summary", to_python(py, &run.summary)?)?;
    let mut points = Array2::<f64>::zeros((run.model.len(), 3));
    for (i, (p, _)) in run.model.iter().enumerate() {
        points[[i, 0]] = p.x;
        points[[i, 1]] = p.y;
        points[[i, 2]] = p.z;
    }
    let intensity: Vec<u8> = run.model.iter().map(|(_, g)| *g).collect();
    d.set_item("points", points.into_pyarray(py))?;
    d.set_item("intensity", intensity.into_pyarray(py))?;
    d.set_item("complete", run.complete())?;
    Ok(d)
}

/// Every key of the configuration of ``command`` (``"odometry"`` or ``"slam"``) with its
/// default, as a dict (what ``rgbid config dump --command NAME`` prints as TOML).
#[pyfunction]
pub fn default_config<'py>(py: Python<'py>, command: &str) -> PyResult<Bound<'py, PyAny>> {
    match command {
        "odometry" => to_python(py, &OdometryConfig::default()),
        "slam" => to_python(py, &SlamConfig::default()),
        other => Err(PyValueError::new_err(format!(
            "command must be 'odometry' or 'slam', got '{other}'"
        ))),
    }
}
