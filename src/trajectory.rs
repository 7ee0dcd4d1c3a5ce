//! Trajectory types: time-stamped poses (`world_from_camera`, metres, seconds) and the TUM line
//! format `timestamp tx ty tz qx qy qz qw` they are written in. Reading and writing files is in
//! `rgbid::io::trajectory` (the plumbing layer).

use glam::{DQuat, DVec3};

use crate::geometry::Se3;

/// A pose with its time stamp (seconds).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TimedPose {
    /// Time stamp in seconds.
    pub timestamp: f64,
    /// The camera's pose, `world_from_camera`.
    pub world_from_camera: Se3,
}

/// Parses one TUM trajectory line (no comment, not blank); the message says what is wrong.
pub fn parse_tum_line(line: &str) -> Result<TimedPose, String> {
    let v: Vec<&str> = line
        .split(|c: char| c.is_whitespace() || c == ',')
        .filter(|s| !s.is_empty())
        .collect();
    if v.len() < 8 {
        return Err(format!(
            "expected 8 numbers (timestamp tx ty tz qx qy qz qw), found {}",
            v.len()
        ));
    }
    let mut x = [0.0f64; 8];
    for (k, s) in v.iter().take(8).enumerate() {
        x[k] = s
            .parse::<f64>()
            .map_err(|_| format!("field {} '{}' is not a number", k + 1, s))?;
        if !x[k].is_finite() {
            return Err(format!("field {} is not finite ({})", k + 1, s));
        }
    }
    let q = DQuat::from_xyzw(x[4], x[5], x[6], x[7]);
    let n = q.length();
    if n.is_nan() || n <= 1e-6 {
        return Err("quaternion has zero length".into());
    }
    Ok(TimedPose {
        timestamp: x[0],
        world_from_camera: Se3::new(q / n, DVec3::new(x[1], x[2], x[3])),
    })
}

/// Formats one pose as a TUM line (without newline).
pub fn format_tum_line(p: &TimedPose) -> String {
    let t = p.world_from_camera.translation;
    let q = p.world_from_camera.rotation;
    format!(
        "{:.6} {:.7} {:.7} {:.7} {:.7} {:.7} {:.7} {:.7}",
        p.timestamp, t.x, t.y, t.z, q.x, q.y, q.z, q.w
    )
}
