//! Meshes of the zero level set by marching tetrahedra: each voxel cube (corners at 8
//! neighbouring voxels, all observed) is split into six tetrahedra around its main diagonal
//! (the Kuhn split, identical in every cube, so faces match across cubes and blocks without a
//! case table); each tetrahedron gives zero, one or two triangles. Vertices on the same grid
//! edge are shared, normals are area-weighted face normals pointing to positive distance
//! (free space), colours are interpolated along the edge.

use std::collections::HashMap;
use std::hash::BuildHasherDefault;

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

struct EdgeVertex {
    key: EdgeKey,
    position: [f32; 3],
    colour: [f32; 3],
}

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

/// Triangles of one cube with corner voxels `v` at global voxel `g`, appended to `out`.
fn cube(g: [i32; 3], v: &[Voxel; 8], voxel_size: f32, out: &mut Vec<[EdgeVertex; 3]>) {
    let edge = |a: usize, b: usize| -> EdgeVertex {
        let (sa, sb) = (v[a].tsdf, v[b].tsdf);
        let t = sa / (sa - sb);
        let (ca, cb) = (corner(a), corner(b));
        let pa = [g[0] + ca[0], g[1] + ca[1], g[2] + ca[2]];
        let position = [0, 1, 2].map(|k| (pa[k] as f32 + t * (cb[k] - ca[k]) as f32) * voxel_size);
        let (ka, kb) = (unpack(v[a].rgb), unpack(v[b].rgb));
        let colour = [0, 1, 2].map(|k| ka[k] + t * (kb[k] - ka[k]));
        EdgeVertex {
            key: (pa, (a ^ b) as u8),
            position,
            colour,
        }
    };
    for tet in TETRAHEDRA {
        let inside: Vec<usize> = tet.iter().copied().filter(|&c| v[c].tsdf < 0.0).collect();
        let outside: Vec<usize> = tet
            .iter()
            .copied()
            .filter(|&c| !(v[c].tsdf < 0.0))
            .collect();
        // Edges always run from the corner with fewer bits set (a Kuhn path adds bits).
        let e = |a: usize, b: usize| if a < b { edge(a, b) } else { edge(b, a) };
        let tris: Vec<[EdgeVertex; 3]> = match (inside.len(), outside.len()) {
            (1, 3) => {
                let i = inside[0];
                vec![[e(i, outside[0]), e(i, outside[1]), e(i, outside[2])]]
            }
            (3, 1) => {
                let o = outside[0];
                vec![[e(inside[0], o), e(inside[1], o), e(inside[2], o)]]
            }
            (2, 2) => {
                let (i, j, k, l) = (inside[0], inside[1], outside[0], outside[1]);
                vec![[e(i, k), e(i, l), e(j, l)], [e(i, k), e(j, l), e(j, k)]]
            }
            _ => Vec::new(),
        };
        if tris.is_empty() {
            continue;
        }
        // Outward = from the inside corners towards the outside ones.
        let centre = |cs: &[usize]| {
            let mut s = [0.0f32; 3];
            for &c in cs {
                let p = corner(c);
                for k in 0..3 {
                    s[k] += p[k] as f32 / cs.len() as f32;
                }
            }
            s
        };
        let outward = sub(centre(&outside), centre(&inside));
        for mut t in tris {
            let n = cross(
                sub(t[1].position, t[0].position),
                sub(t[2].position, t[0].position),
            );
            if dot(n, outward) < 0.0 {
                t.swap(1, 2);
            }
            out.push(t);
        }
    }
}

/// The mesh of every observed cube of the volume.
pub(crate) fn extract(view: &VolumeView<'_>) -> Mesh {
    let n = BLOCK_SIDE as i32;
    let voxel_size = view.voxel_size as f32;
    let per_block: Vec<Vec<[EdgeVertex; 3]>> = view
        .coords
        .par_iter()
        .map(|b| {
            let mut out = Vec::new();
            for z in 0..n {
                for y in 0..n {
                    for x in 0..n {
                        let g = [b[0] * n + x, b[1] * n + y, b[2] * n + z];
                        let mut v = [Voxel::default(); 8];
                        let mut ok = true;
                        for (c, vc) in v.iter_mut().enumerate() {
                            let o = corner(c);
                            match view.voxel([g[0] + o[0], g[1] + o[1], g[2] + o[2]]) {
                                Some(found) if found.weight > 0.0 => *vc = *found,
                                _ => {
                                    ok = false;
                                    break;
                                }
                            }
                        }
                        if !ok {
                            continue;
                        }
                        let neg = v.iter().filter(|q| q.tsdf < 0.0).count();
                        if neg == 0 || neg == 8 {
                            continue;
                        }
                        cube(g, &v, voxel_size, &mut out);
                    }
                }
            }
            out
        })
        .collect();
    let mut mesh = Mesh::default();
    let mut index: HashMap<EdgeKey, u32, BuildHasherDefault<FxHasher>> = HashMap::default();
    for tris in per_block {
        for t in tris {
            let ids = t.map(|ev| {
                *index.entry(ev.key).or_insert_with(|| {
                    mesh.vertices.push(ev.position);
                    mesh.colours
                        .push(ev.colour.map(|c| (c + 0.5).floor().clamp(0.0, 255.0) as u8));
                    (mesh.vertices.len() - 1) as u32
                })
            });
            // Slivers where the surface passes through a grid corner collapse to a point.
            if ids[0] != ids[1] && ids[1] != ids[2] && ids[0] != ids[2] {
                mesh.triangles.push(ids);
            }
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

#[cfg(test)]
mod tests {
    use std::borrow::Cow;
    use std::collections::HashMap;

    use super::super::integrate::{local_index, Voxel};
    use super::super::volume::{BlockMap, VolumeView};
    use super::super::{BLOCK_SIDE, BLOCK_VOXELS};
    use super::extract;

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
