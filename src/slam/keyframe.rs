//! Compact keyframes: 8-bit intensity, half-precision fused inverse depth, 8-bit weights, and
//! the 8-bit RGB colour of the reference frame when the input had colour.
//!
//! Memory per pixel: 4 bytes without colour (1 intensity + 2 inverse depth + 1 weight), 7 with
//! colour; a 640x480 keyframe holds 1.23 MB, or 2.15 MB with colour.

use glam::DVec3;
use half::f16;
use rayon::prelude::*;

use crate::camera::PinholeCamera;
use crate::geometry::{Covariance6, Se3};
use crate::image::{intensity_byte, ColourImage, FrameColour, ImageError, ImageF32, RgbdFrame};

/// How a keyframe is attached to the map when it is created.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum KeyframeLink {
    /// The first keyframe of a map (no constraint).
    First,
    /// Sequential odometry from keyframe `from`: `from_from_this` and its 6x6 covariance
    /// (twist `[v; w]`, metres and radians squared).
    Odometry {
        /// Previous keyframe id.
        from: usize,
        /// `keyframe(from)_from_this`.
        from_from_this: Se3,
        /// Covariance of `from_from_this`.
        covariance: Covariance6,
    },
    /// Relocalised against keyframe `from` after tracking was lost (or at the start of a
    /// session in a loaded map).
    Relocalised {
        /// The keyframe relocalised against.
        from: usize,
        /// `keyframe(from)_from_this`.
        from_from_this: Se3,
        /// Covariance of `from_from_this`.
        covariance: Covariance6,
    },
}

/// A finished keyframe as the front-end hands it to the back-end.
#[derive(Clone, Debug)]
pub struct Keyframe {
    /// Keyframe id (0, 1, ... in map order).
    pub id: usize,
    /// Index of the frame it was created from (in its session).
    pub frame_index: usize,
    /// Session the keyframe was made in (0 for the first).
    pub session: u32,
    /// Time stamp, seconds.
    pub timestamp: f64,
    /// Image width, pixels.
    pub width: usize,
    /// Image height, pixels.
    pub height: usize,
    /// Intensity, rounded to 8 bits.
    pub intensity: Vec<u8>,
    /// Fused inverse depth, 1/m (0 = invalid), half precision.
    pub inverse_depth: Vec<f16>,
    /// Fusion weights (number of fused measurements, capped at 255).
    pub weight: Vec<u8>,
    /// Colour of the frame the keyframe was made from (8-bit RGB, the keyframe's size), when
    /// the input had colour; the fused inverse depth lies on the same pixel grid.
    pub colour: Option<ColourImage>,
    /// `world_from_keyframe` as estimated by the front-end when it was created.
    pub world_from_keyframe: Se3,
    /// How it is attached to the previous map.
    pub link: KeyframeLink,
}

/// Pixels per parallel task when packing: packing runs on the tracking thread between frames.
const MIN_PER_TASK: usize = 1 << 14;

impl Keyframe {
    /// Packs images of one size into a keyframe.
    #[allow(clippy::too_many_arguments)]
    pub fn pack(
        id: usize,
        frame_index: usize,
        session: u32,
        timestamp: f64,
        intensity: &ImageF32,
        inverse_depth: &ImageF32,
        weight: &ImageF32,
        world_from_keyframe: Se3,
        link: KeyframeLink,
    ) -> Keyframe {
        Keyframe {
            id,
            frame_index,
            session,
            timestamp,
            width: intensity.width,
            height: intensity.height,
            intensity: intensity
                .data
                .par_iter()
                .with_min_len(MIN_PER_TASK)
                .map(|&v| intensity_byte(v))
                .collect(),
            inverse_depth: inverse_depth
                .data
                .par_iter()
                .with_min_len(MIN_PER_TASK)
                .map(|&r| f16::from_f32(if r.is_finite() && r > 0.0 { r } else { 0.0 }))
                .collect(),
            weight: weight
                .data
                .par_iter()
                .with_min_len(MIN_PER_TASK)
                .map(|&w| intensity_byte(w))
                .collect(),
            colour: None,
            world_from_keyframe,
            link,
        }
    }

    /// The same keyframe with `colour` (RGB of its reference frame), which must have the
    /// keyframe's size.
    pub fn with_colour(mut self, colour: ColourImage) -> Result<Keyframe, ImageError> {
        if (colour.width(), colour.height()) != (self.width, self.height) {
            return Err(ImageError::SizeMismatch {
                what: "keyframe colour",
                want_w: self.width,
                want_h: self.height,
                got_w: colour.width(),
                got_h: colour.height(),
            });
        }
        self.colour = Some(colour);
        Ok(self)
    }

    /// Intensity as an image (0-255).
    pub fn intensity_image(&self) -> ImageF32 {
        ImageF32 {
            width: self.width,
            height: self.height,
            data: self.intensity.iter().map(|&v| f32::from(v)).collect(),
        }
    }

    /// Fused inverse depth as an image (1/m, 0 = invalid).
    pub fn inverse_depth_image(&self) -> ImageF32 {
        ImageF32 {
            width: self.width,
            height: self.height,
            data: self.inverse_depth.iter().map(|r| r.to_f32()).collect(),
        }
    }

    /// The keyframe as a frame (for dense alignment and TSDF integration), with its colour
    /// when it has one.
    pub fn frame(&self) -> RgbdFrame {
        RgbdFrame {
            timestamp: self.timestamp,
            intensity: self.intensity_image(),
            inverse_depth: self.inverse_depth_image(),
            colour: self.colour.clone().map(FrameColour::ready),
        }
    }

    /// Bytes held by the keyframe's images (colour included).
    pub fn image_bytes(&self) -> usize {
        self.intensity.len()
            + 2 * self.inverse_depth.len()
            + self.weight.len()
            + self.colour.as_ref().map_or(0, |c| c.rgb().len())
    }

    /// The RGB of pixel index `i` (`y * width + x`, below `width * height`): the keyframe's
    /// colour, or its intensity as grey when it has none.
    pub(crate) fn rgb_at(&self, i: usize) -> [u8; 3] {
        match &self.colour {
            Some(c) => {
                let rgb = c.rgb();
                [rgb[3 * i], rgb[3 * i + 1], rgb[3 * i + 2]]
            }
            None => [self.intensity[i]; 3],
        }
    }

    /// Points of the keyframe in its own camera frame (metres) with their intensity, every
    /// `step`-th pixel in x and y, only where the fused weight is at least `min_weight`.
    pub fn points(&self, camera: &PinholeCamera, step: usize, min_weight: u8) -> Vec<(DVec3, u8)> {
        self.pixel_points(camera, step, min_weight)
            .into_iter()
            .map(|(p, i)| (p, self.intensity[i]))
            .collect()
    }

    /// As [`Keyframe::points`], with the pixel index (`y * width + x`) of each point.
    pub(crate) fn pixel_points(
        &self,
        camera: &PinholeCamera,
        step: usize,
        min_weight: u8,
    ) -> Vec<(DVec3, usize)> {
        let step = step.max(1);
        let mut out = Vec::new();
        for y in (0..self.height).step_by(step) {
            for x in (0..self.width).step_by(step) {
                let i = y * self.width + x;
                let r = self.inverse_depth[i].to_f32();
                if r > 0.0 && self.weight[i] >= min_weight {
                    let z = 1.0 / f64::from(r);
                    let p = DVec3::new(
                        (x as f64 - camera.cx) / camera.fx * z,
                        (y as f64 - camera.cy) / camera.fy * z,
                        z,
                    );
                    out.push((p, i));
                }
            }
        }
        out
    }
}
