//! Patches for data association: ZNCC correlation and the catadioptric patch warping of the
//! thesis (sec. 2.5, eq. 2.63-2.70).
//!
//! At initialisation a big square patch (half size `B`) is sampled around the feature. In
//! plain mode ([`PatchMode::Plain`]) the correlation patch is the central `(2h+1)^2` part of
//! it, unchanged. The warped modes resample it for the current prediction: a pixel offset `o`
//! of the correlation patch (current image) maps to
//! `(o . u_now) / k_r * u_init + (o . t_now) / k_t * t_init` in the big patch, sampled
//! bilinearly, where `u` is the unit radial direction of the feature's pixel from the
//! principal point and `t` its tangential direction (`u` turned by +90 degrees). With
//! `k_r = k_t = k` this is the rotation by the change of polar angle
//! `delta_alpha = alpha_now - alpha_init` followed by the scaling `1 / k` of eq. 2.68-2.70 (a
//! catadioptric image turns with the azimuth of the ray). The modes differ in the scales:
//!
//! - [`PatchMode::Warped`] (local magnification): isotropic
//!   `k = (mu(theta_now) / mu(theta_init)) * (d_init / d_now)`, `mu(theta)` the geometric mean
//!   of the unified model's radial `dr/dtheta = gamma (1 + xi cos theta) / (cos theta + xi)^2`
//!   and tangential `r / sin theta = gamma / (cos theta + xi)` magnifications at polar angle
//!   `theta` from the optical axis, and `d` the distance from the camera to the feature (the
//!   ratio from the inverse-depth estimate, whatever its uncertainty).
//! - [`PatchMode::Thesis`] (sec. 2.5.2-2.5.3, eq. 2.63-2.67): isotropic `k = l_now / l_init`,
//!   the ratio of the image lengths of one small scene segment. At initialisation the segment
//!   runs from the feature to the point whose image is `r_im-`, the pixel `h` (the correlation
//!   patch's half size) from the feature towards the principal point; it subtends the angle
//!   `delta_init` at the camera, and `l_init = h`. Now the same segment subtends
//!   `delta_now = atan(tan(delta_init) d_init / d_now)`, and `l_now` is the distance between the
//!   projections of the feature's current ray and of that ray turned by `delta_now` towards
//!   the optical axis, through the unified model itself: the mirror's non-linearity across the
//!   patch enters exactly, where the magnification is a derivative at one point. The depth
//!   ratio `d_init / d_now` is used only once the landmark's depth has converged
//!   (`sigma_rho / rho` at most [`crate::mono::MonoConfig::depth_converged_ratio`]); before,
//!   it is 1, so a depth that is still a guess cannot shrink or blow up the patch.
//! - [`PatchMode::Anisotropic`]: as [`PatchMode::Thesis`] along the radial direction
//!   (`k_r`), and along the tangential direction the same construction with the ray turned by
//!   `delta` about the optical axis's side (perpendicular to the plane of the ray and the
//!   axis), `k_t = l_t,now / l_t,init`: the unified model stretches radial and tangential
//!   lengths differently (their ratio is `(1 + xi cos theta) / (cos theta + xi)`, up to 1.2 at
//!   the rim of the default mirror), which one isotropic factor cannot follow. This departs
//!   from the thesis, which uses one scale.
//!
//! - [`PatchMode::Projective`] (not in the thesis): no scales. Each pixel `uv + o` of the
//!   correlation patch is lifted to its ray in the current camera, carried into the camera
//!   that took the big patch by the predicted relative pose ([`ViewChange`]), met with the
//!   plane through the feature perpendicular to its initial ray, and projected into the
//!   initial image; the big patch is read at that pixel's offset from where `uv` lands.
//!   The change of polar angle of the other modes is the image rotation of a turn about the
//!   mirror's axis only; when the axis is not vertical (a head-worn camera looking ahead) a
//!   turn of the head rotates patches differently, and only the pose-based map follows it.
//!   Until the landmark's depth has converged (as for [`PatchMode::Thesis`]) the point is
//!   taken at infinity, so only the rotation warps the patch.
//!
//! Every scale is limited to `[1 / k_lim, k_lim]` (eq. 2.66-2.67). The warp reads the big
//! patch at offsets up to `sqrt(2) h / k` from its centre, so a shrinking scale needs
//! `k >= sqrt(2) h / B`: `k_lim <= B / (sqrt(2) h)` keeps every read inside the big patch
//! (2.1 for the defaults `B = 15`, `h = 5`; the default `k_lim` is 2). Where a read would still
//! fall outside, it is clamped to the big patch's border.
//!
//! Departures from the thesis: the segment of [`PatchMode::Thesis`] is taken perpendicular to
//! the ray (its orientation in the scene is unknown), and [`PatchMode::Anisotropic`] is not in
//! the thesis.

use glam::{DVec2, DVec3};

use crate::camera::UnifiedCamera;
use crate::image::ImageF32;

/// How correlation patches are built.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum PatchMode {
    /// The patch as seen at initialisation.
    #[default]
    Plain,
    /// Rotated by the change of polar angle and scaled by the ratio of the unified model's
    /// local magnifications times the estimated depth ratio (see the module docs).
    Warped,
    /// Rotated and scaled by the ratio of projected image lengths from `r_im-` (thesis
    /// eq. 2.63-2.67), with the depth ratio only for converged depths (see the module docs).
    Thesis,
    /// As [`PatchMode::Thesis`], with separate radial and tangential scales.
    Anisotropic,
    /// Every pixel mapped through the predicted relative camera pose onto the plane through
    /// the feature perpendicular to its initial ray (see the module docs; not in the thesis).
    Projective,
}

impl PatchMode {
    /// Every mode, in the order of the comparisons.
    pub const ALL: [PatchMode; 5] = [
        PatchMode::Plain,
        PatchMode::Warped,
        PatchMode::Thesis,
        PatchMode::Anisotropic,
        PatchMode::Projective,
    ];

    /// The mode's name as in configuration files.
    pub fn name(self) -> &'static str {
        match self {
            PatchMode::Plain => "plain",
            PatchMode::Warped => "warped",
            PatchMode::Thesis => "thesis",
            PatchMode::Anisotropic => "anisotropic",
            PatchMode::Projective => "projective",
        }
    }
}

/// Bilinear sample at `(x, y)` (pixel centres at integers); `None` outside the image.
#[inline]
pub fn sample_bilinear(img: &ImageF32, x: f64, y: f64) -> Option<f32> {
    if !(x >= 0.0 && y >= 0.0) {
        return None;
    }
    let (x0, y0) = (x.floor() as usize, y.floor() as usize);
    if x0 + 1 >= img.width || y0 + 1 >= img.height {
        return None;
    }
    let (fx, fy) = ((x - x0 as f64) as f32, (y - y0 as f64) as f32);
    let i = y0 * img.width + x0;
    let d = &img.data;
    let top = d[i] * (1.0 - fx) + d[i + 1] * fx;
    let bottom = d[i + img.width] * (1.0 - fx) + d[i + img.width + 1] * fx;
    Some(top * (1.0 - fy) + bottom * fy)
}

#[cfg(test)]
/// Zero-mean normalised cross-correlation of two equally long patches, in `[-1, 1]`;
/// `0` when either is flat.
pub fn zncc(a: &[f32], b: &[f32]) -> f64 {
    let n = a.len().min(b.len());
    if n == 0 {
        return 0.0;
    }
    let (mut sa, mut sb, mut saa, mut sbb, mut sab) = (0.0f64, 0.0, 0.0, 0.0, 0.0);
    for (x, y) in a.iter().zip(b) {
        let (x, y) = (f64::from(*x), f64::from(*y));
        sa += x;
        sb += y;
        saa += x * x;
        sbb += y * y;
        sab += x * y;
    }
    let nf = n as f64;
    let va = saa - sa * sa / nf;
    let vb = sbb - sb * sb / nf;
    if va <= 1e-9 * nf || vb <= 1e-9 * nf {
        return 0.0;
    }
    (sab - sa * sb / nf) / (va * vb).sqrt()
}

/// Sub-pixel offset `(dx, dy)` of the correlation peak at `(bx, by)` (score `best`) in a
/// row-major score window `bw` wide: a parabola through the peak and its two neighbours per
/// axis, limited to half a pixel; 0 on the window's border or where a neighbour is not
/// finite or the scores do not curve down.
pub(crate) fn refine_peak(
    scores: &[f64],
    bw: usize,
    bx: usize,
    by: usize,
    best: f64,
) -> (f64, f64) {
    let bh = scores.len() / bw;
    let at = |x: usize, y: usize| scores[y * bw + x];
    let refine = |m: f64, c: f64, p: f64| {
        let den = m - 2.0 * c + p;
        if m.is_finite() && p.is_finite() && den < -1e-12 {
            (0.5 * (m - p) / den).clamp(-0.5, 0.5)
        } else {
            0.0
        }
    };
    let dx = if bx > 0 && bx + 1 < bw {
        refine(at(bx - 1, by), best, at(bx + 1, by))
    } else {
        0.0
    };
    let dy = if by > 0 && by + 1 < bh {
        refine(at(bx, by - 1), best, at(bx, by + 1))
    } else {
        0.0
    };
    (dx, dy)
}

/// A template normalised once (zero mean, unit norm) for repeated correlation.
#[derive(Clone, Debug)]
pub struct Template {
    /// Half size, pixels.
    pub half: usize,
    values: Vec<f64>,
}

impl Template {
    /// Normalises a `(2 half + 1)^2` patch; `None` when it is (nearly) flat.
    pub fn new(patch: &[f32], half: usize) -> Option<Template> {
        let n = patch.len() as f64;
        let mean = patch.iter().map(|v| f64::from(*v)).sum::<f64>() / n;
        let values: Vec<f64> = patch.iter().map(|v| f64::from(*v) - mean).collect();
        let norm = values.iter().map(|v| v * v).sum::<f64>().sqrt();
        if norm < 1e-3 * n.sqrt() {
            return None;
        }
        Some(Template {
            half,
            values: values.into_iter().map(|v| v / norm).collect(),
        })
    }

    /// ZNCC against the image patch centred on integer pixel `(x, y)`; `None` when the patch
    /// leaves the image.
    pub fn correlate_at(&self, img: &ImageF32, x: i64, y: i64) -> Option<f64> {
        let h = self.half as i64;
        if x - h < 0 || y - h < 0 || x + h >= img.width as i64 || y + h >= img.height as i64 {
            return None;
        }
        // The template has zero mean, so the image mean drops out of the cross term.
        let top = (y - h) as usize * img.width + (x - h) as usize;
        let mut out = [0.0f64];
        zncc_row_body(&img.data, img.width, top, &self.values, self.half, &mut out);
        Some(out[0])
    }

    /// ZNCC at every integer pixel of the window `[x0, x1] x [y0, y1]` (inclusive), row-major
    /// with `x1 - x0 + 1` columns; `NEG_INFINITY` where the patch leaves the image.
    ///
    /// Equal, bit for bit, to [`Template::correlate_at`] at each pixel (the same sums in the
    /// same order), but computed a window row at a time with the template sweeping whole
    /// rows, which the compiler vectorises.
    pub fn correlate_window(&self, img: &ImageF32, x0: i64, y0: i64, x1: i64, y1: i64) -> Vec<f64> {
        let (bw, bh) = ((x1 - x0 + 1).max(0) as usize, (y1 - y0 + 1).max(0) as usize);
        let mut out = vec![f64::NEG_INFINITY; bw * bh];
        let h = self.half as i64;
        let (w, hh) = (img.width as i64, img.height as i64);
        let (vx0, vx1) = (x0.max(h), x1.min(w - 1 - h));
        let (vy0, vy1) = (y0.max(h), y1.min(hh - 1 - h));
        if vx0 > vx1 || vy0 > vy1 {
            return out;
        }
        let vw = (vx1 - vx0 + 1) as usize;
        for y in vy0..=vy1 {
            let top = (y - h) as usize * img.width + (vx0 - h) as usize;
            let base = (y - y0) as usize * bw + (vx0 - x0) as usize;
            zncc_row(
                &img.data,
                img.width,
                top,
                &self.values,
                self.half,
                &mut out[base..base + vw],
            );
        }
        out
    }
}

/// Positions per step of [`zncc_row_avx2`]: their three sums stay in registers.
const LANES: usize = 8;

/// ZNCC of the zero-mean unit-norm `values` (side `2 half + 1`) against the image patches
/// whose top-left corners are `data[top + k]`, `k < out.len()`, in an image `width` wide.
fn zncc_row(data: &[f32], width: usize, top: usize, values: &[f64], half: usize, out: &mut [f64]) {
    #[cfg(target_arch = "x86_64")]
    {
        if std::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU supports the feature enabled on `zncc_row_avx2`.
            unsafe { zncc_row_avx2(data, width, top, values, half, out) };
            return;
        }
    }
    zncc_row_body(data, width, top, values, half, out);
}

/// AVX2 copy of [`zncc_row_body`]: [`LANES`] positions per step; a tail shorter than that
/// is covered by one more step ending at the last position (lanes are independent, so the
/// positions computed twice get the same values).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn zncc_row_avx2(
    data: &[f32],
    width: usize,
    top: usize,
    values: &[f64],
    half: usize,
    out: &mut [f64],
) {
    let len = out.len();
    if len < LANES {
        zncc_row_body(data, width, top, values, half, out);
        return;
    }
    let mut k0 = 0;
    loop {
        let start = k0.min(len - LANES);
        let mut block = [0.0f64; LANES];
        if !zncc_block_avx2(data, width, top + start, values, half, &mut block) {
            zncc_row_body(data, width, top + start, values, half, &mut out[start..]);
            return;
        }
        out[start..start + LANES].copy_from_slice(&block);
        k0 += LANES;
        if start + LANES == len {
            return;
        }
    }
}

/// ZNCC at the [`LANES`] positions whose patches start at `data[top..top + LANES]`, in
/// four-lane registers with separate multiplies and adds (no FMA), so that every sum rounds
/// as in [`zncc_row_body`]. False (and nothing written) when a patch would leave `data`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn zncc_block_avx2(
    data: &[f32],
    width: usize,
    top: usize,
    values: &[f64],
    half: usize,
    out: &mut [f64; LANES],
) -> bool {
    use std::arch::x86_64::{
        _mm256_add_pd, _mm256_castps256_ps128, _mm256_cvtps_pd, _mm256_extractf128_ps,
        _mm256_loadu_ps, _mm256_mul_pd, _mm256_set1_pd, _mm256_setzero_pd, _mm256_storeu_pd,
    };
    let side = 2 * half + 1;
    if values.len() < side * side || top + (side - 1) * (width + 1) + LANES > data.len() {
        return false;
    }
    let z = _mm256_setzero_pd();
    let (mut s0, mut s1, mut q0, mut q1, mut t0, mut t1) = (z, z, z, z, z, z);
    for j in 0..side {
        let row = top + j * width;
        for (i, t) in values[j * side..(j + 1) * side].iter().enumerate() {
            // SAFETY: row + i + LANES <= data.len() by the check above.
            let v = unsafe { _mm256_loadu_ps(data.as_ptr().add(row + i)) };
            let lo = _mm256_cvtps_pd(_mm256_castps256_ps128(v));
            let hi = _mm256_cvtps_pd(_mm256_extractf128_ps::<1>(v));
            let tv = _mm256_set1_pd(*t);
            s0 = _mm256_add_pd(s0, lo);
            s1 = _mm256_add_pd(s1, hi);
            q0 = _mm256_add_pd(q0, _mm256_mul_pd(lo, lo));
            q1 = _mm256_add_pd(q1, _mm256_mul_pd(hi, hi));
            t0 = _mm256_add_pd(t0, _mm256_mul_pd(lo, tv));
            t1 = _mm256_add_pd(t1, _mm256_mul_pd(hi, tv));
        }
    }
    let (mut s, mut ss, mut st) = ([0.0f64; LANES], [0.0f64; LANES], [0.0f64; LANES]);
    // SAFETY: each array holds LANES = 8 f64: two stores of 4.
    unsafe {
        _mm256_storeu_pd(s.as_mut_ptr(), s0);
        _mm256_storeu_pd(s.as_mut_ptr().add(4), s1);
        _mm256_storeu_pd(ss.as_mut_ptr(), q0);
        _mm256_storeu_pd(ss.as_mut_ptr().add(4), q1);
        _mm256_storeu_pd(st.as_mut_ptr(), t0);
        _mm256_storeu_pd(st.as_mut_ptr().add(4), t1);
    }
    let n = (side * side) as f64;
    for l in 0..LANES {
        out[l] = zncc_score(s[l], ss[l], st[l], n);
    }
    true
}

/// ZNCC from the sums of a patch of `n` pixels against a zero-mean unit-norm template.
#[inline(always)]
fn zncc_score(s: f64, ss: f64, st: f64, n: f64) -> f64 {
    let var = ss - s * s / n;
    if var <= 1e-9 * n {
        0.0
    } else {
        st / var.sqrt()
    }
}

/// ZNCC of the zero-mean unit-norm `values` at consecutive positions, one position at a
/// time (the reference for [`zncc_row_avx2`] and [`Template::correlate_at`]).
fn zncc_row_body(
    data: &[f32],
    width: usize,
    top: usize,
    values: &[f64],
    half: usize,
    out: &mut [f64],
) {
    let side = 2 * half + 1;
    let n = (side * side) as f64;
    for (k, o) in out.iter_mut().enumerate() {
        let (mut s, mut ss, mut st) = (0.0f64, 0.0f64, 0.0f64);
        for j in 0..side {
            let row = top + j * width + k;
            for (p, t) in data[row..row + side]
                .iter()
                .zip(&values[j * side..(j + 1) * side])
            {
                let p = f64::from(*p);
                s += p;
                ss += p * p;
                st += p * t;
            }
        }
        *o = zncc_score(s, ss, st, n);
    }
}

/// The big patch kept from a feature's initialisation.
#[derive(Clone, Debug)]
pub struct FeaturePatch {
    /// Half size of the big patch, pixels.
    pub big_half: usize,
    /// The big patch, row-major `(2 big_half + 1)^2`, sampled around the initial pixel.
    pub big: Vec<f32>,
    /// Polar angle of the initial pixel around the principal point, radians.
    pub alpha_init: f64,
    /// Magnification `mu` of the camera model at the initial pixel, pixels per radian.
    pub mu_init: f64,
    /// Unit ray of the initial pixel, camera frame at initialisation.
    pub ray_init: DVec3,
    /// Angle subtended at the camera by the segment from the feature to the point imaged at
    /// `r_im-` (the correlation patch's half size towards the principal point), radians.
    pub delta_init: f64,
    /// Radial image length of that segment at initialisation, pixels (the half size `h`).
    pub radial_init: f64,
    /// Tangential image length of a segment subtending `delta_init` perpendicular to the
    /// plane of the ray and the optical axis, at initialisation, pixels.
    pub tangential_init: f64,
    /// The plain correlation template (centre of the big patch); `None` if flat.
    pub plain: Option<Template>,
}

/// The scales and rotation of one warp (see the module docs).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct WarpScales {
    /// Radial scale `k_r` (current image length over initial), after the `k_lim` limit.
    pub radial: f64,
    /// Tangential scale `k_t`, after the `k_lim` limit.
    pub tangential: f64,
    /// Change of polar angle around the principal point since initialisation, radians.
    pub delta_alpha: f64,
}

/// Polar angle of a pixel around the principal point, radians.
pub fn polar_angle(camera: &UnifiedCamera, uv: DVec2) -> f64 {
    (uv.y - camera.cy).atan2(uv.x - camera.cx)
}

/// Unit radial direction of pixel `uv` from the principal point (`+x` at the point itself).
fn radial_direction(camera: &UnifiedCamera, uv: DVec2) -> DVec2 {
    let d = uv - DVec2::new(camera.cx, camera.cy);
    let n = d.length();
    if n > 1e-9 {
        d / n
    } else {
        DVec2::X
    }
}

/// The unified model's isotropic local magnification at pixel `uv` (pixels per radian of
/// viewing angle), see the module docs; `None` without a pre-image.
pub fn magnification(camera: &UnifiedCamera, uv: DVec2) -> Option<f64> {
    let s = camera.unproject(uv)?;
    let c = s.z.clamp(-1.0, 1.0);
    let w = c + camera.xi;
    if w <= 1e-9 {
        return None;
    }
    let radial = camera.gamma * (1.0 + camera.xi * c) / (w * w);
    let tangential = camera.gamma / w;
    Some((radial * tangential).max(0.0).sqrt())
}

/// The unit vectors at unit ray `s` (camera frame) along which its polar angle from the
/// optical axis grows (`e_r`) and around the axis (`e_t = z x s`, normalised); on the axis,
/// `e_t = +y`.
fn ray_frame(s: DVec3) -> (DVec3, DVec3) {
    let t = DVec3::new(-s.y, s.x, 0.0);
    let n = t.length();
    let e_t = if n > 1e-12 { t / n } else { DVec3::Y };
    (e_t.cross(s), e_t)
}

/// Image lengths (pixels) of the segments that subtend `delta` radians at unit ray `s`:
/// towards the optical axis (radial, the side of `r_im-`) and around it (tangential), each
/// the distance between the projections of `s` and of `s` turned by `delta`; `None` when a
/// ray has no image.
pub fn projected_lengths(camera: &UnifiedCamera, s: DVec3, delta: f64) -> Option<(f64, f64)> {
    let (e_r, e_t) = ray_frame(s);
    let (sd, cd) = delta.sin_cos();
    let centre = camera.project(s)?;
    let inward = camera.project(s * cd - e_r * sd)?;
    let around = camera.project(s * cd + e_t * sd)?;
    Some(((inward - centre).length(), (around - centre).length()))
}

/// The angle subtended now by a segment that subtended `delta_init` at distance `d_init`,
/// seen from distance `d_init / distance_ratio` (the segment perpendicular to the ray).
fn subtended(delta_init: f64, distance_ratio: f64) -> f64 {
    (delta_init.tan() * distance_ratio).atan()
}

impl FeaturePatch {
    /// Samples the big patch around `uv` and the geometry of the warps for a correlation
    /// patch of half size `half`; `None` when it does not fit in the image or the camera has
    /// no pre-image there.
    pub fn new(
        img: &ImageF32,
        camera: &UnifiedCamera,
        uv: DVec2,
        big_half: usize,
        half: usize,
    ) -> Option<FeaturePatch> {
        let side = 2 * big_half + 1;
        let mut big = Vec::with_capacity(side * side);
        for j in 0..side {
            for i in 0..side {
                let x = uv.x + i as f64 - big_half as f64;
                let y = uv.y + j as f64 - big_half as f64;
                big.push(sample_bilinear(img, x, y)?);
            }
        }
        let small = 2 * half + 1;
        let off = big_half - half;
        let mut centre = Vec::with_capacity(small * small);
        for j in 0..small {
            centre.extend_from_slice(&big[(off + j) * side + off..(off + j) * side + off + small]);
        }
        let ray_init = camera.unproject(uv)?;
        // r_im-: the patch's half size towards the principal point.
        let r_im_minus = uv - radial_direction(camera, uv) * half.max(1) as f64;
        let delta_init = ray_init.angle_between(camera.unproject(r_im_minus)?);
        let (radial_init, tangential_init) = projected_lengths(camera, ray_init, delta_init)?;
        if !(delta_init > 0.0 && radial_init > 1e-9 && tangential_init > 1e-9) {
            return None;
        }
        Some(FeaturePatch {
            big_half,
            big,
            alpha_init: polar_angle(camera, uv),
            mu_init: magnification(camera, uv)?,
            ray_init,
            delta_init,
            radial_init,
            tangential_init,
            plain: Template::new(&centre, half),
        })
    }

    /// The scales of `mode` for the feature predicted at `uv` with distance ratio
    /// `d_init / d_now` (pass 1 where the depth is not to be used), before the `k_lim` limit:
    /// `(k_r, k_t)`; `(1, 1)` for [`PatchMode::Plain`]. `None` when a ray has no image.
    pub fn raw_scales(
        &self,
        camera: &UnifiedCamera,
        uv: DVec2,
        mode: PatchMode,
        distance_ratio: f64,
    ) -> Option<(f64, f64)> {
        match mode {
            PatchMode::Plain | PatchMode::Projective => Some((1.0, 1.0)),
            PatchMode::Warped => {
                let k = magnification(camera, uv)? / self.mu_init * distance_ratio;
                Some((k, k))
            }
            PatchMode::Thesis | PatchMode::Anisotropic => {
                let s = camera.unproject(uv)?;
                let delta = subtended(self.delta_init, distance_ratio);
                let (radial, tangential) = projected_lengths(camera, s, delta)?;
                let k_r = radial / self.radial_init;
                if mode == PatchMode::Thesis {
                    Some((k_r, k_r))
                } else {
                    Some((k_r, tangential / self.tangential_init))
                }
            }
        }
    }

    /// The correlation template of `mode` for a feature predicted at `uv` with distance ratio
    /// `d_init / d_now` (1 where the depth is not to be used), scales limited to
    /// `[1 / k_lim, k_lim]`; `None` when flat or when a ray has no image.
    /// [`PatchMode::Projective`] needs the relative pose: here it gives the plain template
    /// (use [`FeaturePatch::template_projective`]).
    pub fn template(
        &self,
        camera: &UnifiedCamera,
        uv: DVec2,
        mode: PatchMode,
        distance_ratio: f64,
        k_lim: f64,
        half: usize,
    ) -> Option<(Template, WarpScales)> {
        if matches!(mode, PatchMode::Plain | PatchMode::Projective) {
            let scales = WarpScales {
                radial: 1.0,
                tangential: 1.0,
                delta_alpha: 0.0,
            };
            return self.plain.clone().map(|t| (t, scales));
        }
        let (k_r, k_t) = self.raw_scales(camera, uv, mode, distance_ratio)?;
        let lim = |k: f64| k.clamp(1.0 / k_lim, k_lim);
        let (k_r, k_t) = (lim(k_r), lim(k_t));
        let u_now = radial_direction(camera, uv);
        let t_now = u_now.perp();
        let u_init = DVec2::from_angle(self.alpha_init);
        let t_init = u_init.perp();
        let small = 2 * half + 1;
        let mut out = Vec::with_capacity(small * small);
        for j in 0..small {
            for i in 0..small {
                let o = DVec2::new(i as f64 - half as f64, j as f64 - half as f64);
                let p = u_init * (o.dot(u_now) / k_r) + t_init * (o.dot(t_now) / k_t);
                out.push(self.sample_big(p));
            }
        }
        let scales = WarpScales {
            radial: k_r,
            tangential: k_t,
            delta_alpha: polar_angle(camera, uv) - self.alpha_init,
        };
        Template::new(&out, half).map(|t| (t, scales))
    }

    /// The big patch at offset `p` (pixels) from its centre, bilinear, reads clamped to it.
    fn sample_big(&self, p: DVec2) -> f32 {
        let side = 2 * self.big_half + 1;
        let b = self.big_half as f64;
        let x = (p.x + b).clamp(0.0, side as f64 - 1.001);
        let y = (p.y + b).clamp(0.0, side as f64 - 1.001);
        let (x0, y0) = (x.floor() as usize, y.floor() as usize);
        let (fx, fy) = ((x - x0 as f64) as f32, (y - y0 as f64) as f32);
        let at = |xx: usize, yy: usize| self.big[yy * side + xx];
        let top = at(x0, y0) * (1.0 - fx) + at(x0 + 1, y0) * fx;
        let bot = at(x0, y0 + 1) * (1.0 - fx) + at(x0 + 1, y0 + 1) * fx;
        top * (1.0 - fy) + bot * fy
    }

    /// The [`PatchMode::Projective`] template for a feature predicted at `uv`: each pixel
    /// `uv + o` is lifted to its ray in the current camera, carried into the initial camera
    /// by `view`, met with the plane through the feature perpendicular to its initial ray
    /// (or, without a converged depth, taken at infinity) and projected into the initial
    /// image; the big patch is read at that pixel's offset from where `uv` itself lands.
    /// `None` when flat or when a ray has no image.
    pub fn template_projective(
        &self,
        camera: &UnifiedCamera,
        uv: DVec2,
        view: &ViewChange,
        half: usize,
    ) -> Option<Template> {
        let to_init = |q: DVec2| -> Option<DVec2> {
            let r = view.init_from_now * camera.unproject(q)?;
            let x = match view.point_in_init {
                Some(p) => {
                    let n = p.normalize_or_zero();
                    let den = n.dot(r);
                    if den.abs() < 1e-9 {
                        return None;
                    }
                    let t = n.dot(p - view.centre_now_in_init) / den;
                    if !(t > 0.0) {
                        return None;
                    }
                    view.centre_now_in_init + r * t
                }
                None => r,
            };
            camera.project(x)
        };
        let centre = to_init(uv)?;
        let small = 2 * half + 1;
        let mut out = Vec::with_capacity(small * small);
        for j in 0..small {
            for i in 0..small {
                let o = DVec2::new(i as f64 - half as f64, j as f64 - half as f64);
                out.push(self.sample_big(to_init(uv + o)? - centre));
            }
        }
        Template::new(&out, half)
    }
}

/// The relative geometry of a [`PatchMode::Projective`] warp, in the initial camera's frame
/// (the camera that took the big patch).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ViewChange {
    /// Rotation `init_from_now`: directions in the current camera frame into the initial one.
    pub init_from_now: glam::DQuat,
    /// The current camera centre in the initial camera frame (the map's length unit).
    pub centre_now_in_init: DVec3,
    /// The feature's point in the initial camera frame; `None` while its depth has not
    /// converged (the warp then treats it as at infinity: rotation only).
    pub point_in_init: Option<DVec3>,
}

#[cfg(test)]
mod tests {
    use super::*;

    fn textured(w: usize, h: usize) -> ImageF32 {
        let mut img = ImageF32::filled(w, h, 0.0);
        for y in 0..h {
            for x in 0..w {
                let (xf, yf) = (x as f32, y as f32);
                img.data[y * w + x] = 128.0
                    + 60.0 * (0.31 * xf + 0.05 * yf).sin()
                    + 40.0 * (0.17 * yf - 0.11 * xf).cos()
                    + 20.0 * (0.023 * xf * yf).sin();
            }
        }
        img
    }

    #[test]
    fn window_correlation_equals_pointwise_correlation_bit_for_bit() {
        // Noisy non-integer intensities, windows inside, across every border and wider than
        // one AVX2 step with tails of every length.
        let (w, h) = (53, 41);
        let mut img = textured(w, h);
        let mut state = 12345u32;
        for v in &mut img.data {
            state = state.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            *v += (state >> 8) as f32 / (1u32 << 24) as f32 * 7.3;
        }
        for half in [1usize, 2, 5] {
            let side = 2 * half + 1;
            let patch: Vec<f32> = (0..side * side)
                .map(|k| img.data[(10 + k / side) * w + 7 + k % side])
                .collect();
            let t = Template::new(&patch, half).unwrap();
            for &(x0, y0, x1, y1) in &[
                (-4i64, -3i64, 20i64, 9i64),
                (10, 10, 10, 10),
                (3, 5, 19, 6),
                (30, 28, 60, 50),
                (0, 0, 52, 40),
                (5, 7, 5 + 8, 8),
                (6, 2, 6 + 22, 30),
            ] {
                let got = t.correlate_window(&img, x0, y0, x1, y1);
                let bw = (x1 - x0 + 1) as usize;
                for (k, g) in got.iter().enumerate() {
                    let (x, y) = (x0 + (k % bw) as i64, y0 + (k / bw) as i64);
                    let want = t.correlate_at(&img, x, y).unwrap_or(f64::NEG_INFINITY);
                    assert_eq!(g.to_bits(), want.to_bits(), "half {half} at ({x}, {y})");
                }
            }
        }
    }

    #[test]
    fn zncc_is_invariant_to_gain_and_offset() {
        let a = [1.0f32, 5.0, 3.0, 8.0, 2.0];
        let b: Vec<f32> = a.iter().map(|v| 2.5 * v + 10.0).collect();
        assert!((zncc(&a, &b) - 1.0).abs() < 1e-12);
        let c: Vec<f32> = a.iter().map(|v| -v).collect();
        assert!((zncc(&a, &c) + 1.0).abs() < 1e-12);
        assert_eq!(zncc(&a, &[3.0; 5]), 0.0);
        let t = Template::new(&a, 0).unwrap();
        let _ = t;
    }

    #[test]
    fn template_correlation_peaks_at_the_source() {
        let img = textured(80, 60);
        let cam = UnifiedCamera::new(0.0, 100.0, 39.5, 29.5, 80, 60);
        let fp = FeaturePatch::new(&img, &cam, DVec2::new(40.0, 30.0), 10, 4).unwrap();
        let t = fp.plain.clone().unwrap();
        let at = t.correlate_at(&img, 40, 30).unwrap();
        assert!((at - 1.0).abs() < 1e-9, "{at}");
        assert!(t.correlate_at(&img, 43, 30).unwrap() < 0.99);
        assert!(t.correlate_at(&img, 2, 2).is_none());
        // Identity warp (same place, same distance) reproduces the plain template.
        for mode in PatchMode::ALL {
            let (w, k) = fp
                .template(&cam, DVec2::new(40.0, 30.0), mode, 1.0, 2.0, 4)
                .unwrap();
            // The magnification ratio is exact; the projected lengths of the other scale
            // rules go through trigonometry and carry its rounding.
            let tol = if matches!(mode, PatchMode::Plain | PatchMode::Warped) {
                1e-12
            } else {
                1e-9
            };
            assert!(
                (k.radial - 1.0).abs() < tol
                    && (k.tangential - 1.0).abs() < tol
                    && k.delta_alpha.abs() < 1e-12,
                "{mode:?}: {k:?}"
            );
            assert!((w.correlate_at(&img, 40, 30).unwrap() - 1.0).abs() < 1e-6);
        }
    }

    /// `img` (square) turned by +90 degrees about its centre: `rot(x, y) = img(y, n - 1 - x)`
    /// (y down).
    fn turned_90(img: &ImageF32) -> ImageF32 {
        let n = img.width;
        let mut rot = ImageF32::filled(n, n, 0.0);
        for y in 0..n {
            for x in 0..n {
                rot.data[y * n + x] = img.at(y, n - 1 - x);
            }
        }
        rot
    }

    #[test]
    fn warp_undoes_a_rotation_and_k_is_limited() {
        // Rotate the image by 90 degrees about the principal point: a feature moves from
        // polar angle 0 to pi/2 and its patch turns by pi/2.
        let n = 81;
        let img = textured(n, n);
        let rot = turned_90(&img);
        let cam = UnifiedCamera::new(0.9, 60.0, 40.0, 40.0, n as u32, n as u32);
        let src = DVec2::new(60.0, 40.0);
        let dst = DVec2::new(40.0, 60.0);
        assert!((rot.at(40, 60) - img.at(60, 40)).abs() < 1e-6);
        let fp = FeaturePatch::new(&img, &cam, src, 10, 4).unwrap();
        let plain = fp
            .plain
            .clone()
            .unwrap()
            .correlate_at(&rot, 40, 60)
            .unwrap();
        assert!(plain < 0.8, "plain {plain}");
        for mode in [PatchMode::Warped, PatchMode::Thesis, PatchMode::Anisotropic] {
            let (warped, k) = fp.template(&cam, dst, mode, 1.0, 2.0, 4).unwrap();
            let warped = warped.correlate_at(&rot, 40, 60).unwrap();
            assert!((k.delta_alpha - std::f64::consts::FRAC_PI_2).abs() < 1e-9);
            assert!(
                (k.radial - 1.0).abs() < 1e-9 && (k.tangential - 1.0).abs() < 1e-9,
                "same radius, same scale: {k:?}"
            );
            assert!(warped > 0.99, "{mode:?}: warped {warped}");
            let (_, k_big) = fp.template(&cam, dst, mode, 10.0, 2.0, 4).unwrap();
            assert!((k_big.radial - 2.0).abs() < 1e-12, "{mode:?}: {k_big:?}");
        }
    }

    #[test]
    fn projective_warp_undoes_a_turn_about_the_optical_axis() {
        // The image turned by +90 degrees about the principal point is what the camera sees
        // after turning by -90 degrees about its optical axis: a current ray (a, b, c) was
        // the initial ray (b, -a, c).
        let n = 81;
        let img = textured(n, n);
        let rot = turned_90(&img);
        let cam = UnifiedCamera::new(0.9, 60.0, 40.0, 40.0, n as u32, n as u32);
        let fp = FeaturePatch::new(&img, &cam, DVec2::new(60.0, 40.0), 10, 4).unwrap();
        let dst = DVec2::new(40.0, 60.0);
        for point in [None, Some(DVec3::new(0.9, 0.1, 0.6))] {
            let view = ViewChange {
                init_from_now: glam::DQuat::from_rotation_z(-std::f64::consts::FRAC_PI_2),
                centre_now_in_init: DVec3::ZERO,
                point_in_init: point,
            };
            let t = fp.template_projective(&cam, dst, &view, 4).unwrap();
            let score = t.correlate_at(&rot, 40, 60).unwrap();
            assert!(score > 0.99, "{point:?}: {score}");
        }
        let plain = fp
            .plain
            .clone()
            .unwrap()
            .correlate_at(&rot, 40, 60)
            .unwrap();
        assert!(plain < 0.8, "plain {plain}");
    }

    /// The rotation `camera_from_world` that takes the world directions `world_ray`,
    /// `world_r`, `world_t` (orthonormal, right-handed) to the unit ray `s` and its radial and
    /// tangential directions `e_r`, `e_t` in the camera frame.
    fn camera_from_world(
        s: DVec3,
        world_ray: DVec3,
        world_r: DVec3,
        world_t: DVec3,
    ) -> glam::DMat3 {
        // Rows: camera-frame coordinates of the world basis chosen so that world_ray -> s,
        // world_r -> e_r(s), world_t -> e_t(s).
        let (e_r, e_t) = ray_frame(s);
        let cam = glam::DMat3::from_cols(s, e_r, e_t);
        let world = glam::DMat3::from_cols(world_ray, world_r, world_t);
        cam * world.transpose()
    }

    #[test]
    fn thesis_scale_is_the_ratio_of_true_image_lengths() {
        // Exact geometry: a feature point P with two short scene segments perpendicular to
        // its ray, one in the plane of the ray and the optical axis (pointing towards the
        // axis), one across it. At initialisation the radial segment ends where the image
        // shows r_im-; later the camera sees P from a different distance and polar angle,
        // with the segments still perpendicular to the ray and in the same relative
        // orientation. The true image lengths then follow from projecting the segments' end
        // points, and the warp's scales must equal their ratios.
        let cam = UnifiedCamera::catadioptric(400, 400);
        let half = 5usize;
        let world_ray = DVec3::new(0.0, 0.0, 1.0);
        let (world_r, world_t) = (DVec3::X, DVec3::Y);
        let uv0 = DVec2::new(cam.cx + 120.0, cam.cy + 45.0);
        let s0 = cam.unproject(uv0).unwrap();
        let d0 = 3.0;
        let img = textured(400, 400);
        let fp = FeaturePatch::new(&img, &cam, uv0, 15, half).unwrap();
        assert!(
            (fp.radial_init - half as f64).abs() < 1e-6,
            "{}",
            fp.radial_init
        );
        // The world-space segments from the initial view: the radial one ends on the ray of
        // r_im-.
        let r0 = camera_from_world(s0, world_ray, world_r, world_t);
        let p = world_ray * d0;
        let u0 = radial_direction(&cam, uv0);
        let s_minus = cam.unproject(uv0 - u0 * half as f64).unwrap();
        // Intersection of the r_im- ray with the plane through P perpendicular to the ray.
        let s_minus_w = r0.transpose() * s_minus;
        let q_r = s_minus_w * (d0 / s_minus_w.dot(world_ray));
        let len = (q_r - p).length();
        assert!(
            (q_r - p).normalize().dot(-world_r) > 1.0 - 1e-9,
            "the radial segment points towards the axis"
        );
        let q_t = p + world_t * len;
        let image_len = |rot: glam::DMat3, centre: DVec3, q: DVec3| {
            let a = cam.project(rot * (p - centre)).unwrap();
            let b = cam.project(rot * (q - centre)).unwrap();
            (a - b).length()
        };
        let l_r0 = image_len(r0, DVec3::ZERO, q_r);
        let l_t0 = image_len(r0, DVec3::ZERO, q_t);
        assert!((l_r0 - half as f64).abs() < 1e-6, "{l_r0}");
        for (uv1, d1) in [
            (DVec2::new(cam.cx + 20.0, cam.cy - 30.0), 1.5),
            (DVec2::new(cam.cx - 150.0, cam.cy + 60.0), 3.0),
            (DVec2::new(cam.cx + 60.0, cam.cy + 170.0), 6.0),
            (DVec2::new(cam.cx - 10.0, cam.cy + 100.0), 2.2),
        ] {
            let s1 = cam.unproject(uv1).unwrap();
            let r1 = camera_from_world(s1, world_ray, world_r, world_t);
            let centre = p - world_ray * d1;
            assert!((cam.project(r1 * (p - centre)).unwrap() - uv1).length() < 1e-6);
            let true_r = image_len(r1, centre, q_r) / l_r0;
            let true_t = image_len(r1, centre, q_t) / l_t0;
            let ratio = d0 / d1;
            let (k_r, k_t) = fp
                .raw_scales(&cam, uv1, PatchMode::Anisotropic, ratio)
                .unwrap();
            assert!(
                (k_r - true_r).abs() < 1e-6 * true_r,
                "{uv1}: {k_r} vs {true_r}"
            );
            assert!(
                (k_t - true_t).abs() < 1e-6 * true_t,
                "{uv1}: {k_t} vs {true_t}"
            );
            let (k, k2) = fp.raw_scales(&cam, uv1, PatchMode::Thesis, ratio).unwrap();
            assert_eq!((k, k2), (k_r, k_r));
        }
    }
}
