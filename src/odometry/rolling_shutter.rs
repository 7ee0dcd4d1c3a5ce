//! Rolling-shutter rectification of the intensity image.
//!
//! A rolling-shutter camera exposes its rows one after the other over the readout time, so
//! while it turns each row sees the scene from a slightly different orientation. Between two
//! consecutive frames the distortion is nearly the same (the camera turns alike) and cancels
//! in the alignment; between a loop's keyframes, taken while the camera turned differently, it
//! does not, and biases the relative pose by about the readout time times the difference of
//! the angular velocities (docs/notes.md). The image is rectified to the orientation at the
//! middle row's time with the camera's angular velocity; the translation within a readout
//! is left out (millimetres at walking speed).

use glam::{DMat3, DQuat, DVec3};
use rayon::prelude::*;

use crate::camera::PinholeCamera;
use crate::geometry::Se3;
use crate::image::{ImageF32, RgbdFrame};

/// Below this largest image shift (pixels) the rectification is skipped: resampling would
/// blur the image more than the distortion moves it.
const MIN_SHIFT_PX: f64 = 0.1;

/// The angular velocity (rad/s, camera frame) of a motion `prev_from_cur` over `interval`
/// seconds; `None` for an interval that is not positive and finite.
pub(crate) fn angular_velocity(prev_from_cur: &Se3, interval: f64) -> Option<DVec3> {
    if !(interval > 0.0 && interval.is_finite()) {
        return None;
    }
    let (axis, angle) = prev_from_cur.rotation.to_axis_angle();
    let w = axis * (angle / interval);
    w.is_finite().then_some(w)
}

/// `frame` with its intensity rectified to the middle row's exposure time: row `v` was
/// exposed `(v / height - 1/2) readout` seconds after the middle row, while the camera turned
/// at `omega` (rad/s, camera frame). Bilinear resampling; pixels whose source falls outside
/// the image take the nearest border pixel. `None` when the largest shift is below a tenth of
/// a pixel (nothing to rectify).
pub(crate) fn rectify(
    frame: &RgbdFrame,
    camera: &PinholeCamera,
    omega: DVec3,
    readout: f64,
) -> Option<RgbdFrame> {
    let (w, h) = (frame.intensity.width(), frame.intensity.height());
    if w < 2 || h < 2 || !(readout > 0.0) {
        return None;
    }
    let focal = camera.fx.max(camera.fy);
    if 0.5 * readout * omega.length() * focal < MIN_SHIFT_PX {
        return None;
    }
    let src = frame.intensity.data();
    let mut out = vec![0.0f32; w * h];
    let (fx, fy, cx, cy) = (camera.fx, camera.fy, camera.cx, camera.cy);
    let (xmax, ymax) = ((w - 1) as f32, (h - 1) as f32);
    out.par_chunks_mut(w).enumerate().for_each(|(v, row)| {
        let tau = (v as f64 / h as f64 - 0.5) * readout;
        // The ray of the middle-row camera seen from the camera at row v's time.
        let r = DMat3::from_quat(DQuat::from_scaled_axis(-omega * tau));
        // The ray of pixel (u, v) is (u - cx)/fx * ex + ((v - cy)/fy, 1): linear in u, so
        // its projection is a ratio of two linear functions of u. Pixel coordinates
        // below a few thousand keep f32 well under a thousandth of a pixel.
        let a = r * DVec3::new(-cx / fx, (v as f64 - cy) / fy, 1.0);
        let b = r * DVec3::new(1.0 / fx, 0.0, 0.0);
        let (ax, ay, az) = ((fx * a.x) as f32, (fy * a.y) as f32, a.z as f32);
        let (bx, by, bz) = ((fx * b.x) as f32, (fy * b.y) as f32, b.z as f32);
        let (cx, cy) = (cx as f32, cy as f32);
        for (u, px) in row.iter_mut().enumerate() {
            let uf = u as f32;
            let z = az + bz * uf;
            let (x, y) = if z > 1e-6 {
                let inv = 1.0 / z;
                ((ax + bx * uf) * inv + cx, (ay + by * uf) * inv + cy)
            } else {
                (uf, v as f32)
            };
            *px = bilinear_clamped(src, w, h, x.clamp(0.0, xmax), y.clamp(0.0, ymax));
        }
    });
    let intensity = ImageF32::from_vec(w, h, out)?;
    Some(RgbdFrame {
        timestamp: frame.timestamp,
        intensity,
        inverse_depth: frame.inverse_depth.clone(),
        colour: frame.colour.clone(),
    })
}

/// Bilinear sample of a `w` x `h` row-major image at `(x, y)`, both already clamped to the
/// image (`0 <= x <= w - 1`, `0 <= y <= h - 1`, `w, h >= 2`).
#[inline]
fn bilinear_clamped(img: &[f32], w: usize, h: usize, x: f32, y: f32) -> f32 {
    let (x0, y0) = ((x as usize).min(w - 2), (y as usize).min(h - 2));
    let (fx, fy) = (x - x0 as f32, y - y0 as f32);
    let i = y0 * w + x0;
    let (top, bottom) = (&img[i..i + 2], &img[i + w..i + w + 2]);
    let t = top[0] + (top[1] - top[0]) * fx;
    let b = bottom[0] + (bottom[1] - bottom[0]) * fx;
    t + (b - t) * fy
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Intensity of a scene at infinity seen along `d` (camera-frame ray of the middle-row
    /// camera, unit or not): a smooth pattern over the directions.
    fn scene(d: DVec3) -> f32 {
        let (x, y) = (d.x / d.z, d.y / d.z);
        (128.0 + 60.0 * (9.0 * x).sin() * (7.0 * y).cos() + 40.0 * (23.0 * x + 11.0 * y).sin())
            as f32
    }

    /// An image of the scene where row `v` is exposed while the camera has turned by
    /// `omega * tau(v)` from its middle-row orientation (`tau = 0` everywhere: global shutter).
    fn render(camera: &PinholeCamera, omega: DVec3, readout: f64) -> RgbdFrame {
        let (w, h) = (camera.width as usize, camera.height as usize);
        let mut data = Vec::with_capacity(w * h);
        for v in 0..h {
            let tau = (v as f64 / h as f64 - 0.5) * readout;
            // The camera at row v's time is turned by exp(omega tau) from the middle-row one:
            // its ray d is the middle-row camera's ray exp(omega tau) d.
            let mid_from_row = DMat3::from_quat(DQuat::from_scaled_axis(omega * tau));
            for u in 0..w {
                let d = DVec3::new(
                    (u as f64 - camera.cx) / camera.fx,
                    (v as f64 - camera.cy) / camera.fy,
                    1.0,
                );
                data.push(scene(mid_from_row * d));
            }
        }
        let intensity = ImageF32::from_vec(w, h, data).expect("sized");
        let depth = ImageF32::from_vec(w, h, vec![0.5; w * h]).expect("sized");
        RgbdFrame::new(0.0, intensity, depth).expect("valid frame")
    }

    fn mean_abs(a: &RgbdFrame, b: &RgbdFrame, border: usize) -> f64 {
        let (w, h) = (a.intensity.width(), a.intensity.height());
        let mut sum = 0.0;
        let mut n = 0;
        for v in border..h - border {
            for u in border..w - border {
                sum += (a.intensity.at(u, v) - b.intensity.at(u, v)).abs() as f64;
                n += 1;
            }
        }
        sum / n as f64
    }

    #[test]
    fn rectification_undoes_a_rolling_shutter_turn() {
        let mut camera = PinholeCamera::new(260.0, 260.0, 79.5, 59.5, 160, 120);
        camera.readout = 0.03;
        // 1.5 rad/s about an axis mostly vertical, as a turning head.
        let omega = DVec3::new(0.3, 1.4, 0.2);
        let global = render(&camera, omega, 0.0);
        let rolling = render(&camera, omega, camera.readout);
        let before = mean_abs(&rolling, &global, 8);
        let rectified = rectify(&rolling, &camera, omega, camera.readout).expect("a turn");
        let after = mean_abs(&rectified, &global, 8);
        assert!(before > 5.0, "the rolling shutter must show: {before}");
        assert!(after < 0.1 * before, "rectified {after} against {before}");
        // The wrong direction of readout makes it worse, not better.
        let wrong = rectify(&rolling, &camera, -omega, camera.readout).expect("a turn");
        assert!(mean_abs(&wrong, &global, 8) > before);
        // The depth map is not touched.
        assert_eq!(rectified.inverse_depth.data(), rolling.inverse_depth.data());
    }

    #[test]
    fn slow_turns_and_global_shutters_are_left_alone() {
        let camera = PinholeCamera::new(260.0, 260.0, 79.5, 59.5, 160, 120);
        let frame = render(&camera, DVec3::ZERO, 0.0);
        assert!(rectify(&frame, &camera, DVec3::new(0.0, 1.0, 0.0), 0.0).is_none());
        // 0.01 rad/s over 30 ms moves a pixel by 0.04 px at f = 260.
        assert!(rectify(&frame, &camera, DVec3::new(0.0, 0.01, 0.0), 0.03).is_none());
    }

    #[test]
    fn angular_velocity_of_a_motion() {
        let m = Se3::new(
            DQuat::from_scaled_axis(DVec3::new(0.0, 0.05, 0.0)),
            DVec3::X,
        );
        let w = angular_velocity(&m, 0.05).expect("valid interval");
        assert!((w - DVec3::new(0.0, 1.0, 0.0)).length() < 1e-9);
        assert!(angular_velocity(&m, 0.0).is_none());
        assert!(angular_velocity(&m, f64::NAN).is_none());
    }
}
