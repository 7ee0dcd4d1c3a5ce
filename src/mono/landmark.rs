//! Anchored inverse-depth landmarks (thesis eq. 2.15, 2.33-2.35, 2.44-2.50; Civera, Davison
//! and Montiel 2008).
//!
//! A landmark is `y = (x_a, y_a, z_a, theta, phi, rho)`: the anchor (the camera centre when it
//! was first seen, metres, world frame), the azimuth and elevation of its ray (radians, world
//! frame) with unit direction `m(theta, phi) = (cos phi sin theta, -sin phi, cos phi cos theta)`,
//! and the inverse depth `rho` along that ray (1/m). The point is `anchor + m / rho`.
//!
//! Measurement: the ray in the camera frame, scaled by `rho` so that points at infinity
//! (`rho = 0`) are fine, `h_c = R^T (rho (anchor - r) + m)`, projected by the unified model
//! (whose projection is invariant to positive scaling of the point).

use glam::{DMat3, DVec2, DVec3};
use nalgebra::SMatrix;

use super::state::CameraState;
use crate::camera::UnifiedCamera;
use crate::geometry::skew;

/// Size of a landmark's parametrisation.
pub const LANDMARK_DIM: usize = 6;

/// 2x6 Jacobian.
pub type Mat2x6 = SMatrix<f64, 2, 6>;

/// An anchored inverse-depth landmark.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct InverseDepthLandmark {
    /// Anchor (camera centre at initialisation), world frame, metres.
    pub anchor: DVec3,
    /// Azimuth of the ray, radians (world frame, about the y axis from +z towards +x).
    pub theta: f64,
    /// Elevation of the ray, radians (positive towards -y).
    pub phi: f64,
    /// Inverse depth along the ray, 1/m.
    pub rho: f64,
}

/// The unit direction of azimuth `theta` and elevation `phi` (radians).
pub fn ray_direction(theta: f64, phi: f64) -> DVec3 {
    DVec3::new(phi.cos() * theta.sin(), -phi.sin(), phi.cos() * theta.cos())
}

/// Azimuth and elevation (radians) of a non-zero direction.
pub fn azimuth_elevation(d: DVec3) -> (f64, f64) {
    (d.x.atan2(d.z), (-d.y).atan2((d.x * d.x + d.z * d.z).sqrt()))
}

/// 2x3 Jacobian of [`azimuth_elevation`] with respect to the direction.
pub fn azimuth_elevation_jacobian(d: DVec3) -> [[f64; 3]; 2] {
    let rxz2 = (d.x * d.x + d.z * d.z).max(1e-300);
    let rxz = rxz2.sqrt();
    let n = rxz2 + d.y * d.y;
    [
        [d.z / rxz2, 0.0, -d.x / rxz2],
        [d.x * d.y / (n * rxz), -rxz / n, d.z * d.y / (n * rxz)],
    ]
}

/// A landmark's predicted measurement with its Jacobians.
#[derive(Clone, Copy, Debug)]
pub struct Prediction {
    /// Predicted pixel.
    pub uv: DVec2,
    /// The ray in the camera frame (scaled by rho, see the module docs).
    pub ray_camera: DVec3,
    /// Jacobian with respect to the camera's position and rotation error, `[dr, dtheta]`.
    pub d_camera: Mat2x6,
    /// Jacobian with respect to the landmark's six parameters.
    pub d_landmark: Mat2x6,
}

fn mat3_to_rows(m: DMat3) -> [[f64; 3]; 3] {
    let c = m.to_cols_array_2d();
    [
        [c[0][0], c[1][0], c[2][0]],
        [c[0][1], c[1][1], c[2][1]],
        [c[0][2], c[1][2], c[2][2]],
    ]
}

impl InverseDepthLandmark {
    /// Unit ray direction, world frame.
    pub fn direction(&self) -> DVec3 {
        ray_direction(self.theta, self.phi)
    }

    /// The Euclidean point (world frame, metres); `None` for `rho <= 0` (at or beyond
    /// infinity).
    pub fn point(&self) -> Option<DVec3> {
        (self.rho > 1e-9).then(|| self.anchor + self.direction() / self.rho)
    }

    /// The scaled ray `h_c = R^T (rho (anchor - r) + m)` in the camera frame.
    pub fn ray_in_camera(&self, cam: &CameraState) -> DVec3 {
        cam.rotation.conjugate() * (self.rho * (self.anchor - cam.position) + self.direction())
    }

    /// Predicted pixel and Jacobians (eq. 2.33-2.35); `None` when the landmark is not in
    /// front of the camera model's visible part of the sphere.
    pub fn predict(&self, camera: &UnifiedCamera, cam: &CameraState) -> Option<Prediction> {
        let m = self.direction();
        let d = self.rho * (self.anchor - cam.position) + m;
        let rt = DMat3::from_quat(cam.rotation.conjugate());
        let hc = rt * d;
        let uv = camera.project(hc)?;
        let jp = camera.project_jacobian(hc);
        let jp = SMatrix::<f64, 2, 3>::from_row_slice(&[
            jp[0][0], jp[0][1], jp[0][2], jp[1][0], jp[1][1], jp[1][2],
        ]);
        let to = |m: DMat3| {
            let r = mat3_to_rows(m);
            SMatrix::<f64, 3, 3>::from_row_slice(&[
                r[0][0], r[0][1], r[0][2], r[1][0], r[1][1], r[1][2], r[2][0], r[2][1], r[2][2],
            ])
        };
        let rt_n = to(rt);
        let d_r = rt_n * (-self.rho);
        let d_th = to(rt * skew(d));
        let (st, ct) = self.theta.sin_cos();
        let (sp, cp) = self.phi.sin_cos();
        let dm_dtheta = DVec3::new(cp * ct, 0.0, -cp * st);
        let dm_dphi = DVec3::new(-sp * st, -cp, -sp * ct);
        let col = |v: DVec3| {
            let w = rt * v;
            nalgebra::Vector3::new(w.x, w.y, w.z)
        };
        let mut d_cam = SMatrix::<f64, 3, 6>::zeros();
        d_cam.fixed_view_mut::<3, 3>(0, 0).copy_from(&d_r);
        d_cam.fixed_view_mut::<3, 3>(0, 3).copy_from(&d_th);
        let mut d_lm = SMatrix::<f64, 3, 6>::zeros();
        d_lm.fixed_view_mut::<3, 3>(0, 0)
            .copy_from(&(rt_n * self.rho));
        d_lm.set_column(3, &col(dm_dtheta));
        d_lm.set_column(4, &col(dm_dphi));
        d_lm.set_column(5, &col(self.anchor - cam.position));
        Some(Prediction {
            uv,
            ray_camera: hc,
            d_camera: jp * d_cam,
            d_landmark: jp * d_lm,
        })
    }

    /// Applies a correction to the six parameters.
    pub fn corrected(&self, d: &[f64]) -> InverseDepthLandmark {
        InverseDepthLandmark {
            anchor: self.anchor + DVec3::new(d[0], d[1], d[2]),
            theta: self.theta + d[3],
            phi: self.phi + d[4],
            rho: self.rho + d[5],
        }
    }

    /// Linearity index of the inverse-depth to Euclidean conversion (Civera et al. 2008):
    /// `4 sigma_d |cos alpha| / d_1`, with `sigma_d = sigma_rho / rho^2`, `d_1` the distance
    /// from the current camera and `alpha` the angle between the anchor's ray and the current
    /// one. Small values (< 0.1) mean the landmark is well described as a 3D point. Infinite
    /// for `rho <= 0`.
    pub fn linearity_index(&self, sigma_rho: f64, camera_position: DVec3) -> f64 {
        let Some(p) = self.point() else {
            return f64::INFINITY;
        };
        let h = p - camera_position;
        let d1 = h.length();
        if d1 < 1e-12 {
            return f64::INFINITY;
        }
        let cos_a = self.direction().dot(h) / d1;
        4.0 * sigma_rho / (self.rho * self.rho) * cos_a.abs() / d1
    }
}

/// A new landmark from a pixel seen by a camera, with the Jacobians of its parameters with
/// respect to the camera's `[dr, dtheta]` (6x6), the pixel (6x2) and the initial inverse
/// depth (6x1) (eq. 2.44-2.50), from which its covariance and cross-covariances follow.
pub struct Initialisation {
    /// The landmark.
    pub landmark: InverseDepthLandmark,
    /// d landmark / d [dr, dtheta].
    pub d_camera: SMatrix<f64, 6, 6>,
    /// d landmark / d pixel.
    pub d_pixel: SMatrix<f64, 6, 2>,
    /// d landmark / d rho0.
    pub d_rho: SMatrix<f64, 6, 1>,
}

/// Initialises a landmark at pixel `uv` with inverse depth `rho0` (1/m) (see
/// [`Initialisation`]); `None` where the pixel has no pre-image.
pub fn initialise(
    camera: &UnifiedCamera,
    cam: &CameraState,
    uv: DVec2,
    rho0: f64,
) -> Option<Initialisation> {
    let s = camera.unproject(uv)?;
    let r = DMat3::from_quat(cam.rotation);
    let d = r * s;
    let (theta, phi) = azimuth_elevation(d);
    let jae = azimuth_elevation_jacobian(d);
    let jae = SMatrix::<f64, 2, 3>::from_row_slice(&[
        jae[0][0], jae[0][1], jae[0][2], jae[1][0], jae[1][1], jae[1][2],
    ]);
    let to = |m: DMat3| {
        let r = mat3_to_rows(m);
        SMatrix::<f64, 3, 3>::from_row_slice(&[
            r[0][0], r[0][1], r[0][2], r[1][0], r[1][1], r[1][2], r[2][0], r[2][1], r[2][2],
        ])
    };
    // d = exp(dtheta) R s  =>  dd/ddtheta = -[d]x
    let dd_dth = to(skew(d)) * -1.0;
    let ju = camera.unproject_jacobian(uv);
    let ju = SMatrix::<f64, 3, 2>::from_row_slice(&[
        ju[0][0], ju[0][1], ju[1][0], ju[1][1], ju[2][0], ju[2][1],
    ]);
    let mut d_camera = SMatrix::<f64, 6, 6>::zeros();
    d_camera
        .fixed_view_mut::<3, 3>(0, 0)
        .copy_from(&SMatrix::<f64, 3, 3>::identity());
    d_camera
        .fixed_view_mut::<2, 3>(3, 3)
        .copy_from(&(jae * dd_dth));
    let mut d_pixel = SMatrix::<f64, 6, 2>::zeros();
    d_pixel
        .fixed_view_mut::<2, 2>(3, 0)
        .copy_from(&(jae * to(r) * ju));
    let mut d_rho = SMatrix::<f64, 6, 1>::zeros();
    d_rho[5] = 1.0;
    Some(Initialisation {
        landmark: InverseDepthLandmark {
            anchor: cam.position,
            theta,
            phi,
            rho: rho0,
        },
        d_camera,
        d_pixel,
        d_rho,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::so3_exp;

    fn cams() -> Vec<UnifiedCamera> {
        vec![
            UnifiedCamera::new(0.0, 260.0, 159.5, 119.5, 320, 240),
            UnifiedCamera::catadioptric(400, 400),
        ]
    }

    fn cam_state() -> CameraState {
        CameraState {
            position: DVec3::new(0.2, -0.1, 0.3),
            rotation: so3_exp(DVec3::new(0.1, 0.3, -0.2)),
            velocity: DVec3::ZERO,
            angular_velocity: DVec3::ZERO,
        }
    }

    fn landmarks() -> Vec<InverseDepthLandmark> {
        let c = cam_state();
        [
            DVec3::new(0.5, 0.2, 3.0),
            DVec3::new(-1.0, -0.5, 2.0),
            DVec3::new(1.5, 0.3, 0.8),
        ]
        .iter()
        .map(|p| {
            let (theta, phi) = azimuth_elevation(*p - DVec3::new(0.0, 0.0, -0.1));
            let _ = c;
            InverseDepthLandmark {
                anchor: DVec3::new(0.0, 0.0, -0.1),
                theta,
                phi,
                rho: 0.4,
            }
        })
        .collect()
    }

    #[test]
    fn direction_round_trip() {
        for d in [
            DVec3::new(0.3, -0.2, 1.0),
            DVec3::new(-1.0, 0.5, -0.4),
            DVec3::new(0.01, 0.99, 0.1),
        ] {
            let (t, p) = azimuth_elevation(d);
            assert!((ray_direction(t, p) - d.normalize()).length() < 1e-12);
        }
    }

    #[test]
    fn measurement_jacobians_match_finite_differences() {
        let h = 1e-6;
        for camera in cams() {
            let c = cam_state();
            for lm in landmarks() {
                let Some(p) = lm.predict(&camera, &c) else {
                    continue;
                };
                for k in 0..6 {
                    let mut d = [0.0; 12];
                    d[k] = h;
                    let a = lm.predict(&camera, &c.corrected(&d)).unwrap().uv;
                    d[k] = -h;
                    let b = lm.predict(&camera, &c.corrected(&d)).unwrap().uv;
                    let num = (a - b) / (2.0 * h);
                    assert!((num.x - p.d_camera[(0, k)]).abs() < 1e-4 * (1.0 + num.x.abs()));
                    assert!((num.y - p.d_camera[(1, k)]).abs() < 1e-4 * (1.0 + num.y.abs()));
                    let mut e = [0.0; 6];
                    e[k] = h;
                    let a = lm.corrected(&e).predict(&camera, &c).unwrap().uv;
                    e[k] = -h;
                    let b = lm.corrected(&e).predict(&camera, &c).unwrap().uv;
                    let num = (a - b) / (2.0 * h);
                    assert!(
                        (num.x - p.d_landmark[(0, k)]).abs() < 1e-4 * (1.0 + num.x.abs()),
                        "landmark k={k}"
                    );
                    assert!((num.y - p.d_landmark[(1, k)]).abs() < 1e-4 * (1.0 + num.y.abs()));
                }
            }
        }
    }

    #[test]
    fn initialisation_jacobians_match_finite_differences() {
        let h = 1e-6;
        let param =
            |l: &InverseDepthLandmark| [l.anchor.x, l.anchor.y, l.anchor.z, l.theta, l.phi, l.rho];
        for camera in cams() {
            let c = cam_state();
            let uv = DVec2::new(
                f64::from(camera.width) * 0.3,
                f64::from(camera.height) * 0.6,
            );
            let init = initialise(&camera, &c, uv, 0.5).unwrap();
            // Re-observing the new landmark from the same camera gives back the pixel.
            let back = init.landmark.predict(&camera, &c).unwrap().uv;
            assert!((back - uv).length() < 1e-6);
            for k in 0..6 {
                let mut d = [0.0; 12];
                d[k] = h;
                let a = param(
                    &initialise(&camera, &c.corrected(&d), uv, 0.5)
                        .unwrap()
                        .landmark,
                );
                d[k] = -h;
                let b = param(
                    &initialise(&camera, &c.corrected(&d), uv, 0.5)
                        .unwrap()
                        .landmark,
                );
                for r in 0..6 {
                    let num = (a[r] - b[r]) / (2.0 * h);
                    assert!(
                        (num - init.d_camera[(r, k)]).abs() < 1e-6,
                        "cam r={r} k={k}"
                    );
                }
            }
            for k in 0..2 {
                let mut du = DVec2::ZERO;
                du[k] = 1e-4;
                let a = param(&initialise(&camera, &c, uv + du, 0.5).unwrap().landmark);
                let b = param(&initialise(&camera, &c, uv - du, 0.5).unwrap().landmark);
                for r in 0..6 {
                    let num = (a[r] - b[r]) / 2e-4;
                    assert!(
                        (num - init.d_pixel[(r, k)]).abs() < 1e-7,
                        "pixel r={r} k={k}"
                    );
                }
            }
        }
    }

    #[test]
    fn linearity_index_drops_with_parallax() {
        let lm = InverseDepthLandmark {
            anchor: DVec3::ZERO,
            theta: 0.0,
            phi: 0.0,
            rho: 0.5,
        };
        let along = lm.linearity_index(0.01, DVec3::new(0.0, 0.0, 0.1));
        let side = lm.linearity_index(0.01, DVec3::new(1.9, 0.0, 1.9));
        assert!(side < along);
        assert!(lm.linearity_index(0.5, DVec3::ZERO) > 0.1);
        let far = InverseDepthLandmark { rho: 0.0, ..lm };
        assert!(far.linearity_index(0.1, DVec3::ZERO).is_infinite());
    }
}
