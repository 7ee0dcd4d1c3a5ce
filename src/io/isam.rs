//! iSAM text pose graphs: `EDGE2 i j dx dy dtheta I11 I12 I22 I33 I13 I23` (also `ODOMETRY`
//! and `CONSTRAINT` with the same layout) in 2D, `EDGE3 i j x y z yaw pitch roll` + the 21
//! upper-triangular information entries over `(x, y, z, yaw, pitch, roll)` in 3D, with
//! `R = Rz(yaw) Ry(pitch) Rx(roll)`. Optional `POSE2D id x y theta` / `POSE3D id x y z yaw
//! pitch roll` lines give initial values; otherwise the spanning tree initialises the graph.
//!
//! The information is converted to this crate's residual order: 2D `(x, y, theta)`, 3D
//! `(x, y, z, rx, ry, rz)` with the rotation vector about x, y, z (roll, pitch, yaw to first
//! order).

use std::path::Path;

use glam::{DQuat, DVec3, EulerRot};

use super::g2o::{parse_f64s, parse_id, upper_to_full, G2oFile, RawGraph};
use super::IoError;
use crate::geometry::Se3;
use crate::graph::Se2;

fn ypr(yaw: f64, pitch: f64, roll: f64) -> DQuat {
    DQuat::from_euler(EulerRot::ZYX, yaw, pitch, roll)
}

/// Parses iSAM text; `path` is only used in error messages.
pub fn parse_isam(text: &str, path: &Path) -> Result<G2oFile, IoError> {
    let mut raw = RawGraph::default();
    for (ln, l) in text.lines().enumerate() {
        let line = ln + 1;
        let toks: Vec<&str> = l.split_whitespace().collect();
        let Some(&tag) = toks.first() else { continue };
        if tag.starts_with('#') {
            continue;
        }
        match tag {
            "EDGE2" | "ODOMETRY" | "CONSTRAINT" => {
                let i = parse_id(path, line, toks.get(1))?;
                let j = parse_id(path, line, toks.get(2))?;
                let v = parse_f64s(path, line, toks.get(3..).unwrap_or(&[]), 9, tag)?;
                // I11 I12 I22 I33 I13 I23
                let (i11, i12, i22, i33, i13, i23) = (v[3], v[4], v[5], v[6], v[7], v[8]);
                let info = vec![i11, i12, i13, i12, i22, i23, i13, i23, i33];
                raw.edges2
                    .push((i, j, Se2::new(v[0], v[1], v[2]), info, line));
            }
            "EDGE3" => {
                let i = parse_id(path, line, toks.get(1))?;
                let j = parse_id(path, line, toks.get(2))?;
                let v = parse_f64s(path, line, toks.get(3..).unwrap_or(&[]), 27, tag)?;
                let z = Se3::new(ypr(v[3], v[4], v[5]), DVec3::new(v[0], v[1], v[2]));
                let full = upper_to_full(&v[6..], 6);
                // isam order (x y z yaw pitch roll) -> ours (x y z roll pitch yaw).
                let perm = [0usize, 1, 2, 5, 4, 3];
                let mut info = vec![0.0; 36];
                for r in 0..6 {
                    for c in 0..6 {
                        info[r * 6 + c] = full[perm[r] * 6 + perm[c]];
                    }
                }
                raw.edges3.push((i, j, z, info, line));
            }
            "POSE2D" | "VERTEX2" => {
                let id = parse_id(path, line, toks.get(1))?;
                let v = parse_f64s(path, line, &toks[2..], 3, tag)?;
                raw.add_vertex2(path, line, id, Se2::new(v[0], v[1], v[2]))?;
            }
            "POSE3D" | "VERTEX3" => {
                let id = parse_id(path, line, toks.get(1))?;
                let v = parse_f64s(path, line, &toks[2..], 6, tag)?;
                raw.add_vertex3(
                    path,
                    line,
                    id,
                    Se3::new(ypr(v[3], v[4], v[5]), DVec3::new(v[0], v[1], v[2])),
                )?;
            }
            other => {
                return Err(IoError::parse(
                    path,
                    line,
                    format!("unsupported iSAM tag '{other}'"),
                ))
            }
        }
    }
    raw.build(path)
}

/// Reads an iSAM text file.
pub fn read_isam(path: impl AsRef<Path>) -> Result<G2oFile, IoError> {
    let path = path.as_ref();
    let text = std::fs::read_to_string(path).map_err(|e| IoError::file(path, e))?;
    parse_isam(&text, path)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::g2o::LoadedGraph;

    #[test]
    fn reads_2d_and_3d() {
        let t2 = "EDGE2 0 1 1 0 0 50 0 50 100 0 0\nODOMETRY 1 2 1 0 0 50 0 50 100 0 0\n";
        let f = parse_isam(t2, Path::new("a.txt")).unwrap();
        let LoadedGraph::Se2(g) = f.graph else {
            panic!("2D expected")
        };
        assert_eq!(g.poses.len(), 3);
        assert!((g.poses[2].x - 2.0).abs() < 1e-12);
        assert_eq!(g.edges[0].information[8], 100.0);
        let t3 = "EDGE3 0 1 1 0 0 0.3 0 0 10 0 0 0 0 0 10 0 0 0 0 10 0 0 0 100 0 0 100 0 25\n";
        let f = parse_isam(t3, Path::new("b.txt")).unwrap();
        let LoadedGraph::Se3(g) = f.graph else {
            panic!("3D expected")
        };
        // yaw info (100) lands on the z rotation, roll info (25) on x.
        assert_eq!(g.edges[0].information[5 * 6 + 5], 100.0);
        assert_eq!(g.edges[0].information[3 * 6 + 3], 25.0);
        let yaw = crate::geometry::so3_log(g.poses[1].rotation);
        assert!((yaw.z - 0.3).abs() < 1e-12);
    }

    #[test]
    fn malformed_line_is_reported() {
        let err = parse_isam(
            "EDGE2 0 1 1 0 0 50 0 50 100 0 0\nEDGE2 1 2 1 0\n",
            Path::new("m.txt"),
        )
        .unwrap_err();
        assert!(err.to_string().starts_with("m.txt:2:"), "{err}");
    }
}
