//! TUM trajectory files: one pose per line, `timestamp tx ty tz qx qy qz qw`, the pose being
//! `world_from_camera` (metres, unit quaternion); `#` starts a comment.

use std::io::Write;
use std::path::Path;

use super::IoError;
use crate::trajectory::{format_tum_line, parse_tum_line, TimedPose};

/// Reads a TUM trajectory, sorted by time stamp. Errors name the file and line.
pub fn read_tum(path: &Path) -> Result<Vec<TimedPose>, IoError> {
    let text = super::read_text(path)?;
    let mut out = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let s = line.trim();
        if s.is_empty() || s.starts_with('#') {
            continue;
        }
        out.push(parse_tum_line(s).map_err(|m| IoError::parse(path, i + 1, m))?);
    }
    if out.is_empty() {
        return Err(IoError::Empty {
            path: path.into(),
            message: "no poses in trajectory file".into(),
        });
    }
    out.sort_by(|a, b| a.timestamp.total_cmp(&b.timestamp));
    Ok(out)
}

/// Writes a TUM trajectory, replacing `path` atomically (a temporary file beside it is
/// renamed over it, so `path` always holds a complete trajectory).
pub fn write_tum(path: &Path, poses: &[TimedPose]) -> Result<(), IoError> {
    super::write_atomic(path, |f| {
        for p in poses {
            writeln!(f, "{}", format_tum_line(p))?;
        }
        Ok(())
    })
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
}
