//! Keyframe inverse-depth fusion by reverse warping (thesis 6.4.2, eq. 6.24-6.25): the WGSL
//! kernel `shaders/fuse.wgsl` and its CPU mirror [`fuse_cpu`] (same f32 operations in the
//! same order), two implementations of one kernel interface (`FusionKernels`) behind
//! [`KeyframeFuser`], which keeps the keyframe resident where the kernel runs.
//!
//! Where it departs from the thesis: the accumulated weight is capped
//! ([`FusionParams::max_weight`]) so that the keyframe can follow small changes. The fixed
//! tolerance `tol_abs + tol_rel rho` and the one-sided covisibility without occlusion test
//! remain as options (docs/notes.md has the measurements that chose the thesis' forms as the
//! defaults); when buffered frames are fused is the SLAM system's schedule
//! (`SlamConfig::buffered_fusion`).
//!
//! On x86-64 with AVX2 the CPU rows run an AVX2 build of the same code (bit-identical: Rust
//! never contracts multiplies and adds); it inlines the nearest-pixel `floor`, which is a
//! library call on the x86-64 baseline.

use std::sync::Arc;

use bytemuck::{Pod, Zeroable};
use rayon::prelude::*;

use super::SlamError;
use crate::camera::PinholeCamera;
use crate::geometry::Se3;
use crate::gpu::{shaders, ComputeBackend, GpuContext, GpuError};
use crate::image::ImageF32;
use crate::odometry::avx2;

/// Parameters of the weighted inverse-depth update.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct FusionParams {
    /// Absolute consistency tolerance on inverse depth, 1/m.
    pub tol_abs: f32,
    /// Relative consistency tolerance (fraction of the keyframe's inverse depth).
    pub tol_rel: f32,
    /// Weight of one new measurement.
    pub new_weight: f32,
    /// Cap of the accumulated weight (keeps the keyframe able to follow small changes).
    pub max_weight: f32,
    /// Consistency tolerance as a multiple of the fused frame's geometric scale sigma_W
    /// (1/m, the odometry's estimate): the thesis' 3 sigma_W (eq. 6.24, the default). `0`
    /// uses `tol_abs + tol_rel * rho` instead.
    pub tol_sigmas: f32,
    /// Count a keyframe pixel as covisible only where the frame's measurement at it is
    /// consistent (within the fusion tolerance): the thesis' occlusion condition of eq. 6.10.
    /// `false` counts every pixel that lands on depth. On by default (docs/notes.md).
    pub occlusion: bool,
    /// Keyframe covisibility as the minimum over both directions (eq. 6.10): also the
    /// fraction of the frame's pixels with depth that land on keyframe depth (consistent
    /// depth with [`Self::occlusion`]; the default). `false` takes the keyframe's side only.
    pub both_directions: bool,
}

impl Default for FusionParams {
    fn default() -> Self {
        FusionParams {
            tol_abs: 0.004,
            tol_rel: 0.03,
            new_weight: 1.0,
            max_weight: 30.0,
            tol_sigmas: 3.0,
            occlusion: true,
            both_directions: true,
        }
    }
}

/// Pixel counts of one fusion pass.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct FusionCounts {
    /// Keyframe pixels with depth.
    pub valid: u64,
    /// Of those, the ones that land on a current-frame pixel with depth.
    pub covisible: u64,
    /// Of those, the ones whose measurement was consistent and fused.
    pub fused: u64,
    /// Frame pixels with depth (counted with [`FusionParams::both_directions`] only, else 0).
    pub frame_valid: u64,
    /// Of those, the ones that land on keyframe depth (consistent depth with
    /// [`FusionParams::occlusion`]).
    pub frame_covisible: u64,
}

impl FusionCounts {
    /// Fraction of the keyframe's pixels with depth seen with depth by the current frame
    /// (the keyframe-side covisibility of eq. 6.10), and where the frame side was counted
    /// ([`FusionParams::both_directions`]) the minimum with the frame side's fraction; 0 when
    /// the keyframe has no depth.
    pub fn covisibility(&self) -> f64 {
        let ratio = |a: u64, b: u64| if a == 0 { 0.0 } else { b as f64 / a as f64 };
        let keyframe_side = ratio(self.valid, self.covisible);
        if self.frame_valid == 0 {
            keyframe_side
        } else {
            keyframe_side.min(ratio(self.frame_valid, self.frame_covisible))
        }
    }
}

/// Uniform block of `fuse.wgsl` (`Params`, same layout; a test compares them).
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
pub(crate) struct FuseUniform {
    /// Keyframe width, pixels.
    pub(crate) width: u32,
    /// Keyframe height, pixels.
    pub(crate) height: u32,
    /// Padding to the 16-byte alignment of the WGSL's `vec4` members.
    pub(crate) _pad: [u32; 2],
    /// Intrinsics, pixels.
    pub(crate) fx: f32,
    pub(crate) fy: f32,
    pub(crate) cx: f32,
    pub(crate) cy: f32,
    /// `cur_from_kf` rows with the translation (m) in the last column.
    pub(crate) fwd: [[f32; 4]; 3],
    /// `kf_from_cur` rows with the translation (m) in the last column.
    pub(crate) inv: [[f32; 4]; 3],
    /// See [`FusionParams`].
    pub(crate) tol_abs: f32,
    pub(crate) tol_rel: f32,
    pub(crate) new_weight: f32,
    pub(crate) max_weight: f32,
    /// Absolute consistency tolerance `tol_sigmas * sigma_W` (1/m); 0: `tol_abs + tol_rel rho`.
    pub(crate) tol_sigma: f32,
    /// 1: [`FusionParams::occlusion`].
    pub(crate) occlusion: u32,
    /// Padding to the 16-byte size multiple of the WGSL uniform.
    pub(crate) _pad2: [u32; 2],
}

fn rows(t: &Se3) -> [[f32; 4]; 3] {
    let r = t.rotation_matrix();
    let mut out = [[0.0f32; 4]; 3];
    for (i, row) in out.iter_mut().enumerate() {
        *row = [
            r.row(i).x as f32,
            r.row(i).y as f32,
            r.row(i).z as f32,
            t.translation[i] as f32,
        ];
    }
    out
}

impl FuseUniform {
    /// The uniform for fusing a frame at `cur_from_kf` whose geometric scale is `sigma_geo`
    /// (1/m) into a keyframe of `camera`.
    pub(crate) fn new(
        camera: &PinholeCamera,
        cur_from_kf: &Se3,
        sigma_geo: f64,
        params: &FusionParams,
    ) -> Self {
        FuseUniform {
            width: camera.width,
            height: camera.height,
            _pad: [0; 2],
            fx: camera.fx as f32,
            fy: camera.fy as f32,
            cx: camera.cx as f32,
            cy: camera.cy as f32,
            fwd: rows(cur_from_kf),
            inv: rows(&cur_from_kf.inverse()),
            tol_abs: params.tol_abs,
            tol_rel: params.tol_rel,
            new_weight: params.new_weight,
            max_weight: params.max_weight,
            tol_sigma: if params.tol_sigmas > 0.0 {
                (f64::from(params.tol_sigmas) * sigma_geo) as f32
            } else {
                0.0
            },
            occlusion: u32::from(params.occlusion),
            _pad2: [0; 2],
        }
    }

    /// The consistency tolerance at keyframe inverse depth `rho` (1/m).
    #[inline(always)]
    fn tolerance(&self, rho: f32) -> f32 {
        if self.tol_sigma > 0.0 {
            self.tol_sigma
        } else {
            self.tol_abs + self.tol_rel * rho
        }
    }
}

#[inline(always)]
fn xform(r: &[[f32; 4]; 3], p: [f32; 3]) -> [f32; 3] {
    let f = |k: usize| r[k][0] * p[0] + r[k][1] * p[1] + r[k][2] * p[2] + r[k][3];
    [f(0), f(1), f(2)]
}

/// What happened at one keyframe pixel: 0 no depth, 1 depth but not covisible (with
/// [`FusionParams::occlusion`] also where the measurement is inconsistent), 2 covisible but
/// not fused, 3 fused (then `(rho, weight)` are the new values).
#[inline(always)]
pub(crate) fn fuse_pixel(
    u: &FuseUniform,
    x: u32,
    y: u32,
    rho: f32,
    weight: f32,
    cur_rho: &[f32],
) -> (u8, f32, f32) {
    if !(rho > 0.0) {
        return (0, rho, weight);
    }
    let (w, h) = (u.width, u.height);
    let (fx, fy, cx, cy) = (u.fx, u.fy, u.cx, u.cy);
    let z = 1.0 / rho;
    let pk = [(x as f32 - cx) / fx * z, (y as f32 - cy) / fy * z, z];
    let pc = xform(&u.fwd, pk);
    if !(pc[2] > 0.0) {
        return (1, rho, weight);
    }
    let uu = fx * pc[0] / pc[2] + cx;
    let vv = fy * pc[1] / pc[2] + cy;
    let qx = (uu + 0.5).floor();
    let qy = (vv + 0.5).floor();
    if !(qx >= 0.0 && qy >= 0.0 && qx <= (w - 1) as f32 && qy <= (h - 1) as f32) {
        return (1, rho, weight);
    }
    let j = qy as usize * w as usize + qx as usize;
    let rc = cur_rho[j];
    if !(rc > 0.0) {
        return (1, rho, weight);
    }
    let zc = 1.0 / rc;
    let qc = [(qx - cx) / fx * zc, (qy - cy) / fy * zc, zc];
    let qk = xform(&u.inv, qc);
    if !(qk[2] > 0.0) {
        return (if u.occlusion == 1 { 1 } else { 2 }, rho, weight);
    }
    let rho_new = 1.0 / qk[2];
    if (rho_new - rho).abs() > u.tolerance(rho) {
        return (if u.occlusion == 1 { 1 } else { 2 }, rho, weight);
    }
    let wn = u.new_weight;
    (
        3,
        (weight * rho + wn * rho_new) / (weight + wn),
        (weight + wn).min(u.max_weight),
    )
}

/// The frame side of the covisibility at current pixel `(x, y)` with inverse depth `rc`:
/// 0 no depth, 1 not covisible (outside the keyframe, onto a keyframe pixel without depth, or
/// with [`FusionParams::occlusion`] onto inconsistent depth), 2 covisible. Mirror of
/// `covisible_back` in `fuse.wgsl`.
#[inline(always)]
pub(crate) fn covisible_back(u: &FuseUniform, x: u32, y: u32, rc: f32, kf_rho: &[f32]) -> u8 {
    if !(rc > 0.0) {
        return 0;
    }
    let (w, h) = (u.width, u.height);
    let (fx, fy, cx, cy) = (u.fx, u.fy, u.cx, u.cy);
    let zc = 1.0 / rc;
    let pc = [(x as f32 - cx) / fx * zc, (y as f32 - cy) / fy * zc, zc];
    let pk = xform(&u.inv, pc);
    if !(pk[2] > 0.0) {
        return 1;
    }
    let uu = fx * pk[0] / pk[2] + cx;
    let vv = fy * pk[1] / pk[2] + cy;
    let qx = (uu + 0.5).floor();
    let qy = (vv + 0.5).floor();
    if !(qx >= 0.0 && qy >= 0.0 && qx <= (w - 1) as f32 && qy <= (h - 1) as f32) {
        return 1;
    }
    let rk = kf_rho[qy as usize * w as usize + qx as usize];
    if !(rk > 0.0) {
        return 1;
    }
    if u.occlusion == 1 && (1.0 / pk[2] - rk).abs() > u.tolerance(rk) {
        return 1;
    }
    2
}

/// [`covisible_back`] over row `y` of the frame: `(pixels with depth, covisible)`.
fn covisible_back_row(u: &FuseUniform, y: usize, row: &[f32], kf_rho: &[f32]) -> (u64, u64) {
    covisible_back_row_from(u, y, row, kf_rho, 0)
}

/// [`covisible_back_row`] from column `x0` on.
#[inline(always)]
fn covisible_back_row_from(
    u: &FuseUniform,
    y: usize,
    row: &[f32],
    kf_rho: &[f32],
    x0: usize,
) -> (u64, u64) {
    let mut c = (0u64, 0u64);
    for (x, &rc) in row.iter().enumerate().skip(x0) {
        let code = covisible_back(u, x as u32, y as u32, rc, kf_rho);
        c.0 += u64::from(code >= 1);
        c.1 += u64::from(code == 2);
    }
    c
}

/// [`covisible_back_row`] eight pixels at a time in AVX2 lanes (the same f32 operations in the
/// same order, so the counts are those of the scalar row), the row's tail in scalar code.
///
/// # Safety
/// The CPU has AVX2; `kf_rho` holds `u.width * u.height` values and that count fits an `i32`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn covisible_back_row_avx2(
    u: &FuseUniform,
    y: usize,
    row: &[f32],
    kf_rho: &[f32],
) -> (u64, u64) {
    let mut c = (0u64, 0u64);
    let mut x = 0;
    while x + 8 <= row.len() {
        // SAFETY: x + 8 <= row.len(); the caller guarantees AVX2 and the keyframe's size.
        let (valid, covisible) = unsafe { lanes::covisible_back8(u, x, y, &row[x..x + 8], kf_rho) };
        c.0 += u64::from(valid.count_ones());
        c.1 += u64::from(covisible.count_ones());
        x += 8;
    }
    let tail = covisible_back_row_from(u, y, row, kf_rho, x);
    (c.0 + tail.0, c.1 + tail.1)
}

/// Whether the rows can run in AVX2 lanes against an image of `len` values: the CPU has AVX2,
/// the image covers the uniform's size and its indices fit the gathers' `i32`.
fn lanes_fit(u: &FuseUniform, len: usize) -> bool {
    let pixels = u.width as usize * u.height as usize;
    avx2() && len >= pixels && pixels <= i32::MAX as usize
}

/// [`covisible_back`] over every frame pixel: `(frame pixels with depth, covisible)`.
fn covisible_back_rows(kf_rho: &[f32], cur_rho: &[f32], u: &FuseUniform) -> (u64, u64) {
    let w = (u.width as usize).max(1);
    let fast = lanes_fit(u, kf_rho.len());
    cur_rho
        .par_chunks(w)
        .enumerate()
        .map(|(y, row)| {
            #[cfg(target_arch = "x86_64")]
            if fast {
                // SAFETY: `lanes_fit` checked AVX2 and the keyframe's size.
                return unsafe { covisible_back_row_avx2(u, y, row, kf_rho) };
            }
            let _ = fast;
            covisible_back_row(u, y, row, kf_rho)
        })
        .reduce(|| (0, 0), |a, b| (a.0 + b.0, a.1 + b.1))
}

#[cfg(test)]
/// CPU mirror of the `fuse` kernel: updates `kf_rho` / `kf_weight` (row-major, the camera's
/// size) in place with the frame whose inverse depth is `cur_rho`, at `cur_from_kf`.
pub fn fuse_cpu(
    kf_rho: &mut [f32],
    kf_weight: &mut [f32],
    cur_rho: &[f32],
    camera: &PinholeCamera,
    cur_from_kf: &Se3,
    sigma_geo: f64,
    params: &FusionParams,
) -> FusionCounts {
    let u = FuseUniform::new(camera, cur_from_kf, sigma_geo, params);
    fuse_both(kf_rho, kf_weight, cur_rho, &u, params.both_directions)
}

/// The frame side of the covisibility (when `both_directions`, against the keyframe before
/// this fusion, as the GPU dispatches it first), then [`fuse_rows`].
fn fuse_both(
    kf_rho: &mut [f32],
    kf_weight: &mut [f32],
    cur_rho: &[f32],
    u: &FuseUniform,
    both_directions: bool,
) -> FusionCounts {
    let back = if both_directions {
        covisible_back_rows(kf_rho, cur_rho, u)
    } else {
        (0, 0)
    };
    let mut c = fuse_rows(kf_rho, kf_weight, cur_rho, u);
    (c.frame_valid, c.frame_covisible) = back;
    c
}

/// [`fuse_pixel`] over keyframe row `y` (`rr`, `ww`), updating it in place.
fn fuse_row(
    u: &FuseUniform,
    y: usize,
    rr: &mut [f32],
    ww: &mut [f32],
    cur_rho: &[f32],
) -> FusionCounts {
    fuse_row_from(u, y, rr, ww, cur_rho, 0)
}

/// [`fuse_row`] from column `x0` on.
#[inline(always)]
fn fuse_row_from(
    u: &FuseUniform,
    y: usize,
    rr: &mut [f32],
    ww: &mut [f32],
    cur_rho: &[f32],
    x0: usize,
) -> FusionCounts {
    let mut c = FusionCounts::default();
    for x in x0..rr.len().min(ww.len()) {
        let (code, r, wt) = fuse_pixel(u, x as u32, y as u32, rr[x], ww[x], cur_rho);
        if code >= 1 {
            c.valid += 1;
        }
        if code >= 2 {
            c.covisible += 1;
        }
        if code == 3 {
            c.fused += 1;
            rr[x] = r;
            ww[x] = wt;
        }
    }
    c
}

/// [`fuse_row`] eight pixels at a time in AVX2 lanes (the same f32 operations in the same
/// order: bit-identical values), the row's tail in scalar code.
///
/// # Safety
/// The CPU has AVX2; `cur_rho` holds `u.width * u.height` values and that count fits an
/// `i32`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn fuse_row_avx2(
    u: &FuseUniform,
    y: usize,
    rr: &mut [f32],
    ww: &mut [f32],
    cur_rho: &[f32],
) -> FusionCounts {
    let n = rr.len().min(ww.len());
    let mut c = FusionCounts::default();
    let mut x = 0;
    while x + 8 <= n {
        // SAFETY: x + 8 <= n; the caller guarantees AVX2 and the frame's size.
        let (valid, covisible, fused) =
            unsafe { lanes::fuse8(u, x, y, &mut rr[x..x + 8], &mut ww[x..x + 8], cur_rho) };
        c.valid += u64::from(valid.count_ones());
        c.covisible += u64::from(covisible.count_ones());
        c.fused += u64::from(fused.count_ones());
        x += 8;
    }
    let tail = fuse_row_from(u, y, rr, ww, cur_rho, x);
    c.valid += tail.valid;
    c.covisible += tail.covisible;
    c.fused += tail.fused;
    c
}

/// The AVX2 lanes of [`fuse_pixel`] and [`covisible_back`].
#[cfg(target_arch = "x86_64")]
mod lanes {
    use super::FuseUniform;
    use std::arch::x86_64::*;

    /// One row of `R p + t` in lanes: `((r0 p0 + r1 p1) + r2 p2) + r3`, as [`super::xform`].
    #[target_feature(enable = "avx2")]
    #[inline]
    fn xform_row(r: &[f32; 4], p: [__m256; 3]) -> __m256 {
        let set = _mm256_set1_ps;
        _mm256_add_ps(
            _mm256_add_ps(
                _mm256_add_ps(
                    _mm256_mul_ps(set(r[0]), p[0]),
                    _mm256_mul_ps(set(r[1]), p[1]),
                ),
                _mm256_mul_ps(set(r[2]), p[2]),
            ),
            set(r[3]),
        )
    }

    #[target_feature(enable = "avx2")]
    #[inline]
    fn xform(r: &[[f32; 4]; 3], p: [__m256; 3]) -> [__m256; 3] {
        [
            xform_row(&r[0], p),
            xform_row(&r[1], p),
            xform_row(&r[2], p),
        ]
    }

    /// `((c - cx) / fx) * z` and `((r - cy) / fy) * z` for columns `col`, rows `row`.
    #[target_feature(enable = "avx2")]
    #[inline]
    fn unproject(u: &FuseUniform, col: __m256, row: __m256, z: __m256) -> [__m256; 3] {
        let set = _mm256_set1_ps;
        [
            _mm256_mul_ps(_mm256_div_ps(_mm256_sub_ps(col, set(u.cx)), set(u.fx)), z),
            _mm256_mul_ps(_mm256_div_ps(_mm256_sub_ps(row, set(u.cy)), set(u.fy)), z),
            z,
        ]
    }

    /// The nearest pixel of the projection of `p` (`floor(fx p0 / p2 + cx + 0.5)`, same for
    /// y), the mask of `p2 > 0` and of the pixel inside the image, and its index.
    #[target_feature(enable = "avx2")]
    #[inline]
    fn nearest(u: &FuseUniform, p: [__m256; 3]) -> (__m256, __m256, __m256, __m256i) {
        let set = _mm256_set1_ps;
        let zero = _mm256_setzero_ps();
        let front = _mm256_cmp_ps::<_CMP_GT_OQ>(p[2], zero);
        let uu = _mm256_add_ps(
            _mm256_div_ps(_mm256_mul_ps(set(u.fx), p[0]), p[2]),
            set(u.cx),
        );
        let vv = _mm256_add_ps(
            _mm256_div_ps(_mm256_mul_ps(set(u.fy), p[1]), p[2]),
            set(u.cy),
        );
        let qx = _mm256_floor_ps(_mm256_add_ps(uu, set(0.5)));
        let qy = _mm256_floor_ps(_mm256_add_ps(vv, set(0.5)));
        let inside = _mm256_and_ps(
            _mm256_and_ps(
                _mm256_cmp_ps::<_CMP_GE_OQ>(qx, zero),
                _mm256_cmp_ps::<_CMP_GE_OQ>(qy, zero),
            ),
            _mm256_and_ps(
                _mm256_cmp_ps::<_CMP_LE_OQ>(qx, set((u.width - 1) as f32)),
                _mm256_cmp_ps::<_CMP_LE_OQ>(qy, set((u.height - 1) as f32)),
            ),
        );
        let ok = _mm256_and_ps(front, inside);
        // Masked lanes may hold NaN or out-of-range values: their index is zeroed.
        let qxi = _mm256_cvttps_epi32(_mm256_and_ps(qx, ok));
        let qyi = _mm256_cvttps_epi32(_mm256_and_ps(qy, ok));
        let j = _mm256_add_epi32(
            _mm256_mullo_epi32(qyi, _mm256_set1_epi32(u.width as i32)),
            qxi,
        );
        (ok, qx, qy, j)
    }

    /// `tolerance(rho)` in lanes.
    #[target_feature(enable = "avx2")]
    #[inline]
    fn tolerance(u: &FuseUniform, rho: __m256) -> __m256 {
        let set = _mm256_set1_ps;
        if u.tol_sigma > 0.0 {
            set(u.tol_sigma)
        } else {
            _mm256_add_ps(set(u.tol_abs), _mm256_mul_ps(set(u.tol_rel), rho))
        }
    }

    /// `|a - b| > tol` (false where any is NaN, as the scalar comparison).
    #[target_feature(enable = "avx2")]
    #[inline]
    fn beyond(a: __m256, b: __m256, tol: __m256) -> __m256 {
        let d = _mm256_andnot_ps(_mm256_set1_ps(-0.0), _mm256_sub_ps(a, b));
        _mm256_cmp_ps::<_CMP_GT_OQ>(d, tol)
    }

    /// Columns `x .. x + 8` of row `y` as floats.
    #[target_feature(enable = "avx2")]
    #[inline]
    fn columns(x: usize) -> __m256 {
        let base = _mm256_set1_ps(x as f32);
        _mm256_add_ps(base, _mm256_setr_ps(0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0))
    }

    /// Masked gather of `v[j]` (0 where `mask` is clear).
    ///
    /// # Safety
    /// Every index `j` of a set lane is within `v`.
    #[target_feature(enable = "avx2")]
    #[inline]
    unsafe fn gather(v: &[f32], j: __m256i, mask: __m256) -> __m256 {
        unsafe { _mm256_mask_i32gather_ps::<4>(_mm256_setzero_ps(), v.as_ptr(), j, mask) }
    }

    /// [`super::fuse_pixel`] on keyframe pixels `x .. x + 8` of row `y` (`rr`, `ww`: those
    /// eight values, updated where fused). Returns the lane masks `(code >= 1, code >= 2,
    /// code == 3)`.
    ///
    /// # Safety
    /// AVX2; `rr` and `ww` hold eight values; `cur_rho` holds `width * height` values.
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn fuse8(
        u: &FuseUniform,
        x: usize,
        y: usize,
        rr: &mut [f32],
        ww: &mut [f32],
        cur_rho: &[f32],
    ) -> (u32, u32, u32) {
        let set = _mm256_set1_ps;
        let zero = _mm256_setzero_ps();
        let one = set(1.0);
        // SAFETY: the caller passes eight values.
        let (rho, weight) = unsafe { (_mm256_loadu_ps(rr.as_ptr()), _mm256_loadu_ps(ww.as_ptr())) };
        let valid = _mm256_cmp_ps::<_CMP_GT_OQ>(rho, zero);
        let z = _mm256_div_ps(one, rho);
        let pk = unproject(u, columns(x), set(y as f32), z);
        let pc = xform(&u.fwd, pk);
        let (ok, qx, qy, j) = nearest(u, pc);
        let ok = _mm256_and_ps(ok, valid);
        // SAFETY: set lanes of `ok` index inside the image, which `cur_rho` covers.
        let rc = unsafe { gather(cur_rho, j, ok) };
        let seen = _mm256_and_ps(ok, _mm256_cmp_ps::<_CMP_GT_OQ>(rc, zero));
        let zc = _mm256_div_ps(one, rc);
        let qc = unproject(u, qx, qy, zc);
        let qk = xform(&u.inv, qc);
        let front = _mm256_and_ps(seen, _mm256_cmp_ps::<_CMP_GT_OQ>(qk[2], zero));
        let rho_new = _mm256_div_ps(one, qk[2]);
        let fused = _mm256_andnot_ps(beyond(rho_new, rho, tolerance(u, rho)), front);
        let wn = set(u.new_weight);
        let fused_rho = _mm256_div_ps(
            _mm256_add_ps(_mm256_mul_ps(weight, rho), _mm256_mul_ps(wn, rho_new)),
            _mm256_add_ps(weight, wn),
        );
        let fused_weight = _mm256_min_ps(_mm256_add_ps(weight, wn), set(u.max_weight));
        // SAFETY: the caller passes eight values.
        unsafe {
            _mm256_storeu_ps(rr.as_mut_ptr(), _mm256_blendv_ps(rho, fused_rho, fused));
            _mm256_storeu_ps(
                ww.as_mut_ptr(),
                _mm256_blendv_ps(weight, fused_weight, fused),
            );
        }
        // Covisible: landed on depth, and (with the occlusion test) consistent; without it
        // also what lands on depth behind the camera or inconsistently.
        let covisible = if u.occlusion == 1 { fused } else { seen };
        (
            _mm256_movemask_ps(valid) as u32,
            _mm256_movemask_ps(covisible) as u32,
            _mm256_movemask_ps(fused) as u32,
        )
    }

    /// [`super::covisible_back`] on frame pixels `x .. x + 8` of row `y` (`rc`: their eight
    /// inverse depths). Returns the lane masks `(code >= 1, code == 2)`.
    ///
    /// # Safety
    /// AVX2; `rc` holds eight values; `kf_rho` holds `width * height` values.
    #[target_feature(enable = "avx2")]
    pub(super) unsafe fn covisible_back8(
        u: &FuseUniform,
        x: usize,
        y: usize,
        rc: &[f32],
        kf_rho: &[f32],
    ) -> (u32, u32) {
        let set = _mm256_set1_ps;
        let zero = _mm256_setzero_ps();
        // SAFETY: the caller passes eight values.
        let rc = unsafe { _mm256_loadu_ps(rc.as_ptr()) };
        let valid = _mm256_cmp_ps::<_CMP_GT_OQ>(rc, zero);
        let zc = _mm256_div_ps(set(1.0), rc);
        let pc = unproject(u, columns(x), set(y as f32), zc);
        let pk = xform(&u.inv, pc);
        let (ok, _, _, j) = nearest(u, pk);
        let ok = _mm256_and_ps(ok, valid);
        // SAFETY: set lanes of `ok` index inside the image, which `kf_rho` covers.
        let rk = unsafe { gather(kf_rho, j, ok) };
        let mut covisible = _mm256_and_ps(ok, _mm256_cmp_ps::<_CMP_GT_OQ>(rk, zero));
        if u.occlusion == 1 {
            let far = beyond(_mm256_div_ps(set(1.0), pk[2]), rk, tolerance(u, rk));
            covisible = _mm256_andnot_ps(far, covisible);
        }
        (
            _mm256_movemask_ps(valid) as u32,
            _mm256_movemask_ps(covisible) as u32,
        )
    }
}

/// [`fuse_pixel`] over every keyframe pixel, rows in parallel.
fn fuse_rows(
    kf_rho: &mut [f32],
    kf_weight: &mut [f32],
    cur_rho: &[f32],
    u: &FuseUniform,
) -> FusionCounts {
    let w = (u.width as usize).max(1);
    let fast = lanes_fit(u, cur_rho.len());
    kf_rho
        .par_chunks_mut(w)
        .zip(kf_weight.par_chunks_mut(w))
        .enumerate()
        .map(|(y, (rr, ww))| {
            #[cfg(target_arch = "x86_64")]
            if fast {
                // SAFETY: `lanes_fit` checked AVX2 and the frame's size.
                return unsafe { fuse_row_avx2(u, y, rr, ww, cur_rho) };
            }
            let _ = fast;
            fuse_row(u, y, rr, ww, cur_rho)
        })
        .reduce(FusionCounts::default, |a, b| FusionCounts {
            valid: a.valid + b.valid,
            covisible: a.covisible + b.covisible,
            fused: a.fused + b.fused,
            frame_valid: 0,
            frame_covisible: 0,
        })
}

/// The keyframe fusion kernel of one backend, with the keyframe resident where it runs (the
/// kernel interface [`KeyframeFuser`] is written against).
pub(crate) trait FusionKernels: Send {
    /// Takes a new keyframe: inverse depth `rho` (1/m, 0 = invalid) and weights.
    fn start(&mut self, rho: Vec<f32>, weight: Vec<f32>) -> Result<(), SlamError>;
    /// Fuses one frame's inverse depth into the resident keyframe; with `both_directions`
    /// the frame side of the covisibility is counted first.
    fn fuse(
        &mut self,
        cur_rho: &[f32],
        u: &FuseUniform,
        both_directions: bool,
    ) -> Result<FusionCounts, SlamError>;
    /// The keyframe: `(rho, weight)`.
    fn read(&self) -> Result<(Vec<f32>, Vec<f32>), SlamError>;
    /// Bytes held, `(host, device)`.
    fn memory_bytes(&self) -> (usize, usize);
}

/// The CPU mirror, with the keyframe in host memory.
struct CpuFusion {
    rho: Vec<f32>,
    weight: Vec<f32>,
}

impl FusionKernels for CpuFusion {
    fn start(&mut self, rho: Vec<f32>, weight: Vec<f32>) -> Result<(), SlamError> {
        self.rho = rho;
        self.weight = weight;
        Ok(())
    }

    fn fuse(
        &mut self,
        cur_rho: &[f32],
        u: &FuseUniform,
        both_directions: bool,
    ) -> Result<FusionCounts, SlamError> {
        Ok(fuse_both(
            &mut self.rho,
            &mut self.weight,
            cur_rho,
            u,
            both_directions,
        ))
    }

    fn read(&self) -> Result<(Vec<f32>, Vec<f32>), SlamError> {
        Ok((self.rho.clone(), self.weight.clone()))
    }

    fn memory_bytes(&self) -> (usize, usize) {
        let f = std::mem::size_of::<f32>();
        ((self.rho.capacity() + self.weight.capacity()) * f, 0)
    }
}

/// Bytes of the kernel's counters: keyframe valid, covisible, fused, frame valid, frame
/// covisible (`u32` each), rounded up to 16.
const COUNTS_BYTES: u64 = 32;

/// The fusion kernel compiled on a device, with the keyframe's buffers resident there.
struct GpuFusion {
    ctx: Arc<GpuContext>,
    pipeline: wgpu::ComputePipeline,
    /// `covisible_back`: the frame side of the covisibility.
    back: wgpu::ComputePipeline,
    layout: wgpu::BindGroupLayout,
    uniform: wgpu::Buffer,
    counts: wgpu::Buffer,
    buffers: Option<(wgpu::Buffer, wgpu::Buffer, wgpu::Buffer, wgpu::BindGroup)>,
    pixels: usize,
}

impl GpuFusion {
    /// Compiles `fuse.wgsl` on `ctx`.
    fn new(ctx: Arc<GpuContext>) -> Result<Self, SlamError> {
        let src = shaders::assembled("fuse.wgsl").ok_or_else(|| GpuError::Shader {
            name: "fuse.wgsl".into(),
            message: "not embedded".into(),
        })?;
        let layout = ctx.buffer_layout("fuse", &[true, false, false, false]);
        let mut pipes = ctx.compute_pipelines_with_layout(
            "fuse.wgsl",
            &src,
            &["fuse", "covisible_back"],
            Some(&layout),
        )?;
        let no_pipeline = || GpuError::Shader {
            name: "fuse.wgsl".into(),
            message: "no pipeline".into(),
        };
        let back = pipes.pop().ok_or_else(no_pipeline)?;
        let pipeline = pipes.pop().ok_or_else(no_pipeline)?;
        let uniform = ctx.uniform("fuse params", std::mem::size_of::<FuseUniform>() as u64);
        let counts = ctx.storage("fuse counts", COUNTS_BYTES);
        Ok(GpuFusion {
            ctx,
            pipeline,
            back,
            layout,
            uniform,
            counts,
            buffers: None,
            pixels: 0,
        })
    }
}

impl FusionKernels for GpuFusion {
    /// Uploads a new keyframe (`rho`, `weight`).
    fn start(&mut self, rho: Vec<f32>, weight: Vec<f32>) -> Result<(), SlamError> {
        let ctx = &self.ctx;
        let n = rho.len();
        if self.pixels == n {
            if let Some((_, kr, kw, _)) = &self.buffers {
                ctx.queue.write_buffer(kr, 0, bytemuck::cast_slice(&rho));
                ctx.queue.write_buffer(kw, 0, bytemuck::cast_slice(&weight));
                return Ok(());
            }
        }
        let cur = ctx.storage("fuse current rho", (n * 4) as u64);
        let kr = ctx.storage_init("fuse keyframe rho", &rho);
        let kw = ctx.storage_init("fuse keyframe weight", &weight);
        let bind = ctx.bind_buffers(
            "fuse",
            &self.layout,
            &[&self.uniform, &cur, &kr, &kw, &self.counts],
        );
        self.buffers = Some((cur, kr, kw, bind));
        self.pixels = n;
        Ok(())
    }

    /// Fuses one frame into the resident keyframe; returns the pixel counts.
    fn fuse(
        &mut self,
        cur_rho: &[f32],
        u: &FuseUniform,
        both_directions: bool,
    ) -> Result<FusionCounts, SlamError> {
        let ctx = &self.ctx;
        let Some((cur, _, _, bind)) = &self.buffers else {
            return Err(SlamError::Internal("fusion before a keyframe".into()));
        };
        if cur_rho.len() != self.pixels {
            return Err(SlamError::Internal("fusion frame size changed".into()));
        }
        ctx.queue
            .write_buffer(cur, 0, bytemuck::cast_slice(cur_rho));
        ctx.queue
            .write_buffer(&self.uniform, 0, bytemuck::bytes_of(u));
        ctx.queue
            .write_buffer(&self.counts, 0, &[0u8; COUNTS_BYTES as usize]);
        let mut enc = ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("fuse"),
            });
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("fuse"),
                timestamp_writes: None,
            });
            pass.set_bind_group(0, bind, &[]);
            // The frame side first: it reads the keyframe before this fusion updates it.
            if both_directions {
                pass.set_pipeline(&self.back);
                pass.dispatch_workgroups(u.width.div_ceil(16), u.height.div_ceil(16), 1);
            }
            pass.set_pipeline(&self.pipeline);
            pass.dispatch_workgroups(u.width.div_ceil(16), u.height.div_ceil(16), 1);
        }
        ctx.submit(enc.finish());
        let c: Vec<u32> = ctx.read_buffer(&self.counts, 5)?;
        ctx.check()?;
        let at = |k: usize| u64::from(c.get(k).copied().unwrap_or(0));
        Ok(FusionCounts {
            valid: at(0),
            covisible: at(1),
            fused: at(2),
            frame_valid: at(3),
            frame_covisible: at(4),
        })
    }

    /// Device: the buffers allocated (parameters, counts, and the resident keyframe and
    /// current frame); nothing on the host.
    fn memory_bytes(&self) -> (usize, usize) {
        let resident = self
            .buffers
            .as_ref()
            .map_or(0, |(cur, kr, kw, _)| cur.size() + kr.size() + kw.size());
        (
            0,
            (self.uniform.size() + self.counts.size() + resident) as usize,
        )
    }

    /// Reads the keyframe back: `(rho, weight)`.
    fn read(&self) -> Result<(Vec<f32>, Vec<f32>), SlamError> {
        let Some((_, kr, kw, _)) = &self.buffers else {
            return Err(SlamError::Internal("read before a keyframe".into()));
        };
        let r = self.ctx.read_buffer(kr, self.pixels)?;
        let w = self.ctx.read_buffer(kw, self.pixels)?;
        Ok((r, w))
    }
}

/// Accumulates frames into the current keyframe's inverse depth, on the GPU when the backend
/// has one (the keyframe stays resident there) or with the CPU mirror. The backend is chosen
/// once, in [`Self::new`].
pub struct KeyframeFuser {
    camera: PinholeCamera,
    params: FusionParams,
    kernels: Box<dyn FusionKernels>,
    /// Pixels of the current keyframe (0 before the first).
    pixels: usize,
}

impl KeyframeFuser {
    /// A fuser for images of `camera` on `backend`.
    pub fn new(
        camera: PinholeCamera,
        params: FusionParams,
        backend: &ComputeBackend,
    ) -> Result<Self, SlamError> {
        let kernels: Box<dyn FusionKernels> = match backend {
            ComputeBackend::Cpu => Box::new(CpuFusion {
                rho: Vec::new(),
                weight: Vec::new(),
            }),
            ComputeBackend::Gpu(ctx) => Box::new(GpuFusion::new(ctx.clone())?),
        };
        Ok(KeyframeFuser {
            camera,
            params,
            kernels,
            pixels: 0,
        })
    }

    /// Bytes this fuser holds, `(host, device)`: the keyframe's inverse depth and weights in
    /// host memory on the CPU backend, and on a GPU the buffers allocated for the resident
    /// keyframe, the frame being fused and the kernel's parameters. Allocates nothing.
    pub fn memory_bytes(&self) -> (usize, usize) {
        self.kernels.memory_bytes()
    }

    /// Starts a keyframe from the inverse depth `rho` (1/m, 0 = invalid): weight 1 where valid.
    pub fn start(&mut self, rho: &ImageF32) -> Result<(), SlamError> {
        let rho: Vec<f32> = rho
            .data
            .iter()
            .map(|&r| if r.is_finite() && r > 0.0 { r } else { 0.0 })
            .collect();
        let weight = rho
            .iter()
            .map(|&r| if r > 0.0 { 1.0 } else { 0.0 })
            .collect();
        self.pixels = rho.len();
        self.kernels.start(rho, weight)
    }

    /// Fuses a frame with inverse depth `cur_rho` whose pose is `cur_from_kf` and whose
    /// geometric scale sigma_W (1/m, the odometry's estimate) is `sigma_geo` (used with
    /// [`FusionParams::tol_sigmas`] > 0 only).
    pub fn fuse(
        &mut self,
        cur_rho: &ImageF32,
        cur_from_kf: &Se3,
        sigma_geo: f64,
    ) -> Result<FusionCounts, SlamError> {
        if cur_rho.data.len() != (self.camera.width * self.camera.height) as usize
            || self.pixels != cur_rho.data.len()
        {
            return Err(SlamError::Internal("fusion frame size mismatch".into()));
        }
        let u = FuseUniform::new(&self.camera, cur_from_kf, sigma_geo, &self.params);
        self.kernels
            .fuse(&cur_rho.data, &u, self.params.both_directions)
    }

    /// The fused keyframe: `(inverse depth, weights)` images.
    pub fn finish(&mut self) -> Result<(ImageF32, ImageF32), SlamError> {
        let (w, h) = (self.camera.width as usize, self.camera.height as usize);
        let (r, wt) = self.kernels.read()?;
        let rho = ImageF32::from_vec(w, h, r)
            .ok_or_else(|| SlamError::Internal("fused keyframe size".into()))?;
        let weight = ImageF32::from_vec(w, h, wt)
            .ok_or_else(|| SlamError::Internal("fused weight size".into()))?;
        Ok((rho, weight))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gpu::{host_layout, layout_mismatches, shaders};

    /// The AVX2 builds of the row loops give the plain builds' values bit for bit (and the
    /// same counts) on a keyframe and a frame with noise, holes and a moved pose, for both
    /// tolerance rules.
    #[cfg(target_arch = "x86_64")]
    #[test]
    fn avx2_rows_match_the_plain_rows_bit_for_bit() {
        if !avx2() {
            eprintln!("no AVX2 on this CPU: nothing to compare");
            return;
        }
        // 83 columns: ten groups of eight and a scalar tail per row.
        let camera = PinholeCamera::new(90.0, 90.0, 41.0, 29.5, 83, 60);
        let (w, h) = (83usize, 60usize);
        let mut state = 12345u64;
        let mut next = move || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((state >> 33) as f32) / (1u64 << 31) as f32
        };
        let mut kf: Vec<f32> = (0..w * h).map(|_| 0.3 + 0.5 * next()).collect();
        // Up to 3 % apart: some measurements fall outside the 3 sigma_W tolerance.
        let mut cur: Vec<f32> = kf
            .iter()
            .map(|r| r * (1.0 + 0.06 * (next() - 0.5)))
            .collect();
        for i in (0..w * h).step_by(7) {
            kf[i] = 0.0;
        }
        for i in (3..w * h).step_by(11) {
            cur[i] = 0.0;
        }
        let weight: Vec<f32> = (0..w * h).map(|_| 1.0 + 10.0 * next()).collect();
        let pose = Se3::exp(&[0.02, -0.01, 0.03, 0.01, 0.02, -0.015]);
        for params in [
            FusionParams::default(),
            FusionParams {
                tol_sigmas: 0.0,
                occlusion: false,
                ..FusionParams::default()
            },
        ] {
            let u = FuseUniform::new(&camera, &pose, 0.004, &params);
            let mut total = FusionCounts::default();
            let (mut r1, mut w1) = (kf.clone(), weight.clone());
            let (mut r2, mut w2) = (kf.clone(), weight.clone());
            for y in 0..h {
                let span = y * w..(y + 1) * w;
                let a = fuse_row(&u, y, &mut r1[span.clone()], &mut w1[span.clone()], &cur);
                // SAFETY: AVX2 checked above.
                let b = unsafe {
                    fuse_row_avx2(&u, y, &mut r2[span.clone()], &mut w2[span.clone()], &cur)
                };
                assert_eq!(a, b, "row {y}");
                total.valid += a.valid;
                total.covisible += a.covisible;
                total.fused += a.fused;
                let c = covisible_back_row(&u, y, &cur[span.clone()], &kf);
                // SAFETY: AVX2 checked above.
                let d = unsafe { covisible_back_row_avx2(&u, y, &cur[span], &kf) };
                assert_eq!(c, d, "row {y}");
            }
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&r1), bits(&r2));
            assert_eq!(bits(&w1), bits(&w2));
            // Every outcome occurs: pixels off the frame or on holes, covisible ones left
            // unfused (inconsistent), fused ones.
            assert!(
                total.fused > 0 && total.covisible < total.valid,
                "{params:?}: {total:?}"
            );
            if params.occlusion {
                assert!(total.fused < (w * h) as u64 * 6 / 7, "{total:?}");
            } else {
                assert!(total.fused < total.covisible, "{total:?}");
            }
            assert_ne!(
                bits(&r1),
                bits(&kf),
                "nothing was fused: the comparison is empty"
            );
        }
    }

    #[test]
    fn fuse_uniform_matches_the_wgsl_layout() {
        let host = host_layout!(FuseUniform {
            width,
            height,
            _pad0 = _pad[0] stride 4,
            _pad1 = _pad[1] stride 4,
            fx,
            fy,
            cx,
            cy,
            rot0 = fwd[0] stride 16,
            rot1 = fwd[1] stride 16,
            rot2 = fwd[2] stride 16,
            inv0 = inv[0] stride 16,
            inv1 = inv[1] stride 16,
            inv2 = inv[2] stride 16,
            tol_abs,
            tol_rel,
            new_weight,
            max_weight,
            tol_sigma,
            occlusion,
            _pad2a = _pad2[0] stride 4,
            _pad2b = _pad2[1] stride 4,
        });
        let src = shaders::assembled("fuse.wgsl").unwrap_or_default();
        let size = std::mem::size_of::<FuseUniform>();
        let bad = layout_mismatches(&src, "Params", &host, size);
        assert!(bad.is_empty(), "{}", bad.join("\n"));
    }
}
