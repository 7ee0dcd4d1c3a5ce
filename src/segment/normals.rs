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
#[serde(default)]
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
) -> ImageF32 {
    match (labels, along_x) {
        (Some(l), true) => smooth_pass_with::<true>(rho, radius, tolerance, |a, b| l[a] == l[b]),
        (Some(l), false) => smooth_pass_with::<false>(rho, radius, tolerance, |a, b| l[a] == l[b]),
        (None, true) => smooth_pass_with::<true>(rho, radius, tolerance, |_, _| true),
        (None, false) => smooth_pass_with::<false>(rho, radius, tolerance, |_, _| true),
    }
}

/// [`smooth_pass`] for one direction and one same-segment test `same(neighbour, centre)`
/// (monomorphised, so the inner loop has neither branch on them).
fn smooth_pass_with<const ALONG_X: bool>(
    rho: &ImageF32,
    radius: usize,
    tolerance: f32,
    same: impl Fn(usize, usize) -> bool + Sync,
) -> ImageF32 {
    let (w, h) = (rho.width, rho.height);
    let mut out = vec![0.0f32; w * h];
    let data = &rho.data[..w * h];
    let stride = if ALONG_X { 1 } else { w };
    if w > 0 {
        out.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
            for (x, o) in row.iter_mut().enumerate() {
                let i = y * w + x;
                let c = data[i];
                if c.is_nan() || c <= 0.0 {
                    continue;
                }
                let tol = tolerance * c;
                let ok = |j: usize| {
                    let v = data[j];
                    v > 0.0 && (v - c).abs() <= tol && same(j, i)
                };
                let (pos, len) = if ALONG_X { (x, w) } else { (y, h) };
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
                *o = sum / n;
            }
        });
    }
    ImageF32 {
        width: w,
        height: h,
        data: out,
    }
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
    let r = params.smooth_radius as usize;
    let t = params.smooth_tolerance;
    let x = smooth_pass(inverse_depth, r, t, labels, true);
    Some(smooth_pass(&x, r, t, labels, false))
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

/// One-sided / central difference with discontinuity handling (mirrors `diff` in the shader).
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

/// An inverse-depth sample as the kernel reads it: NaN as 0 (no measurement).
#[inline(always)]
fn sample(v: f32) -> f32 {
    if v.is_nan() {
        0.0
    } else {
        v
    }
}

/// The normals of row `y` into `out` (one per pixel, left as they are where invalid; callers
/// pass zeros). Same operations as the WGSL kernel, per pixel; the normalised image
/// coordinates `x_n = (x - cx) / fx` of the columns come precomputed in `xns` (the same
/// values).
fn normal_row(
    rho: &ImageF32,
    y: usize,
    xns: &[f32],
    cam: [f32; 4],
    p: &NormalParams,
    out: &mut [[f32; 3]],
) {
    let (w, h) = (rho.width, rho.height);
    let s = p.step.max(1) as usize;
    let row_at = |yy: usize| rho.data.get(yy * w..(yy + 1) * w);
    let Some(row) = row_at(y) else {
        return;
    };
    let up = y.checked_sub(s).and_then(row_at);
    let down = if y + s < h { row_at(y + s) } else { None };
    let inv_s = 1.0 / s as f32;
    let [fx, fy, _, cy] = cam;
    let yn = (y as f32 - cy) / fy;
    for ((x, o), &xn) in out.iter_mut().enumerate().zip(xns).take(w) {
        let r0 = row[x];
        if r0.is_nan() || r0 <= 0.0 {
            continue;
        }
        let tol = p.jump_tolerance * r0;
        let xm = if x >= s { sample(row[x - s]) } else { 0.0 };
        let xp = if x + s < w { sample(row[x + s]) } else { 0.0 };
        let ym = up.map_or(0.0, |r| sample(r[x]));
        let yp = down.map_or(0.0, |r| sample(r[x]));
        let (Some(gx), Some(gy)) = (diff(xm, r0, xp, tol), diff(ym, r0, yp, tol)) else {
            continue;
        };
        let mx = fx * (gx * inv_s);
        let my = fy * (gy * inv_s);
        let mz = r0 - xn * mx - yn * my;
        let len = (mx * mx + my * my + mz * mz).sqrt();
        if !(len > 0.0) || !len.is_finite() {
            continue;
        }
        *o = [-mx / len, -my / len, -mz / len];
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
    let (w, h) = (inverse_depth.width, inverse_depth.height);
    let cam = cam_f32(camera);
    let mut data = vec![[0.0f32; 3]; w * h];
    if w > 0 {
        let [fx, _, cx, _] = cam;
        let xns: Vec<f32> = (0..w).map(|x| (x as f32 - cx) / fx).collect();
        data.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
            normal_row(inverse_depth, y, &xns, cam, params, row);
        });
    }
    NormalMap {
        width: w,
        height: h,
        data,
    }
}

/// Back-projects every pixel with inverse depth `rho > 0` to a camera-frame point (metres);
/// invalid pixels get `[0, 0, 0]`.
pub fn points_from_inverse_depth(
    inverse_depth: &ImageF32,
    camera: &PinholeCamera,
) -> Vec<[f32; 3]> {
    let (w, h) = (inverse_depth.width, inverse_depth.height);
    let [fx, fy, cx, cy] = cam_f32(camera);
    let mut out = vec![[0.0f32; 3]; w * h];
    if w > 0 {
        out.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
            for (x, o) in row.iter_mut().enumerate() {
                let r = inverse_depth.data[y * w + x];
                if r > 0.0 && r.is_finite() {
                    let z = 1.0 / r;
                    *o = [(x as f32 - cx) / fx * z, (y as f32 - cy) / fy * z, z];
                }
            }
        });
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

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
