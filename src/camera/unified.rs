//! The unified sphere model of central catadioptric (and wide-angle) cameras (Geyer and
//! Daniilidis; Barreto; thesis eq. 2.1-2.7).
//!
//! A point `X` in the camera frame (metres, x right, y down, z forward) is projected onto the
//! unit sphere, `Xs = X / |X|`; the sphere point is seen from a centre shifted by `xi` along
//! -z, giving normalised coordinates `m = (xs / (zs + xi), ys / (zs + xi))`, and pixels
//! `u = gamma * mx + cx`, `v = gamma * my + cy` (`gamma` the generalised focal length in
//! pixels). `xi = 0` is the pinhole model; `xi = 1` a parabolic mirror. Lifting a pixel back
//! to the sphere: with `r2 = mx^2 + my^2`,
//! `eta = (xi + sqrt(1 + (1 - xi^2) r2)) / (r2 + 1)` and `Xs = (eta mx, eta my, eta - xi)`.
//! The mirror's rim limits the image to a circle of radius `fov_radius` around `(cx, cy)`.

use glam::{DVec2, DVec3};

use super::CameraError;

/// Unified sphere camera model.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct UnifiedCamera {
    /// Mirror parameter xi (0 = pinhole, 1 = parabolic), dimensionless, >= 0.
    pub xi: f64,
    /// Generalised focal length gamma, pixels.
    pub gamma: f64,
    /// Principal point x, pixels (pixel centres are integers).
    pub cx: f64,
    /// Principal point y, pixels.
    pub cy: f64,
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
    /// Radius (pixels) of the circular field of view around `(cx, cy)`; `None` = no mask.
    #[serde(default)]
    pub fov_radius: Option<f64>,
    /// Radius (pixels) of the central blind disc (the camera's own reflection); `None` = none.
    #[serde(default)]
    pub inner_radius: Option<f64>,
}

impl UnifiedCamera {
    /// A model without field-of-view mask.
    pub fn new(xi: f64, gamma: f64, cx: f64, cy: f64, width: u32, height: u32) -> Self {
        UnifiedCamera {
            xi,
            gamma,
            cx,
            cy,
            width,
            height,
            fov_radius: None,
            inner_radius: None,
        }
    }

    /// A typical catadioptric camera filling a `width x height` image: xi = 0.9, the mirror
    /// rim at 47% of the smaller image side, and gamma set so that the rim is 15 degrees
    /// above the horizon (the field of view reaches 105 degrees from the optical axis).
    pub fn catadioptric(width: u32, height: u32) -> Self {
        let xi = 0.9;
        let rim = 0.47 * f64::from(width.min(height));
        let theta = 105f64.to_radians();
        // m at polar angle theta: sin / (cos + xi).
        let m = theta.sin() / (theta.cos() + xi);
        UnifiedCamera {
            xi,
            gamma: rim / m,
            cx: f64::from(width) * 0.5 - 0.5,
            cy: f64::from(height) * 0.5 - 0.5,
            width,
            height,
            fov_radius: Some(rim),
            inner_radius: Some(0.08 * f64::from(width.min(height))),
        }
    }

    /// Checks the parameters.
    pub fn validate(&self) -> Result<(), CameraError> {
        if !(self.xi.is_finite() && self.xi >= 0.0) {
            return Err(CameraError::InvalidParameter {
                name: "xi",
                value: self.xi,
                why: "must be finite and >= 0",
            });
        }
        if !(self.gamma.is_finite() && self.gamma > 0.0) {
            return Err(CameraError::InvalidParameter {
                name: "gamma",
                value: self.gamma,
                why: "must be finite and > 0",
            });
        }
        for (name, value) in [("cx", self.cx), ("cy", self.cy)] {
            if !value.is_finite() {
                return Err(CameraError::InvalidParameter {
                    name,
                    value,
                    why: "must be finite",
                });
            }
        }
        if self.width == 0 || self.height == 0 {
            return Err(CameraError::InvalidParameter {
                name: "width/height",
                value: f64::from(self.width.min(self.height)),
                why: "image size must be non-zero",
            });
        }
        Ok(())
    }

    /// True when the point (camera frame) is on the visible part of the sphere: in front of
    /// the projection centre and, for `xi > 1`, not on the hidden far cap.
    fn visible(&self, p: DVec3) -> bool {
        let rho = p.length();
        if rho < 1e-12 {
            return false;
        }
        let zs = p.z / rho;
        if self.xi <= 1.0 {
            zs + self.xi > 1e-9
        } else {
            zs > -1.0 / self.xi + 1e-9
        }
    }

    /// Projects a point in the camera frame (metres) to pixels; `None` when it is not
    /// visible. Does not apply the field-of-view mask (see [`Self::in_fov`]).
    pub fn project(&self, p: DVec3) -> Option<DVec2> {
        if !self.visible(p) {
            return None;
        }
        let rho = p.length();
        let w = p.z + self.xi * rho;
        Some(DVec2::new(
            self.gamma * p.x / w + self.cx,
            self.gamma * p.y / w + self.cy,
        ))
    }

    /// Lifts a pixel to the unit sphere (a unit ray direction in the camera frame); `None`
    /// where the pixel has no pre-image (outside the model's domain).
    pub fn unproject(&self, uv: DVec2) -> Option<DVec3> {
        let mx = (uv.x - self.cx) / self.gamma;
        let my = (uv.y - self.cy) / self.gamma;
        let r2 = mx * mx + my * my;
        let s = 1.0 + (1.0 - self.xi * self.xi) * r2;
        if s < 0.0 {
            return None;
        }
        let eta = (self.xi + s.sqrt()) / (r2 + 1.0);
        let xs = DVec3::new(eta * mx, eta * my, eta - self.xi);
        self.visible(xs).then_some(xs)
    }

    /// True when pixel `uv` lies inside the mirror's circular field of view (and outside the
    /// central blind disc).
    pub fn in_fov(&self, uv: DVec2) -> bool {
        let r = (uv - DVec2::new(self.cx, self.cy)).length();
        self.fov_radius.is_none_or(|f| r <= f) && self.inner_radius.is_none_or(|i| r >= i)
    }

    /// The image mask (row-major, `width * height`): true where a pixel sees the scene.
    pub fn fov_mask(&self) -> Vec<bool> {
        let (w, h) = (self.width as usize, self.height as usize);
        (0..w * h)
            .map(|i| {
                let uv = DVec2::new((i % w) as f64, (i / w) as f64);
                self.in_fov(uv) && self.unproject(uv).is_some()
            })
            .collect()
    }

    /// 2x3 Jacobian of [`Self::project`] with respect to the point, row-major.
    pub fn project_jacobian(&self, p: DVec3) -> [[f64; 3]; 2] {
        let rho = p.length();
        let w = p.z + self.xi * rho;
        let g = self.gamma / (w * w);
        // dw/dp = (xi x / rho, xi y / rho, 1 + xi z / rho)
        let dw = [
            self.xi * p.x / rho,
            self.xi * p.y / rho,
            1.0 + self.xi * p.z / rho,
        ];
        [
            [g * (w - p.x * dw[0]), -g * p.x * dw[1], -g * p.x * dw[2]],
            [-g * p.y * dw[0], g * (w - p.y * dw[1]), -g * p.y * dw[2]],
        ]
    }

    /// 2x4 Jacobian of [`Self::project`] with respect to the parameters `(xi, gamma, cx, cy)`.
    pub fn project_param_jacobian(&self, p: DVec3) -> [[f64; 4]; 2] {
        let rho = p.length();
        let w = p.z + self.xi * rho;
        [
            [-self.gamma * p.x * rho / (w * w), p.x / w, 1.0, 0.0],
            [-self.gamma * p.y * rho / (w * w), p.y / w, 0.0, 1.0],
        ]
    }

    /// 3x2 Jacobian of [`Self::unproject`] (the unit-sphere point) with respect to the pixel.
    pub fn unproject_jacobian(&self, uv: DVec2) -> [[f64; 2]; 3] {
        let mx = (uv.x - self.cx) / self.gamma;
        let my = (uv.y - self.cy) / self.gamma;
        let r2 = mx * mx + my * my;
        let k = 1.0 - self.xi * self.xi;
        let s = (1.0 + k * r2).max(1e-300).sqrt();
        let eta = (self.xi + s) / (r2 + 1.0);
        // d eta / d r2
        let deta = (k / (2.0 * s) * (r2 + 1.0) - (self.xi + s)) / ((r2 + 1.0) * (r2 + 1.0));
        let dm = 1.0 / self.gamma;
        // d r2 / d(mx, my) = (2 mx, 2 my)
        let de = [deta * 2.0 * mx * dm, deta * 2.0 * my * dm];
        [
            [eta * dm + mx * de[0], mx * de[1]],
            [my * de[0], eta * dm + my * de[1]],
            [de[0], de[1]],
        ]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cams() -> Vec<UnifiedCamera> {
        vec![
            UnifiedCamera::new(0.0, 300.0, 319.5, 239.5, 640, 480),
            UnifiedCamera::new(0.8, 260.0, 321.0, 238.0, 640, 480),
            UnifiedCamera::new(1.0, 250.0, 320.0, 240.0, 640, 480),
            UnifiedCamera::new(1.4, 240.0, 318.0, 241.0, 640, 480),
            UnifiedCamera::catadioptric(640, 480),
        ]
    }

    fn points() -> Vec<DVec3> {
        vec![
            DVec3::new(0.3, -0.2, 1.7),
            DVec3::new(-1.0, 0.5, 0.4),
            DVec3::new(2.0, 1.0, -0.3),
            DVec3::new(0.01, 0.02, 3.0),
            DVec3::new(-0.7, -0.9, 0.05),
        ]
    }

    #[test]
    fn pinhole_is_xi_zero() {
        let u = UnifiedCamera::new(0.0, 525.0, 319.5, 239.5, 640, 480);
        let p = crate::camera::PinholeCamera::new(525.0, 525.0, 319.5, 239.5, 640, 480);
        let x = DVec3::new(0.3, -0.2, 1.7);
        assert!((u.project(x).unwrap() - p.project(x).unwrap()).length() < 1e-9);
    }

    #[test]
    fn project_unproject_round_trip() {
        for c in cams() {
            for p in points() {
                let Some(uv) = c.project(p) else {
                    // Only points behind a (near-)pinhole camera are invisible here.
                    assert!(c.xi < 0.5 && p.z < 0.0, "{c:?} {p}");
                    continue;
                };
                let s = c.unproject(uv).expect("pre-image exists");
                assert!(
                    (s - p.normalize()).length() < 1e-9,
                    "{c:?} {p} -> {uv} -> {s}"
                );
                assert!((c.project(s).unwrap() - uv).length() < 1e-7);
            }
            // Pixel -> sphere -> pixel over a grid.
            for v in (0..480).step_by(37) {
                for u in (0..640).step_by(41) {
                    let uv = DVec2::new(u as f64, v as f64);
                    if let Some(s) = c.unproject(uv) {
                        assert!((s.length() - 1.0).abs() < 1e-12);
                        let back = c.project(s).expect("sphere point visible");
                        assert!((back - uv).length() < 1e-6, "{c:?} {uv} -> {back}");
                    }
                }
            }
        }
    }

    #[test]
    fn wide_angle_sees_behind_the_image_plane() {
        let c = UnifiedCamera::catadioptric(640, 480);
        let p = DVec3::new(1.0, 0.0, -0.2);
        let uv = c
            .project(p)
            .expect("points slightly behind are visible with xi = 0.9");
        assert!(c.in_fov(uv));
        assert!(c.project(DVec3::new(0.0, 0.0, -1.0)).is_none());
        let mask = c.fov_mask();
        let inside = mask.iter().filter(|m| **m).count() as f64 / mask.len() as f64;
        assert!(inside > 0.4 && inside < 0.75, "{inside}");
        assert!(!mask[0] && mask[240 * 640 + 320 + 100]);
    }

    #[test]
    fn jacobians_match_finite_differences() {
        let h = 1e-6;
        for c in cams() {
            for p in points() {
                if c.project(p).is_none() {
                    continue;
                }
                let j = c.project_jacobian(p);
                for k in 0..3 {
                    let mut dp = DVec3::ZERO;
                    dp[k] = h;
                    let d = (c.project(p + dp).unwrap() - c.project(p - dp).unwrap()) / (2.0 * h);
                    assert!(
                        (d.x - j[0][k]).abs() < 1e-4 && (d.y - j[1][k]).abs() < 1e-4,
                        "{c:?} {p} k={k}"
                    );
                }
                let jp = c.project_param_jacobian(p);
                for k in 0..4 {
                    let mut a = c;
                    let mut b = c;
                    match k {
                        0 => {
                            a.xi += h;
                            b.xi -= h;
                        }
                        1 => {
                            a.gamma += h;
                            b.gamma -= h;
                        }
                        2 => {
                            a.cx += h;
                            b.cx -= h;
                        }
                        _ => {
                            a.cy += h;
                            b.cy -= h;
                        }
                    }
                    let d = (a.project(p).unwrap() - b.project(p).unwrap()) / (2.0 * h);
                    assert!(
                        (d.x - jp[0][k]).abs() < 1e-4 && (d.y - jp[1][k]).abs() < 1e-4,
                        "param {k}"
                    );
                }
                let uv = c.project(p).unwrap();
                let ju = c.unproject_jacobian(uv);
                for k in 0..2 {
                    let mut du = DVec2::ZERO;
                    du[k] = 1e-4;
                    let d = (c.unproject(uv + du).unwrap() - c.unproject(uv - du).unwrap()) / 2e-4;
                    for r in 0..3 {
                        assert!(
                            (d[r] - ju[r][k]).abs() < 1e-7,
                            "unproject {c:?} {uv} r={r} k={k}"
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn validation_rejects_bad_parameters() {
        assert!(UnifiedCamera::new(-0.1, 300.0, 0.0, 0.0, 10, 10)
            .validate()
            .is_err());
        assert!(UnifiedCamera::new(0.5, 0.0, 0.0, 0.0, 10, 10)
            .validate()
            .is_err());
        assert!(UnifiedCamera::new(0.5, 300.0, f64::NAN, 0.0, 10, 10)
            .validate()
            .is_err());
        assert!(UnifiedCamera::new(0.5, 300.0, 0.0, 0.0, 0, 10)
            .validate()
            .is_err());
        assert!(UnifiedCamera::catadioptric(640, 480).validate().is_ok());
    }
}
