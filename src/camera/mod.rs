//! Camera models.
//!
//! Camera frame: x right, y down, z forward (OpenCV). Pixel coordinates `(u, v)` with integer
//! values at pixel centres, so TUM's `cx = 319.5` is the centre of a 640-pixel-wide image.
//! Depth along z in metres; inverse depth in 1/m with 0 meaning "no measurement".

mod pinhole;
mod unified;

pub use pinhole::{BrownConrady, CameraError, PinholeCamera};
pub use unified::UnifiedCamera;
