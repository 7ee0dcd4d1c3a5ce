//! Dense single-channel images and RGB-D frames as the algorithms consume them.
//!
//! Intensity is f32 in `[0, 255]`; inverse depth is f32 in 1/m with `0` meaning "no
//! measurement". Images are row-major, index `y * width + x`.

use std::sync::{Arc, OnceLock};

/// Errors of the frame and image constructors: which buffer does not fit, and how.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ImageError {
    /// A buffer's length is not what the size needs.
    #[error("{what} buffer has {got} values, but {width}x{height} needs {want}")]
    BufferLength {
        /// Which buffer (`"intensity"`, `"rgb"`, `"depth"`, ...).
        what: &'static str,
        /// Width asked for, pixels.
        width: usize,
        /// Height asked for, pixels.
        height: usize,
        /// Values the size needs.
        want: usize,
        /// Values the buffer has.
        got: usize,
    },
    /// Two images of one frame differ in size.
    #[error("{what} is {got_w}x{got_h} but the frame is {want_w}x{want_h}")]
    SizeMismatch {
        /// Which image.
        what: &'static str,
        /// The frame's width.
        want_w: usize,
        /// The frame's height.
        want_h: usize,
        /// The image's width.
        got_w: usize,
        /// The image's height.
        got_h: usize,
    },
    /// The depth factor is not a finite positive number.
    #[error("depth factor {0} must be finite and > 0 (depth units per metre, e.g. 5000 for TUM, 1000 for millimetres)")]
    DepthFactor(f64),
    /// The time stamp is not finite.
    #[error("time stamp {0} is not finite")]
    Timestamp(f64),
}

/// A row-major single-channel f32 image; holds exactly `width * height` values.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ImageF32 {
    pub(crate) width: usize,
    pub(crate) height: usize,
    pub(crate) data: Vec<f32>,
}

impl ImageF32 {
    /// An image filled with `value`.
    pub fn filled(width: usize, height: usize, value: f32) -> Self {
        Self {
            width,
            height,
            data: vec![value; width * height],
        }
    }

    /// Wraps a buffer; `None` if its length is not `width * height`.
    pub fn from_vec(width: usize, height: usize, data: Vec<f32>) -> Option<Self> {
        (data.len() == width * height).then_some(Self {
            width,
            height,
            data,
        })
    }

    /// Width in pixels.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Height in pixels.
    pub fn height(&self) -> usize {
        self.height
    }

    /// Row-major pixel values, `width * height` of them.
    pub fn data(&self) -> &[f32] {
        &self.data
    }

    /// Row-major pixel values, mutable (the size stays fixed).
    pub fn data_mut(&mut self) -> &mut [f32] {
        &mut self.data
    }

    /// The pixel values, consuming the image.
    pub fn into_data(self) -> Vec<f32> {
        self.data
    }

    /// Pixel at integer coordinates (no bounds check beyond the slice's).
    #[inline]
    pub fn at(&self, x: usize, y: usize) -> f32 {
        self.data[y * self.width + x]
    }
}

/// A row-major 8-bit RGB image (channel order R, G, B), as cameras and decoders give it.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct ColourImage {
    width: usize,
    height: usize,
    data: Vec<u8>,
}

impl ColourImage {
    /// Wraps interleaved RGB bytes (`3 * width * height` of them).
    pub fn from_rgb(width: usize, height: usize, rgb: Vec<u8>) -> Result<Self, ImageError> {
        check_len("rgb", width, height, 3, rgb.len())?;
        Ok(Self {
            width,
            height,
            data: rgb,
        })
    }

    /// Width in pixels.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Height in pixels.
    pub fn height(&self) -> usize {
        self.height
    }

    /// Interleaved RGB bytes, row-major.
    pub fn rgb(&self) -> &[u8] {
        &self.data
    }

    /// The RGB of pixel `(x, y)`.
    pub fn at(&self, x: usize, y: usize) -> [u8; 3] {
        let i = 3 * (y * self.width + x);
        [self.data[i], self.data[i + 1], self.data[i + 2]]
    }
}

/// The image part of a camera frame, as raw 8-bit buffers (row-major).
#[derive(Clone, Copy, Debug)]
pub enum ImageBuffer<'a> {
    /// One grey value per pixel, `[0, 255]`.
    Gray(&'a [u8]),
    /// Interleaved R, G, B per pixel (BGR sources swap channels first). The colour is kept in
    /// the frame; the intensity is its BT.601 luma ([`rgb_to_intensity`]).
    Rgb(&'a [u8]),
}

/// The depth part of a camera frame (row-major).
#[derive(Clone, Copy, Debug)]
pub enum DepthBuffer<'a> {
    /// Raw 16-bit depth with `factor` units per metre (TUM 5000, millimetre sensors 1000);
    /// 0 and 65535 (the saturated value 7-Scenes and other datasets write for "no
    /// measurement") mean no measurement.
    U16 {
        /// The raw values.
        data: &'a [u16],
        /// Depth units per metre.
        factor: f64,
    },
    /// Depth in metres; 0, negative and non-finite values mean no measurement.
    Metres(&'a [f32]),
}

fn check_len(
    what: &'static str,
    width: usize,
    height: usize,
    per_pixel: usize,
    got: usize,
) -> Result<(), ImageError> {
    let want = width * height * per_pixel;
    if got == want {
        Ok(())
    } else {
        Err(ImageError::BufferLength {
            what,
            width,
            height,
            want,
            got,
        })
    }
}

/// One RGB-D frame: intensity and inverse depth on the same pixel grid, the colour when the
/// camera gave one, and the time stamp. The constructors check that every image has the
/// frame's size.
#[derive(Clone, Debug)]
pub struct RgbdFrame {
    pub(crate) timestamp: f64,
    pub(crate) intensity: ImageF32,
    pub(crate) inverse_depth: ImageF32,
    pub(crate) colour: Option<FrameColour>,
}

/// A correction that maps a decoded colour image onto its frame's pixel grid (e.g. lens
/// undistortion).
pub(crate) type ColourFix = Arc<dyn Fn(&ColourImage) -> ColourImage + Send + Sync>;

/// A frame's colour, with its correction applied the first time it is read: most frames'
/// colour is never read (only keyframes keep theirs), so a reader need not pay for
/// correcting all of them.
#[derive(Clone)]
pub(crate) struct FrameColour {
    pub(crate) stored: ColourImage,
    fix: Option<ColourFix>,
    pub(crate) fixed: OnceLock<ColourImage>,
}

impl FrameColour {
    /// Colour already on the frame's pixel grid.
    pub(crate) fn ready(colour: ColourImage) -> Self {
        Self {
            stored: colour,
            fix: None,
            fixed: OnceLock::new(),
        }
    }

    /// This colour, with `fix` applied to it (after any correction it already has) when it
    /// is first read. `fix` must keep the image's size.
    pub(crate) fn fixed_later(self, fix: ColourFix) -> Self {
        let (stored, fix) = match (self.fixed.into_inner(), self.fix) {
            (Some(fixed), _) => (fixed, fix),
            (None, None) => (self.stored, fix),
            (None, Some(first)) => {
                let both: ColourFix = Arc::new(move |c: &ColourImage| fix(&first(c)));
                (self.stored, both)
            }
        };
        Self {
            stored,
            fix: Some(fix),
            fixed: OnceLock::new(),
        }
    }

    /// The colour on the frame's pixel grid.
    pub(crate) fn get(&self) -> &ColourImage {
        match &self.fix {
            None => &self.stored,
            Some(fix) => self.fixed.get_or_init(|| fix(&self.stored)),
        }
    }
}

impl std::fmt::Debug for FrameColour {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FrameColour")
            .field("width", &self.stored.width)
            .field("height", &self.stored.height)
            .field("deferred", &self.fix.is_some())
            .field("fixed", &self.fixed.get().is_some())
            .finish()
    }
}

impl RgbdFrame {
    /// A frame from the buffers a camera driver or an image decoder produces: a `width x
    /// height` image (grey or RGB) and depth (raw 16-bit with a factor, or metres), taken at
    /// `timestamp` seconds. Intensity is in `[0, 255]`, inverse depth in 1/m (0 = none).
    ///
    /// ```
    /// use rgbid::image::{DepthBuffer, ImageBuffer, RgbdFrame};
    /// let (w, h) = (4, 3);
    /// let rgb = vec![200u8; 3 * w * h];
    /// let depth = vec![5000u16; w * h]; // 1 m in TUM units
    /// let f = RgbdFrame::from_buffers(
    ///     0.5, w, h,
    ///     ImageBuffer::Rgb(&rgb),
    ///     DepthBuffer::U16 { data: &depth, factor: 5000.0 },
    /// )?;
    /// assert_eq!(f.inverse_depth().at(1, 1), 1.0);
    /// assert!(f.colour().is_some());
    /// // A depth buffer of the wrong size names itself:
    /// let e = RgbdFrame::from_buffers(0.5, w, h, ImageBuffer::Rgb(&rgb),
    ///     DepthBuffer::U16 { data: &depth[1..], factor: 5000.0 }).unwrap_err();
    /// assert!(e.to_string().starts_with("depth buffer has 11 values"));
    /// # Ok::<(), rgbid::image::ImageError>(())
    /// ```
    pub fn from_buffers(
        timestamp: f64,
        width: usize,
        height: usize,
        image: ImageBuffer<'_>,
        depth: DepthBuffer<'_>,
    ) -> Result<Self, ImageError> {
        if !timestamp.is_finite() {
            return Err(ImageError::Timestamp(timestamp));
        }
        let (intensity, colour) = match image {
            ImageBuffer::Gray(g) => {
                check_len("grey image", width, height, 1, g.len())?;
                (g.iter().map(|&v| f32::from(v)).collect(), None)
            }
            ImageBuffer::Rgb(c) => {
                check_len("rgb", width, height, 3, c.len())?;
                let i = c
                    .chunks_exact(3)
                    .map(|p| rgb_to_intensity(p[0], p[1], p[2]))
                    .collect();
                (
                    i,
                    Some(FrameColour::ready(ColourImage {
                        width,
                        height,
                        data: c.to_vec(),
                    })),
                )
            }
        };
        let inverse_depth = match depth {
            DepthBuffer::U16 { data, factor } => {
                check_len("depth", width, height, 1, data.len())?;
                if !(factor.is_finite() && factor > 0.0) {
                    return Err(ImageError::DepthFactor(factor));
                }
                inverse_depth_from_u16(data, factor)
            }
            DepthBuffer::Metres(data) => {
                check_len("depth", width, height, 1, data.len())?;
                data.iter()
                    .map(|&d| {
                        if d.is_finite() && d > 0.0 {
                            1.0 / d
                        } else {
                            0.0
                        }
                    })
                    .collect()
            }
        };
        Ok(Self {
            timestamp,
            intensity: ImageF32 {
                width,
                height,
                data: intensity,
            },
            inverse_depth: ImageF32 {
                width,
                height,
                data: inverse_depth,
            },
            colour,
        })
    }

    /// A frame from intensity (`[0, 255]`) and inverse depth (1/m, 0 = none; non-finite and
    /// negative values become 0) images of the same size, taken at `timestamp` seconds.
    pub fn new(
        timestamp: f64,
        intensity: ImageF32,
        mut inverse_depth: ImageF32,
    ) -> Result<Self, ImageError> {
        if !timestamp.is_finite() {
            return Err(ImageError::Timestamp(timestamp));
        }
        if (inverse_depth.width, inverse_depth.height) != (intensity.width, intensity.height) {
            return Err(ImageError::SizeMismatch {
                what: "inverse depth",
                want_w: intensity.width,
                want_h: intensity.height,
                got_w: inverse_depth.width,
                got_h: inverse_depth.height,
            });
        }
        for r in &mut inverse_depth.data {
            if !(r.is_finite() && *r > 0.0) {
                *r = 0.0;
            }
        }
        Ok(Self {
            timestamp,
            intensity,
            inverse_depth,
            colour: None,
        })
    }

    /// The same frame with `colour` attached (it must have the frame's size).
    pub fn with_colour(mut self, colour: ColourImage) -> Result<Self, ImageError> {
        if (colour.width, colour.height) != (self.width(), self.height()) {
            return Err(ImageError::SizeMismatch {
                what: "colour",
                want_w: self.width(),
                want_h: self.height(),
                got_w: colour.width,
                got_h: colour.height,
            });
        }
        self.colour = Some(FrameColour::ready(colour));
        Ok(self)
    }

    /// The same frame with another time stamp (seconds).
    pub fn with_timestamp(mut self, timestamp: f64) -> Self {
        self.timestamp = timestamp;
        self
    }

    /// Time stamp, seconds.
    pub fn timestamp(&self) -> f64 {
        self.timestamp
    }

    /// Intensity in `[0, 255]`.
    pub fn intensity(&self) -> &ImageF32 {
        &self.intensity
    }

    /// Inverse depth in 1/m, 0 where there is no measurement.
    pub fn inverse_depth(&self) -> &ImageF32 {
        &self.inverse_depth
    }

    /// Intensity, mutable (its size stays the frame's).
    pub fn intensity_mut(&mut self) -> &mut ImageF32 {
        &mut self.intensity
    }

    /// Inverse depth, mutable (its size stays the frame's).
    pub fn inverse_depth_mut(&mut self) -> &mut ImageF32 {
        &mut self.inverse_depth
    }

    /// The colour image, when the frame was made from RGB.
    pub fn colour(&self) -> Option<&ColourImage> {
        self.colour.as_ref().map(FrameColour::get)
    }

    /// `(intensity, inverse depth)`, consuming the frame.
    pub fn into_images(self) -> (ImageF32, ImageF32) {
        (self.intensity, self.inverse_depth)
    }

    /// Image width in pixels.
    pub fn width(&self) -> usize {
        self.intensity.width
    }
    /// Image height in pixels.
    pub fn height(&self) -> usize {
        self.intensity.height
    }
}

/// Inverse depth (1/m) of raw 16-bit depth with `factor` units per metre; 0 stays 0 (no
/// measurement). The factor is applied in f32, as every loader of the library does.
pub(crate) fn inverse_depth_from_u16(raw: &[u16], factor: f64) -> Vec<f32> {
    let factor = factor as f32;
    raw.iter()
        .map(|&d| {
            if d == 0 || d == u16::MAX {
                0.0
            } else {
                factor / f32::from(d)
            }
        })
        .collect()
}

/// Converts 8-bit RGB to intensity in `[0, 255]` with ITU-R BT.601 luma weights
/// (`0.299 R + 0.587 G + 0.114 B`, as OpenCV's `cvtColor`).
#[inline]
pub fn rgb_to_intensity(r: u8, g: u8, b: u8) -> f32 {
    0.299 * f32::from(r) + 0.587 * f32::from(g) + 0.114 * f32::from(b)
}

/// An intensity in `[0, 255]` as a byte: rounded to the nearest, clamped (NaN gives 0).
#[inline]
pub(crate) fn intensity_byte(v: f32) -> u8 {
    v.round().clamp(0.0, 255.0) as u8
}

/// A deterministic textured frame for kernel tests: intensity from a few sinusoids plus
/// hashed noise, inverse depth of a slanted plane with a bump, and holes (0) in a corner and
/// on a sparse grid (so the validity logic is exercised).
pub fn test_pattern(w: usize, h: usize, seed: u32) -> RgbdFrame {
    let hash = |x: u32, y: u32| {
        let mut v =
            x.wrapping_mul(374761393) ^ y.wrapping_mul(668265263) ^ seed.wrapping_mul(2246822519);
        v = (v ^ (v >> 13)).wrapping_mul(1274126177);
        (v ^ (v >> 16)) as f32 / u32::MAX as f32
    };
    let mut i = Vec::with_capacity(w * h);
    let mut r = Vec::with_capacity(w * h);
    for y in 0..h {
        for x in 0..w {
            let (fx, fy) = (x as f32 / w as f32, y as f32 / h as f32);
            let v = 128.0
                + 50.0 * (fx * 23.0).sin() * (fy * 17.0).cos()
                + 30.0 * (fx * 7.0 + fy * 11.0).sin()
                + 20.0 * hash((x / 3) as u32, (y / 3) as u32);
            i.push(v.clamp(0.0, 255.0));
            let hole = (x < w / 8 && y < h / 8) || (x % 17 == 0 && y % 13 == 0);
            let bump = 0.3 * (-((fx - 0.6).powi(2) + (fy - 0.4).powi(2)) * 20.0).exp();
            r.push(if hole {
                0.0
            } else {
                1.0 / (1.2 + 0.8 * fx + 0.3 * fy - bump)
            });
        }
    }
    RgbdFrame {
        timestamp: 0.0,
        intensity: ImageF32::from_vec(w, h, i).unwrap_or_else(|| ImageF32::filled(w, h, 0.0)),
        inverse_depth: ImageF32::from_vec(w, h, r).unwrap_or_else(|| ImageF32::filled(w, h, 0.0)),
        colour: None,
    }
}

/// Offsets `(dx, dy)` in pixels of the 16 pixels of the radius-3 Bresenham circle of the FAST
/// corner test (Rosten and Drummond 2006), clockwise from the top, `y` down.
pub const FAST_CIRCLE: [(i32, i32); 16] = [
    (0, -3),
    (1, -3),
    (2, -2),
    (3, -1),
    (3, 0),
    (3, 1),
    (2, 2),
    (1, 3),
    (0, 3),
    (-1, 3),
    (-2, 2),
    (-3, 1),
    (-3, 0),
    (-3, -1),
    (-2, -2),
    (-1, -3),
];

#[cfg(test)]
mod tests {
    use super::*;

    fn colour(data: Vec<u8>) -> ColourImage {
        ColourImage::from_rgb(2, 1, data).unwrap()
    }

    /// Corrections apply in the order they were added, once, and on top of a correction
    /// already applied by a read.
    #[test]
    fn deferred_corrections_compose_in_order() {
        let calls = Arc::new(std::sync::atomic::AtomicUsize::new(0));
        let counted = Arc::clone(&calls);
        let invert: ColourFix = Arc::new(move |c: &ColourImage| {
            counted.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
            colour(c.rgb().iter().map(|v| 255 - v).collect())
        });
        let halve: ColourFix =
            Arc::new(|c: &ColourImage| colour(c.rgb().iter().map(|v| v / 2).collect()));
        let c = FrameColour::ready(colour(vec![0, 10, 20, 30, 40, 50]))
            .fixed_later(Arc::clone(&invert))
            .fixed_later(Arc::clone(&halve));
        let want = colour(vec![127, 122, 117, 112, 107, 102]);
        assert_eq!(c.get(), &want);
        assert_eq!(c.get(), &want);
        assert_eq!(calls.load(std::sync::atomic::Ordering::SeqCst), 1);
        // Read first, then one more correction: it starts from the corrected colour.
        let read = FrameColour::ready(colour(vec![0, 10, 20, 30, 40, 50])).fixed_later(invert);
        assert_eq!(read.get().rgb(), &[255, 245, 235, 225, 215, 205]);
        assert_eq!(read.fixed_later(halve).get(), &want);
        assert_eq!(calls.load(std::sync::atomic::Ordering::SeqCst), 2);
    }
}
