//! The rayon CPU backend of the odometry kernels: same buffer layout and per-pixel math as the
//! WGSL (`kernel.rs`), partial sums per chunk in f32, finished in f64.

use rayon::prelude::*;

use super::kernel::{
    accumulate_pixel, covisible, downsample, gradients, pack_level0, pixel_terms, sample_index,
    WarpParams, INVALID_RESIDUAL, PARTIAL_LEN,
};
use crate::image::RgbdFrame;

/// Dimensions and offset of one pyramid level within a frame's buffers.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct LevelLayout {
    /// Width in pixels.
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// Offset of the level's first pixel in the concatenated buffers.
    pub offset: usize,
}

/// Layout of `levels` levels for a `width x height` level 0.
pub fn pyramid_layout(width: usize, height: usize, levels: usize) -> Vec<LevelLayout> {
    let mut out = Vec::with_capacity(levels);
    let (mut w, mut h, mut off) = (width, height, 0);
    for _ in 0..levels {
        out.push(LevelLayout {
            width: w,
            height: h,
            offset: off,
        });
        off += w * h;
        w /= 2;
        h /= 2;
    }
    out
}

/// A frame's pyramid on the CPU, all levels concatenated.
#[derive(Clone, Debug)]
pub struct CpuPyramid {
    /// Level layouts (level 0 = full resolution).
    pub levels: Vec<LevelLayout>,
    /// `(I, dI/du, dI/dv, 0)` per pixel.
    pub photo: Vec<[f32; 4]>,
    /// `(rho, drho/du, drho/dv, 0)` per pixel.
    pub geo: Vec<[f32; 4]>,
}

impl CpuPyramid {
    /// Builds the pyramid and gradients of `frame` with `levels` levels.
    pub fn build(frame: &RgbdFrame, levels: usize) -> CpuPyramid {
        let layout = pyramid_layout(frame.width(), frame.height(), levels);
        let total = layout
            .last()
            .map(|l| l.offset + l.width * l.height)
            .unwrap_or(0);
        let mut photo = vec![[0.0f32; 4]; total];
        let mut geo = vec![[0.0f32; 4]; total];
        let n0 = layout[0].width * layout[0].height;
        photo[..n0]
            .par_iter_mut()
            .zip(geo[..n0].par_iter_mut())
            .enumerate()
            .for_each(|(i, (p, g))| {
                let (a, b) = pack_level0(frame.intensity.data[i], frame.inverse_depth.data[i]);
                *p = a;
                *g = b;
            });
        for l in 1..layout.len() {
            let (s, d) = (layout[l - 1], layout[l]);
            let (src_p, dst_p) = photo.split_at_mut(d.offset);
            let (src_g, dst_g) = geo.split_at_mut(d.offset);
            let src_p = &src_p[s.offset..s.offset + s.width * s.height];
            let src_g = &src_g[s.offset..s.offset + s.width * s.height];
            dst_p[..d.width * d.height]
                .par_chunks_mut(d.width)
                .zip(dst_g[..d.width * d.height].par_chunks_mut(d.width))
                .enumerate()
                .for_each(|(y, (rp, rg))| {
                    for x in 0..d.width {
                        let k = 2 * y * s.width + 2 * x;
                        let idx = [k, k + 1, k + s.width, k + s.width + 1];
                        let (i, r) = downsample(idx.map(|j| src_p[j][0]), idx.map(|j| src_g[j][0]));
                        rp[x] = [i, 0.0, 0.0, 0.0];
                        rg[x] = [r, 0.0, 0.0, 0.0];
                    }
                });
        }
        for l in &layout {
            let range = l.offset..l.offset + l.width * l.height;
            let grads: Vec<([f32; 2], [f32; 2])> = (0..l.width * l.height)
                .into_par_iter()
                .map(|i| {
                    gradients(
                        &photo[range.clone()],
                        &geo[range.clone()],
                        l.width,
                        l.height,
                        i % l.width,
                        i / l.width,
                    )
                })
                .collect();
            for (i, (gp, gg)) in grads.into_iter().enumerate() {
                let k = l.offset + i;
                photo[k][1] = gp[0];
                photo[k][2] = gp[1];
                geo[k][1] = gg[0];
                geo[k][2] = gg[1];
            }
        }
        CpuPyramid {
            levels: layout,
            photo,
            geo,
        }
    }

    fn level(&self, l: usize) -> (&[[f32; 4]], &[[f32; 4]]) {
        let lv = self.levels[l];
        let r = lv.offset..lv.offset + lv.width * lv.height;
        (&self.photo[r.clone()], &self.geo[r])
    }
}

/// Systematic sample of residuals `(r_photo, r_geo)`, `INVALID_RESIDUAL` where invalid.
pub fn sample_residuals(
    p: &WarpParams,
    reference: &CpuPyramid,
    current: &CpuPyramid,
    level: usize,
) -> Vec<[f32; 2]> {
    let (rp, rg) = reference.level(level);
    let (cp, cg) = current.level(level);
    let n = p.dims[0] * p.dims[1];
    let count = p.dims[3];
    (0..count)
        .into_par_iter()
        .map(|k| {
            let i = sample_index(k, count, n) as usize;
            let t = pixel_terms(p, rp, rg, cp, cg, i, false);
            [
                t.r_photo.unwrap_or(INVALID_RESIDUAL),
                t.r_geo.unwrap_or(INVALID_RESIDUAL),
            ]
        })
        .collect()
}

/// Per-chunk partial sums of the IRLS normal equations (the same partial layout as the GPU's
/// per-workgroup output). `chunks` is the number of partials.
pub fn normal_equation_partials(
    p: &WarpParams,
    reference: &CpuPyramid,
    current: &CpuPyramid,
    level: usize,
    chunks: usize,
) -> Vec<[f32; PARTIAL_LEN]> {
    let (rp, rg) = reference.level(level);
    let (cp, cg) = current.level(level);
    let n = (p.dims[0] * p.dims[1]) as usize;
    let per = n.div_ceil(chunks.max(1));
    (0..chunks)
        .into_par_iter()
        .map(|c| {
            let mut acc = [0.0f32; PARTIAL_LEN];
            // Rows of 4 pixels accumulate in a small f32 buffer flushed per row for accuracy.
            let end = ((c + 1) * per).min(n);
            let mut row = [0.0f32; PARTIAL_LEN];
            let mut in_row = 0;
            for i in c * per..end {
                accumulate_pixel(p, rp, rg, cp, cg, i, &mut row);
                in_row += 1;
                if in_row == 64 {
                    for k in 0..PARTIAL_LEN {
                        acc[k] += row[k];
                    }
                    row = [0.0; PARTIAL_LEN];
                    in_row = 0;
                }
            }
            for k in 0..PARTIAL_LEN {
                acc[k] += row[k];
            }
            acc
        })
        .collect()
}

/// Covisibility counts `(pixels with depth, covisible pixels)` of `reference` in `current`.
pub fn covisibility_counts(
    p: &WarpParams,
    reference: &CpuPyramid,
    current: &CpuPyramid,
    level: usize,
) -> (u64, u64) {
    let (_, rg) = reference.level(level);
    let (_, cg) = current.level(level);
    let n = (p.dims[0] * p.dims[1]) as usize;
    (0..n)
        .into_par_iter()
        .map(|i| match covisible(p, rg, cg, i) {
            0 => (0u64, 0u64),
            1 => (1, 0),
            _ => (1, 1),
        })
        .reduce(|| (0, 0), |a, b| (a.0 + b.0, a.1 + b.1))
}
