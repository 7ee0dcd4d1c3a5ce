//! ORB features (Rublee et al. 2011) as used by ORB-SLAM: an image pyramid (8 levels, scale
//! 1.2), FAST-9 corners spread evenly over each level by a grid of cells with a per-cell
//! adaptive threshold, orientation by intensity centroid, and rotated BRIEF 256-bit
//! descriptors with the learned sampling pattern of [`super::pattern`].
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
    /// FAST score: the largest intensity threshold at which it is still a corner.
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

/// ORB extraction parameters (defaults as ORB-SLAM).
#[derive(Clone, Debug, PartialEq)]
pub struct OrbParams {
    /// Target number of keypoints over all levels.
    pub n_features: usize,
    /// Number of pyramid levels.
    pub n_levels: usize,
    /// Scale between consecutive levels (> 1).
    pub scale_factor: f64,
    /// FAST threshold tried first in every cell (intensity units, `[0, 255]` scale).
    pub initial_threshold: f32,
    /// Lower FAST threshold used in cells where the initial one finds nothing.
    pub min_threshold: f32,
    /// Approximate cell size in level pixels.
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

/// Bilinear resampling to `w x h` with pixel centres aligned (`src = (dst + 0.5) * s - 0.5`).
fn resize_bilinear(src: &ImageF32, w: usize, h: usize) -> ImageF32 {
    let sx = src.width as f32 / w as f32;
    let sy = src.height as f32 / h as f32;
    let mut out = vec![0.0f32; w * h];
    let xs: Vec<(usize, usize, f32)> = (0..w)
        .map(|x| {
            let fx = ((x as f32 + 0.5) * sx - 0.5).clamp(0.0, (src.width - 1) as f32);
            let x0 = fx.floor() as usize;
            let x1 = (x0 + 1).min(src.width - 1);
            (x0, x1, fx - x0 as f32)
        })
        .collect();
    out.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        let fy = ((y as f32 + 0.5) * sy - 0.5).clamp(0.0, (src.height - 1) as f32);
        let y0 = fy.floor() as usize;
        let y1 = (y0 + 1).min(src.height - 1);
        let ty = fy - y0 as f32;
        let r0 = &src.data[y0 * src.width..(y0 + 1) * src.width];
        let r1 = &src.data[y1 * src.width..(y1 + 1) * src.width];
        for (o, &(x0, x1, tx)) in row.iter_mut().zip(xs.iter()) {
            let a = r0[x0] + (r0[x1] - r0[x0]) * tx;
            let b = r1[x0] + (r1[x1] - r1[x0]) * tx;
            *o = a + (b - a) * ty;
        }
    });
    ImageF32 {
        width: w,
        height: h,
        data: out,
    }
}

/// 7x7 Gaussian blur with sigma 2 (as OpenCV's ORB before BRIEF), reflected borders.
fn gaussian_blur7(img: &ImageF32) -> ImageF32 {
    let mut k = [0.0f32; 7];
    for (i, ki) in k.iter_mut().enumerate() {
        let d = i as f32 - 3.0;
        *ki = (-d * d / 8.0).exp();
    }
    let s: f32 = k.iter().sum();
    k.iter_mut().for_each(|v| *v /= s);
    let (w, h) = (img.width, img.height);
    let reflect = |i: i64, n: usize| -> usize {
        let n = n as i64;
        let mut i = i;
        if i < 0 {
            i = -i - 1;
        }
        if i >= n {
            i = 2 * n - i - 1;
        }
        i.clamp(0, n - 1) as usize
    };
    let mut tmp = vec![0.0f32; w * h];
    tmp.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        let src = &img.data[y * w..(y + 1) * w];
        for (x, o) in row.iter_mut().enumerate() {
            let mut acc = 0.0;
            if x >= 3 && x + 3 < w {
                for (j, kj) in k.iter().enumerate() {
                    acc += kj * src[x + j - 3];
                }
            } else {
                for (j, kj) in k.iter().enumerate() {
                    acc += kj * src[reflect(x as i64 + j as i64 - 3, w)];
                }
            }
            *o = acc;
        }
    });
    let mut out = vec![0.0f32; w * h];
    out.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        let rows: [usize; 7] = std::array::from_fn(|j| reflect(y as i64 + j as i64 - 3, h));
        for (x, o) in row.iter_mut().enumerate() {
            let mut acc = 0.0;
            for (j, kj) in k.iter().enumerate() {
                acc += kj * tmp[rows[j] * w + x];
            }
            *o = acc;
        }
    });
    ImageF32 {
        width: w,
        height: h,
        data: out,
    }
}

/// FAST-9 score of pixel `(x, y)` (needs a 3-pixel border): the largest threshold `t` such that
/// 9 contiguous circle pixels are all brighter than `p + t` or all darker than `p - t`; values
/// `<= min_t` are returned as 0 (not a corner at `min_t`).
#[inline]
fn fast_score(img: &[f32], w: usize, offs: &[isize; 16], x: usize, y: usize, min_t: f32) -> f32 {
    let c = y * w + x;
    let p = img[c];
    let at = |k: usize| img[(c as isize + offs[k]) as usize];
    // Quick rejection: an arc of 9 contains at least two of the four compass pixels.
    let (v0, v4, v8, v12) = (at(0), at(4), at(8), at(12));
    let bright = [v0, v4, v8, v12].iter().filter(|&&v| v > p + min_t).count();
    let dark = [v0, v4, v8, v12].iter().filter(|&&v| v < p - min_t).count();
    if bright < 2 && dark < 2 {
        return 0.0;
    }
    let mut d = [0.0f32; 25];
    for k in 0..16 {
        d[k] = at(k) - p;
    }
    for k in 16..25 {
        d[k] = d[k - 16];
    }
    let mut best_b = f32::MIN;
    let mut best_d = f32::MIN;
    for s in 0..16 {
        let mut mn = f32::MAX;
        let mut mx = f32::MIN;
        for &v in &d[s..s + 9] {
            mn = mn.min(v);
            mx = mx.max(v);
        }
        best_b = best_b.max(mn);
        best_d = best_d.max(-mx);
    }
    let s = best_b.max(best_d);
    if s > min_t {
        s
    } else {
        0.0
    }
}

/// Intensity-centroid orientation over the radius-15 disc at integer pixel `(x, y)`.
fn ic_angle(img: &ImageF32, x: usize, y: usize, umax: &[i32; 16]) -> f32 {
    let w = img.width as isize;
    let c = (y * img.width + x) as isize;
    let (mut m01, mut m10) = (0.0f32, 0.0f32);
    for u in -HALF_PATCH..=HALF_PATCH {
        m10 += u as f32 * img.data[(c + u as isize) as usize];
    }
    for v in 1..=HALF_PATCH {
        let d = umax[v as usize];
        let mut v_sum = 0.0f32;
        for u in -d..=d {
            let plus = img.data[(c + u as isize + v as isize * w) as usize];
            let minus = img.data[(c + u as isize - v as isize * w) as usize];
            v_sum += plus - minus;
            m10 += u as f32 * (plus + minus);
        }
        m01 += v as f32 * v_sum;
    }
    m01.atan2(m10)
}

/// Rotated-BRIEF descriptor at integer pixel `(x, y)` of the blurred level image.
fn brief(img: &ImageF32, x: usize, y: usize, angle: f32) -> Descriptor {
    let (s, c) = angle.sin_cos();
    let w = img.width as isize;
    let centre = (y * img.width + x) as isize;
    let get = |px: i8, py: i8| -> f32 {
        let (px, py) = (f32::from(px), f32::from(py));
        let rx = (px * c - py * s).round() as isize;
        let ry = (px * s + py * c).round() as isize;
        img.data[(centre + ry * w + rx) as usize]
    };
    let mut d = [0u64; 4];
    for (i, p) in ORB_PATTERN.iter().enumerate() {
        if get(p[0], p[1]) < get(p[2], p[3]) {
            d[i / 64] |= 1u64 << (i % 64);
        }
    }
    Descriptor(d)
}

struct Candidate {
    x: usize,
    y: usize,
    score: f32,
}

/// Detects FAST corners on one level and spreads `budget` of them over a grid of cells.
fn detect_level(
    img: &ImageF32,
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
    let offs: [isize; 16] =
        std::array::from_fn(|k| CIRCLE[k].1 as isize * w as isize + CIRCLE[k].0 as isize);
    let min_t = params.min_threshold;
    // Score map over the keypoint region (plus one pixel for non-maximum suppression).
    let (x0, x1, y0, y1) = (e - 1, w - e + 1, e - 1, h - e + 1);
    let mut score = vec![0.0f32; w * h];
    score[y0 * w..y1 * w]
        .par_chunks_mut(w)
        .enumerate()
        .for_each(|(r, row)| {
            let y = y0 + r;
            for x in x0..x1 {
                row[x] = fast_score(&img.data, w, &offs, x, y, min_t);
            }
        });
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
    // Cells over the keypoint region [e, w - e) x [e, h - e).
    let (rw, rh) = (w - 2 * e, h - 2 * e);
    let ncx = (rw / params.cell_size.max(1)).max(1);
    let ncy = (rh / params.cell_size.max(1)).max(1);
    let cells: Vec<Vec<Candidate>> = (0..ncx * ncy)
        .into_par_iter()
        .map(|ci| {
            let (cx, cy) = (ci % ncx, ci / ncx);
            let (xa, xb) = (e + cx * rw / ncx, e + (cx + 1) * rw / ncx);
            let (ya, yb) = (e + cy * rh / ncy, e + (cy + 1) * rh / ncy);
            let mut found = Vec::new();
            for y in ya..yb {
                for x in xa..xb {
                    let s = score[y * w + x];
                    if s <= 0.0 {
                        continue;
                    }
                    // 3x3 non-maximum suppression (ties broken towards the later pixel).
                    let mut is_max = true;
                    'n: for dy in 0..3 {
                        for dx in 0..3 {
                            if dx == 1 && dy == 1 {
                                continue;
                            }
                            let o = score[(y + dy - 1) * w + x + dx - 1];
                            if o > s || (o == s && (dy > 1 || (dy == 1 && dx > 1))) {
                                is_max = false;
                                break 'n;
                            }
                        }
                    }
                    if is_max && mask_ok(x, y) {
                        found.push(Candidate { x, y, score: s });
                    }
                }
            }
            // Adaptive threshold: keep the strong corners if the cell has any.
            if found.iter().any(|c| c.score > params.initial_threshold) {
                found.retain(|c| c.score > params.initial_threshold);
            }
            found.sort_by(|a, b| b.score.total_cmp(&a.score));
            found
        })
        .collect();
    // Round-robin over cells by rank, so every cell gets its best corners first.
    let mut out = Vec::with_capacity(budget);
    let max_rank = cells.iter().map(Vec::len).max().unwrap_or(0);
    for rank in 0..max_rank {
        let mut tier: Vec<Candidate> = Vec::new();
        for c in cells.iter() {
            if rank < c.len() {
                let cand = &c[rank];
                tier.push(Candidate {
                    x: cand.x,
                    y: cand.y,
                    score: cand.score,
                });
            }
        }
        if out.len() + tier.len() > budget {
            tier.sort_by(|a, b| b.score.total_cmp(&a.score));
            tier.truncate(budget - out.len());
        }
        out.extend(tier);
        if out.len() >= budget {
            break;
        }
    }
    out
}

/// The image pyramid: level 0 is the image, level `l` is `1 / scale^l` of its size.
pub fn build_pyramid(image: &ImageF32, params: &OrbParams) -> Vec<ImageF32> {
    let mut levels = vec![image.clone()];
    for l in 1..params.n_levels {
        let s = params.scale_factor.powi(l as i32);
        let w = (image.width as f64 / s).round() as usize;
        let h = (image.height as f64 / s).round() as usize;
        if w < 2 * EDGE_THRESHOLD + 1 || h < 2 * EDGE_THRESHOLD + 1 {
            break;
        }
        let prev = &levels[l - 1];
        let next = resize_bilinear(prev, w, h);
        levels.push(next);
    }
    levels
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
    let pyramid = build_pyramid(image, params);
    let n_levels = pyramid.len();
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

    let mut umax = [0i32; 16];
    for (v, u) in umax.iter_mut().enumerate() {
        *u = ((225.0 - (v * v) as f64).sqrt()).round() as i32;
    }

    let per_level: Vec<(Vec<KeyPoint>, Vec<Descriptor>)> = pyramid
        .par_iter()
        .enumerate()
        .map(|(l, img)| {
            let scale = params.scale_factor.powi(l as i32);
            let cands = detect_level(img, scale, budgets[l], params, mask);
            let blurred = gaussian_blur7(img);
            let mut kps = Vec::with_capacity(cands.len());
            let mut descs = Vec::with_capacity(cands.len());
            for c in cands {
                let angle = ic_angle(img, c.x, c.y, &umax);
                descs.push(brief(&blurred, c.x, c.y, angle));
                kps.push(KeyPoint {
                    uv: DVec2::new(
                        (c.x as f64 + 0.5) * scale - 0.5,
                        (c.y as f64 + 0.5) * scale - 0.5,
                    ),
                    level: l as u8,
                    angle,
                    score: c.score,
                    size: (31.0 * scale) as f32,
                });
            }
            (kps, descs)
        })
        .collect();
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
        let mut img = ImageF32::filled(w, w, 50.0);
        for y in 32..w {
            for x in 32..w {
                img.data[y * w + x] = 200.0;
            }
        }
        let offs: [isize; 16] =
            std::array::from_fn(|k| CIRCLE[k].1 as isize * w as isize + CIRCLE[k].0 as isize);
        assert!(fast_score(&img.data, w, &offs, 32, 32, 7.0) > 100.0);
        assert_eq!(fast_score(&img.data, w, &offs, 10, 10, 7.0), 0.0);
        assert_eq!(
            fast_score(&img.data, w, &offs, 45, 32, 7.0),
            0.0,
            "straight edge is not a corner"
        );
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
