//! The rayon CPU backend of the odometry kernels: same buffer layout and per-pixel math as the
//! WGSL (`kernel.rs`), partial sums per chunk in f32, finished in f64.

use rayon::prelude::*;

use super::kernel::{
    bilateral, covisible, downsample, gradients_of_lane, pack_level0, Partial, PartialSums,
    PartialsAndSample, PyrParams, WarpParams, INVALID_RESIDUAL,
};
use super::rows::{accumulate_rows, first_sample_at, sample_range, Buffers, SampleWalk, Warp};
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
    /// `(rho, drho/du, drho/dv, z)` per pixel, with `z = 1 / rho` (0 where rho is invalid)
    /// cached for the CPU's warp (the GPU layout leaves `.w` at 0).
    pub geo: Vec<[f32; 4]>,
}

impl CpuPyramid {
    #[cfg(test)]
    /// Builds the pyramid and gradients of `frame` with `levels` levels.
    pub fn build(frame: &RgbdFrame, levels: usize) -> CpuPyramid {
        Self::build_reusing(frame, levels, 0, None)
    }

    /// Like [`Self::build`], writing into `recycle`'s buffers when it has the same layout (every
    /// value is overwritten), which saves allocating and zeroing them per frame. Levels finer
    /// than `first_gradient_level` get no gradients (and no cached depth): they are only the
    /// source of the coarser levels, for an odometry that does not optimise them.
    pub fn build_reusing(
        frame: &RgbdFrame,
        levels: usize,
        first_gradient_level: usize,
        recycle: Option<CpuPyramid>,
    ) -> CpuPyramid {
        let layout = pyramid_layout(frame.width(), frame.height(), levels);
        let total = layout
            .last()
            .map(|l| l.offset + l.width * l.height)
            .unwrap_or(0);
        let (mut photo, mut geo) = match recycle {
            Some(r) if r.levels == layout && r.photo.len() == total && r.geo.len() == total => {
                (r.photo, r.geo)
            }
            _ => (vec![[0.0f32; 4]; total], vec![[0.0f32; 4]; total]),
        };
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
        for l in layout.iter().skip(first_gradient_level) {
            write_gradients(&mut photo, &mut geo, l, 0);
        }
        CpuPyramid {
            levels: layout,
            photo,
            geo,
        }
    }

    /// A copy of level `level` whose gradients are those of its bilateral-filtered intensity
    /// and inverse depth (`f` gives the level's size and offset and the filter's scales), for
    /// the covariance pass of the odometry (thesis 6.20, 6.21). The result has this pyramid's
    /// layout; within `level` each pixel holds `(I, dIf/du, dIf/dv, If)` and
    /// `(rho, drhof/du, drhof/dv, z)`, with `If` the filtered intensity, `drhof` the gradient
    /// of the filtered inverse depth and `z = 1 / rho` cached as in a pyramid build (the raw
    /// values stay in `.x`, so residuals and IRLS weights are unchanged; the cache lets the
    /// level serve as the reference of a normal-equation pass, which the reference-frame
    /// linearisation's covariance pass needs). Other levels are unspecified: use it only at
    /// `level`. Reuses `recycle`'s buffers when the layout matches. Mirror of
    /// `GpuKernels::filtered_level`, except `geo.w`, which holds the filtered inverse depth
    /// there (the WGSL warp computes `z` from `.x`).
    pub fn filtered_level(
        &self,
        level: usize,
        f: &PyrParams,
        recycle: Option<CpuPyramid>,
    ) -> CpuPyramid {
        let total = self.photo.len();
        let (mut photo, mut geo) = match recycle {
            Some(r) if r.levels == self.levels && r.photo.len() == total => (r.photo, r.geo),
            _ => (vec![[0.0f32; 4]; total], vec![[0.0f32; 4]; total]),
        };
        let Some(l) = self.levels.get(level).copied() else {
            return CpuPyramid {
                levels: self.levels.clone(),
                photo,
                geo,
            };
        };
        let range = l.offset..l.offset + l.width * l.height;
        let (sp, sg) = self.level(level);
        photo[range.clone()]
            .par_chunks_mut(l.width)
            .zip(geo[range.clone()].par_chunks_mut(l.width))
            .enumerate()
            .for_each(|(y, (rp, rg))| {
                for x in 0..l.width {
                    let (i, r) = bilateral(f, sp, sg, x, y);
                    rp[x] = [sp[y * l.width + x][0], 0.0, 0.0, i];
                    rg[x] = [sg[y * l.width + x][0], 0.0, 0.0, r];
                }
            });
        write_gradients(&mut photo, &mut geo, &l, 3);
        for g in &mut geo[range] {
            g[3] = if g[0] > 0.0 { 1.0 / g[0] } else { 0.0 };
        }
        CpuPyramid {
            levels: self.levels.clone(),
            photo,
            geo,
        }
    }

    /// Bytes of host memory this pyramid holds (capacities).
    pub fn host_bytes(&self) -> usize {
        self.levels.capacity() * std::mem::size_of::<LevelLayout>()
            + (self.photo.capacity() + self.geo.capacity()) * std::mem::size_of::<[f32; 4]>()
    }

    fn level(&self, l: usize) -> (&[[f32; 4]], &[[f32; 4]]) {
        let lv = self.levels[l];
        let r = lv.offset..lv.offset + lv.width * lv.height;
        (&self.photo[r.clone()], &self.geo[r])
    }
}

/// Writes the gradients of the values in `lane` of level `l` into lanes 1 and 2 (see
/// [`gradients_of_lane`]). For `lane == 0` (a pyramid build) it also caches `z = 1 / rho` in
/// `geo.w` (0 where rho is invalid); other lanes keep `.w` (it holds the filtered values).
fn write_gradients(photo: &mut [[f32; 4]], geo: &mut [[f32; 4]], l: &LevelLayout, lane: usize) {
    /// A level's photometric and geometric values.
    type LevelCopy = (Vec<[f32; 4]>, Vec<[f32; 4]>);
    thread_local! {
        /// The copies of the last level this thread wrote gradients for: kept, so that a
        /// build per frame neither allocates nor first touches fresh memory. Taken out while
        /// in use: while this thread waits for the parallel rows below, rayon may run another
        /// build on it, which then finds the cell empty and allocates its own.
        static SOURCE: std::cell::Cell<LevelCopy> =
            const { std::cell::Cell::new((Vec::new(), Vec::new())) };
    }
    let range = l.offset..l.offset + l.width * l.height;
    // The level's values, so that rows can be written in parallel while their neighbours
    // are read.
    let (mut src_p, mut src_g) = SOURCE.take();
    src_p.clear();
    src_p.extend_from_slice(&photo[range.clone()]);
    src_g.clear();
    src_g.extend_from_slice(&geo[range.clone()]);
    photo[range.clone()]
        .par_chunks_mut(l.width)
        .zip(geo[range].par_chunks_mut(l.width))
        .enumerate()
        .for_each(|(y, (rp, rg))| {
            for x in 0..l.width {
                let (gp, gg) = gradients_of_lane(&src_p, &src_g, l.width, l.height, x, y, lane);
                rp[x][1] = gp[0];
                rp[x][2] = gp[1];
                rg[x][1] = gg[0];
                rg[x][2] = gg[1];
                if lane == 0 {
                    let rho = rg[x][0];
                    rg[x][3] = if rho > 0.0 { 1.0 / rho } else { 0.0 };
                }
            }
        });
    SOURCE.set((src_p, src_g));
}

/// The buffers of `level` of `reference` and `current` that one warp reads.
fn level_buffers<'a>(
    reference: &'a CpuPyramid,
    current: &'a CpuPyramid,
    level: usize,
) -> Buffers<'a> {
    let (ref_photo, ref_geo) = reference.level(level);
    let (cur_photo, cur_geo) = current.level(level);
    Buffers {
        ref_photo,
        ref_geo,
        cur_photo,
        cur_geo,
    }
}

/// Systematic sample of residuals `(r_photo, r_geo)`, `INVALID_RESIDUAL` where invalid.
pub fn sample_residuals(
    p: &WarpParams,
    reference: &CpuPyramid,
    current: &CpuPyramid,
    level: usize,
) -> Vec<[f32; 2]> {
    let bufs = level_buffers(reference, current, level);
    let count = p.samples as usize;
    let k = Warp::new(p);
    let mut out = vec![[INVALID_RESIDUAL; 2]; count];
    const BLOCK: usize = 2048;
    out.par_chunks_mut(BLOCK)
        .enumerate()
        .for_each(|(b, chunk)| sample_range(&k, &bufs, b * BLOCK, count, chunk));
    out
}

/// Per-chunk partial sums of the IRLS normal equations (the same partial layout as the GPU's
/// per-workgroup output). `chunks` is the number of partials; each covers a band of rows.
pub fn normal_equation_partials(
    p: &WarpParams,
    reference: &CpuPyramid,
    current: &CpuPyramid,
    level: usize,
    chunks: usize,
) -> Vec<Partial> {
    let bufs = level_buffers(reference, current, level);
    let h = p.height as usize;
    let k = Warp::new(p);
    let rows_per = h.div_ceil(chunks.max(1)).max(1);
    (0..h.div_ceil(rows_per))
        .into_par_iter()
        .map(|c| {
            let mut acc = PartialSums::default();
            let rows = c * rows_per..((c + 1) * rows_per).min(h);
            accumulate_rows(&k, &bufs, rows, &mut acc, None);
            acc.to_partial()
        })
        .collect()
}

/// [`normal_equation_partials`] and, from the same pass, the systematic residual sample of
/// [`sample_residuals`] at the same pose (the tracker uses it for the next iteration's scale).
pub fn normal_equations_and_sample(
    p: &WarpParams,
    reference: &CpuPyramid,
    current: &CpuPyramid,
    level: usize,
    chunks: usize,
) -> PartialsAndSample {
    let bufs = level_buffers(reference, current, level);
    let (w, h) = (p.width as usize, p.height as usize);
    let (n, count) = (w * h, p.samples as usize);
    let k = Warp::new(p);
    let rows_per = h.div_ceil(chunks.max(1)).max(1);
    let bands = h.div_ceil(rows_per);
    // Band `c` takes the samples whose pixels fall in its rows, `first[c]..first[c + 1]`,
    // written in place into the one sample.
    let first: Vec<usize> = (0..=bands)
        .map(|c| first_sample_at((c * rows_per).min(h) * w, count, n).min(count))
        .collect();
    let mut sample = vec![[INVALID_RESIDUAL; 2]; count];
    let mut slices = Vec::with_capacity(bands);
    let mut rest: &mut [[f32; 2]] = &mut sample;
    for c in 0..bands {
        let (band, after) = std::mem::take(&mut rest).split_at_mut(first[c + 1] - first[c]);
        slices.push(band);
        rest = after;
    }
    let parts = slices
        .into_par_iter()
        .enumerate()
        .map(|(c, band_sample)| {
            let rows = c * rows_per..((c + 1) * rows_per).min(h);
            let mut acc = PartialSums::default();
            let walk = SampleWalk::new(first[c], count, n);
            accumulate_rows(&k, &bufs, rows, &mut acc, Some((band_sample, walk)));
            acc.to_partial()
        })
        .collect();
    (parts, sample)
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
    let n = p.pixels();
    (0..n)
        .into_par_iter()
        .map(|i| match covisible(p, rg, cg, i) {
            0 => (0u64, 0u64),
            1 => (1, 0),
            _ => (1, 1),
        })
        .reduce(|| (0, 0), |a, b| (a.0 + b.0, a.1 + b.1))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::image::ImageF32;

    /// A vertical step edge (intensity 60 -> 180, inverse depth 0.5 -> 1.0 1/m at x = 40) with
    /// deterministic pseudo-random noise (intensity +-3, inverse depth +-0.002).
    fn noisy_step(w: usize, h: usize) -> RgbdFrame {
        let mut state = 7u32;
        let mut noise = move || {
            state = state.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            (state >> 8) as f32 / (1u32 << 24) as f32 * 2.0 - 1.0
        };
        let (mut i, mut r) = (Vec::new(), Vec::new());
        for _y in 0..h {
            for x in 0..w {
                let left = x < 40;
                i.push(if left { 60.0 } else { 180.0 } + 3.0 * noise());
                r.push(if left { 0.5 } else { 1.0 } + 0.002 * noise());
            }
        }
        RgbdFrame {
            timestamp: 0.0,
            intensity: ImageF32::from_vec(w, h, i).unwrap(),
            inverse_depth: ImageF32::from_vec(w, h, r).unwrap(),
            colour: None,
        }
    }

    #[test]
    fn bilateral_gradients_keep_edges_and_damp_noise() {
        let (w, h) = (80, 60);
        let pyr = CpuPyramid::build(&noisy_step(w, h), 1);
        let f = PyrParams::filter(w, h, 0, 3.0 * 1.7, 3.0 * 0.0012);
        let filt = pyr.filtered_level(0, &f, None);
        // Raw values are kept for the residuals.
        for k in 0..w * h {
            assert_eq!(filt.photo[k][0], pyr.photo[k][0]);
            assert_eq!(filt.geo[k][0], pyr.geo[k][0]);
        }
        // Mean squared gradient away from the edge (noise only) and across it.
        let energy = |p: &CpuPyramid, flat: bool| {
            let (mut s, mut n) = (0.0f64, 0usize);
            for y in 3..h - 3 {
                for x in 3..w - 3 {
                    let near = (38..=41).contains(&x);
                    if near == flat {
                        continue;
                    }
                    let g = p.photo[y * w + x];
                    s += f64::from(g[1] * g[1] + g[2] * g[2]);
                    n += 1;
                }
            }
            s / n as f64
        };
        let (raw_flat, bil_flat) = (energy(&pyr, true), energy(&filt, true));
        let (raw_edge, bil_edge) = (energy(&pyr, false), energy(&filt, false));
        assert!(bil_flat < 0.3 * raw_flat, "noise {raw_flat} -> {bil_flat}");
        assert!(bil_edge > 0.8 * raw_edge, "edge {raw_edge} -> {bil_edge}");
        // The inverse-depth step stays a discontinuity (no geometric gradient across it),
        // and flat inverse depth keeps valid gradients.
        let row = 30 * w;
        assert_eq!(filt.geo[row + 39][1], super::super::kernel::INVALID_GRAD);
        assert!(filt.geo[row + 20][1].abs() < 0.002);
    }
}
