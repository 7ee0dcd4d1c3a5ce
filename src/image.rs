//! Dense single-channel images and RGB-D frames as the algorithms consume them.
//!
//! Intensity is f32 in `[0, 255]`; inverse depth is f32 in 1/m with `0` meaning "no
//! measurement". Images are row-major, index `y * width + x`.

/// A row-major single-channel f32 image.
#[derive(Clone, Debug, PartialEq)]
pub struct ImageF32 {
    /// Width in pixels.
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// Row-major pixel values, `width * height` of them.
    pub data: Vec<f32>,
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

    /// Pixel at integer coordinates (no bounds check beyond the slice's).
    #[inline]
    pub fn at(&self, x: usize, y: usize) -> f32 {
        self.data[y * self.width + x]
    }
}

/// One RGB-D frame: intensity and inverse depth on the same pixel grid, plus its time stamp.
#[derive(Clone, Debug)]
pub struct RgbdFrame {
    /// Time stamp in seconds.
    pub timestamp: f64,
    /// Intensity in `[0, 255]`.
    pub intensity: ImageF32,
    /// Inverse depth in 1/m, `0` where there is no measurement.
    pub inverse_depth: ImageF32,
}

impl RgbdFrame {
    /// Image width in pixels.
    pub fn width(&self) -> usize {
        self.intensity.width
    }
    /// Image height in pixels.
    pub fn height(&self) -> usize {
        self.intensity.height
    }
}

/// Converts 8-bit RGB to intensity in `[0, 255]` with ITU-R BT.601 luma weights
/// (`0.299 R + 0.587 G + 0.114 B`, as OpenCV's `cvtColor`).
#[inline]
pub fn rgb_to_intensity(r: u8, g: u8, b: u8) -> f32 {
    0.299 * f32::from(r) + 0.587 * f32::from(g) + 0.114 * f32::from(b)
}
