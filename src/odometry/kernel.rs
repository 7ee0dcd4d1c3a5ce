//! The per-pixel mathematics of the odometry kernels: the CPU mirror of
//! `shaders/pyramid.wgsl` and `shaders/odometry.wgsl`, operation for operation.
//!
//! Buffer layout shared by both backends: per frame, all pyramid levels concatenated, two
//! `vec4<f32>` per pixel:
//! - `photo = (I, dI/du, dI/dv, 0)`, intensity in [0, 255] and its central-difference gradient;
//! - `geo = (rho, drho/du, drho/dv, 0)`, inverse depth in 1/m (0 = invalid) and its gradient,
//!   with [`INVALID_GRAD`] where the gradient cannot be computed.

use bytemuck::{Pod, Zeroable};

use super::robust::weight;

/// Sentinel stored in the inverse-depth gradient where it is undefined.
pub const INVALID_GRAD: f32 = 1.0e30;
/// Sentinel for an invalid sampled residual.
pub const INVALID_RESIDUAL: f32 = 3.0e38;
/// Inverse-depth gradients larger than this fraction of the inverse depth per pixel mark a
/// depth discontinuity: the geometric residual is not used there (its linearisation is
/// meaningless across an occluding edge).
pub const MAX_REL_GRAD: f32 = 0.05;
/// Closest point depth (m) accepted after warping.
pub const MIN_DEPTH: f32 = 0.05;
/// Number of f32 values per reduction partial: 21 (upper-triangular H) + 6 (g) + cost +
/// photometric count + geometric count + (unused).
pub const PARTIAL_LEN: usize = 30;

/// Normal-equation partials and the residual sample taken in the same pass
/// (`(partials, [(r_photo, r_geo)])`, see `normal_equations_and_sample` of both backends).
pub type PartialsAndSample = (Vec<[f32; PARTIAL_LEN]>, Vec<[f32; 2]>);

/// Uniform parameters of the warp kernels (mirrors `WarpParams` in `odometry.wgsl`).
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
pub struct WarpParams {
    /// width, height, level offset (pixels), sample count.
    pub dims: [u32; 4],
    /// fx, fy, cx, cy of the level, pixels.
    pub intr: [f32; 4],
    /// Rows of the rotation of `cur_from_ref`; `.w` holds the translation component (m).
    pub rot: [[f32; 4]; 3],
    /// sigma_I, sigma_W, nu_I, nu_W.
    pub robust: [f32; 4],
    /// estimator code, term mask (1 photometric, 2 geometric), geometric code (bit 0: depth
    /// instead of inverse depth; bit 1: first-order instead of nearest inverse-depth
    /// sampling), offset of the residual sample in the GPU output buffer.
    pub flags: [u32; 4],
}

impl WarpParams {
    /// Builds the rotation/translation rows from `cur_from_ref`.
    pub fn set_pose(&mut self, cur_from_ref: &crate::geometry::Se3) {
        let r = cur_from_ref.rotation_matrix();
        let t = cur_from_ref.translation;
        for i in 0..3 {
            self.rot[i] = [
                r.row(i).x as f32,
                r.row(i).y as f32,
                r.row(i).z as f32,
                t[i] as f32,
            ];
        }
    }
}

/// Uniform parameters of the pyramid kernels (mirrors `PyrParams` in `pyramid.wgsl`).
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
pub struct PyrParams {
    /// destination width, height, destination offset, source offset.
    pub dims: [u32; 4],
    /// source width, source height, unused, unused.
    pub src: [u32; 4],
}

/// Level 0 packing: intensity and inverse depth into `photo.x` and `geo.x`.
/// Non-finite or negative inverse depths become 0 (invalid).
#[inline]
pub fn pack_level0(i: f32, rho: f32) -> ([f32; 4], [f32; 4]) {
    let r = if rho.is_finite() && rho > 0.0 {
        rho
    } else {
        0.0
    };
    ([i, 0.0, 0.0, 0.0], [r, 0.0, 0.0, 0.0])
}

/// Downsampled pixel from a 2x2 block: mean intensity, mean of the valid inverse depths.
#[inline]
pub fn downsample(i4: [f32; 4], r4: [f32; 4]) -> (f32, f32) {
    let i = 0.25 * (i4[0] + i4[1] + i4[2] + i4[3]);
    let mut s = 0.0;
    let mut n = 0.0;
    for r in r4 {
        if r > 0.0 {
            s += r;
            n += 1.0;
        }
    }
    (i, if n > 0.0 { s / n } else { 0.0 })
}

/// Central-difference gradients at (x, y) of one level (clamped at the borders) of the values
/// in `lane` of each pixel (0: the level's own values; 3: the bilateral-filtered values written
/// by [`bilateral`]). Returns the photometric and geometric gradient pairs. Mirror of
/// `level_gradients` in `pyramid.wgsl`.
#[inline]
pub fn gradients_of_lane(
    photo: &[[f32; 4]],
    geo: &[[f32; 4]],
    w: usize,
    h: usize,
    x: usize,
    y: usize,
    lane: usize,
) -> ([f32; 2], [f32; 2]) {
    let xl = x.saturating_sub(1);
    let xr = (x + 1).min(w - 1);
    let yu = y.saturating_sub(1);
    let yd = (y + 1).min(h - 1);
    let gx = 0.5 * (photo[y * w + xr][lane] - photo[y * w + xl][lane]);
    let gy = 0.5 * (photo[yd * w + x][lane] - photo[yu * w + x][lane]);
    let c = geo[y * w + x][lane];
    let gdx = one_axis(
        geo[y * w + xl][lane],
        c,
        geo[y * w + xr][lane],
        x > 0,
        x + 1 < w,
    );
    let gdy = one_axis(
        geo[yu * w + x][lane],
        c,
        geo[yd * w + x][lane],
        y > 0,
        y + 1 < h,
    );
    let lim = MAX_REL_GRAD * c;
    if c > 0.0 && gdx != INVALID_GRAD && gdy != INVALID_GRAD && gdx.abs() <= lim && gdy.abs() <= lim
    {
        ([gx, gy], [gdx, gdy])
    } else {
        ([gx, gy], [INVALID_GRAD, INVALID_GRAD])
    }
}

/// Radius (pixels) of the bilateral filter of [`bilateral`]: a 5x5 window.
pub const BILATERAL_RADIUS: usize = 2;

/// Uniform parameters of the bilateral-gradient kernels (mirrors `FilterParams` in
/// `pyramid.wgsl`).
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
pub struct FilterParams {
    /// width, height, level offset (pixels), unused.
    pub dims: [u32; 4],
    /// unused, `1 / (2 sigma_I^2)` (1/intensity^2), `1 / (2 sigma_rho^2)` (m^2), unused.
    pub inv2: [f32; 4],
}

impl FilterParams {
    /// Parameters for a `w x h` level at `offset` with photometric range scale `sigma_photo`
    /// (intensity levels) and inverse-depth range scale `sigma_rho` (1/m).
    pub fn new(w: usize, h: usize, offset: usize, sigma_photo: f64, sigma_rho: f64) -> Self {
        let inv2 = |s: f64| (0.5 / (s * s).max(1e-30)) as f32;
        Self {
            dims: [w as u32, h as u32, offset as u32, 0],
            inv2: [0.0, inv2(sigma_photo), inv2(sigma_rho), 0.0],
        }
    }
}

// The GPU writes `FilterParams` into a `PyrParams` uniform.
const _: () = assert!(std::mem::size_of::<FilterParams>() == std::mem::size_of::<PyrParams>());

/// Bilateral filter at (x, y) of one level, over a `(2 BILATERAL_RADIUS + 1)^2` window clamped
/// to the image, with a flat spatial kernel and the Cauchy range kernel
/// `1 / (1 + d^2 / (2 sigma^2))` (no transcendental per tap: the filter runs once per frame on
/// the finest level used): intensity weighted by its difference to the centre, inverse depth
/// by its difference over valid (> 0) neighbours only (0 where the pixel itself has no
/// depth). Returns `(I_filtered, rho_filtered)`. Mirror of `bilateral` in `pyramid.wgsl`.
#[inline]
pub fn bilateral(
    f: &FilterParams,
    photo: &[[f32; 4]],
    geo: &[[f32; 4]],
    x: usize,
    y: usize,
) -> (f32, f32) {
    let (w, h) = (f.dims[0] as usize, f.dims[1] as usize);
    let c = y * w + x;
    let (ic, rc) = (photo[c][0], geo[c][0]);
    let (mut si, mut wi, mut sr, mut wr) = (0.0f32, 0.0f32, 0.0f32, 0.0f32);
    let r = BILATERAL_RADIUS;
    for v in y.saturating_sub(r)..(y + r + 1).min(h) {
        for u in x.saturating_sub(r)..(x + r + 1).min(w) {
            let k = v * w + u;
            let di = photo[k][0] - ic;
            let a = 1.0 / (1.0 + f.inv2[1] * di * di);
            si += a * photo[k][0];
            wi += a;
            let rk = geo[k][0];
            if rc > 0.0 && rk > 0.0 {
                let dr = rk - rc;
                let b = 1.0 / (1.0 + f.inv2[2] * dr * dr);
                sr += b * rk;
                wr += b;
            }
        }
    }
    // The centre's own weight is 1, so both sums are positive where they are used.
    (si / wi, if rc > 0.0 && wr > 0.0 { sr / wr } else { 0.0 })
}

/// Derivative of inverse depth along one axis: central if both neighbours are valid, one-sided
/// if one is, [`INVALID_GRAD`] otherwise.
#[inline]
fn one_axis(l: f32, c: f32, r: f32, has_l: bool, has_r: bool) -> f32 {
    let lv = has_l && l > 0.0;
    let rv = has_r && r > 0.0;
    if lv && rv {
        0.5 * (r - l)
    } else if rv {
        r - c
    } else if lv {
        c - l
    } else {
        INVALID_GRAD
    }
}

/// Residuals and Jacobians of one reference pixel.
#[derive(Clone, Copy, Debug, Default)]
pub struct PixelTerms {
    /// Photometric residual `I_cur(w(x)) - I_ref(x)` (intensity levels), if valid.
    pub r_photo: Option<f32>,
    /// Its Jacobian with respect to the left twist of `cur_from_ref`, `[v; w]`.
    pub j_photo: [f32; 6],
    /// Geometric residual (inverse depth 1/m, or depth m), if valid.
    pub r_geo: Option<f32>,
    /// Its Jacobian.
    pub j_geo: [f32; 6],
}

#[inline]
fn cross(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

/// Reference pixel `i` back-projected with its inverse depth and moved into the current
/// camera by `cur_from_ref` (metres); `None` where it has no depth. Mirror of `warp_point`
/// in the WGSL.
#[inline]
fn warp_point(p: &WarpParams, ref_geo: &[[f32; 4]], i: usize) -> Option<[f32; 3]> {
    let w = p.dims[0] as usize;
    let rho = ref_geo[i][0];
    if rho <= 0.0 {
        return None;
    }
    let (fx, fy, cx, cy) = (p.intr[0], p.intr[1], p.intr[2], p.intr[3]);
    let x = (i % w) as f32;
    let y = (i / w) as f32;
    let z = 1.0 / rho;
    let pr = [(x - cx) / fx * z, (y - cy) / fy * z, z];
    let r = &p.rot;
    Some([
        r[0][0] * pr[0] + r[0][1] * pr[1] + r[0][2] * pr[2] + r[0][3],
        r[1][0] * pr[0] + r[1][1] * pr[1] + r[1][2] * pr[2] + r[1][3],
        r[2][0] * pr[0] + r[2][1] * pr[1] + r[2][2] * pr[2] + r[2][3],
    ])
}

/// Warps reference pixel `i` of the level into the current frame and evaluates the residuals
/// and Jacobians (thesis eq. 6.5-6.13; bilinear intensity, nearest inverse depth).
/// Mirror of `pixel_terms` in `odometry.wgsl`.
#[inline]
pub fn pixel_terms(
    p: &WarpParams,
    ref_photo: &[[f32; 4]],
    ref_geo: &[[f32; 4]],
    cur_photo: &[[f32; 4]],
    cur_geo: &[[f32; 4]],
    i: usize,
    want_jacobians: bool,
) -> PixelTerms {
    let mut out = PixelTerms::default();
    let w = p.dims[0] as usize;
    let h = p.dims[1] as usize;
    let Some(q) = warp_point(p, ref_geo, i) else {
        return out;
    };
    let (fx, fy, cx, cy) = (p.intr[0], p.intr[1], p.intr[2], p.intr[3]);
    if q[2] < MIN_DEPTH {
        return out;
    }
    let iz = 1.0 / q[2];
    let u = fx * q[0] * iz + cx;
    let v = fy * q[1] * iz + cy;
    if !(u >= 0.0 && v >= 0.0 && u < (w - 1) as f32 && v < (h - 1) as f32) {
        return out;
    }
    let x0 = u.floor();
    let y0 = v.floor();
    let ax = u - x0;
    let ay = v - y0;
    let k = y0 as usize * w + x0 as usize;
    let (p00, p10, p01, p11) = (
        cur_photo[k],
        cur_photo[k + 1],
        cur_photo[k + w],
        cur_photo[k + w + 1],
    );
    let b00 = (1.0 - ax) * (1.0 - ay);
    let b10 = ax * (1.0 - ay);
    let b01 = (1.0 - ax) * ay;
    let b11 = ax * ay;
    let mut c = [0.0f32; 3];
    for (ch, cc) in c.iter_mut().enumerate() {
        *cc = b00 * p00[ch] + b10 * p10[ch] + b01 * p01[ch] + b11 * p11[ch];
    }
    let terms = p.flags[1];
    if terms & 1 != 0 {
        out.r_photo = Some(c[0] - ref_photo[i][0]);
        if want_jacobians {
            let a = c[1] * fx * iz;
            let b = c[2] * fy * iz;
            let jt = [a, b, -(a * q[0] + b * q[1]) * iz];
            let jr = cross(q, jt);
            out.j_photo = [jt[0], jt[1], jt[2], jr[0], jr[1], jr[2]];
        }
    }
    if terms & 2 != 0 {
        let xn = (u + 0.5).floor() as usize;
        let yn = (v + 0.5).floor() as usize;
        let g = cur_geo[yn * w + xn];
        if g[0] > 0.0 && g[1] != INVALID_GRAD {
            let depth_param = p.flags[2] & 1 == 1;
            let rho = if p.flags[2] & 2 == 2 {
                g[0] + g[1] * (u - xn as f32) + g[2] * (v - yn as f32)
            } else {
                g[0]
            };
            let (res, gu, gv, dz) = if depth_param {
                let ig2 = 1.0 / (rho * rho);
                (1.0 / rho - q[2], -g[1] * ig2, -g[2] * ig2, -1.0)
            } else {
                (rho - iz, g[1], g[2], iz * iz)
            };
            out.r_geo = Some(res);
            if want_jacobians {
                let a = gu * fx * iz;
                let b = gv * fy * iz;
                let jt = [a, b, -(a * q[0] + b * q[1]) * iz + dz];
                let jr = cross(q, jt);
                out.j_geo = [jt[0], jt[1], jt[2], jr[0], jr[1], jr[2]];
            }
        }
    }
    out
}

/// Adds `wt * J J^T` and `wt * J r` to a partial (mirror of `accumulate` in the WGSL).
#[inline]
pub fn accumulate(acc: &mut [f32; PARTIAL_LEN], j: &[f32; 6], r: f32, wt: f32) {
    let mut k = 0;
    for a in 0..6 {
        let wa = wt * j[a];
        for b in a..6 {
            acc[k] += wa * j[b];
            k += 1;
        }
    }
    for a in 0..6 {
        acc[21 + a] += wt * j[a] * r;
    }
}

/// Accumulates the IRLS normal equations of reference pixel `i` into `acc`.
/// Mirror of the body of `normal_equations` in the WGSL.
#[inline]
pub fn accumulate_pixel(
    p: &WarpParams,
    ref_photo: &[[f32; 4]],
    ref_geo: &[[f32; 4]],
    cur_photo: &[[f32; 4]],
    cur_geo: &[[f32; 4]],
    i: usize,
    acc: &mut [f32; PARTIAL_LEN],
) {
    let t = pixel_terms(p, ref_photo, ref_geo, cur_photo, cur_geo, i, true);
    let est = p.flags[0];
    if let Some(r) = t.r_photo {
        let s = p.robust[0];
        let z = r / s;
        let w = weight(est, z, p.robust[2]) / (s * s);
        accumulate(acc, &t.j_photo, r, w);
        acc[27] += w * r * r;
        acc[28] += 1.0;
    }
    if let Some(r) = t.r_geo {
        let s = p.robust[1];
        let z = r / s;
        let w = weight(est, z, p.robust[3]) / (s * s);
        accumulate(acc, &t.j_geo, r, w);
        acc[27] += w * r * r;
        acc[29] += 1.0;
    }
}

/// Index of the `k`-th of `count` systematic samples among `n` pixels.
#[inline]
pub fn sample_index(k: u32, count: u32, n: u32) -> u32 {
    ((u64::from(k) * u64::from(n)) / u64::from(count.max(1))) as u32
}

/// Covisibility test of reference pixel `i`: 0 if it has no depth, 1 if it has depth but
/// warps outside the current image or onto a pixel without depth, 2 if it is covisible.
#[inline]
pub fn covisible(p: &WarpParams, ref_geo: &[[f32; 4]], cur_geo: &[[f32; 4]], i: usize) -> u32 {
    let w = p.dims[0] as usize;
    let h = p.dims[1] as usize;
    let Some(q) = warp_point(p, ref_geo, i) else {
        return 0;
    };
    let (fx, fy, cx, cy) = (p.intr[0], p.intr[1], p.intr[2], p.intr[3]);
    if q[2] < MIN_DEPTH {
        return 1;
    }
    let u = fx * q[0] / q[2] + cx;
    let v = fy * q[1] / q[2] + cy;
    let xn = (u + 0.5).floor();
    let yn = (v + 0.5).floor();
    if !(xn >= 0.0 && yn >= 0.0 && xn < w as f32 && yn < h as f32) {
        return 1;
    }
    if cur_geo[yn as usize * w + xn as usize][0] > 0.0 {
        2
    } else {
        1
    }
}

#[cfg(test)]
mod tests {
    use super::super::robust::{HUBER_K, TUKEY_C};
    use super::*;

    use crate::geometry::Se3;
    use crate::image::{ImageF32, RgbdFrame};
    use crate::odometry::cpu::CpuPyramid;

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
        }
    }

    #[test]
    fn jacobians_match_finite_differences() {
        let (w, h) = (160usize, 120usize);
        let f = smooth_frame(w, h);
        let pyr = CpuPyramid::build(&f, 1);
        let cur_from_ref = Se3::exp(&[0.01, -0.005, 0.02, 0.004, -0.006, 0.002]);
        for (param, terms) in [(0u32, 3u32), (1, 3)] {
            let mut p = WarpParams {
                dims: [w as u32, h as u32, 0, 0],
                intr: [130.0, 130.0, 79.5, 59.5],
                rot: [[0.0; 4]; 3],
                robust: [1.0, 1.0, 5.0, 5.0],
                flags: [0, terms, param, 0],
            };
            let mut checked = 0;
            for i in [60 * w + 80, 40 * w + 50, 70 * w + 100, 30 * w + 120] {
                p.set_pose(&cur_from_ref);
                let t = pixel_terms(&p, &pyr.photo, &pyr.geo, &pyr.photo, &pyr.geo, i, true);
                let (Some(rp), Some(rg)) = (t.r_photo, t.r_geo) else {
                    continue;
                };
                let _ = (rp, rg);
                for k in 0..6 {
                    // Small steps for the bilinear photometric residual; steps that move the warp
                    // by several pixels for the geometric one, which samples inverse depth at the
                    // nearest pixel (tiny steps would see a flat function).
                    let fd = |p: &mut WarpParams, eps: f64| {
                        let mut d = [0.0; 6];
                        d[k] = eps;
                        p.set_pose(&(Se3::exp(&d) * cur_from_ref));
                        let a =
                            pixel_terms(p, &pyr.photo, &pyr.geo, &pyr.photo, &pyr.geo, i, false);
                        d[k] = -eps;
                        p.set_pose(&(Se3::exp(&d) * cur_from_ref));
                        let b =
                            pixel_terms(p, &pyr.photo, &pyr.geo, &pyr.photo, &pyr.geo, i, false);
                        let e = 2.0 * eps as f32;
                        (
                            (a.r_photo.unwrap() - b.r_photo.unwrap()) / e,
                            (a.r_geo.unwrap() - b.r_geo.unwrap()) / e,
                        )
                    };
                    let (num_p, _) = fd(&mut p, 1e-4);
                    let (_, num_g) = fd(&mut p, 2e-2);
                    let tol_p = 0.03 * t.j_photo.iter().map(|x| x.abs()).fold(0.0, f32::max);
                    let tol_g = 0.1 * t.j_geo.iter().map(|x| x.abs()).fold(0.0, f32::max);
                    assert!(
                        (num_p - t.j_photo[k]).abs() < tol_p,
                        "param {param} photo k={k}: fd {num_p} vs {}",
                        t.j_photo[k]
                    );
                    assert!(
                        (num_g - t.j_geo[k]).abs() < tol_g,
                        "param {param} geo k={k}: fd {num_g} vs {}",
                        t.j_geo[k]
                    );
                }
                checked += 1;
            }
            assert!(checked >= 3);
        }
    }

    #[test]
    fn wgsl_constants_match_the_mirror() {
        let src = crate::gpu::shaders::raw("common.wgsl").unwrap_or_default();
        for (name, v) in [
            ("HUBER_K", HUBER_K),
            ("TUKEY_C", TUKEY_C),
            ("INVALID_GRAD", INVALID_GRAD),
            ("INVALID_RESIDUAL", INVALID_RESIDUAL),
            ("MIN_DEPTH", MIN_DEPTH),
            ("MAX_REL_GRAD", MAX_REL_GRAD),
        ] {
            let line = src
                .lines()
                .find(|l| l.contains(&format!("const {name}:")))
                .unwrap_or_default();
            let value: f32 = line
                .split('=')
                .nth(1)
                .unwrap_or("")
                .trim()
                .trim_end_matches(';')
                .parse()
                .unwrap_or(f32::NAN);
            assert_eq!(value, v, "{name} differs between common.wgsl and kernel.rs");
        }
    }
}
