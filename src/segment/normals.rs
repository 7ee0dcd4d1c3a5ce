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
pub struct NormalParams {
    /// Distance in pixels of the finite differences (1 = adjacent pixels; larger smooths noise).
    pub step: u32,
    /// Relative disagreement of the two one-sided inverse-depth differences, as a fraction of
    /// the centre inverse depth, above which the pixel is treated as a depth discontinuity.
    pub jump_tolerance: f32,
}

impl Default for NormalParams {
    fn default() -> Self {
        Self {
            step: 2,
            jump_tolerance: 0.02,
        }
    }
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

/// The normal of pixel `(x, y)`; `[0, 0, 0]` if invalid. Same operations as the WGSL kernel.
#[inline]
pub(crate) fn normal_at(
    rho: &ImageF32,
    x: usize,
    y: usize,
    cam: [f32; 4],
    p: &NormalParams,
) -> [f32; 3] {
    let (w, h) = (rho.width, rho.height);
    let r0 = rho.data[y * w + x];
    if r0.is_nan() || r0 <= 0.0 {
        return [0.0; 3];
    }
    let s = p.step.max(1) as usize;
    let tol = p.jump_tolerance * r0;
    let get = |xx: Option<usize>, yy: Option<usize>| -> f32 {
        match (xx, yy) {
            (Some(a), Some(b)) if a < w && b < h => {
                let v = rho.data[b * w + a];
                if v.is_nan() {
                    0.0
                } else {
                    v
                }
            }
            _ => 0.0,
        }
    };
    let xm = get(x.checked_sub(s), Some(y));
    let xp = get(Some(x + s), Some(y));
    let ym = get(Some(x), y.checked_sub(s));
    let yp = get(Some(x), Some(y + s));
    let (Some(gx), Some(gy)) = (diff(xm, r0, xp, tol), diff(ym, r0, yp, tol)) else {
        return [0.0; 3];
    };
    let inv_s = 1.0 / s as f32;
    let [fx, fy, cx, cy] = cam;
    let xn = (x as f32 - cx) / fx;
    let yn = (y as f32 - cy) / fy;
    let mx = fx * (gx * inv_s);
    let my = fy * (gy * inv_s);
    let mz = r0 - xn * mx - yn * my;
    let len = (mx * mx + my * my + mz * mz).sqrt();
    if !(len > 0.0) || !len.is_finite() {
        return [0.0; 3];
    }
    [-mx / len, -my / len, -mz / len]
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
        data.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
            for (x, out) in row.iter_mut().enumerate() {
                *out = normal_at(inverse_depth, x, y, cam, params);
            }
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
