//! The per-pixel mathematics of the odometry kernels: the CPU mirror of
//! `shaders/pyramid.wgsl` and `shaders/odometry.wgsl`, operation for operation.
//!
//! Buffer layout shared by both backends: per frame, all pyramid levels concatenated, two
//! `vec4<f32>` per pixel:
//! - `photo = (I, dI/du, dI/dv, 0)`, intensity in [0, 255] and its central-difference gradient;
//! - `geo = (rho, drho/du, drho/dv, 0)`, inverse depth in 1/m (0 = invalid) and its gradient,
//!   with [`INVALID_GRAD`] where the gradient cannot be computed.

use bytemuck::{Pod, Zeroable};

use super::config::Terms;

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
/// One reduction partial: the IRLS normal equations summed over a group of pixels (a GPU
/// workgroup or subgroup, or a CPU band of rows), in f32. Same layout as `Partial` in
/// `shaders/odometry.wgsl` (a test compares them); finished in f64 on the CPU.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct Partial {
    /// Upper triangle of `sum w J^T J / sigma^2`, row-major: (0,0), (0,1), .., (0,5), (1,1), ..
    pub h: [f32; 21],
    /// `sum w J^T r / sigma^2`.
    pub g: [f32; 6],
    /// `sum w (r / sigma)^2`.
    pub cost: f32,
    /// Valid photometric residuals.
    pub n_photo: f32,
    /// Valid geometric residuals.
    pub n_geo: f32,
}

/// The f64 accumulator of one [`Partial`] on the CPU backend.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PartialSums {
    /// See [`Partial::h`].
    pub h: [f64; 21],
    /// See [`Partial::g`].
    pub g: [f64; 6],
    /// See [`Partial::cost`].
    pub cost: f64,
    /// See [`Partial::n_photo`].
    pub n_photo: f64,
    /// See [`Partial::n_geo`].
    pub n_geo: f64,
}

impl PartialSums {
    /// Rounded to the f32 partial the kernels exchange.
    pub fn to_partial(self) -> Partial {
        Partial {
            h: self.h.map(|v| v as f32),
            g: self.g.map(|v| v as f32),
            cost: self.cost as f32,
            n_photo: self.n_photo as f32,
            n_geo: self.n_geo as f32,
        }
    }
}

/// Normal-equation partials and the residual sample taken in the same pass
/// (`(partials, [(r_photo, r_geo)])`, see `normal_equations_and_sample` of both backends).
pub type PartialsAndSample = (Vec<Partial>, Vec<[f32; 2]>);

/// Uniform parameters of the warp kernels (`WarpParams` in `odometry.wgsl`, same layout).
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
pub struct WarpParams {
    /// Level width, pixels.
    pub width: u32,
    /// Level height, pixels.
    pub height: u32,
    /// Offset of the level in the concatenated pyramid buffers, pixels.
    pub offset: u32,
    /// Size of the systematic residual sample (0: no sample).
    pub samples: u32,
    /// Focal length x of the level, pixels.
    pub fx: f32,
    /// Focal length y of the level, pixels.
    pub fy: f32,
    /// Principal point x of the level, pixels.
    pub cx: f32,
    /// Principal point y of the level, pixels.
    pub cy: f32,
    /// Rows of the rotation of `cur_from_ref`; `[3]` holds the translation component (m).
    pub rot: [[f32; 4]; 3],
    /// Photometric scale sigma_I, intensity levels.
    pub sigma_photo: f32,
    /// Geometric scale sigma_W (1/m, or m with the depth parametrisation).
    pub sigma_geo: f32,
    /// Student-t degrees of freedom of the photometric residuals.
    pub nu_photo: f32,
    /// Student-t degrees of freedom of the geometric residuals.
    pub nu_geo: f32,
    /// [`super::Estimator`] as `u32`.
    pub estimator: u32,
    /// [`Terms`] as `u32` (bit 0 photometric, bit 1 geometric).
    pub terms: u32,
    /// [`super::GeometricParam`] as `u32`.
    pub geometric: u32,
    /// [`super::GeometricSampling`] as `u32`.
    pub sampling: u32,
    /// Occlusion tolerance of the covisibility test (thesis eq. 4.33, 6.10), in the units of
    /// the geometric residual (1/m with inverse depth, m with depth): a reference point counts
    /// as covisible only where the current frame's value at its nearest pixel differs from the
    /// warped point's by less than this. `0` disables the test (any pixel with depth counts).
    pub occlusion: f32,
    /// Location mu_I of the photometric residuals (thesis eq. 4.26-4.27), intensity levels:
    /// the weights and the normal equations use `r - mu`; the residual sample stays `r`.
    pub mu_photo: f32,
    /// Location mu_W of the geometric residuals, in their units.
    pub mu_geo: f32,
    /// [`super::Linearisation`] as `u32`: 0 the current frame's gradients at the warped point
    /// (left twist of `cur_from_ref`), 1 the reference frame's at the reference pixel (right
    /// twist, geometric residual in the reference frame).
    pub linearisation: u32,
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

    /// Pixels of the level.
    pub fn pixels(&self) -> usize {
        self.width as usize * self.height as usize
    }

    /// Whether the photometric term is used.
    pub fn photometric(&self) -> bool {
        self.terms & Terms::Photometric as u32 != 0
    }

    /// Whether the geometric term is used.
    pub fn geometric_term(&self) -> bool {
        self.terms & Terms::Geometric as u32 != 0
    }
}

/// Uniform parameters of the pyramid kernels (`PyrParams` in `pyramid.wgsl`, same layout).
/// The bilateral-gradient kernels of the covariance pass use the same block
/// ([`PyrParams::filter`]).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, Pod, Zeroable)]
pub struct PyrParams {
    /// Destination level width, pixels.
    pub width: u32,
    /// Destination level height, pixels.
    pub height: u32,
    /// Destination level offset in the pyramid buffers, pixels.
    pub offset: u32,
    /// Source level offset (downsampling), pixels.
    pub src_offset: u32,
    /// Source level width (downsampling), pixels.
    pub src_width: u32,
    /// Source level height (downsampling), pixels.
    pub src_height: u32,
    /// Bilateral filter: `1 / (2 sigma_I^2)`, 1/intensity^2.
    pub inv2_photo: f32,
    /// Bilateral filter: `1 / (2 sigma_rho^2)`, m^2.
    pub inv2_rho: f32,
}

impl PyrParams {
    /// Parameters of the bilateral-gradient kernels for a `w x h` level at `offset` with
    /// photometric range scale `sigma_photo` (intensity levels) and inverse-depth range scale
    /// `sigma_rho` (1/m).
    pub fn filter(w: usize, h: usize, offset: usize, sigma_photo: f64, sigma_rho: f64) -> Self {
        let inv2 = |s: f64| (0.5 / (s * s).max(1e-30)) as f32;
        Self {
            width: w as u32,
            height: h as u32,
            offset: offset as u32,
            inv2_photo: inv2(sigma_photo),
            inv2_rho: inv2(sigma_rho),
            ..Self::default()
        }
    }
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

/// Bilateral filter at (x, y) of one level, over a `(2 BILATERAL_RADIUS + 1)^2` window clamped
/// to the image, with a flat spatial kernel and the Cauchy range kernel
/// `1 / (1 + d^2 / (2 sigma^2))` (no transcendental per tap: the filter runs once per frame on
/// the finest level used): intensity weighted by its difference to the centre, inverse depth
/// by its difference over valid (> 0) neighbours only (0 where the pixel itself has no
/// depth). Returns `(I_filtered, rho_filtered)`. Mirror of `bilateral` in `pyramid.wgsl`.
#[inline]
pub fn bilateral(
    f: &PyrParams,
    photo: &[[f32; 4]],
    geo: &[[f32; 4]],
    x: usize,
    y: usize,
) -> (f32, f32) {
    let (w, h) = (f.width as usize, f.height as usize);
    let c = y * w + x;
    let (ic, rc) = (photo[c][0], geo[c][0]);
    let (mut si, mut wi, mut sr, mut wr) = (0.0f32, 0.0f32, 0.0f32, 0.0f32);
    let r = BILATERAL_RADIUS;
    for v in y.saturating_sub(r)..(y + r + 1).min(h) {
        for u in x.saturating_sub(r)..(x + r + 1).min(w) {
            let k = v * w + u;
            let di = photo[k][0] - ic;
            let a = 1.0 / (1.0 + f.inv2_photo * di * di);
            si += a * photo[k][0];
            wi += a;
            let rk = geo[k][0];
            if rc > 0.0 && rk > 0.0 {
                let dr = rk - rc;
                let b = 1.0 / (1.0 + f.inv2_rho * dr * dr);
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

/// Reference pixel `i` back-projected with its inverse depth and moved into the current
/// camera by `cur_from_ref` (metres); `None` where it has no depth. Mirror of `warp_point`
/// in the WGSL.
#[inline]
pub fn warp_point(p: &WarpParams, ref_geo: &[[f32; 4]], i: usize) -> Option<[f32; 3]> {
    let w = p.width as usize;
    let rho = ref_geo[i][0];
    if rho <= 0.0 {
        return None;
    }
    let (fx, fy, cx, cy) = (p.fx, p.fy, p.cx, p.cy);
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

/// Index of the `k`-th of `count` systematic samples among `n` pixels (the WGSL computes it
/// incrementally as `sample_pixel`, the row loops as `SampleWalk`).
#[cfg(test)]
#[inline]
pub fn sample_index(k: u32, count: u32, n: u32) -> u32 {
    ((u64::from(k) * u64::from(n)) / u64::from(count.max(1))) as u32
}

/// Covisibility test of reference pixel `i`: 0 if it has no depth, 1 if it has depth but
/// warps outside the current image, onto a pixel without depth, or (with
/// [`WarpParams::occlusion`] > 0) onto a pixel whose depth is inconsistent with it (occluded
/// or occluding, eq. 4.33), 2 if it is covisible.
#[inline]
pub fn covisible(p: &WarpParams, ref_geo: &[[f32; 4]], cur_geo: &[[f32; 4]], i: usize) -> u32 {
    let w = p.width as usize;
    let h = p.height as usize;
    let Some(q) = warp_point(p, ref_geo, i) else {
        return 0;
    };
    let (fx, fy, cx, cy) = (p.fx, p.fy, p.cx, p.cy);
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
    let rc = cur_geo[yn as usize * w + xn as usize][0];
    if !(rc > 0.0) {
        return 1;
    }
    if p.occlusion > 0.0 {
        // The geometric residual of the thesis' occlusion condition, in the parametrisation
        // the residuals use: |W_B(p_w) - 1/z| (inverse depth) or |1/W_B(p_w) - z| (depth).
        let r = if p.geometric == 1 {
            1.0 / rc - q[2]
        } else {
            rc - 1.0 / q[2]
        };
        if !(r.abs() < p.occlusion) {
            return 1;
        }
    }
    2
}

#[cfg(test)]
mod tests {
    use super::super::robust::{HUBER_K, TUKEY_C};
    use super::*;

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

    /// `(shader, struct, host fields and offsets, host size)`.
    type Layout = (
        &'static str,
        &'static str,
        Vec<(&'static str, usize)>,
        usize,
    );

    /// The host structs of the odometry kernels, field by field, as `odometry.wgsl` and
    /// `pyramid.wgsl` lay them out.
    fn layouts() -> Vec<Layout> {
        use crate::gpu::host_layout;
        use std::mem::size_of;
        vec![
            (
                "odometry.wgsl",
                "WarpParams",
                host_layout!(WarpParams {
                    width,
                    height,
                    offset,
                    samples,
                    fx,
                    fy,
                    cx,
                    cy,
                    rot0 = rot[0] stride 16,
                    rot1 = rot[1] stride 16,
                    rot2 = rot[2] stride 16,
                    sigma_photo,
                    sigma_geo,
                    nu_photo,
                    nu_geo,
                    estimator,
                    terms,
                    geometric,
                    sampling,
                    occlusion,
                    mu_photo,
                    mu_geo,
                    linearisation,
                }),
                size_of::<WarpParams>(),
            ),
            (
                "odometry.wgsl",
                "Partial",
                host_layout!(Partial {
                    h,
                    g,
                    cost,
                    n_photo,
                    n_geo
                }),
                size_of::<Partial>(),
            ),
            (
                "pyramid.wgsl",
                "PyrParams",
                host_layout!(PyrParams {
                    width,
                    height,
                    offset,
                    src_offset,
                    src_width,
                    src_height,
                    inv2_photo,
                    inv2_rho,
                }),
                size_of::<PyrParams>(),
            ),
        ]
    }

    #[test]
    fn host_structs_match_the_wgsl_layouts() {
        for (shader, name, host, size) in layouts() {
            let src = crate::gpu::shaders::assembled(shader).unwrap_or_default();
            let bad = crate::gpu::layout_mismatches(&src, name, &host, size);
            assert!(bad.is_empty(), "{shader}:\n{}", bad.join("\n"));
        }
    }

    /// The layout check catches a WGSL struct whose fields were reordered: two scalars of
    /// the same type swapped (same offsets, different names), and a scalar moved behind a
    /// `vec4` (different offsets).
    #[test]
    fn the_layout_check_catches_reordered_wgsl_fields() {
        let src = crate::gpu::shaders::assembled("odometry.wgsl").unwrap_or_default();
        let (_, _, host, size) = layouts().remove(0);
        let swapped = src.replacen(
            "    fx: f32,           // level intrinsics, pixels\n    fy: f32,",
            "    fy: f32,\n    fx: f32,",
            1,
        );
        let moved = src.replacen(
            "    sigma_photo: f32,  // robust scales and Student-t degrees of freedom\n",
            "",
            1,
        );
        let moved = moved.replacen(
            "    rot0: vec4<f32>,",
            "    sigma_photo: f32,\n    rot0: vec4<f32>,",
            1,
        );
        for (what, edited) in [("swapped", swapped), ("moved", moved)] {
            assert_ne!(edited, src, "{what}: the edit did not apply");
            let bad = crate::gpu::layout_mismatches(&edited, "WarpParams", &host, size);
            assert!(
                !bad.is_empty(),
                "{what}: the reordered struct passed the check"
            );
            eprintln!("{what}:\n{}", bad.join("\n"));
        }
    }

    /// A 4x4 level at identity: every reference pixel at 2 m lands on itself; the current
    /// frame has depth 2 m except one occluding pixel at 1 m, one pixel without depth, and one
    /// pixel 1 cm behind (well inside 3 sigma_W at the tolerance used).
    fn occlusion_case(geometric: u32, occlusion: f32) -> Vec<u32> {
        let mut p = WarpParams::zeroed();
        p.width = 4;
        p.height = 4;
        p.fx = 4.0;
        p.fy = 4.0;
        p.cx = 1.5;
        p.cy = 1.5;
        p.geometric = geometric;
        p.occlusion = occlusion;
        p.set_pose(&crate::geometry::Se3::IDENTITY);
        let ref_geo = vec![[0.5f32, 0.0, 0.0, 0.0]; 16];
        let mut cur_geo = ref_geo.clone();
        cur_geo[5][0] = 1.0;
        cur_geo[6][0] = 0.0;
        cur_geo[9][0] = 1.0 / 2.01;
        (0..16)
            .map(|i| covisible(&p, &ref_geo, &cur_geo, i))
            .collect()
    }

    #[test]
    fn covisibility_occlusion_test_rejects_inconsistent_depth_only() {
        // Without the test, every pixel landing on depth is covisible.
        let plain = occlusion_case(0, 0.0);
        assert_eq!(plain.iter().filter(|&&c| c == 2).count(), 15);
        assert_eq!(plain[6], 1);
        // Inverse depth: |1 - 0.5| = 0.5 1/m is far outside 3 * 0.01; 1/2.01 - 0.5 is inside.
        let id = occlusion_case(0, 0.03);
        assert_eq!(id[5], 1, "the occluding pixel must not be covisible");
        assert_eq!(id[6], 1);
        assert_eq!(id[9], 2, "a pixel within the tolerance stays covisible");
        assert_eq!(id.iter().filter(|&&c| c == 2).count(), 14);
        // Depth: |1 m - 2 m| is outside 3 * 0.02 m, |2.01 - 2| inside.
        let d = occlusion_case(1, 0.06);
        assert_eq!((d[5], d[9]), (1, 2));
        // A tolerance below the 1 cm offset rejects that pixel too (the test can fail).
        let tight = occlusion_case(1, 0.005);
        assert_eq!(tight[9], 1);
    }
}
