//! Dense single-channel images and RGB-D frames as the algorithms consume them.
//!
//! Intensity is f32 in `[0, 255]`; inverse depth is f32 in 1/m with `0` meaning "no
//! measurement". Images are row-major, index `y * width + x`.

/// A row-major single-channel f32 image.
#[derive(Clone, Debug, Default, PartialEq)]
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
