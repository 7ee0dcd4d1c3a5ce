//! FAST-9 corners (Rosten and Drummond 2006) on an f32 intensity image, restricted to a
//! rectangle, with a corner score for picking the strongest one.

use crate::image::ImageF32;
use crate::image::FAST_CIRCLE as CIRCLE;

/// A detected corner: pixel centre and score (sum of absolute differences beyond the
/// threshold over the contiguous arc, intensity units).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Corner {
    /// Column, pixels.
    pub x: usize,
    /// Row, pixels.
    pub y: usize,
    /// Score, larger is stronger.
    pub score: f32,
}

/// FAST-9 score at `(x, y)`: `None` when it is not a corner (fewer than 9 contiguous circle
/// pixels all brighter than `centre + t` or all darker than `centre - t`). The caller keeps
/// `(x, y)` at least 3 pixels from the border.
pub fn fast_score(img: &ImageF32, x: usize, y: usize, t: f32) -> Option<f32> {
    let c = img.at(x, y);
    let at = |k: usize| {
        let (dx, dy) = CIRCLE[k];
        img.at((x as i32 + dx) as usize, (y as i32 + dy) as usize)
    };
    // Quick rejection: any arc of 9 contiguous circle pixels covers at least 2 of the 4
    // compass points.
    let compass = [at(0), at(4), at(8), at(12)];
    let bright = compass.iter().filter(|v| **v > c + t).count();
    let dark = compass.iter().filter(|v| **v < c - t).count();
    if bright < 2 && dark < 2 {
        return None;
    }
    let mut vals = [0.0f32; 16];
    for (k, v) in vals.iter_mut().enumerate() {
        *v = at(k);
    }
    let mut best: Option<f32> = None;
    for sign in [1.0f32, -1.0] {
        let mut run = 0usize;
        let mut sum = 0.0f32;
        let mut best_sum = 0.0f32;
        let mut found = false;
        // Walk the circle twice to catch arcs that wrap around.
        for k in 0..32 {
            let d = sign * (vals[k % 16] - c) - t;
            if d > 0.0 {
                run += 1;
                sum += d;
                if run >= 9 {
                    found = true;
                    best_sum = best_sum.max(sum);
                }
                if run >= 16 {
                    break;
                }
            } else {
                run = 0;
                sum = 0.0;
            }
        }
        if found {
            best = Some(best.map_or(best_sum, |b: f32| b.max(best_sum)));
        }
    }
    best
}

/// All FAST-9 corners with threshold `t` in the rectangle `[x0, x1) x [y0, y1)` (clipped to
/// 3 pixels inside the image) that pass `keep(x, y)`, with 3x3 non-maximum suppression.
pub fn detect(
    img: &ImageF32,
    rect: (usize, usize, usize, usize),
    t: f32,
    keep: impl Fn(usize, usize) -> bool,
) -> Vec<Corner> {
    let (w, h) = (img.width, img.height);
    if w < 7 || h < 7 {
        return Vec::new();
    }
    let x0 = rect.0.max(3);
    let y0 = rect.1.max(3);
    let x1 = rect.2.min(w - 3);
    let y1 = rect.3.min(h - 3);
    if x0 >= x1 || y0 >= y1 {
        return Vec::new();
    }
    let (rw, rh) = (x1 - x0, y1 - y0);
    let mut score = vec![0.0f32; rw * rh];
    for y in y0..y1 {
        for x in x0..x1 {
            if keep(x, y) {
                if let Some(s) = fast_score(img, x, y, t) {
                    score[(y - y0) * rw + x - x0] = s;
                }
            }
        }
    }
    let mut out = Vec::new();
    for j in 0..rh {
        for i in 0..rw {
            let s = score[j * rw + i];
            if s <= 0.0 {
                continue;
            }
            let mut is_max = true;
            'n: for dj in -1i32..=1 {
                for di in -1i32..=1 {
                    let (ii, jj) = (i as i32 + di, j as i32 + dj);
                    if (di, dj) == (0, 0) || ii < 0 || jj < 0 || ii >= rw as i32 || jj >= rh as i32
                    {
                        continue;
                    }
                    let o = score[jj as usize * rw + ii as usize];
                    // Ties broken by scan order so plateaus keep one corner.
                    if o > s || (o == s && (dj < 0 || (dj == 0 && di < 0))) {
                        is_max = false;
                        break 'n;
                    }
                }
            }
            if is_max {
                out.push(Corner {
                    x: x0 + i,
                    y: y0 + j,
                    score: s,
                });
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn corner_of_a_bright_square_is_found_edges_and_flat_are_not() {
        let (w, h) = (40, 40);
        let mut img = ImageF32::filled(w, h, 50.0);
        for y in 20..h {
            for x in 20..w {
                img.data[y * w + x] = 200.0;
            }
        }
        let corners = detect(&img, (0, 0, w, h), 20.0, |_, _| true);
        assert!(!corners.is_empty());
        assert!(corners
            .iter()
            .all(|c| (c.x as i32 - 20).abs() <= 2 && (c.y as i32 - 20).abs() <= 2));
        // A straight edge only.
        let mut edge = ImageF32::filled(w, h, 50.0);
        for y in 0..h {
            for x in 20..w {
                edge.data[y * w + x] = 200.0;
            }
        }
        assert!(detect(&edge, (0, 0, w, h), 20.0, |_, _| true).is_empty());
        assert!(
            detect(&ImageF32::filled(w, h, 9.0), (0, 0, w, h), 20.0, |_, _| {
                true
            })
            .is_empty()
        );
        // The keep mask is honoured.
        assert!(detect(&img, (0, 0, w, h), 20.0, |x, _| x < 10).is_empty());
    }
}
