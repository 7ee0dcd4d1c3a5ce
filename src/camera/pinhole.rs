use glam::{DVec2, DVec3};

/// Errors from camera models and their parameters.
#[derive(Debug, thiserror::Error)]
pub enum CameraError {
    /// A parameter is not finite or not positive where it must be.
    #[error("invalid camera parameter {name} = {value}: {why}")]
    InvalidParameter {
        /// Parameter name.
        name: &'static str,
        /// Offending value.
        value: f64,
        /// What is required.
        why: &'static str,
    },
}

/// Brown-Conrady radial-tangential distortion (OpenCV order `k1 k2 p1 p2 k3`), applied to
/// normalised image coordinates `(x/z, y/z)`.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct BrownConrady {
    /// Radial coefficient of r^2.
    pub k1: f64,
    /// Radial coefficient of r^4.
    pub k2: f64,
    /// Tangential coefficient.
    pub p1: f64,
    /// Tangential coefficient.
    pub p2: f64,
    /// Radial coefficient of r^6.
    pub k3: f64,
}

impl BrownConrady {
    /// True when all coefficients are zero.
    pub fn is_zero(&self) -> bool {
        self.k1 == 0.0 && self.k2 == 0.0 && self.p1 == 0.0 && self.p2 == 0.0 && self.k3 == 0.0
    }

    /// Distorts normalised coordinates.
    pub fn distort(&self, n: DVec2) -> DVec2 {
        let (x, y) = (n.x, n.y);
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
        DVec2::new(
            x * radial + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x),
            y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y,
        )
    }

    /// Inverts [`Self::distort`] by fixed-point iteration (converges for the mild distortion
    /// of RGB-D cameras).
    pub fn undistort(&self, d: DVec2) -> DVec2 {
        let mut n = d;
        for _ in 0..20 {
            let e = self.distort(n) - d;
            n -= e;
            if e.length_squared() < 1e-24 {
                break;
            }
        }
        n
    }
}

/// Pinhole camera intrinsics in pixels, with optional distortion of the *raw* images.
///
/// The odometry works on undistorted images; `distortion` describes how raw images must be
/// resampled (see `io::undistort`).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct PinholeCamera {
    /// Focal length along x, pixels.
    pub fx: f64,
    /// Focal length along y, pixels.
    pub fy: f64,
    /// Principal point x, pixels (pixel centres are integers).
    pub cx: f64,
    /// Principal point y, pixels.
    pub cy: f64,
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
    /// Distortion of the raw images (zero for none).
    #[serde(default)]
    pub distortion: BrownConrady,
    /// Rolling-shutter readout time of the intensity image: seconds from the exposure of the
    /// first row to that of the last (row 0 first); 0 for a global shutter. The odometry
    /// rectifies each frame for it (the odometry configuration's `rolling_shutter`).
    #[serde(default)]
    pub readout: f64,
}

impl PinholeCamera {
    /// An undistorted pinhole camera.
    pub fn new(fx: f64, fy: f64, cx: f64, cy: f64, width: u32, height: u32) -> Self {
        Self {
            fx,
            fy,
            cx,
            cy,
            width,
            height,
            distortion: BrownConrady::default(),
            readout: 0.0,
        }
    }

    /// Checks that the parameters are finite and positive where needed.
    pub fn validate(&self) -> Result<(), CameraError> {
        for (name, value) in [("fx", self.fx), ("fy", self.fy)] {
            if !(value.is_finite() && value > 0.0) {
                return Err(CameraError::InvalidParameter {
                    name,
                    value,
                    why: "must be finite and > 0",
                });
            }
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
        if !(self.readout.is_finite() && (0.0..1.0).contains(&self.readout)) {
            return Err(CameraError::InvalidParameter {
                name: "readout",
                value: self.readout,
                why: "must be in [0, 1) s",
            });
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

    /// Projects a point in the camera frame (metres) to pixels; `None` behind the camera.
    pub fn project(&self, p: DVec3) -> Option<DVec2> {
        if p.z <= 1e-9 {
            return None;
        }
        Some(DVec2::new(
            self.fx * p.x / p.z + self.cx,
            self.fy * p.y / p.z + self.cy,
        ))
    }

    /// Back-projects pixel `(u, v)` at depth `z` (metres) to a point in the camera frame.
    pub fn unproject(&self, uv: DVec2, z: f64) -> DVec3 {
        DVec3::new(
            (uv.x - self.cx) / self.fx * z,
            (uv.y - self.cy) / self.fy * z,
            z,
        )
    }

    /// The intrinsics of pyramid level `level` (each level halves the resolution; pixel
    /// centres stay at integers, so `c' = (c + 0.5) / 2 - 0.5`).
    pub fn at_level(&self, level: usize) -> PinholeCamera {
        let mut c = *self;
        for _ in 0..level {
            c.fx *= 0.5;
            c.fy *= 0.5;
            c.cx = (c.cx + 0.5) * 0.5 - 0.5;
            c.cy = (c.cy + 0.5) * 0.5 - 0.5;
            c.width /= 2;
            c.height /= 2;
        }
        c.distortion = BrownConrady::default();
        c
    }

    /// 2x3 Jacobian of [`Self::project`] with respect to the point, row-major.
    pub fn project_jacobian(&self, p: DVec3) -> [[f64; 3]; 2] {
        let iz = 1.0 / p.z;
        [
            [self.fx * iz, 0.0, -self.fx * p.x * iz * iz],
            [0.0, self.fy * iz, -self.fy * p.y * iz * iz],
        ]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn project_unproject_round_trip() {
        let c = PinholeCamera::new(525.0, 525.0, 319.5, 239.5, 640, 480);
        let p = DVec3::new(0.3, -0.2, 1.7);
        let uv = c.project(p).unwrap();
        assert!((c.unproject(uv, p.z) - p).length() < 1e-12);
    }

    #[test]
    fn projection_jacobian_matches_finite_differences() {
        let c = PinholeCamera::new(525.0, 520.0, 319.5, 239.5, 640, 480);
        let p = DVec3::new(0.3, -0.2, 1.7);
        let j = c.project_jacobian(p);
        let h = 1e-6;
        for k in 0..3 {
            let mut dp = DVec3::ZERO;
            dp[k] = h;
            let d = (c.project(p + dp).unwrap() - c.project(p - dp).unwrap()) / (2.0 * h);
            assert!((d.x - j[0][k]).abs() < 1e-5 && (d.y - j[1][k]).abs() < 1e-5);
        }
    }

    #[test]
    fn undistort_inverts_distort() {
        let d = BrownConrady {
            k1: 0.2624,
            k2: -0.9531,
            p1: -0.0054,
            p2: 0.0026,
            k3: 1.1633,
        };
        let n = DVec2::new(0.4, -0.3);
        assert!((d.undistort(d.distort(n)) - n).length() < 1e-10);
    }

    #[test]
    fn level_intrinsics_keep_pixel_centres() {
        let c = PinholeCamera::new(525.0, 525.0, 319.5, 239.5, 640, 480).at_level(1);
        assert_eq!((c.cx, c.cy, c.width, c.height), (159.5, 119.5, 320, 240));
    }
}
