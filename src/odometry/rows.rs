//! The CPU backend's hot loops: the per-pixel mathematics of [`super::kernel::pixel_terms`]
//! and [`super::kernel::accumulate_pixel`], restructured for a CPU (row-wise, scalar
//! temporaries, a SIMD-friendly 7x8 accumulator, no integer divisions). The same equations,
//! operation for operation up to floating-point reassociation; `tests/odometry_parity.rs`
//! compares them with the WGSL and the unit test below with the reference mirror.

use super::kernel::{WarpParams, INVALID_GRAD, INVALID_RESIDUAL, MIN_DEPTH, PARTIAL_LEN};
use super::robust::weight;

/// Level constants of one warp, unpacked from [`WarpParams`].
#[derive(Clone)]
pub(crate) struct Warp {
    w: usize,
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
    est: u32,
    sigma: [f32; 2],
    nu: [f32; 2],
    /// `(x - cx) / fx` per column and `(y - cy) / fy` per row (the same f32 operations as the
    /// per-pixel mirror, computed once).
    rx: Vec<f32>,
    ry: Vec<f32>,
}

impl Warp {
    pub(crate) fn new(p: &WarpParams) -> Self {
        Self {
            w: p.dims[0] as usize,
            h: p.dims[1] as usize,
            wm1: p.dims[0].saturating_sub(1) as f32,
            hm1: p.dims[1].saturating_sub(1) as f32,
            fx: p.intr[0],
            fy: p.intr[1],
            cx: p.intr[2],
            cy: p.intr[3],
            r: p.rot,
            photo: p.flags[1] & 1 != 0,
            geo: p.flags[1] & 2 != 0,
            depth_param: p.flags[2] & 1 == 1,
            linear_geo: p.flags[2] & 2 == 2,
            est: p.flags[0],
            sigma: [p.robust[0], p.robust[1]],
            nu: [p.robust[2], p.robust[3]],
            rx: (0..p.dims[0])
                .map(|x| (x as f32 - p.intr[2]) / p.intr[0])
                .collect(),
            ry: (0..p.dims[1])
                .map(|y| (y as f32 - p.intr[3]) / p.intr[1])
                .collect(),
        }
    }
}

/// Residuals (and optionally Jacobians) of the reference pixel with intensity `ref_i`, depth
/// `z = 1 / rho` (rho > 0) and normalised coordinates `rx = (x - cx) / fx`,
/// `ry = (y - cy) / fy`. `INVALID_RESIDUAL` marks an invalid residual.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn terms<const JAC: bool>(
    k: &Warp,
    ref_i: f32,
    z: f32,
    rx: f32,
    ry: f32,
    cur_photo: &[[f32; 4]],
    cur_geo: &[[f32; 4]],
) -> (f32, [f32; 6], f32, [f32; 6]) {
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
    let (mut rp, mut jp, mut rg, mut jg) = invalid;
    if k.photo {
        // u, v >= 0: truncation is floor.
        let (xi, yi) = (u as i32 as usize, v as i32 as usize);
        let (ax, ay) = (u - xi as f32, v - yi as f32);
        let i0 = yi * k.w + xi;
        let top = &cur_photo[i0..i0 + 2];
        let bot = &cur_photo[i0 + k.w..i0 + k.w + 2];
        let (b00, b10, b01, b11) = (
            (1.0 - ax) * (1.0 - ay),
            ax * (1.0 - ay),
            (1.0 - ax) * ay,
            ax * ay,
        );
        let c0 = b00 * top[0][0] + b10 * top[1][0] + b01 * bot[0][0] + b11 * bot[1][0];
        rp = c0 - ref_i;
        if JAC {
            let c1 = b00 * top[0][1] + b10 * top[1][1] + b01 * bot[0][1] + b11 * bot[1][1];
            let c2 = b00 * top[0][2] + b10 * top[1][2] + b01 * bot[0][2] + b11 * bot[1][2];
            jp = jacobian(k, c1, c2, 0.0, qx, qy, qz, iz);
        }
    }
    if k.geo {
        let (xn, yn) = ((u + 0.5) as i32 as usize, (v + 0.5) as i32 as usize);
        let g = cur_geo[yn * k.w + xn];
        if g[0] > 0.0 && g[1] != INVALID_GRAD {
            // Nearest sample, or its first-order extension to (u, v) along the stored
            // gradient (`GeometricSampling::Linear`).
            let rho = if k.linear_geo {
                g[0] + g[1] * (u - xn as f32) + g[2] * (v - yn as f32)
            } else {
                g[0]
            };
            let (res, gu, gv, dz) = if k.depth_param {
                let ig2 = 1.0 / (rho * rho);
                (1.0 / rho - qz, -g[1] * ig2, -g[2] * ig2, -1.0)
            } else {
                (rho - iz, g[1], g[2], iz * iz)
            };
            rg = res;
            if JAC {
                jg = jacobian(k, gu, gv, dz, qx, qy, qz, iz);
            }
        }
    }
    (rp, jp, rg, jg)
}

/// `[jt; q x jt]` with `jt = (a, b, -(a qx + b qy) / qz + dz)`, `a = gu fx / qz`,
/// `b = gv fy / qz` (eq. 6.12-6.13).
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
#[allow(clippy::too_many_arguments)]
pub(crate) fn accumulate_rows(
    k: &Warp,
    ref_photo: &[[f32; 4]],
    ref_geo: &[[f32; 4]],
    cur_photo: &[[f32; 4]],
    cur_geo: &[[f32; 4]],
    rows: std::ops::Range<usize>,
    out: &mut [f64; PARTIAL_LEN],
    sample: Option<(&mut [[f32; 2]], SampleWalk)>,
) {
    #[cfg(target_arch = "x86_64")]
    {
        if std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma") {
            // SAFETY: the CPU supports the features enabled on `accumulate_rows_avx2`.
            unsafe {
                accumulate_rows_avx2(k, ref_photo, ref_geo, cur_photo, cur_geo, rows, out, sample);
            }
            return;
        }
    }
    accumulate_rows_body(k, ref_photo, ref_geo, cur_photo, cur_geo, rows, out, sample);
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
#[allow(clippy::too_many_arguments)]
fn accumulate_rows_avx2(
    k: &Warp,
    ref_photo: &[[f32; 4]],
    ref_geo: &[[f32; 4]],
    cur_photo: &[[f32; 4]],
    cur_geo: &[[f32; 4]],
    rows: std::ops::Range<usize>,
    out: &mut [f64; PARTIAL_LEN],
    sample: Option<(&mut [[f32; 2]], SampleWalk)>,
) {
    accumulate_rows_body(k, ref_photo, ref_geo, cur_photo, cur_geo, rows, out, sample);
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
    fn push(&mut self, j: [f32; 6], r: f32, wt: f32, out: &mut [f64; PARTIAL_LEN]) {
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

    /// Adds `sum w v_a v_b` (upper triangle, gradient, cost) of the block to `out`.
    #[inline(always)]
    fn flush_into(&mut self, out: &mut [f64; PARTIAL_LEN]) {
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
                out[k] += f64::from(dot(&wv[a], &self.v[b]));
                k += 1;
            }
        }
        for a in 0..6 {
            out[21 + a] += f64::from(dot(&wv[a], &self.v[6]));
        }
        out[27] += f64::from(dot(&wv[6], &self.v[6]));
        self.len = 0;
    }
}

/// `sum x_i y_i` over one block in 4 x 8 independent f32 lanes (vectorisable without
/// reassociation flags, and without one long dependency chain).
#[inline(always)]
fn dot(x: &[f32; BLOCK], y: &[f32; BLOCK]) -> f32 {
    let mut lanes = [[0.0f32; 8]; 4];
    for c in 0..BLOCK / 32 {
        for (q, lane) in lanes.iter_mut().enumerate() {
            for l in 0..8 {
                let i = 32 * c + 8 * q + l;
                lane[l] += x[i] * y[i];
            }
        }
    }
    lanes.iter().flatten().sum::<f32>()
}

#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn accumulate_rows_body(
    k: &Warp,
    ref_photo: &[[f32; 4]],
    ref_geo: &[[f32; 4]],
    cur_photo: &[[f32; 4]],
    cur_geo: &[[f32; 4]],
    rows: std::ops::Range<usize>,
    out: &mut [f64; PARTIAL_LEN],
    sample: Option<(&mut [[f32; 2]], SampleWalk)>,
) {
    // The sample residuals of these rows (if wanted): `slots` in order, at the walk's pixels.
    let (slots, mut walk) = match sample {
        Some((s, wk)) => (s, wk),
        None => (&mut [][..], SampleWalk::new(0, 1, 0)),
    };
    let mut slot = 0usize;
    let w = k.w;
    let (sp, sg) = (k.sigma[0], k.sigma[1]);
    let (isp2, isg2) = (1.0 / (sp * sp), 1.0 / (sg * sg));
    let mut buf = TermBlock::new();
    let (mut n_photo, mut n_geo) = (0u64, 0u64);
    for y in rows {
        let rp = &ref_photo[y * w..(y + 1) * w];
        let rg = &ref_geo[y * w..(y + 1) * w];
        let ry = k.ry[y];
        for (x, ((pi, gi), &rx)) in rp.iter().zip(rg).zip(&k.rx).enumerate() {
            let sampled = slot < slots.len() && walk.i == y * w + x;
            // geo.w caches z = 1 / rho (see `CpuPyramid`).
            if gi[0] <= 0.0 {
                if sampled {
                    slots[slot] = [INVALID_RESIDUAL; 2];
                    slot += 1;
                    walk.advance();
                }
                continue;
            }
            let (r_p, j_p, r_g, j_g) = terms::<true>(k, pi[0], gi[3], rx, ry, cur_photo, cur_geo);
            if sampled {
                slots[slot] = [r_p, r_g];
                slot += 1;
                walk.advance();
            }
            if r_p != INVALID_RESIDUAL {
                let wt = weight(k.est, r_p / sp, k.nu[0]) * isp2;
                buf.push(j_p, r_p, wt, out);
                n_photo += 1;
            }
            if r_g != INVALID_RESIDUAL {
                let wt = weight(k.est, r_g / sg, k.nu[1]) * isg2;
                buf.push(j_g, r_g, wt, out);
                n_geo += 1;
            }
        }
    }
    buf.flush_into(out);
    out[28] += n_photo as f64;
    out[29] += n_geo as f64;
}

/// Residuals `(r_photo, r_geo)` of the systematic sample `k0..k0 + out.len()` of `count`
/// samples among the level's pixels ([`super::kernel::sample_index`], computed incrementally).
#[allow(clippy::too_many_arguments)]
pub(crate) fn sample_range(
    k: &Warp,
    ref_photo: &[[f32; 4]],
    ref_geo: &[[f32; 4]],
    cur_photo: &[[f32; 4]],
    cur_geo: &[[f32; 4]],
    k0: usize,
    count: usize,
    out: &mut [[f32; 2]],
) {
    let mut walk = SampleWalk::new(k0, count, k.w * k.h);
    let (mut x, mut y) = (walk.i % k.w, walk.i / k.w);
    for o in out.iter_mut() {
        let i = walk.i;
        let g = ref_geo.get(i).copied().unwrap_or_default();
        *o = if g[0] > 0.0 {
            let (r_p, _, r_g, _) = terms::<false>(
                k,
                ref_photo[i][0],
                g[3],
                k.rx[x],
                k.ry[y],
                cur_photo,
                cur_geo,
            );
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
    use crate::odometry::kernel::{accumulate_pixel, pixel_terms, sample_index};

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
                    0.6 + 0.0008 * fx
                });
            }
        }
        RgbdFrame {
            timestamp: 0.0,
            intensity: ImageF32::from_vec(w, h, i).unwrap(),
            inverse_depth: ImageF32::from_vec(w, h, r).unwrap(),
        }
    }

    /// The row loops agree with the per-pixel reference mirror (which the GPU parity test
    /// checks against the WGSL) for every estimator, term set and parametrisation.
    #[test]
    fn row_loops_match_the_reference_mirror() {
        let (w, h) = (96usize, 72usize);
        let a = CpuPyramid::build(&frame(w, h, 0.0), 1);
        let b = CpuPyramid::build(&frame(w, h, 1.3), 1);
        let pose = Se3::exp(&[0.01, -0.004, 0.02, 0.003, -0.005, 0.002]);
        for est in 0..4u32 {
            // param: bit 0 depth parametrisation, bit 1 first-order inverse-depth sampling.
            for (terms_mask, param) in [(3u32, 0u32), (1, 0), (2, 0), (3, 1), (3, 2), (2, 3)] {
                let mut p = WarpParams {
                    dims: [w as u32, h as u32, 0, 1000],
                    intr: [90.0, 90.0, 47.5, 35.5],
                    rot: [[0.0; 4]; 3],
                    robust: [4.0, if param & 1 == 1 { 0.01 } else { 0.003 }, 4.0, 6.0],
                    flags: [est, terms_mask, param, 0],
                };
                p.set_pose(&pose);
                let mut want = [0.0f32; PARTIAL_LEN];
                for i in 0..w * h {
                    accumulate_pixel(&p, &a.photo, &a.geo, &b.photo, &b.geo, i, &mut want);
                }
                let mut got = [0.0f64; PARTIAL_LEN];
                accumulate_rows(
                    &Warp::new(&p),
                    &a.photo,
                    &a.geo,
                    &b.photo,
                    &b.geo,
                    0..h,
                    &mut got,
                    None,
                );
                assert_eq!(got[28] as f32, want[28], "photometric count");
                assert_eq!(got[29] as f32, want[29], "geometric count");
                assert!(want[28] + want[29] > 1000.0);
                let scale = want.iter().take(28).map(|v| v.abs()).fold(0.0, f32::max) as f64;
                for i in 0..28 {
                    let d = (got[i] - f64::from(want[i])).abs();
                    assert!(
                        d <= 1e-4 * scale + 1e-4 * got[i].abs(),
                        "entry {i}: {} vs {}",
                        got[i],
                        want[i]
                    );
                }
                // The sample taken during the reduction equals the separate sample pass.
                let (_, fused) =
                    crate::odometry::cpu::normal_equations_and_sample(&p, &a, &b, 0, 5);
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
                sample_range(
                    &Warp::new(&p),
                    &a.photo,
                    &a.geo,
                    &b.photo,
                    &b.geo,
                    0,
                    count,
                    &mut s[..600],
                );
                sample_range(
                    &Warp::new(&p),
                    &a.photo,
                    &a.geo,
                    &b.photo,
                    &b.geo,
                    600,
                    count,
                    &mut s[600..],
                );
                for (kk, got) in s.iter().enumerate() {
                    let i = sample_index(kk as u32, count as u32, (w * h) as u32) as usize;
                    let t = pixel_terms(&p, &a.photo, &a.geo, &b.photo, &b.geo, i, false);
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
    }
}
