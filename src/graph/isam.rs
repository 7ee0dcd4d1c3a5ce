//! iSAM text pose graphs as distributed with the iSAM benchmark files:
//! `EDGE2 i j dx dy dtheta` + the 6 upper-triangular information entries row by row
//! (`I11 I12 I13 I22 I23 I33` over `(x, y, theta)`; `ODOMETRY` and `CONSTRAINT` are the same
//! layout) in 2D, and `EDGE3 i j x y z roll pitch yaw` + the 21 upper-triangular
//! information entries over `(x, y, z, roll, pitch, yaw)` in 3D, with
//! `R = Rz(yaw) Ry(pitch) Rx(roll)`. Optional `POSE2D id x y theta` / `POSE3D id x y z roll
//! pitch yaw` lines give initial values; otherwise the spanning tree initialises the graph.
//!
//! The orders are those of the files themselves, checked against the g2o conversions of the
//! same datasets in SE-Sync's `data/`: city10000's `50 0 0 50 0 100` is `diag(50, 50, 100)`
//! there (the TORO order `I11 I12 I22 I33 I13 I23` would make it indefinite), and
//! sphere2500's first edge `(-0.00306, 0.00822, 0.1802)` is the quaternion
//! `(-0.00189, 0.00396, 0.0900, 0.9959)` only as `Rz(0.1802) Ry(0.00822) Rx(-0.00306)`.
//! The numbers are information (not square-root information), as in those conversions.
//!
//! The information is converted to this crate's residual order: 2D `(x, y, theta)`, 3D
//! `(x, y, z, rx, ry, rz)` with the rotation vector about x, y, z (roll, pitch, yaw to first
//! order), so it is used as it stands.

use std::path::Path;

use glam::{DQuat, DVec3, EulerRot};

use super::g2o::{parse_f64s, parse_id, upper_to_full, G2oFile, RawGraph};
use super::Se2;
use crate::geometry::Se3;
use crate::io::IoError;

/// `Rz(yaw) Ry(pitch) Rx(roll)` from the file's `roll pitch yaw`.
fn rpy(roll: f64, pitch: f64, yaw: f64) -> DQuat {
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
                let info = upper_to_full(&v[3..], 3);
                raw.edges2
                    .push((i, j, Se2::new(v[0], v[1], v[2]), info, line));
            }
            "EDGE3" => {
                let i = parse_id(path, line, toks.get(1))?;
                let j = parse_id(path, line, toks.get(2))?;
                let v = parse_f64s(path, line, toks.get(3..).unwrap_or(&[]), 27, tag)?;
                let z = Se3::new(rpy(v[3], v[4], v[5]), DVec3::new(v[0], v[1], v[2]));
                let info = upper_to_full(&v[6..], 6);
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
                    Se3::new(rpy(v[3], v[4], v[5]), DVec3::new(v[0], v[1], v[2])),
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
    let text = crate::io::read_text(path)?;
    parse_isam(&text, path)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::graph::g2o::LoadedGraph;

    #[test]
    fn reads_2d_and_3d() {
        let t2 = "EDGE2 0 1 1 0 0 50 0 0 50 0 100\nODOMETRY 1 2 1 0 0 50 0 0 50 0 100\n";
        let f = parse_isam(t2, Path::new("a.txt")).unwrap();
        let LoadedGraph::Se2(g) = f.graph else {
            panic!("2D expected")
        };
        assert_eq!(g.poses.len(), 3);
        assert!((g.poses[2].x - 2.0).abs() < 1e-12);
        assert_eq!(g.edges[0].information[8], 100.0);
        let t3 = "EDGE3 0 1 1 0 0 0 0 0.3 10 0 0 0 0 0 10 0 0 0 0 10 0 0 0 100 0 0 100 0 25\n";
        let f = parse_isam(t3, Path::new("b.txt")).unwrap();
        let LoadedGraph::Se3(g) = f.graph else {
            panic!("3D expected")
        };
        // Roll info (100) on the x rotation, yaw info (25) on z.
        assert_eq!(g.edges[0].information[3 * 6 + 3], 100.0);
        assert_eq!(g.edges[0].information[5 * 6 + 5], 25.0);
        assert_eq!(g.edges[0].information[2 * 6 + 2], 10.0);
        let yaw = crate::geometry::so3_log(g.poses[1].rotation);
        assert!((yaw.z - 0.3).abs() < 1e-12);
    }

    /// The first edge of sphere2500 in iSAM text and in SE-Sync's g2o conversion.
    #[test]
    fn isam_angles_match_the_g2o_conversion() {
        let t = "EDGE3 0 1 0.341895 -0.0416997 0.0330394 -0.00305942 0.00822248 0.1802 \
                 10 0 0 0 0 0 10 0 0 0 0 10 0 0 0 100 0 0 100 0 25\n";
        let f = parse_isam(t, Path::new("s.txt")).unwrap();
        let LoadedGraph::Se3(g) = f.graph else {
            panic!("3D expected")
        };
        let q = g.edges[0].measurement.rotation;
        let expected = DQuat::from_xyzw(-0.00189341, 0.00395691, 0.0899835, 0.995934);
        assert!(q.dot(expected).abs() > 1.0 - 1e-10, "{q:?}");
    }

    #[test]
    fn malformed_line_is_reported() {
        let err = parse_isam(
            "EDGE2 0 1 1 0 0 50 0 0 50 0 100\nEDGE2 1 2 1 0\n",
            Path::new("m.txt"),
        )
        .unwrap_err();
        assert!(err.to_string().starts_with("m.txt:2:"), "{err}");
    }
}
