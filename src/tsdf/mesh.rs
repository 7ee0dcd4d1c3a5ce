//! Meshes of the zero level set by marching tetrahedra: each voxel cube (corners at 8
//! neighbouring voxels, all observed) is split into six tetrahedra around its main diagonal
//! (the Kuhn split, identical in every cube, so faces match across cubes and blocks without a
//! case table); each tetrahedron gives zero, one or two triangles. Vertices on the same grid
//! edge are shared, normals are area-weighted face normals pointing to positive distance
//! (free space), colours are interpolated along the edge.
//!
//! The per-cube work (which tetrahedra cross the surface, the edge vertices' positions and
//! colours, each triangle's orientation) is [`cube_triangles`], the CPU mirror of
//! `shaders/tsdf_mesh.wgsl` (same f32 operations in the same order). Its output, triangles in
//! cube order with each vertex naming its grid edge, is turned into a [`Mesh`] by
//! [`assemble`] on the host for both backends: vertices shared by grid-edge key in that order,
//! then area-weighted normals.

use std::collections::HashMap;
use std::hash::BuildHasherDefault;

use bytemuck::{Pod, Zeroable};
use rayon::prelude::*;
use rustc_hash::FxHasher;

use super::integrate::Voxel;
use super::volume::VolumeView;
use super::BLOCK_SIDE;

/// A triangle mesh in the world frame.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Mesh {
    /// Vertex positions, world frame, metres.
    pub vertices: Vec<[f32; 3]>,
    /// Unit vertex normals, world frame, pointing out of the surface (towards free space).
    pub normals: Vec<[f32; 3]>,
    /// Vertex colours, 8-bit RGB.
    pub colours: Vec<[u8; 3]>,
    /// Triangles as vertex indices, counter-clockwise seen from the normals' side.
    pub triangles: Vec<[u32; 3]>,
}

impl Mesh {
    /// Writes the mesh as binary PLY with normals, colours and faces (overwrites `path`).
    pub fn write_ply(&self, path: &std::path::Path) -> Result<(), super::TsdfError> {
        crate::io::ply::write_mesh_ply(
            path,
            &self.vertices,
            &self.normals,
            &self.colours,
            &self.triangles,
        )?;
        Ok(())
    }
}

/// Uniform block of `tsdf_mesh.wgsl` (`Params`, same layout; a test compares them).
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
pub(crate) struct MeshUniform {
    /// Hash table entries minus one (a power of two minus one).
    pub(crate) table_mask: u32,
    /// Block slots the counting pass visits.
    pub(crate) blocks: u32,
    /// Rows of cubes the emitting pass visits.
    pub(crate) rows: u32,
    /// Voxel edge, m.
    pub(crate) voxel_size: f32,
}

/// One vertex of a cube's triangle, as `tsdf_mesh.wgsl` writes it (`CubeVertex`, same layout).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub(crate) struct CubeVertex {
    /// World frame, metres.
    pub(crate) position: [f32; 3],
    /// Colour `0x00BBGGRR` in bits 0-23; the grid edge as the cube corners it joins (bit 0 =
    /// +x, bit 1 = +y, bit 2 = +z): the lower corner in bits 24-26, the upper in bits 27-29.
    pub(crate) code: u32,
}

impl CubeVertex {
    /// The cube corners `(a, b)` of the vertex's edge (`a`'s bits a subset of `b`'s).
    pub(crate) fn edge(&self) -> (usize, usize) {
        (
            ((self.code >> 24) & 7) as usize,
            ((self.code >> 27) & 7) as usize,
        )
    }

    /// The vertex colour, 8-bit RGB.
    pub(crate) fn colour(&self) -> [u8; 3] {
        [
            self.code as u8,
            (self.code >> 8) as u8,
            (self.code >> 16) as u8,
        ]
    }
}

/// The per-cube output of marching tetrahedra over a volume.
#[derive(Clone, Debug, Default, PartialEq)]
pub(crate) struct CubeTriangles {
    /// The cubes that emit triangles, in traversal order (block after block in slot order,
    /// cubes in voxel order within a block): the global voxel coordinates of the cube's
    /// corner 0 and its number of triangles (1 to 12).
    pub(crate) cubes: Vec<([i32; 3], u32)>,
    /// Three vertices per triangle, cube after cube, counter-clockwise seen from free space.
    pub(crate) vertices: Vec<CubeVertex>,
}

/// Cubes per row of a block (a row runs along x); the kernel handles one row per invocation.
pub(crate) const ROW_CUBES: usize = BLOCK_SIDE;
/// Rows of cubes per block.
pub(crate) const BLOCK_ROWS: usize = BLOCK_SIDE * BLOCK_SIDE;

/// The six tetrahedra of a cube as corner indices (bit 0 = +x, bit 1 = +y, bit 2 = +z).
const TETRAHEDRA: [[usize; 4]; 6] = [
    [0, 1, 3, 7],
    [0, 1, 5, 7],
    [0, 2, 3, 7],
    [0, 2, 6, 7],
    [0, 4, 5, 7],
    [0, 4, 6, 7],
];

/// A vertex on the grid edge from voxel `g` in direction `kind` (a corner bit mask).
type EdgeKey = ([i32; 3], u8);

fn corner(c: usize) -> [i32; 3] {
    [(c & 1) as i32, ((c >> 1) & 1) as i32, ((c >> 2) & 1) as i32]
}

fn unpack(rgb: u32) -> [f32; 3] {
    [
        (rgb & 255) as f32,
        ((rgb >> 8) & 255) as f32,
        ((rgb >> 16) & 255) as f32,
    ]
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

fn dot(a: [f32; 3], b: [f32; 3]) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// Triangles a tetrahedron with `inside` of its 4 corners inside gives.
fn tet_triangles(inside: usize) -> u32 {
    match inside {
        1 | 3 => 1,
        2 => 2,
        _ => 0,
    }
}

/// Whether the triangle on the tetrahedron edges `tri` (corner pairs) faces from the corners
/// inside (`sum_in` of `n_in` corners) towards those outside, in exact integer arithmetic on
/// the edges' midpoints (doubled). A vertex lies strictly inside its edge or at the outside
/// end, and over that whole range the triangle's side never changes, so the midpoints decide
/// it for every crossing without rounding; a float test on the actual vertices would flip on
/// near-degenerate triangles, differently on the CPU and the GPU.
fn faces_outward(
    tri: &[(usize, usize); 3],
    sum_in: [i32; 3],
    n_in: i32,
    sum_out: [i32; 3],
    n_out: i32,
) -> bool {
    let m = tri.map(|(a, b)| {
        let (ca, cb) = (corner(a), corner(b));
        [ca[0] + cb[0], ca[1] + cb[1], ca[2] + cb[2]]
    });
    let u = [0, 1, 2].map(|k| m[1][k] - m[0][k]);
    let w = [0, 1, 2].map(|k| m[2][k] - m[0][k]);
    let n = [
        u[1] * w[2] - u[2] * w[1],
        u[2] * w[0] - u[0] * w[2],
        u[0] * w[1] - u[1] * w[0],
    ];
    let outward = [0, 1, 2].map(|k| sum_out[k] * n_in - sum_in[k] * n_out);
    n[0] * outward[0] + n[1] * outward[1] + n[2] * outward[2] > 0
}

/// The vertex on the edge from corner `a` to corner `b` (`a`'s bits a subset of `b`'s) of
/// the cube at global voxel `g` with corner voxels `v`.
fn edge_vertex(g: [i32; 3], v: &[Voxel; 8], a: usize, b: usize, voxel_size: f32) -> CubeVertex {
    let (sa, sb) = (v[a].tsdf, v[b].tsdf);
    let t = sa / (sa - sb);
    let ca = corner(a);
    let cb = corner(b);
    let pa = [g[0] + ca[0], g[1] + ca[1], g[2] + ca[2]];
    let position = [0, 1, 2].map(|k| (pa[k] as f32 + t * (cb[k] - ca[k]) as f32) * voxel_size);
    let (ka, kb) = (unpack(v[a].rgb), unpack(v[b].rgb));
    let c = [0, 1, 2].map(|k| {
        (ka[k] + t * (kb[k] - ka[k]) + 0.5)
            .floor()
            .clamp(0.0, 255.0) as u32
    });
    CubeVertex {
        position,
        code: c[0] | (c[1] << 8) | (c[2] << 16) | ((a as u32) << 24) | ((b as u32) << 27),
    }
}

/// Triangles of one cube with corner voxels `v` at global voxel `g`, appended to `out`
/// (three vertices each); returns how many. The CPU mirror of `cube_triangles` in
/// `tsdf_mesh.wgsl`.
fn cube(g: [i32; 3], v: &[Voxel; 8], voxel_size: f32, out: &mut Vec<CubeVertex>) -> u32 {
    let mut count = 0;
    for tet in TETRAHEDRA {
        let mut inside = [0usize; 4];
        let mut outside = [0usize; 4];
        let (mut n_in, mut n_out) = (0usize, 0usize);
        let (mut sum_in, mut sum_out) = ([0i32; 3], [0i32; 3]);
        for c in tet {
            let p = corner(c);
            if v[c].tsdf < 0.0 {
                inside[n_in] = c;
                n_in += 1;
                sum_in = [0, 1, 2].map(|k| sum_in[k] + p[k]);
            } else {
                outside[n_out] = c;
                n_out += 1;
                sum_out = [0, 1, 2].map(|k| sum_out[k] + p[k]);
            }
        }
        // Edges always run from the corner with fewer bits set (a Kuhn path adds bits).
        let e = |a: usize, b: usize| if a < b { (a, b) } else { (b, a) };
        let (i, o) = (inside, outside);
        let tris: [[(usize, usize); 3]; 2] = match n_in {
            1 => [[e(i[0], o[0]), e(i[0], o[1]), e(i[0], o[2])]; 2],
            3 => [[e(i[0], o[0]), e(i[1], o[0]), e(i[2], o[0])]; 2],
            _ => [
                [e(i[0], o[0]), e(i[0], o[1]), e(i[1], o[1])],
                [e(i[0], o[0]), e(i[1], o[1]), e(i[1], o[0])],
            ],
        };
        let n = tet_triangles(n_in) as usize;
        for mut tri in tris.into_iter().take(n) {
            if !faces_outward(&tri, sum_in, n_in as i32, sum_out, n_out as i32) {
                tri.swap(1, 2);
            }
            for (a, b) in tri {
                out.push(edge_vertex(g, v, a, b, voxel_size));
            }
            count += 1;
        }
    }
    count
}

/// The corner voxels of the cube at global voxel `g`, `None` when one is unallocated or
/// unobserved.
fn corners(view: &VolumeView<'_>, g: [i32; 3]) -> Option<[Voxel; 8]> {
    let mut v = [Voxel::default(); 8];
    for (c, vc) in v.iter_mut().enumerate() {
        let o = corner(c);
        match view.voxel([g[0] + o[0], g[1] + o[1], g[2] + o[2]]) {
            Some(found) if found.weight > 0.0 => *vc = *found,
            _ => return None,
        }
    }
    Some(v)
}

/// The triangles of every observed cube of the volume, cube by cube (the CPU mirror of
/// `tsdf_mesh.wgsl`).
pub(crate) fn cube_triangles(view: &VolumeView<'_>) -> CubeTriangles {
    let n = BLOCK_SIDE as i32;
    let voxel_size = view.voxel_size as f32;
    let per_block: Vec<CubeTriangles> = view
        .coords
        .par_iter()
        .map(|b| {
            let mut out = CubeTriangles::default();
            for z in 0..n {
                for y in 0..n {
                    for x in 0..n {
                        let g = [b[0] * n + x, b[1] * n + y, b[2] * n + z];
                        let Some(v) = corners(view, g) else {
                            continue;
                        };
                        let neg = v.iter().filter(|q| q.tsdf < 0.0).count();
                        if neg == 0 || neg == 8 {
                            continue;
                        }
                        let count = cube(g, &v, voxel_size, &mut out.vertices);
                        if count > 0 {
                            out.cubes.push((g, count));
                        }
                    }
                }
            }
            out
        })
        .collect();
    let mut all = CubeTriangles::default();
    for part in per_block {
        all.cubes.extend(part.cubes);
        all.vertices.extend(part.vertices);
    }
    all
}

/// The mesh of per-cube triangles: vertices shared by grid edge (the first vertex of an edge
/// in cube order gives its position and colour), area-weighted normals.
pub(crate) fn assemble(cubes: &CubeTriangles) -> Mesh {
    let mut mesh = Mesh::default();
    let mut index: HashMap<EdgeKey, u32, BuildHasherDefault<FxHasher>> = HashMap::default();
    let mut tris = cubes.vertices.chunks_exact(3);
    for &(g, count) in &cubes.cubes {
        for t in tris.by_ref().take(count as usize) {
            let mut ids = [0u32; 3];
            for (id, cv) in ids.iter_mut().zip(t) {
                let (a, b) = cv.edge();
                let ca = corner(a);
                let key = ([g[0] + ca[0], g[1] + ca[1], g[2] + ca[2]], (a ^ b) as u8);
                *id = *index.entry(key).or_insert_with(|| {
                    mesh.vertices.push(cv.position);
                    mesh.colours.push(cv.colour());
                    (mesh.vertices.len() - 1) as u32
                });
            }
            // The three edges of a triangle are distinct grid edges, so its ids differ.
            mesh.triangles.push(ids);
        }
    }
    let mut normals = vec![[0.0f32; 3]; mesh.vertices.len()];
    for t in &mesh.triangles {
        let p = t.map(|i| mesh.vertices[i as usize]);
        let n = cross(sub(p[1], p[0]), sub(p[2], p[0]));
        for &i in t {
            for k in 0..3 {
                normals[i as usize][k] += n[k];
            }
        }
    }
    for n in &mut normals {
        let l = dot(*n, *n).sqrt();
        if l > 0.0 {
            *n = n.map(|c| c / l);
        }
    }
    mesh.normals = normals;
    mesh
}

/// The mesh of every observed cube of the volume, on the CPU.
#[cfg(test)]
pub(crate) fn extract(view: &VolumeView<'_>) -> Mesh {
    assemble(&cube_triangles(view))
}
#[cfg(test)]
mod tests {
    use std::borrow::Cow;
    use std::collections::HashMap;

    use rand::{Rng, SeedableRng};

    use super::super::integrate::{local_index, Voxel};
    use super::super::volume::{BlockMap, VolumeView};
    use super::super::{BLOCK_SIDE, BLOCK_VOXELS};
    use super::{corner, cube, extract, CubeVertex, MeshUniform, TETRAHEDRA};
    use crate::gpu::{host_layout, layout_mismatches, shaders};

    #[test]
    fn mesh_uniform_and_vertex_match_the_wgsl_layout() {
        let src = shaders::assembled("tsdf_mesh.wgsl").unwrap_or_default();
        let host = host_layout!(MeshUniform {
            table_mask,
            blocks,
            rows,
            voxel_size,
        });
        let mut bad = layout_mismatches(&src, "Params", &host, std::mem::size_of::<MeshUniform>());
        let host = host_layout!(CubeVertex { position, code });
        bad.extend(layout_mismatches(
            &src,
            "CubeVertex",
            &host,
            std::mem::size_of::<CubeVertex>(),
        ));
        assert!(bad.is_empty(), "{}", bad.join("\n"));
    }

    /// Over random cubes (distances of either sign, some exactly zero), every triangle that
    /// the integer side test oriented faces from its tetrahedron's inside corners to its
    /// outside ones when measured on the actual vertices, wherever that measure is not lost
    /// in rounding (a near-degenerate triangle).
    #[test]
    fn triangle_sides_from_edge_midpoints_match_every_crossing() {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(7);
        let mut checked = 0usize;
        let mut by_count = [0usize; 4];
        for _ in 0..20_000 {
            let mut v = [Voxel::default(); 8];
            for q in &mut v {
                q.weight = 1.0;
                q.tsdf = if rng.random_bool(0.1) {
                    0.0
                } else {
                    rng.random_range(-1.0f32..1.0)
                };
            }
            let mut out: Vec<CubeVertex> = Vec::new();
            let n = cube([3, -2, 5], &v, 1.0, &mut out);
            assert_eq!(out.len(), 3 * n as usize);
            for t in out.chunks_exact(3) {
                // The tetrahedron is the set of corners the three edges join.
                let mut corners: Vec<usize> = t
                    .iter()
                    .flat_map(|cv| {
                        let (a, b) = cv.edge();
                        [a, b]
                    })
                    .collect();
                corners.sort_unstable();
                corners.dedup();
                assert_eq!(corners.len(), 4, "{t:?}");
                assert!(TETRAHEDRA
                    .iter()
                    .any(|tet| tet.as_slice() == corners.as_slice()));
                let inside: Vec<usize> = corners
                    .iter()
                    .copied()
                    .filter(|&c| v[c].tsdf < 0.0)
                    .collect();
                by_count[inside.len()] += 1;
                let centre = |cs: Vec<usize>| {
                    let k = cs.len() as f64;
                    cs.iter().fold([0.0f64; 3], |s, &c| {
                        let p = corner(c);
                        [0, 1, 2].map(|i| s[i] + f64::from(p[i]) / k)
                    })
                };
                let outside: Vec<usize> = corners
                    .iter()
                    .copied()
                    .filter(|&c| !(v[c].tsdf < 0.0))
                    .collect();
                let (ci, co) = (centre(inside), centre(outside));
                let outward = [0, 1, 2].map(|i| co[i] - ci[i]);
                let p = [0, 1, 2].map(|k| t[k].position.map(f64::from));
                let u = [0, 1, 2].map(|i| p[1][i] - p[0][i]);
                let w = [0, 1, 2].map(|i| p[2][i] - p[0][i]);
                let nrm = [
                    u[1] * w[2] - u[2] * w[1],
                    u[2] * w[0] - u[0] * w[2],
                    u[0] * w[1] - u[1] * w[0],
                ];
                let d: f64 = (0..3).map(|i| nrm[i] * outward[i]).sum();
                if d.abs() > 1e-6 {
                    assert!(d > 0.0, "triangle {t:?} faces inwards ({d})");
                    checked += 1;
                }
            }
        }
        assert!(checked > 50_000, "{checked} triangles checked");
        assert!(
            by_count[1] > 0 && by_count[2] > 0 && by_count[3] > 0,
            "{by_count:?}"
        );
    }

    /// A volume of 3^3 blocks holding the exact signed distance of a sphere (voxels of
    /// `voxel` m, centre and radius in metres), all voxels observed.
    fn sphere_volume(
        voxel: f64,
        centre: [f64; 3],
        radius: f64,
    ) -> (Vec<Voxel>, BlockMap, Vec<[i32; 3]>) {
        let mut map = BlockMap::default();
        let mut coords = Vec::new();
        let mut voxels = Vec::new();
        let n = BLOCK_SIDE as i32;
        for bz in 0..3 {
            for by in 0..3 {
                for bx in 0..3 {
                    map.insert([bx, by, bz], coords.len() as u32);
                    coords.push([bx, by, bz]);
                    let mut block = vec![Voxel::default(); BLOCK_VOXELS];
                    for z in 0..BLOCK_SIDE {
                        for y in 0..BLOCK_SIDE {
                            for x in 0..BLOCK_SIDE {
                                let g = [bx * n + x as i32, by * n + y as i32, bz * n + z as i32];
                                let d = (0..3)
                                    .map(|k| (f64::from(g[k]) * voxel - centre[k]).powi(2))
                                    .sum::<f64>()
                                    .sqrt()
                                    - radius;
                                block[local_index(x, y, z)] = Voxel {
                                    tsdf: d as f32,
                                    weight: 1.0,
                                    rgb: 0x00_30_20_10,
                                };
                            }
                        }
                    }
                    voxels.extend(block);
                }
            }
        }
        (voxels, map, coords)
    }

    #[test]
    fn sphere_mesh_is_closed_consistently_oriented_and_on_the_surface() {
        let voxel = 0.01;
        let centre = [0.121, 0.117, 0.124];
        let radius = 0.07;
        let (voxels, map, coords) = sphere_volume(voxel, centre, radius);
        let view = VolumeView {
            voxels: Cow::Owned(voxels),
            map: &map,
            coords: &coords,
            voxel_size: voxel,
        };
        let mesh = extract(&view);
        assert!(
            mesh.triangles.len() > 500,
            "{} triangles",
            mesh.triangles.len()
        );
        // Closed and consistently oriented: every directed edge once, its reverse once.
        let mut directed: HashMap<(u32, u32), usize> = HashMap::new();
        for t in &mesh.triangles {
            for k in 0..3 {
                *directed.entry((t[k], t[(k + 1) % 3])).or_default() += 1;
            }
        }
        for (&(a, b), &count) in &directed {
            assert_eq!(count, 1, "directed edge {a}-{b} used {count} times");
            assert_eq!(directed.get(&(b, a)), Some(&1), "edge {a}-{b} has no twin");
        }
        // Vertices within a small fraction of a voxel of the sphere (linear interpolation
        // of an exact distance field), normals pointing outwards, colours carried over.
        for ((v, n), c) in mesh.vertices.iter().zip(&mesh.normals).zip(&mesh.colours) {
            let r: Vec<f64> = (0..3).map(|k| f64::from(v[k]) - centre[k]).collect();
            let len = r.iter().map(|x| x * x).sum::<f64>().sqrt();
            assert!(
                (len - radius).abs() < 0.1 * voxel,
                "vertex {v:?} at {len} m"
            );
            let cos = (0..3).map(|k| r[k] * f64::from(n[k])).sum::<f64>() / len;
            assert!(cos > 0.95, "normal {n:?} at {v:?}: cos {cos}");
            assert_eq!(*c, [0x10, 0x20, 0x30]);
        }
    }

    #[test]
    fn unobserved_voxels_give_no_faces() {
        let (mut voxels, map, coords) = sphere_volume(0.01, [0.12, 0.12, 0.12], 0.07);
        for v in &mut voxels {
            v.weight = 0.0;
        }
        let view = VolumeView {
            voxels: Cow::Owned(voxels),
            map: &map,
            coords: &coords,
            voxel_size: 0.01,
        };
        assert!(extract(&view).triangles.is_empty());
    }
}
