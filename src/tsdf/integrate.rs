//! Integration of one frame into the active blocks: the per-voxel update shared by the CPU
//! mirror ([`update_voxel`]) and `shaders/tsdf.wgsl` (same f32 operations in the same order),
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

/// Weighted average of one 8-bit channel, rounded half up.
#[inline]
fn blend(old: u32, new: u32, w: f32, wn: f32, wt: f32) -> u32 {
    let v = (old as f32 * w + new as f32 * wn) / wt;
    ((v + 0.5).floor() as u32).min(255)
}

/// The update of the voxel at global voxel coordinates `g` (position `g * voxel_size` in the
/// world) by the frame `rho` (inverse depth, 1/m) / `rgb` (packed colour).
#[inline]
pub(crate) fn update_voxel(
    u: &IntegrateUniform,
    g: [i32; 3],
    v: Voxel,
    rho: &[f32],
    rgb: &[u32],
) -> Voxel {
    let s = u.voxel_size;
    let pw = [g[0] as f32 * s, g[1] as f32 * s, g[2] as f32 * s];
    let pc = xform(&u.camera_from_world, pw);
    if !(pc[2] > 0.0) {
        return v;
    }
    let qx = (u.fx * pc[0] / pc[2] + u.cx + 0.5).floor();
    let qy = (u.fy * pc[1] / pc[2] + u.cy + 0.5).floor();
    if !(qx >= 0.0 && qy >= 0.0 && qx <= (u.width - 1) as f32 && qy <= (u.height - 1) as f32) {
        return v;
    }
    let j = qy as usize * u.width as usize + qx as usize;
    let r = rho[j];
    if !(r >= u.min_rho && r <= u.max_rho) {
        return v;
    }
    let z = 1.0 / r;
    let sdf = z - pc[2];
    let mu = truncation(u, z);
    if sdf < -mu {
        return v;
    }
    let d = sdf.min(mu);
    let wn = (r * r) * (r * r);
    let w = v.weight;
    let wt = w + wn;
    let tsdf = (v.tsdf * w + d * wn) / wt;
    let mut out_rgb = v.rgb;
    if u.has_colour != 0 {
        let c = rgb[j];
        let ch = |x: u32, k: u32| (x >> (8 * k)) & 255;
        out_rgb = blend(ch(v.rgb, 0), ch(c, 0), w, wn, wt)
            | (blend(ch(v.rgb, 1), ch(c, 1), w, wn, wt) << 8)
            | (blend(ch(v.rgb, 2), ch(c, 2), w, wn, wt) << 16);
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

/// Updates one block (`voxels`, [`BLOCK_VOXELS`] long) at block coordinates `b`.
pub(crate) fn integrate_block(
    u: &IntegrateUniform,
    b: [i32; 3],
    voxels: &mut [Voxel],
    rho: &[f32],
    rgb: &[u32],
) {
    let n = BLOCK_SIDE as i32;
    for z in 0..BLOCK_SIDE {
        for y in 0..BLOCK_SIDE {
            for x in 0..BLOCK_SIDE {
                let i = local_index(x, y, z);
                let g = [
                    b[0] * n + x as i32,
                    b[1] * n + y as i32,
                    b[2] * n + z as i32,
                ];
                voxels[i] = update_voxel(u, g, voxels[i], rho, rgb);
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
    /// Bytes held, `(host, device)`.
    fn memory_bytes(&self) -> (usize, usize);
}

/// The CPU mirror: voxels in host memory, blocks in parallel.
#[derive(Default)]
pub(crate) struct CpuTsdf {
    voxels: Vec<Voxel>,
    /// Per slot: true while it is in the current frame's active list.
    mark: Vec<bool>,
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
        self.mark.clear();
        self.mark.resize(blocks, false);
        let mut coords = vec![[0i32; 3]; blocks];
        for a in active {
            let slot = a[3] as usize;
            if slot < blocks {
                self.mark[slot] = true;
                coords[slot] = [a[0], a[1], a[2]];
            }
        }
        let rgb = rgb.unwrap_or(&[]);
        let mut work: Vec<(usize, &mut [Voxel])> = self
            .voxels
            .chunks_mut(BLOCK_VOXELS)
            .enumerate()
            .filter(|(s, _)| self.mark[*s])
            .collect();
        work.par_iter_mut()
            .for_each(|(s, vox)| integrate_block(u, coords[*s], vox, rho, rgb));
        Ok(())
    }

    fn voxels(&self) -> Result<Cow<'_, [Voxel]>, TsdfError> {
        Ok(Cow::Borrowed(&self.voxels))
    }

    fn memory_bytes(&self) -> (usize, usize) {
        (
            self.voxels.capacity() * std::mem::size_of::<Voxel>() + self.mark.capacity(),
            0,
        )
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
