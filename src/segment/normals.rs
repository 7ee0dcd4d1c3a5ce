//! Surface normals from an inverse-depth map in the image domain (thesis eq. 5.2), CPU mirror
//! of `shaders/normals.wgsl`.
//!
//! With normalised image coordinates `x = (u - cx) / fx`, `y = (v - cy) / fy` and a plane
//! `n . p = d` in the camera frame, the inverse depth is affine in `(x, y)`:
//! `rho(x, y) = (n_x x + n_y y + n_z) / d`. So from the image gradient of `rho` in pixels,
//! `m = (fx rho_u, fy rho_v, rho - x fx rho_u - y fy rho_v) = n / d`, and the unit normal
//! facing the camera is `-m / |m|` (since `m . (x, y, 1) = rho > 0`). This is exact for planes
//! and needs neither depth nor 3D points: one pass over the inverse-depth image.
//!
//! Derivatives are differences at `step` pixels. Where the two one-sided differences disagree
//! by more than `jump_tolerance * rho` (a depth discontinuity), the one of smaller magnitude is
//! used, so a surface's normals are not bent by the surface behind or in front of it.

use rayon::prelude::*;

use crate::camera::PinholeCamera;
use crate::image::ImageF32;

/// Parameters of the image-domain normal estimator.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct NormalParams {
    /// Distance in pixels of the finite differences (1 = adjacent pixels; larger smooths noise).
    pub step: u32,
    /// Relative disagreement of the two one-sided inverse-depth differences, as a fraction of
    /// the centre inverse depth, above which the pixel is treated as a depth discontinuity.
    pub jump_tolerance: f32,
    /// Half-width in pixels of the edge-aware smoothing of the inverse depth from which the
    /// normals of the superjut *features* (histogram, entropy, horizontality) are computed
    /// (0 = none; the segmentation graph always uses the unsmoothed normals, so creases stay
    /// sharp). Kinect-like depth is quantised in disparity: without smoothing the normals of a
    /// wall scatter over tens of degrees and its neg-entropy drops from ~1 to ~0.25 (measured
    /// on generated sequences), which makes neg-entropy thresholds meaningless.
    pub smooth_radius: u32,
    /// Neighbours whose inverse depth differs from the centre's by more than this fraction of
    /// it are left out of the smoothing (depth discontinuities are kept).
    pub smooth_tolerance: f32,
}

impl Default for NormalParams {
    fn default() -> Self {
        Self {
            step: 2,
            jump_tolerance: 0.02,
            smooth_radius: 3,
            smooth_tolerance: 0.05,
        }
    }
}

/// One edge-aware box pass along x or y: the mean of the centre and the symmetric pairs of
/// neighbours at distance `1..=radius`, stopping at the first pair with an invalid member or
/// one further than `tolerance * centre` from the centre. The window stays symmetric, so an
/// inverse depth that is affine along the line (any plane) is reproduced exactly, borders and
/// discontinuities included.
fn smooth_pass(
    rho: &ImageF32,
    radius: usize,
    tolerance: f32,
    labels: Option<&[u32]>,
    along_x: bool,
    out: &mut ImageF32,
) {
    match (labels, along_x) {
        (Some(l), true) => smooth_pass_with::<true, true>(rho, radius, tolerance, l, out),
        (Some(l), false) => smooth_pass_with::<false, true>(rho, radius, tolerance, l, out),
        (None, true) => smooth_pass_with::<true, false>(rho, radius, tolerance, &[], out),
        (None, false) => smooth_pass_with::<false, false>(rho, radius, tolerance, &[], out),
    }
}

/// Sizes `v` to `n` elements for an output that is then overwritten in full: a buffer of that
/// length (kept from an earlier call) is left as it is, any other is replaced by a fresh one
/// of `zero`s (for zero bit patterns a lazily mapped allocation: see [`normal_row`]).
pub(crate) fn size_for_overwrite<T: Clone>(v: &mut Vec<T>, n: usize, zero: T) {
    if v.len() != n {
        *v = vec![zero; n];
    }
}

/// The reference form of one smoothed pixel `i` (a loop that stops at the first failing
/// pair); used at the image borders, where the window is cut short. `same(j, i)` tells
/// whether neighbour `j` may be averaged with centre `i` (same segment).
#[inline(always)]
fn smooth_pixel<const ALONG_X: bool>(
    data: &[f32],
    (w, h): (usize, usize),
    i: usize,
    radius: usize,
    tolerance: f32,
    same: impl Fn(usize, usize) -> bool,
) -> f32 {
    let c = data[i];
    if c.is_nan() || c <= 0.0 {
        return 0.0;
    }
    let tol = tolerance * c;
    let ok = |j: usize| {
        let v = data[j];
        v > 0.0 && (v - c).abs() <= tol && same(j, i)
    };
    let stride = if ALONG_X { 1 } else { w };
    let (pos, len) = if ALONG_X { (i % w, w) } else { (i / w, h) };
    let reach = radius.min(pos).min(len - 1 - pos);
    let (mut sum, mut n) = (c, 1.0f32);
    for k in 1..=reach {
        let (a, b) = (i - k * stride, i + k * stride);
        if !(ok(a) && ok(b)) {
            break;
        }
        sum += data[a] + data[b];
        n += 2.0;
    }
    sum / n
}

/// Per-row scratch of [`smooth_span`].
#[derive(Default)]
struct SmoothScratch {
    sum: Vec<f32>,
    n: Vec<f32>,
    alive: Vec<bool>,
}

/// One run of pixels for [`smooth_span`]: the `len` pixels from index `start` of `data`
/// (row-major inverse depth, 1/m), neighbours at `start +- k * stride` for `k` in
/// `1..=radius`, all inside the image.
#[derive(Clone, Copy)]
struct Span<'a> {
    data: &'a [f32],
    labels: &'a [u32],
    start: usize,
    len: usize,
    stride: usize,
    radius: usize,
    tolerance: f32,
}

/// [`smooth_pixel`] for a [`Span`]: the pairs are taken distance by distance over the
/// whole span, a pixel's sum growing while all its pairs so far passed (adding `0.0` once one
/// failed leaves the sum bit for bit as the early exit does). No branches in the inner
/// loops, so they vectorise.
#[inline(always)]
fn smooth_span<const LABELS: bool>(span: &Span<'_>, out: &mut [f32], scratch: &mut SmoothScratch) {
    let Span {
        data,
        labels,
        start,
        len,
        stride,
        radius,
        tolerance,
    } = *span;
    let centre = &data[start..start + len];
    let lc = if LABELS {
        &labels[start..start + len]
    } else {
        &[][..]
    };
    let SmoothScratch { sum, n, alive } = scratch;
    sum.clear();
    sum.extend_from_slice(centre);
    n.clear();
    n.resize(len, 1.0);
    alive.clear();
    alive.extend(centre.iter().map(|&c| c > 0.0));
    for k in 1..=radius {
        let (a, b) = (start - k * stride, start + k * stride);
        let (m, p) = (&data[a..a + len], &data[b..b + len]);
        let (lm, lp) = if LABELS {
            (&labels[a..a + len], &labels[b..b + len])
        } else {
            (&[][..], &[][..])
        };
        let (sum, n, alive) = (&mut sum[..len], &mut n[..len], &mut alive[..len]);
        for i in 0..len {
            let c = centre[i];
            let tol = tolerance * c;
            let (vm, vp) = (m[i], p[i]);
            // `&`, not `&&`: every load is made, so no lane needs a masked load.
            let mut ok = alive[i]
                & (vm > 0.0)
                & ((vm - c).abs() <= tol)
                & (vp > 0.0)
                & ((vp - c).abs() <= tol);
            if LABELS {
                ok = ok & (lm[i] == lc[i]) & (lp[i] == lc[i]);
            }
            sum[i] += if ok { vm + vp } else { 0.0 };
            n[i] += if ok { 2.0 } else { 0.0 };
            alive[i] = ok;
        }
    }
    for i in 0..len {
        let c = centre[i];
        out[i] = if c > 0.0 { sum[i] / n[i] } else { 0.0 };
    }
}

/// [`smooth_pass`] for one direction, with or without the same-segment test (monomorphised,
/// so the inner loops have no branch on them). Interior spans go through [`smooth_span`]
/// (AVX2 where the CPU has it), border pixels through [`smooth_pixel`]: the same values.
fn smooth_pass_with<const ALONG_X: bool, const LABELS: bool>(
    rho: &ImageF32,
    radius: usize,
    tolerance: f32,
    labels: &[u32],
    out_image: &mut ImageF32,
) {
    let (w, h) = (rho.width, rho.height);
    out_image.width = w;
    out_image.height = h;
    let out = &mut out_image.data;
    size_for_overwrite(out, w * h, 0.0f32);
    let data = &rho.data[..w * h];
    if !(w > 0 && (!LABELS || labels.len() >= w * h)) {
        out.fill(0.0);
    } else {
        let same = |a: usize, b: usize| !LABELS || labels[a] == labels[b];
        out.par_chunks_mut(w).enumerate().for_each_init(
            SmoothScratch::default,
            |scratch, (y, row)| {
                let pixel = |x: usize| {
                    smooth_pixel::<ALONG_X>(data, (w, h), y * w + x, radius, tolerance, same)
                };
                let (x0, x1) = if ALONG_X {
                    (radius.min(w), w.saturating_sub(radius).max(radius.min(w)))
                } else if y >= radius && y + radius < h {
                    (0, w)
                } else {
                    (0, 0)
                };
                for x in (0..x0).chain(x1..w) {
                    row[x] = pixel(x);
                }
                if x1 > x0 {
                    let stride = if ALONG_X { 1 } else { w };
                    let span = Span {
                        data,
                        labels,
                        start: y * w + x0,
                        len: x1 - x0,
                        stride,
                        radius,
                        tolerance,
                    };
                    smooth_span_dispatch::<LABELS>(&span, &mut row[x0..x1], scratch);
                }
            },
        );
    }
}

/// Runs [`smooth_span`], compiled for AVX2 when the CPU has it (the same IEEE operations).
fn smooth_span_dispatch<const LABELS: bool>(
    span: &Span<'_>,
    out: &mut [f32],
    scratch: &mut SmoothScratch,
) {
    #[cfg(target_arch = "x86_64")]
    {
        if std::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU supports the feature enabled on `smooth_span_avx2`.
            unsafe { smooth_span_avx2::<LABELS>(span, out, scratch) };
            return;
        }
    }
    smooth_span::<LABELS>(span, out, scratch);
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn smooth_span_avx2<const LABELS: bool>(
    span: &Span<'_>,
    out: &mut [f32],
    scratch: &mut SmoothScratch,
) {
    smooth_span::<LABELS>(span, out, scratch);
}

/// Edge-aware smoothing of an inverse-depth map (1/m, 0 = invalid) as [`NormalParams`] asks:
/// two separable passes (x then y); invalid pixels stay invalid. With `labels` (row-major, one
/// per pixel) only pixels of the centre's label are averaged, so the smoothing never crosses a
/// segment boundary (a crease). `None` when no smoothing is asked.
pub fn smooth_inverse_depth(
    inverse_depth: &ImageF32,
    params: &NormalParams,
    labels: Option<&[u32]>,
) -> Option<ImageF32> {
    if params.smooth_radius == 0 {
        return None;
    }
    let (mut x, mut out) = (ImageF32::default(), ImageF32::default());
    smooth_inverse_depth_into(inverse_depth, params, labels, &mut x, &mut out).then_some(out)
}

/// [`smooth_inverse_depth`] into `out`, with `tmp` for the first pass (both buffers reused,
/// as kept between keyframes); false (and the buffers untouched) when no smoothing is asked.
pub(crate) fn smooth_inverse_depth_into(
    inverse_depth: &ImageF32,
    params: &NormalParams,
    labels: Option<&[u32]>,
    tmp: &mut ImageF32,
    out: &mut ImageF32,
) -> bool {
    if params.smooth_radius == 0 {
        return false;
    }
    let r = params.smooth_radius as usize;
    let t = params.smooth_tolerance;
    smooth_pass(inverse_depth, r, t, labels, true, tmp);
    smooth_pass(tmp, r, t, labels, false, out);
    true
}

/// A unit-normal image in the camera frame (x right, y down, z forward), normals facing the
/// camera; `[0, 0, 0]` where no normal could be estimated.
#[derive(Clone, Debug, PartialEq)]
pub struct NormalMap {
    /// Width in pixels.
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// Row-major unit normals (dimensionless), zero vector = invalid.
    pub data: Vec<[f32; 3]>,
}

impl NormalMap {
    /// True if pixel index `i` has a normal.
    #[inline]
    pub fn is_valid(&self, i: usize) -> bool {
        let n = self.data[i];
        n[0] != 0.0 || n[1] != 0.0 || n[2] != 0.0
    }

    /// Number of pixels with a normal.
    pub fn valid_count(&self) -> usize {
        (0..self.data.len()).filter(|&i| self.is_valid(i)).count()
    }
}

/// An inverse-depth sample as the kernel reads it: NaN as 0 (no measurement).
#[inline(always)]
fn sample(v: f32) -> f32 {
    if v.is_nan() {
        0.0
    } else {
        v
    }
}

/// Derivative of [`diff`] without branches: `(value, valid)`, the same value wherever
/// [`diff`] returns `Some` (every case is computed and the result selected).
#[inline(always)]
fn diff_select(minus: f32, centre: f32, plus: f32, tol: f32) -> (f32, bool) {
    let vm = minus > 0.0;
    let vp = plus > 0.0;
    let dm = centre - minus;
    let dp = plus - centre;
    let avg = 0.5 * (dm + dp);
    let both = if (dp - dm).abs() <= tol {
        avg
    } else if dp.abs() < dm.abs() {
        dp
    } else {
        dm
    };
    let one = if vm { dm } else { dp };
    (if vm && vp { both } else { one }, vm || vp)
}

/// The normal of one pixel from its inverse depth `r0` and the samples `xm, xp, ym, yp` at
/// `step` pixels left, right, up and down (0 where there is none), or `None`. The
/// operations of [`normal_row`]'s scalar path, written as selects so that a row's interior
/// vectorises.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn normal_select(
    r0: f32,
    xm: f32,
    xp: f32,
    ym: f32,
    yp: f32,
    xn: f32,
    yn: f32,
    fx: f32,
    fy: f32,
    inv_s: f32,
    jump_tolerance: f32,
) -> ([f32; 3], bool) {
    let tol = jump_tolerance * r0;
    let (gx, okx) = diff_select(sample(xm), r0, sample(xp), tol);
    let (gy, oky) = diff_select(sample(ym), r0, sample(yp), tol);
    let mx = fx * (gx * inv_s);
    let my = fy * (gy * inv_s);
    let mz = r0 - xn * mx - yn * my;
    let len = (mx * mx + my * my + mz * mz).sqrt();
    let ok = r0 > 0.0 && okx && oky && len > 0.0 && len.is_finite();
    ([-mx / len, -my / len, -mz / len], ok)
}

/// What every row of [`normals_cpu`] shares: the inverse depth (1/m), the normalised image
/// coordinates `x_n = (x - cx) / fx` of the columns (the values the WGSL computes), a row of
/// `0.0` standing in for rows above or below the image, the intrinsics and the parameters.
#[derive(Clone, Copy)]
struct NormalRows<'a> {
    rho: &'a ImageF32,
    xns: &'a [f32],
    zeros: &'a [f32],
    cam: [f32; 4],
    params: &'a NormalParams,
}

/// The normals of row `y` into `out` (one per pixel, `[0, 0, 0]` where invalid). Every
/// element is written and none is read: an output freshly allocated as zeros then takes one
/// plain page fault per page, where reading it first maps the shared zero page and the write
/// after it costs a copy-on-write fault with a TLB shootdown across cores. Same operations as the WGSL kernel, per pixel. The interior columns run
/// through a loop without branches (the compiler vectorises it; with AVX2 where the CPU has
/// it), the `step` columns at each border through the same per-pixel function with their
/// missing neighbours as 0.
fn normal_row(rows: &NormalRows<'_>, y: usize, out: &mut [[f32; 3]]) {
    #[cfg(target_arch = "x86_64")]
    {
        if std::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU supports the feature enabled on `normal_row_avx2`.
            unsafe { normal_row_avx2(rows, y, out) };
            return;
        }
    }
    normal_row_body(rows, y, out);
}

/// [`normal_row_body`] compiled for AVX2 (8 lanes; the same IEEE operations, so the same
/// results).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn normal_row_avx2(rows: &NormalRows<'_>, y: usize, out: &mut [[f32; 3]]) {
    normal_row_body(rows, y, out);
}

#[inline(always)]
fn normal_row_body(rows: &NormalRows<'_>, y: usize, out: &mut [[f32; 3]]) {
    let NormalRows {
        rho,
        xns,
        zeros,
        cam,
        params: p,
    } = *rows;
    let (w, h) = (rho.width, rho.height);
    let s = p.step.max(1) as usize;
    let row_at = |yy: usize| rho.data.get(yy * w..(yy + 1) * w);
    let Some(row) = row_at(y) else {
        return;
    };
    if xns.len() < w || zeros.len() < w || out.len() < w {
        return;
    }
    let up = y.checked_sub(s).and_then(row_at).unwrap_or(&zeros[..w]);
    let down = if y + s < h { row_at(y + s) } else { None }.unwrap_or(&zeros[..w]);
    let inv_s = 1.0 / s as f32;
    let [fx, fy, _, cy] = cam;
    let yn = (y as f32 - cy) / fy;
    let jt = p.jump_tolerance;
    let px = |x: usize| {
        let xm = if x >= s { row[x - s] } else { 0.0 };
        let xp = if x + s < w { row[x + s] } else { 0.0 };
        normal_select(
            row[x], xm, xp, up[x], down[x], xns[x], yn, fx, fy, inv_s, jt,
        )
    };
    if w <= 2 * s {
        for (x, o) in out.iter_mut().enumerate().take(w) {
            let (n, ok) = px(x);
            *o = if ok { n } else { [0.0; 3] };
        }
        return;
    }
    for x in (0..s).chain(w - s..w) {
        let (n, ok) = px(x);
        out[x] = if ok { n } else { [0.0; 3] };
    }
    let n_in = w - 2 * s;
    let centre = &row[s..s + n_in];
    let minus = &row[..n_in];
    let plus = &row[2 * s..2 * s + n_in];
    let (up, down, xns) = (&up[s..s + n_in], &down[s..s + n_in], &xns[s..s + n_in]);
    let out = &mut out[s..s + n_in];
    for i in 0..n_in {
        let (n, ok) = normal_select(
            centre[i], minus[i], plus[i], up[i], down[i], xns[i], yn, fx, fy, inv_s, jt,
        );
        out[i] = [
            if ok { n[0] } else { 0.0 },
            if ok { n[1] } else { 0.0 },
            if ok { n[2] } else { 0.0 },
        ];
    }
}

/// Camera intrinsics as the f32 quadruple the kernels use.
pub(crate) fn cam_f32(camera: &PinholeCamera) -> [f32; 4] {
    [
        camera.fx as f32,
        camera.fy as f32,
        camera.cx as f32,
        camera.cy as f32,
    ]
}

/// Image-domain normals of an inverse-depth map (1/m, 0 = invalid) on the CPU (rayon).
///
/// The camera's `width`/`height` are not checked here; callers that mix images check sizes.
pub fn normals_cpu(
    inverse_depth: &ImageF32,
    camera: &PinholeCamera,
    params: &NormalParams,
) -> NormalMap {
    let mut data = Vec::new();
    normals_cpu_into(inverse_depth, camera, params, &mut data);
    NormalMap {
        width: inverse_depth.width,
        height: inverse_depth.height,
        data,
    }
}

/// [`normals_cpu`]'s data into `data` (a buffer kept from an earlier call of the same size is
/// overwritten in place).
pub(crate) fn normals_cpu_into(
    inverse_depth: &ImageF32,
    camera: &PinholeCamera,
    params: &NormalParams,
    data: &mut Vec<[f32; 3]>,
) {
    let (w, h) = (inverse_depth.width, inverse_depth.height);
    let cam = cam_f32(camera);
    size_for_overwrite(data, w * h, [0.0f32; 3]);
    if inverse_depth.data.len() < w * h {
        // Rows without data are not written below.
        data.fill([0.0; 3]);
    }
    if w > 0 {
        let [fx, _, cx, _] = cam;
        let xns: Vec<f32> = (0..w).map(|x| (x as f32 - cx) / fx).collect();
        let zeros = vec![0.0f32; w];
        let rows = NormalRows {
            rho: inverse_depth,
            xns: &xns,
            zeros: &zeros,
            cam,
            params,
        };
        data.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
            normal_row(&rows, y, row);
        });
    }
}

/// Back-projects every pixel with inverse depth `rho > 0` to a camera-frame point (metres);
/// invalid pixels get `[0, 0, 0]`.
pub fn points_from_inverse_depth(
    inverse_depth: &ImageF32,
    camera: &PinholeCamera,
) -> Vec<[f32; 3]> {
    let mut out = Vec::new();
    points_from_inverse_depth_into(inverse_depth, camera, &mut out);
    out
}

/// [`points_from_inverse_depth`] into `out` (a buffer kept from an earlier call of the same
/// size is overwritten in place).
pub(crate) fn points_from_inverse_depth_into(
    inverse_depth: &ImageF32,
    camera: &PinholeCamera,
    out: &mut Vec<[f32; 3]>,
) {
    let (w, h) = (inverse_depth.width, inverse_depth.height);
    let [fx, fy, cx, cy] = cam_f32(camera);
    size_for_overwrite(out, w * h, [0.0f32; 3]);
    if inverse_depth.data.len() < w * h {
        // Rows without data are not written below.
        out.fill([0.0; 3]);
    }
    if w > 0 {
        let xs: Vec<f32> = (0..w).map(|x| (x as f32 - cx) / fx).collect();
        out.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
            let yn = (y as f32 - cy) / fy;
            let rho = inverse_depth.data.get(y * w..(y + 1) * w).unwrap_or(&[]);
            // Selects, not branches, so the row vectorises; the same values. Written without
            // reading the output first (see `normal_row`).
            for ((o, &r), &xn) in row.iter_mut().zip(rho).zip(&xs) {
                let ok = r > 0.0 && r.is_finite();
                let z = 1.0 / r;
                let p = [xn * z, yn * z, z];
                *o = if ok { p } else { [0.0; 3] };
            }
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// One-sided / central difference with discontinuity handling (the branching form of `diff` in the shader): the reference for `diff_select`.
    #[inline]
    fn diff(minus: f32, centre: f32, plus: f32, tol: f32) -> Option<f32> {
        let vm = minus > 0.0;
        let vp = plus > 0.0;
        let dm = centre - minus;
        let dp = plus - centre;
        if vm && vp {
            if (dp - dm).abs() <= tol {
                Some(0.5 * (dm + dp))
            } else if dp.abs() < dm.abs() {
                Some(dp)
            } else {
                Some(dm)
            }
        } else if vm {
            Some(dm)
        } else if vp {
            Some(dp)
        } else {
            None
        }
    }

    /// The vectorised spans give, bit for bit, what the per-pixel loop with its early exit
    /// gives, on noisy depth with holes, NaNs, jumps and segment labels, along both axes.
    #[test]
    fn smoothing_spans_match_the_per_pixel_loop() {
        let (w, h) = (53, 41);
        use rand::{Rng, SeedableRng};
        let mut rng = rand_pcg::Pcg64::seed_from_u64(11);
        let mut next = || rng.random::<f32>();
        let mut rho = ImageF32::filled(w, h, 0.0);
        for y in 0..h {
            for x in 0..w {
                let u = next();
                let base = if x < 25 { 0.4 } else { 0.7 } + 0.002 * y as f32;
                rho.data[y * w + x] = match u {
                    u if u < 0.05 => 0.0,
                    u if u < 0.07 => f32::NAN,
                    u if u < 0.08 => -0.2,
                    _ => base * (1.0 + 0.04 * (next() - 0.5)),
                };
            }
        }
        let labels: Vec<u32> = (0..w * h)
            .map(|i| ((i % w) / 9 + (i / w) / 13) as u32)
            .collect();
        // One output buffer for all runs: each must overwrite what the last one left.
        let mut got = ImageF32::default();
        for radius in [1usize, 3, 5] {
            for along_x in [true, false] {
                for lab in [None, Some(&labels[..])] {
                    smooth_pass(&rho, radius, 0.05, lab, along_x, &mut got);
                    for i in 0..w * h {
                        let same = |a: usize, b: usize| lab.is_none_or(|l| l[a] == l[b]);
                        let want = if along_x {
                            smooth_pixel::<true>(&rho.data, (w, h), i, radius, 0.05, same)
                        } else {
                            smooth_pixel::<false>(&rho.data, (w, h), i, radius, 0.05, same)
                        };
                        assert_eq!(
                            got.data[i].to_bits(),
                            want.to_bits(),
                            "pixel {i} r {radius}"
                        );
                    }
                }
            }
        }
    }

    /// The branch-free derivative equals the branching one on every kind of input:
    /// both sides valid (smooth and across a jump), one side, none, NaN and negative samples.
    #[test]
    fn diff_select_matches_the_branching_form() {
        let vals = [
            0.0f32,
            -0.3,
            f32::NAN,
            0.25,
            0.5,
            0.5001,
            0.51,
            0.7,
            1.0e-6,
            3.0,
        ];
        for &m in &vals {
            for &c in &vals[3..] {
                for &p in &vals {
                    for tol in [0.0f32, 0.001, 0.02, 1.0] {
                        let (m, p) = (sample(m), sample(p));
                        let (g, ok) = diff_select(m, c, p, tol);
                        match diff(m, c, p, tol) {
                            Some(r) => {
                                assert!(ok && g.to_bits() == r.to_bits(), "{m} {c} {p} {tol}")
                            }
                            None => assert!(!ok, "{m} {c} {p} {tol}"),
                        }
                    }
                }
            }
        }
    }

    /// A plane's inverse depth is affine in the pixel coordinates; the symmetric windows keep
    /// it exactly (borders included), while a step (a discontinuity) is not smeared.
    #[test]
    fn smoothing_keeps_planes_and_steps() {
        let (w, h) = (40, 30);
        let mut rho = ImageF32::filled(w, h, 0.0);
        for y in 0..h {
            for x in 0..w {
                let v = 0.5 + 0.004 * x as f32 - 0.003 * y as f32;
                rho.data[y * w + x] = if x < 20 { v } else { v + 0.3 };
            }
        }
        rho.data[5 * w + 5] = 0.0; // a hole stays a hole
        let p = NormalParams::default();
        let s = smooth_inverse_depth(&rho, &p, None).unwrap();
        assert_eq!(s.data[5 * w + 5], 0.0);
        for i in 0..w * h {
            assert!((s.data[i] - rho.data[i]).abs() < 1e-5, "pixel {i}");
        }
        // Labels stop the smoothing too: noise on label 1 does not leak into label 0.
        let labels: Vec<u32> = (0..w * h).map(|i| u32::from(i % w >= 10)).collect();
        let mut noisy = rho.clone();
        for y in 0..h {
            noisy.data[y * w + 10] += 0.01;
        }
        let s = smooth_inverse_depth(&noisy, &p, Some(&labels)).unwrap();
        for y in 0..h {
            for x in 0..10 {
                let i = y * w + x;
                assert!((s.data[i] - noisy.data[i]).abs() < 1e-5, "pixel {x},{y}");
            }
        }
        let off = NormalParams {
            smooth_radius: 0,
            ..p
        };
        assert!(smooth_inverse_depth(&rho, &off, None).is_none());
    }
}
