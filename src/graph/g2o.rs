//! g2o pose-graph files: `VERTEX_SE2 id x y theta`, `EDGE_SE2 i j dx dy dtheta I11 I12 I13 I22
//! I23 I33`, `VERTEX_SE3:QUAT id x y z qx qy qz qw`, `EDGE_SE3:QUAT i j x y z qx qy qz qw` +
//! the 21 upper-triangular information entries (translation first), and `FIX id`.
//!
//! Vertices are `world_from_body`, edges `i_from_j`. Files without VERTEX lines get the
//! spanning-tree (odometry) estimate composed along the edges from the lowest id; a file with
//! VERTEX lines must declare every vertex its edges name (an undeclared one is an error at the
//! edge's line), and `FIX` must name an existing vertex. Vertices are stored sorted by id.
//! Malformed lines are errors with file:line.

use std::collections::{BTreeMap, BTreeSet};
use std::fmt::Write as _;
use std::path::Path;

use glam::{DQuat, DVec3};

use super::{GraphError, PoseGraph2, PoseGraph3, Se2};
use crate::geometry::Se3;
use crate::io::IoError;

/// A pose graph read from a file, 2D or 3D.
#[derive(Clone, Debug)]
pub enum LoadedGraph {
    /// SE(2) graph.
    Se2(PoseGraph2),
    /// SE(3) graph.
    Se3(PoseGraph3),
}

/// Parsed graph plus what the reader had to fill in.
#[derive(Clone, Debug)]
pub struct G2oFile {
    /// The graph.
    pub graph: LoadedGraph,
    /// True when some vertices had no VERTEX line and the spanning tree initialised them.
    pub spanning_tree_initialised: bool,
    /// Lines (1-based) whose information matrix was not positive definite and was made so
    /// by dropping its translation-rotation cross blocks (see [`repair_information`]); the
    /// cubicle benchmark has such edges.
    pub repaired_information: Vec<usize>,
}

pub(crate) fn parse_f64s(
    path: &Path,
    line: usize,
    toks: &[&str],
    n: usize,
    what: &str,
) -> Result<Vec<f64>, IoError> {
    if toks.len() != n {
        return Err(IoError::parse(
            path,
            line,
            format!("{what}: expected {n} numbers, found {}", toks.len()),
        ));
    }
    toks.iter()
        .map(|t| {
            t.parse::<f64>()
                .map_err(|_| IoError::parse(path, line, format!("{what}: '{t}' is not a number")))
                .and_then(|v| {
                    if v.is_finite() {
                        Ok(v)
                    } else {
                        Err(IoError::parse(
                            path,
                            line,
                            format!("{what}: non-finite value '{t}'"),
                        ))
                    }
                })
        })
        .collect()
}

pub(crate) fn parse_id(path: &Path, line: usize, t: Option<&&str>) -> Result<i64, IoError> {
    let t = t.ok_or_else(|| IoError::parse(path, line, "missing vertex id"))?;
    t.parse::<i64>()
        .map_err(|_| IoError::parse(path, line, format!("'{t}' is not an integer vertex id")))
}

pub(crate) fn quat(
    path: &Path,
    line: usize,
    x: f64,
    y: f64,
    z: f64,
    w: f64,
) -> Result<DQuat, IoError> {
    let q = DQuat::from_xyzw(x, y, z, w);
    let n = q.length();
    if !(n > 1e-9) {
        return Err(IoError::parse(path, line, "zero-norm quaternion"));
    }
    Ok(q / n)
}

pub(crate) fn upper_to_full(up: &[f64], d: usize) -> Vec<f64> {
    let mut m = vec![0.0; d * d];
    let mut k = 0;
    for r in 0..d {
        for c in r..d {
            m[r * d + c] = up[k];
            m[c * d + r] = up[k];
            k += 1;
        }
    }
    m
}

/// Intermediate representation shared by the g2o and iSAM readers.
#[derive(Default)]
pub(crate) struct RawGraph {
    pub vertices2: BTreeMap<i64, Se2>,
    pub vertices3: BTreeMap<i64, Se3>,
    pub edges2: Vec<(i64, i64, Se2, Vec<f64>, usize)>,
    pub edges3: Vec<(i64, i64, Se3, Vec<f64>, usize)>,
    /// FIX ids with the line of their FIX.
    pub fixed: BTreeMap<i64, usize>,
    pub first_vertex_line: BTreeMap<i64, usize>,
}

/// Makes an information matrix usable when it is not symmetric positive definite but its
/// translation block (first `dt` rows/columns) and rotation block (the rest) are: the
/// cross blocks are dropped (zeroed), which is what SE-Sync's isotropic weights assume
/// anyway. Returns `None` when even the diagonal blocks are not positive definite. The
/// input is returned unchanged when it is already positive definite.
pub fn repair_information(info: &[f64], dim: usize, dt: usize) -> Option<Vec<f64>> {
    use super::lie::cholesky_lower;
    if info.len() != dim * dim || info.iter().any(|v| !v.is_finite()) {
        return None;
    }
    let symmetric = (0..dim).all(|r| {
        (0..dim).all(|c| {
            let (a, b) = (info[r * dim + c], info[c * dim + r]);
            (a - b).abs() <= 1e-9 * a.abs().max(b.abs()).max(1.0)
        })
    });
    if symmetric && cholesky_lower(info, dim).is_some() {
        return Some(info.to_vec());
    }
    let mut m = info.to_vec();
    for r in 0..dim {
        for c in 0..dim {
            if (r < dt) != (c < dt) {
                m[r * dim + c] = 0.0;
            } else {
                let avg = 0.5 * (info[r * dim + c] + info[c * dim + r]);
                m[r * dim + c] = avg;
            }
        }
    }
    cholesky_lower(&m, dim).map(|_| m)
}

/// Vertices, edges and fixed ids of one dimension, as parsed.
struct RawPart<P> {
    vertices: BTreeMap<i64, P>,
    edges: Vec<(i64, i64, P, Vec<f64>, usize)>,
}

fn build_part<P: crate::graph::Pose>(
    part: RawPart<P>,
    fixed: &BTreeMap<i64, usize>,
    first_vertex_line: &BTreeMap<i64, usize>,
    path: &Path,
) -> Result<(crate::graph::PoseGraph<P>, bool, Vec<usize>), IoError> {
    let gerr = |line: usize, e: GraphError| IoError::parse(path, line, e.to_string());
    let mut ids: BTreeSet<i64> = part.vertices.keys().copied().collect();
    let before = ids.len();
    for (i, j, ..) in &part.edges {
        ids.insert(*i);
        ids.insert(*j);
    }
    let missing = ids.len() > before;
    if missing && before > 0 {
        // A file that declares vertices declares all of them: an edge to an undeclared one is
        // a typo, which the spanning-tree initialisation would otherwise hide by replacing
        // every declared pose.
        for (i, j, .., line) in &part.edges {
            for id in [i, j] {
                if !part.vertices.contains_key(id) {
                    return Err(IoError::parse(
                        path,
                        *line,
                        format!(
                            "edge {i} -> {j} names vertex {id}, which the file does not declare \
                             (a file with vertex lines must declare every vertex)"
                        ),
                    ));
                }
            }
        }
    }
    if ids.is_empty() {
        return Err(IoError::Empty {
            path: path.into(),
            message: "no vertices or edges".into(),
        });
    }
    let mut g = crate::graph::PoseGraph::<P>::new();
    for id in &ids {
        let p = part.vertices.get(id).copied().unwrap_or_else(P::identity);
        g.add_vertex(*id, p)
            .map_err(|e| gerr(first_vertex_line.get(id).copied().unwrap_or(0), e))?;
    }
    for (f, line) in fixed {
        match g.index_of(*f) {
            Some(k) => g.fixed[k] = true,
            None => {
                return Err(IoError::parse(
                    path,
                    *line,
                    format!("FIX names vertex {f}, which no vertex or edge of the file has"),
                ))
            }
        }
    }
    let dim = <P as crate::graph::Manifold>::DIM;
    let dt = if dim == 3 { 2 } else { 3 };
    let mut repaired = Vec::new();
    for (i, j, z, info, line) in part.edges {
        let info = match repair_information(&info, dim, dt) {
            Some(m) if m != info => {
                repaired.push(line);
                m
            }
            Some(m) => m,
            // Not repairable: let the graph report it with the edge's ids.
            None => info,
        };
        g.add_edge(i, j, z, info).map_err(|e| gerr(line, e))?;
    }
    if missing {
        g.initialize_spanning_tree().map_err(|e| IoError::Empty {
            path: path.into(),
            message: e.to_string(),
        })?;
    }
    Ok((g, missing, repaired))
}

impl RawGraph {
    pub(crate) fn build(self, path: &Path) -> Result<G2oFile, IoError> {
        let is3 = !self.vertices3.is_empty() || !self.edges3.is_empty();
        if is3 && (!self.vertices2.is_empty() || !self.edges2.is_empty()) {
            return Err(IoError::Empty {
                path: path.into(),
                message: "mixes 2D and 3D vertices/edges".into(),
            });
        }
        if is3 {
            let part = RawPart {
                vertices: self.vertices3,
                edges: self.edges3,
            };
            let (g, missing, repaired) =
                build_part(part, &self.fixed, &self.first_vertex_line, path)?;
            Ok(G2oFile {
                graph: LoadedGraph::Se3(g),
                spanning_tree_initialised: missing,
                repaired_information: repaired,
            })
        } else {
            let part = RawPart {
                vertices: self.vertices2,
                edges: self.edges2,
            };
            let (g, missing, repaired) =
                build_part(part, &self.fixed, &self.first_vertex_line, path)?;
            Ok(G2oFile {
                graph: LoadedGraph::Se2(g),
                spanning_tree_initialised: missing,
                repaired_information: repaired,
            })
        }
    }

    pub(crate) fn add_vertex2(
        &mut self,
        path: &Path,
        line: usize,
        id: i64,
        v: Se2,
    ) -> Result<(), IoError> {
        if self.vertices2.insert(id, v).is_some() {
            return Err(IoError::parse(
                path,
                line,
                format!("duplicate vertex id {id}"),
            ));
        }
        self.first_vertex_line.insert(id, line);
        Ok(())
    }
    pub(crate) fn add_vertex3(
        &mut self,
        path: &Path,
        line: usize,
        id: i64,
        v: Se3,
    ) -> Result<(), IoError> {
        if self.vertices3.insert(id, v).is_some() {
            return Err(IoError::parse(
                path,
                line,
                format!("duplicate vertex id {id}"),
            ));
        }
        self.first_vertex_line.insert(id, line);
        Ok(())
    }
}

/// Parses g2o text; `path` is only used in error messages.
pub fn parse_g2o(text: &str, path: &Path) -> Result<G2oFile, IoError> {
    let mut raw = RawGraph::default();
    for (ln, l) in text.lines().enumerate() {
        let line = ln + 1;
        let toks: Vec<&str> = l.split_whitespace().collect();
        let Some(&tag) = toks.first() else { continue };
        if tag.starts_with('#') {
            continue;
        }
        match tag {
            "VERTEX_SE2" => {
                let id = parse_id(path, line, toks.get(1))?;
                let v = parse_f64s(path, line, &toks[2..], 3, tag)?;
                raw.add_vertex2(path, line, id, Se2::new(v[0], v[1], v[2]))?;
            }
            "VERTEX_SE3:QUAT" => {
                let id = parse_id(path, line, toks.get(1))?;
                let v = parse_f64s(path, line, &toks[2..], 7, tag)?;
                let q = quat(path, line, v[3], v[4], v[5], v[6])?;
                raw.add_vertex3(path, line, id, Se3::new(q, DVec3::new(v[0], v[1], v[2])))?;
            }
            "EDGE_SE2" => {
                let i = parse_id(path, line, toks.get(1))?;
                let j = parse_id(path, line, toks.get(2))?;
                let v = parse_f64s(path, line, toks.get(3..).unwrap_or(&[]), 9, tag)?;
                raw.edges2.push((
                    i,
                    j,
                    Se2::new(v[0], v[1], v[2]),
                    upper_to_full(&v[3..], 3),
                    line,
                ));
            }
            "EDGE_SE3:QUAT" => {
                let i = parse_id(path, line, toks.get(1))?;
                let j = parse_id(path, line, toks.get(2))?;
                let v = parse_f64s(path, line, toks.get(3..).unwrap_or(&[]), 28, tag)?;
                let q = quat(path, line, v[3], v[4], v[5], v[6])?;
                raw.edges3.push((
                    i,
                    j,
                    Se3::new(q, DVec3::new(v[0], v[1], v[2])),
                    upper_to_full(&v[7..], 6),
                    line,
                ));
            }
            "FIX" => {
                for t in &toks[1..] {
                    raw.fixed.insert(parse_id(path, line, Some(t))?, line);
                }
            }
            other => {
                return Err(IoError::parse(
                    path,
                    line,
                    format!("unsupported g2o tag '{other}'"),
                ))
            }
        }
    }
    raw.build(path)
}

/// Reads a g2o file.
pub fn read_g2o(path: impl AsRef<Path>) -> Result<G2oFile, IoError> {
    let path = path.as_ref();
    let text = crate::io::read_text(path)?;
    parse_g2o(&text, path)
}

fn info_upper(info: &[f64], d: usize, out: &mut String) {
    for r in 0..d {
        for c in r..d {
            let _ = write!(out, " {}", info[r * d + c]);
        }
    }
}

/// g2o text of a 2D or 3D graph (vertices with their current poses, then edges).
pub fn format_g2o(graph: &LoadedGraph) -> String {
    let mut s = String::new();
    match graph {
        LoadedGraph::Se2(g) => {
            for (id, p) in g.ids.iter().zip(&g.poses) {
                let _ = writeln!(s, "VERTEX_SE2 {id} {} {} {}", p.x, p.y, p.theta);
            }
            for e in &g.edges {
                let z = e.measurement;
                let _ = write!(
                    s,
                    "EDGE_SE2 {} {} {} {} {}",
                    g.ids[e.from], g.ids[e.to], z.x, z.y, z.theta
                );
                info_upper(&e.information, 3, &mut s);
                s.push('\n');
            }
            for (id, f) in g.ids.iter().zip(&g.fixed) {
                if *f {
                    let _ = writeln!(s, "FIX {id}");
                }
            }
        }
        LoadedGraph::Se3(g) => {
            for (id, p) in g.ids.iter().zip(&g.poses) {
                let (t, q) = (p.translation, p.rotation);
                let _ = writeln!(
                    s,
                    "VERTEX_SE3:QUAT {id} {} {} {} {} {} {} {}",
                    t.x, t.y, t.z, q.x, q.y, q.z, q.w
                );
            }
            for e in &g.edges {
                let (t, q) = (e.measurement.translation, e.measurement.rotation);
                let _ = write!(
                    s,
                    "EDGE_SE3:QUAT {} {} {} {} {} {} {} {} {}",
                    g.ids[e.from], g.ids[e.to], t.x, t.y, t.z, q.x, q.y, q.z, q.w
                );
                info_upper(&e.information, 6, &mut s);
                s.push('\n');
            }
            for (id, f) in g.ids.iter().zip(&g.fixed) {
                if *f {
                    let _ = writeln!(s, "FIX {id}");
                }
            }
        }
    }
    s
}

/// Writes a graph as g2o.
pub fn write_g2o(path: impl AsRef<Path>, graph: &LoadedGraph) -> Result<(), IoError> {
    let path = path.as_ref();
    crate::io::write_atomic(path, |w| {
        use std::io::Write;
        w.write_all(format_g2o(graph).as_bytes())
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    const SMALL2: &str =
        "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0.1\nEDGE_SE2 0 1 1 0 0.1 10 0 0 10 0 100\n";

    /// An edge of the cubicle benchmark (line 5753): its z-roll and z-pitch couplings make
    /// the full matrix indefinite while both diagonal blocks are positive definite.
    #[test]
    fn indefinite_information_with_definite_blocks_is_repaired() {
        let line = "EDGE_SE3:QUAT 1 2 -0.000106623 0.000270013 0 0 0 0.000126644 1 2.46483e+06 \
                    5.3553e+06 0 0 0 0 1.52034e+07 0 0 0 0 10 84022.3 132748 0 10 0 0 10 0 91520.2\n";
        let f = parse_g2o(line, Path::new("c.g2o")).unwrap();
        assert_eq!(f.repaired_information, vec![1]);
        let LoadedGraph::Se3(g) = f.graph else {
            panic!("3D expected")
        };
        let m = &g.edges[0].information;
        assert_eq!(m[2 * 6 + 3], 0.0);
        assert_eq!(m[3 * 6 + 2], 0.0);
        assert_eq!(m[0], 2.46483e6);
        assert_eq!(m[5 * 6 + 5], 91520.2);
        // A matrix whose diagonal blocks are indefinite too is still an error with its line.
        let bad = "EDGE_SE2 0 1 1 0 0 1 5 0 1 0 1\n";
        let err = parse_g2o(bad, Path::new("d.g2o")).unwrap_err();
        assert!(err.to_string().starts_with("d.g2o:1:"), "{err}");
    }

    #[test]
    fn round_trip_2d() {
        let f = parse_g2o(SMALL2, Path::new("a.g2o")).unwrap();
        let text = format_g2o(&f.graph);
        let back = parse_g2o(&text, Path::new("b.g2o")).unwrap();
        let (LoadedGraph::Se2(a), LoadedGraph::Se2(b)) = (f.graph, back.graph) else {
            panic!("2D expected")
        };
        assert_eq!(a.ids, b.ids);
        assert_eq!(a.poses, b.poses);
        assert_eq!(a.edges[0].information, b.edges[0].information);
    }

    #[test]
    fn malformed_lines_report_file_and_line() {
        let cases = [
            ("VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 1 1 0\n", 2),
            ("VERTEX_SE2 0 0 0 x\n", 1),
            ("VERTEX_SE2 0 0 0 0\n\nVERTEX_SE2 0 1 1 1\n", 3),
            ("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 0\n", 1),
            ("VERTEX_SE3:QUAT 0 0 0 0 nan 0 0 1\n", 1),
            (
                "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 0 0 0\nEDGE_SE2 0 1 1 0 0 -1 0 0 1 0 1\n",
                3,
            ),
            ("BOGUS 1 2\n", 1),
        ];
        for (text, line) in cases {
            let err = parse_g2o(text, Path::new("f.g2o")).unwrap_err().to_string();
            assert!(
                err.starts_with(&format!("f.g2o:{line}:")),
                "{text:?} -> {err}"
            );
        }
    }

    #[test]
    fn missing_vertices_get_spanning_tree() {
        let text =
            "EDGE_SE2 0 1 1 0 1.5707963267948966 1 0 0 1 0 1\nEDGE_SE2 1 2 1 0 0 1 0 0 1 0 1\n";
        let f = parse_g2o(text, Path::new("t.g2o")).unwrap();
        assert!(f.spanning_tree_initialised);
        let LoadedGraph::Se2(g) = f.graph else {
            panic!("2D expected")
        };
        let p = g.poses[2];
        assert!((p.x - 1.0).abs() < 1e-12 && (p.y - 1.0).abs() < 1e-12);
    }

    #[test]
    fn undeclared_vertices_and_fixes_are_errors_with_their_line() {
        // An edge to a vertex the file does not declare (a typo: 7 for 1).
        let typo = "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nEDGE_SE2 0 7 1 0 0 1 0 0 1 0 1\n";
        let err = parse_g2o(typo, Path::new("t.g2o")).unwrap_err().to_string();
        assert!(
            err.starts_with("t.g2o:3:") && err.contains("vertex 7"),
            "{err}"
        );
        let fix = format!("{SMALL2}FIX 0\nFIX 5\n");
        let err = parse_g2o(&fix, Path::new("f.g2o")).unwrap_err().to_string();
        assert!(
            err.starts_with("f.g2o:5:") && err.contains("vertex 5"),
            "{err}"
        );
        let ok = parse_g2o(&format!("{SMALL2}FIX 1\n"), Path::new("f.g2o")).unwrap();
        let LoadedGraph::Se2(g) = ok.graph else {
            panic!("2D expected")
        };
        assert_eq!(g.fixed, vec![false, true]);
    }

    #[test]
    fn disconnected_file_is_an_error() {
        let text = "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\nEDGE_SE2 2 3 1 0 0 1 0 0 1 0 1\n";
        let err = parse_g2o(text, Path::new("d.g2o")).unwrap_err().to_string();
        assert!(err.contains("not connected"), "{err}");
    }
}
