//! Integration of one frame into the active blocks: the CPU mirror of `shaders/tsdf.wgsl`
//! ([`integrate_block`], which updates each row of eight voxels as SIMD lanes in
//! [`update_row`], with the same f32 operations in the same order as the WGSL's per-voxel
//! update), and the kernel interface ([`TsdfKernels`]) with its CPU implementation.

use std::borrow::Cow;

use bytemuck::{Pod, Zeroable};
use rayon::prelude::*;
use wide::{f32x8, i32x8};

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
#[cfg(test)]
fn blend(old: u32, new: u32, w: f32, wn: f32, inv_wt: f32) -> u32 {
    let v = (old as f32 * w + new as f32 * wn) * inv_wt;
    // v >= 0: truncation is the floor.
    ((v + 0.5) as u32).min(255)
}

/// The update of voxel `v` at depth `zc` (m, camera frame) whose nearest pixel is `j`, by the
/// frame `rho` (inverse depth, 1/m) / `rgb` (packed colour), one voxel at a time as the WGSL
/// writes it: the reference that [`update_row`] is tested against.
#[cfg(test)]
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
/// it because it is non-negative. The row is then updated by [`update_row`] (voxels that do
/// not land in the image are kept).
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
            let row = &mut voxels[local_index(0, y, z)..][..BLOCK_SIDE];
            update_row(u, row, &hit, &idx, &zc, rho, rgb);
        }
    }
}

/// The per-voxel update of `shaders/tsdf.wgsl` (`update_measured` in the tests) on a row of
/// [`BLOCK_SIDE`] voxels whose nearest pixels are `idx` (used where `hit`) at camera depths
/// `zc` (m), as eight SIMD lanes: every lane computes the update and a mask chooses between it
/// and the old voxel. Lanes without a valid measurement compute with inverse depth 1, so every
/// value stays finite, and keep their voxel. The same f32 operations in the same order as the
/// per-voxel form, with minimum and maximum taken so that a NaN operand gives what
/// `f32::min`/`f32::max` give, so the voxels are the same bit for bit (a test compares them).
#[inline]
pub(crate) fn update_row(
    u: &IntegrateUniform,
    row: &mut [Voxel],
    hit: &[bool; BLOCK_SIDE],
    idx: &[u32; BLOCK_SIDE],
    zc: &[f32; BLOCK_SIDE],
    rho: &[f32],
    rgb: &[u32],
) {
    let colour = u.has_colour != 0;
    let mut r = [f32::NAN; BLOCK_SIDE];
    let mut c = [0i32; BLOCK_SIDE];
    for x in 0..BLOCK_SIDE {
        if hit[x] {
            let j = idx[x] as usize;
            r[x] = rho.get(j).copied().unwrap_or(f32::NAN);
            if colour {
                c[x] = rgb.get(j).copied().unwrap_or(0) as i32;
            }
        }
    }
    let r = f32x8::from(r);
    let valid = r.simd_ge(f32x8::splat(u.min_rho)) & r.simd_le(f32x8::splat(u.max_rho));
    if valid.none() {
        return;
    }
    let one = f32x8::splat(1.0);
    let rs = valid.select(r, one);
    let z = one / rs;
    let sdf = z - f32x8::from(*zc);
    // `max(a, b)`/`min(a, b)` of SSE return `b` when either is NaN: operands ordered as
    // `f32::max(trunc_min, k)` and `f32::min(sdf, mu)` behave.
    let mu = (f32x8::splat(u.trunc_sigmas) * (f32x8::splat(u.rho_sigma) * z * z))
        .fast_max(f32x8::splat(u.trunc_min));
    let update = valid & sdf.simd_ge(-mu);
    if update.none() {
        return;
    }
    let d = sdf.fast_min(mu);
    let wn = (rs * rs) * (rs * rs);
    let mut tsdf = [0.0f32; BLOCK_SIDE];
    let mut weight = [0.0f32; BLOCK_SIDE];
    let mut old_rgb = [0i32; BLOCK_SIDE];
    for (x, v) in row.iter().enumerate().take(BLOCK_SIDE) {
        tsdf[x] = v.tsdf;
        weight[x] = v.weight;
        old_rgb[x] = v.rgb as i32;
    }
    let (old_tsdf, w) = (f32x8::from(tsdf), f32x8::from(weight));
    let wt = w + wn;
    let inv_wt = one / wt;
    let new_tsdf = update.select((old_tsdf * w + d * wn) * inv_wt, old_tsdf);
    let new_weight = update.select(wt.fast_min(f32x8::splat(u.max_weight)), w);
    let old_rgb = i32x8::from(old_rgb);
    let new_rgb = if colour {
        let c = i32x8::from(c);
        let byte = i32x8::splat(255);
        let half = f32x8::splat(0.5);
        let (zero, top) = (f32x8::ZERO, f32x8::splat(255.0));
        let mut packed = i32x8::ZERO;
        for k in 0..3 {
            let old_ch = f32x8::from_i32x8((old_rgb >> (8 * k)) & byte);
            let new_ch = f32x8::from_i32x8((c >> (8 * k)) & byte);
            let v = (old_ch * w + new_ch * wn) * inv_wt;
            // The scalar `((v + 0.5) as u32).min(255)` clamped as floats first (a NaN goes to
            // 0 as the saturating cast sends it), so the plain truncation is exact.
            let q = (v + half).fast_max(zero).fast_min(top).fast_trunc_int();
            packed |= q << (8 * k);
        }
        bytemuck::cast::<f32x8, i32x8>(update).select(packed, old_rgb)
    } else {
        old_rgb
    };
    let (t, w, c) = (
        new_tsdf.to_array(),
        new_weight.to_array(),
        new_rgb.to_array(),
    );
    for (x, v) in row.iter_mut().enumerate().take(BLOCK_SIDE) {
        *v = Voxel {
            tsdf: t[x],
            weight: w[x],
            rgb: c[x] as u32,
        };
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
    use rand::{Rng, SeedableRng};

    use super::{update_measured, update_row, IntegrateUniform, Voxel, BLOCK_SIDE};
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

    /// The SIMD row update equals the per-voxel update bit for bit, over voxels that are
    /// unobserved, observed or at the weight cap, and measurements that are missing (0, NaN),
    /// out of range, in front of, near and far behind the voxel, with and without colour.
    #[test]
    fn the_row_update_equals_the_per_voxel_update_bit_for_bit() {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(7);
        let (w, h) = (16u32, 8u32);
        let n = (w * h) as usize;
        let mut rows_updated = 0;
        for case in 0..4000 {
            let u = IntegrateUniform {
                width: w,
                height: h,
                active_count: 1,
                has_colour: u32::from(case % 3 != 0),
                fx: 500.0,
                fy: 500.0,
                cx: 8.0,
                cy: 4.0,
                camera_from_world: [
                    [1.0, 0.0, 0.0, 0.0],
                    [0.0, 1.0, 0.0, 0.0],
                    [0.0, 0.0, 1.0, 0.0],
                ],
                voxel_size: 0.02,
                rho_sigma: 0.0025,
                trunc_min: 0.06,
                trunc_sigmas: 3.0,
                max_weight: 30.0,
                min_rho: 1.0 / 8.0,
                max_rho: 1.0 / 0.2,
                _pad: 0,
            };
            let rho: Vec<f32> = (0..n)
                .map(|_| match rng.random_range(0..10) {
                    0 => 0.0,
                    1 => f32::NAN,
                    2 => rng.random_range(0.01..0.2f32),
                    3 => rng.random_range(5.0..20.0f32),
                    _ => rng.random_range(0.125..5.0f32),
                })
                .collect();
            let rgb: Vec<u32> = (0..n).map(|_| rng.random::<u32>() & 0xff_ffff).collect();
            let mut hit = [false; BLOCK_SIDE];
            let mut idx = [0u32; BLOCK_SIDE];
            let mut zc = [0.0f32; BLOCK_SIDE];
            let mut row = [Voxel::default(); BLOCK_SIDE];
            for x in 0..BLOCK_SIDE {
                hit[x] = rng.random_range(0..8) != 0;
                idx[x] = rng.random_range(0..n as u32);
                let r = rho[idx[x] as usize];
                // Voxel depths around the measured surface (truncation 6-30 cm), or anywhere.
                zc[x] = if r > 0.0 && rng.random_bool(0.8) {
                    1.0 / r + rng.random_range(-0.4..0.4f32)
                } else {
                    rng.random_range(0.1..10.0f32)
                };
                row[x] = match rng.random_range(0..4) {
                    0 => Voxel::default(),
                    1 => Voxel {
                        tsdf: rng.random_range(-0.3..0.3),
                        weight: 30.0,
                        rgb: rng.random::<u32>() & 0xff_ffff,
                    },
                    _ => Voxel {
                        tsdf: rng.random_range(-0.3..0.3),
                        weight: rng.random_range(0.0..30.0),
                        rgb: rng.random::<u32>() & 0xff_ffff,
                    },
                };
            }
            let expected: Vec<Voxel> = (0..BLOCK_SIDE)
                .map(|x| match hit[x] {
                    true => update_measured(&u, row[x], zc[x], idx[x] as usize, &rho, &rgb),
                    false => row[x],
                })
                .collect();
            let before = row;
            update_row(&u, &mut row, &hit, &idx, &zc, &rho, &rgb);
            for x in 0..BLOCK_SIDE {
                let (a, b) = (row[x], expected[x]);
                assert_eq!(
                    (a.tsdf.to_bits(), a.weight.to_bits(), a.rgb),
                    (b.tsdf.to_bits(), b.weight.to_bits(), b.rgb),
                    "case {case}, lane {x}: {a:?} against {b:?}"
                );
            }
            rows_updated += usize::from(row != before);
        }
        // The cases exercise the update, not only the early returns.
        assert!(rows_updated > 2000, "{rows_updated} rows updated");
    }
}
