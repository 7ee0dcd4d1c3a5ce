//! Ray casting of the volume: depth, normals and colour of the zero crossing seen from a
//! camera. [`cast`] is the CPU mirror of `shaders/tsdf_cast.wgsl` (same f32 operations in the
//! same order); [`block_table`] builds the hash table through which the kernel finds blocks.

use bytemuck::{Pod, Zeroable};
use rayon::prelude::*;

use super::integrate::Voxel;
use super::volume::VolumeView;
use super::{BLOCK_SIDE, BLOCK_VOXELS};
use crate::camera::PinholeCamera;
use crate::geometry::Se3;
use crate::image::ImageF32;

/// What [`super::TsdfVolume::ray_cast`] sees.
#[derive(Clone, Debug)]
pub struct RayCastImages {
    /// Depth along the optical axis, metres; 0 where no surface was found.
    pub depth: ImageF32,
    /// Unit surface normals in the camera frame, facing the camera (`[0; 3]` where no
    /// surface was found, or where the TSDF gradient needs a voxel that is unobserved),
    /// row-major.
    pub normals: Vec<[f32; 3]>,
    /// 8-bit RGB of the surface, trilinear in the voxels' colours (`[0; 3]` where no surface
    /// was found), row-major.
    pub colours: Vec<[u8; 3]>,
}

/// Uniform block of `tsdf_cast.wgsl` (`Params`, same layout; a test compares them).
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
pub(crate) struct CastUniform {
    /// Rows of the `world_from_camera` rotation, the camera centre (world frame, m) in `[3]`.
    pub(crate) world_from_camera: [[f32; 4]; 3],
    /// Image size, pixels.
    pub(crate) width: u32,
    pub(crate) height: u32,
    /// Hash table entries minus one (a power of two minus one).
    pub(crate) table_mask: u32,
    /// 1: the kernel writes normals.
    pub(crate) with_normals: u32,
    /// Intrinsics, pixels.
    pub(crate) fx: f32,
    pub(crate) fy: f32,
    pub(crate) cx: f32,
    pub(crate) cy: f32,
    /// Voxel edge, m.
    pub(crate) voxel_size: f32,
    /// Largest march step in free space, m.
    pub(crate) step: f32,
    /// Searched depth range along the optical axis, m.
    pub(crate) min_depth: f32,
    pub(crate) max_depth: f32,
}

impl CastUniform {
    /// The uniform of a cast by `camera` at `world_from_camera` over `table_len` hash entries.
    pub(crate) fn new(
        camera: &PinholeCamera,
        world_from_camera: &Se3,
        voxel_size: f64,
        step: f32,
        depth_range: (f32, f32),
        table_len: usize,
        with_normals: bool,
    ) -> Self {
        let r = world_from_camera.rotation_matrix();
        let t = world_from_camera.translation;
        let origin = [t.x as f32, t.y as f32, t.z as f32];
        let row = |i: usize| {
            let v = r.row(i);
            [v.x as f32, v.y as f32, v.z as f32, origin[i]]
        };
        CastUniform {
            world_from_camera: [row(0), row(1), row(2)],
            width: camera.width,
            height: camera.height,
            table_mask: (table_len.max(1) - 1) as u32,
            with_normals: u32::from(with_normals),
            fx: camera.fx as f32,
            fy: camera.fy as f32,
            cx: camera.cx as f32,
            cy: camera.cy as f32,
            voxel_size: voxel_size as f32,
            step,
            min_depth: depth_range.0,
            max_depth: depth_range.1,
        }
    }
}

/// The hash of block coordinates used by `tsdf_cast.wgsl` (wrapping 32-bit arithmetic).
fn block_hash(b: [i32; 3]) -> u32 {
    (b[0] as u32).wrapping_mul(73_856_093)
        ^ (b[1] as u32).wrapping_mul(19_349_669)
        ^ (b[2] as u32).wrapping_mul(83_492_791)
}

/// An open-addressing hash table (linear probing) of `(block coordinates, slot)` entries as
/// `[bx, by, bz, slot]`, with a power-of-two length of at least twice the entries so probes
/// stay short; empty entries have slot -1.
pub(crate) fn block_table(blocks: &[([i32; 3], u32)]) -> Vec<[i32; 4]> {
    let len = (2 * blocks.len()).next_power_of_two().max(16);
    let mask = len - 1;
    let mut table = vec![[0, 0, 0, -1]; len];
    for &(b, slot) in blocks {
        let mut i = block_hash(b) as usize & mask;
        // The table is at most half full, so a free entry is always found.
        while table[i][3] >= 0 {
            i = (i + 1) & mask;
        }
        table[i] = [b[0], b[1], b[2], slot as i32];
    }
    table
}

/// The trilinear TSDF at world point `p` (metres), `None` when one of the 8 voxels around it
/// is unallocated or unobserved.
fn sample(view: &VolumeView<'_>, p: [f32; 3]) -> Option<f32> {
    trilinear(view, p, |v| [v.tsdf, 0.0, 0.0, 0.0]).map(|a| a[0])
}

/// The trilinear colour (R, G, B in 0-255) at world point `p` (metres), `None` as [`sample`].
fn sample_colour(view: &VolumeView<'_>, p: [f32; 3]) -> Option<[u8; 3]> {
    let ch = |rgb: u32, k: u32| ((rgb >> (8 * k)) & 255) as f32;
    let c = trilinear(view, p, |v| [ch(v.rgb, 0), ch(v.rgb, 1), ch(v.rgb, 2), 0.0])?;
    Some([0, 1, 2].map(|k| (c[k] + 0.5).floor().clamp(0.0, 255.0) as u8))
}

/// Trilinear interpolation of `value` over the 8 voxels around world point `p` (metres),
/// `None` when one of them is unallocated or unobserved.
fn trilinear(
    view: &VolumeView<'_>,
    p: [f32; 3],
    value: impl Fn(&Voxel) -> [f32; 4],
) -> Option<[f32; 4]> {
    let s = view.voxel_size as f32;
    let q = p.map(|c| c / s);
    let b = q.map(|c| c.floor());
    let f = [q[0] - b[0], q[1] - b[1], q[2] - b[2]];
    let g = b.map(|c| c as i32);
    let n = BLOCK_SIDE as i32;
    let l = g.map(|c| c.rem_euclid(n));
    // When the 8 voxels share a block (most positions), one block look-up serves them all.
    let block = if l.iter().all(|&c| c < n - 1) {
        let key = g.map(|c| c.div_euclid(n));
        let slot = *view.map.get(&key)? as usize;
        view.voxels
            .get(slot * BLOCK_VOXELS..(slot + 1) * BLOCK_VOXELS)
    } else {
        None
    };
    let mut acc = [0.0f32; 4];
    for c in 0..8 {
        let o = [c & 1, (c >> 1) & 1, (c >> 2) & 1];
        let v = match block {
            Some(voxels) => {
                let i = (l[0] + o[0] + n * (l[1] + o[1] + n * (l[2] + o[2]))) as usize;
                voxels.get(i)?
            }
            None => view.voxel([g[0] + o[0], g[1] + o[1], g[2] + o[2]])?,
        };
        if !(v.weight > 0.0) {
            return None;
        }
        let w = (0..3)
            .map(|k| if o[k] == 1 { f[k] } else { 1.0 - f[k] })
            .product::<f32>();
        for (a, x) in acc.iter_mut().zip(value(v)) {
            *a += w * x;
        }
    }
    Some(acc)
}

/// Ray casts `view` from `camera` at `world_from_camera`; `step` (m) is the largest march
/// step in free space, depths are searched in `[min_depth, max_depth]` (m). Without
/// `with_normals` the normals stay `[0; 3]` (their six extra TSDF samples per pixel are
/// skipped).
pub(crate) fn cast(
    view: &VolumeView<'_>,
    camera: &PinholeCamera,
    world_from_camera: &Se3,
    step: f32,
    depth_range: (f32, f32),
    with_normals: bool,
) -> RayCastImages {
    let (min_depth, max_depth) = depth_range;
    let (w, h) = (camera.width as usize, camera.height as usize);
    let r = world_from_camera.rotation_matrix();
    let t = world_from_camera.translation;
    let rot = |v: [f32; 3]| -> [f32; 3] {
        [0, 1, 2]
            .map(|i| r.row(i).x as f32 * v[0] + r.row(i).y as f32 * v[1] + r.row(i).z as f32 * v[2])
    };
    let origin = [t.x as f32, t.y as f32, t.z as f32];
    let voxel = view.voxel_size as f32;
    let block = voxel * BLOCK_SIDE as f32;
    type Row = (Vec<f32>, Vec<[f32; 3]>, Vec<[u8; 3]>);
    let rows: Vec<Row> = (0..h)
        .into_par_iter()
        .map(|y| {
            let mut depth = vec![0.0f32; w];
            let mut normals = vec![[0.0f32; 3]; w];
            let mut colours = vec![[0u8; 3]; w];
            for x in 0..w {
                let ray_c = [
                    (x as f32 - camera.cx as f32) / camera.fx as f32,
                    (y as f32 - camera.cy as f32) / camera.fy as f32,
                    1.0,
                ];
                let ray = rot(ray_c);
                let at = |z: f32| [0, 1, 2].map(|k| origin[k] + ray[k] * z);
                let len = (ray_c[0] * ray_c[0] + ray_c[1] * ray_c[1] + 1.0).sqrt();
                let mut z = min_depth;
                let mut prev: Option<(f32, f32)> = None;
                while z < max_depth {
                    match sample(view, at(z)) {
                        None => {
                            prev = None;
                            // Unknown space: skip faster where the whole block is missing.
                            let p = at(z);
                            let g = p.map(|c| (c / voxel).floor() as i32);
                            let n = BLOCK_SIDE as i32;
                            let blk = [g[0].div_euclid(n), g[1].div_euclid(n), g[2].div_euclid(n)];
                            let dz = if view.map.contains_key(&blk) {
                                voxel
                            } else {
                                0.5 * block
                            };
                            z += dz / len;
                        }
                        Some(s) => {
                            if let Some((zp, sp)) = prev {
                                if sp > 0.0 && s <= 0.0 {
                                    let zh = zp + (z - zp) * sp / (sp - s);
                                    depth[x] = zh;
                                    if with_normals {
                                        normals[x] = normal(view, at(zh), voxel, ray_c, &r);
                                    }
                                    colours[x] = sample_colour(view, at(zh)).unwrap_or([0; 3]);
                                    break;
                                }
                                if sp < 0.0 && s > 0.0 {
                                    // Seen from behind: not a surface facing this camera.
                                    break;
                                }
                            }
                            prev = Some((z, s));
                            z += (s.abs().min(step)).max(voxel) * 0.8 / len;
                        }
                    }
                }
            }
            (depth, normals, colours)
        })
        .collect();
    let mut depth = Vec::with_capacity(w * h);
    let mut normals = Vec::with_capacity(w * h);
    let mut colours = Vec::with_capacity(w * h);
    for (d, n, c) in rows {
        depth.extend(d);
        normals.extend(n);
        colours.extend(c);
    }
    RayCastImages {
        depth: ImageF32::from_vec(w, h, depth).unwrap_or_else(|| ImageF32::filled(w, h, 0.0)),
        normals,
        colours,
    }
}

/// Unit normal (camera frame, facing the camera) from central differences of the TSDF.
fn normal(
    view: &VolumeView<'_>,
    p: [f32; 3],
    voxel: f32,
    ray_c: [f32; 3],
    world_from_camera_rot: &glam::DMat3,
) -> [f32; 3] {
    let mut g = [0.0f32; 3];
    for k in 0..3 {
        let mut a = p;
        let mut b = p;
        a[k] += voxel;
        b[k] -= voxel;
        match (sample(view, a), sample(view, b)) {
            (Some(sa), Some(sb)) => g[k] = sa - sb,
            _ => return [0.0; 3],
        }
    }
    // World to camera: the transpose of world_from_camera's rotation.
    let r = world_from_camera_rot;
    let c = [0, 1, 2]
        .map(|i| r.col(i).x as f32 * g[0] + r.col(i).y as f32 * g[1] + r.col(i).z as f32 * g[2]);
    let l = (c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt();
    if !(l > 0.0) {
        return [0.0; 3];
    }
    let mut n = c.map(|v| v / l);
    if n[0] * ray_c[0] + n[1] * ray_c[1] + n[2] * ray_c[2] > 0.0 {
        n = n.map(|v| -v);
    }
    n
}

#[cfg(test)]
mod tests {
    use super::{block_hash, block_table, CastUniform};
    use crate::gpu::{host_layout, layout_mismatches, shaders};

    #[test]
    fn cast_uniform_matches_the_wgsl_layout() {
        let host = host_layout!(CastUniform {
            rot0 = world_from_camera[0] stride 16,
            rot1 = world_from_camera[1] stride 16,
            rot2 = world_from_camera[2] stride 16,
            width,
            height,
            table_mask,
            with_normals,
            fx,
            fy,
            cx,
            cy,
            voxel_size,
            step,
            min_depth,
            max_depth,
        });
        let src = shaders::assembled("tsdf_cast.wgsl").unwrap_or_default();
        let size = std::mem::size_of::<CastUniform>();
        let bad = layout_mismatches(&src, "Params", &host, size);
        assert!(bad.is_empty(), "{}", bad.join("\n"));
    }

    #[test]
    fn every_block_is_found_by_probing_from_its_hash() {
        let blocks: Vec<([i32; 3], u32)> = (0..300)
            .map(|k: i32| ([k % 7 - 3, (k / 7) % 11 - 5, k / 77 - 2], k as u32))
            .collect();
        let table = block_table(&blocks);
        assert!(table.len().is_power_of_two() && table.len() >= 2 * blocks.len());
        let mask = table.len() - 1;
        let find = |b: [i32; 3]| {
            let mut i = block_hash(b) as usize & mask;
            loop {
                let e = table[i];
                if e[3] < 0 {
                    return None;
                }
                if [e[0], e[1], e[2]] == b {
                    return Some(e[3] as u32);
                }
                i = (i + 1) & mask;
            }
        };
        for (b, slot) in &blocks {
            assert_eq!(find(*b), Some(*slot), "block {b:?}");
        }
        assert_eq!(find([100, 100, 100]), None);
    }
}
