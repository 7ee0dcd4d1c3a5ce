//! The CPU mirror of the warp kernels of `shaders/odometry.wgsl` (`pixel_terms`, the
//! normal-equation body, `sample_residuals`): the same per-pixel mathematics, restructured for
//! a CPU (row-wise, scalar temporaries, a SIMD-friendly 7x8 accumulator, no integer
//! divisions). Where the CPU has
//! AVX2 and FMA, the normal-equation loop computes eight pixels at a time in lanes (`lanes`:
//! the same operations as the scalar [`terms`], so residuals are bit-identical) and appends
//! their terms to the sum block eight at a time. The same equations, operation for operation
//! up to floating-point reassociation; `parity_tests.rs` compares them with the WGSL, and the
//! unit tests below the lanes with the scalar loop and both with the literal transcription of
//! the WGSL in `oracle.rs`.

use super::config::{GeometricParam, GeometricSampling, Linearisation};
use super::kernel::{PartialSums, WarpParams, INVALID_GRAD, INVALID_RESIDUAL, MIN_DEPTH};
use super::robust::weight;

/// The four buffers one warp reads, all of the same pyramid level: the reference frame's
/// `(I, dI/du, dI/dv, 0)` and `(rho, drho/du, drho/dv, z)` per pixel, and the current frame's.
#[derive(Clone, Copy)]
pub(crate) struct Buffers<'a> {
    pub(crate) ref_photo: &'a [[f32; 4]],
    pub(crate) ref_geo: &'a [[f32; 4]],
    pub(crate) cur_photo: &'a [[f32; 4]],
    pub(crate) cur_geo: &'a [[f32; 4]],
}

/// Level constants of one warp, unpacked from [`WarpParams`].
#[derive(Clone)]
pub(crate) struct Warp {
    pub(crate) w: usize,
    h: usize,
    /// `(w - 1) as f32` and `(h - 1) as f32`: the last valid bilinear base coordinates.
    wm1: f32,
    hm1: f32,
    fx: f32,
    fy: f32,
    cx: f32,
    cy: f32,
    r: [[f32; 4]; 3],
    photo: bool,
    geo: bool,
    depth_param: bool,
    linear_geo: bool,
    /// [`super::Linearisation::Reference`]: Jacobians from the reference pixel's gradients
    /// at the reference point, geometric residual in the reference frame.
    reference: bool,
    pub(crate) est: u32,
    pub(crate) sigma: [f32; 2],
    pub(crate) nu: [f32; 2],
    /// Residual locations `[mu_photo, mu_geo]` subtracted before weighting and summing.
    pub(crate) mu: [f32; 2],
    /// `(x - cx) / fx` per column and `(y - cy) / fy` per row (the same f32 operations as the
    /// per-pixel mirror, computed once).
    rx: Vec<f32>,
    ry: Vec<f32>,
}

impl Warp {
    pub(crate) fn new(p: &WarpParams) -> Self {
        Self {
            w: p.width as usize,
            h: p.height as usize,
            wm1: p.width.saturating_sub(1) as f32,
            hm1: p.height.saturating_sub(1) as f32,
            fx: p.fx,
            fy: p.fy,
            cx: p.cx,
            cy: p.cy,
            r: p.rot,
            photo: p.photometric(),
            geo: p.geometric_term(),
            depth_param: p.geometric == GeometricParam::Depth as u32,
            linear_geo: p.sampling == GeometricSampling::Linear as u32,
            reference: p.linearisation == Linearisation::Reference as u32,
            est: p.estimator,
            sigma: [p.sigma_photo, p.sigma_geo],
            nu: [p.nu_photo, p.nu_geo],
            mu: [p.mu_photo, p.mu_geo],
            rx: (0..p.width).map(|x| (x as f32 - p.cx) / p.fx).collect(),
            ry: (0..p.height).map(|y| (y as f32 - p.cy) / p.fy).collect(),
        }
    }
}

/// Residuals (and optionally Jacobians) of the reference pixel with `rp = (I, dI/du, dI/dv, _)`
/// and `rg = (rho, drho/du, drho/dv, z = 1 / rho)` (rho > 0) at normalised coordinates
/// `rx = (x - cx) / fx`, `ry = (y - cy) / fy`. `INVALID_RESIDUAL` marks an invalid residual.
#[inline(always)]
fn terms<const JAC: bool>(
    k: &Warp,
    rp: [f32; 4],
    rg: [f32; 4],
    rx: f32,
    ry: f32,
    bufs: &Buffers,
) -> (f32, [f32; 6], f32, [f32; 6]) {
    let (ref_i, z) = (rp[0], rg[3]);
    let invalid = (INVALID_RESIDUAL, [0.0; 6], INVALID_RESIDUAL, [0.0; 6]);
    let px = rx * z;
    let py = ry * z;
    let r = &k.r;
    let qx = r[0][0] * px + r[0][1] * py + r[0][2] * z + r[0][3];
    let qy = r[1][0] * px + r[1][1] * py + r[1][2] * z + r[1][3];
    let qz = r[2][0] * px + r[2][1] * py + r[2][2] * z + r[2][3];
    if qz < MIN_DEPTH {
        return invalid;
    }
    let iz = 1.0 / qz;
    let u = k.fx * qx * iz + k.cx;
    let v = k.fy * qy * iz + k.cy;
    if !(u >= 0.0 && v >= 0.0 && u < k.wm1 && v < k.hm1) {
        return invalid;
    }
    let (mut r_p, mut jp, mut r_g, mut jg) = invalid;
    if k.photo {
        // u, v >= 0: truncation is floor.
        let (xi, yi) = (u as i32 as usize, v as i32 as usize);
        let (ax, ay) = (u - xi as f32, v - yi as f32);
        let i0 = yi * k.w + xi;
        let top = &bufs.cur_photo[i0..i0 + 2];
        let bot = &bufs.cur_photo[i0 + k.w..i0 + k.w + 2];
        let (b00, b10, b01, b11) = (
            (1.0 - ax) * (1.0 - ay),
            ax * (1.0 - ay),
            (1.0 - ax) * ay,
            ax * ay,
        );
        let c0 = b00 * top[0][0] + b10 * top[1][0] + b01 * bot[0][0] + b11 * bot[1][0];
        r_p = c0 - ref_i;
        if JAC {
            jp = if k.reference {
                // The reference pixel's stored gradient, at the reference point.
                jacobian(k, rp[1], rp[2], 0.0, px, py, z, rg[0])
            } else {
                let c1 = b00 * top[0][1] + b10 * top[1][1] + b01 * bot[0][1] + b11 * bot[1][1];
                let c2 = b00 * top[0][2] + b10 * top[1][2] + b01 * bot[0][2] + b11 * bot[1][2];
                jacobian(k, c1, c2, 0.0, qx, qy, qz, iz)
            };
        }
    }
    if k.geo {
        let (xn, yn) = ((u + 0.5) as i32 as usize, (v + 0.5) as i32 as usize);
        let g = bufs.cur_geo[yn * k.w + xn];
        // The reference form differentiates the reference's inverse depth: it needs its
        // gradient. The current sample's gradient must be valid in both forms: a nearest
        // sample at a depth discontinuity may come from either side of it.
        let ref_ok = !k.reference || rg[1] != INVALID_GRAD;
        if g[0] > 0.0 && g[1] != INVALID_GRAD && ref_ok {
            // Nearest sample, or its first-order extension to (u, v) along the stored
            // gradient (`GeometricSampling::Linear`).
            let rho = if k.linear_geo {
                g[0] + g[1] * (u - xn as f32) + g[2] * (v - yn as f32)
            } else {
                g[0]
            };
            if k.reference {
                // The sample as a point of B on the ray through w(p), `q rho_B^-1 / q_z`,
                // moved into A by `T^-1 = (R^T, -R^T t)`: only its depth in A is needed, the
                // third column of R dotted with the point minus t.
                let s = 1.0 / (rho * qz);
                let r = &k.r;
                let (dx, dy, dq) = (qx * s - r[0][3], qy * s - r[1][3], qz * s - r[2][3]);
                let za = r[0][2] * dx + r[1][2] * dy + r[2][2] * dq;
                if za >= MIN_DEPTH {
                    let rho_a = rg[0];
                    let (res, gu, gv, dz) = if k.depth_param {
                        let ig2 = 1.0 / (rho_a * rho_a);
                        (za - z, -rg[1] * ig2, -rg[2] * ig2, -1.0)
                    } else {
                        (1.0 / za - rho_a, rg[1], rg[2], rho_a * rho_a)
                    };
                    r_g = res;
                    if JAC {
                        jg = jacobian(k, gu, gv, dz, px, py, z, rho_a);
                    }
                }
            } else {
                let (res, gu, gv, dz) = if k.depth_param {
                    let ig2 = 1.0 / (rho * rho);
                    (1.0 / rho - qz, -g[1] * ig2, -g[2] * ig2, -1.0)
                } else {
                    (rho - iz, g[1], g[2], iz * iz)
                };
                r_g = res;
                if JAC {
                    jg = jacobian(k, gu, gv, dz, qx, qy, qz, iz);
                }
            }
        }
    }
    (r_p, jp, r_g, jg)
}

/// Residuals (and Jacobians when `JAC`) of reference pixel `i` of the level, as the row loops
/// compute them: `(r_photo, J_photo, r_geo, J_geo)`, `INVALID_RESIDUAL` where a residual is
/// invalid (also where the pixel has no depth). The reference buffers must cache `z = 1 / rho`
/// in `geo.w`, as [`super::cpu::CpuPyramid`] does.
pub(crate) fn pixel_terms<const JAC: bool>(
    k: &Warp,
    bufs: &Buffers,
    i: usize,
) -> (f32, [f32; 6], f32, [f32; 6]) {
    let g = bufs.ref_geo[i];
    if g[0] <= 0.0 {
        return (INVALID_RESIDUAL, [0.0; 6], INVALID_RESIDUAL, [0.0; 6]);
    }
    terms::<JAC>(k, bufs.ref_photo[i], g, k.rx[i % k.w], k.ry[i / k.w], bufs)
}

/// `[jt; q x jt]` with `jt = (a, b, -(a qx + b qy) / qz + dz)`, `a = gu fx / qz`,
/// `b = gv fy / qz` (eq. 6.12-6.13): the image gradient `(gu, gv)` times the projection
/// Jacobian at `q` (the warped point, or the reference point in the reference form) times
/// `[I | -q^]`, plus `dz` times the twist's motion of `q` along the optical axis.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn jacobian(k: &Warp, gu: f32, gv: f32, dz: f32, qx: f32, qy: f32, qz: f32, iz: f32) -> [f32; 6] {
    let a = gu * k.fx * iz;
    let b = gv * k.fy * iz;
    let c = -(a * qx + b * qy) * iz + dz;
    [a, b, c, qy * c - qz * b, qz * a - qx * c, qx * b - qy * a]
}

/// Walks the systematic sample `i_k = floor(k n / count)` ([`super::kernel::sample_index`])
/// from `k0` on, as quotient and remainder (no division per step).
pub(crate) struct SampleWalk {
    /// The current sample's pixel index.
    pub(crate) i: usize,
    rem: usize,
    step: usize,
    step_rem: usize,
    count: usize,
}

impl SampleWalk {
    pub(crate) fn new(k0: usize, count: usize, n: usize) -> Self {
        let count = count.max(1);
        let num = k0 as u64 * n as u64;
        Self {
            i: (num / count as u64) as usize,
            rem: (num % count as u64) as usize,
            step: n / count,
            step_rem: n % count,
            count,
        }
    }

    /// Moves to the next sample; returns how far the pixel index moved.
    #[inline(always)]
    pub(crate) fn advance(&mut self) -> usize {
        let mut d = self.step;
        self.rem += self.step_rem;
        if self.rem >= self.count {
            self.rem -= self.count;
            d += 1;
        }
        self.i += d;
        d
    }
}

/// The first sample index `k` whose pixel `floor(k n / count)` is at or after pixel `i`.
pub(crate) fn first_sample_at(i: usize, count: usize, n: usize) -> usize {
    ((i as u64 * count as u64).div_ceil(n.max(1) as u64)) as usize
}

/// Accumulates the IRLS normal equations of rows `rows` of the reference level.
pub(crate) fn accumulate_rows(
    k: &Warp,
    bufs: &Buffers,
    rows: std::ops::Range<usize>,
    out: &mut PartialSums,
    sample: Option<(&mut [[f32; 2]], SampleWalk)>,
) {
    #[cfg(target_arch = "x86_64")]
    {
        if std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma") {
            // SAFETY: the CPU supports the features enabled on `accumulate_rows_avx2`.
            unsafe {
                accumulate_rows_avx2(k, bufs, rows, out, sample);
            }
            return;
        }
    }
    accumulate_rows_body(k, bufs, rows, out, sample);
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
fn accumulate_rows_avx2(
    k: &Warp,
    bufs: &Buffers,
    rows: std::ops::Range<usize>,
    out: &mut PartialSums,
    sample: Option<(&mut [[f32; 2]], SampleWalk)>,
) {
    let n = k.w * k.h;
    // The lanes gather with i32 float offsets (4 per pixel).
    let fits_i32 = n < (i32::MAX as usize) / 4 - 8;
    if fits_i32
        && bufs.ref_photo.len() >= n
        && bufs.ref_geo.len() >= n
        && bufs.cur_photo.len() >= n
        && bufs.cur_geo.len() >= n
    {
        // SAFETY: this function runs only with AVX2 and FMA enabled, and the buffer sizes
        // and the offset range are checked above.
        unsafe {
            lanes::accumulate_rows_lanes(k, bufs, rows, out, sample);
        }
    } else {
        accumulate_rows_body(k, bufs, rows, out, sample);
    }
}

/// Entries per block of [`TermBlock`]: small enough to stay in L1, a multiple of 32.
const BLOCK: usize = 64;

/// Jacobians, residuals and weights of up to [`BLOCK`] residual terms, structure of arrays, so
/// that the sums of products vectorise across terms. Full blocks are summed into the f64
/// partial as they fill up.
struct TermBlock {
    /// `J_a` for a = 0..6 and `r` as the 7th row.
    v: [[f32; BLOCK]; 7],
    /// Robust weight over sigma^2.
    w: [f32; BLOCK],
    len: usize,
}

impl TermBlock {
    fn new() -> Self {
        Self {
            v: [[0.0; BLOCK]; 7],
            w: [0.0; BLOCK],
            len: 0,
        }
    }

    #[inline(always)]
    fn push(&mut self, j: [f32; 6], r: f32, wt: f32, out: &mut PartialSums) {
        // `len < BLOCK` always holds here; the mask lets the compiler drop the bounds checks.
        let i = self.len & (BLOCK - 1);
        let vals = [j[0], j[1], j[2], j[3], j[4], j[5], r];
        for (a, val) in vals.into_iter().enumerate() {
            self.v[a][i] = val;
        }
        self.w[i] = wt;
        self.len = i + 1;
        if self.len == BLOCK {
            self.flush_into(out);
        }
    }

    /// Appends eight terms (`j[a][l]`, `r[l]`, `wt[l]` for lane `l`) at an 8-aligned slot:
    /// the block is first padded with zero-weighted, zero terms (which add exactly 0).
    #[inline(always)]
    fn push8(&mut self, j: &[[f32; 8]; 6], r: &[f32; 8], wt: &[f32; 8], out: &mut PartialSums) {
        let pad = self.len.next_multiple_of(8).min(BLOCK);
        if pad > self.len {
            self.w[self.len..pad].fill(0.0);
            for a in 0..7 {
                self.v[a][self.len..pad].fill(0.0);
            }
            self.len = pad;
        }
        if self.len == BLOCK {
            self.flush_into(out);
        }
        // `len` is a multiple of 8 below BLOCK; the mask lets the compiler drop the checks.
        let i = self.len & (BLOCK - 8);
        for a in 0..6 {
            self.v[a][i..i + 8].copy_from_slice(&j[a]);
        }
        self.v[6][i..i + 8].copy_from_slice(r);
        self.w[i..i + 8].copy_from_slice(wt);
        self.len = i + 8;
        if self.len == BLOCK {
            self.flush_into(out);
        }
    }

    /// Adds `sum w v_a v_b` (upper triangle, gradient, cost) of the block to `out`.
    #[inline(always)]
    fn flush_into(&mut self, out: &mut PartialSums) {
        let n = self.len.min(BLOCK);
        // Unused slots are zero-weighted so that the sums always run over whole blocks.
        self.w[n..].fill(0.0);
        for a in 0..7 {
            self.v[a][n..].fill(0.0);
        }
        let mut wv = [[0.0f32; BLOCK]; 7];
        for a in 0..7 {
            for k in 0..BLOCK {
                wv[a][k] = self.w[k] * self.v[a][k];
            }
        }
        let mut k = 0;
        for a in 0..6 {
            for b in a..6 {
                out.h[k] += f64::from(dot(&wv[a], &self.v[b]));
                k += 1;
            }
        }
        for a in 0..6 {
            out.g[a] += f64::from(dot(&wv[a], &self.v[6]));
        }
        out.cost += f64::from(dot(&wv[6], &self.v[6]));
        self.len = 0;
    }
}

/// `sum x_i y_i` over one block in 4 x 8 independent f32 lanes (vectorisable without
/// reassociation flags, and without one long dependency chain). Each product is added with
/// one rounding (`mul_add`): one instruction where the processor fuses them, and the same
/// sum on every path of the row loops.
#[inline(always)]
fn dot(x: &[f32; BLOCK], y: &[f32; BLOCK]) -> f32 {
    let mut lanes = [[0.0f32; 8]; 4];
    for c in 0..BLOCK / 32 {
        for (q, lane) in lanes.iter_mut().enumerate() {
            for l in 0..8 {
                let i = 32 * c + 8 * q + l;
                lane[l] = x[i].mul_add(y[i], lane[l]);
            }
        }
    }
    // Pairwise: vector adds and a few shuffles instead of a chain of 31 scalar adds.
    let mut s = [0.0f32; 8];
    for (l, v) in s.iter_mut().enumerate() {
        *v = (lanes[0][l] + lanes[1][l]) + (lanes[2][l] + lanes[3][l]);
    }
    let h = [s[0] + s[4], s[1] + s[5], s[2] + s[6], s[3] + s[7]];
    (h[0] + h[2]) + (h[1] + h[3])
}

/// What the row loops do with a reference pixel's terms: the sample slot (if the pixel is
/// sampled), the weighted sums and the counts. The scalar loop feeds it pixel by pixel; the
/// lane loop records its samples and counts the same way and appends its terms to the same
/// block eight at a time (`TermBlock::push8`).
struct Consumer<'a> {
    slots: &'a mut [[f32; 2]],
    slot: usize,
    walk: SampleWalk,
    sp: f32,
    sg: f32,
    isp2: f32,
    isg2: f32,
    est: u32,
    nu: [f32; 2],
    mu: [f32; 2],
    buf: TermBlock,
    n_photo: u64,
    n_geo: u64,
}

impl<'a> Consumer<'a> {
    fn new(k: &Warp, sample: Option<(&'a mut [[f32; 2]], SampleWalk)>) -> Self {
        // The sample residuals of these rows (if wanted): `slots` in order, at the walk's
        // pixels.
        let (slots, walk) = match sample {
            Some((s, wk)) => (s, wk),
            None => (&mut [][..], SampleWalk::new(0, 1, 0)),
        };
        let (sp, sg) = (k.sigma[0], k.sigma[1]);
        Self {
            slots,
            slot: 0,
            walk,
            sp,
            sg,
            isp2: 1.0 / (sp * sp),
            isg2: 1.0 / (sg * sg),
            est: k.est,
            nu: k.nu,
            mu: k.mu,
            buf: TermBlock::new(),
            n_photo: 0,
            n_geo: 0,
        }
    }

    /// Whether pixel `i` is the next sampled pixel.
    #[inline(always)]
    fn sampled(&self, i: usize) -> bool {
        self.slot < self.slots.len() && self.walk.i == i
    }

    /// Records `r` as the sample of the current pixel and moves the walk on.
    #[inline(always)]
    fn record(&mut self, r: [f32; 2]) {
        self.slots[self.slot] = r;
        self.slot += 1;
        self.walk.advance();
    }

    /// A pixel without reference depth.
    #[inline(always)]
    fn skip(&mut self, i: usize) {
        if self.sampled(i) {
            self.record([INVALID_RESIDUAL; 2]);
        }
    }

    /// A pixel with reference depth and its (possibly invalid) terms.
    #[inline(always)]
    fn pixel(
        &mut self,
        i: usize,
        (r_p, j_p, r_g, j_g): (f32, [f32; 6], f32, [f32; 6]),
        out: &mut PartialSums,
    ) {
        if self.sampled(i) {
            self.record([r_p, r_g]);
        }
        if r_p != INVALID_RESIDUAL {
            let r_p = r_p - self.mu[0];
            let wt = weight(self.est, r_p / self.sp, self.nu[0]) * self.isp2;
            self.buf.push(j_p, r_p, wt, out);
            self.n_photo += 1;
        }
        if r_g != INVALID_RESIDUAL {
            let r_g = r_g - self.mu[1];
            let wt = weight(self.est, r_g / self.sg, self.nu[1]) * self.isg2;
            self.buf.push(j_g, r_g, wt, out);
            self.n_geo += 1;
        }
    }

    // Inlined so that the last block's sums use the caller's fused multiply-add (the lane
    // loop's AVX2 + FMA); a separate copy would call the C library's `fmaf` per product.
    #[inline(always)]
    fn finish(mut self, out: &mut PartialSums) {
        self.buf.flush_into(out);
        out.n_photo += self.n_photo as f64;
        out.n_geo += self.n_geo as f64;
    }
}

/// The scalar terms of reference pixels `xs` of row `y`, fed to `c`.
#[inline(always)]
fn scalar_pixels(
    k: &Warp,
    bufs: &Buffers,
    y: usize,
    xs: std::ops::Range<usize>,
    c: &mut Consumer,
    out: &mut PartialSums,
) {
    let w = k.w;
    let ry = k.ry[y];
    for x in xs {
        let i = y * w + x;
        let gi = bufs.ref_geo[i];
        // geo.w caches z = 1 / rho (see `CpuPyramid`).
        if gi[0] <= 0.0 {
            c.skip(i);
            continue;
        }
        let t = terms::<true>(k, bufs.ref_photo[i], gi, k.rx[x], ry, bufs);
        c.pixel(i, t, out);
    }
}

#[inline(always)]
fn accumulate_rows_body(
    k: &Warp,
    bufs: &Buffers,
    rows: std::ops::Range<usize>,
    out: &mut PartialSums,
    sample: Option<(&mut [[f32; 2]], SampleWalk)>,
) {
    let mut c = Consumer::new(k, sample);
    for y in rows {
        scalar_pixels(k, bufs, y, 0..k.w, &mut c, out);
    }
    c.finish(out);
}

/// The row loop with the per-pixel warp, interpolation and Jacobians computed for eight
/// pixels at a time in AVX2 lanes. Every lane repeats the scalar [`terms`] operation for
/// operation (separate multiplies and adds, no fused multiply-add, IEEE division), so the
/// terms are bit-identical to the scalar loop's, and they are consumed in the same order.
#[cfg(target_arch = "x86_64")]
mod lanes {
    use super::*;
    use std::arch::x86_64::*;

    /// One kind of term (photometric or geometric) of eight pixels, one entry per lane.
    #[derive(Default)]
    struct Terms8 {
        /// Residuals, [`INVALID_RESIDUAL`] where there is none (for the sample).
        r: [f32; 8],
        /// The same with 0 where there is none, the Jacobians and the IRLS weights over
        /// sigma^2 (0 there too): ready to be summed.
        rz: [f32; 8],
        j: [[f32; 8]; 6],
        w: [f32; 8],
        /// Number of valid terms.
        n: u32,
    }

    impl Terms8 {
        /// No term in any lane.
        fn none(&mut self) {
            self.r = [INVALID_RESIDUAL; 8];
            self.n = 0;
        }

        /// Residuals `res` where `valid` (kept as they are for the sample), with `res - mu`
        /// and its weights (estimator `est`, scale `sigma`, `isig2 = 1 / sigma^2`, degrees
        /// of freedom `nu`, location `mu`) for the sums, and the Jacobians of [`jacobian8`]
        /// from the image gradient `(gu, gv)` and depth term `dz`.
        #[target_feature(enable = "avx2,fma")]
        #[inline]
        #[allow(clippy::too_many_arguments)]
        unsafe fn set(
            &mut self,
            res: __m256,
            valid: __m256,
            (est, sigma, isig2, nu, mu): (u32, f32, f32, f32, f32),
            (fx, fy): (__m256, __m256),
            (gu, gv, dz): (__m256, __m256, __m256),
            q: [__m256; 3],
            iz: __m256,
        ) {
            unsafe {
                let invalid = _mm256_set1_ps(INVALID_RESIDUAL);
                _mm256_storeu_ps(self.r.as_mut_ptr(), _mm256_blendv_ps(invalid, res, valid));
                let centred = _mm256_sub_ps(res, _mm256_set1_ps(mu));
                _mm256_storeu_ps(self.rz.as_mut_ptr(), _mm256_and_ps(centred, valid));
                let wt = weights8(est, centred, valid, sigma, isig2, nu);
                _mm256_storeu_ps(self.w.as_mut_ptr(), wt);
                self.n = _mm256_movemask_ps(valid).count_ones();
                jacobian8(fx, fy, gu, gv, dz, q, iz, valid, &mut self.j);
            }
        }
    }

    /// Terms of eight pixels.
    #[derive(Default)]
    struct Eight {
        /// Reference pixel has depth.
        has_depth: [bool; 8],
        photo: Terms8,
        geo: Terms8,
    }

    /// The rows `rows` of [`super::accumulate_rows`], eight pixels at a time.
    ///
    /// # Safety
    /// The CPU has AVX2 and FMA, all four buffers hold at least `k.w * k.h` pixels, and
    /// `4 * k.w * k.h + 32` fits an `i32` (the lanes' float offsets).
    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn accumulate_rows_lanes(
        k: &Warp,
        bufs: &Buffers,
        rows: std::ops::Range<usize>,
        out: &mut PartialSums,
        sample: Option<(&mut [[f32; 2]], SampleWalk)>,
    ) {
        let w = k.w;
        let mut c = Consumer::new(k, sample);
        let mut e = Eight::default();
        for y in rows {
            let mut x = 0;
            while x + 8 <= w {
                // SAFETY: pixels y * w + x .. + 8 are inside the level (x + 8 <= w, y < h),
                // and the caller guarantees the buffer sizes and CPU features.
                unsafe { eight(k, &c, bufs, y, x, &mut e) };
                c.eight(y * w + x, &e, out);
                x += 8;
            }
            scalar_pixels(k, bufs, y, x..w, &mut c, out);
        }
        c.finish(out);
    }

    impl Consumer<'_> {
        /// The terms `e` of pixels `i0 .. i0 + 8`: their samples (the walk's pixels
        /// increase), sums and counts.
        #[inline(always)]
        fn eight(&mut self, i0: usize, e: &Eight, out: &mut PartialSums) {
            while self.slot < self.slots.len() && self.walk.i < i0 + 8 {
                let l = self.walk.i - i0;
                self.record(if e.has_depth[l] {
                    [e.photo.r[l], e.geo.r[l]]
                } else {
                    [INVALID_RESIDUAL; 2]
                });
            }
            if e.photo.n > 0 {
                self.buf.push8(&e.photo.j, &e.photo.rz, &e.photo.w, out);
                self.n_photo += u64::from(e.photo.n);
            }
            if e.geo.n > 0 {
                self.buf.push8(&e.geo.j, &e.geo.rz, &e.geo.w, out);
                self.n_geo += u64::from(e.geo.n);
            }
        }
    }

    /// One row of `R p + t` in lanes: `((r0 px + r1 py) + r2 z) + r3`, as the scalar code.
    #[target_feature(enable = "avx2,fma")]
    #[inline]
    fn transform_row(r: &[f32; 4], px: __m256, py: __m256, z: __m256) -> __m256 {
        let set = _mm256_set1_ps;
        _mm256_add_ps(
            _mm256_add_ps(
                _mm256_add_ps(_mm256_mul_ps(set(r[0]), px), _mm256_mul_ps(set(r[1]), py)),
                _mm256_mul_ps(set(r[2]), z),
            ),
            set(r[3]),
        )
    }

    /// The four channels of eight `[f32; 4]` pixels, lane `l`'s starting at float `at(l)` of
    /// `base`: lane `l` of output `c` is channel `c` of that pixel (one 4-float load per lane
    /// and a transpose, cheaper than a gather per channel).
    ///
    /// # Safety
    /// AVX2; floats `at(l) .. at(l) + 4` of `base` are readable for every lane.
    #[target_feature(enable = "avx2,fma")]
    #[inline]
    unsafe fn channels8(base: *const f32, at: impl Fn(usize) -> usize) -> [__m256; 4] {
        // SAFETY: each lane's four floats are readable, as the caller guarantees.
        let r = |k: usize| unsafe {
            _mm256_insertf128_ps::<1>(
                _mm256_castps128_ps256(_mm_loadu_ps(base.add(at(k)))),
                _mm_loadu_ps(base.add(at(k + 4))),
            )
        };
        transpose4x2([r(0), r(1), r(2), r(3)])
    }

    /// Each 128-bit half of the rows `r` transposed as a 4x4 block: float `l` of half `h` of
    /// output `k` is float `k` of half `h` of `r[l]`.
    #[target_feature(enable = "avx2,fma")]
    #[inline]
    fn transpose4x2(r: [__m256; 4]) -> [__m256; 4] {
        let t0 = _mm256_unpacklo_ps(r[0], r[1]);
        let t1 = _mm256_unpackhi_ps(r[0], r[1]);
        let t2 = _mm256_unpacklo_ps(r[2], r[3]);
        let t3 = _mm256_unpackhi_ps(r[2], r[3]);
        [
            _mm256_shuffle_ps::<0x44>(t0, t2),
            _mm256_shuffle_ps::<0xEE>(t0, t2),
            _mm256_shuffle_ps::<0x44>(t1, t3),
            _mm256_shuffle_ps::<0xEE>(t1, t3),
        ]
    }

    /// The lanes of `v` as `usize` (non-negative by construction at the call sites).
    #[target_feature(enable = "avx2,fma")]
    #[inline]
    fn lanes_usize(v: __m256i) -> [usize; 8] {
        let mut a = [0i32; 8];
        // SAFETY: 8 i32s into an 8-element array.
        unsafe { _mm256_storeu_si256(a.as_mut_ptr() as *mut __m256i, v) };
        a.map(|x| x as usize)
    }

    /// Rows `r[l]` (lane `l`) transposed: lane `l` of output `k` is `r[l][k]`.
    #[target_feature(enable = "avx2,fma")]
    #[inline]
    fn transpose8(r: [__m256; 8]) -> [__m256; 8] {
        let [s0, s1, s2, s3] = transpose4x2([r[0], r[1], r[2], r[3]]);
        let [s4, s5, s6, s7] = transpose4x2([r[4], r[5], r[6], r[7]]);
        [
            _mm256_permute2f128_ps::<0x20>(s0, s4),
            _mm256_permute2f128_ps::<0x20>(s1, s5),
            _mm256_permute2f128_ps::<0x20>(s2, s6),
            _mm256_permute2f128_ps::<0x20>(s3, s7),
            _mm256_permute2f128_ps::<0x31>(s0, s4),
            _mm256_permute2f128_ps::<0x31>(s1, s5),
            _mm256_permute2f128_ps::<0x31>(s2, s6),
            _mm256_permute2f128_ps::<0x31>(s3, s7),
        ]
    }

    /// Bilinear samples of channels 0, 1 and 2 of `[f32; 4]` pixels: lane `l`'s top-left
    /// corner starts at float `top[l]` of `base` and its bottom-left at `bottom[l]`, weights
    /// `b` (`b00, b10, b01, b11`), summed left to right as the scalar code. Each lane's two
    /// horizontal neighbours are one 8-float load per row (transposed into channels), which
    /// costs less than a gather per corner and channel. Lanes whose result is not used must
    /// still point into the buffer (index 0 does).
    ///
    /// # Safety
    /// AVX2 and FMA; floats `top[l] .. top[l] + 8` and `bottom[l] .. bottom[l] + 8` are in
    /// the buffer for every lane.
    #[target_feature(enable = "avx2,fma")]
    #[inline]
    unsafe fn bilinear3(
        base: *const f32,
        top: __m256i,
        bottom: __m256i,
        b: [__m256; 4],
    ) -> [__m256; 3] {
        // SAFETY: the caller guarantees both 8-float rows of every lane are in the buffer.
        let load = |o: usize| unsafe { _mm256_loadu_ps(base.add(o)) };
        let rt = transpose8(lanes_usize(top).map(load));
        let rb = transpose8(lanes_usize(bottom).map(load));
        let mix = |c: usize| {
            _mm256_add_ps(
                _mm256_add_ps(
                    _mm256_add_ps(_mm256_mul_ps(b[0], rt[c]), _mm256_mul_ps(b[1], rt[4 + c])),
                    _mm256_mul_ps(b[2], rb[c]),
                ),
                _mm256_mul_ps(b[3], rb[4 + c]),
            )
        };
        [mix(0), mix(1), mix(2)]
    }

    /// [`weight`]`(est, r / sigma, nu) * isig2` in lanes (the same operations), 0 where
    /// `valid` is clear.
    #[target_feature(enable = "avx2,fma")]
    #[inline]
    fn weights8(est: u32, r: __m256, valid: __m256, sigma: f32, isig2: f32, nu: f32) -> __m256 {
        use crate::odometry::robust::{HUBER_K, TUKEY_C};
        let set = _mm256_set1_ps;
        let one = set(1.0);
        let z = _mm256_div_ps(r, set(sigma));
        let w = match est {
            1 => {
                let a = _mm256_andnot_ps(set(-0.0), z);
                let far = _mm256_div_ps(set(HUBER_K), a);
                _mm256_blendv_ps(far, one, _mm256_cmp_ps::<_CMP_LE_OQ>(a, set(HUBER_K)))
            }
            2 => {
                let t = _mm256_div_ps(z, set(TUKEY_C));
                let sq = _mm256_sub_ps(one, _mm256_mul_ps(t, t));
                let inside = _mm256_cmp_ps::<_CMP_LT_OQ>(_mm256_andnot_ps(set(-0.0), t), one);
                _mm256_and_ps(_mm256_mul_ps(sq, sq), inside)
            }
            3 => _mm256_div_ps(
                _mm256_add_ps(set(nu), one),
                _mm256_add_ps(set(nu), _mm256_mul_ps(z, z)),
            ),
            _ => one,
        };
        _mm256_and_ps(_mm256_mul_ps(w, set(isig2)), valid)
    }

    /// `[jt; q x jt]` of [`super::jacobian`] in lanes, same operations.
    #[target_feature(enable = "avx2,fma")]
    #[inline]
    #[allow(clippy::too_many_arguments)]
    unsafe fn jacobian8(
        fx: __m256,
        fy: __m256,
        gu: __m256,
        gv: __m256,
        dz: __m256,
        q: [__m256; 3],
        iz: __m256,
        valid: __m256,
        out: &mut [[f32; 8]; 6],
    ) {
        unsafe {
            let a = _mm256_mul_ps(_mm256_mul_ps(gu, fx), iz);
            let b = _mm256_mul_ps(_mm256_mul_ps(gv, fy), iz);
            let t = _mm256_add_ps(_mm256_mul_ps(a, q[0]), _mm256_mul_ps(b, q[1]));
            let neg = _mm256_xor_ps(t, _mm256_set1_ps(-0.0));
            let c = _mm256_add_ps(_mm256_mul_ps(neg, iz), dz);
            let j = [
                a,
                b,
                c,
                _mm256_sub_ps(_mm256_mul_ps(q[1], c), _mm256_mul_ps(q[2], b)),
                _mm256_sub_ps(_mm256_mul_ps(q[2], a), _mm256_mul_ps(q[0], c)),
                _mm256_sub_ps(_mm256_mul_ps(q[0], b), _mm256_mul_ps(q[1], a)),
            ];
            for (o, v) in out.iter_mut().zip(j) {
                _mm256_storeu_ps(o.as_mut_ptr(), _mm256_and_ps(v, valid));
            }
        }
    }

    /// The terms of pixels `x .. x + 8` of row `y` into `e`.
    #[target_feature(enable = "avx2,fma")]
    #[inline]
    unsafe fn eight(k: &Warp, c: &Consumer, bufs: &Buffers, y: usize, x: usize, e: &mut Eight) {
        unsafe {
            let i = y * k.w + x;
            let set = _mm256_set1_ps;
            let rg_base = bufs.ref_geo.as_ptr().add(i) as *const f32;
            let ref_geo = channels8(rg_base, |l| 4 * l);
            let (rho_ref, z) = (ref_geo[0], ref_geo[3]);
            // `!(rho <= 0)`, as the scalar test (NaN counts as depth there too).
            let has_depth = _mm256_cmp_ps::<_CMP_NLE_UQ>(rho_ref, _mm256_setzero_ps());
            let rp_base = bufs.ref_photo.as_ptr().add(i) as *const f32;
            let ref_photo = channels8(rp_base, |l| 4 * l);
            let ref_i = ref_photo[0];
            let rx = _mm256_loadu_ps(k.rx.as_ptr().add(x));
            let ry = set(k.ry[y]);
            let px = _mm256_mul_ps(rx, z);
            let py = _mm256_mul_ps(ry, z);
            let qx = transform_row(&k.r[0], px, py, z);
            let qy = transform_row(&k.r[1], px, py, z);
            let qz = transform_row(&k.r[2], px, py, z);
            let iz = _mm256_div_ps(set(1.0), qz);
            let (fx, fy) = (set(k.fx), set(k.fy));
            let u = _mm256_add_ps(_mm256_mul_ps(_mm256_mul_ps(fx, qx), iz), set(k.cx));
            let v = _mm256_add_ps(_mm256_mul_ps(_mm256_mul_ps(fy, qy), iz), set(k.cy));
            let zero = _mm256_setzero_ps();
            let mut valid =
                _mm256_and_ps(has_depth, _mm256_cmp_ps::<_CMP_NLT_UQ>(qz, set(MIN_DEPTH)));
            valid = _mm256_and_ps(valid, _mm256_cmp_ps::<_CMP_GE_OQ>(u, zero));
            valid = _mm256_and_ps(valid, _mm256_cmp_ps::<_CMP_GE_OQ>(v, zero));
            valid = _mm256_and_ps(valid, _mm256_cmp_ps::<_CMP_LT_OQ>(u, set(k.wm1)));
            valid = _mm256_and_ps(valid, _mm256_cmp_ps::<_CMP_LT_OQ>(v, set(k.hm1)));
            let q = [qx, qy, qz];
            // The point and inverse depth the Jacobians are taken at.
            let (jq, jiz) = if k.reference {
                ([px, py, z], rho_ref)
            } else {
                (q, iz)
            };
            let wv = _mm256_set1_epi32(k.w as i32);
            let mut hd = [0.0f32; 8];
            _mm256_storeu_ps(hd.as_mut_ptr(), has_depth);
            for (o, m) in e.has_depth.iter_mut().zip(hd) {
                *o = m.to_bits() != 0;
            }
            if k.photo {
                // Lanes outside the image read pixel 0 and the row below it (index 0);
                // `valid` masks their terms.
                let xi = _mm256_cvttps_epi32(u);
                let yi = _mm256_cvttps_epi32(v);
                let ax = _mm256_sub_ps(u, _mm256_cvtepi32_ps(xi));
                let ay = _mm256_sub_ps(v, _mm256_cvtepi32_ps(yi));
                let i0 = _mm256_add_epi32(_mm256_mullo_epi32(yi, wv), xi);
                let i0 = _mm256_and_si256(i0, _mm256_castps_si256(valid));
                let t0 = _mm256_slli_epi32::<2>(i0);
                let b0 = _mm256_add_epi32(t0, _mm256_slli_epi32::<2>(wv));
                let one = set(1.0);
                let (nax, nay) = (_mm256_sub_ps(one, ax), _mm256_sub_ps(one, ay));
                let b00 = _mm256_mul_ps(nax, nay);
                let b10 = _mm256_mul_ps(ax, nay);
                let b01 = _mm256_mul_ps(nax, ay);
                let b11 = _mm256_mul_ps(ax, ay);
                let base = bufs.cur_photo.as_ptr() as *const f32;
                let [c0, c1, c2] = bilinear3(base, t0, b0, [b00, b10, b01, b11]);
                let rp = _mm256_sub_ps(c0, ref_i);
                let robust = (c.est, c.sp, c.isp2, c.nu[0], c.mu[0]);
                let (gu, gv) = if k.reference {
                    // The reference pixel's stored gradient.
                    (ref_photo[1], ref_photo[2])
                } else {
                    (c1, c2)
                };
                e.photo
                    .set(rp, valid, robust, (fx, fy), (gu, gv, zero), jq, jiz);
            } else {
                e.photo.none();
            }
            if k.geo {
                let half = set(0.5);
                let xn = _mm256_cvttps_epi32(_mm256_add_ps(u, half));
                let yn = _mm256_cvttps_epi32(_mm256_add_ps(v, half));
                let n = _mm256_add_epi32(_mm256_mullo_epi32(yn, wv), xn);
                let n = _mm256_and_si256(n, _mm256_castps_si256(valid));
                let n4 = _mm256_slli_epi32::<2>(n);
                let base = bufs.cur_geo.as_ptr() as *const f32;
                // Lanes outside the image read pixel 0; `valid` masks their terms.
                let n4 = lanes_usize(n4);
                let [g0, g1, g2, _] = channels8(base, |l| n4[l]);
                let mut gvalid = _mm256_and_ps(
                    valid,
                    _mm256_and_ps(
                        _mm256_cmp_ps::<_CMP_GT_OQ>(g0, zero),
                        _mm256_cmp_ps::<_CMP_NEQ_UQ>(g1, set(INVALID_GRAD)),
                    ),
                );
                let rho = if k.linear_geo {
                    let du = _mm256_sub_ps(u, _mm256_cvtepi32_ps(xn));
                    let dv = _mm256_sub_ps(v, _mm256_cvtepi32_ps(yn));
                    _mm256_add_ps(
                        _mm256_add_ps(g0, _mm256_mul_ps(g1, du)),
                        _mm256_mul_ps(g2, dv),
                    )
                } else {
                    g0
                };
                let neg = set(-0.0);
                let (res, gu, gv, dz) = if k.reference {
                    // As the scalar `terms`: the sample's depth in A.
                    let (a1, a2) = (ref_geo[1], ref_geo[2]);
                    let s = _mm256_div_ps(set(1.0), _mm256_mul_ps(rho, qz));
                    let r = &k.r;
                    let dx = _mm256_sub_ps(_mm256_mul_ps(qx, s), set(r[0][3]));
                    let dy = _mm256_sub_ps(_mm256_mul_ps(qy, s), set(r[1][3]));
                    let dq = _mm256_sub_ps(_mm256_mul_ps(qz, s), set(r[2][3]));
                    let za = _mm256_add_ps(
                        _mm256_add_ps(
                            _mm256_mul_ps(set(r[0][2]), dx),
                            _mm256_mul_ps(set(r[1][2]), dy),
                        ),
                        _mm256_mul_ps(set(r[2][2]), dq),
                    );
                    gvalid = _mm256_and_ps(
                        gvalid,
                        _mm256_and_ps(
                            _mm256_cmp_ps::<_CMP_NEQ_UQ>(a1, set(INVALID_GRAD)),
                            _mm256_cmp_ps::<_CMP_GE_OQ>(za, set(MIN_DEPTH)),
                        ),
                    );
                    if k.depth_param {
                        let ig2 = _mm256_div_ps(set(1.0), _mm256_mul_ps(rho_ref, rho_ref));
                        (
                            _mm256_sub_ps(za, z),
                            _mm256_mul_ps(_mm256_xor_ps(a1, neg), ig2),
                            _mm256_mul_ps(_mm256_xor_ps(a2, neg), ig2),
                            set(-1.0),
                        )
                    } else {
                        (
                            _mm256_sub_ps(_mm256_div_ps(set(1.0), za), rho_ref),
                            a1,
                            a2,
                            _mm256_mul_ps(rho_ref, rho_ref),
                        )
                    }
                } else if k.depth_param {
                    let ig2 = _mm256_div_ps(set(1.0), _mm256_mul_ps(rho, rho));
                    (
                        _mm256_sub_ps(_mm256_div_ps(set(1.0), rho), qz),
                        _mm256_mul_ps(_mm256_xor_ps(g1, neg), ig2),
                        _mm256_mul_ps(_mm256_xor_ps(g2, neg), ig2),
                        set(-1.0),
                    )
                } else {
                    (_mm256_sub_ps(rho, iz), g1, g2, _mm256_mul_ps(iz, iz))
                };
                let robust = (c.est, c.sg, c.isg2, c.nu[1], c.mu[1]);
                e.geo
                    .set(res, gvalid, robust, (fx, fy), (gu, gv, dz), jq, jiz);
            } else {
                e.geo.none();
            }
        }
    }
}

/// Residuals `(r_photo, r_geo)` of the systematic sample `k0..k0 + out.len()` of `count`
/// samples among the level's pixels ([`super::kernel::sample_index`], computed incrementally).
pub(crate) fn sample_range(
    k: &Warp,
    bufs: &Buffers,
    k0: usize,
    count: usize,
    out: &mut [[f32; 2]],
) {
    let mut walk = SampleWalk::new(k0, count, k.w * k.h);
    let (mut x, mut y) = (walk.i % k.w, walk.i / k.w);
    for o in out.iter_mut() {
        let i = walk.i;
        let g = bufs.ref_geo.get(i).copied().unwrap_or_default();
        *o = if g[0] > 0.0 {
            let (r_p, _, r_g, _) = terms::<false>(k, bufs.ref_photo[i], g, k.rx[x], k.ry[y], bufs);
            [r_p, r_g]
        } else {
            [INVALID_RESIDUAL, INVALID_RESIDUAL]
        };
        x += walk.advance();
        while x >= k.w {
            x -= k.w;
            y += 1;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::Se3;
    use crate::image::{ImageF32, RgbdFrame};
    use crate::odometry::cpu::CpuPyramid;
    use crate::odometry::kernel::{sample_index, Partial};
    use crate::odometry::oracle::{accumulate_pixel, pixel_terms as oracle_terms};

    /// The 28 sums of a partial (h, g, cost) in order, and the two counts.
    fn sums(h: &[f64], g: &[f64], cost: f64) -> Vec<f64> {
        h.iter().chain(g).copied().chain([cost]).collect()
    }

    fn sums64(p: &PartialSums) -> (Vec<f64>, f64, f64) {
        (sums(&p.h, &p.g, p.cost), p.n_photo, p.n_geo)
    }

    fn sums32(p: &Partial) -> (Vec<f64>, f64, f64) {
        let h: Vec<f64> = p.h.iter().map(|&v| f64::from(v)).collect();
        let g: Vec<f64> = p.g.iter().map(|&v| f64::from(v)).collect();
        (
            sums(&h, &g, f64::from(p.cost)),
            f64::from(p.n_photo),
            f64::from(p.n_geo),
        )
    }

    fn frame(w: usize, h: usize, shift: f32) -> RgbdFrame {
        let mut i = Vec::new();
        let mut r = Vec::new();
        for y in 0..h {
            for x in 0..w {
                let (fx, fy) = (x as f32 + shift, y as f32);
                i.push(
                    120.0 + 60.0 * (fx * 0.07).sin() * (fy * 0.05).cos() + 9.0 * (fx * 0.5).sin(),
                );
                // Holes and a step in depth so invalid and masked pixels occur.
                let hole = (x * 7 + y * 3) % 23 == 0;
                r.push(if hole {
                    0.0
                } else if x > w / 2 {
                    0.4
                } else {
                    0.6 + 0.0008 * fx + 0.0006 * fy
                });
            }
        }
        RgbdFrame {
            timestamp: 0.0,
            intensity: ImageF32::from_vec(w, h, i).unwrap(),
            inverse_depth: ImageF32::from_vec(w, h, r).unwrap(),
            colour: None,
        }
    }

    /// Every estimator (0-3) with each term set (bit 0 photometric, bit 1 geometric) and
    /// option (bit 0 depth parametrisation, bit 1 first-order inverse-depth sampling, bit 2
    /// the reference-frame linearisation) the tests cover: `(estimator, terms, param)`.
    fn variants() -> impl Iterator<Item = (u32, u32, u32)> {
        (0..4u32).flat_map(|est| {
            [
                (3u32, 0u32),
                (1, 0),
                (2, 0),
                (3, 1),
                (3, 2),
                (2, 3),
                (3, 4),
                (1, 4),
                (2, 4),
                (3, 5),
                (3, 6),
                (2, 7),
            ]
            .map(|(terms, param)| (est, terms, param))
        })
    }

    /// Warp parameters of a `w x h` level (f = 90, principal point `c`) at `pose`, with
    /// `count` samples and robust scales that suit the test frames.
    fn params(
        w: usize,
        h: usize,
        c: [f32; 2],
        count: u32,
        v: (u32, u32, u32),
        pose: &Se3,
    ) -> WarpParams {
        let (est, terms, param) = v;
        let mut p = WarpParams {
            width: w as u32,
            height: h as u32,
            offset: 0,
            samples: count,
            fx: 90.0,
            fy: 90.0,
            cx: c[0],
            cy: c[1],
            rot: [[0.0; 4]; 3],
            sigma_photo: 4.0,
            sigma_geo: if param & 1 == 1 { 0.01 } else { 0.003 },
            nu_photo: 4.0,
            nu_geo: 6.0,
            estimator: est,
            terms,
            geometric: param & 1,
            sampling: (param >> 1) & 1,
            occlusion: 0.0,
            // Non-zero locations, so the loops' centring is compared too.
            mu_photo: 0.75,
            mu_geo: if param & 1 == 1 { 0.002 } else { 0.0006 },
            linearisation: (param >> 2) & 1,
        };
        p.set_pose(pose);
        p
    }

    /// The AVX2 lane loop (chosen by `accumulate_rows` where the CPU has AVX2 and FMA) gives
    /// the scalar loop's counts and sample bit for bit (its residuals are computed with the
    /// same operations) and the same sums up to f32 summation order (its terms fill the
    /// blocks eight at a time), for widths that are not a multiple of 8, poses that move
    /// pixels out of the image, and every estimator, term set, parametrisation and sampling.
    #[test]
    fn lane_loop_matches_the_scalar_loop() {
        #[cfg(target_arch = "x86_64")]
        if !(std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma")) {
            eprintln!("no AVX2+FMA: the lane loop is not used on this CPU");
            return;
        }
        let (w, h) = (101usize, 37usize);
        let a = CpuPyramid::build(&frame(w, h, 0.0), 1);
        let b = CpuPyramid::build(&frame(w, h, 2.1), 1);
        let bufs = Buffers {
            ref_photo: &a.photo,
            ref_geo: &a.geo,
            cur_photo: &b.photo,
            cur_geo: &b.geo,
        };
        let poses = [
            Se3::exp(&[0.01, -0.004, 0.02, 0.003, -0.005, 0.002]),
            // Large enough that a band of pixels leaves the image.
            Se3::exp(&[0.12, 0.05, -0.03, 0.02, 0.06, -0.01]),
        ];
        for pose in poses {
            for v in variants() {
                let (est, terms_mask, param) = v;
                let p = params(w, h, [50.0, 18.0], 700, v, &pose);
                let k = Warp::new(&p);
                let count = p.samples as usize;
                let run = |lanes: bool| {
                    let mut acc = PartialSums::default();
                    let mut smp = vec![[0.0f32; 2]; count];
                    let walk = SampleWalk::new(0, count, w * h);
                    let s = Some((&mut smp[..], walk));
                    if lanes {
                        accumulate_rows(&k, &bufs, 0..h, &mut acc, s);
                    } else {
                        accumulate_rows_body(&k, &bufs, 0..h, &mut acc, s);
                    }
                    (sums64(&acc), smp)
                };
                let ((la, lnp, lng), ls) = run(true);
                let ((sa, snp, sng), ss) = run(false);
                assert!(snp + sng > 500.0, "too few terms: {snp} {sng}");
                assert_eq!(lnp, snp, "photometric count");
                assert_eq!(lng, sng, "geometric count");
                let scale = sa.iter().map(|v| v.abs()).fold(0.0, f64::max);
                for i in 0..28 {
                    assert!(
                        (la[i] - sa[i]).abs() <= 1e-6 * scale,
                        "entry {i} (est {est}, terms {terms_mask}, param {param}): {} vs {}",
                        la[i],
                        sa[i]
                    );
                }
                for (x, y) in ls.iter().zip(&ss) {
                    assert_eq!(x.map(f32::to_bits), y.map(f32::to_bits));
                }
            }
        }
    }

    /// The row loops agree with the per-pixel reference mirror (which the GPU parity test
    /// checks against the WGSL) for every estimator, term set and parametrisation.
    #[test]
    fn row_loops_match_the_reference_mirror() {
        let (w, h) = (96usize, 72usize);
        let a = CpuPyramid::build(&frame(w, h, 0.0), 1);
        let b = CpuPyramid::build(&frame(w, h, 1.3), 1);
        let bufs = Buffers {
            ref_photo: &a.photo,
            ref_geo: &a.geo,
            cur_photo: &b.photo,
            cur_geo: &b.geo,
        };
        let pose = Se3::exp(&[0.01, -0.004, 0.02, 0.003, -0.005, 0.002]);
        for v in variants() {
            let p = params(w, h, [47.5, 35.5], 1000, v, &pose);
            let mut want = Partial::default();
            for i in 0..w * h {
                accumulate_pixel(&p, &a.photo, &a.geo, &b.photo, &b.geo, i, &mut want);
            }
            let mut acc = PartialSums::default();
            accumulate_rows(&Warp::new(&p), &bufs, 0..h, &mut acc, None);
            let (got, gnp, gng) = sums64(&acc);
            let (want, wnp, wng) = sums32(&want);
            assert_eq!(gnp, wnp, "photometric count");
            assert_eq!(gng, wng, "geometric count");
            assert!(wnp + wng > 1000.0);
            let scale = want.iter().map(|v| v.abs()).fold(0.0, f64::max);
            for i in 0..28 {
                let d = (got[i] - want[i]).abs();
                assert!(
                    d <= 1e-4 * scale + 1e-4 * got[i].abs(),
                    "entry {i}: {} vs {}",
                    got[i],
                    want[i]
                );
            }
            // The sample taken during the reduction equals the separate sample pass.
            let (_, fused) = crate::odometry::cpu::normal_equations_and_sample(&p, &a, &b, 0, 5);
            let separate = crate::odometry::cpu::sample_residuals(&p, &a, &b, 0);
            assert_eq!(fused.len(), separate.len());
            for (f, s) in fused.iter().zip(&separate) {
                assert!(
                    (f[0] - s[0]).abs() <= 1e-5 * s[0].abs().max(1.0),
                    "{f:?} vs {s:?}"
                );
                assert!(
                    (f[1] - s[1]).abs() <= 1e-5 * s[1].abs().max(1.0),
                    "{f:?} vs {s:?}"
                );
            }
            // The incremental sample walks the same pixels as `sample_index`.
            let count = 1000usize;
            let mut s = vec![[0.0f32; 2]; count];
            sample_range(&Warp::new(&p), &bufs, 0, count, &mut s[..600]);
            sample_range(&Warp::new(&p), &bufs, 600, count, &mut s[600..]);
            for (kk, got) in s.iter().enumerate() {
                let i = sample_index(kk as u32, count as u32, (w * h) as u32) as usize;
                let t = oracle_terms(&p, &a.photo, &a.geo, &b.photo, &b.geo, i, false);
                let want = [
                    t.r_photo.unwrap_or(INVALID_RESIDUAL),
                    t.r_geo.unwrap_or(INVALID_RESIDUAL),
                ];
                for c in 0..2 {
                    assert!(
                        (got[c] - want[c]).abs() <= 1e-5 * want[c].abs().max(1.0),
                        "sample {kk}: {got:?} vs {want:?}"
                    );
                }
            }
        }
    }

    /// A smooth synthetic frame: a slanted plane with low-frequency texture.
    fn smooth_frame(w: usize, h: usize) -> RgbdFrame {
        let mut i = Vec::new();
        let mut r = Vec::new();
        for y in 0..h {
            for x in 0..w {
                let (fx, fy) = (x as f32, y as f32);
                i.push(120.0 + 60.0 * (fx * 0.07).sin() * (fy * 0.05).cos() + 0.2 * fx);
                // A plane: inverse depth exactly linear in the pixel coordinates, so the
                // nearest-neighbour geometric residual has a well-defined slope.
                r.push(0.6 + 0.0008 * fx + 0.0005 * fy);
            }
        }
        RgbdFrame {
            timestamp: 0.0,
            intensity: ImageF32::from_vec(w, h, i).unwrap(),
            inverse_depth: ImageF32::from_vec(w, h, r).unwrap(),
            colour: None,
        }
    }

    /// The Jacobians of the row loop (eq. 6.12-6.13) match central differences of its
    /// residuals, for both geometric parametrisations.
    #[test]
    fn jacobians_match_finite_differences() {
        let (w, h) = (160usize, 120usize);
        let f = smooth_frame(w, h);
        let pyr = CpuPyramid::build(&f, 1);
        let bufs = Buffers {
            ref_photo: &pyr.photo,
            ref_geo: &pyr.geo,
            cur_photo: &pyr.photo,
            cur_geo: &pyr.geo,
        };
        let cur_from_ref = Se3::exp(&[0.01, -0.005, 0.02, 0.004, -0.006, 0.002]);
        for param in [0u32, 1] {
            let mut p = params(w, h, [79.5, 59.5], 0, (0, 3, param), &cur_from_ref);
            p.fx = 130.0;
            p.fy = 130.0;
            let at = |p: &WarpParams, i: usize, jac: bool| {
                let k = Warp::new(p);
                if jac {
                    super::pixel_terms::<true>(&k, &bufs, i)
                } else {
                    super::pixel_terms::<false>(&k, &bufs, i)
                }
            };
            let mut checked = 0;
            for i in [60 * w + 80, 40 * w + 50, 70 * w + 100, 30 * w + 120] {
                p.set_pose(&cur_from_ref);
                let (rp, j_photo, rg, j_geo) = at(&p, i, true);
                if rp == INVALID_RESIDUAL || rg == INVALID_RESIDUAL {
                    continue;
                }
                for k in 0..6 {
                    // Small steps for the bilinear photometric residual; steps that move the warp
                    // by several pixels for the geometric one, which samples inverse depth at the
                    // nearest pixel (tiny steps would see a flat function).
                    let fd = |p: &mut WarpParams, eps: f64| {
                        let mut d = [0.0; 6];
                        d[k] = eps;
                        p.set_pose(&(Se3::exp(&d) * cur_from_ref));
                        let a = at(p, i, false);
                        d[k] = -eps;
                        p.set_pose(&(Se3::exp(&d) * cur_from_ref));
                        let b = at(p, i, false);
                        let e = 2.0 * eps as f32;
                        ((a.0 - b.0) / e, (a.2 - b.2) / e)
                    };
                    let (num_p, _) = fd(&mut p, 1e-4);
                    let (_, num_g) = fd(&mut p, 2e-2);
                    let tol_p = 0.03 * j_photo.iter().map(|x| x.abs()).fold(0.0, f32::max);
                    let tol_g = 0.1 * j_geo.iter().map(|x| x.abs()).fold(0.0, f32::max);
                    assert!(
                        (num_p - j_photo[k]).abs() < tol_p,
                        "param {param} photo k={k}: fd {num_p} vs {}",
                        j_photo[k]
                    );
                    assert!(
                        (num_g - j_geo[k]).abs() < tol_g,
                        "param {param} geo k={k}: fd {num_g} vs {}",
                        j_geo[k]
                    );
                }
                checked += 1;
            }
            assert!(checked >= 3);
        }
    }

    /// A textured plane seen from the reference camera (A) and from the current camera at
    /// `cur_from_ref` (B), `w x h` pixels at focal length 130 and principal point the image
    /// centre: `(reference, current)`, consistent (the residuals vanish at that pose up to
    /// interpolation).
    fn plane_pair(w: usize, h: usize, cur_from_ref: &Se3) -> (RgbdFrame, RgbdFrame) {
        use glam::DVec3;
        let (f, cx, cy) = (130.0, (w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0);
        let n = DVec3::new(0.15, -0.2, 1.0).normalize();
        let d = 1.5;
        // Texture on the plane as a function of the point in A (m), smooth at pixel scale.
        let tex = |x: DVec3| 120.0 + 60.0 * (4.0 * x.x).sin() * (3.0 * x.y).cos() + 25.0 * x.x;
        let r = cur_from_ref.rotation_matrix();
        let t = cur_from_ref.translation;
        let (n_b, d_b) = (r * n, d + (r * n).dot(t));
        let render = |n: DVec3, d: f64, to_a: &dyn Fn(DVec3) -> DVec3| {
            let (mut i, mut rho) = (Vec::new(), Vec::new());
            for y in 0..h {
                for x in 0..w {
                    let ray = DVec3::new((x as f64 - cx) / f, (y as f64 - cy) / f, 1.0);
                    let inv = n.dot(ray) / d;
                    rho.push(inv as f32);
                    i.push(tex(to_a(ray / inv)) as f32);
                }
            }
            RgbdFrame {
                timestamp: 0.0,
                intensity: ImageF32::from_vec(w, h, i).unwrap(),
                inverse_depth: ImageF32::from_vec(w, h, rho).unwrap(),
                colour: None,
            }
        };
        let a = render(n, d, &|x| x);
        let b = render(n_b, d_b, &|x| r.transpose() * (x - t));
        (a, b)
    }

    /// The reference-frame Jacobians (nabla I_A, nabla W_A at X_A, eq. 4.16-4.17, 6.12-6.13)
    /// match central differences of the residuals with respect to a right twist of
    /// `cur_from_ref` (`T exp(e)`) at the pose that aligns a consistent pair, for both
    /// geometric parametrisations; and the tracker's left twist `Ad(T) delta` is that right
    /// twist. The pose rotates by 0.1 rad, so the left-twist derivatives (what the
    /// current-frame form computes) differ from the right-twist ones by more than the
    /// tolerance, and a small baseline keeps the parallax the reference form neglects
    /// (moving X_A off the surface) well inside it.
    #[test]
    fn reference_jacobians_match_finite_differences() {
        let (w, h) = (160usize, 120usize);
        let cur_from_ref = Se3::exp(&[0.008, -0.004, 0.006, 0.06, -0.07, 0.03]);
        let (fa, fb) = plane_pair(w, h, &cur_from_ref);
        let (a, b) = (CpuPyramid::build(&fa, 1), CpuPyramid::build(&fb, 1));
        let bufs = Buffers {
            ref_photo: &a.photo,
            ref_geo: &a.geo,
            cur_photo: &b.photo,
            cur_geo: &b.geo,
        };
        let (mut worst_left, mut worst_right) = (0.0f32, [0.0f32; 2]);
        // param: bit 1 first-order sampling (the plane's inverse depth is affine in the
        // pixel coordinates, so the sample is smooth in the pose), bit 2 reference form;
        // with and without bit 0 (depth parametrisation).
        for param in [6u32, 7] {
            let mut p = params(w, h, [79.5, 59.5], 0, (0, 3, param), &cur_from_ref);
            p.fx = 130.0;
            p.fy = 130.0;
            let at = |p: &WarpParams, i: usize, jac: bool| {
                let k = Warp::new(p);
                if jac {
                    super::pixel_terms::<true>(&k, &bufs, i)
                } else {
                    super::pixel_terms::<false>(&k, &bufs, i)
                }
            };
            let mut checked = 0;
            for i in [
                60 * w + 80,
                40 * w + 50,
                70 * w + 100,
                30 * w + 110,
                85 * w + 60,
            ] {
                p.set_pose(&cur_from_ref);
                let (rp, j_photo, rg, j_geo) = at(&p, i, true);
                assert!(
                    rp != INVALID_RESIDUAL && rg != INVALID_RESIDUAL,
                    "pixel {i}"
                );
                // Aligned: the residuals are interpolation-sized.
                assert!(rp.abs() < 0.5, "photometric residual {rp} at {i}");
                let tol_rg = if param & 1 == 1 { 1e-4 } else { 1e-5 };
                assert!(rg.abs() < tol_rg, "geometric residual {rg} at {i}");
                let fd = |p: &mut WarpParams, k: usize, left: bool| {
                    let eps = 2e-3;
                    let mut d = [0.0; 6];
                    let mut eval = |s: f64| {
                        d[k] = s * eps;
                        let e = Se3::exp(&d);
                        p.set_pose(&if left {
                            e * cur_from_ref
                        } else {
                            cur_from_ref * e
                        });
                        at(p, i, false)
                    };
                    let (x, y) = (eval(1.0), eval(-1.0));
                    let e = 2.0 * eps as f32;
                    ((x.0 - y.0) / e, (x.2 - y.2) / e)
                };
                let max_p = j_photo.iter().map(|x| x.abs()).fold(0.0, f32::max);
                let max_g = j_geo.iter().map(|x| x.abs()).fold(0.0, f32::max);
                for k in 0..6 {
                    let (num_p, num_g) = fd(&mut p, k, false);
                    assert!(
                        (num_p - j_photo[k]).abs() < 0.03 * max_p,
                        "param {param} pixel {i} photo k={k}: fd {num_p} vs {}",
                        j_photo[k]
                    );
                    assert!(
                        (num_g - j_geo[k]).abs() < 0.03 * max_g,
                        "param {param} pixel {i} geo k={k}: fd {num_g} vs {}",
                        j_geo[k]
                    );
                    worst_right[0] = worst_right[0].max((num_p - j_photo[k]).abs() / max_p);
                    worst_right[1] = worst_right[1].max((num_g - j_geo[k]).abs() / max_g);
                    let (left_p, _) = fd(&mut p, k, true);
                    worst_left = worst_left.max((left_p - j_photo[k]).abs() / max_p);
                }
                checked += 1;
            }
            assert_eq!(checked, 5);
        }
        eprintln!(
            "largest differences over max |J|: photometric {}, geometric {}, left twist {}",
            worst_right[0], worst_right[1], worst_left
        );
        // The right twist and the wrong (left) one are told apart at this pose.
        assert!(
            worst_left > 0.06,
            "left-twist derivatives within {worst_left}"
        );
        // The tracker's update: exp(Ad(T) delta) T = T exp(delta).
        let delta = [0.01, -0.02, 0.005, 0.03, 0.01, -0.02];
        let lt = crate::odometry::tracker::left_twist(
            crate::odometry::Linearisation::Reference,
            &cur_from_ref,
            &delta,
        );
        let diff = (Se3::exp(&lt) * cur_from_ref).inverse() * (cur_from_ref * Se3::exp(&delta));
        assert!(
            diff.log().iter().all(|x| x.abs() < 1e-12),
            "{:?}",
            diff.log()
        );
    }
}
