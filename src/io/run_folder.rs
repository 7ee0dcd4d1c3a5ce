//! The run folder of a SLAM run (what `rgbid slam --out DIR` writes and `rgbid-viewer --output
//! DIR` reads), written and read here only:
//!
//! | file | content | written |
//! |---|---|---|
//! | `summary.json` | [`RunSummary`]: format version, status, counts, accuracy, plus free keys | at creation (`status: running`), at each [`RunFolderWriter::checkpoint`], by [`RunFolderWriter::finish`] / [`RunFolderWriter::end`] |
//! | `timing.csv` | one [`FrameRow`] per frame | a row per frame, flushed |
//! | `odometry.txt` | front-end pose of every tracked frame (TUM) | a line per frame, flushed |
//! | `loops.csv` | one [`LoopRow`] per checked loop or relocalisation | a row per loop, flushed |
//! | `keyframe_timing.csv` | one [`KeyframeTimingRow`] per new keyframe | rows as given, flushed |
//! | `trajectory.txt` | optimised pose of every frame (TUM) | at checkpoints (the estimate so far) and at the end |
//! | `keyframes.txt` | optimised keyframe poses (TUM) | at checkpoints and at the end |
//! | `groundtruth.txt` | ground truth (TUM), when the source has it | at the end |
//! | `model.ply` | voxel-filtered model (see [`super::ply`]) | at the end |
//! | `mesh.ply` | TSDF mesh of the keyframes (`rgbid slam --mesh`) | at the end, by the caller |
//! | `volume.tsdf` | the TSDF volume of that mesh (`TsdfVolume::save` of the tsdf module) | at the end, by the caller |
//!
//! Rows are written as they come and flushed, so an interrupted run leaves a readable folder
//! with the frames processed so far; whole files are replaced atomically (a temporary file
//! renamed over them), so a file is the previous version or the new one, never half of one.
//! While a writer is open the folder holds a lock file (`.rgbid-lock`, with the process id):
//! a second writer on the same folder is refused. CSV files have a header line and are read by column
//! name: columns may come in any order, unknown columns are ignored, and the optional ones
//! (the odometry diagnostics, added after the first version) may be missing. This module only
//! knows plain rows; the SLAM system and the CLI convert their records into them.
//!
//! ```no_run
//! # use rgbid::io::run_folder::*;
//! # fn f() -> Result<(), rgbid::io::IoError> {
//! let mut w = RunFolderWriter::create(std::path::Path::new("slam-out"))?;
//! w.frame(&FrameRow { index: 0, status: "NewKeyframe".into(), ..Default::default() })?;
//! w.finish(RunSummary { frames: 1, ..Default::default() })?;
//! let run = RunFolder::read(std::path::Path::new("slam-out"))?;
//! assert_eq!(run.frames.len(), 1);
//! # Ok(()) }
//! ```

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use glam::DVec3;
use serde::{Deserialize, Serialize};

use super::IoError;
use crate::trajectory::{format_tum_line, TimedPose};

/// Version of the run-folder format written by this build. 1: the first versioned format
/// (`summary.json` has `format_version`; folders without it are read as version 0, whose
/// files have the same columns).
pub const FORMAT_VERSION: u32 = 1;

/// File names inside a run folder.
pub mod files {
    /// Summary (JSON).
    pub const SUMMARY: &str = "summary.json";
    /// Per-frame statistics (CSV).
    pub const TIMING: &str = "timing.csv";
    /// Loop and relocalisation checks (CSV).
    pub const LOOPS: &str = "loops.csv";
    /// Back-end time per keyframe (CSV).
    pub const KEYFRAME_TIMING: &str = "keyframe_timing.csv";
    /// Front-end trajectory (TUM).
    pub const ODOMETRY: &str = "odometry.txt";
    /// Optimised trajectory of every frame (TUM).
    pub const TRAJECTORY: &str = "trajectory.txt";
    /// Optimised keyframe poses (TUM).
    pub const KEYFRAMES: &str = "keyframes.txt";
    /// Ground truth (TUM).
    pub const GROUNDTRUTH: &str = "groundtruth.txt";
    /// Model point cloud (PLY).
    pub const MODEL: &str = "model.ply";
    /// TSDF mesh of the keyframes (PLY).
    pub const MESH: &str = "mesh.ply";
    /// TSDF volume of the keyframes (rgbid's binary volume format).
    pub const VOLUME: &str = "volume.tsdf";
    /// Lock file of an open writer (holds its process id).
    pub const LOCK: &str = ".rgbid-lock";
}

/// `summary.json`'s `status` while the run is going.
pub const STATUS_RUNNING: &str = "running";
/// `summary.json`'s `status` of a run that finished and wrote everything.
pub const STATUS_COMPLETE: &str = "complete";
/// `summary.json`'s `status` of a run stopped by a signal (its outputs cover the frames
/// processed before).
pub const STATUS_INTERRUPTED: &str = "interrupted";

/// How a run ended, for [`RunFolderWriter::end`].
#[derive(Clone, Debug, PartialEq)]
pub enum RunStatus {
    /// Finished; every output written (`status: complete`).
    Complete,
    /// Stopped by a signal (`status: interrupted`).
    Interrupted,
    /// Stopped by an error (`status: failed: <error>`).
    Failed(String),
}

impl RunStatus {
    /// The text stored in `summary.json`.
    pub fn text(&self) -> String {
        match self {
            RunStatus::Complete => STATUS_COMPLETE.into(),
            RunStatus::Interrupted => STATUS_INTERRUPTED.into(),
            RunStatus::Failed(e) => format!("failed: {e}"),
        }
    }
}

/// One frame's front-end statistics (a line of `timing.csv`). Times in milliseconds.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct FrameRow {
    /// Frame index in the sequence.
    pub index: usize,
    /// Time stamp, seconds.
    pub timestamp: f64,
    /// What happened to the frame (`Tracking`, `NewKeyframe`, `Lost`, `Relocalised`, ...).
    pub status: String,
    /// Front-end total.
    pub frontend_ms: f64,
    /// Pyramid construction.
    pub pyramid_ms: f64,
    /// Robust scale estimation.
    pub scale_ms: f64,
    /// Residuals and normal-equation reduction.
    pub reduce_ms: f64,
    /// 6x6 solves.
    pub solve_ms: f64,
    /// Covisibility.
    pub covisibility_ms: f64,
    /// Keyframe fusion.
    pub fusion_ms: f64,
    /// Covisibility with the odometry reference (0..1).
    pub covisibility: f64,
    /// Covisibility of the keyframe with the frame (0..1).
    pub keyframe_covisibility: f64,
    /// Photometric residual scale sigma_I at the finest level (intensity levels).
    #[serde(default)]
    pub sigma_photo: Option<f64>,
    /// Geometric residual scale sigma_W at the finest level (1/m).
    #[serde(default)]
    pub sigma_geo: Option<f64>,
    /// Student-t degrees of freedom.
    #[serde(default)]
    pub nu: Option<f64>,
    /// Condition number of the final Hessian.
    #[serde(default)]
    pub condition_number: Option<f64>,
    /// Gauss-Newton iterations.
    #[serde(default)]
    pub iterations: Option<usize>,
}

/// One loop or relocalisation check (a line of `loops.csv`).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct LoopRow {
    /// Query keyframe id (for a relocalisation: the keyframe count when it was tried).
    pub query: usize,
    /// Candidate keyframe id.
    pub candidate: usize,
    /// RANSAC inliers.
    pub inliers: usize,
    /// Translation of the dense refinement away from the RANSAC pose, metres.
    pub refine_translation_m: f64,
    /// Rotation of the dense refinement away from the RANSAC pose, radians.
    pub refine_rotation_rad: f64,
    /// Dense covisibility of the two keyframes.
    pub covisibility: f64,
    /// Whether the loop was accepted.
    pub accepted: bool,
    /// Whether this was a relocalisation rather than a loop.
    pub relocalisation: bool,
    /// Why it was accepted or rejected.
    pub reason: String,
}

/// Back-end time of one new keyframe (a line of `keyframe_timing.csv`), milliseconds.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct KeyframeTimingRow {
    /// Keyframe id.
    pub id: usize,
    /// Superjut segmentation and masks.
    pub segment_ms: f64,
    /// ORB and bags of words.
    pub describe_ms: f64,
    /// Database query and verification.
    pub query_ms: f64,
    /// Dense loop alignment.
    pub align_ms: f64,
    /// Pose-graph optimisation.
    pub optimise_ms: f64,
    /// Total.
    pub total_ms: f64,
}

/// `summary.json`: the format version, what the run did and how well, plus any other keys
/// (configuration, versions, memory breakdown, ...) kept in `extra`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct RunSummary {
    /// Run-folder format version ([`FORMAT_VERSION`] when written by this build; 0 when the
    /// file has none).
    #[serde(default)]
    pub format_version: u32,
    /// Whether the run finished and wrote everything (false while it runs, or when it was
    /// interrupted; folders from before the versioned format have no such key and read true).
    #[serde(default = "yes")]
    pub complete: bool,
    /// `running`, `complete`, `interrupted` or `failed: <error>` (see [`RunStatus`]); empty in
    /// folders written before the field existed.
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub status: String,
    /// Frames processed.
    #[serde(default)]
    pub frames: usize,
    /// Frames dropped (real-time feeding).
    #[serde(default)]
    pub dropped: usize,
    /// Frames skipped because their images could not be used (corrupt, implausible depth).
    #[serde(default)]
    pub skipped_frames: usize,
    /// Warnings of a run that finished with exit code 3 (frames skipped, a depth factor that
    /// does not fit the sensor's range, an evaluation that could not be done), as printed.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub warnings: Vec<String>,
    /// Frames with a front-end pose.
    #[serde(default)]
    pub tracked: usize,
    /// Frames lost.
    #[serde(default)]
    pub lost: usize,
    /// Frames relocalised.
    #[serde(default)]
    pub relocalised: usize,
    /// Keyframes.
    #[serde(default)]
    pub keyframes: usize,
    /// Accepted loops (relocalisations not counted).
    #[serde(default)]
    pub loops_accepted: usize,
    /// Wall time, seconds.
    #[serde(default)]
    pub wall_s: f64,
    /// Points in `model.ply` (0 when none was written).
    #[serde(default)]
    pub model_points: usize,
    /// Peak resident memory of the process, MB, when known.
    #[serde(default)]
    pub peak_rss_mb: Option<f64>,
    /// ATE RMSE of the SLAM trajectory against ground truth, metres.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub slam_ate_rmse: Option<f64>,
    /// RPE RMSE of the SLAM trajectory, m/s.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub slam_rpe_rmse: Option<f64>,
    /// ATE RMSE of the front-end trajectory, metres.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub odometry_ate_rmse: Option<f64>,
    /// RPE RMSE of the front-end trajectory, m/s.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub odometry_rpe_rmse: Option<f64>,
    /// Every other key of the file.
    #[serde(flatten)]
    pub extra: serde_json::Map<String, serde_json::Value>,
}

fn yes() -> bool {
    true
}

/// An append-only CSV file whose rows are flushed as they are written.
struct CsvAppender {
    path: PathBuf,
    writer: csv::Writer<File>,
}

impl CsvAppender {
    /// Creates the file with its header line (written at once, so that a file without rows
    /// still has one; the rows' fields are in the same order).
    fn create(path: PathBuf, columns: &[&str]) -> Result<Self, IoError> {
        let file = File::create(&path).map_err(|e| IoError::file(&path, e))?;
        let mut writer = csv::WriterBuilder::new()
            .has_headers(false)
            .from_writer(file);
        writer
            .write_record(columns)
            .map_err(|e| csv_error(&path, e))?;
        writer.flush().map_err(|e| IoError::file(&path, e))?;
        Ok(CsvAppender { path, writer })
    }

    fn write<T: Serialize>(&mut self, row: &T) -> Result<(), IoError> {
        self.writer
            .serialize(row)
            .map_err(|e| csv_error(&self.path, e))?;
        self.writer
            .flush()
            .map_err(|e| IoError::file(&self.path, e))
    }
}

/// Writes a run folder incrementally: [`create`](Self::create) opens the per-frame files, the
/// row methods append and flush, [`finish`](Self::finish) writes `summary.json` last. Files
/// of a previous run in the same folder are replaced. The folder is locked while the writer
/// exists.
pub struct RunFolderWriter {
    dir: PathBuf,
    timing: CsvAppender,
    loops: CsvAppender,
    keyframe_timing: CsvAppender,
    odometry: (PathBuf, BufWriter<File>),
    loops_written: usize,
    // Last, so that it is dropped after the files are closed.
    _lock: FolderLock,
}

impl RunFolderWriter {
    /// Creates `dir` (and its parents) and the per-frame files, with their headers, and an
    /// incomplete `summary.json`. Files that are only written at the end
    /// (`trajectory.txt`, `keyframes.txt`, `groundtruth.txt`, `model.ply`, `mesh.ply`,
    /// `volume.tsdf`) are removed, so
    /// that an interrupted run does not leave a previous run's results beside its own.
    ///
    /// A folder another live writer holds (its lock file names a running process) is
    /// refused with [`IoError::FolderLocked`]; a lock left by a process that no longer runs is
    /// taken over.
    pub fn create(dir: &Path) -> Result<Self, IoError> {
        std::fs::create_dir_all(dir).map_err(|e| IoError::file(dir, e))?;
        let lock = FolderLock::acquire(dir)?;
        for stale in [
            files::TRAJECTORY,
            files::KEYFRAMES,
            files::GROUNDTRUTH,
            files::MODEL,
            files::MESH,
            files::VOLUME,
        ] {
            let p = dir.join(stale);
            match std::fs::remove_file(&p) {
                Ok(()) => {}
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
                Err(e) => return Err(IoError::file(p, e)),
            }
        }
        let timing = CsvAppender::create(dir.join(files::TIMING), FRAME_COLUMNS)?;
        let loops = CsvAppender::create(dir.join(files::LOOPS), LOOP_COLUMNS)?;
        let keyframe_timing =
            CsvAppender::create(dir.join(files::KEYFRAME_TIMING), KEYFRAME_TIMING_COLUMNS)?;
        let odo = dir.join(files::ODOMETRY);
        let odometry = BufWriter::new(File::create(&odo).map_err(|e| IoError::file(&odo, e))?);
        let w = RunFolderWriter {
            dir: dir.to_path_buf(),
            timing,
            loops,
            keyframe_timing,
            odometry: (odo, odometry),
            loops_written: 0,
            _lock: lock,
        };
        w.write_summary(&RunSummary {
            complete: false,
            status: STATUS_RUNNING.into(),
            ..Default::default()
        })?;
        Ok(w)
    }

    /// The folder.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Appends a frame's statistics to `timing.csv`.
    pub fn frame(&mut self, row: &FrameRow) -> Result<(), IoError> {
        self.timing.write(row)
    }

    /// Appends a front-end pose to `odometry.txt`.
    pub fn odometry_pose(&mut self, pose: &TimedPose) -> Result<(), IoError> {
        let (path, w) = &mut self.odometry;
        writeln!(w, "{}", format_tum_line(pose))
            .and_then(|()| w.flush())
            .map_err(|e| IoError::file(&*path, e))
    }

    /// Appends a loop check to `loops.csv`.
    pub fn loop_checked(&mut self, row: &LoopRow) -> Result<(), IoError> {
        self.loops.write(row)?;
        self.loops_written += 1;
        Ok(())
    }

    /// Loop rows written so far (to append only the new ones of a growing list).
    pub fn loops_written(&self) -> usize {
        self.loops_written
    }

    /// Appends a keyframe's back-end times to `keyframe_timing.csv`.
    pub fn keyframe_timing(&mut self, row: &KeyframeTimingRow) -> Result<(), IoError> {
        self.keyframe_timing.write(row)
    }

    /// Writes a checkpoint, so that a run killed later (SIGKILL, a crash, a full disk)
    /// leaves a readable folder: flushes the per-frame files, then replaces
    /// `trajectory.txt`, `keyframes.txt` and, last, `summary.json` (with `status: running`
    /// and `complete: false`) atomically. The summary is written after the trajectories, so
    /// its counts never exceed what they hold. `trajectory` is the best estimate so far of
    /// every posed frame and `keyframes` that of the keyframes (`world_from_camera`, TUM).
    ///
    /// An error (a full disk among them) leaves each file as the previous checkpoint wrote
    /// it, or the new version of it, never part of one.
    pub fn checkpoint(
        &mut self,
        trajectory: &[TimedPose],
        keyframes: &[TimedPose],
        summary: RunSummary,
    ) -> Result<(), IoError> {
        let (path, w) = &mut self.odometry;
        w.flush().map_err(|e| IoError::file(&*path, e))?;
        self.trajectory(trajectory)?;
        self.keyframes(keyframes)?;
        self.write_summary(&RunSummary {
            complete: false,
            status: STATUS_RUNNING.into(),
            ..summary
        })
    }

    /// Writes the optimised trajectory of every frame (`trajectory.txt`).
    pub fn trajectory(&self, poses: &[TimedPose]) -> Result<(), IoError> {
        super::trajectory::write_tum(&self.dir.join(files::TRAJECTORY), poses)
    }

    /// Writes the optimised keyframe poses (`keyframes.txt`).
    pub fn keyframes(&self, poses: &[TimedPose]) -> Result<(), IoError> {
        super::trajectory::write_tum(&self.dir.join(files::KEYFRAMES), poses)
    }

    /// Writes the ground truth (`groundtruth.txt`).
    pub fn groundtruth(&self, poses: &[TimedPose]) -> Result<(), IoError> {
        super::trajectory::write_tum(&self.dir.join(files::GROUNDTRUTH), poses)
    }

    /// Writes the model (`model.ply`, grey points: `(world position in metres, intensity)`).
    pub fn model(&self, points: &[(DVec3, u8)]) -> Result<(), IoError> {
        super::ply::write_ply_grey(&self.dir.join(files::MODEL), points)
    }

    /// Writes the model (`model.ply`) with 8-bit RGB colour per point (world position in
    /// metres).
    pub fn model_coloured(&self, points: &[(DVec3, [u8; 3])]) -> Result<(), IoError> {
        super::ply::write_ply(&self.dir.join(files::MODEL), points)
    }

    /// Writes `summary.json` with [`FORMAT_VERSION`] and `complete: true` and closes the
    /// folder. Returns the folder.
    pub fn finish(self, summary: RunSummary) -> Result<PathBuf, IoError> {
        self.end(summary, RunStatus::Complete)
    }

    /// Writes `summary.json` with [`FORMAT_VERSION`] and `status` (`complete` is true only
    /// for [`RunStatus::Complete`]) and closes the folder. Returns the folder.
    pub fn end(mut self, summary: RunSummary, status: RunStatus) -> Result<PathBuf, IoError> {
        let (path, w) = &mut self.odometry;
        w.flush().map_err(|e| IoError::file(&*path, e))?;
        self.write_summary(&RunSummary {
            complete: status == RunStatus::Complete,
            status: status.text(),
            ..summary
        })?;
        Ok(self.dir.clone())
    }

    fn write_summary(&self, summary: &RunSummary) -> Result<(), IoError> {
        let s = RunSummary {
            format_version: FORMAT_VERSION,
            ..summary.clone()
        };
        let path = self.dir.join(files::SUMMARY);
        let text = serde_json::to_string_pretty(&s).map_err(|e| IoError::Malformed {
            path: path.clone(),
            message: e.to_string(),
        })?;
        super::write_atomic(&path, |w| w.write_all(text.as_bytes()))
    }
}

/// The lock file of a run folder; removed when dropped.
struct FolderLock {
    path: PathBuf,
}

impl FolderLock {
    fn acquire(dir: &Path) -> Result<Self, IoError> {
        let path = dir.join(files::LOCK);
        for _ in 0..2 {
            match std::fs::OpenOptions::new()
                .write(true)
                .create_new(true)
                .open(&path)
            {
                Ok(mut f) => {
                    writeln!(f, "{}", std::process::id()).map_err(|e| IoError::file(&path, e))?;
                    return Ok(FolderLock { path });
                }
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {
                    let holder = std::fs::read_to_string(&path)
                        .ok()
                        .and_then(|t| t.trim().parse::<u32>().ok());
                    match holder {
                        Some(pid) if process_alive(pid) => {
                            return Err(IoError::FolderLocked {
                                path: dir.to_path_buf(),
                                pid,
                            })
                        }
                        // Left by a run that no longer exists (killed): take it over.
                        _ => match std::fs::remove_file(&path) {
                            Ok(()) => {}
                            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
                            Err(e) => return Err(IoError::file(&path, e)),
                        },
                    }
                }
                Err(e) => return Err(IoError::file(&path, e)),
            }
        }
        Err(IoError::FolderLocked {
            path: dir.to_path_buf(),
            pid: 0,
        })
    }
}

impl Drop for FolderLock {
    fn drop(&mut self) {
        // Nothing to report to: a lock that cannot be removed is taken over by the next run
        // once this process has exited.
        let _ = std::fs::remove_file(&self.path);
    }
}

/// Whether a process with this id runs (where `/proc` exists; elsewhere every holder is
/// assumed alive, so a stale lock must be removed by hand).
fn process_alive(pid: u32) -> bool {
    let proc = Path::new("/proc");
    if !proc.is_dir() {
        return true;
    }
    pid == std::process::id() || proc.join(pid.to_string()).exists()
}

const FRAME_COLUMNS: &[&str] = &[
    "index",
    "timestamp",
    "status",
    "frontend_ms",
    "pyramid_ms",
    "scale_ms",
    "reduce_ms",
    "solve_ms",
    "covisibility_ms",
    "fusion_ms",
    "covisibility",
    "keyframe_covisibility",
    "sigma_photo",
    "sigma_geo",
    "nu",
    "condition_number",
    "iterations",
];
const LOOP_COLUMNS: &[&str] = &[
    "query",
    "candidate",
    "inliers",
    "refine_translation_m",
    "refine_rotation_rad",
    "covisibility",
    "accepted",
    "relocalisation",
    "reason",
];
const KEYFRAME_TIMING_COLUMNS: &[&str] = &[
    "id",
    "segment_ms",
    "describe_ms",
    "query_ms",
    "align_ms",
    "optimise_ms",
    "total_ms",
];

fn csv_error(path: &Path, e: csv::Error) -> IoError {
    let line = e.position().map_or(0, |p| p.line() as usize);
    match e.into_kind() {
        csv::ErrorKind::Io(source) => IoError::file(path, source),
        kind => IoError::Parse {
            path: path.to_path_buf(),
            line,
            message: csv_kind_message(&kind),
        },
    }
}

fn csv_kind_message(kind: &csv::ErrorKind) -> String {
    match kind {
        csv::ErrorKind::Deserialize { err, .. } => match err.field() {
            Some(f) => format!("column {}: {}", f + 1, err.kind()),
            None => err.kind().to_string(),
        },
        csv::ErrorKind::UnequalLengths {
            expected_len, len, ..
        } => format!("{len} fields, the header has {expected_len}"),
        other => format!("{other:?}"),
    }
}

/// Reads all rows of a CSV file by header name.
pub fn read_csv<T: for<'de> Deserialize<'de>>(path: &Path) -> Result<Vec<T>, IoError> {
    let mut reader = csv::ReaderBuilder::new()
        .trim(csv::Trim::All)
        .from_path(path)
        .map_err(|e| csv_error(path, e))?;
    reader
        .deserialize()
        .collect::<Result<Vec<T>, _>>()
        .map_err(|e| csv_error(path, e))
}

/// Everything in a run folder.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct RunFolder {
    /// The folder.
    pub dir: PathBuf,
    /// `summary.json`, when present (a run interrupted before it was first written, or a
    /// folder of an old version, may have none).
    pub summary: Option<RunSummary>,
    /// Optimised trajectory (`trajectory.txt`); for an interrupted run, which never wrote
    /// one, the front-end trajectory.
    pub trajectory: Vec<TimedPose>,
    /// Front-end trajectory (`odometry.txt`; empty when absent).
    pub odometry: Vec<TimedPose>,
    /// Keyframe poses (`keyframes.txt`; empty when absent).
    pub keyframes: Vec<TimedPose>,
    /// Ground truth (`groundtruth.txt`), when present.
    pub groundtruth: Option<Vec<TimedPose>>,
    /// Per-frame statistics (`timing.csv`; empty when absent).
    pub frames: Vec<FrameRow>,
    /// Loop checks (`loops.csv`; empty when absent).
    pub loops: Vec<LoopRow>,
    /// Back-end times per keyframe (`keyframe_timing.csv`; empty when absent).
    pub keyframe_timings: Vec<KeyframeTimingRow>,
    /// The model (`model.ply`; empty when absent).
    pub model: Vec<(DVec3, u8)>,
}

impl RunFolder {
    /// Whether `dir` looks like a run folder (has `summary.json` or `trajectory.txt`).
    pub fn is_run_folder(dir: &Path) -> bool {
        dir.join(files::SUMMARY).is_file() || dir.join(files::TRAJECTORY).is_file()
    }

    /// Reads a run folder. `trajectory.txt` or `odometry.txt` must hold poses; every other
    /// file is optional. A `summary.json` of a newer format version than [`FORMAT_VERSION`]
    /// is an error.
    pub fn read(dir: &Path) -> Result<Self, IoError> {
        if !dir.is_dir() {
            return Err(IoError::MissingFolder { path: dir.into() });
        }
        let summary_path = dir.join(files::SUMMARY);
        let summary = if summary_path.is_file() {
            let text = std::fs::read_to_string(&summary_path)
                .map_err(|e| IoError::file(&summary_path, e))?;
            let s: RunSummary = serde_json::from_str(&text)
                .map_err(|e| IoError::parse(&summary_path, e.line(), e.to_string()))?;
            if s.format_version > FORMAT_VERSION {
                return Err(IoError::Malformed {
                    path: summary_path,
                    message: format!(
                        "run-folder format version {} is newer than this build reads ({FORMAT_VERSION})",
                        s.format_version
                    ),
                });
            }
            Some(s)
        } else {
            None
        };
        let tum = |name: &str| -> Result<Option<Vec<TimedPose>>, IoError> {
            let p = dir.join(name);
            if !p.is_file() {
                return Ok(None);
            }
            match super::trajectory::read_tum(&p) {
                Ok(t) => Ok(Some(t)),
                // An interrupted run may have created a file without poses yet.
                Err(IoError::Empty { .. }) => Ok(Some(Vec::new())),
                Err(e) => Err(e),
            }
        };
        let odometry = tum(files::ODOMETRY)?.unwrap_or_default();
        let trajectory = match tum(files::TRAJECTORY)? {
            Some(t) if !t.is_empty() => t,
            _ if !odometry.is_empty() => odometry.clone(),
            _ => {
                return Err(IoError::MissingFile {
                    path: dir.join(files::TRAJECTORY),
                    what: "a trajectory (trajectory.txt or odometry.txt with poses): not a run folder, or a run that stopped before its first frame".into(),
                })
            }
        };
        let csv_rows = |name: &str| -> Result<bool, IoError> { Ok(dir.join(name).is_file()) };
        let frames = if csv_rows(files::TIMING)? {
            read_csv(&dir.join(files::TIMING))?
        } else {
            Vec::new()
        };
        let loops = if csv_rows(files::LOOPS)? {
            read_csv(&dir.join(files::LOOPS))?
        } else {
            Vec::new()
        };
        let keyframe_timings = if csv_rows(files::KEYFRAME_TIMING)? {
            read_csv(&dir.join(files::KEYFRAME_TIMING))?
        } else {
            Vec::new()
        };
        let model_path = dir.join(files::MODEL);
        let model = if model_path.is_file() {
            super::ply::read_ply_grey(&model_path)?
        } else {
            Vec::new()
        };
        Ok(RunFolder {
            dir: dir.to_path_buf(),
            summary,
            trajectory,
            odometry,
            keyframes: tum(files::KEYFRAMES)?.unwrap_or_default(),
            groundtruth: tum(files::GROUNDTRUTH)?.filter(|g| !g.is_empty()),
            frames,
            loops,
            keyframe_timings,
            model,
        })
    }

    /// Whether the run finished (its summary says so; folders without a summary did not).
    pub fn complete(&self) -> bool {
        self.summary.as_ref().is_some_and(|s| s.complete)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::Se3;

    fn pose(t: f64) -> TimedPose {
        TimedPose {
            timestamp: t,
            world_from_camera: Se3::exp(&[0.1 * t, 0.2, 0.3, 0.01, -0.02, 0.03 * t]),
        }
    }

    fn frame(i: usize) -> FrameRow {
        FrameRow {
            index: i,
            timestamp: i as f64 / 30.0,
            status: if i == 0 { "NewKeyframe" } else { "Tracking" }.into(),
            frontend_ms: 3.25 + i as f64,
            pyramid_ms: 0.5,
            scale_ms: 0.125,
            reduce_ms: 1.0,
            solve_ms: 0.01,
            covisibility_ms: 0.2,
            fusion_ms: 0.7,
            covisibility: 0.95,
            keyframe_covisibility: 0.8,
            sigma_photo: (i > 0).then_some(4.5),
            sigma_geo: (i > 0).then_some(0.002),
            nu: (i > 0).then_some(5.5),
            condition_number: (i > 0).then_some(1.2e4),
            iterations: (i > 0).then_some(14),
        }
    }

    #[test]
    fn round_trip() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("run");
        let mut w = RunFolderWriter::create(&out).unwrap();
        let frames: Vec<FrameRow> = (0..3).map(frame).collect();
        let odometry: Vec<TimedPose> = (0..3).map(|i| pose(i as f64 / 30.0)).collect();
        for (f, p) in frames.iter().zip(&odometry) {
            w.frame(f).unwrap();
            w.odometry_pose(p).unwrap();
        }
        let loops = vec![
            LoopRow {
                query: 9,
                candidate: 2,
                inliers: 40,
                refine_translation_m: 0.01,
                refine_rotation_rad: 0.002,
                covisibility: 0.8,
                accepted: true,
                relocalisation: false,
                reason: "accepted, \"quoted\", with commas".into(),
            },
            LoopRow {
                query: 3,
                reason: String::new(),
                ..Default::default()
            },
        ];
        for l in &loops {
            w.loop_checked(l).unwrap();
        }
        assert_eq!(w.loops_written(), 2);
        let kt = KeyframeTimingRow {
            id: 1,
            segment_ms: 10.0,
            describe_ms: 5.0,
            query_ms: 1.0,
            align_ms: 0.0,
            optimise_ms: 0.0,
            total_ms: 16.0,
        };
        w.keyframe_timing(&kt).unwrap();
        // Partial results are readable before the end.
        let partial = RunFolder::read(&out).unwrap();
        assert!(!partial.complete());
        assert_eq!(partial.frames, frames);
        assert_eq!(partial.trajectory.len(), 3, "odometry stands in");
        let trajectory: Vec<TimedPose> = (0..3).map(|i| pose(0.5 + i as f64)).collect();
        w.trajectory(&trajectory).unwrap();
        w.keyframes(&trajectory[..1]).unwrap();
        w.groundtruth(&odometry).unwrap();
        let model = vec![
            (DVec3::new(1.0, 2.0, 3.0), 9u8),
            (DVec3::new(-1.0, 0.5, 2.0), 250),
        ];
        w.model(&model).unwrap();
        let mut extra = serde_json::Map::new();
        extra.insert("command".into(), serde_json::json!(["rgbid", "slam"]));
        let summary = RunSummary {
            frames: 3,
            tracked: 3,
            keyframes: 1,
            loops_accepted: 1,
            wall_s: 1.5,
            model_points: 2,
            peak_rss_mb: Some(100.0),
            slam_ate_rmse: Some(0.01),
            extra,
            ..Default::default()
        };
        let written = w.finish(summary.clone()).unwrap();
        assert_eq!(written, out);
        let back = RunFolder::read(&out).unwrap();
        assert!(back.complete());
        let s = back.summary.clone().unwrap();
        assert_eq!(s.format_version, FORMAT_VERSION);
        assert_eq!(
            s,
            RunSummary {
                format_version: FORMAT_VERSION,
                complete: true,
                status: STATUS_COMPLETE.into(),
                ..summary
            }
        );
        assert_eq!(back.frames, frames);
        assert_eq!(back.loops, loops);
        assert_eq!(back.keyframe_timings, vec![kt]);
        assert_eq!(back.model, model);
        assert_eq!(back.odometry.len(), 3);
        assert_eq!(back.keyframes.len(), 1);
        assert_eq!(back.groundtruth.as_ref().map(Vec::len), Some(3));
        let close = |a: &TimedPose, b: &TimedPose| {
            (a.timestamp - b.timestamp).abs() < 1e-6
                && (a.world_from_camera.translation - b.world_from_camera.translation).length()
                    < 1e-6
        };
        assert!(back
            .trajectory
            .iter()
            .zip(&trajectory)
            .all(|(a, b)| close(a, b)));
        assert!(back
            .odometry
            .iter()
            .zip(&odometry)
            .all(|(a, b)| close(a, b)));
    }

    #[test]
    fn reads_the_unversioned_files_by_column_name() {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        std::fs::write(d.join(files::TRAJECTORY), "0.0 1 2 3 0 0 0 1\n").unwrap();
        // The first timing.csv had no diagnostic columns; column order does not matter.
        std::fs::write(
            d.join(files::TIMING),
            "index,timestamp,status,frontend_ms,pyramid_ms,scale_ms,reduce_ms,solve_ms,covisibility_ms,fusion_ms,keyframe_covisibility,covisibility\n\
             0,0.000000,NewKeyframe,1.0,0.1,0.2,0.3,0.4,0.5,0.6,0.9000,1.0000\n",
        )
        .unwrap();
        std::fs::write(
            d.join(files::LOOPS),
            "query,candidate,inliers,refine_translation_m,refine_rotation_rad,covisibility,accepted,relocalisation,reason\n\
             9,2,40,0.0100,0.0100,0.800,true,false,\"ok, fine\"\n",
        )
        .unwrap();
        std::fs::write(
            d.join(files::SUMMARY),
            r#"{"frames": 1, "wall_s": 2.0, "peak_rss_mb": null, "instance_peak_bytes": 5}"#,
        )
        .unwrap();
        let r = RunFolder::read(d).unwrap();
        assert_eq!(r.frames[0].fusion_ms, 0.6);
        assert_eq!(r.frames[0].covisibility, 1.0);
        assert_eq!(r.frames[0].sigma_photo, None);
        assert_eq!(r.loops[0].reason, "ok, fine");
        let s = r.summary.unwrap();
        assert_eq!((s.format_version, s.complete, s.frames), (0, true, 1));
        assert_eq!(s.extra["instance_peak_bytes"], serde_json::json!(5));
    }

    #[test]
    fn errors_name_the_file_and_line() {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        assert!(matches!(
            RunFolder::read(d),
            Err(IoError::MissingFile { .. })
        ));
        std::fs::write(d.join(files::TRAJECTORY), "0.0 1 2 3 0 0 0 1\n").unwrap();
        std::fs::write(d.join(files::TIMING), "index,timestamp\n0,0.0\n1,x\n").unwrap();
        let e = RunFolder::read(d).unwrap_err().to_string();
        assert!(e.contains("timing.csv:2:"), "{e}");
        std::fs::remove_file(d.join(files::TIMING)).unwrap();
        std::fs::write(d.join(files::SUMMARY), r#"{"format_version": 99}"#).unwrap();
        let e = RunFolder::read(d).unwrap_err().to_string();
        assert!(e.contains("newer"), "{e}");
        std::fs::write(d.join(files::SUMMARY), "{").unwrap();
        let e = RunFolder::read(d).unwrap_err().to_string();
        assert!(e.contains("summary.json:1:"), "{e}");
    }
}
