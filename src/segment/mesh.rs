//! Triangle meshes of a keyframe (thesis 5.3.1): grid triangulation of a depth map, Delaunay
//! triangulation of a point cloud (`spade`), vertex normals averaged from incident
//! triangles, mesh-edge graphs for segmentation, and projection of mesh segments into an
//! image.

use spade::{DelaunayTriangulation, HasPosition, Point2, Triangulation};

use super::graph::{convexity_weight, Edge, NO_SEGMENT};
use super::SegmentError;
use crate::camera::PinholeCamera;
use crate::geometry::Se3;
use crate::image::ImageF32;

/// A triangle mesh in the frame of its points (metres).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct TriMesh {
    /// Vertex positions, metres.
    pub vertices: Vec<[f32; 3]>,
    /// Triangles as vertex index triples.
    pub triangles: Vec<[u32; 3]>,
    /// Unit vertex normals (see [`TriMesh::compute_vertex_normals`]); zero for vertices
    /// without triangles. Empty until computed.
    pub normals: Vec<[f32; 3]>,
    /// For grid meshes: the pixel index of every vertex; empty otherwise.
    pub pixel_of_vertex: Vec<u32>,
}

fn sub(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn cross(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}
fn norm(a: [f32; 3]) -> f32 {
    (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt()
}

impl TriMesh {
    /// Vertex normals: the normalised mean of the unit normals of incident triangles, each
    /// triangle oriented to face `viewpoint` (the camera centre in the mesh frame, metres).
    pub fn compute_vertex_normals(&mut self, viewpoint: [f32; 3]) {
        let mut acc = vec![[0.0f32; 3]; self.vertices.len()];
        for t in &self.triangles {
            let [a, b, c] = t.map(|i| self.vertices[i as usize]);
            let mut n = cross(sub(b, a), sub(c, a));
            let l = norm(n);
            if !(l > 0.0) {
                continue;
            }
            let to_view = sub(viewpoint, a);
            let s = if n[0] * to_view[0] + n[1] * to_view[1] + n[2] * to_view[2] < 0.0 {
                -1.0 / l
            } else {
                1.0 / l
            };
            n = n.map(|v| v * s);
            for &i in t {
                let e = &mut acc[i as usize];
                e[0] += n[0];
                e[1] += n[1];
                e[2] += n[2];
            }
        }
        self.normals = acc
            .into_iter()
            .map(|n| {
                let l = norm(n);
                if l > 0.0 {
                    n.map(|v| v / l)
                } else {
                    [0.0; 3]
                }
            })
            .collect();
    }

    /// The unique undirected edges of the mesh, `a < b`, sorted.
    pub fn edges(&self) -> Vec<(u32, u32)> {
        let mut e: Vec<(u32, u32)> = self
            .triangles
            .iter()
            .flat_map(|t| [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])])
            .map(|(a, b)| if a < b { (a, b) } else { (b, a) })
            .collect();
        e.sort_unstable();
        e.dedup();
        e
    }

    /// Mesh edges weighted by [`convexity_weight`] (needs vertex normals).
    pub(crate) fn weighted_edges(&self) -> Vec<Edge> {
        self.edges()
            .into_iter()
            .filter_map(|(a, b)| {
                let (na, nb) = (
                    *self.normals.get(a as usize)?,
                    *self.normals.get(b as usize)?,
                );
                let w =
                    convexity_weight(self.vertices[a as usize], na, self.vertices[b as usize], nb);
                Some(Edge { w, a, b })
            })
            .collect()
    }
}

/// Grid triangulation of an inverse-depth map (1/m, 0 = invalid): one vertex per valid pixel
/// (camera frame), two triangles per 2x2 block whose four pixels are valid and whose inverse
/// depths differ by at most `max_jump` of the largest (relative), so depth discontinuities
/// are not bridged. Vertex normals are computed facing the camera.
pub fn triangulate_depth(
    inverse_depth: &ImageF32,
    camera: &PinholeCamera,
    max_jump: f32,
) -> TriMesh {
    let (w, h) = (inverse_depth.width, inverse_depth.height);
    let points = super::normals::points_from_inverse_depth(inverse_depth, camera);
    let mut index = vec![u32::MAX; w * h];
    let mut mesh = TriMesh::default();
    for i in 0..w * h {
        let r = inverse_depth.data[i];
        if r > 0.0 && r.is_finite() {
            index[i] = mesh.vertices.len() as u32;
            mesh.vertices.push(points[i]);
            mesh.pixel_of_vertex.push(i as u32);
        }
    }
    for y in 0..h.saturating_sub(1) {
        for x in 0..w.saturating_sub(1) {
            let q = [
                y * w + x,
                y * w + x + 1,
                (y + 1) * w + x,
                (y + 1) * w + x + 1,
            ];
            if q.iter().any(|&i| index[i] == u32::MAX) {
                continue;
            }
            let r = q.map(|i| inverse_depth.data[i]);
            let (lo, hi) = r
                .iter()
                .fold((f32::MAX, 0.0f32), |(l, hh), &v| (l.min(v), hh.max(v)));
            if hi - lo > max_jump * hi {
                continue;
            }
            let v = q.map(|i| index[i]);
            mesh.triangles.push([v[0], v[2], v[1]]);
            mesh.triangles.push([v[1], v[2], v[3]]);
        }
    }
    mesh.compute_vertex_normals([0.0; 3]);
    mesh
}

struct Projected {
    pos: Point2<f64>,
    idx: u32,
}

impl HasPosition for Projected {
    type Scalar = f64;
    fn position(&self) -> Point2<f64> {
        self.pos
    }
}

/// Delaunay triangulation (with `spade`) of a point cloud in a camera frame (metres): points
/// in front of the camera (`z > 0`) are triangulated on the normalised image plane
/// `(x/z, y/z)` (a 2.5D mesh as seen from the camera), and triangles with an edge longer than
/// `max_edge_ratio` times the triangle's mean depth are dropped (they bridge gaps between
/// surfaces). Vertex normals are computed facing the camera. Points behind the camera stay
/// in `vertices` without triangles.
pub fn triangulate_points(
    points: &[[f32; 3]],
    max_edge_ratio: f32,
) -> Result<TriMesh, SegmentError> {
    let proj: Vec<Projected> = points
        .iter()
        .enumerate()
        .filter(|(_, p)| p[2] > 1e-6 && p.iter().all(|v| v.is_finite()))
        .map(|(i, p)| Projected {
            pos: Point2::new(f64::from(p[0] / p[2]), f64::from(p[1] / p[2])),
            idx: i as u32,
        })
        .collect();
    let tri: DelaunayTriangulation<Projected> = DelaunayTriangulation::bulk_load(proj)
        .map_err(|e| SegmentError::Triangulation(format!("{e:?}")))?;
    let mut mesh = TriMesh {
        vertices: points.to_vec(),
        ..TriMesh::default()
    };
    for f in tri.inner_faces() {
        let v = f.vertices().map(|v| v.data().idx);
        let p = v.map(|i| points[i as usize]);
        let mean_z = (p[0][2] + p[1][2] + p[2][2]) / 3.0;
        let longest = norm(sub(p[0], p[1]))
            .max(norm(sub(p[1], p[2])))
            .max(norm(sub(p[2], p[0])));
        if longest <= max_edge_ratio * mean_z {
            mesh.triangles.push(v);
        }
    }
    mesh.compute_vertex_normals([0.0; 3]);
    Ok(mesh)
}

/// Projects labelled mesh triangles into an image with a z-buffer: each pixel centre covered
/// by a triangle gets the label of the triangle's vertex with the largest barycentric weight
/// (`NO_SEGMENT` where nothing is visible). `camera_from_mesh` maps mesh points into the
/// camera frame.
pub fn project_labels(
    mesh: &TriMesh,
    labels: &[u32],
    camera: &PinholeCamera,
    camera_from_mesh: &Se3,
) -> Vec<u32> {
    let (w, h) = (camera.width as usize, camera.height as usize);
    let mut out = vec![NO_SEGMENT; w * h];
    let mut zbuf = vec![f64::INFINITY; w * h];
    let cam_pts: Vec<Option<(f64, f64, f64)>> = mesh
        .vertices
        .iter()
        .map(|p| {
            let q = *camera_from_mesh
                * glam::DVec3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]));
            camera.project(q).map(|uv| (uv.x, uv.y, q.z))
        })
        .collect();
    for t in &mesh.triangles {
        let (Some(a), Some(b), Some(c)) = (
            cam_pts[t[0] as usize],
            cam_pts[t[1] as usize],
            cam_pts[t[2] as usize],
        ) else {
            continue;
        };
        let area = (b.0 - a.0) * (c.1 - a.1) - (c.0 - a.0) * (b.1 - a.1);
        if area.abs() < 1e-12 {
            continue;
        }
        let x0 = a.0.min(b.0).min(c.0).ceil().max(0.0) as usize;
        let x1 = a.0.max(b.0).max(c.0).floor().min(w as f64 - 1.0);
        let y0 = a.1.min(b.1).min(c.1).ceil().max(0.0) as usize;
        let y1 = a.1.max(b.1).max(c.1).floor().min(h as f64 - 1.0);
        if x1 < 0.0 || y1 < 0.0 {
            continue;
        }
        let (x1, y1) = (x1 as usize, y1 as usize);
        for y in y0..=y1 {
            for x in x0..=x1 {
                let (px, py) = (x as f64, y as f64);
                let wa = ((b.0 - px) * (c.1 - py) - (c.0 - px) * (b.1 - py)) / area;
                let wb = ((c.0 - px) * (a.1 - py) - (a.0 - px) * (c.1 - py)) / area;
                let wc = 1.0 - wa - wb;
                if wa < -1e-9 || wb < -1e-9 || wc < -1e-9 {
                    continue;
                }
                // Perspective-correct depth: interpolate inverse depth.
                let iz = wa / a.2 + wb / b.2 + wc / c.2;
                let z = 1.0 / iz;
                let i = y * w + x;
                if z < zbuf[i] {
                    zbuf[i] = z;
                    let k = if wa >= wb && wa >= wc {
                        0
                    } else if wb >= wc {
                        1
                    } else {
                        2
                    };
                    out[i] = labels.get(t[k] as usize).copied().unwrap_or(NO_SEGMENT);
                }
            }
        }
    }
    out
}
