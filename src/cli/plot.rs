//! PNG plots of the CLI (`rgbid eval --plot`, `rgbid scale --plot`): a grid of panels, each
//! with axes, tick labels, axis descriptions, a title and a legend, drawn with `plotters` into
//! an RGB buffer and written as PNG through `image`.
//!
//! Text needs a TrueType font: `RGBID_FONT` names one, otherwise the first of a few common
//! system fonts (DejaVu Sans, Liberation Sans, Arial) is read once per process. No fontconfig
//! is linked, so the binary builds on machines without its development files.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use anyhow::{anyhow, bail, Context, Result};
use plotters::prelude::*;

/// The family name plot text is registered under.
const FAMILY: &str = "sans-serif";

/// Fonts tried, in order, when `RGBID_FONT` is not set.
const SYSTEM_FONTS: &[&str] = &[
    "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/TTF/DejaVuSans.ttf",
    "/usr/share/fonts/dejavu/DejaVuSans.ttf",
    "/usr/share/fonts/dejavu-sans-fonts/DejaVuSans.ttf",
    "/usr/share/fonts/truetype/liberation/LiberationSans-Regular.ttf",
    "/usr/share/fonts/liberation-sans/LiberationSans-Regular.ttf",
    "/Library/Fonts/Arial.ttf",
    "/System/Library/Fonts/Supplemental/Arial.ttf",
    "C:\\Windows\\Fonts\\arial.ttf",
];

/// Blue of estimates.
pub const BLUE: RGBColor = RGBColor(30, 80, 200);
/// Red of ground truth in scale plots.
pub const RED: RGBColor = RGBColor(200, 40, 40);
/// Near-black of ground truth in trajectory plots.
pub const DARK: RGBColor = RGBColor(40, 40, 40);

/// One line or dot series of a panel.
#[derive(Clone, Debug)]
pub struct Series {
    /// Legend entry (empty: none).
    pub label: String,
    /// Points `(x, y)` in the panel's units; a non-finite coordinate breaks the line.
    pub points: Vec<(f64, f64)>,
    /// Colour.
    pub color: RGBColor,
    /// Dots instead of a line.
    pub dots: bool,
}

/// One chart of a figure.
#[derive(Clone, Debug, Default)]
pub struct Panel {
    /// Title above the chart.
    pub title: String,
    /// Description of the x axis, with its unit.
    pub x_label: String,
    /// Description of the y axis, with its unit.
    pub y_label: String,
    /// What is drawn.
    pub series: Vec<Series>,
    /// Same scale on both axes (top views of trajectories).
    pub equal_axes: bool,
}

/// Reads and registers the plot font once; later calls return the first outcome.
fn ensure_font() -> Result<()> {
    static FONT: OnceLock<std::result::Result<PathBuf, String>> = OnceLock::new();
    let outcome = FONT.get_or_init(|| {
        let candidates: Vec<PathBuf> = match std::env::var_os("RGBID_FONT") {
            Some(p) => vec![PathBuf::from(p)],
            None => SYSTEM_FONTS.iter().map(PathBuf::from).collect(),
        };
        for path in &candidates {
            let Ok(bytes) = std::fs::read(path) else {
                continue;
            };
            // plotters keeps fonts for the life of the process; one font is read per process.
            let bytes: &'static [u8] = Box::leak(bytes.into_boxed_slice());
            return match plotters::style::register_font(FAMILY, FontStyle::Normal, bytes) {
                Ok(()) => Ok(path.clone()),
                Err(_) => Err(format!("{} is not a TrueType font", path.display())),
            };
        }
        Err(format!(
            "no font for the plot's text: none of {} could be read; install a TrueType font \
             (Debian: fonts-dejavu-core) or set RGBID_FONT=/path/to/font.ttf",
            candidates
                .iter()
                .map(|p| p.display().to_string())
                .collect::<Vec<_>>()
                .join(", ")
        ))
    });
    outcome.as_ref().map(|_| ()).map_err(|m| anyhow!("{m}"))
}

/// The finite range of `values` with a 5 % margin (a unit range around a single value).
fn padded_range(values: impl Iterator<Item = f64>) -> (f64, f64) {
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for v in values.filter(|v| v.is_finite()) {
        lo = lo.min(v);
        hi = hi.max(v);
    }
    if !lo.is_finite() {
        return (0.0, 1.0);
    }
    if hi - lo <= 1e-12 * lo.abs().max(1.0) {
        return (lo - 0.5, hi + 0.5);
    }
    let pad = 0.05 * (hi - lo);
    (lo - pad, hi + pad)
}

/// Widens the shorter range so that one unit spans as many pixels on both axes.
fn equalise(x: (f64, f64), y: (f64, f64), px_w: f64, px_h: f64) -> ((f64, f64), (f64, f64)) {
    let per_px = ((x.1 - x.0) / px_w).max((y.1 - y.0) / px_h);
    let widen = |r: (f64, f64), px: f64| {
        let mid = 0.5 * (r.0 + r.1);
        (mid - 0.5 * per_px * px, mid + 0.5 * per_px * px)
    };
    (widen(x, px_w), widen(y, px_h))
}

/// Splits a series at non-finite points into drawable runs.
fn runs(points: &[(f64, f64)]) -> Vec<Vec<(f64, f64)>> {
    let mut out = vec![Vec::new()];
    for &(x, y) in points {
        if x.is_finite() && y.is_finite() {
            if let Some(last) = out.last_mut() {
                last.push((x, y));
            }
        } else if out.last().is_some_and(|r| !r.is_empty()) {
            out.push(Vec::new());
        }
    }
    out.retain(|r| !r.is_empty());
    out
}

const CAPTION_PX: u32 = 22;
const X_LABEL_AREA: u32 = 45;
const Y_LABEL_AREA: u32 = 70;
const MARGIN: u32 = 12;

fn draw_panel<DB: DrawingBackend>(
    area: &DrawingArea<DB, plotters::coord::Shift>,
    p: &Panel,
) -> Result<()>
where
    DB::ErrorType: 'static,
{
    let all = || p.series.iter().flat_map(|s| s.points.iter());
    let mut xr = padded_range(all().map(|q| q.0));
    let mut yr = padded_range(all().map(|q| q.1));
    if p.equal_axes {
        let (w, h) = area.dim_in_pixel();
        let px_w = w.saturating_sub(Y_LABEL_AREA + 2 * MARGIN).max(1) as f64;
        let px_h = h
            .saturating_sub(X_LABEL_AREA + 2 * MARGIN + CAPTION_PX + 10)
            .max(1) as f64;
        (xr, yr) = equalise(xr, yr, px_w, px_h);
    }
    let err = |e: &dyn std::fmt::Display| anyhow!("drawing panel '{}': {e}", p.title);
    let mut chart = ChartBuilder::on(area)
        .caption(&p.title, (FAMILY, CAPTION_PX))
        .margin(MARGIN)
        .x_label_area_size(X_LABEL_AREA)
        .y_label_area_size(Y_LABEL_AREA)
        .build_cartesian_2d(xr.0..xr.1, yr.0..yr.1)
        .map_err(|e| err(&e))?;
    chart
        .configure_mesh()
        .x_desc(&p.x_label)
        .y_desc(&p.y_label)
        .label_style((FAMILY, 14))
        .axis_desc_style((FAMILY, 16))
        .light_line_style(TRANSPARENT)
        .bold_line_style(RGBColor(215, 215, 215))
        .draw()
        .map_err(|e| err(&e))?;
    for s in &p.series {
        let color = s.color;
        let legend = |c: RGBColor| {
            move |(x, y): (i32, i32)| PathElement::new(vec![(x, y), (x + 18, y)], c.stroke_width(2))
        };
        if s.dots {
            let dots = s
                .points
                .iter()
                .filter(|q| q.0.is_finite() && q.1.is_finite())
                .map(|&q| Circle::new(q, 2, color.filled()));
            let a = chart.draw_series(dots).map_err(|e| err(&e))?;
            if !s.label.is_empty() {
                a.label(&s.label).legend(legend(color));
            }
        } else {
            for (k, run) in runs(&s.points).into_iter().enumerate() {
                let a = chart
                    .draw_series(LineSeries::new(run, color.stroke_width(2)))
                    .map_err(|e| err(&e))?;
                if k == 0 && !s.label.is_empty() {
                    a.label(&s.label).legend(legend(color));
                }
            }
        }
    }
    if p.series.iter().any(|s| !s.label.is_empty()) {
        chart
            .configure_series_labels()
            .label_font((FAMILY, 14))
            .background_style(WHITE.mix(0.85))
            .border_style(RGBColor(160, 160, 160))
            .position(SeriesLabelPosition::UpperRight)
            .draw()
            .map_err(|e| err(&e))?;
    }
    Ok(())
}

/// Draws `panels` row by row into a `rows x cols` grid of a `width x height` pixel image and
/// writes it as PNG to `path`.
pub fn write_png(
    path: &Path,
    panels: &[Panel],
    (rows, cols): (usize, usize),
    (width, height): (u32, u32),
) -> Result<()> {
    if panels.is_empty() || rows * cols < panels.len() {
        bail!("{} panels do not fit a {rows}x{cols} grid", panels.len());
    }
    ensure_font()?;
    let mut buf = vec![0u8; width as usize * height as usize * 3];
    {
        let root = BitMapBackend::with_buffer(&mut buf, (width, height)).into_drawing_area();
        root.fill(&WHITE).map_err(|e| anyhow!("{e}"))?;
        let areas = root.split_evenly((rows, cols));
        for (area, panel) in areas.iter().zip(panels) {
            draw_panel(area, panel)?;
        }
        root.present().map_err(|e| anyhow!("{e}"))?;
    }
    let img = image::RgbImage::from_raw(width, height, buf)
        .ok_or_else(|| anyhow!("plot buffer does not match {width}x{height}"))?;
    let mut png = Vec::new();
    img.write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
        .context("encoding the plot as PNG")?;
    std::fs::write(path, &png).with_context(|| format!("writing plot {}", path.display()))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn runs_break_at_non_finite_points() {
        let r = runs(&[
            (0.0, 1.0),
            (1.0, f64::NAN),
            (2.0, 2.0),
            (3.0, 3.0),
            (f64::INFINITY, 0.0),
        ]);
        assert_eq!(r, vec![vec![(0.0, 1.0)], vec![(2.0, 2.0), (3.0, 3.0)]]);
    }

    #[test]
    fn equal_axes_give_equal_units_per_pixel() {
        let (x, y) = equalise((0.0, 10.0), (0.0, 1.0), 400.0, 200.0);
        assert!(((x.1 - x.0) / 400.0 - (y.1 - y.0) / 200.0).abs() < 1e-12);
        assert!(x.0 <= 0.0 && x.1 >= 10.0 && y.0 <= 0.0 && y.1 >= 1.0);
    }

    #[test]
    fn padded_range_handles_constant_and_empty_data() {
        assert_eq!(padded_range([2.0, 2.0].into_iter()), (1.5, 2.5));
        assert_eq!(padded_range([f64::NAN].into_iter()), (0.0, 1.0));
        let (lo, hi) = padded_range([0.0, 10.0].into_iter());
        assert!((lo + 0.5).abs() < 1e-12 && (hi - 10.5).abs() < 1e-12);
    }
}
