//! Residual and IRLS-weight images of an alignment, for inspection (the viewer's panels,
//! residual plots, debugging a wrong convergence).
//!
//! The images are recomputed on the CPU through the mirror of the kernels (the row loop's
//! per-pixel terms and the IRLS weight), so they are the same for both backends and cost one pass over one pyramid level (a few ms at 320x240). They are laid
//! out on the *reference* frame's pixel grid of that level: pixel `x` holds the residual of
//! the reference pixel `x` warped into the current frame by `cur_from_ref`.

use super::config::OdometryConfig;
use super::cpu::CpuPyramid;
use super::kernel::INVALID_RESIDUAL;
use super::robust::weight;
use super::rows::{pixel_terms, Buffers, Warp};
use super::tracker::warp_params;
use super::OdometryError;
use crate::camera::PinholeCamera;
use crate::geometry::Se3;
use crate::image::{ImageF32, RgbdFrame};

/// Robust scales of the two residual populations (as reported by
/// [`super::FrameStats`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RobustScales {
    /// Photometric scale sigma_I, intensity levels (0-255).
    pub sigma_photo: f64,
    /// Geometric scale sigma_W: 1/m for inverse-depth residuals, m for depth residuals.
    pub sigma_geo: f64,
    /// Student-t degrees of freedom, used for both populations (the odometry ties them:
    /// `nu_I = max(nu_I, nu_W)`); ignored by the other estimators.
    pub nu: f64,
}

/// Per-pixel residuals and normalised IRLS weights on one pyramid level of the reference
/// frame. Pixels without a residual (no depth, warped outside the current image, behind the
/// camera, no valid current inverse depth for the geometric term, or the term switched off)
/// are NaN.
#[derive(Clone, Debug)]
pub struct ResidualImages {
    /// Pyramid level (0 = full resolution).
    pub level: usize,
    /// Photometric residual `I_cur(w(x)) - I_ref(x)`, intensity levels.
    pub photometric: ImageF32,
    /// Geometric residual: inverse depth (1/m) or depth (m) by the configuration.
    pub geometric: ImageF32,
    /// IRLS weight of the photometric residual, `w(r / sigma_I)` in [0, 1] (1 for least
    /// squares and for small residuals).
    pub photometric_weight: ImageF32,
    /// IRLS weight of the geometric residual, in [0, 1].
    pub geometric_weight: ImageF32,
}

impl ResidualImages {
    /// Share of the reference pixels with a photometric residual, in [0, 1].
    pub fn photometric_coverage(&self) -> f64 {
        coverage(&self.photometric)
    }
    /// Mean photometric IRLS weight over the pixels with a residual (NaN when none).
    pub fn mean_photometric_weight(&self) -> f64 {
        mean_finite(&self.photometric_weight)
    }
    /// Mean geometric IRLS weight over the pixels with a residual (NaN when none).
    pub fn mean_geometric_weight(&self) -> f64 {
        mean_finite(&self.geometric_weight)
    }
}

fn coverage(img: &ImageF32) -> f64 {
    let n = img.data.len().max(1);
    img.data.iter().filter(|v| v.is_finite()).count() as f64 / n as f64
}

fn mean_finite(img: &ImageF32) -> f64 {
    let (s, n) = img
        .data
        .iter()
        .filter(|v| v.is_finite())
        .fold((0.0f64, 0usize), |(s, n), &v| (s + f64::from(v), n + 1));
    if n == 0 {
        f64::NAN
    } else {
        s / n as f64
    }
}

/// Residual and weight images of `reference` warped into `current` by `cur_from_ref`
/// (reference camera to current camera, metres) on pyramid `level`, with the configuration's
/// estimator, terms and geometric parametrisation and the given robust `scales`.
///
/// Errors: frames whose size differs from `camera`'s, a level the image is too small for,
/// or non-positive / non-finite scales.
pub fn residual_images(
    reference: &RgbdFrame,
    current: &RgbdFrame,
    camera: &PinholeCamera,
    cur_from_ref: &Se3,
    config: &OdometryConfig,
    scales: RobustScales,
    level: usize,
) -> Result<ResidualImages, OdometryError> {
    let (w0, h0) = (camera.width as usize, camera.height as usize);
    for f in [reference, current] {
        if f.width() != w0 || f.height() != h0 {
            return Err(OdometryError::FrameSize {
                want_w: w0,
                want_h: h0,
                got_w: f.width(),
                got_h: f.height(),
            });
        }
    }
    if (w0 >> level) < 8 || (h0 >> level) < 8 {
        return Err(OdometryError::TooManyLevels {
            width: w0,
            height: h0,
            levels: level + 1,
        });
    }
    let ok = |v: f64| v.is_finite() && v > 0.0;
    if !(ok(scales.sigma_photo) && ok(scales.sigma_geo) && ok(scales.nu)) {
        return Err(OdometryError::InvalidConfig(format!(
            "robust scales must be finite and > 0: {scales:?}"
        )));
    }
    if !cur_from_ref.is_finite() {
        return Err(OdometryError::InvalidConfig(
            "cur_from_ref is not finite".into(),
        ));
    }
    let levels = level + 1;
    // Gradients only on the level asked for (the finer ones only feed the downsampling).
    let r = CpuPyramid::build_reusing(reference, levels, level, None);
    let c = CpuPyramid::build_reusing(current, levels, level, None);
    let lay = r.levels[level];
    let mut p = warp_params(config, camera, level, cur_from_ref, 0);
    p.sigma_photo = scales.sigma_photo as f32;
    p.sigma_geo = scales.sigma_geo as f32;
    p.nu_photo = scales.nu as f32;
    p.nu_geo = scales.nu as f32;
    let range = lay.offset..lay.offset + lay.width * lay.height;
    let bufs = Buffers {
        ref_photo: &r.photo[range.clone()],
        ref_geo: &r.geo[range.clone()],
        cur_photo: &c.photo[range.clone()],
        cur_geo: &c.geo[range],
    };
    let k = Warp::new(&p);
    let n = lay.width * lay.height;
    let mut out = [
        vec![f32::NAN; n],
        vec![f32::NAN; n],
        vec![f32::NAN; n],
        vec![f32::NAN; n],
    ];
    for i in 0..n {
        let (rp, _, rg, _) = pixel_terms::<false>(&k, &bufs, i);
        if rp != INVALID_RESIDUAL {
            out[0][i] = rp;
            out[2][i] = weight(k.est, rp / k.sigma[0], k.nu[0]);
        }
        if rg != INVALID_RESIDUAL {
            out[1][i] = rg;
            out[3][i] = weight(k.est, rg / k.sigma[1], k.nu[1]);
        }
    }
    let [photo, geo, wp, wg] = out;
    let img = |data: Vec<f32>| ImageF32 {
        width: lay.width,
        height: lay.height,
        data,
    };
    Ok(ResidualImages {
        level,
        photometric: img(photo),
        geometric: img(geo),
        photometric_weight: img(wp),
        geometric_weight: img(wg),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::odometry::Estimator;

    /// A textured slanted plane seen by two cameras `cur_from_ref` apart.
    fn views(cur_from_ref: &Se3) -> (PinholeCamera, RgbdFrame, RgbdFrame) {
        let cam = PinholeCamera::new(80.0, 80.0, 39.5, 29.5, 80, 60);
        let tex = |x: f64, y: f64| {
            128.0 + 60.0 * (7.0 * x).sin() * (5.0 * y).cos() + 30.0 * (13.0 * x + 3.0 * y).sin()
        };
        // Plane z = 2 + 0.2 x in the reference frame; texture fixed on the plane.
        let render = |cam_from_ref: &Se3| {
            let ref_from_cam = cam_from_ref.inverse();
            let mut i = vec![0.0f32; 80 * 60];
            let mut rho = vec![0.0f32; 80 * 60];
            for v in 0..60 {
                for u in 0..80 {
                    let d =
                        glam::DVec3::new((u as f64 - 39.5) / 80.0, (v as f64 - 29.5) / 80.0, 1.0);
                    let o = ref_from_cam.translation;
                    let dir = ref_from_cam.rotation * d;
                    // (o + t dir).z = 2 + 0.2 (o + t dir).x
                    let t = (2.0 + 0.2 * o.x - o.z) / (dir.z - 0.2 * dir.x);
                    let p = o + t * dir;
                    i[v * 80 + u] = tex(p.x, p.y) as f32;
                    rho[v * 80 + u] = (1.0 / t) as f32; // z in the camera = t (d.z = 1)
                }
            }
            RgbdFrame {
                timestamp: 0.0,
                intensity: ImageF32 {
                    width: 80,
                    height: 60,
                    data: i,
                },
                inverse_depth: ImageF32 {
                    width: 80,
                    height: 60,
                    data: rho,
                },
                colour: None,
            }
        };
        (cam, render(&Se3::IDENTITY), render(cur_from_ref))
    }

    #[test]
    fn residuals_vanish_at_the_true_pose_and_an_outlier_patch_is_downweighted() {
        let truth = Se3::exp(&[0.03, -0.01, 0.02, 0.01, 0.015, -0.005]);
        let (cam, reference, mut current) = views(&truth);
        let cfg = OdometryConfig::default();
        let scales = RobustScales {
            sigma_photo: 2.0,
            sigma_geo: 0.002,
            nu: 5.0,
        };
        let at_truth =
            residual_images(&reference, &current, &cam, &truth, &cfg, scales, 0).unwrap();
        assert!(at_truth.photometric_coverage() > 0.8);
        let med = |img: &ImageF32| {
            let mut v: Vec<f32> = img
                .data
                .iter()
                .filter(|v| v.is_finite())
                .map(|v| v.abs())
                .collect();
            v.sort_by(f32::total_cmp);
            v[v.len() / 2]
        };
        let wrong = Se3::exp(&[0.03, 0.0, 0.0, 0.0, 0.0, 0.0]) * truth;
        let off = residual_images(&reference, &current, &cam, &wrong, &cfg, scales, 0).unwrap();
        assert!(
            med(&at_truth.photometric) < 1.0,
            "{}",
            med(&at_truth.photometric)
        );
        assert!(med(&off.photometric) > 5.0 * med(&at_truth.photometric).max(0.2));
        assert!(med(&at_truth.geometric) < 1e-3);
        // A bright square over the current image: its reference pixels get Student-t weights
        // near 0, the rest near 1; least squares weighs everything 1.
        for v in 20..40 {
            for u in 30..50 {
                current.intensity.data[v * 80 + u] = 255.0;
            }
        }
        let img = residual_images(&reference, &current, &cam, &truth, &cfg, scales, 0).unwrap();
        let (mut inside, mut outside) = (Vec::new(), Vec::new());
        for (i, &r) in img.photometric.data.iter().enumerate() {
            if r.is_finite() {
                let wt = img.photometric_weight.data[i];
                if r.abs() > 40.0 {
                    inside.push(wt)
                } else {
                    outside.push(wt)
                }
            }
        }
        let mean = |v: &[f32]| v.iter().sum::<f32>() / v.len() as f32;
        assert!(
            inside.len() > 100 && mean(&inside) < 0.05,
            "{}",
            mean(&inside)
        );
        assert!(mean(&outside) > 0.8, "{}", mean(&outside));
        let ls = OdometryConfig {
            estimator: Estimator::LeastSquares,
            ..cfg.clone()
        };
        let img = residual_images(&reference, &current, &cam, &truth, &ls, scales, 0).unwrap();
        assert!((img.mean_photometric_weight() - 1.0).abs() < 1e-9);
        // The coarser level is half the size.
        let l1 = residual_images(&reference, &current, &cam, &truth, &cfg, scales, 1).unwrap();
        assert_eq!((l1.photometric.width, l1.photometric.height), (40, 30));
    }

    #[test]
    fn bad_inputs_are_errors() {
        let truth = Se3::IDENTITY;
        let (cam, reference, current) = views(&truth);
        let cfg = OdometryConfig::default();
        let good = RobustScales {
            sigma_photo: 2.0,
            sigma_geo: 0.002,
            nu: 5.0,
        };
        let bad = RobustScales {
            sigma_photo: f64::NAN,
            ..good
        };
        assert!(residual_images(&reference, &current, &cam, &truth, &cfg, bad, 0).is_err());
        assert!(residual_images(&reference, &current, &cam, &truth, &cfg, good, 4).is_err());
        let small = PinholeCamera::new(80.0, 80.0, 19.5, 14.5, 40, 30);
        assert!(residual_images(&reference, &current, &small, &truth, &cfg, good, 0).is_err());
    }
}
