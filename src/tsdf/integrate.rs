//! Integration of one frame into the active blocks: the per-voxel update shared by the CPU
//! mirror ([`integrate_block`], [`update_measured`]) and `shaders/tsdf.wgsl` (same f32 operations in the same order),
//! and the kernel interface ([`TsdfKernels`]) with its CPU implementation.

use std::borrow::Cow;

use bytemuck::{Pod, Zeroable};
use rayon::prelude::*;

use super::{TsdfError, BLOCK_SIDE, BLOCK_VOXELS};

/// One voxel: truncated signed distance (metres, positive in front of the surface), weight
/// (sum of measurement weights, capped), colour packed as `0x00BBGGRR`. Weight 0 = unobserved.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub(crate) struct Voxel {
    pub(crate) tsdf: f32,
    pub(crate) weight: f32,
    pub(crate) rgb: u32,
}

/// Uniform block of `tsdf.wgsl` (`Params`, same layout; a test compares them).
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
pub(crate) struct IntegrateUniform {
    /// Frame size, pixels.
    pub(crate) width: u32,
    pub(crate) height: u32,
    /// Number of entries of the active-block list.
    pub(crate) active_count: u32,
    /// 1 when the frame has colour.
    pub(crate) has_colour: u32,
    /// Intrinsics, pixels.
    pub(crate) fx: f32,
    pub(crate) fy: f32,
    pub(crate) cx: f32,
    pub(crate) cy: f32,
    /// `camera_from_world` rows with the translation (m) in the last column.
    pub(crate) camera_from_world: [[f32; 4]; 3],
    /// Voxel edge, m.
    pub(crate) voxel_size: f32,
    /// Inverse-depth noise sigma_rho, 1/m.
    pub(crate) rho_sigma: f32,
    /// Smallest truncation, m.
    pub(crate) trunc_min: f32,
    /// Truncation in depth sigmas.
    pub(crate) trunc_sigmas: f32,
    /// Cap of the accumulated weight.
    pub(crate) max_weight: f32,
    /// Valid inverse depths, 1/m: `[min_rho, max_rho]`.
    pub(crate) min_rho: f32,
    pub(crate) max_rho: f32,
    /// Padding to the 16-byte size of the WGSL struct.
    pub(crate) _pad: u32,
}

#[inline]
fn xform(r: &[[f32; 4]; 3], p: [f32; 3]) -> [f32; 3] {
    let f = |k: usize| r[k][0] * p[0] + r[k][1] * p[1] + r[k][2] * p[2] + r[k][3];
    [f(0), f(1), f(2)]
}

/// Truncation distance (m) for a measurement at depth `z` (m).
#[inline]
pub(crate) fn truncation(u: &IntegrateUniform, z: f32) -> f32 {
    u.trunc_min.max(u.trunc_sigmas * (u.rho_sigma * z * z))
}

/// Weighted average of one 8-bit channel (`inv_wt` = 1 / (w + wn)), rounded half up.
#[inline]
fn blend(old: u32, new: u32, w: f32, wn: f32, inv_wt: f32) -> u32 {
    let v = (old as f32 * w + new as f32 * wn) * inv_wt;
    // v >= 0: truncation is the floor.
    ((v + 0.5) as u32).min(255)
}

/// The update of voxel `v` at depth `zc` (m, camera frame) whose nearest pixel is `j`, by the
/// frame `rho` (inverse depth, 1/m) / `rgb` (packed colour). Two divisions (depth, weight).
#[inline]
pub(crate) fn update_measured(
    u: &IntegrateUniform,
    v: Voxel,
    zc: f32,
    j: usize,
    rho: &[f32],
    rgb: &[u32],
) -> Voxel {
    let r = rho[j];
    if !(r >= u.min_rho && r <= u.max_rho) {
        return v;
    }
    let z = 1.0 / r;
    let sdf = z - zc;
    let mu = truncation(u, z);
    if sdf < -mu {
        return v;
    }
    let d = sdf.min(mu);
    let wn = (r * r) * (r * r);
    let w = v.weight;
    let wt = w + wn;
    let inv_wt = 1.0 / wt;
    let tsdf = (v.tsdf * w + d * wn) * inv_wt;
    let mut out_rgb = v.rgb;
    if u.has_colour != 0 {
        let c = rgb[j];
        let ch = |x: u32, k: u32| (x >> (8 * k)) & 255;
        out_rgb = blend(ch(v.rgb, 0), ch(c, 0), w, wn, inv_wt)
            | (blend(ch(v.rgb, 1), ch(c, 1), w, wn, inv_wt) << 8)
            | (blend(ch(v.rgb, 2), ch(c, 2), w, wn, inv_wt) << 16);
    }
    Voxel {
        tsdf,
        weight: wt.min(u.max_weight),
        rgb: out_rgb,
    }
}

/// Local index of voxel `(x, y, z)` inside a block.
#[inline]
pub(crate) fn local_index(x: usize, y: usize, z: usize) -> usize {
    x + BLOCK_SIDE * (y + BLOCK_SIDE * z)
}

/// Updates one block (`voxels`, [`BLOCK_VOXELS`] long) at block coordinates `b`: voxel `g`
/// (global voxel coordinates) sits at `g * voxel_size` in the world.
///
/// Each row of 8 voxels is first moved into the camera and projected to its nearest pixel,
/// without branches (so the compiler can use SIMD lanes): one division and no `floor`, since
/// a pixel coordinate `q + 0.5` is range-checked as a float and then truncated, which floors
/// it because it is non-negative. Only the voxels that land in the image are then updated
/// ([`update_measured`]).
pub(crate) fn integrate_block(
    u: &IntegrateUniform,
    b: [i32; 3],
    voxels: &mut [Voxel],
    rho: &[f32],
    rgb: &[u32],
) {
    let n = BLOCK_SIDE as i32;
    let s = u.voxel_size;
    let (wf, hf) = (u.width as f32, u.height as f32);
    let mut idx = [0u32; BLOCK_SIDE];
    let mut zc = [0.0f32; BLOCK_SIDE];
    let mut hit = [false; BLOCK_SIDE];
    for z in 0..BLOCK_SIDE {
        let pz = (b[2] * n + z as i32) as f32 * s;
        for y in 0..BLOCK_SIDE {
            let py = (b[1] * n + y as i32) as f32 * s;
            for x in 0..BLOCK_SIDE {
                let px = (b[0] * n + x as i32) as f32 * s;
                let pc = xform(&u.camera_from_world, [px, py, pz]);
                let inv_z = 1.0 / pc[2];
                let qx = u.fx * pc[0] * inv_z + u.cx + 0.5;
                let qy = u.fy * pc[1] * inv_z + u.cy + 0.5;
                hit[x] = (pc[2] > 0.0) & (qx >= 0.0) & (qy >= 0.0) & (qx < wf) & (qy < hf);
                idx[x] = (qy as u32).wrapping_mul(u.width).wrapping_add(qx as u32);
                zc[x] = pc[2];
            }
            for x in 0..BLOCK_SIDE {
                if hit[x] {
                    let i = local_index(x, y, z);
                    voxels[i] = update_measured(u, voxels[i], zc[x], idx[x] as usize, rho, rgb);
                }
            }
        }
    }
}

/// The TSDF integration kernel of one backend, with the voxels resident where it runs.
pub(crate) trait TsdfKernels: Send {
    /// Integrates the frame into the blocks of `active` (`[bx, by, bz, slot]`); `blocks` is
    /// the number of allocated slots (the storage grows to hold them, new slots unobserved).
    fn integrate(
        &mut self,
        blocks: usize,
        active: &[[i32; 4]],
        rho: &[f32],
        rgb: Option<&[u32]>,
        u: &IntegrateUniform,
    ) -> Result<(), TsdfError>;
    /// All voxels, slot after slot ([`BLOCK_VOXELS`] each).
    fn voxels(&self) -> Result<Cow<'_, [Voxel]>, TsdfError>;
    /// Replaces all voxels by `voxels` (`blocks` slots of [`BLOCK_VOXELS`]), as a loaded file
    /// holds them.
    fn set_voxels(&mut self, blocks: usize, voxels: &[Voxel]) -> Result<(), TsdfError>;
    /// Bytes held, `(host, device)`.
    fn memory_bytes(&self) -> (usize, usize);
    /// Ray casts the voxels where they are resident, finding blocks through `table` (see
    /// [`super::raycast::block_table`]); `None` when this backend has no ray-cast kernel of its
    /// own and the caller runs the CPU mirror on its view of the voxels.
    fn ray_cast(
        &self,
        _table: &[[i32; 4]],
        _u: &super::raycast::CastUniform,
    ) -> Result<Option<super::RayCastImages>, TsdfError> {
        Ok(None)
    }
    /// Marching tetrahedra over the voxels where they are resident: the triangles of every
    /// cube of the blocks of `coords` (`[bx, by, bz, _]` per slot, in slot order), finding
    /// neighbouring blocks through `table` (see [`super::raycast::block_table`]); `None` when
    /// this backend has no mesh kernel of its own and the caller runs the CPU mirror
    /// ([`super::mesh::cube_triangles`]) on its view of the voxels.
    fn mesh_cubes(
        &self,
        _table: &[[i32; 4]],
        _coords: &[[i32; 4]],
        _u: &super::mesh::MeshUniform,
    ) -> Result<Option<super::mesh::CubeTriangles>, TsdfError> {
        Ok(None)
    }
    /// The voxels of `slots`, one block after another (paging out).
    fn read_slots(&self, slots: &[u32]) -> Result<Vec<Voxel>, TsdfError>;
    /// Makes room for `blocks` slots, writes each `(slot, voxels)` of `uploads` (paging in,
    /// [`BLOCK_VOXELS`] voxels each) and clears the slots of `zeroed` to unobserved.
    fn write_slots(
        &mut self,
        blocks: usize,
        uploads: &[(u32, Vec<Voxel>)],
        zeroed: &[u32],
    ) -> Result<(), TsdfError>;
    /// Most slots the storage may hold (`None` = unbounded); storage beyond it is released
    /// (the slots there must be unused).
    fn set_slot_limit(&mut self, limit: Option<usize>) -> Result<(), TsdfError>;
    /// Slots the storage holds now (its capacity in blocks).
    fn slot_capacity(&self) -> usize;
}

/// The CPU mirror: voxels in host memory, blocks in parallel.
#[derive(Default)]
pub(crate) struct CpuTsdf {
    voxels: Vec<Voxel>,
    /// Per slot: 1 + the index in the current frame's active list, 0 when not active (reset
    /// after every frame, so a frame costs its active blocks, not all blocks).
    mark: Vec<u32>,
}

impl TsdfKernels for CpuTsdf {
    fn integrate(
        &mut self,
        blocks: usize,
        active: &[[i32; 4]],
        rho: &[f32],
        rgb: Option<&[u32]>,
        u: &IntegrateUniform,
    ) -> Result<(), TsdfError> {
        self.voxels.resize(blocks * BLOCK_VOXELS, Voxel::default());
        self.mark.resize(blocks, 0);
        for (i, a) in active.iter().enumerate() {
            if let Some(m) = self.mark.get_mut(a[3] as usize) {
                *m = i as u32 + 1;
            }
        }
        let rgb = rgb.unwrap_or(&[]);
        let mark = &self.mark;
        let mut work: Vec<(usize, &mut [Voxel])> = self
            .voxels
            .chunks_mut(BLOCK_VOXELS)
            .enumerate()
            .filter_map(|(s, vox)| match mark[s] {
                0 => None,
                i => Some((i as usize - 1, vox)),
            })
            .collect();
        work.par_iter_mut().for_each(|(i, vox)| {
            let a = active[*i];
            integrate_block(u, [a[0], a[1], a[2]], vox, rho, rgb);
        });
        for a in active {
            if let Some(m) = self.mark.get_mut(a[3] as usize) {
                *m = 0;
            }
        }
        Ok(())
    }

    fn voxels(&self) -> Result<Cow<'_, [Voxel]>, TsdfError> {
        Ok(Cow::Borrowed(&self.voxels))
    }

    fn set_voxels(&mut self, blocks: usize, voxels: &[Voxel]) -> Result<(), TsdfError> {
        self.voxels.clear();
        self.voxels.extend_from_slice(voxels);
        self.voxels.resize(blocks * BLOCK_VOXELS, Voxel::default());
        self.mark.clear();
        self.mark.resize(blocks, 0);
        Ok(())
    }

    fn memory_bytes(&self) -> (usize, usize) {
        (
            self.voxels.capacity() * std::mem::size_of::<Voxel>() + self.mark.capacity() * 4,
            0,
        )
    }

    fn read_slots(&self, slots: &[u32]) -> Result<Vec<Voxel>, TsdfError> {
        let mut out = Vec::with_capacity(slots.len() * BLOCK_VOXELS);
        for &s in slots {
            let s = s as usize;
            match self.voxels.get(s * BLOCK_VOXELS..(s + 1) * BLOCK_VOXELS) {
                Some(v) => out.extend_from_slice(v),
                None => out.resize(out.len() + BLOCK_VOXELS, Voxel::default()),
            }
        }
        Ok(out)
    }

    fn write_slots(
        &mut self,
        blocks: usize,
        uploads: &[(u32, Vec<Voxel>)],
        zeroed: &[u32],
    ) -> Result<(), TsdfError> {
        if self.voxels.len() < blocks * BLOCK_VOXELS {
            self.voxels.resize(blocks * BLOCK_VOXELS, Voxel::default());
            self.mark.resize(blocks, 0);
        }
        let zero = [Voxel::default(); BLOCK_VOXELS];
        let writes = uploads
            .iter()
            .map(|(s, v)| (*s, v.as_slice()))
            .chain(zeroed.iter().map(|s| (*s, &zero[..])));
        for (s, v) in writes {
            let s = s as usize;
            if let Some(dst) = self
                .voxels
                .get_mut(s * BLOCK_VOXELS..(s + 1) * BLOCK_VOXELS)
            {
                let n = v.len().min(BLOCK_VOXELS);
                dst[..n].copy_from_slice(&v[..n]);
            }
        }
        Ok(())
    }

    fn set_slot_limit(&mut self, limit: Option<usize>) -> Result<(), TsdfError> {
        if let Some(b) = limit {
            self.voxels.truncate(b * BLOCK_VOXELS);
            self.mark.truncate(b);
        }
        Ok(())
    }

    fn slot_capacity(&self) -> usize {
        self.voxels.len() / BLOCK_VOXELS
    }
}

#[cfg(test)]
mod tests {
    use super::{IntegrateUniform, Voxel};
    use crate::gpu::{host_layout, layout_mismatches, shaders};

    #[test]
    fn integrate_uniform_matches_the_wgsl_layout() {
        let host = host_layout!(IntegrateUniform {
            width,
            height,
            active_count,
            has_colour,
            fx,
            fy,
            cx,
            cy,
            rot0 = camera_from_world[0] stride 16,
            rot1 = camera_from_world[1] stride 16,
            rot2 = camera_from_world[2] stride 16,
            voxel_size,
            rho_sigma,
            trunc_min,
            trunc_sigmas,
            max_weight,
            min_rho,
            max_rho,
            _pad,
        });
        let src = shaders::assembled("tsdf.wgsl").unwrap_or_default();
        let size = std::mem::size_of::<IntegrateUniform>();
        let bad = layout_mismatches(&src, "Params", &host, size);
        assert!(bad.is_empty(), "{}", bad.join("\n"));
    }

    #[test]
    fn voxel_matches_the_wgsl_layout() {
        let host = host_layout!(Voxel { tsdf, weight, rgb });
        let src = shaders::assembled("tsdf.wgsl").unwrap_or_default();
        let bad = layout_mismatches(&src, "Voxel", &host, std::mem::size_of::<Voxel>());
        assert!(bad.is_empty(), "{}", bad.join("\n"));
    }
}
