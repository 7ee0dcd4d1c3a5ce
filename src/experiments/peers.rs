//! Runners for the peer implementations the benchmarks compare against (OpenCV and Open3D
//! odometry, GTSAM pose graphs), through the Python scripts in `../shared/eval/`. Each script
//! prints one JSON object per line; lines that are not JSON (progress, warnings) are skipped.

use std::path::{Path, PathBuf};
use std::process::Command;

/// Errors of the peer runners.
#[derive(Debug, thiserror::Error)]
pub enum PeerError {
    /// The peer script does not exist.
    #[error("{0}: peer script not found")]
    MissingScript(PathBuf),
    /// The Python interpreter could not be started.
    #[error("starting {python} {script}: {source}")]
    Start {
        /// The interpreter.
        python: String,
        /// The script.
        script: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
    /// The script exited with an error.
    #[error("{script} failed on {input}: {message}")]
    Failed {
        /// The script.
        script: PathBuf,
        /// What it was run on.
        input: PathBuf,
        /// The last line of its standard error.
        message: String,
    },
}

/// One odometry peer's run over a sequence, as its script reports it.
#[derive(Clone, Debug, PartialEq)]
pub struct OdometryPeerRun {
    /// The method's name (e.g. `cv_rgbd`).
    pub method: String,
    /// Frames processed.
    pub frames: usize,
    /// Median and 90th-percentile time per frame, milliseconds.
    pub ms_median: f64,
    /// 90th-percentile time per frame, milliseconds.
    pub ms_p90: f64,
    /// ATE RMSE (metres) as the script computed it, if it did.
    pub ate_rmse_m: Option<f64>,
    /// Translational RPE (m/s) as the script computed it, if it did.
    pub rpe_m_per_s: Option<f64>,
    /// The trajectory the script wrote (TUM format, `world_from_camera`).
    pub trajectory: PathBuf,
}

/// Options of [`run_odometry_peers`].
#[derive(Clone, Debug)]
pub struct OdometryPeerOptions<'a> {
    /// The Python interpreter (with numpy, scipy and the peers' packages).
    pub python: &'a str,
    /// The peer script (`../shared/eval/peer_odometry.py`).
    pub script: &'a Path,
    /// Comma-separated peer methods (`cv_rgbd,o3d_hybrid`, ...).
    pub methods: &'a str,
    /// Only the first N frames.
    pub max_frames: Option<usize>,
}

/// Runs the odometry peers on the TUM folder `sequence`; their trajectories go to `out_dir`.
pub fn run_odometry_peers(
    opts: &OdometryPeerOptions<'_>,
    sequence: &Path,
    out_dir: &Path,
) -> Result<Vec<OdometryPeerRun>, PeerError> {
    let mut cmd = Command::new(opts.python);
    cmd.arg(opts.script)
        .arg(sequence)
        .arg(out_dir)
        .arg("--methods")
        .arg(opts.methods);
    if let Some(n) = opts.max_frames {
        cmd.arg("--max-frames").arg(n.to_string());
    }
    log::info!("running peers: {cmd:?}");
    let lines = run_json_lines(cmd, opts.python, opts.script, sequence)?;
    Ok(lines
        .iter()
        .map(|v| {
            let method = v["method"].as_str().unwrap_or("?").to_string();
            OdometryPeerRun {
                trajectory: out_dir.join(format!("{method}.txt")),
                method,
                frames: v["frames"].as_u64().unwrap_or(0) as usize,
                ms_median: v["ms_median"].as_f64().unwrap_or(f64::NAN),
                ms_p90: v["ms_p90"].as_f64().unwrap_or(f64::NAN),
                ate_rmse_m: v["ate_rmse"].as_f64(),
                rpe_m_per_s: v["rpe_rmse_per_s"].as_f64(),
            }
        })
        .collect())
}

/// One GTSAM run on a pose-graph file.
#[derive(Clone, Debug, PartialEq)]
pub struct GraphPeerRun {
    /// The optimiser (e.g. `gtsam_lm`).
    pub method: String,
    /// Wall time, seconds.
    pub seconds: f64,
    /// Final chi2 (g2o's cost).
    pub chi2: f64,
    /// Final SE-Sync objective `F`.
    pub sesync_objective: f64,
}

/// Runs the pose-graph peer script (`../shared/eval/peer_posegraph.py`) on one g2o/iSAM file;
/// one entry per successful run.
pub fn run_graph_peer(
    python: &str,
    script: &Path,
    file: &Path,
) -> Result<Vec<GraphPeerRun>, PeerError> {
    let mut cmd = Command::new(python);
    cmd.arg(script).arg(file);
    let lines = run_json_lines(cmd, python, script, file)?;
    Ok(lines
        .iter()
        .filter_map(|v| {
            Some(GraphPeerRun {
                method: v["method"].as_str()?.to_string(),
                seconds: v["s"].as_f64()?,
                chi2: v["chi2"].as_f64()?,
                sesync_objective: v["F"].as_f64()?,
            })
        })
        .collect())
}

/// Runs `cmd` and returns the JSON objects of its standard output, one per line.
fn run_json_lines(
    mut cmd: Command,
    python: &str,
    script: &Path,
    input: &Path,
) -> Result<Vec<serde_json::Value>, PeerError> {
    if !script.exists() {
        return Err(PeerError::MissingScript(script.to_path_buf()));
    }
    let out = cmd.output().map_err(|source| PeerError::Start {
        python: python.to_string(),
        script: script.to_path_buf(),
        source,
    })?;
    if !out.status.success() {
        return Err(PeerError::Failed {
            script: script.to_path_buf(),
            input: input.to_path_buf(),
            message: String::from_utf8_lossy(&out.stderr)
                .lines()
                .last()
                .unwrap_or("")
                .to_string(),
        });
    }
    Ok(String::from_utf8_lossy(&out.stdout)
        .lines()
        .filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok())
        .filter(|v| v.is_object())
        .collect())
}
