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

use super::avx2;
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
    rectify_with(frame, camera, omega, readout, avx2())
}

/// [`rectify`], in AVX2 lanes where `lanes` is true and the CPU has AVX2.
fn rectify_with(
    frame: &RgbdFrame,
    camera: &PinholeCamera,
    omega: DVec3,
    readout: f64,
    lanes: bool,
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
    let lanes = lanes && avx2() && src.len() >= w * h && w * h + w < i32::MAX as usize;
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
        let line = RowMap {
            a: [ax, ay, az],
            b: [bx, by, bz],
            c: [cx as f32, cy as f32],
            v: v as f32,
            max: [xmax, ymax],
        };
        let mut u = 0;
        #[cfg(target_arch = "x86_64")]
        if lanes {
            // SAFETY: AVX2 is present and the image's size fits the gathers (`lanes`).
            u = unsafe { rectify_row_avx2(&line, src, w, h, row) };
        }
        for (u, px) in row.iter_mut().enumerate().skip(u) {
            *px = line.sample(src, w, h, u as f32);
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

/// The source position of one output row: output pixel `u` comes from
/// `((a.x + b.x u) / (a.z + b.z u) + c.x, (a.y + b.y u) / (a.z + b.z u) + c.y)`, clamped to the
/// image (its own position `(u, v)` where the ray turns behind the camera).
struct RowMap {
    a: [f32; 3],
    b: [f32; 3],
    c: [f32; 2],
    v: f32,
    /// Largest x and y inside the image (`w - 1`, `h - 1`).
    max: [f32; 2],
}

impl RowMap {
    /// The rectified intensity of pixel `u` of the row, sampled from `img` (`w` x `h`).
    #[inline]
    fn sample(&self, img: &[f32], w: usize, h: usize, uf: f32) -> f32 {
        let z = self.a[2] + self.b[2] * uf;
        let (x, y) = if z > 1e-6 {
            let inv = 1.0 / z;
            (
                (self.a[0] + self.b[0] * uf) * inv + self.c[0],
                (self.a[1] + self.b[1] * uf) * inv + self.c[1],
            )
        } else {
            (uf, self.v)
        };
        bilinear_clamped(
            img,
            w,
            h,
            x.clamp(0.0, self.max[0]),
            y.clamp(0.0, self.max[1]),
        )
    }
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

/// [`RowMap::sample`] for the row's pixels eight at a time, with the same operations in the
/// same order (separate multiplies and adds, a true division), so the values are those of the
/// scalar loop. Returns the number of pixels written; the caller does the tail.
///
/// # Safety
/// The CPU has AVX2; `img` holds at least `w * h` values, `w, h >= 2` and `w * h + w` fits an
/// `i32`.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn rectify_row_avx2(m: &RowMap, img: &[f32], w: usize, h: usize, row: &mut [f32]) -> usize {
    use std::arch::x86_64::*;
    let set = |v: f32| _mm256_set1_ps(v);
    let (ax, ay, az) = (set(m.a[0]), set(m.a[1]), set(m.a[2]));
    let (bx, by, bz) = (set(m.b[0]), set(m.b[1]), set(m.b[2]));
    let (cx, cy) = (set(m.c[0]), set(m.c[1]));
    let (xmax, ymax) = (set(m.max[0]), set(m.max[1]));
    let (zero, one, eps, vrow) = (_mm256_setzero_ps(), set(1.0), set(1e-6), set(m.v));
    let (wm2, hm2) = (
        _mm256_set1_epi32(w as i32 - 2),
        _mm256_set1_epi32(h as i32 - 2),
    );
    let (wi, one_i) = (_mm256_set1_epi32(w as i32), _mm256_set1_epi32(1));
    let step = _mm256_setr_ps(0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0);
    let base = img.as_ptr();
    let mut u = 0;
    while u + 8 <= row.len() {
        let uf = _mm256_add_ps(set(u as f32), step);
        let z = _mm256_add_ps(az, _mm256_mul_ps(bz, uf));
        let ahead = _mm256_cmp_ps::<_CMP_GT_OQ>(z, eps);
        let inv = _mm256_div_ps(one, z);
        let xr = _mm256_add_ps(
            _mm256_mul_ps(_mm256_add_ps(ax, _mm256_mul_ps(bx, uf)), inv),
            cx,
        );
        let yr = _mm256_add_ps(
            _mm256_mul_ps(_mm256_add_ps(ay, _mm256_mul_ps(by, uf)), inv),
            cy,
        );
        let x = _mm256_blendv_ps(uf, xr, ahead);
        let y = _mm256_blendv_ps(vrow, yr, ahead);
        // `clamp(0, max)` of a number (the positions are finite: a finite rotation).
        let x = _mm256_min_ps(_mm256_max_ps(x, zero), xmax);
        let y = _mm256_min_ps(_mm256_max_ps(y, zero), ymax);
        let x0 = _mm256_min_epi32(_mm256_cvttps_epi32(x), wm2);
        let y0 = _mm256_min_epi32(_mm256_cvttps_epi32(y), hm2);
        let fx = _mm256_sub_ps(x, _mm256_cvtepi32_ps(x0));
        let fy = _mm256_sub_ps(y, _mm256_cvtepi32_ps(y0));
        let i = _mm256_add_epi32(_mm256_mullo_epi32(y0, wi), x0);
        let j = _mm256_add_epi32(i, wi);
        // SAFETY: 0 <= x0 <= w - 2 and 0 <= y0 <= h - 2, so i + 1 and i + w + 1 are below
        // w * h <= img.len(); all fit an i32 (caller).
        let (t0, t1, b0, b1) = unsafe {
            (
                _mm256_i32gather_ps::<4>(base, i),
                _mm256_i32gather_ps::<4>(base, _mm256_add_epi32(i, one_i)),
                _mm256_i32gather_ps::<4>(base, j),
                _mm256_i32gather_ps::<4>(base, _mm256_add_epi32(j, one_i)),
            )
        };
        let t = _mm256_add_ps(t0, _mm256_mul_ps(_mm256_sub_ps(t1, t0), fx));
        let b = _mm256_add_ps(b0, _mm256_mul_ps(_mm256_sub_ps(b1, b0), fx));
        let v = _mm256_add_ps(t, _mm256_mul_ps(_mm256_sub_ps(b, t), fy));
        // SAFETY: u + 8 <= row.len().
        unsafe { _mm256_storeu_ps(row.as_mut_ptr().add(u), v) };
        u += 8;
    }
    u
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
    fn lanes_rectify_as_the_scalar_loop() {
        if !avx2() {
            eprintln!("skipped: no AVX2 on this CPU");
            return;
        }
        // A width that is not a multiple of eight: the lanes leave a tail to the scalar loop.
        let mut camera = PinholeCamera::new(300.0, 300.0, 101.3, 60.7, 203, 121);
        camera.readout = 0.04;
        for omega in [DVec3::new(0.3, 1.4, 0.2), DVec3::new(-2.0, 0.5, 3.0)] {
            let rolling = render(&camera, omega, camera.readout);
            let lanes = rectify_with(&rolling, &camera, omega, camera.readout, true);
            let scalar = rectify_with(&rolling, &camera, omega, camera.readout, false);
            let (lanes, scalar) = (lanes.expect("a turn"), scalar.expect("a turn"));
            let bits = |f: &RgbdFrame| {
                f.intensity
                    .data()
                    .iter()
                    .map(|v| v.to_bits())
                    .collect::<Vec<_>>()
            };
            assert_eq!(bits(&lanes), bits(&scalar), "omega {omega}");
        }
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
