//! ORB features (Rublee et al. 2011) as OpenCV's `ORB` computes them: an 8-bit image pyramid
//! (8 levels, scale 1.2, bilinear), FAST-9 corners (threshold 20, or 7 on a level that has too
//! few) after 3x3 non-maximum suppression, the best `2n` by FAST score re-ranked by the Harris
//! response and the best `n` kept per level, orientation by intensity centroid, and rotated
//! BRIEF 256-bit descriptors with the learned sampling pattern of [`super::pattern`] on the
//! level blurred by a 7x7 Gaussian (sigma 2). Optionally ([`OrbParams::distribute`]) the corners
//! are spread over a grid of cells with a per-cell threshold fallback, as ORB-SLAM does; that
//! covers weak-texture regions but is markedly less repeatable.
//!
//! Everything after the conversion of the input to 8 bits is integer arithmetic except the
//! orientation's `atan2` and the pattern rotation, and the result does not depend on the number
//! of threads.
//!
//! Keypoint coordinates are level-0 pixels (integer coordinates are pixel centres); a level-`l`
//! pixel `p_l` maps to `(p_l + 0.5) * 1.2^l - 0.5`. Keypoints can be lifted to 3D (camera frame,
//! metres) with an inverse-depth image and a pinhole camera.

use glam::{DVec2, DVec3};
use rayon::prelude::*;

use super::pattern::ORB_PATTERN;
use super::PlaceError;
use crate::camera::PinholeCamera;
use crate::image::ImageF32;

/// Border (level pixels) inside which no keypoint is kept: the rotated 31x31 pattern reaches
/// `sqrt(2) * 13 < 19` pixels from the centre.
pub const EDGE_THRESHOLD: usize = 19;
const HALF_PATCH: i32 = 15;

/// A 256-bit binary descriptor. Bit `i` (bit `i % 64` of word `i / 64`) is the `i`-th
/// intensity test of the pattern; the little-endian byte layout equals OpenCV's.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub struct Descriptor(pub [u64; 4]);

impl Descriptor {
    /// The 32 bytes in OpenCV / DBoW2 order (byte `j` holds tests `8j..8j+8`, LSB first).
    pub fn to_bytes(&self) -> [u8; 32] {
        let mut out = [0u8; 32];
        for (w, chunk) in self.0.iter().zip(out.chunks_exact_mut(8)) {
            chunk.copy_from_slice(&w.to_le_bytes());
        }
        out
    }

    /// Inverse of [`Self::to_bytes`].
    pub fn from_bytes(b: &[u8; 32]) -> Self {
        let mut w = [0u64; 4];
        for (i, wi) in w.iter_mut().enumerate() {
            let mut le = [0u8; 8];
            le.copy_from_slice(&b[8 * i..8 * i + 8]);
            *wi = u64::from_le_bytes(le);
        }
        Descriptor(w)
    }

    /// Hamming distance (number of differing bits, 0..=256).
    #[inline]
    pub fn distance(&self, other: &Descriptor) -> u32 {
        (self.0[0] ^ other.0[0]).count_ones()
            + (self.0[1] ^ other.0[1]).count_ones()
            + (self.0[2] ^ other.0[2]).count_ones()
            + (self.0[3] ^ other.0[3]).count_ones()
    }

    /// Bit `i` (0..256).
    #[inline]
    pub fn bit(&self, i: usize) -> bool {
        (self.0[i / 64] >> (i % 64)) & 1 == 1
    }
}

/// One oriented multi-scale keypoint.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct KeyPoint {
    /// Level-0 pixel coordinates (integers are pixel centres).
    pub uv: DVec2,
    /// Pyramid level it was detected on.
    pub level: u8,
    /// Orientation in radians (image x axis towards y, i.e. clockwise on screen), `(-pi, pi]`.
    pub angle: f32,
    /// FAST score: the smallest absolute intensity difference to the centre along the best arc
    /// of 9 circle pixels (it is a corner for every FAST threshold below this value).
    pub score: f32,
    /// Diameter of the descriptor patch in level-0 pixels (`31 * 1.2^level`).
    pub size: f32,
}

impl KeyPoint {
    /// The nearest pixel `(x, y)` of the keypoint, clamped into a `width x height` image.
    pub fn nearest_pixel(&self, width: usize, height: usize) -> (usize, usize) {
        let x = (self.uv.x.round().max(0.0) as usize).min(width.saturating_sub(1));
        let y = (self.uv.y.round().max(0.0) as usize).min(height.saturating_sub(1));
        (x, y)
    }
}

/// ORB extraction parameters (defaults as ORB-SLAM and OpenCV: 1000 features, 8 levels, 1.2).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct OrbParams {
    /// Target number of keypoints over all levels.
    pub n_features: usize,
    /// Number of pyramid levels.
    pub n_levels: usize,
    /// Scale between consecutive levels (> 1).
    pub scale_factor: f64,
    /// FAST threshold tried first in every cell (intensity units, `[0, 255]` scale).
    pub initial_threshold: f32,
    /// Lower FAST threshold, used on a level (or, with [`Self::distribute`], in a cell) where
    /// the initial one finds too few corners.
    pub min_threshold: f32,
    /// Spread the corners over a grid of cells (ORB-SLAM) instead of keeping each level's
    /// strongest by Harris response (OpenCV). Off by default: the grid fills weak-texture
    /// cells with corners that are rarely detected again.
    pub distribute: bool,
    /// Approximate cell size in level pixels (only with [`Self::distribute`]).
    pub cell_size: usize,
}

impl Default for OrbParams {
    fn default() -> Self {
        Self {
            n_features: 1000,
            n_levels: 8,
            scale_factor: 1.2,
            initial_threshold: 20.0,
            min_threshold: 7.0,
            distribute: false,
            cell_size: 30,
        }
    }
}

/// Keypoints, their descriptors and (after [`OrbFeatures::lift`]) their 3D points.
#[derive(Clone, Debug, Default)]
pub struct OrbFeatures {
    /// Keypoints, level-0 pixels.
    pub keypoints: Vec<KeyPoint>,
    /// One descriptor per keypoint.
    pub descriptors: Vec<Descriptor>,
    /// One entry per keypoint: the point in the camera frame (metres), `None` where the
    /// inverse depth is missing. Empty until lifted.
    pub points: Vec<Option<DVec3>>,
    /// Image width in pixels.
    pub width: usize,
    /// Image height in pixels.
    pub height: usize,
}

impl OrbFeatures {
    /// Number of keypoints.
    pub fn len(&self) -> usize {
        self.keypoints.len()
    }

    /// True when there are no keypoints.
    pub fn is_empty(&self) -> bool {
        self.keypoints.is_empty()
    }

    /// Lifts every keypoint to 3D with the inverse depth (1/m, 0 = invalid) at its nearest
    /// pixel, unprojected with `camera`. Fills [`Self::points`].
    pub fn lift(
        &mut self,
        inverse_depth: &ImageF32,
        camera: &PinholeCamera,
    ) -> Result<(), PlaceError> {
        if inverse_depth.width != self.width || inverse_depth.height != self.height {
            return Err(PlaceError::SizeMismatch {
                what: "inverse depth",
                got_w: inverse_depth.width,
                got_h: inverse_depth.height,
                want_w: self.width,
                want_h: self.height,
            });
        }
        self.points = self
            .keypoints
            .iter()
            .map(|k| {
                let x = k.uv.x.round();
                let y = k.uv.y.round();
                if x < 0.0 || y < 0.0 || x >= self.width as f64 || y >= self.height as f64 {
                    return None;
                }
                let rho = inverse_depth.at(x as usize, y as usize);
                (rho.is_finite() && rho > 0.0).then(|| camera.unproject(k.uv, 1.0 / f64::from(rho)))
            })
            .collect();
        Ok(())
    }
}

// The FAST circle (shared with the monocular EKF's detector).
use crate::image::FAST_CIRCLE as CIRCLE;

/// An 8-bit single-channel image: the extractor works on integer intensities, as OpenCV's and
/// ORB-SLAM's ORB do (the FAST test, Harris response, orientation and BRIEF tests are all on
/// `u8` pixels).
#[derive(Clone, Debug)]
struct Gray {
    width: usize,
    height: usize,
    data: Vec<u8>,
}

impl Gray {
    /// Rounds an intensity image to `u8` (values clamped into `[0, 255]`, NaN as 0).
    fn from_f32(img: &ImageF32) -> Self {
        let data = img
            .data
            .iter()
            .map(|&v| {
                // `as u8` saturates and maps NaN to 0.
                (v + 0.5) as u8
            })
            .collect();
        Self {
            width: img.width,
            height: img.height,
            data,
        }
    }

    #[cfg(test)]
    fn to_f32(&self) -> ImageF32 {
        ImageF32 {
            width: self.width,
            height: self.height,
            data: self.data.iter().map(|&v| f32::from(v)).collect(),
        }
    }
}

/// Bilinear resampling to `w x h` with pixel centres aligned (`src = (dst + 0.5) * s - 0.5`),
/// in 8-bit fixed point (weights in 1/256, result rounded), like OpenCV's `INTER_LINEAR_EXACT`.
/// Each output row blends two horizontally resampled source rows.
fn resize_bilinear(src: &Gray, w: usize, h: usize) -> Gray {
    let tap = |dst: usize, n_dst: usize, n: usize| -> (usize, usize, u16) {
        let s = n as f64 / n_dst as f64;
        let f = ((dst as f64 + 0.5) * s - 0.5).clamp(0.0, (n - 1) as f64);
        let i0 = f.floor() as usize;
        let i1 = (i0 + 1).min(n - 1);
        (i0, i1, ((f - i0 as f64) * 256.0).round() as u16)
    };
    let xs: Vec<(usize, usize, u16)> = (0..w).map(|x| tap(x, w, src.width)).collect();
    let hresample = |y: usize, out: &mut [u16]| {
        let r = &src.data[y * src.width..(y + 1) * src.width];
        for (o, &(x0, x1, tx)) in out.iter_mut().zip(xs.iter()) {
            *o = u16::from(r[x0]) * (256 - tx) + u16::from(r[x1]) * tx;
        }
    };
    let mut out = vec![0u8; w * h];
    out.par_chunks_mut(w * 16)
        .enumerate()
        .for_each(|(chunk, rows)| {
            let (mut h0, mut h1) = (vec![0u16; w], vec![0u16; w]);
            let mut have = (usize::MAX, usize::MAX);
            for (r, row) in rows.chunks_exact_mut(w).enumerate() {
                let (y0, y1, ty) = tap(chunk * 16 + r, h, src.height);
                if have.0 != y0 {
                    if have.1 == y0 {
                        std::mem::swap(&mut h0, &mut h1);
                        have.1 = usize::MAX;
                    } else {
                        hresample(y0, &mut h0);
                    }
                    have.0 = y0;
                }
                if have.1 != y1 {
                    hresample(y1, &mut h1);
                    have.1 = y1;
                }
                let (wa, wb) = (u32::from(256 - ty), u32::from(ty));
                for ((o, &a), &b) in row.iter_mut().zip(h0.iter()).zip(h1.iter()) {
                    *o = ((u32::from(a) * wa + u32::from(b) * wb + (1 << 15)) >> 16) as u8;
                }
            }
        });
    Gray {
        width: w,
        height: h,
        data: out,
    }
}

/// Index `i` reflected into `0..n` without repeating the edge pixel (OpenCV's
/// `BORDER_REFLECT_101`), for `-n < i < 2n - 1`.
#[inline]
fn reflect101(i: isize, n: usize) -> usize {
    let n = n as isize;
    let r = if i < 0 {
        -i
    } else if i >= n {
        2 * n - 2 - i
    } else {
        i
    };
    r.clamp(0, n - 1) as usize
}

/// 7x7 Gaussian blur with sigma 2 (as OpenCV's ORB before BRIEF), separable, in fixed point
/// (taps in 1/256, rounded result), `BORDER_REFLECT_101`.
fn gaussian_blur7(img: &Gray) -> Gray {
    let g: [f64; 4] = std::array::from_fn(|d| (-((d * d) as f64) / 8.0).exp());
    let total = g[0] + 2.0 * (g[1] + g[2] + g[3]);
    let side: [u16; 3] = std::array::from_fn(|d| (256.0 * g[d + 1] / total).round() as u16);
    let centre = 256 - 2 * (side[0] + side[1] + side[2]);
    let k: [u16; 7] = [side[2], side[1], side[0], centre, side[0], side[1], side[2]];
    let (w, h) = (img.width, img.height);
    // Horizontal pass into u16 (at most 255 * 256).
    let mut tmp = vec![0u16; w * h];
    tmp.chunks_mut(w).enumerate().for_each(|(y, row)| {
        let src = &img.data[y * w..(y + 1) * w];
        let at = |x: isize| u16::from(src[reflect101(x, w)]);
        for x in (0..3.min(w)).chain(w.saturating_sub(3).max(3)..w) {
            row[x] = (0..7).map(|j| at(x as isize + j - 3) * k[j as usize]).sum();
        }
        if w > 6 {
            let n = w - 6;
            let c = |o: usize| &src[o..o + n];
            let (a0, a1, a2, a3, a4, a5, a6) = (c(0), c(1), c(2), c(3), c(4), c(5), c(6));
            for (i, o) in row[3..3 + n].iter_mut().enumerate() {
                *o = (u16::from(a0[i]) + u16::from(a6[i])) * k[0]
                    + (u16::from(a1[i]) + u16::from(a5[i])) * k[1]
                    + (u16::from(a2[i]) + u16::from(a4[i])) * k[2]
                    + u16::from(a3[i]) * k[3];
            }
        }
    });
    let mut out = vec![0u8; w * h];
    out.chunks_mut(w).enumerate().for_each(|(y, row)| {
        let r: [&[u16]; 7] = std::array::from_fn(|j| {
            let yy = reflect101(y as isize + j as isize - 3, h);
            &tmp[yy * w..(yy + 1) * w]
        });
        let k: [u32; 7] = k.map(u32::from);
        let row = &mut row[..w];
        let (r0, r1, r2, r3, r4, r5, r6) = (
            &r[0][..w],
            &r[1][..w],
            &r[2][..w],
            &r[3][..w],
            &r[4][..w],
            &r[5][..w],
            &r[6][..w],
        );
        for x in 0..w {
            let acc = (u32::from(r0[x]) + u32::from(r6[x])) * k[0]
                + (u32::from(r1[x]) + u32::from(r5[x])) * k[1]
                + (u32::from(r2[x]) + u32::from(r4[x])) * k[2]
                + u32::from(r3[x]) * k[3];
            row[x] = ((acc + (1 << 15)) >> 16) as u8;
        }
    });
    Gray {
        width: w,
        height: h,
        data: out,
    }
}

/// Offsets of the 16 FAST circle pixels in an image with row stride `w`.
fn circle_offsets(w: usize) -> [isize; 16] {
    std::array::from_fn(|k| CIRCLE[k].1 as isize * w as isize + CIRCLE[k].0 as isize)
}

/// FAST-9 score of the pixel at index `c` of `img` (a 3-pixel border is needed): the largest
/// `m` such that 9 contiguous circle pixels all differ from the centre by at least `m` in the
/// same direction, if `m > t`; else 0. [`fast_row`] calls it only for the pixels that pass
/// its high-speed pre-test.
#[inline]
fn fast_score_u8(img: &[u8], offs: &[isize; 16], c: usize, t: u8) -> u8 {
    let vals: [u8; 16] = std::array::from_fn(|k| img[c.wrapping_add_signed(offs[k])]);
    let p = img[c];
    let (hi, lo) = (p.saturating_add(t), p.saturating_sub(t));
    let (mut dark, mut bright) = (0u32, 0u32);
    for (k, &v) in vals.iter().enumerate() {
        bright |= u32::from(v > hi) << k;
        dark |= u32::from(v < lo) << k;
    }
    let arc9 = |m: u32| {
        let m = m | (m << 16);
        let m2 = m & (m >> 1);
        let m4 = m2 & (m2 >> 2);
        let m8 = m4 & (m4 >> 4);
        (m8 & (m >> 8)) != 0
    };
    if !arc9(dark) && !arc9(bright) {
        return 0;
    }
    let m = fast_score_exact(&vals, p);
    if m > t {
        m
    } else {
        0
    }
}

/// The FAST score of the centre `p` with circle pixels `vals` (clockwise): the largest `m`
/// such that 9 contiguous circle pixels all differ from `p` by at least `m` in the same
/// direction (0 when no arc is on one side). Window minima and maxima by doubling (2, 4, 8,
/// then 9) over the circle unrolled to 24 entries, in straight-line `i16` code that vectorises.
#[inline]
fn fast_score_exact(vals: &[u8; 16], p: u8) -> u8 {
    let pi = i16::from(p);
    let d: [i16; 24] = std::array::from_fn(|k| i16::from(vals[k & 15]) - pi);
    let lo2: [i16; 23] = std::array::from_fn(|k| d[k].min(d[k + 1]));
    let hi2: [i16; 23] = std::array::from_fn(|k| d[k].max(d[k + 1]));
    let lo4: [i16; 21] = std::array::from_fn(|k| lo2[k].min(lo2[k + 2]));
    let hi4: [i16; 21] = std::array::from_fn(|k| hi2[k].max(hi2[k + 2]));
    let lo8: [i16; 17] = std::array::from_fn(|k| lo4[k].min(lo4[k + 4]));
    let hi8: [i16; 17] = std::array::from_fn(|k| hi4[k].max(hi4[k + 4]));
    // Arc k..=k+8 for k in 0..16: the brightest arc's minimum, the darkest arc's maximum.
    let mut bright = i16::MIN;
    let mut dark = i16::MAX;
    for k in 0..16 {
        bright = bright.max(lo8[k].min(d[k + 8]));
        dark = dark.min(hi8[k].max(d[k + 8]));
    }
    bright.max(-dark).clamp(0, 255) as u8
}

/// Harris corner response (OpenCV's ORB: 7x7 block of 3x3 Sobel gradients, `k = 0.04`) at
/// `(x, y)`, which must be at least 4 pixels inside the image.
fn harris_response(img: &Gray, x: usize, y: usize) -> f32 {
    let w = img.width;
    let d = &img.data;
    let (mut a, mut b, mut c) = (0i64, 0i64, 0i64);
    for yy in y - 3..=y + 3 {
        let up = &d[(yy - 1) * w..yy * w];
        let mid = &d[yy * w..(yy + 1) * w];
        let dn = &d[(yy + 1) * w..(yy + 2) * w];
        let (mut sa, mut sb, mut sc) = (0i32, 0i32, 0i32);
        for xx in x - 3..=x + 3 {
            let g = |r: &[u8], i: usize| i32::from(r[i]);
            let ix = (g(mid, xx + 1) - g(mid, xx - 1)) * 2
                + (g(up, xx + 1) - g(up, xx - 1))
                + (g(dn, xx + 1) - g(dn, xx - 1));
            let iy = (g(dn, xx) - g(up, xx)) * 2
                + (g(dn, xx - 1) - g(up, xx - 1))
                + (g(dn, xx + 1) - g(up, xx + 1));
            sa += ix * ix;
            sb += iy * iy;
            sc += ix * iy;
        }
        a += i64::from(sa);
        b += i64::from(sb);
        c += i64::from(sc);
    }
    // Scaled as OpenCV (gradients by 1 / (4 * 7 * 255)) so values are comparable to its.
    let scale = 1.0 / (4.0 * 7.0 * 255.0);
    let (a, b, c) = (a as f64, b as f64, c as f64);
    let r = a * b - c * c - 0.04 * (a + b) * (a + b);
    (r * scale * scale * scale * scale) as f32
}

/// Offsets `(dx, dy)` of the radius-15 disc rows used by the intensity centroid: row `v`
/// spans `-umax[v]..=umax[v]` (made symmetric in x and y, as OpenCV's ORB).
fn disc_umax() -> [i32; 16] {
    let hp = HALF_PATCH as usize;
    let mut umax = [0i32; 16];
    let vmax = (hp as f64 * std::f64::consts::FRAC_1_SQRT_2 + 1.0).floor() as usize;
    let vmin = (hp as f64 * std::f64::consts::FRAC_1_SQRT_2).ceil() as usize;
    for (v, u) in umax.iter_mut().enumerate().take(vmax + 1) {
        *u = ((hp * hp) as f64 - (v * v) as f64).sqrt().round() as i32;
    }
    // Mirror the octant so the disc is symmetric under swapping x and y.
    let mut v0 = 0usize;
    let mut v = hp;
    while v >= vmin {
        while umax[v0] == umax[v0 + 1] {
            v0 += 1;
        }
        umax[v] = v0 as i32;
        v0 += 1;
        v -= 1;
    }
    umax
}

/// Intensity-centroid orientation over the radius-15 disc at integer pixel `(x, y)`.
fn ic_angle(img: &Gray, x: usize, y: usize, umax: &[i32; 16]) -> f32 {
    let w = img.width;
    let d = &img.data;
    let c = y * w + x;
    let (mut m01, mut m10) = (0i32, 0i32);
    let hp = HALF_PATCH as usize;
    for (u, &v) in d[c - hp..=c + hp].iter().enumerate() {
        m10 += (u as i32 - HALF_PATCH) * i32::from(v);
    }
    for v in 1..=hp {
        let r = umax[v] as usize;
        let plus = &d[c + v * w - r..=c + v * w + r];
        let minus = &d[c - v * w - r..=c - v * w + r];
        let mut v_sum = 0i32;
        for (i, (&p, &m)) in plus.iter().zip(minus.iter()).enumerate() {
            let (p, m) = (i32::from(p), i32::from(m));
            v_sum += p - m;
            m10 += (i as i32 - r as i32) * (p + m);
        }
        m01 += v as i32 * v_sum;
    }
    (m01 as f32).atan2(m10 as f32)
}

/// The 512 pattern points (first and second point of each pair, interleaved) as `f32`
/// coordinates, for a vectorisable rotation.
fn pattern_points() -> &'static ([f32; 512], [f32; 512]) {
    static POINTS: std::sync::OnceLock<([f32; 512], [f32; 512])> = std::sync::OnceLock::new();
    POINTS.get_or_init(|| {
        let xs = std::array::from_fn(|i| f32::from(ORB_PATTERN[i / 2][2 * (i % 2)]));
        let ys = std::array::from_fn(|i| f32::from(ORB_PATTERN[i / 2][2 * (i % 2) + 1]));
        (xs, ys)
    })
}

/// Nearest integer of `v` as `f32`, halves to even (as OpenCV's `cvRound`), for
/// `|v| < 2^22`: adding and subtracting `1.5 * 2^23` rounds in the FPU's default mode; plain
/// arithmetic, so it vectorises (no libm call on baseline x86-64).
#[inline]
fn round_even(v: f32) -> f32 {
    const MAGIC: f32 = 12_582_912.0;
    (v + MAGIC) - MAGIC
}

/// Rotated-BRIEF descriptor at integer pixel `(x, y)` of the blurred level image: the pattern
/// is rotated by `angle` and rounded to pixels (as OpenCV's ORB), then tested.
fn brief(img: &Gray, x: usize, y: usize, angle: f32) -> Descriptor {
    let (s, c) = angle.sin_cos();
    let w = img.width as f32;
    let (xs, ys) = pattern_points();
    let mut offs = [0i32; 512];
    for ((o, &px), &py) in offs.iter_mut().zip(xs.iter()).zip(ys.iter()) {
        // Exact in f32: |offset| <= 19 * (w + 1) is far below 2^24 for any image that fits.
        *o = (round_even(px * s + py * c) * w + round_even(px * c - py * s)) as i32;
    }
    let centre = y * img.width + x;
    let d = &img.data;
    let get = |o: i32| d[centre.wrapping_add_signed(o as isize)];
    let mut out = [0u64; 4];
    for (word, pairs) in out.iter_mut().zip(offs.chunks_exact(128)) {
        let mut bits = 0u64;
        for (i, o) in pairs.chunks_exact(2).enumerate() {
            bits |= u64::from(get(o[0]) < get(o[1])) << i;
        }
        *word = bits;
    }
    Descriptor(out)
}

#[derive(Clone, Copy, Debug)]
struct Candidate {
    x: usize,
    y: usize,
    /// FAST score (see [`fast_score_u8`]).
    fast: u8,
    /// Harris response, filled for the candidates that are ranked by it.
    harris: f32,
}

/// Orders by descending `key`, ties by raster position (deterministic).
fn by_key_desc(
    a: &Candidate,
    b: &Candidate,
    key: impl Fn(&Candidate) -> f32,
) -> std::cmp::Ordering {
    key(b)
        .total_cmp(&key(a))
        .then(a.y.cmp(&b.y))
        .then(a.x.cmp(&b.x))
}

/// FAST scores of row `y`, columns `x0..x1` (at least 3 pixels inside the image), into
/// `out` (the row's slice of the score map). A vectorisable pre-test over the row keeps the
/// pixels for which two circle-adjacent compass pixels (0/4, 4/8, 8/12 or 12/0) and two
/// adjacent diagonal ones (2/6, 6/10, 10/14 or 14/2) are all brighter than `p + t` or all
/// darker than `p - t`, which every arc of 9 needs (9 consecutive circle pixels include
/// two consecutive ones of each set); only those get the full test. `flags` is scratch of the row's length.
#[allow(clippy::too_many_arguments)]
fn fast_row(
    img: &[u8],
    w: usize,
    y: usize,
    x0: usize,
    x1: usize,
    t: u8,
    offs: &[isize; 16],
    flags: &mut [u8],
    out: &mut [u8],
) {
    let n = x1 - x0;
    let mid = &img[y * w + x0..y * w + x1];
    let up = &img[(y - 3) * w + x0..(y - 3) * w + x1];
    let dn = &img[(y + 3) * w + x0..(y + 3) * w + x1];
    let right = &img[y * w + x0 + 3..y * w + x1 + 3];
    let left = &img[y * w + x0 - 3..y * w + x1 - 3];
    let flags = &mut flags[..n];
    // Bit 1: dark, bit 2: bright, for two adjacent pixels of the four at `a, b, c, d`
    // (consecutive around the circle, 4 apart).
    let pair_test = |p: u8, a: u8, b: u8, c: u8, d: u8| -> u8 {
        let hi = p.saturating_add(t);
        let lo = p.saturating_sub(t);
        let (ba, bb, bc, bd) = (a > hi, b > hi, c > hi, d > hi);
        let (da, db, dc, dd) = (a < lo, b < lo, c < lo, d < lo);
        let bright = (ba & bb) | (bb & bc) | (bc & bd) | (bd & ba);
        let dark = (da & db) | (db & dc) | (dc & dd) | (dd & da);
        (u8::from(bright) << 1) | u8::from(dark)
    };
    // Compass pixels 0, 4, 8, 12.
    for (((((f, &p), &a), &b), &c), &d) in flags
        .iter_mut()
        .zip(mid)
        .zip(up)
        .zip(right)
        .zip(dn)
        .zip(left)
    {
        *f = pair_test(p, a, b, c, d);
    }
    // Diagonal pixels 2, 6, 10, 14 (every 9-arc holds two adjacent ones of these too).
    let ne = &img[(y - 2) * w + x0 + 2..(y - 2) * w + x1 + 2];
    let se = &img[(y + 2) * w + x0 + 2..(y + 2) * w + x1 + 2];
    let sw = &img[(y + 2) * w + x0 - 2..(y + 2) * w + x1 - 2];
    let nw = &img[(y - 2) * w + x0 - 2..(y - 2) * w + x1 - 2];
    for (((((f, &p), &a), &b), &c), &d) in flags.iter_mut().zip(mid).zip(ne).zip(se).zip(sw).zip(nw)
    {
        *f &= pair_test(p, a, b, c, d);
    }
    let mut i = 0;
    while i < n {
        if i + 8 <= n {
            let mut word = [0u8; 8];
            word.copy_from_slice(&flags[i..i + 8]);
            if u64::from_ne_bytes(word) == 0 {
                i += 8;
                continue;
            }
        }
        if flags[i] != 0 {
            out[x0 + i] = fast_score_u8(img, offs, y * w + x0 + i, t);
        }
        i += 1;
    }
}

/// FAST corners (score `> t`) of one level inside the keypoint region
/// `[e, w - e) x [e, h - e)` (`e >= 4`; [`EDGE_THRESHOLD`]), after 3x3 non-maximum
/// suppression and the mask.
fn fast_corners(
    img: &Gray,
    t: u8,
    e: usize,
    scale: f64,
    mask: Option<&ImageF32>,
) -> Vec<Candidate> {
    let (w, h) = (img.width, img.height);
    let offs = circle_offsets(w);
    let mask_ok = |x: usize, y: usize| -> bool {
        match mask {
            None => true,
            Some(m) => {
                let u = ((x as f64 + 0.5) * scale - 0.5)
                    .round()
                    .clamp(0.0, (m.width - 1) as f64) as usize;
                let v = ((y as f64 + 0.5) * scale - 0.5)
                    .round()
                    .clamp(0.0, (m.height - 1) as f64) as usize;
                m.at(u, v) > 0.0
            }
        }
    };
    // Scores over the keypoint region plus one pixel for non-maximum suppression, three rows
    // at a time: row `y` lives in `ring[y % 3]`.
    let (x0, x1) = (e - 1, w - e + 1);
    let mut flags = vec![0u8; w];
    let mut ring = [vec![0u8; w], vec![0u8; w], vec![0u8; w]];
    let mut score_row = |y: usize, row: &mut Vec<u8>| {
        row.fill(0);
        fast_row(&img.data, w, y, x0, x1, t, &offs, &mut flags, row);
    };
    score_row(e - 1, &mut ring[(e - 1) % 3]);
    score_row(e, &mut ring[e % 3]);
    let mut found = Vec::new();
    for y in e..h - e {
        score_row(y + 1, &mut ring[(y + 1) % 3]);
        let (up, mid, dn) = (&ring[(y - 1) % 3], &ring[y % 3], &ring[(y + 1) % 3]);
        let mut x = e;
        while x < w - e {
            // Skip runs of non-corners 8 pixels at a time.
            if x + 8 <= w - e {
                let mut word = [0u8; 8];
                word.copy_from_slice(&mid[x..x + 8]);
                if u64::from_ne_bytes(word) == 0 {
                    x += 8;
                    continue;
                }
            }
            let s = mid[x];
            // 3x3 non-maximum suppression; ties go to the later pixel in raster order.
            let is_max = s > 0
                && up[x - 1] <= s
                && up[x] <= s
                && up[x + 1] <= s
                && mid[x - 1] <= s
                && mid[x + 1] < s
                && dn[x - 1] < s
                && dn[x] < s
                && dn[x + 1] < s;
            if is_max && mask_ok(x, y) {
                found.push(Candidate {
                    x,
                    y,
                    fast: s,
                    harris: 0.0,
                });
            }
            x += 1;
        }
    }
    found
}

/// Keeps the `n` best of `cands` by `key` (descending; ties by raster position).
fn retain_best(cands: &mut Vec<Candidate>, n: usize, key: impl Fn(&Candidate) -> f32 + Copy) {
    if cands.len() > n {
        if n > 0 {
            cands.select_nth_unstable_by(n - 1, |a, b| by_key_desc(a, b, key));
        }
        cands.truncate(n);
    }
}

/// Detects and selects up to `budget` keypoints on one level.
fn detect_level(
    img: &Gray,
    scale: f64,
    budget: usize,
    params: &OrbParams,
    mask: Option<&ImageF32>,
) -> Vec<Candidate> {
    let (w, h) = (img.width, img.height);
    let e = EDGE_THRESHOLD;
    if w < 2 * e + 1 || h < 2 * e + 1 || budget == 0 {
        return Vec::new();
    }
    let t_hi = params.initial_threshold.clamp(0.0, 254.0) as u8;
    let t_lo = params.min_threshold.clamp(0.0, 254.0) as u8;
    if !params.distribute {
        let mut cands = fast_corners(img, t_hi, e, scale, mask);
        if cands.len() < budget && t_lo < t_hi {
            cands = fast_corners(img, t_lo, e, scale, mask);
        }
        retain_best(&mut cands, 2 * budget, |c| f32::from(c.fast));
        for c in cands.iter_mut() {
            c.harris = harris_response(img, c.x, c.y);
        }
        retain_best(&mut cands, budget, |c| c.harris);
        cands.sort_by(|a, b| by_key_desc(a, b, |c| c.harris));
        return cands;
    }
    // Grid of cells, per-cell fallback threshold, Harris ranking within cells.
    let all = fast_corners(img, t_lo.min(t_hi), e, scale, mask);
    let (rw, rh) = (w - 2 * e, h - 2 * e);
    let ncx = (rw / params.cell_size.max(1)).max(1);
    let ncy = (rh / params.cell_size.max(1)).max(1);
    let mut cells: Vec<Vec<Candidate>> = vec![Vec::new(); ncx * ncy];
    for c in all {
        let cx = ((c.x - e) * ncx / rw).min(ncx - 1);
        let cy = ((c.y - e) * ncy / rh).min(ncy - 1);
        cells[cy * ncx + cx].push(c);
    }
    cells.iter_mut().for_each(|found| {
        if found.iter().any(|c| c.fast > t_hi) {
            found.retain(|c| c.fast > t_hi);
        }
        for c in found.iter_mut() {
            c.harris = harris_response(img, c.x, c.y);
        }
        found.sort_by(|a, b| by_key_desc(a, b, |c| c.harris));
    });
    let mut out = Vec::with_capacity(budget);
    let max_rank = cells.iter().map(Vec::len).max().unwrap_or(0);
    for rank in 0..max_rank {
        let mut tier: Vec<Candidate> = cells.iter().filter_map(|c| c.get(rank).copied()).collect();
        if out.len() + tier.len() > budget {
            tier.sort_by(|a, b| by_key_desc(a, b, |c| c.harris));
            tier.truncate(budget - out.len());
        }
        out.extend(tier);
        if out.len() >= budget {
            break;
        }
    }
    out
}

/// Sizes of the pyramid levels of a `width x height` image, level 0 first: `1 / scale^l` of
/// it, rounded, down to the last level that still has a descriptor border.
fn level_sizes(width: usize, height: usize, params: &OrbParams) -> Vec<(usize, usize)> {
    let mut sizes = vec![(width, height)];
    for l in 1..params.n_levels {
        let s = params.scale_factor.powi(l as i32);
        let w = (width as f64 / s).round() as usize;
        let h = (height as f64 / s).round() as usize;
        if w < 2 * EDGE_THRESHOLD + 1 || h < 2 * EDGE_THRESHOLD + 1 {
            break;
        }
        sizes.push((w, h));
    }
    sizes
}

/// Detects, selects and describes the keypoints of pyramid level `l`.
fn extract_level(
    img: &Gray,
    l: usize,
    budget: usize,
    params: &OrbParams,
    mask: Option<&ImageF32>,
    umax: &[i32; 16],
) -> (Vec<KeyPoint>, Vec<Descriptor>) {
    let scale = params.scale_factor.powi(l as i32);
    let cands = detect_level(img, scale, budget, params, mask);
    if cands.is_empty() {
        return (Vec::new(), Vec::new());
    }
    let blurred = gaussian_blur7(img);
    cands
        .iter()
        .map(|c| {
            let angle = ic_angle(img, c.x, c.y, umax);
            let kp = KeyPoint {
                uv: DVec2::new(
                    (c.x as f64 + 0.5) * scale - 0.5,
                    (c.y as f64 + 0.5) * scale - 0.5,
                ),
                level: l as u8,
                angle,
                score: f32::from(c.fast),
                size: (31.0 * scale) as f32,
            };
            (kp, brief(&blurred, c.x, c.y, angle))
        })
        .unzip()
}

/// Extracts ORB keypoints and descriptors from `image` (intensity in `[0, 255]`).
///
/// `mask`, if given, has the image's size; keypoints whose level-0 pixel has mask value `<= 0`
/// are discarded before the per-level budgets are filled. The result has no 3D points; call
/// [`OrbFeatures::lift`] for them.
pub fn extract_orb(
    image: &ImageF32,
    mask: Option<&ImageF32>,
    params: &OrbParams,
) -> Result<OrbFeatures, PlaceError> {
    if params.n_levels == 0 || params.n_levels > 32 {
        return Err(PlaceError::InvalidParameter {
            name: "n_levels",
            why: "must be in 1..=32".into(),
        });
    }
    if !(params.scale_factor > 1.0 && params.scale_factor.is_finite()) {
        return Err(PlaceError::InvalidParameter {
            name: "scale_factor",
            why: "must be finite and > 1".into(),
        });
    }
    if image.width < 2 * EDGE_THRESHOLD + 1 || image.height < 2 * EDGE_THRESHOLD + 1 {
        return Err(PlaceError::ImageTooSmall {
            width: image.width,
            height: image.height,
        });
    }
    if image.data.len() != image.width * image.height {
        return Err(PlaceError::SizeMismatch {
            what: "image buffer",
            got_w: image.data.len(),
            got_h: 1,
            want_w: image.width,
            want_h: image.height,
        });
    }
    if let Some(m) = mask {
        if m.width != image.width || m.height != image.height || m.data.len() != m.width * m.height
        {
            return Err(PlaceError::SizeMismatch {
                what: "mask",
                got_w: m.width,
                got_h: m.height,
                want_w: image.width,
                want_h: image.height,
            });
        }
    }
    let sizes = level_sizes(image.width, image.height, params);
    let n_levels = sizes.len();
    // Per-level budgets: geometric in 1/scale, as ORB-SLAM.
    let f = 1.0 / params.scale_factor;
    let mut budgets = vec![0usize; n_levels];
    let mut per = params.n_features as f64 * (1.0 - f) / (1.0 - f.powi(n_levels as i32));
    let mut used = 0;
    for b in budgets.iter_mut().take(n_levels - 1) {
        *b = per.round() as usize;
        used += *b;
        per *= f;
    }
    budgets[n_levels - 1] = params.n_features.saturating_sub(used);

    let umax = disc_umax();
    let level = |l: usize, img: &Gray| extract_level(img, l, budgets[l], params, mask, &umax);
    // Level 0 is described while the rest of the pyramid is built and described.
    let level0 = Gray::from_f32(image);
    let (first, rest) = rayon::join(
        || level(0, &level0),
        || {
            let mut levels: Vec<Gray> = Vec::with_capacity(n_levels - 1);
            for &(w, h) in &sizes[1..] {
                let next = resize_bilinear(levels.last().unwrap_or(&level0), w, h);
                levels.push(next);
            }
            levels
                .par_iter()
                .enumerate()
                .map(|(i, img)| level(i + 1, img))
                .collect::<Vec<_>>()
        },
    );
    let per_level = std::iter::once(first).chain(rest);
    let mut out = OrbFeatures {
        width: image.width,
        height: image.height,
        ..Default::default()
    };
    for (k, d) in per_level {
        out.keypoints.extend(k);
        out.descriptors.extend(d);
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A small deterministic generator (xorshift64*).
    struct Rng(u64);

    impl Rng {
        fn next(&mut self) -> u64 {
            self.0 ^= self.0 >> 12;
            self.0 ^= self.0 << 25;
            self.0 ^= self.0 >> 27;
            self.0.wrapping_mul(0x2545_f491_4f6c_dd1d)
        }
        fn below(&mut self, n: u64) -> u64 {
            self.next() % n
        }
    }

    /// Random rectangles of random grey over noise: many corners of all strengths.
    fn random_gray(w: usize, h: usize, seed: u64) -> Gray {
        let mut rng = Rng(seed | 1);
        let mut data: Vec<u8> = (0..w * h).map(|_| 100 + rng.below(12) as u8).collect();
        for _ in 0..(w * h / 150) {
            let (x0, y0) = (rng.below(w as u64) as usize, rng.below(h as u64) as usize);
            let (bw, bh) = (2 + rng.below(14) as usize, 2 + rng.below(14) as usize);
            let v = rng.below(256) as u8;
            for y in y0..(y0 + bh).min(h) {
                for x in x0..(x0 + bw).min(w) {
                    data[y * w + x] = v;
                }
            }
        }
        Gray {
            width: w,
            height: h,
            data,
        }
    }

    /// The floating-point FAST-9 score this module used before the 8-bit version: the largest
    /// `m` over arcs of 9 of the minimum same-sign difference, if `> min_t`, else 0.
    fn reference_fast_score(img: &[f32], w: usize, x: usize, y: usize, min_t: f32) -> f32 {
        let c = y * w + x;
        let p = img[c];
        let d: Vec<f32> = (0..25)
            .map(|k| {
                let (dx, dy) = CIRCLE[k % 16];
                img[((y as i32 + dy) as usize) * w + (x as i32 + dx) as usize] - p
            })
            .collect();
        let mut best = f32::MIN;
        for s in 0..16 {
            let mn = d[s..s + 9].iter().copied().fold(f32::MAX, f32::min);
            let mx = d[s..s + 9].iter().copied().fold(f32::MIN, f32::max);
            best = best.max(mn).max(-mx);
        }
        if best > min_t {
            best
        } else {
            0.0
        }
    }

    #[test]
    fn descriptor_bytes_round_trip_and_distance() {
        let mut a = Descriptor::default();
        a.0[0] = 0b1011;
        a.0[3] = 1 << 63;
        let b = Descriptor::from_bytes(&a.to_bytes());
        assert_eq!(a, b);
        assert_eq!(a.to_bytes()[0], 0b1011);
        assert_eq!(a.to_bytes()[31], 0x80);
        assert_eq!(a.distance(&Descriptor::default()), 4);
        assert!(a.bit(0) && a.bit(1) && !a.bit(2) && a.bit(255));
    }

    #[test]
    fn fast_detects_a_bright_square_corner_and_not_flat_or_edges() {
        let w = 64;
        let mut data = vec![50u8; w * w];
        for y in 32..w {
            for x in 32..w {
                data[y * w + x] = 200;
            }
        }
        let offs = circle_offsets(w);
        assert_eq!(fast_score_u8(&data, &offs, 32 * w + 32, 7), 150);
        assert_eq!(fast_score_u8(&data, &offs, 10 * w + 10, 7), 0);
        assert_eq!(
            fast_score_u8(&data, &offs, 32 * w + 45, 7),
            0,
            "straight edge is not a corner"
        );
    }

    #[test]
    fn u8_fast_with_the_row_pretest_agrees_with_the_reference_float_test() {
        let mut corners = 0;
        for seed in 1..4u64 {
            let img = random_gray(97, 71, seed);
            let (w, h) = (img.width, img.height);
            let f: Vec<f32> = img.data.iter().map(|&v| f32::from(v)).collect();
            let offs = circle_offsets(w);
            for t in [1u8, 7, 20, 60] {
                let mut flags = vec![0u8; w];
                for y in 3..h - 3 {
                    let mut row = vec![0u8; w];
                    fast_row(&img.data, w, y, 3, w - 3, t, &offs, &mut flags, &mut row);
                    for x in 3..w - 3 {
                        let want = reference_fast_score(&f, w, x, y, f32::from(t));
                        let direct = fast_score_u8(&img.data, &offs, y * w + x, t);
                        assert_eq!(f32::from(direct), want, "({x}, {y}) t={t}");
                        assert_eq!(row[x], direct, "row path ({x}, {y}) t={t}");
                        corners += usize::from(direct > 0);
                    }
                }
            }
        }
        assert!(
            corners > 1000,
            "only {corners} corners: the test image is too plain"
        );
    }

    #[test]
    fn harris_response_orders_corner_edge_and_flat() {
        let w = 40;
        let square = |contrast: u8| {
            let mut data = vec![60u8; w * w];
            for y in 20..w {
                for x in 20..w {
                    data[y * w + x] = 60 + contrast;
                }
            }
            Gray {
                width: w,
                height: w,
                data,
            }
        };
        let strong = square(150);
        let weak = square(30);
        let corner = harris_response(&strong, 20, 20);
        assert!(corner > 0.0);
        assert!(corner > harris_response(&weak, 20, 20) && harris_response(&weak, 20, 20) > 0.0);
        assert!(
            harris_response(&strong, 20, 30) < 0.0,
            "an edge scores below zero"
        );
        assert_eq!(harris_response(&strong, 8, 8), 0.0, "flat");
    }

    #[test]
    fn harris_ranking_keeps_the_strongest_corners() {
        // A 6x6 grid of squares; the even ones have 5x the contrast of the odd ones, and the
        // budget is the number of corners of the strong squares.
        let (w, h) = (260usize, 260usize);
        let mut data = vec![100u8; w * h];
        let mut strong_squares = Vec::new();
        for gy in 0..6 {
            for gx in 0..6 {
                let (x0, y0) = (40 + gx * 30, 40 + gy * 30);
                let strong = (gx + gy) % 2 == 0;
                let v = if strong { 200 } else { 130 };
                for y in y0..y0 + 12 {
                    for x in x0..x0 + 12 {
                        data[y * w + x] = v;
                    }
                }
                if strong {
                    strong_squares.push((x0, y0));
                }
            }
        }
        let img = Gray {
            width: w,
            height: h,
            data,
        };
        let all = fast_corners(&img, 20, EDGE_THRESHOLD, 1.0, None);
        let near_strong = |c: &Candidate| {
            strong_squares
                .iter()
                .any(|&(x0, y0)| c.x + 3 >= x0 && c.x <= x0 + 14 && c.y + 3 >= y0 && c.y <= y0 + 14)
        };
        let n_strong = all.iter().filter(|c| near_strong(c)).count();
        assert!(
            n_strong >= 4 * strong_squares.len(),
            "{n_strong} strong corners"
        );
        assert!(all.len() > n_strong, "the weak squares have corners too");
        let kept = detect_level(&img, 1.0, n_strong, &OrbParams::default(), None);
        assert_eq!(kept.len(), n_strong);
        assert!(
            kept.iter().all(near_strong),
            "a weak corner displaced a strong one"
        );
        // Sorted by decreasing Harris response.
        assert!(kept.windows(2).all(|p| p[0].harris >= p[1].harris));
    }

    #[test]
    fn blur_and_resize_match_floating_point_references() {
        let img = random_gray(83, 61, 7);
        let (w, h) = (img.width, img.height);
        let flat = Gray {
            width: w,
            height: h,
            data: vec![77; w * h],
        };
        assert!(gaussian_blur7(&flat).data.iter().all(|&v| v == 77));
        assert!(resize_bilinear(&flat, 50, 40).data.iter().all(|&v| v == 77));
        // Blur against a separable f64 Gaussian with the same border.
        let g: Vec<f64> = (-3..=3)
            .map(|d: i32| (-f64::from(d * d) / 8.0).exp())
            .collect();
        let gs: f64 = g.iter().sum();
        let blurred = gaussian_blur7(&img);
        let px = |x: isize, y: isize| f64::from(img.data[reflect101(y, h) * w + reflect101(x, w)]);
        for y in 0..h as isize {
            for x in 0..w as isize {
                let mut acc = 0.0;
                for (j, gj) in g.iter().enumerate() {
                    for (i, gi) in g.iter().enumerate() {
                        acc += gi * gj * px(x + i as isize - 3, y + j as isize - 3);
                    }
                }
                let got = f64::from(blurred.data[y as usize * w + x as usize]);
                assert!((got - acc / (gs * gs)).abs() <= 1.5, "blur ({x}, {y})");
            }
        }
        // Resize against f64 bilinear with aligned pixel centres.
        let (rw, rh) = (57usize, 43usize);
        let small = resize_bilinear(&img, rw, rh);
        for y in 0..rh {
            for x in 0..rw {
                let fx = ((x as f64 + 0.5) * w as f64 / rw as f64 - 0.5).clamp(0.0, (w - 1) as f64);
                let fy = ((y as f64 + 0.5) * h as f64 / rh as f64 - 0.5).clamp(0.0, (h - 1) as f64);
                let (x0, y0) = (fx.floor() as isize, fy.floor() as isize);
                let (tx, ty) = (fx - x0 as f64, fy - y0 as f64);
                let x1 = (x0 + 1).min(w as isize - 1);
                let y1 = (y0 + 1).min(h as isize - 1);
                let want = (px(x0, y0) * (1.0 - tx) + px(x1, y0) * tx) * (1.0 - ty)
                    + (px(x0, y1) * (1.0 - tx) + px(x1, y1) * tx) * ty;
                let got = f64::from(small.data[y * rw + x]);
                assert!(
                    (got - want).abs() <= 1.5,
                    "resize ({x}, {y}): {got} vs {want}"
                );
            }
        }
    }

    #[test]
    fn orientation_disc_is_opencvs() {
        assert_eq!(
            disc_umax(),
            [15, 15, 15, 15, 14, 14, 14, 13, 13, 12, 11, 10, 9, 8, 6, 3]
        );
    }

    #[test]
    fn unrotated_brief_is_the_plain_pattern_test() {
        let img = random_gray(64, 64, 11);
        let (x, y) = (30usize, 33usize);
        let d = brief(&img, x, y, 0.0);
        for (i, p) in ORB_PATTERN.iter().enumerate() {
            let at = |dx: i8, dy: i8| {
                img.data[(y as isize + isize::from(dy)) as usize * 64
                    + (x as isize + isize::from(dx)) as usize]
            };
            assert_eq!(d.bit(i), at(p[0], p[1]) < at(p[2], p[3]), "bit {i}");
        }
    }

    #[test]
    fn extraction_is_deterministic_and_independent_of_the_thread_count() {
        let g = random_gray(320, 240, 5);
        let img = g.to_f32();
        let params = OrbParams {
            n_features: 500,
            ..Default::default()
        };
        let a = extract_orb(&img, None, &params).unwrap();
        let b = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap()
            .install(|| extract_orb(&img, None, &params).unwrap());
        assert!(a.len() > 300, "{} keypoints", a.len());
        assert_eq!(a.keypoints, b.keypoints);
        assert_eq!(a.descriptors, b.descriptors);
        let spread = OrbParams {
            distribute: true,
            ..params
        };
        let c = extract_orb(&img, None, &spread).unwrap();
        assert!(c.len() > 300);
        assert_ne!(c.keypoints, a.keypoints, "the grid selects differently");
    }

    #[test]
    fn pattern_points_stay_inside_the_border() {
        for p in ORB_PATTERN.iter() {
            for &c in p {
                assert!(i32::from(c).abs() <= 13);
            }
        }
    }
}
