//! Odometry configuration: every option of thesis sections 4.4 and 6.3.5, with defaults that
//! are used unchanged on every sequence.

use super::robust::{Estimator, ScaleMethod};
use super::OdometryError;

/// Which residuals are minimised (thesis tables 4.1, 4.2).
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "lowercase")]
#[repr(u32)]
pub enum Terms {
    /// Photometric and geometric (the default).
    Both = 3,
    /// Photometric only.
    Photometric = 1,
    /// Geometric only.
    Geometric = 2,
}

/// Parametrisation of the geometric error.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "lowercase")]
#[repr(u32)]
pub enum GeometricParam {
    /// Inverse depth, 1/m (the thesis' choice: noise roughly constant over depth).
    #[serde(alias = "inverse-depth", alias = "inverse_depth")]
    InverseDepth = 0,
    /// Depth, m (for comparison).
    Depth = 1,
}

/// How the current frame's inverse depth is sampled at a warped point for the geometric
/// residual.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "lowercase")]
#[repr(u32)]
pub enum GeometricSampling {
    /// The nearest pixel (thesis eq. 6.5-6.9; the default).
    Nearest = 0,
    /// The nearest pixel extended to the warped point along its (already stored) inverse-depth
    /// gradient: a first-order sample consistent with the Jacobian, never across a depth
    /// discontinuity (the gradient is invalid there). Removes the nearest sample's bias on
    /// noiseless rendered views; not the default because it did not help on real Kinect data
    /// (docs/notes.md).
    Linear = 1,
    /// [`Self::Linear`] on the levels coarser than the finest optimised one, nearest on the
    /// finest: on coarse levels the nearest sample's jumps as the warp moves keep the update
    /// from falling below [`OdometryConfig::convergence`], so every iteration runs; the
    /// first-order sample is smooth in the pose and lets the convergence test end them early.
    #[serde(alias = "coarse-linear", alias = "coarse_linear")]
    CoarseLinear = 2,
}

impl GeometricSampling {
    /// The kernels' `sampling` code on `level` when `finest` is the finest level optimised:
    /// 0 nearest, 1 first-order.
    pub(crate) fn kernel_code(self, level: usize, finest: usize) -> u32 {
        match self {
            GeometricSampling::Nearest => 0,
            GeometricSampling::Linear => 1,
            GeometricSampling::CoarseLinear => u32::from(level > finest),
        }
    }
}

/// Which warped pixels count as covisible in the covisibility ratio (thesis eq. 4.33, 6.10)
/// that switches the reference frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "lowercase")]
pub enum CovisibilityTest {
    /// A reference pixel with depth is covisible where it warps inside the current image onto
    /// a pixel with depth, whatever that depth is.
    Depth,
    /// The thesis' condition (eq. 4.33, 6.10): additionally the geometric residual at the
    /// nearest pixel must be below [`OCCLUSION_SIGMAS`] times the geometric scale sigma_W
    /// (the last estimated one when tracking; [`OdometryConfig::fixed_sigma_geo`] for the
    /// two-view entry points), so occluded and occluding pixels do not count. The default:
    /// better ATE than [`Self::Depth`] on both real sequences (redkitchen 0-299 and fr1/rpy
    /// 0-199, `docs/results/thesis_options.json`) at no measurable cost.
    Consistent,
}

/// Multiple of the geometric scale sigma_W within which a warped point is consistent with the
/// current frame's depth in [`CovisibilityTest::Consistent`] (the thesis' 3 sigma_W).
pub const OCCLUSION_SIGMAS: f64 = 3.0;

/// Location of the residual distributions in the robust estimation (thesis eq. 4.26-4.27).
///
/// An estimated location mu is found with the scale (maximum likelihood: the Student-t EM
/// update `mu = sum(w r) / sum(w)`; the median with MAD; the mean for least squares), and the
/// weights and normal equations use `r - mu`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "lowercase")]
pub enum Location {
    /// Residuals centred at zero: the scale alone is estimated.
    Zero,
    /// A location for the photometric residuals only: it absorbs a global brightness change
    /// between the frames (the exposure steps of an automatic exposure).
    Photometric,
    /// A location for both residual types (the thesis' formulation), the geometric one on the
    /// finest level optimised only. An inverse-depth offset is nearly confounded with a
    /// translation along the optical axis where the scene's depth varies little: estimated
    /// on the coarse levels, where the pose is still the guess, it absorbs the guess' error
    /// along that axis and the alternation of location and pose never removes it (a
    /// noiseless pair 1.5 cm apart along z ends 17.6 mm off). The default: the best mean
    /// odometry ATE against OpenCV on the real sequences, and better SLAM on both
    /// (docs/notes.md).
    Both,
}

impl Location {
    /// Whether the location of the photometric (`geometric == false`) or geometric residuals
    /// is estimated.
    pub(crate) fn estimates(self, geometric: bool) -> bool {
        match self {
            Location::Zero => false,
            Location::Photometric => !geometric,
            Location::Both => true,
        }
    }
}

/// Where the odometry's residuals are linearised (thesis eq. 4.16-4.17, 6.9, 6.12-6.13).
///
/// Both forms minimise the same photometric residual `I_B(w(p, T)) - I_A(p)` over the
/// reference pixels `p` (A the reference frame, B the current one, `T = cur_from_ref`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "lowercase")]
#[repr(u32)]
pub enum Linearisation {
    /// Forward compositional: the Jacobians take the current frame's gradients at the warped
    /// point (bilinear) and the projection Jacobian there, for a left twist of `T`; the
    /// geometric residual is compared in the current frame, `W_B(w(p)) - 1/z_B`. The default:
    /// over the two real sequences (redkitchen 0-299, fr1/rpy 0-199) it gave the better mean
    /// odometry ATE against OpenCV's, and the better mean SLAM ATE, though the reference form
    /// is better on fr1/rpy and the odometry's margin is far below what two short sequences
    /// resolve (docs/notes.md).
    Current = 0,
    /// The thesis' form, inverse compositional: the Jacobians take the reference frame's
    /// stored gradients `nabla I_A(p)`, `nabla W_A(p)` and the projection Jacobian at the
    /// reference point `X_A(p)`, so they do not change over a level's iterations; the
    /// geometric residual is compared in the reference frame, `W_B*(p) - W_A(p)`, with
    /// `W_B*(p)` the current frame's inverse depth sampled at `w(p)`, moved into A by
    /// `T^-1` and taken as `1/z` there. The solved increment is applied on the reference
    /// side, `T <- T exp(delta)` (the reference-side twist's sign folded in, see
    /// `Tracker::solve_level`), and the covariance pass filters the reference level.
    Reference = 1,
}

/// Gradients used for the covariance of an alignment (thesis 6.20, 6.21).
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "lowercase")]
pub enum CovarianceGradients {
    /// The inverse of the last Gauss-Newton Hessian (raw image gradients, at the pose before
    /// the last update). The default: on rendered views with known noise the bilateral pass
    /// barely improves the consistency (NEES) and costs an extra pass per frame
    /// (`examples/odo_covariance.rs`, docs/notes.md).
    Raw,
    /// The thesis' method (6.20, 6.21): an extra normal-equation pass at the final pose on
    /// the finest level used, with the gradients of the bilateral-filtered intensity and
    /// inverse depth of the frame the Jacobians differentiate (the current frame with
    /// [`Linearisation::Current`], the reference frame with [`Linearisation::Reference`]) (5x5 window, Cauchy range kernel scaled by [`OdometryConfig::bilateral_range`]).
    Bilateral,
}

/// Odometry options.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct OdometryConfig {
    /// Pyramid levels (level 0 = full resolution).
    pub levels: usize,
    /// Maximum Gauss-Newton iterations per level, index 0 = the finest level used (see
    /// [`Self::finest_level`]), then coarser. Missing entries repeat the last one.
    pub iterations: Vec<usize>,
    /// Finest level used (`stopLevel` of 4.4.6; 0 = full resolution).
    pub stop_level: usize,
    /// Levels wider than this many pixels are not optimised (an automatic `stopLevel`): on
    /// Kinect-class data the full 640x480 level costs four times the 320x240 one and does not
    /// improve accuracy (docs/notes.md). `0` disables the rule.
    pub max_width: usize,
    /// Robust estimator.
    pub estimator: Estimator,
    /// How residual scales are estimated.
    pub scale: ScaleMethod,
    /// Which residuals' location is estimated with their scale (`"zero"`, `"photometric"`,
    /// `"both"`; ignored with `ScaleMethod::Fixed`).
    pub location: Location,
    /// Fixed photometric scale (intensity levels) for `ScaleMethod::Fixed` (`sigmaFix`).
    pub fixed_sigma_photo: f64,
    /// Fixed geometric scale (1/m for inverse depth, m for depth) for `ScaleMethod::Fixed`.
    pub fixed_sigma_geo: f64,
    /// Fixed Student-t degrees of freedom used with `ScaleMethod::Fixed`.
    pub fixed_nu: f64,
    /// Maximum number of pixels in the systematic sample for scale estimation.
    pub max_samples: usize,
    /// Residual terms.
    pub terms: Terms,
    /// Geometric error parametrisation.
    pub geometric: GeometricParam,
    /// Convergence threshold on the norm of the update twist (m and rad).
    pub convergence: f64,
    /// Convergence threshold in pixels of the level being optimised: a level also stops when
    /// the update twist's norm times the level's focal length (pixels) is below this, i.e.
    /// the update moves image points by about that much (a rotation of `|w|` rad moves them
    /// by `f |w|` pixels, a translation of `|v|` m at 1 m by `f |v|`). On a coarse level a
    /// step that [`Self::convergence`] still counts as motion is a small fraction of a pixel.
    /// 0 turns it off (only [`Self::convergence`] applies). Default 0.01: on the real
    /// sequences it gave the best mean ATE against OpenCV of 0 / 0.01 / 0.02 / 0.05 with
    /// fewer iterations (docs/notes.md).
    pub convergence_pixels: f64,
    /// Initial guess from the previous inter-frame motion (constant velocity).
    pub constant_velocity: bool,
    /// Switch the reference frame when covisibility drops below this ratio; `None` aligns
    /// every frame to the previous one (frame-to-frame).
    pub reference_switch: Option<f64>,
    /// Pyramid level on which covisibility is computed.
    pub covisibility_level: usize,
    /// Which warped pixels count as covisible.
    pub covisibility_test: CovisibilityTest,
    /// How inverse depth is sampled for the geometric residual.
    pub geometric_sampling: GeometricSampling,
    /// Where the residuals are linearised (`"current"`, the default, or `"reference"`, the
    /// thesis' inverse-compositional form).
    pub linearisation: Linearisation,
    /// How the covariance (and the reported condition number) is computed.
    pub covariance: CovarianceGradients,
    /// Range scales of the bilateral filter as multiples of the final residual scales
    /// (sigma_I for intensity, sigma_W for inverse depth; with the depth parametrisation,
    /// of `fixed_sigma_geo` read as 1/m).
    pub bilateral_range: f64,
    /// Rectify each frame's intensity for the camera's rolling shutter
    /// ([`crate::camera::PinholeCamera::readout`]; nothing to do with a global shutter):
    /// [`crate::odometry::Odometry::track`] turns each row to the middle row's time with the
    /// angular velocity of the previous inter-frame motion (constant velocity) before
    /// aligning; the depth map is left as it is. Default on.
    pub rolling_shutter: bool,
}

impl Default for OdometryConfig {
    fn default() -> Self {
        Self {
            levels: 4,
            iterations: vec![6, 8, 10],
            stop_level: 0,
            max_width: 320,
            estimator: Estimator::Student,
            scale: ScaleMethod::Ml,
            location: Location::Both,
            fixed_sigma_photo: 5.0,
            fixed_sigma_geo: 0.0025,
            fixed_nu: 5.0,
            max_samples: 19200,
            terms: Terms::Both,
            geometric: GeometricParam::InverseDepth,
            convergence: 1e-5,
            convergence_pixels: 0.01,
            constant_velocity: true,
            reference_switch: Some(0.9),
            covisibility_level: 2,
            covisibility_test: CovisibilityTest::Consistent,
            geometric_sampling: GeometricSampling::Nearest,
            linearisation: Linearisation::Current,
            covariance: CovarianceGradients::Raw,
            bilateral_range: 3.0,
            rolling_shutter: true,
        }
    }
}

impl OdometryConfig {
    /// The finest level optimised for images `width` pixels wide: at least `stop_level`, and
    /// coarse enough to be at most `max_width` wide (never coarser than the coarsest level).
    pub fn finest_level(&self, width: usize) -> usize {
        let mut level = self.stop_level;
        if self.max_width > 0 {
            while level + 1 < self.levels && (width >> level) > self.max_width {
                level += 1;
            }
        }
        level.min(self.levels.saturating_sub(1))
    }

    /// Maximum iterations at `level` when `finest` is the finest level optimised.
    pub fn iterations_at(&self, level: usize, finest: usize) -> usize {
        self.iterations
            .get(level.saturating_sub(finest))
            .or(self.iterations.last())
            .copied()
            .unwrap_or(10)
    }

    /// Checks the options.
    pub fn validate(&self) -> Result<(), OdometryError> {
        let bad = |m: &str| Err(OdometryError::InvalidConfig(m.to_string()));
        if self.levels == 0 || self.levels > 8 {
            return bad("levels must be in 1..=8");
        }
        if self.stop_level >= self.levels {
            return bad("stop_level must be below levels");
        }
        if self.iterations.is_empty() {
            return bad("iterations must list at least one count");
        }
        if !(self.convergence_pixels >= 0.0 && self.convergence_pixels.is_finite()) {
            return bad("convergence_pixels must be finite and >= 0");
        }
        if self.max_samples < 64 {
            return bad("max_samples must be at least 64");
        }
        if !(self.fixed_sigma_photo > 0.0 && self.fixed_sigma_geo > 0.0) {
            return bad("fixed sigmas must be > 0");
        }
        if !(self.bilateral_range > 0.0) {
            return bad("bilateral_range must be > 0");
        }
        if let Some(t) = self.reference_switch {
            if !(0.0..=1.0).contains(&t) {
                return bad("reference_switch must be in [0, 1]");
            }
        }
        Ok(())
    }

    /// Reads a JSON configuration file (missing keys take their defaults).
    pub fn from_json_file(path: &std::path::Path) -> Result<Self, OdometryError> {
        let text = std::fs::read_to_string(path)
            .map_err(|e| OdometryError::InvalidConfig(format!("{}: {e}", path.display())))?;
        let c: OdometryConfig = serde_json::from_str(&text)
            .map_err(|e| OdometryError::InvalidConfig(format!("{}: {e}", path.display())))?;
        c.validate()?;
        Ok(c)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn coarse_linear_sampling_is_first_order_above_the_finest_level_only() {
        let c = OdometryConfig::default();
        // 640 wide with max_width 320: level 1 is the finest optimised.
        let finest = c.finest_level(640);
        assert_eq!(finest, 1);
        let codes: Vec<u32> = (0..4)
            .map(|l| GeometricSampling::CoarseLinear.kernel_code(l, finest))
            .collect();
        assert_eq!(codes, [0, 0, 1, 1]);
        for l in 0..4 {
            assert_eq!(GeometricSampling::Nearest.kernel_code(l, finest), 0);
            assert_eq!(GeometricSampling::Linear.kernel_code(l, finest), 1);
        }
        let p = super::super::tracker::warp_params(
            &OdometryConfig {
                geometric_sampling: GeometricSampling::CoarseLinear,
                ..c
            },
            &crate::camera::PinholeCamera::new(525.0, 525.0, 319.5, 239.5, 640, 480),
            2,
            &crate::geometry::Se3::IDENTITY,
            0,
        );
        assert_eq!(p.sampling, 1);
    }
}
