//! RGB-D dataset layouts other than TUM's image lists, read into the same
//! [`TumSequence`](super::tum::TumSequence) (colour + 16-bit depth file pairs with time stamps,
//! a camera, and ground truth when the layout has it).
//!
//! | layout | files | camera | depth | ground truth |
//! |---|---|---|---|---|
//! | [`Layout::Tum`] | `rgb.txt` + `depth.txt` (or `associations.txt`) | `calib.txt` or a preset | 5000 / m | `groundtruth.txt` (TUM lines) |
//! | [`Layout::Eth3d`] | `rgb.txt` + `depth.txt`, `calibration.txt` (`fx fy cx cy`) | `calibration.txt`, size from the first image | 5000 / m | `groundtruth.txt` |
//! | [`Layout::SevenScenes`] | `frame-NNNNNN.color.png` (or `.jpg`), `frame-NNNNNN.depth.png` in one `seq-NN` folder | preset `7scenes` (585, 585, 320, 240) | mm, 65535 = none | `frame-NNNNNN.pose.txt` (4x4 camera-to-world) |
//! | [`Layout::ScanNet`] | `color/N.jpg` (1296 x 968), `depth/N.png` (640 x 480), `intrinsic/intrinsic_{color,depth}.txt` as the ScanNet exporter writes them | `intrinsic_depth.txt`; colour resampled onto the depth camera through `intrinsic_color.txt` | mm | `pose/N.txt` (4x4 camera-to-world; frames whose pose is not finite are left out) |
//! | [`Layout::Replica`] | `results/frameNNNNNN.jpg`, `results/depthNNNNNN.png` | preset `replica` (600, 600, 599.5, 339.5, 1200 x 680) | 6553.5 / m | `traj.txt` (one row-major 4x4 camera-to-world per line) |
//!
//! Layouts without time stamps (7-Scenes, ScanNet, Replica) get `index / frame_rate` seconds
//! ([`OpenOptions::frame_rate`](super::tum::OpenOptions::frame_rate), default 30 Hz).
//! ICL-NUIM's TUM-compatible sequences are TUM folders; their camera is the preset
//! `icl_nuim`.

use std::path::{Path, PathBuf};

use glam::{DMat4, DVec4};

use super::config::{parse_numbers, CameraConfig};
use super::tum::SequenceEntry;
use super::IoError;
use crate::camera::PinholeCamera;
use crate::geometry::Se3;
use crate::trajectory::TimedPose;

/// A dataset's folder layout.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
pub enum Layout {
    /// TUM RGB-D (also Bonn, ICL-NUIM's TUM variant): `rgb.txt`, `depth.txt`.
    #[default]
    Tum,
    /// ETH3D SLAM: TUM lists plus `calibration.txt`.
    Eth3d,
    /// Microsoft 7-Scenes, one `seq-NN` folder as distributed.
    #[cfg_attr(feature = "clap", value(name = "7scenes"))]
    SevenScenes,
    /// A ScanNet scene as its exporter writes it: `color/`, `depth/`, `pose/`, `intrinsic/`.
    #[cfg_attr(feature = "clap", value(name = "scannet"))]
    ScanNet,
    /// Replica as rendered for NICE-SLAM: `results/` and `traj.txt`.
    Replica,
}

impl Layout {
    /// Every layout's name, as [`Self::from_name`] reads it.
    pub const NAMES: [&'static str; 5] = ["tum", "eth3d", "7scenes", "scannet", "replica"];

    /// The layout of a name in [`Self::NAMES`] (case-insensitive).
    pub fn from_name(name: &str) -> Option<Layout> {
        match name.to_ascii_lowercase().as_str() {
            "tum" => Some(Layout::Tum),
            "eth3d" => Some(Layout::Eth3d),
            "7scenes" | "7-scenes" | "sevenscenes" => Some(Layout::SevenScenes),
            "scannet" => Some(Layout::ScanNet),
            "replica" => Some(Layout::Replica),
            _ => None,
        }
    }

    /// The layout's name.
    pub fn name(self) -> &'static str {
        match self {
            Layout::Tum => "tum",
            Layout::Eth3d => "eth3d",
            Layout::SevenScenes => "7scenes",
            Layout::ScanNet => "scannet",
            Layout::Replica => "replica",
        }
    }

    /// The layout of `dir` from its content: `calibration.txt` beside TUM lists is ETH3D,
    /// `frame-000000.color.*` is 7-Scenes, `intrinsic/intrinsic_depth.txt` is ScanNet,
    /// `results/` with `traj.txt` is Replica, anything else is read as TUM (whose reader then
    /// names what is missing).
    pub fn detect(dir: &Path) -> Layout {
        if dir.join("calibration.txt").is_file() && dir.join("rgb.txt").is_file() {
            Layout::Eth3d
        } else if seven_scenes_colour(dir, 0).is_some() {
            Layout::SevenScenes
        } else if dir.join("intrinsic").join("intrinsic_depth.txt").is_file() {
            Layout::ScanNet
        } else if dir.join("results").is_dir() && dir.join("traj.txt").is_file() {
            Layout::Replica
        } else {
            Layout::Tum
        }
    }
}

impl std::fmt::Display for Layout {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// Where a sequence's ground truth is and how it is written.
#[derive(Clone, Debug, PartialEq)]
pub(crate) enum Truth {
    /// No ground truth.
    None,
    /// A TUM trajectory file (its own time stamps).
    TumFile(PathBuf),
    /// One 4x4 `world_from_camera` text file per frame (7-Scenes), in frame order.
    PerFrame(Vec<PathBuf>),
    /// As `PerFrame`, but frames whose matrix is not finite (ScanNet marks lost tracking with
    /// `-inf`) have no ground truth.
    PerFrameSkipInvalid(Vec<PathBuf>),
    /// One row-major 4x4 `world_from_camera` per line, line `i` for frame `i` (Replica).
    MatrixLines(PathBuf),
}

impl Truth {
    /// The ground-truth poses; frames without a file time-stamped like `entries`.
    pub(crate) fn read(
        &self,
        entries: &[SequenceEntry],
    ) -> Result<Option<Vec<TimedPose>>, IoError> {
        match self {
            Truth::None => Ok(None),
            Truth::TumFile(p) => super::trajectory::read_tum(p).map(Some),
            Truth::PerFrame(files) | Truth::PerFrameSkipInvalid(files) => {
                let skip = matches!(self, Truth::PerFrameSkipInvalid(_));
                let mut out = Vec::new();
                for (p, e) in files.iter().zip(entries) {
                    let text = super::read_text(p)?;
                    let lower = text.to_ascii_lowercase();
                    if skip && (lower.contains("inf") || lower.contains("nan")) {
                        continue;
                    }
                    let v = parse_numbers(&text).map_err(|m| IoError::parse(p, 1, m))?;
                    out.push(TimedPose {
                        timestamp: e.timestamp,
                        world_from_camera: pose_from_rows(&v)
                            .map_err(|m| IoError::parse(p, 1, m))?,
                    });
                }
                Ok(Some(out))
            }
            Truth::MatrixLines(p) => {
                let text = super::read_text(p)?;
                let mut out = Vec::new();
                for (i, line) in text.lines().enumerate() {
                    if line.trim().is_empty() || line.trim_start().starts_with('#') {
                        continue;
                    }
                    let Some(e) = entries.get(out.len()) else {
                        break; // poses past the frames read (e.g. --max-frames)
                    };
                    let v = parse_numbers(line).map_err(|m| IoError::parse(p, i + 1, m))?;
                    out.push(TimedPose {
                        timestamp: e.timestamp,
                        world_from_camera: pose_from_rows(&v)
                            .map_err(|m| IoError::parse(p, i + 1, m))?,
                    });
                }
                Ok(Some(out))
            }
        }
    }
}

/// A rigid transform from the 16 numbers of a row-major 4x4 matrix (the rotation block is
/// re-orthonormalised; the last row must be `0 0 0 1`).
fn pose_from_rows(v: &[f64]) -> Result<Se3, String> {
    if v.len() != 16 {
        return Err(format!(
            "expected a 4x4 matrix (16 numbers), found {}",
            v.len()
        ));
    }
    if v.iter().any(|x| !x.is_finite()) {
        return Err("the matrix holds a non-finite number".into());
    }
    if (v[12].abs() + v[13].abs() + v[14].abs() + (v[15] - 1.0).abs()) > 1e-6 {
        return Err(format!(
            "the last row is {} {} {} {}, not 0 0 0 1",
            v[12], v[13], v[14], v[15]
        ));
    }
    let col = |j: usize| DVec4::new(v[j], v[4 + j], v[8 + j], v[12 + j]);
    let m = DMat4::from_cols(col(0), col(1), col(2), col(3));
    let det = m.determinant();
    if !(det > 0.5 && det < 2.0) {
        return Err(format!(
            "the rotation block is not a rotation (determinant {det})"
        ));
    }
    Ok(Se3::from_mat4(&m))
}

/// Frames of a layout without image lists.
pub(crate) struct Listing {
    /// The frames, in order.
    pub(crate) entries: Vec<SequenceEntry>,
    /// Ground truth.
    pub(crate) truth: Truth,
}

/// The camera a layout brings when none is given: `None` for TUM (whose `calib.txt` or the
/// `default` preset applies).
pub(crate) fn layout_camera(layout: Layout, dir: &Path) -> Result<Option<CameraConfig>, IoError> {
    Ok(match layout {
        Layout::Tum => None,
        Layout::Eth3d => Some(eth3d_calibration(dir)?),
        Layout::ScanNet => {
            let first = dir.join("depth").join("0.png");
            let (w, h) = image::image_dimensions(&first).map_err(|e| IoError::Image {
                path: first.clone(),
                message: e.to_string(),
            })?;
            let path = dir.join("intrinsic").join("intrinsic_depth.txt");
            let cfg = CameraConfig {
                camera: intrinsic_matrix(&path, w, h)?,
                depth_factor: 1000.0,
                source: path.display().to_string(),
            };
            cfg.validate(&path)?;
            Some(cfg)
        }
        Layout::SevenScenes => CameraConfig::preset("7scenes"),
        Layout::Replica => CameraConfig::preset("replica"),
    })
}

/// The pinhole camera of a 4x4 (or 3x3) intrinsic matrix file as ScanNet writes them, for
/// images of `width` x `height`.
fn intrinsic_matrix(path: &Path, width: u32, height: u32) -> Result<PinholeCamera, IoError> {
    let text = super::read_text(path)?;
    let v = parse_numbers(&text).map_err(|m| IoError::parse(path, 1, m))?;
    let n = match v.len() {
        16 => 4,
        9 => 3,
        k => {
            return Err(IoError::Malformed {
                path: path.into(),
                message: format!("expected a 4x4 or 3x3 intrinsic matrix, found {k} numbers"),
            })
        }
    };
    Ok(PinholeCamera::new(
        v[0],
        v[n + 1],
        v[2],
        v[n + 2],
        width,
        height,
    ))
}

/// ScanNet's colour camera (`intrinsic/intrinsic_color.txt`) for colour images of
/// `width` x `height`.
pub(crate) fn scannet_colour_camera(
    dir: &Path,
    width: u32,
    height: u32,
) -> Result<PinholeCamera, IoError> {
    intrinsic_matrix(
        &dir.join("intrinsic").join("intrinsic_color.txt"),
        width,
        height,
    )
}

/// ETH3D's `calibration.txt` (`fx fy cx cy`), with the image size of the first colour image
/// of `rgb.txt` and TUM's depth factor.
fn eth3d_calibration(dir: &Path) -> Result<CameraConfig, IoError> {
    let path = dir.join("calibration.txt");
    let text = super::read_text(&path)?;
    let (line, s) = text
        .lines()
        .enumerate()
        .map(|(i, l)| (i + 1, l.split('#').next().unwrap_or("").trim()))
        .find(|(_, l)| !l.is_empty())
        .ok_or_else(|| IoError::Empty {
            path: path.clone(),
            message: "no calibration line".into(),
        })?;
    let v = parse_numbers(s).map_err(|m| IoError::parse(&path, line, m))?;
    if v.len() != 4 {
        return Err(IoError::parse(
            &path,
            line,
            format!("expected `fx fy cx cy`, found {} numbers", v.len()),
        ));
    }
    let first = first_listed_image(dir)?;
    let (w, h) = image::image_dimensions(&first).map_err(|e| IoError::Image {
        path: first.clone(),
        message: e.to_string(),
    })?;
    let cfg = CameraConfig {
        camera: PinholeCamera::new(v[0], v[1], v[2], v[3], w, h),
        depth_factor: super::config::TUM_DEPTH_FACTOR,
        source: path.display().to_string(),
    };
    cfg.validate(&path)?;
    Ok(cfg)
}

/// The first image named in `dir/rgb.txt`.
fn first_listed_image(dir: &Path) -> Result<PathBuf, IoError> {
    let list = dir.join("rgb.txt");
    let text = super::read_text(&list)?;
    text.lines()
        .map(str::trim)
        .filter(|l| !l.is_empty() && !l.starts_with('#'))
        .find_map(|l| l.split_whitespace().nth(1).map(|p| dir.join(p)))
        .ok_or_else(|| IoError::Empty {
            path: list,
            message: "no entries in image list".into(),
        })
}

/// 7-Scenes' colour image of frame `i`, if it exists (`.color.png`, else `.color.jpg`).
fn seven_scenes_colour(dir: &Path, i: usize) -> Option<PathBuf> {
    ["png", "jpg"]
        .iter()
        .map(|ext| dir.join(format!("frame-{i:06}.color.{ext}")))
        .find(|p| p.is_file())
}

/// The files of frame `i` of a layout without image lists: colour (`None` when frame `i`
/// does not exist, which ends the sequence), depth, and pose file (if the layout has one).
fn frame_files(
    layout: Layout,
    dir: &Path,
    i: usize,
) -> (Option<PathBuf>, PathBuf, Option<PathBuf>) {
    match layout {
        Layout::SevenScenes => (
            seven_scenes_colour(dir, i),
            dir.join(format!("frame-{i:06}.depth.png")),
            Some(dir.join(format!("frame-{i:06}.pose.txt"))),
        ),
        Layout::ScanNet => (
            Some(dir.join("color").join(format!("{i}.jpg"))).filter(|p| p.is_file()),
            dir.join("depth").join(format!("{i}.png")),
            Some(dir.join("pose").join(format!("{i}.txt"))),
        ),
        _ => (
            Some(dir.join("results").join(format!("frame{i:06}.jpg"))).filter(|p| p.is_file()),
            dir.join("results").join(format!("depth{i:06}.png")),
            None,
        ),
    }
}

/// The frames of a layout without image lists, numbered from 0 until the first missing one,
/// time-stamped at `frame_rate` Hz.
pub(crate) fn list_frames(
    layout: Layout,
    dir: &Path,
    frame_rate: f64,
    max_frames: Option<usize>,
) -> Result<Listing, IoError> {
    if matches!(layout, Layout::Tum | Layout::Eth3d) {
        return Err(IoError::Malformed {
            path: dir.into(),
            message: format!("the {layout} layout has image lists"),
        });
    }
    if !(frame_rate.is_finite() && frame_rate > 0.0) {
        return Err(IoError::Malformed {
            path: dir.into(),
            message: format!("frame rate must be > 0 Hz (got {frame_rate})"),
        });
    }
    let limit = max_frames.unwrap_or(usize::MAX);
    let mut entries = Vec::new();
    let mut poses = Vec::new();
    while entries.len() < limit {
        let i = entries.len();
        let (Some(rgb), depth, pose) = frame_files(layout, dir, i) else {
            break;
        };
        if !depth.is_file() {
            return Err(IoError::MissingFile {
                path: depth,
                what: format!("depth of frame {i} ({})", rgb.display()),
            });
        }
        poses.extend(pose);
        entries.push(SequenceEntry {
            timestamp: i as f64 / frame_rate,
            rgb,
            depth,
        });
    }
    if entries.is_empty() {
        let first = match layout {
            Layout::SevenScenes => dir.join("frame-000000.color.png"),
            Layout::ScanNet => dir.join("color").join("0.jpg"),
            _ => dir.join("results").join("frame000000.jpg"),
        };
        return Err(IoError::MissingFile {
            path: first,
            what: format!("first frame of a {layout} folder"),
        });
    }
    let all_poses = !poses.is_empty() && poses.iter().all(|p| p.is_file());
    let truth = match layout {
        Layout::SevenScenes if all_poses => Truth::PerFrame(poses),
        Layout::ScanNet if all_poses => Truth::PerFrameSkipInvalid(poses),
        Layout::Replica => Truth::MatrixLines(dir.join("traj.txt")),
        _ => Truth::None,
    };
    Ok(Listing { entries, truth })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn matrices_become_poses_and_bad_ones_are_named() {
        let t = pose_from_rows(&[
            0.0, -1.0, 0.0, 1.0, 1.0, 0.0, 0.0, 2.0, 0.0, 0.0, 1.0, 3.0, 0.0, 0.0, 0.0, 1.0,
        ])
        .unwrap();
        let p = t.transform_point(glam::DVec3::X);
        assert!(
            (p - glam::DVec3::new(1.0, 3.0, 3.0)).length() < 1e-12,
            "{p}"
        );
        assert!(pose_from_rows(&[1.0; 12])
            .unwrap_err()
            .contains("16 numbers"));
        let mut bad = [0.0; 16];
        bad[15] = 1.0;
        assert!(pose_from_rows(&bad).unwrap_err().contains("determinant"));
        let mut row = [
            1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0,
        ];
        row[12] = 0.5;
        assert!(pose_from_rows(&row).unwrap_err().contains("last row"));
    }

    #[test]
    fn names_round_trip() {
        for n in Layout::NAMES {
            assert_eq!(Layout::from_name(n).map(Layout::name), Some(n));
        }
        assert_eq!(Layout::from_name("7-Scenes"), Some(Layout::SevenScenes));
        assert_eq!(Layout::from_name("kitti"), None);
    }
}
