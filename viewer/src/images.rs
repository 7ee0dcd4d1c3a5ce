//! Images of the library (intensity, inverse depth, segmentation) as egui colour images.

use egui::{Color32, ColorImage};
use rgbid::image::ImageF32;
use rgbid::place::PixelMatch;

use crate::worker::KeypointMark;

/// The "turbo" colour map (polynomial approximation by Google), `t` in [0, 1].
pub fn turbo(t: f32) -> Color32 {
    let t = t.clamp(0.0, 1.0);
    let t2 = t * t;
    let t3 = t2 * t;
    let t4 = t3 * t;
    let t5 = t4 * t;
    let r = 0.135_721_38 + 4.615_392_6 * t - 42.660_324 * t2 + 132.131_08 * t3 - 152.942_4 * t4
        + 59.286_38 * t5;
    let g = 0.091_402_61 + 2.194_188_4 * t + 4.842_966_6 * t2 - 14.185_034 * t3
        + 4.277_298_6 * t4
        + 2.829_566 * t5;
    let b = 0.106_673_3 + 12.641_946 * t - 60.582_05 * t2 + 110.362_77 * t3 - 89.903_11 * t4
        + 27.348_25 * t5;
    let c = |v: f32| (v.clamp(0.0, 1.0) * 255.0).round() as u8;
    Color32::from_rgb(c(r), c(g), c(b))
}

/// Grey image of intensities in [0, 255].
pub fn intensity_image(img: &ImageF32) -> ColorImage {
    let pixels = img
        .data()
        .iter()
        .map(|&v| {
            let g = v.clamp(0.0, 255.0) as u8;
            Color32::from_gray(g)
        })
        .collect();
    ColorImage::new([img.width(), img.height()], pixels)
}

/// The value below which `q` (0-1) of the positive finite values lie; `None` when there are none.
pub fn quantile_positive(values: &[f32], q: f32) -> Option<f32> {
    let mut v: Vec<f32> = values
        .iter()
        .copied()
        .filter(|x| x.is_finite() && *x > 0.0)
        .collect();
    if v.is_empty() {
        return None;
    }
    let k = ((v.len() - 1) as f32 * q.clamp(0.0, 1.0)).round() as usize;
    let (_, x, _) = v.select_nth_unstable_by(k, f32::total_cmp);
    Some(*x)
}

/// Inverse depth through the turbo map, scaled to `[0, max]` (1/m; near = red), invalid
/// (0) black. With `max = None` the 98th percentile of the valid values is used.
pub fn inverse_depth_image(img: &ImageF32, max: Option<f32>) -> ColorImage {
    let max = max
        .or_else(|| quantile_positive(img.data(), 0.98))
        .filter(|m| *m > 0.0)
        .unwrap_or(1.0);
    let pixels = img
        .data()
        .iter()
        .map(|&rho| {
            if rho > 0.0 && rho.is_finite() {
                turbo(rho / max)
            } else {
                Color32::BLACK
            }
        })
        .collect();
    ColorImage::new([img.width(), img.height()], pixels)
}

/// Signed residuals on a blue-white-red scale saturating at `+-scale` (red positive);
/// pixels without a residual (NaN) are black. With `scale = None` the 95th percentile of
/// the absolute residuals is used.
pub fn signed_image(img: &ImageF32, scale: Option<f32>) -> ColorImage {
    let abs: Vec<f32> = img.data().iter().map(|v| v.abs()).collect();
    let s = scale
        .or_else(|| quantile_positive(&abs, 0.95))
        .filter(|s| *s > 0.0)
        .unwrap_or(1.0);
    let pixels = img
        .data()
        .iter()
        .map(|&r| {
            if !r.is_finite() {
                return Color32::BLACK;
            }
            let t = (r / s).clamp(-1.0, 1.0);
            let fade = |a: f32| (255.0 * (1.0 - a)).round() as u8;
            if t >= 0.0 {
                Color32::from_rgb(255, fade(t), fade(t))
            } else {
                Color32::from_rgb(fade(-t), fade(-t), 255)
            }
        })
        .collect();
    ColorImage::new([img.width(), img.height()], pixels)
}

/// IRLS weights in [0, 1] through the turbo map (0 = blue, outliers; 1 = red); pixels
/// without a residual (NaN) are black.
pub fn weight_image(img: &ImageF32) -> ColorImage {
    let pixels = img
        .data()
        .iter()
        .map(|&w| {
            if w.is_finite() {
                turbo(w)
            } else {
                Color32::BLACK
            }
        })
        .collect();
    ColorImage::new([img.width(), img.height()], pixels)
}

/// The intensity image with each keypoint drawn as a circle (2.5 px at pyramid level 0,
/// growing with the detection scale): green where `kept`, orange where a mask drops it.
pub fn keypoints_overlay(intensity: &ImageF32, keypoints: &[KeypointMark]) -> ColorImage {
    let mut img = intensity_image(intensity);
    let (w, h) = (intensity.width() as i64, intensity.height() as i64);
    for k in keypoints {
        let colour = if k.kept {
            Color32::from_rgb(60, 230, 90)
        } else {
            Color32::from_rgb(255, 140, 30)
        };
        // 2.5 px at level 0, growing with the detection scale (31 px patch at level 0).
        let r = 2.5 * f64::from(k.size) / 31.0;
        let steps = (2.0 * std::f64::consts::PI * r).ceil().max(8.0) as usize;
        for s in 0..steps {
            let a = s as f64 / steps as f64 * std::f64::consts::TAU;
            let x = (f64::from(k.x) + r * a.cos()).round() as i64;
            let y = (f64::from(k.y) + r * a.sin()).round() as i64;
            if x >= 0 && y >= 0 && x < w && y < h {
                img.pixels[(y * w + x) as usize] = colour;
            }
        }
    }
    img
}

/// Rows of background between the query (top) and candidate (bottom) images of
/// [`loop_matches_image`], pixels.
pub const LOOP_GAP: usize = 4;

/// Where [`loop_matches_image`] draws each inlier pair: from the query keypoint (the query
/// image is on top, unmoved) to the candidate keypoint moved down by the query's height plus
/// [`LOOP_GAP`]. Pixel coordinates `(x, y)` of the stacked image, same order as `matches`.
pub fn loop_match_segments(matches: &[PixelMatch], query_height: usize) -> Vec<PixelMatch> {
    let dy = (query_height + LOOP_GAP) as f32;
    matches
        .iter()
        .map(|&(q, c)| (q, [c[0], c[1] + dy]))
        .collect()
}

/// Colour of the `i`-th of `n` loop matches (along the turbo map, so neighbours differ).
pub fn loop_match_colour(i: usize, n: usize) -> Color32 {
    turbo(0.1 + 0.8 * ((i * 7919) % n.max(1)) as f32 / n.max(1) as f32)
}

/// The query image above the candidate image ([`LOOP_GAP`] black rows between them), with a
/// line for each inlier pair and a 3x3 dot at both of its ends, in
/// [`loop_match_colour`]s. Parts of lines outside the image are left out.
pub fn loop_matches_image(
    query: &ImageF32,
    candidate: &ImageF32,
    matches: &[PixelMatch],
) -> ColorImage {
    let w = query.width().max(candidate.width());
    let h = query.height() + LOOP_GAP + candidate.height();
    let mut img = ColorImage::new([w, h], vec![Color32::BLACK; w * h]);
    for (src, y0) in [(query, 0), (candidate, query.height() + LOOP_GAP)] {
        for y in 0..src.height() {
            for x in 0..src.width() {
                let g = src.data()[y * src.width() + x].clamp(0.0, 255.0) as u8;
                img.pixels[(y0 + y) * w + x] = Color32::from_gray(g);
            }
        }
    }
    let mut put = |x: f32, y: f32, c: Color32| {
        let (x, y) = (x.round(), y.round());
        if x >= 0.0 && y >= 0.0 && (x as usize) < w && (y as usize) < h {
            img.pixels[y as usize * w + x as usize] = c;
        }
    };
    let segments = loop_match_segments(matches, query.height());
    let n = segments.len();
    for (i, (a, b)) in segments.iter().enumerate() {
        let c = loop_match_colour(i, n);
        let steps = (b[0] - a[0]).abs().max((b[1] - a[1]).abs()).ceil().max(1.0) as usize;
        for s in 0..=steps {
            let t = s as f32 / steps as f32;
            put(a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1]), c);
        }
        for p in [a, b] {
            for dy in -1..=1 {
                for dx in -1..=1 {
                    put(p[0] + dx as f32, p[1] + dy as f32, c);
                }
            }
        }
    }
    img
}

/// RGB8 row-major bytes as an image; `None` when the size does not match.
pub fn rgb_image(width: usize, height: usize, rgb: &[u8]) -> Option<ColorImage> {
    (rgb.len() == width * height * 3).then(|| ColorImage::from_rgb([width, height], rgb))
}

/// Neg-entropy of each pixel's segment through the turbo map over the intensity (half and
/// half); pixels without a segment (non-finite or zero value) show the intensity only.
pub fn neg_entropy_overlay(neg_entropy: &ImageF32, intensity: Option<&ImageF32>) -> ColorImage {
    let finite: Vec<f32> = neg_entropy
        .data()
        .iter()
        .copied()
        .filter(|v| v.is_finite())
        .collect();
    let lo = finite.iter().copied().fold(f32::INFINITY, f32::min);
    let hi = finite.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    let span = if hi > lo { hi - lo } else { 1.0 };
    let pixels = neg_entropy
        .data()
        .iter()
        .enumerate()
        .map(|(i, &v)| {
            let g = intensity
                .filter(|im| im.data().len() == neg_entropy.data().len())
                .map_or(0.0, |im| im.data()[i].clamp(0.0, 255.0));
            if v.is_finite() && v != 0.0 {
                let c = turbo((v - lo) / span);
                let mix = |a: u8| (0.5 * f32::from(a) + 0.5 * g) as u8;
                Color32::from_rgb(mix(c.r()), mix(c.g()), mix(c.b()))
            } else {
                Color32::from_gray(g as u8)
            }
        })
        .collect();
    ColorImage::new([neg_entropy.width(), neg_entropy.height()], pixels)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn turbo_runs_from_blue_to_red() {
        let a = turbo(0.15);
        let b = turbo(0.95);
        assert!(a.b() > a.r(), "{a:?}");
        assert!(b.r() > b.b(), "{b:?}");
        assert_eq!(turbo(-1.0), turbo(0.0));
        assert_eq!(turbo(2.0), turbo(1.0));
    }

    #[test]
    fn inverse_depth_invalid_is_black_and_sizes_match() {
        let img = ImageF32::from_vec(3, 2, vec![0.0, 0.5, 1.0, f32::NAN, 2.0, 0.25]).unwrap();
        let c = inverse_depth_image(&img, Some(2.0));
        assert_eq!(c.size, [3, 2]);
        assert_eq!(c.pixels[0], Color32::BLACK);
        assert_eq!(c.pixels[3], Color32::BLACK);
        assert_eq!(c.pixels[4], turbo(1.0));
        assert_eq!(quantile_positive(img.data(), 1.0), Some(2.0));
        assert_eq!(quantile_positive(&[0.0, -1.0], 0.5), None);
    }

    #[test]
    fn residual_and_weight_colours() {
        let img = ImageF32::from_vec(4, 1, vec![f32::NAN, 0.0, 2.0, -4.0]).unwrap();
        let c = signed_image(&img, Some(2.0));
        assert_eq!(c.pixels[0], Color32::BLACK);
        assert_eq!(c.pixels[1], Color32::WHITE);
        assert_eq!(c.pixels[2], Color32::from_rgb(255, 0, 0));
        assert_eq!(c.pixels[3], Color32::from_rgb(0, 0, 255));
        let w = weight_image(&ImageF32::from_vec(2, 1, vec![1.0, f32::NAN]).unwrap());
        assert_eq!(w.pixels[0], turbo(1.0));
        assert_eq!(w.pixels[1], Color32::BLACK);
    }

    #[test]
    fn keypoints_are_drawn_inside_the_image_only() {
        let img = ImageF32::from_vec(20, 20, vec![100.0; 400]).unwrap();
        let kp = [
            KeypointMark {
                x: 10.0,
                y: 10.0,
                size: 24.8,
                kept: true,
            },
            KeypointMark {
                x: 0.0,
                y: 19.0,
                size: 24.8,
                kept: false,
            },
        ];
        let c = keypoints_overlay(&img, &kp);
        assert_eq!(c.pixels[10 * 20 + 12], Color32::from_rgb(60, 230, 90));
        assert_eq!(c.pixels[10 * 20 + 10], Color32::from_gray(100));
        assert!(c.pixels.contains(&Color32::from_rgb(255, 140, 30)));
    }

    #[test]
    fn loop_matches_are_drawn_from_query_to_candidate_keypoints() {
        let q = ImageF32::from_vec(40, 30, vec![100.0; 1200]).unwrap();
        let c = ImageF32::from_vec(40, 30, vec![50.0; 1200]).unwrap();
        let matches = [([5.0, 6.0], [30.0, 20.0]), ([35.0, 25.0], [4.0, 3.0])];
        let segs = loop_match_segments(&matches, q.height());
        assert_eq!(segs[0], ([5.0, 6.0], [30.0, 20.0 + 34.0]));
        assert_eq!(segs[1], ([35.0, 25.0], [4.0, 3.0 + 34.0]));
        let img = loop_matches_image(&q, &c, &matches);
        assert_eq!(img.size, [40, 64]);
        let at = |x: usize, y: usize| img.pixels[y * 40 + x];
        for (i, (a, b)) in segs.iter().enumerate() {
            let colour = loop_match_colour(i, 2);
            assert_eq!(at(a[0] as usize, a[1] as usize), colour);
            assert_eq!(at(b[0] as usize, b[1] as usize), colour);
        }
        assert_ne!(loop_match_colour(0, 2), loop_match_colour(1, 2));
        // Images where no line passes; the gap stays black.
        assert_eq!(at(1, 28), Color32::from_gray(100));
        assert_eq!(at(38, 62), Color32::from_gray(50));
        assert_eq!(at(38, 31), Color32::BLACK);
        // Matches outside the image are clipped, not a panic.
        let far = loop_matches_image(&q, &c, &[([-50.0, 500.0], [90.0, -3.0])]);
        assert_eq!(far.size, [40, 64]);
    }

    #[test]
    fn rgb_image_checks_size() {
        assert!(rgb_image(2, 2, &[0; 12]).is_some());
        assert!(rgb_image(2, 2, &[0; 11]).is_none());
    }
}
