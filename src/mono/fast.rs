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

#[cfg(test)]
/// FAST-9 score at `(x, y)`: `None` when it is not a corner (fewer than 9 contiguous circle
/// pixels all brighter than `centre + t` or all darker than `centre - t`). The caller keeps
/// `(x, y)` at least 3 pixels from the border.
pub fn fast_score(img: &ImageF32, x: usize, y: usize, t: f32) -> Option<f32> {
    fast_score_at(&img.data, y * img.width + x, &circle_offsets(img.width), t)
}

/// Offsets of the 16 circle pixels from the centre in a row-major image `width` wide.
fn circle_offsets(width: usize) -> [isize; 16] {
    CIRCLE.map(|(dx, dy)| dy as isize * width as isize + dx as isize)
}

/// [`fast_score`] at index `i` of the row-major `data`, with the circle at `offs`.
#[inline(always)]
fn fast_score_at(data: &[f32], i: usize, offs: &[isize; 16], t: f32) -> Option<f32> {
    let c = data[i];
    let at = |k: usize| data[i.wrapping_add_signed(offs[k])];
    let (hi, lo) = (c + t, c - t);
    // Quick rejection: any arc of 9 contiguous circle pixels contains pixel 0 or pixel 8
    // (they are 8 apart), and at least 2 of the 4 compass points.
    let (p0, p8) = (at(0), at(8));
    if !(p0 > hi || p0 < lo || p8 > hi || p8 < lo) {
        return None;
    }
    let compass = [p0, at(4), p8, at(12)];
    let bright = compass.iter().filter(|v| **v > hi).count();
    let dark = compass.iter().filter(|v| **v < lo).count();
    if bright < 2 && dark < 2 {
        return None;
    }
    let mut vals = [0.0f32; 16];
    for (k, v) in vals.iter_mut().enumerate() {
        *v = at(k);
    }
    let mut best: Option<f32> = None;
    for sign in [1.0f32, -1.0] {
        // Bit k set when circle pixel k passes; the scoring walk below runs only when some
        // 9 contiguous bits (cyclically) are set, i.e. when it would find an arc.
        let mut bits = 0u32;
        for (k, v) in vals.iter().enumerate() {
            if sign * (*v - c) - t > 0.0 {
                bits |= 1 << k;
            }
        }
        let doubled = bits | (bits << 16);
        let mut arc = doubled;
        for shift in 1..9 {
            arc &= doubled >> shift;
        }
        if arc & 0xffff == 0 {
            continue;
        }
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
    let offs = circle_offsets(w);
    let mut candidate = vec![false; rw];
    for y in y0..y1 {
        // The compass test of `fast_score_at` for a whole row, branch-free so that it
        // vectorises; the full test runs only where it passes.
        let row = &img.data[y * w + x0..y * w + x1];
        let up = &img.data[(y - 3) * w + x0..(y - 3) * w + x1];
        let down = &img.data[(y + 3) * w + x0..(y + 3) * w + x1];
        let left = &img.data[y * w + x0 - 3..y * w + x1 - 3];
        let right = &img.data[y * w + x0 + 3..y * w + x1 + 3];
        for (k, flag) in candidate.iter_mut().enumerate() {
            let (hi, lo) = (row[k] + t, row[k] - t);
            let (p0, p4, p8, p12) = (up[k], right[k], down[k], left[k]);
            let bright =
                u8::from(p0 > hi) + u8::from(p4 > hi) + u8::from(p8 > hi) + u8::from(p12 > hi);
            let dark =
                u8::from(p0 < lo) + u8::from(p4 < lo) + u8::from(p8 < lo) + u8::from(p12 < lo);
            *flag = bright >= 2 || dark >= 2;
        }
        for (k, _) in candidate.iter().enumerate().filter(|(_, f)| **f) {
            let x = x0 + k;
            if let Some(s) = fast_score_at(&img.data, y * w + x, &offs, t) {
                if keep(x, y) {
                    score[(y - y0) * rw + k] = s;
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

    /// The plain FAST-9 score (no early rejection): both signs walked over the circle twice.
    fn reference_score(img: &ImageF32, x: usize, y: usize, t: f32) -> Option<f32> {
        let c = img.at(x, y);
        let vals: Vec<f32> = CIRCLE
            .iter()
            .map(|(dx, dy)| img.at((x as i32 + dx) as usize, (y as i32 + dy) as usize))
            .collect();
        let mut best: Option<f32> = None;
        for sign in [1.0f32, -1.0] {
            let (mut run, mut sum, mut best_sum, mut found) = (0usize, 0.0f32, 0.0f32, false);
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

    #[test]
    fn early_rejections_do_not_change_any_score() {
        // Random blocky images: many corners, many near-corners, every arc length.
        let (w, h) = (64, 48);
        let mut state = 99u32;
        let mut next = || {
            state = state.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            (state >> 8) as f32 / (1u32 << 24) as f32
        };
        let mut corners = 0;
        for round in 0..4 {
            let block = 1 + round;
            let mut img = ImageF32::filled(w, h, 0.0);
            let cells: Vec<f32> = (0..w * h).map(|_| next() * 255.0).collect();
            for y in 0..h {
                for x in 0..w {
                    img.data[y * w + x] = cells[(y / block) * w + x / block];
                }
            }
            for t in [5.0f32, 20.0, 60.0] {
                for y in 3..h - 3 {
                    for x in 3..w - 3 {
                        let want = reference_score(&img, x, y, t);
                        assert_eq!(fast_score(&img, x, y, t), want, "({x}, {y}) t {t}");
                        corners += usize::from(want.is_some());
                    }
                }
                let found = detect(&img, (0, 0, w, h), t, |_, _| true);
                assert!(found
                    .iter()
                    .all(|c| reference_score(&img, c.x, c.y, t) == Some(c.score)));
            }
        }
        assert!(corners > 1000, "{corners}");
    }

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
