//! Trajectory files, every pose `world_from_camera` (metres, seconds):
//!
//! - TUM: one pose per line, `timestamp tx ty tz qx qy qz qw`; `#` starts a comment.
//! - KITTI: one row-major 3x4 matrix `[R | t]` per line (12 numbers); the time stamps (seconds,
//!   one per line) in `<stem>.times.txt` or `times.txt` beside the file.
//! - EuRoC CSV: `timestamp [ns], p_x, p_y, p_z, q_w, q_x, q_y, q_z` (further columns, as in
//!   `state_groundtruth_estimate0/data.csv`, are ignored); `#` starts the header.
//!
//! [`read_trajectory`] detects the format ([`TrajectoryFormat::detect`]).

use std::io::Write;
use std::path::{Path, PathBuf};

use glam::{DMat3, DQuat, DVec3};

use super::config::parse_numbers;
use super::IoError;
use crate::geometry::Se3;
use crate::trajectory::{format_tum_line, parse_tum_line, TimedPose};

/// A trajectory file format.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
pub enum TrajectoryFormat {
    /// `timestamp tx ty tz qx qy qz qw` lines.
    #[default]
    Tum,
    /// 3x4 matrix rows, time stamps in a `times.txt` beside.
    Kitti,
    /// EuRoC / ASL CSV with nanosecond time stamps and the quaternion `w` first.
    Euroc,
}

impl TrajectoryFormat {
    /// The format of a file: a `.csv` extension or comma-separated columns under a `#`
    /// header is EuRoC; 12 numbers per line is KITTI; anything else is read as TUM (whose
    /// reader then names what is wrong).
    pub fn detect(path: &Path, text: &str) -> TrajectoryFormat {
        let csv = path
            .extension()
            .and_then(|e| e.to_str())
            .is_some_and(|e| e.eq_ignore_ascii_case("csv"));
        if csv || text.trim_start().starts_with("#timestamp") {
            return TrajectoryFormat::Euroc;
        }
        let first = text
            .lines()
            .map(str::trim)
            .find(|l| !l.is_empty() && !l.starts_with('#'));
        match first.map(|l| l.split_whitespace().count()) {
            Some(12) => TrajectoryFormat::Kitti,
            _ => TrajectoryFormat::Tum,
        }
    }

    /// The format a file name asks for when writing: `.csv` is EuRoC, `.kitti` KITTI, else
    /// TUM.
    pub fn from_extension(path: &Path) -> TrajectoryFormat {
        match path
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase)
            .as_deref()
        {
            Some("csv") => TrajectoryFormat::Euroc,
            Some("kitti") => TrajectoryFormat::Kitti,
            _ => TrajectoryFormat::Tum,
        }
    }
}

/// Reads a trajectory in any [`TrajectoryFormat`] (detected), sorted by time stamp.
pub fn read_trajectory(path: &Path) -> Result<Vec<TimedPose>, IoError> {
    let text = super::read_text(path)?;
    read_trajectory_text(path, &text, TrajectoryFormat::detect(path, &text))
}

/// Reads a trajectory in `format`, sorted by time stamp. Errors name the file and line.
pub fn read_trajectory_as(
    path: &Path,
    format: TrajectoryFormat,
) -> Result<Vec<TimedPose>, IoError> {
    let text = super::read_text(path)?;
    read_trajectory_text(path, &text, format)
}

fn read_trajectory_text(
    path: &Path,
    text: &str,
    format: TrajectoryFormat,
) -> Result<Vec<TimedPose>, IoError> {
    let mut out = match format {
        TrajectoryFormat::Tum => tum_lines(path, text)?,
        TrajectoryFormat::Kitti => read_kitti(path, text)?,
        TrajectoryFormat::Euroc => read_euroc(path, text)?,
    };
    if out.is_empty() {
        return Err(IoError::Empty {
            path: path.into(),
            message: "no poses in trajectory file".into(),
        });
    }
    out.sort_by(|a, b| a.timestamp.total_cmp(&b.timestamp));
    Ok(out)
}

/// The time-stamp file of a KITTI trajectory: `<stem>.times.txt`, else `times.txt`, beside it.
pub fn kitti_times_path(path: &Path) -> PathBuf {
    let own = path.with_extension("times.txt");
    if own.is_file() {
        return own;
    }
    let shared = path.with_file_name("times.txt");
    if shared.is_file() {
        shared
    } else {
        own
    }
}

fn read_kitti(path: &Path, text: &str) -> Result<Vec<TimedPose>, IoError> {
    let times_path = kitti_times_path(path);
    let times_text = super::read_text(&times_path).map_err(|e| IoError::MissingFile {
        path: times_path.clone(),
        what: format!(
            "time stamps of the KITTI trajectory {} ({e})",
            path.display()
        ),
    })?;
    let mut times = Vec::new();
    for (i, l) in times_text.lines().enumerate() {
        let l = l.trim();
        if l.is_empty() || l.starts_with('#') {
            continue;
        }
        let t: f64 = l
            .parse()
            .ok()
            .filter(|t: &f64| t.is_finite())
            .ok_or_else(|| IoError::parse(&times_path, i + 1, format!("'{l}' is not a time")))?;
        times.push(t);
    }
    let mut out = Vec::new();
    for (i, l) in text.lines().enumerate() {
        let l = l.trim();
        if l.is_empty() || l.starts_with('#') {
            continue;
        }
        let v = parse_numbers(l).map_err(|m| IoError::parse(path, i + 1, m))?;
        if v.len() != 12 {
            return Err(IoError::parse(
                path,
                i + 1,
                format!(
                    "expected 12 numbers (a 3x4 matrix row by row), found {}",
                    v.len()
                ),
            ));
        }
        let r = DMat3::from_cols(
            DVec3::new(v[0], v[4], v[8]),
            DVec3::new(v[1], v[5], v[9]),
            DVec3::new(v[2], v[6], v[10]),
        );
        let det = r.determinant();
        if !(det > 0.5 && det < 2.0) {
            return Err(IoError::parse(
                path,
                i + 1,
                format!("the rotation block is not a rotation (determinant {det})"),
            ));
        }
        let Some(&timestamp) = times.get(out.len()) else {
            return Err(IoError::parse(
                path,
                i + 1,
                format!(
                    "pose {} has no time stamp ({} holds {})",
                    out.len() + 1,
                    times_path.display(),
                    times.len()
                ),
            ));
        };
        out.push(TimedPose {
            timestamp,
            world_from_camera: Se3::new(
                DQuat::from_mat3(&r).normalize(),
                DVec3::new(v[3], v[7], v[11]),
            ),
        });
    }
    Ok(out)
}

fn read_euroc(path: &Path, text: &str) -> Result<Vec<TimedPose>, IoError> {
    let mut out = Vec::new();
    for (i, l) in text.lines().enumerate() {
        let l = l.trim();
        if l.is_empty() || l.starts_with('#') {
            continue;
        }
        let f: Vec<&str> = l.split(',').map(str::trim).collect();
        if f.len() < 8 {
            return Err(IoError::parse(
                path,
                i + 1,
                format!(
                    "expected 8 comma-separated columns (timestamp [ns], p_x, p_y, p_z, q_w, q_x, q_y, q_z), found {}",
                    f.len()
                ),
            ));
        }
        let ns: i64 = f[0].parse().map_err(|_| {
            IoError::parse(
                path,
                i + 1,
                format!("time stamp '{}' is not integer nanoseconds", f[0]),
            )
        })?;
        let mut x = [0.0f64; 7];
        for (k, s) in f[1..8].iter().enumerate() {
            x[k] = s
                .parse()
                .ok()
                .filter(|v: &f64| v.is_finite())
                .ok_or_else(|| {
                    IoError::parse(
                        path,
                        i + 1,
                        format!("column {} '{s}' is not a finite number", k + 2),
                    )
                })?;
        }
        let q = DQuat::from_xyzw(x[4], x[5], x[6], x[3]);
        let n = q.length();
        if n <= 1e-6 {
            return Err(IoError::parse(path, i + 1, "quaternion has zero length"));
        }
        out.push(TimedPose {
            timestamp: ns as f64 * 1e-9,
            world_from_camera: Se3::new(q / n, DVec3::new(x[0], x[1], x[2])),
        });
    }
    Ok(out)
}

/// Writes a trajectory in `format` (overwrites `path`; KITTI also writes
/// `<stem>.times.txt` beside it).
pub fn write_trajectory(
    path: &Path,
    poses: &[TimedPose],
    format: TrajectoryFormat,
) -> Result<(), IoError> {
    let lines: Vec<String> = match format {
        TrajectoryFormat::Tum => return write_tum(path, poses),
        TrajectoryFormat::Kitti => {
            let times: Vec<String> = poses
                .iter()
                .map(|p| format!("{:.9}", p.timestamp))
                .collect();
            write_lines(&path.with_extension("times.txt"), &times)?;
            poses
                .iter()
                .map(|p| {
                    let m = p.world_from_camera.rotation_matrix();
                    let t = p.world_from_camera.translation;
                    let r = |i: usize| m.row(i);
                    let (a, b, c) = (r(0), r(1), r(2));
                    format!(
                        "{:.9e} {:.9e} {:.9e} {:.9e} {:.9e} {:.9e} {:.9e} {:.9e} {:.9e} {:.9e} {:.9e} {:.9e}",
                        a.x, a.y, a.z, t.x, b.x, b.y, b.z, t.y, c.x, c.y, c.z, t.z
                    )
                })
                .collect()
        }
        TrajectoryFormat::Euroc => std::iter::once(
            "#timestamp [ns],p_x [m],p_y [m],p_z [m],q_w [],q_x [],q_y [],q_z []".to_string(),
        )
        .chain(poses.iter().map(|p| {
            let t = p.world_from_camera.translation;
            let q = p.world_from_camera.rotation;
            format!(
                "{},{:.9},{:.9},{:.9},{:.9},{:.9},{:.9},{:.9}",
                (p.timestamp * 1e9).round() as i64,
                t.x,
                t.y,
                t.z,
                q.w,
                q.x,
                q.y,
                q.z
            )
        }))
        .collect(),
    };
    write_lines(path, &lines)
}

/// Writes `lines`, replacing `path` atomically (a temporary file beside it is renamed over it,
/// so `path` always holds a complete trajectory).
fn write_lines(path: &Path, lines: &[String]) -> Result<(), IoError> {
    super::write_atomic(path, |f| {
        for l in lines {
            writeln!(f, "{l}")?;
        }
        Ok(())
    })
}

/// Reads a TUM trajectory, sorted by time stamp. Errors name the file and line.
pub fn read_tum(path: &Path) -> Result<Vec<TimedPose>, IoError> {
    let text = super::read_text(path)?;
    read_trajectory_text(path, &text, TrajectoryFormat::Tum)
}

fn tum_lines(path: &Path, text: &str) -> Result<Vec<TimedPose>, IoError> {
    let mut out = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let s = line.trim();
        if s.is_empty() || s.starts_with('#') {
            continue;
        }
        out.push(parse_tum_line(s).map_err(|m| IoError::parse(path, i + 1, m))?);
    }
    Ok(out)
}

/// Writes a TUM trajectory, replacing `path` atomically.
pub fn write_tum(path: &Path, poses: &[TimedPose]) -> Result<(), IoError> {
    let lines: Vec<String> = poses.iter().map(format_tum_line).collect();
    write_lines(path, &lines)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::Se3;

    #[test]
    fn round_trip_and_errors() {
        let dir = std::env::temp_dir().join(format!("rgbid-traj-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join("t.txt");
        let poses = vec![TimedPose {
            timestamp: 1.5,
            world_from_camera: Se3::exp(&[0.1, 0.2, 0.3, 0.01, -0.02, 0.03]),
        }];
        write_tum(&p, &poses).unwrap();
        let back = read_tum(&p).unwrap();
        assert!(
            (back[0].world_from_camera.translation - poses[0].world_from_camera.translation)
                .length()
                < 1e-6
        );
        std::fs::write(&p, "# c\n1 2 3\n").unwrap();
        let e = read_tum(&p).unwrap_err().to_string();
        assert!(e.contains(":2:") && e.contains("expected 8"), "{e}");
        std::fs::write(&p, "1 0 0 nan 0 0 0 1\n").unwrap();
        assert!(read_tum(&p).unwrap_err().to_string().contains("not finite"));
        std::fs::write(&p, "").unwrap();
        assert!(matches!(read_tum(&p), Err(IoError::Empty { .. })));
    }

    #[test]
    fn formats_round_trip_and_are_detected() {
        let dir = tempfile::tempdir().unwrap();
        let poses: Vec<TimedPose> = (0..5)
            .map(|i| TimedPose {
                timestamp: 1_403_636_579.763_555_5 + 0.05 * i as f64,
                world_from_camera: Se3::exp(&[
                    0.1 * i as f64,
                    0.2,
                    -0.3,
                    0.01,
                    -0.02 * i as f64,
                    0.03,
                ]),
            })
            .collect();
        for (name, format) in [
            ("t.txt", TrajectoryFormat::Tum),
            ("t.kitti", TrajectoryFormat::Kitti),
            ("t.csv", TrajectoryFormat::Euroc),
        ] {
            let p = dir.path().join(name);
            write_trajectory(&p, &poses, TrajectoryFormat::from_extension(&p)).unwrap();
            let text = std::fs::read_to_string(&p).unwrap();
            assert_eq!(TrajectoryFormat::detect(&p, &text), format, "{name}");
            let back = read_trajectory(&p).unwrap();
            assert_eq!(back.len(), poses.len());
            for (a, b) in back.iter().zip(&poses) {
                assert!(
                    (a.timestamp - b.timestamp).abs() < 2e-6,
                    "{name}: {}",
                    a.timestamp - b.timestamp
                );
                let d = a.world_from_camera.inverse() * b.world_from_camera;
                assert!(d.translation.length() < 2e-6 && d.angle() < 2e-6, "{name}");
            }
        }
        // A KITTI file without its time stamps names the file it looked for.
        std::fs::remove_file(dir.path().join("t.times.txt")).unwrap();
        let e = read_trajectory(&dir.path().join("t.kitti"))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("t.times.txt") && e.contains("time stamps"),
            "{e}"
        );
        // EuRoC rows are checked column by column.
        let p = dir.path().join("bad.csv");
        std::fs::write(&p, "#timestamp\n1403636579763555584,1,2,3,1,0,0\n").unwrap();
        let e = read_trajectory(&p).unwrap_err().to_string();
        assert!(e.contains(":2:") && e.contains("found 7"), "{e}");
        std::fs::write(&p, "1.5,1,2,3,1,0,0,0\n").unwrap();
        let e = read_trajectory(&p).unwrap_err().to_string();
        assert!(e.contains("integer nanoseconds"), "{e}");
    }
}
