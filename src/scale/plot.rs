//! Minimal PNG line plots (stacked panels, hand-drawn with the `image` crate; no text).
//!
//! Each panel has its own y range (from its data, with a 5 % margin) and a shared x range;
//! light grid lines mark the x range in tenths and the panel's zero when visible.

use std::path::Path;

use image::{Rgb, RgbImage};

use super::ScaleError;

/// One line (or dot series) of a panel.
#[derive(Clone, Debug)]
pub struct Series {
    /// Points `(x, y)`; non-finite `y` breaks the line.
    pub points: Vec<(f64, f64)>,
    /// RGB colour.
    pub color: [u8; 3],
    /// Draw dots instead of a line.
    pub dots: bool,
}

fn line(img: &mut RgbImage, (x0, y0): (i64, i64), (x1, y1): (i64, i64), c: Rgb<u8>) {
    let (dx, dy) = ((x1 - x0).abs(), -(y1 - y0).abs());
    let (sx, sy) = (if x0 < x1 { 1 } else { -1 }, if y0 < y1 { 1 } else { -1 });
    let (mut x, mut y, mut err) = (x0, y0, dx + dy);
    let (w, h) = (img.width() as i64, img.height() as i64);
    for _ in 0..(dx - dy + 2) {
        if x >= 0 && y >= 0 && x < w && y < h {
            img.put_pixel(x as u32, y as u32, c);
        }
        if x == x1 && y == y1 {
            break;
        }
        let e2 = 2 * err;
        if e2 >= dy {
            err += dy;
            x += sx;
        }
        if e2 <= dx {
            err += dx;
            y += sy;
        }
    }
}

/// Writes `panels` stacked vertically into a `width x height` PNG at `path`.
pub fn plot_panels(
    path: &Path,
    panels: &[Vec<Series>],
    width: u32,
    height: u32,
) -> Result<(), ScaleError> {
    let err = |m: String| ScaleError::Plot {
        path: path.into(),
        message: m,
    };
    if panels.is_empty() || width < 50 || height < 50 * panels.len() as u32 {
        return Err(err(format!(
            "{} panels do not fit {width}x{height}",
            panels.len()
        )));
    }
    let mut img = RgbImage::from_pixel(width, height, Rgb([255, 255, 255]));
    let all = panels.iter().flatten().flat_map(|s| s.points.iter());
    let (mut xmin, mut xmax) = (f64::INFINITY, f64::NEG_INFINITY);
    for p in all.filter(|p| p.0.is_finite()) {
        xmin = xmin.min(p.0);
        xmax = xmax.max(p.0);
    }
    if !(xmax > xmin) {
        xmax = xmin + 1.0;
    }
    let ph = height / panels.len() as u32;
    let margin = 12i64;
    for (k, panel) in panels.iter().enumerate() {
        let top = (k as u32 * ph) as i64 + margin;
        let bottom = ((k as u32 + 1) * ph) as i64 - margin;
        let (left, right) = (margin * 3, width as i64 - margin);
        let (mut ymin, mut ymax) = (f64::INFINITY, f64::NEG_INFINITY);
        for p in panel
            .iter()
            .flat_map(|s| s.points.iter())
            .filter(|p| p.1.is_finite())
        {
            ymin = ymin.min(p.1);
            ymax = ymax.max(p.1);
        }
        if !(ymax > ymin) {
            ymin -= 0.5;
            ymax += 0.5;
        }
        let pad = 0.05 * (ymax - ymin);
        let (ymin, ymax) = (ymin - pad, ymax + pad);
        let to_px = |x: f64, y: f64| -> (i64, i64) {
            let u = left as f64 + (x - xmin) / (xmax - xmin) * (right - left) as f64;
            let v = bottom as f64 - (y - ymin) / (ymax - ymin) * (bottom - top) as f64;
            (u.round() as i64, v.round() as i64)
        };
        let grid = Rgb([225, 225, 225]);
        for g in 0..=10 {
            let x = xmin + (xmax - xmin) * g as f64 / 10.0;
            line(&mut img, to_px(x, ymin), to_px(x, ymax), grid);
        }
        if ymin < 0.0 && ymax > 0.0 {
            line(
                &mut img,
                to_px(xmin, 0.0),
                to_px(xmax, 0.0),
                Rgb([170, 170, 170]),
            );
        }
        let axis = Rgb([0, 0, 0]);
        line(&mut img, (left, top), (left, bottom), axis);
        line(&mut img, (left, bottom), (right, bottom), axis);
        for s in panel {
            let c = Rgb(s.color);
            let mut prev: Option<(i64, i64)> = None;
            for &(x, y) in &s.points {
                if !(x.is_finite() && y.is_finite()) {
                    prev = None;
                    continue;
                }
                let p = to_px(x, y);
                if s.dots {
                    for d in [(-1, 0), (1, 0), (0, -1), (0, 1), (0, 0)] {
                        line(&mut img, (p.0 + d.0, p.1 + d.1), (p.0 + d.0, p.1 + d.1), c);
                    }
                } else if let Some(q) = prev {
                    line(&mut img, q, p, c);
                }
                prev = Some(p);
            }
        }
    }
    img.save(path).map_err(|e| err(e.to_string()))
}
