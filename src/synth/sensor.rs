//! Kinect-like sensor model applied to the ray caster's clean output: depth from disparity
//! (Gaussian noise in disparity, disparity quantisation, range limits, dropout at grazing
//! angles and on the far side of depth discontinuities), colour noise, gain, 8-bit colour and
//! 16-bit depth quantisation (TUM factor 5000) so that in-memory frames equal what a TUM
//! reader gets back from the written files.
//!
//! Noise is counter-based (a hash of pixel index, frame seed and channel), so results do not
//! depend on the thread count or on the backend that did the ray casting.

use rayon::prelude::*;

use super::raycast::{pcg_hash, unit, CastSample, NO_OBJECT};
use crate::image::{rgb_to_intensity, ImageF32};

/// TUM depth PNG factor: 16-bit value per metre.
pub const DEPTH_FACTOR: f64 = 5000.0;

/// Parameters of the simulated RGB-D sensor. Distances in metres, disparities in pixels.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SensorModel {
    /// Closest valid depth, metres.
    pub min_range: f64,
    /// Farthest valid depth, metres. Depth is stored as 16-bit TUM values
    /// ([`DEPTH_FACTOR`] per metre), so nothing beyond 65535 / `DEPTH_FACTOR` metres (13.1 m)
    /// has depth whatever this is.
    pub max_range: f64,
    /// Projector-camera baseline, metres (disparity = focal * baseline / depth).
    pub baseline: f64,
    /// Focal length used for disparity, pixels; `None` = the camera's (fx, or gamma).
    pub focal_px: Option<f64>,
    /// Standard deviation of the Gaussian disparity noise, pixels. The inverse-depth noise is
    /// then `disparity_sigma / (focal * baseline)` 1/m at every depth.
    pub disparity_sigma: f64,
    /// Disparity quantisation step, pixels (Kinect: 1/8); 0 disables.
    pub disparity_step: f64,
    /// Largest angle between the ray and the surface normal that still gives depth, radians
    /// (>= pi/2 disables the grazing-angle dropout).
    pub max_incidence: f64,
    /// Relative depth jump to a 4-neighbour above which the farther pixel loses its depth
    /// (the projector's shadow at discontinuities); 0 disables.
    pub discontinuity: f64,
    /// Probability that a valid depth pixel drops out at random.
    pub dropout: f64,
    /// Standard deviation of the colour noise, in 8-bit levels per channel.
    pub color_sigma: f64,
    /// Exposure gain multiplying the colour (1 = nominal).
    pub gain: f64,
}

impl SensorModel {
    /// A Kinect-like sensor: 0.5-4.0 m range, disparity noise 0.1 px with 1/8 px steps
    /// (baseline 7.5 cm), grazing-angle (> 78 deg) and discontinuity dropout, 0.2% random
    /// dropout, colour noise 2 levels.
    pub fn kinect() -> Self {
        SensorModel {
            min_range: 0.5,
            max_range: 4.0,
            baseline: 0.075,
            focal_px: None,
            disparity_sigma: 0.1,
            disparity_step: 0.125,
            max_incidence: 78f64.to_radians(),
            discontinuity: 0.04,
            dropout: 0.002,
            color_sigma: 2.0,
            gain: 1.0,
        }
    }

    /// No noise and no dropout: depth wherever a surface is hit between 0.05 m and the 16-bit
    /// storage's 13.1 m (only the 16-bit / 8-bit storage quantisation remains).
    pub fn noiseless() -> Self {
        SensorModel {
            min_range: 0.05,
            max_range: 100.0,
            baseline: 0.075,
            focal_px: None,
            disparity_sigma: 0.0,
            disparity_step: 0.0,
            max_incidence: std::f64::consts::FRAC_PI_2,
            discontinuity: 0.0,
            dropout: 0.0,
            color_sigma: 0.0,
            gain: 1.0,
        }
    }

    /// The standard deviation of inverse depth this model produces (1/m), ignoring
    /// quantisation, for a camera of focal length `focal_px`.
    pub fn inverse_depth_sigma(&self, focal_px: f64) -> f64 {
        self.disparity_sigma / (self.focal_px.unwrap_or(focal_px) * self.baseline)
    }
}

impl Default for SensorModel {
    fn default() -> Self {
        SensorModel::kinect()
    }
}

/// A standard normal sample from the counter `(index, stream)` under `seed`.
#[inline]
pub(crate) fn gauss(seed: u64, index: u32, stream: u32) -> f64 {
    let k = pcg_hash((seed as u32) ^ pcg_hash((seed >> 32) as u32 ^ pcg_hash(stream)));
    let h1 = pcg_hash(index ^ k);
    let h2 = pcg_hash(h1 ^ 0x68e3_1da4);
    let u1 = f64::from(unit(h1)) + 1.0 / 33_554_432.0;
    let u2 = f64::from(unit(h2));
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

#[inline]
fn uniform(seed: u64, index: u32, stream: u32) -> f64 {
    let k = pcg_hash((seed as u32) ^ pcg_hash((seed >> 32) as u32 ^ pcg_hash(stream)));
    f64::from(unit(pcg_hash(index ^ k)))
}

/// Output of [`apply`]: 8-bit RGB, intensity, inverse depth.
pub(crate) struct SensorOutput {
    pub rgb: Vec<u8>,
    pub intensity: ImageF32,
    pub inverse_depth: ImageF32,
}

/// Applies the sensor model to a cast image of `width x height` samples.
pub(crate) fn apply(
    samples: &[CastSample],
    width: usize,
    height: usize,
    sensor: &SensorModel,
    focal_px: f64,
    seed: u64,
) -> SensorOutput {
    let fb = sensor.focal_px.unwrap_or(focal_px) * sensor.baseline;
    let cos_min = sensor.max_incidence.cos();
    let n = width * height;
    let mut rgb = vec![0u8; 3 * n];
    let mut intensity = vec![0f32; n];
    let mut inverse = vec![0f32; n];
    let rows = rgb
        .par_chunks_mut(3 * width.max(1))
        .zip(intensity.par_chunks_mut(width.max(1)))
        .zip(inverse.par_chunks_mut(width.max(1)));
    rows.enumerate()
        .for_each(|(y, ((rgb_row, int_row), inv_row))| {
            for x in 0..width {
                let i = y * width + x;
                let s = &samples[i];
                // Colour: gain, noise, 8-bit.
                let mut c8 = [0u8; 3];
                for k in 0..3 {
                    let mut v = f64::from(s.rgb[k]) * 255.0 * sensor.gain;
                    if sensor.color_sigma > 0.0 {
                        v += sensor.color_sigma * gauss(seed, i as u32, 1 + k as u32);
                    }
                    c8[k] = v.round().clamp(0.0, 255.0) as u8;
                }
                rgb_row[3 * x..3 * x + 3].copy_from_slice(&c8);
                int_row[x] = rgb_to_intensity(c8[0], c8[1], c8[2]);
                // Depth.
                let z = f64::from(s.z);
                if s.object == NO_OBJECT || z <= 0.0 || z < sensor.min_range || z > sensor.max_range
                {
                    continue;
                }
                if f64::from(s.cos_incidence) < cos_min {
                    continue;
                }
                if sensor.discontinuity > 0.0 {
                    let mut shadow = false;
                    let nb = [
                        (x > 0).then(|| i - 1),
                        (x + 1 < width).then(|| i + 1),
                        (y > 0).then(|| i - width),
                        (y + 1 < height).then(|| i + width),
                    ];
                    for j in nb.into_iter().flatten() {
                        let zn = f64::from(samples[j].z);
                        if samples[j].object == NO_OBJECT
                            || zn <= 0.0
                            || z > zn * (1.0 + sensor.discontinuity)
                        {
                            shadow = true;
                        }
                    }
                    if shadow {
                        continue;
                    }
                }
                if sensor.dropout > 0.0 && uniform(seed, i as u32, 7) < sensor.dropout {
                    continue;
                }
                let mut disparity = fb / z;
                if sensor.disparity_sigma > 0.0 {
                    disparity += sensor.disparity_sigma * gauss(seed, i as u32, 8);
                }
                if sensor.disparity_step > 0.0 {
                    disparity = (disparity / sensor.disparity_step).round() * sensor.disparity_step;
                }
                if disparity <= 0.0 {
                    continue;
                }
                let zq = (fb / disparity * DEPTH_FACTOR).round();
                if !(1.0..=65535.0).contains(&zq) {
                    continue;
                }
                inv_row[x] = (DEPTH_FACTOR / zq) as f32;
            }
        });
    SensorOutput {
        rgb,
        intensity: ImageF32 {
            width,
            height,
            data: intensity,
        },
        inverse_depth: ImageF32 {
            width,
            height,
            data: inverse,
        },
    }
}
