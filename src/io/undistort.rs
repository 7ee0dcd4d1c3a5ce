//! Undistortion of raw images through a precomputed remap table.
//!
//! The output image has the same size and intrinsics (`fx fy cx cy`) as the raw one, without
//! distortion: output pixel `(u, v)` back-projects to normalised coordinates
//! `n = ((u - cx) / fx, (v - cy) / fy)`, which the Brown-Conrady model maps to the raw pixel
//! `(fx d.x + cx, fy d.y + cy)` with `d = distort(n)`. Intensity is resampled bilinearly
//! (border pixels replicated), depth by nearest neighbour (no measurement outside the raw image),
//! so inverse depths are never blended across depth edges.

use glam::DVec2;
use rayon::prelude::*;

use crate::camera::PinholeCamera;
use crate::image::ImageF32;

/// Rows of the output per parallel task: a frame's remap is a few milliseconds of work, which
/// a tracking thread would otherwise wait for alone.
const ROWS_PER_TASK: usize = 32;

/// One bilinear tap: top-left source index and the fractional offsets.
#[derive(Clone, Copy, Debug)]
struct Tap {
    index: u32,
    wx: f32,
    wy: f32,
}

/// A remap table from undistorted output pixels to raw source pixels.
#[derive(Clone)]
pub struct UndistortMap {
    width: usize,
    height: usize,
    bilinear: Vec<Tap>,
    nearest: Vec<u32>,
}

impl std::fmt::Debug for UndistortMap {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "UndistortMap({} x {})", self.width, self.height)
    }
}

/// Marks an output pixel whose nearest raw pixel lies outside the image.
const OUTSIDE: u32 = u32::MAX;

impl UndistortMap {
    /// Builds the table for `camera` (its `width x height`, intrinsics and distortion).
    pub fn new(camera: &PinholeCamera) -> Self {
        let (w, h) = (camera.width as usize, camera.height as usize);
        let mut bilinear = Vec::with_capacity(w * h);
        let mut nearest = Vec::with_capacity(w * h);
        let d = camera.distortion;
        for v in 0..h {
            for u in 0..w {
                let n = DVec2::new(
                    (u as f64 - camera.cx) / camera.fx,
                    (v as f64 - camera.cy) / camera.fy,
                );
                let p = d.distort(n);
                let (sx, sy) = (camera.fx * p.x + camera.cx, camera.fy * p.y + camera.cy);
                bilinear.push(bilinear_tap(sx, sy, w, h));
                let (rx, ry) = (sx.round(), sy.round());
                let inside = rx >= 0.0 && ry >= 0.0 && rx <= (w - 1) as f64 && ry <= (h - 1) as f64;
                nearest.push(if inside {
                    (ry as usize * w + rx as usize) as u32
                } else {
                    OUTSIDE
                });
            }
        }
        Self {
            width: w,
            height: h,
            bilinear,
            nearest,
        }
    }

    /// Image width the table was built for, pixels.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Image height the table was built for, pixels.
    pub fn height(&self) -> usize {
        self.height
    }

    /// The table as the WGSL kernel (`shaders/undistort.wgsl`) reads it, one entry per
    /// output pixel in row-major order: `[top-left bilinear source index, x weight as f32
    /// bits, y weight as f32 bits, nearest source index or u32::MAX when outside]`.
    pub fn gpu_table(&self) -> Vec<[u32; 4]> {
        self.bilinear
            .iter()
            .zip(&self.nearest)
            .map(|(t, &n)| [t.index, t.wx.to_bits(), t.wy.to_bits(), n])
            .collect()
    }

    /// Bilinear resampling of a raw intensity image (`width * height` values) into `out`.
    ///
    /// Both slices must have `width * height` elements; shorter ones leave the rest of `out`
    /// untouched (no panic).
    pub fn remap_bilinear(&self, raw: &[f32], out: &mut [f32]) {
        let w = self.width;
        if raw.len() < w * self.height || w == 0 {
            return;
        }
        let step_x = usize::from(w > 1);
        let step_y = if self.height > 1 { w } else { 0 };
        let band = w * ROWS_PER_TASK;
        out.par_chunks_mut(band)
            .zip(self.bilinear.par_chunks(band))
            .for_each(|(out, taps)| {
                for (o, t) in out.iter_mut().zip(taps) {
                    let i = t.index as usize;
                    // One bounds check for the four taps.
                    let Some(p) = raw.get(i..=i + step_y + step_x) else {
                        continue;
                    };
                    let (a, b) = (p[0], p[step_x]);
                    let (c, d) = (p[step_y], p[step_y + step_x]);
                    let top = a + (b - a) * t.wx;
                    let bottom = c + (d - c) * t.wx;
                    *o = top + (bottom - top) * t.wy;
                }
            });
    }

    /// Bilinear resampling of interleaved 8-bit RGB (`3` bytes per pixel), the arithmetic of
    /// [`Self::remap_bilinear`] per channel, rounded half up to the nearest byte. One pass
    /// reads each tap once for the three channels. Does nothing when `raw` or `out` is smaller
    /// than the table's image.
    pub(crate) fn remap_bilinear_rgb8(&self, raw: &[u8], out: &mut [u8]) {
        let w = self.width;
        let n = w * self.height;
        if raw.len() < 3 * n || out.len() < 3 * n || w == 0 {
            return;
        }
        let step_x = 3 * usize::from(w > 1);
        let step_y = if self.height > 1 { 3 * w } else { 0 };
        let band = w * ROWS_PER_TASK;
        out[..3 * n]
            .par_chunks_mut(3 * band)
            .zip(self.bilinear.par_chunks(band))
            .for_each(|(out, taps)| {
                for (o, t) in out.chunks_exact_mut(3).zip(taps) {
                    let i = 3 * t.index as usize;
                    // One bounds check for the four taps' three channels.
                    let Some(p) = raw.get(i..i + step_y + step_x + 3) else {
                        continue;
                    };
                    for (ch, o) in o.iter_mut().enumerate() {
                        let at = |k: usize| f32::from(p[k + ch]);
                        let (a, b) = (at(0), at(step_x));
                        let (c, d) = (at(step_y), at(step_y + step_x));
                        let top = a + (b - a) * t.wx;
                        let bottom = c + (d - c) * t.wx;
                        // A saturating cast: the blend of bytes stays within 0..=255 up to
                        // rounding.
                        *o = (top + (bottom - top) * t.wy + 0.5) as u8;
                    }
                }
            });
    }

    /// Nearest-neighbour resampling (for depth); pixels that map outside the raw image get `0`.
    pub fn remap_nearest(&self, raw: &[f32], out: &mut [f32]) {
        let band = self.width.max(1) * ROWS_PER_TASK;
        out.par_chunks_mut(band)
            .zip(self.nearest.par_chunks(band))
            .for_each(|(out, nearest)| {
                for (o, &i) in out.iter_mut().zip(nearest) {
                    *o = if i == OUTSIDE {
                        0.0
                    } else {
                        raw.get(i as usize).copied().unwrap_or(0.0)
                    };
                }
            });
    }

    /// Undistorts an intensity image (bilinear); `None` if its size is not the table's.
    pub fn intensity(&self, raw: &ImageF32) -> Option<ImageF32> {
        if raw.width != self.width || raw.height != self.height {
            return None;
        }
        let mut out = vec![0.0; raw.data.len()];
        self.remap_bilinear(&raw.data, &mut out);
        ImageF32::from_vec(raw.width, raw.height, out)
    }

    /// Undistorts an inverse-depth image (nearest neighbour); `None` if its size is not the
    /// table's.
    pub fn inverse_depth(&self, raw: &ImageF32) -> Option<ImageF32> {
        if raw.width != self.width || raw.height != self.height {
            return None;
        }
        let mut out = vec![0.0; raw.data.len()];
        self.remap_nearest(&raw.data, &mut out);
        ImageF32::from_vec(raw.width, raw.height, out)
    }
}

/// The bilinear tap for source position `(sx, sy)`, clamped to the image (border replicated).
fn bilinear_tap(sx: f64, sy: f64, w: usize, h: usize) -> Tap {
    let clamp = |s: f64, n: usize| -> (usize, f32) {
        if n < 2 {
            return (0, 0.0);
        }
        let s = s.clamp(0.0, (n - 1) as f64);
        let i = (s.floor() as usize).min(n - 2);
        (i, (s - i as f64) as f32)
    };
    let (x0, wx) = clamp(sx, w);
    let (y0, wy) = clamp(sy, h);
    Tap {
        index: (y0 * w + x0) as u32,
        wx,
        wy,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::BrownConrady;

    fn fr1_small() -> PinholeCamera {
        let mut c = PinholeCamera::new(129.3, 129.1, 79.6, 63.8, 160, 120);
        c.distortion = BrownConrady {
            k1: 0.2624,
            k2: -0.9531,
            p1: -0.0054,
            p2: 0.0026,
            k3: 1.1633,
        };
        c
    }

    #[test]
    fn zero_distortion_is_identity() {
        let cam = PinholeCamera::new(100.0, 100.0, 31.5, 23.5, 64, 48);
        let m = UndistortMap::new(&cam);
        let raw =
            ImageF32::from_vec(64, 48, (0..64 * 48).map(|i| (i % 251) as f32).collect()).unwrap();
        assert_eq!(m.intensity(&raw).unwrap(), raw);
        assert_eq!(m.inverse_depth(&raw).unwrap(), raw);
    }

    #[test]
    fn linear_ramp_is_resampled_exactly_at_distorted_positions() {
        // A raw image that is linear in x is reproduced exactly by bilinear interpolation, so
        // the output must equal the raw x coordinate of each output pixel's distorted position.
        let cam = fr1_small();
        let m = UndistortMap::new(&cam);
        let (w, h) = (160usize, 120usize);
        let raw = ImageF32::from_vec(w, h, (0..w * h).map(|i| (i % w) as f32).collect()).unwrap();
        let out = m.intensity(&raw).unwrap();
        let mut checked = 0;
        for v in (0..h).step_by(7) {
            for u in (0..w).step_by(5) {
                let n = DVec2::new((u as f64 - cam.cx) / cam.fx, (v as f64 - cam.cy) / cam.fy);
                let p = cam.distortion.distort(n);
                let (sx, sy) = (cam.fx * p.x + cam.cx, cam.fy * p.y + cam.cy);
                if (0.0..=(w - 1) as f64).contains(&sx) && (0.0..=(h - 1) as f64).contains(&sy) {
                    assert!((f64::from(out.at(u, v)) - sx).abs() < 1e-3, "{u} {v}");
                    checked += 1;
                }
            }
        }
        assert!(checked > 200);
        // The distortion is not negligible: some pixel moves by more than one pixel.
        assert!(out
            .data
            .iter()
            .zip(&raw.data)
            .any(|(a, b)| (a - b).abs() > 1.0));
    }

    #[test]
    fn rgb_resampling_matches_the_plane_by_plane_resampling() {
        let cam = fr1_small();
        let map = UndistortMap::new(&cam);
        let (w, h) = (cam.width as usize, cam.height as usize);
        let rgb: Vec<u8> = (0..3 * w * h)
            .map(|k| ((k * 37 + (k / (3 * w)) * 11) % 256) as u8)
            .collect();
        let mut out = vec![0u8; 3 * w * h];
        map.remap_bilinear_rgb8(&rgb, &mut out);
        let (mut plane, mut resampled) = (vec![0.0f32; w * h], vec![0.0f32; w * h]);
        for ch in 0..3 {
            for (p, px) in plane.iter_mut().zip(rgb.chunks_exact(3)) {
                *p = f32::from(px[ch]);
            }
            map.remap_bilinear(&plane, &mut resampled);
            for (k, v) in resampled.iter().enumerate() {
                assert_eq!(
                    out[3 * k + ch],
                    v.round().clamp(0.0, 255.0) as u8,
                    "pixel {k} channel {ch} (value {v})"
                );
            }
        }
    }

    #[test]
    fn depth_is_never_blended() {
        let cam = fr1_small();
        let m = UndistortMap::new(&cam);
        let raw = ImageF32::from_vec(
            160,
            120,
            (0..160 * 120)
                .map(|i| if (i % 160) < 80 { 0.5 } else { 2.0 })
                .collect(),
        )
        .unwrap();
        let out = m.inverse_depth(&raw).unwrap();
        assert!(out.data.iter().all(|&d| d == 0.0 || d == 0.5 || d == 2.0));
    }
}
