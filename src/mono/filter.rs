//! The monocular EKF SLAM loop (thesis sec. 2.3-2.5, 3.3.1).
//!
//! Per frame: prediction with the constant-velocity model; for each landmark predicted inside
//! the image, its innovation covariance `S = H P H^T + sigma_pixel^2 I` and an active search
//! over the integer pixels inside the 95 % ellipse (`nu^T S^-1 nu <= 5.99`, eq. 2.36) for the
//! best ZNCC score of its (plain or warped) patch, accepted above the threshold and refined
//! to sub-pixel by a parabola; 1-point RANSAC (Civera et al. 2010) over the matches, each
//! hypothesis being the state after an EKF update with a single match, the inliers those
//! within `ransac_threshold` pixels of its prediction; an EKF update (eq. 2.37-2.43, rotation
//! corrected on the manifold) with the low-innovation inliers; a second update with the
//! remaining matches that are compatible (95 % gate) after the first ("rescued"
//! high-innovation inliers); map management: a landmark unmatched for
//! `max_unmatched_frames` consecutive frames, or matched in fewer than half of at least 10
//! attempts, leaves the state; if it is then a 3D point (its inverse depth bounded away
//! from zero, `rho > point_sigmas * sigma_rho`) it joins the fixed map, otherwise (a ray:
//! too little parallax, depth still compatible with infinity) it is dropped; new landmarks at FAST corners in image cells without predicted landmarks.
//!
//! Statistics of table 2.1 ([`MonoStats`]): FI, features initialised; Rm, successful matches
//! per initialised feature; Rf, features that became 3D map points per initialised feature.

use std::time::Instant;

use faer::linalg::matmul::triangular::{self, BlockStructure};
use faer::linalg::triangular_solve::solve_lower_triangular_in_place;
use faer::{Accum, Mat, MatMut, Par, Side};
use glam::{DQuat, DVec2, DVec3};
use nalgebra::{DMatrix, DVector, SMatrix};
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;
use rayon::prelude::*;

use super::fast;
use super::landmark::{initialise, InverseDepthLandmark, Prediction, LANDMARK_DIM};
use super::patch::{FeaturePatch, PatchMode, ViewChange};
use super::state::{CameraState, CAMERA_DIM};
use super::{MonoConfig, MonoError};
use crate::camera::UnifiedCamera;
use crate::geometry::Se3;
use crate::image::ImageF32;

/// 95 % quantile of the chi-square distribution with 2 degrees of freedom.
pub const CHI2_95_2DOF: f64 = 5.991;

/// A landmark in the filter with its appearance and bookkeeping.
#[derive(Clone, Debug)]
pub struct Feature {
    /// Unique id (order of initialisation).
    pub id: usize,
    /// The inverse-depth parameters.
    pub landmark: InverseDepthLandmark,
    /// Appearance from the initialisation frame.
    pub patch: FeaturePatch,
    /// The filter's camera pose estimate when the patch was taken: `world_from_camera`
    /// rotation and centre (filter world frame, map units).
    pub camera_init: (DQuat, DVec3),
    /// Consecutive frames without a match.
    pub frames_unmatched: usize,
    /// Searches attempted (predicted inside the image).
    pub attempts: usize,
    /// Successful matches used in an update.
    pub matches: usize,
}

/// Statistics over a run (thesis table 2.1).
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct MonoStats {
    /// Frames processed.
    pub frames: usize,
    /// Features initialised (FI).
    pub features_initialised: usize,
    /// Successful matches (inliers used in updates), summed over all features and frames.
    pub matches: usize,
    /// Features moved to the fixed map as 3D points.
    pub map_points: usize,
    /// Features dropped as rays (too little parallax) when they left the state.
    pub rays_dropped: usize,
    /// Matches rejected by 1-point RANSAC (and the rescue gate).
    pub outliers: usize,
}

impl MonoStats {
    /// Matches per initialised feature (Rm).
    pub fn rm(&self) -> f64 {
        self.matches as f64 / self.features_initialised.max(1) as f64
    }
    /// 3D map features per initialised feature (Rf); pass the number of landmarks still in
    /// the state that are points, counted at the end of the run.
    pub fn rf(&self, points_in_state: usize) -> f64 {
        (self.map_points + points_in_state) as f64 / self.features_initialised.max(1) as f64
    }
}

/// Milliseconds spent per stage in one frame.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct StageTimes {
    /// Motion-model prediction of state and covariance.
    pub predict: f64,
    /// Measurement prediction, innovation covariances and active search (ZNCC).
    pub search: f64,
    /// 1-point RANSAC.
    pub ransac: f64,
    /// EKF updates (low-innovation inliers, then rescued ones).
    pub update: f64,
    /// Map management and initialisation of new features (FAST).
    pub manage: f64,
}

impl StageTimes {
    /// Sum of the stages, milliseconds.
    pub fn total(&self) -> f64 {
        self.predict + self.search + self.ransac + self.update + self.manage
    }
}

/// What happened in one frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FrameReport {
    /// Time stamp, seconds.
    pub timestamp: f64,
    /// Estimated pose `world_from_camera` (filter world = first camera; scale unknown).
    pub world_from_camera: Se3,
    /// Landmarks predicted inside the image.
    pub visible: usize,
    /// Landmarks whose search found a ZNCC peak above the threshold.
    pub matched: usize,
    /// Low-innovation inliers of 1-point RANSAC.
    pub inliers: usize,
    /// High-innovation inliers rescued after the first update.
    pub rescued: usize,
    /// New landmarks initialised.
    pub initialised: usize,
    /// Landmarks in the state after the frame.
    pub landmarks: usize,
    /// Per-stage times, milliseconds.
    pub times: StageTimes,
}

/// A landmark added this frame whose covariance is not in the state yet: the Jacobian of
/// its parameters with respect to the camera pose `[r, theta]` and its own 6x6 block.
type NewLandmark = (SMatrix<f64, 6, 6>, SMatrix<f64, 6, 6>);

/// Pixels taken by landmarks, bucketed by squares of the minimum feature distance, so that
/// "is every taken pixel farther than `min_distance`" looks at 3x3 buckets only.
struct Occupancy {
    cell: f64,
    min_distance2: f64,
    cols: usize,
    rows: usize,
    buckets: Vec<Vec<DVec2>>,
}

impl Occupancy {
    fn new(width: usize, height: usize, min_distance: f64) -> Occupancy {
        let cell = min_distance.max(1.0);
        let cols = (width as f64 / cell).ceil() as usize + 1;
        let rows = (height as f64 / cell).ceil() as usize + 1;
        Occupancy {
            cell,
            min_distance2: min_distance * min_distance,
            cols,
            rows,
            buckets: vec![Vec::new(); cols * rows],
        }
    }

    fn bucket(&self, uv: DVec2) -> (usize, usize) {
        let bx = (uv.x / self.cell).floor().max(0.0) as usize;
        let by = (uv.y / self.cell).floor().max(0.0) as usize;
        (bx.min(self.cols - 1), by.min(self.rows - 1))
    }

    fn insert(&mut self, uv: DVec2) {
        let (bx, by) = self.bucket(uv);
        self.buckets[by * self.cols + bx].push(uv);
    }

    /// True when every taken pixel is farther than the minimum distance from `uv`.
    fn is_free(&self, uv: DVec2) -> bool {
        let (bx, by) = self.bucket(uv);
        (by.saturating_sub(1)..(by + 2).min(self.rows)).all(|y| {
            (bx.saturating_sub(1)..(bx + 2).min(self.cols)).all(|x| {
                self.buckets[y * self.cols + x]
                    .iter()
                    .all(|t| (*t - uv).length_squared() > self.min_distance2)
            })
        })
    }
}

/// A match found by active search.
#[derive(Clone, Copy, Debug)]
struct Match {
    feature: usize,
    z: DVec2,
    pred: Prediction,
}

/// Monocular EKF SLAM.
pub struct MonoSlam {
    camera: UnifiedCamera,
    config: MonoConfig,
    state: CameraState,
    features: Vec<Feature>,
    cov: DMatrix<f64>,
    last_time: Option<f64>,
    next_id: usize,
    fixed_map: Vec<DVec3>,
    stats: MonoStats,
    rng: Pcg64,
    mask: Vec<bool>,
}

fn landmark_offset(i: usize) -> usize {
    CAMERA_DIM + LANDMARK_DIM * i
}

impl MonoSlam {
    /// A filter for `camera` (unified model; a pinhole camera is `xi = 0`).
    pub fn new(camera: UnifiedCamera, config: MonoConfig) -> Result<MonoSlam, MonoError> {
        camera
            .validate()
            .map_err(|e| MonoError::Camera(e.to_string()))?;
        config.validate()?;
        let mask = camera.fov_mask();
        let mut cov = DMatrix::zeros(CAMERA_DIM, CAMERA_DIM);
        // The first camera defines the world frame (zero position and rotation covariance);
        // the velocities are unknown.
        for k in 0..3 {
            cov[(6 + k, 6 + k)] = 0.3 * 0.3;
            cov[(9 + k, 9 + k)] = 0.5 * 0.5;
        }
        Ok(MonoSlam {
            camera,
            rng: Pcg64::seed_from_u64(config.seed),
            config,
            state: CameraState::default(),
            features: Vec::new(),
            cov,
            last_time: None,
            next_id: 0,
            fixed_map: Vec::new(),
            stats: MonoStats::default(),
            mask,
        })
    }

    /// The camera model.
    pub fn camera(&self) -> &UnifiedCamera {
        &self.camera
    }
    /// The configuration.
    pub fn config(&self) -> &MonoConfig {
        &self.config
    }
    /// The current camera state.
    pub fn state(&self) -> &CameraState {
        &self.state
    }
    /// The landmarks in the state.
    pub fn features(&self) -> &[Feature] {
        &self.features
    }
    /// The full covariance (error state `[camera 12, landmarks 6 each]`).
    pub fn covariance(&self) -> &DMatrix<f64> {
        &self.cov
    }
    /// Points moved out of the state into the fixed map (world frame, up to scale).
    pub fn fixed_map(&self) -> &[DVec3] {
        &self.fixed_map
    }
    /// Run statistics so far.
    pub fn stats(&self) -> &MonoStats {
        &self.stats
    }
    /// Landmarks in the state that are currently well described as 3D points.
    pub fn points_in_state(&self) -> usize {
        (0..self.features.len())
            .filter(|&i| self.is_point(i))
            .count()
    }

    fn sigma_rho(&self, i: usize) -> f64 {
        let o = landmark_offset(i) + 5;
        self.cov[(o, o)].max(0.0).sqrt()
    }

    /// True when landmark `i` has a bounded depth (a 3D point), false for a ray.
    pub fn is_point(&self, i: usize) -> bool {
        i < self.features.len()
            && self.features[i].landmark.rho > self.config.point_sigmas * self.sigma_rho(i)
    }

    /// Linearity index of landmark `i` at the current camera (see
    /// [`InverseDepthLandmark::linearity_index`]); infinite for an unknown index.
    pub fn linearity_index(&self, i: usize) -> f64 {
        self.features.get(i).map_or(f64::INFINITY, |f| {
            f.landmark
                .linearity_index(self.sigma_rho(i), self.state.position)
        })
    }

    /// Processes one grey image (intensity in `[0, 255]`) taken at `timestamp` seconds.
    pub fn process(&mut self, timestamp: f64, image: &ImageF32) -> Result<FrameReport, MonoError> {
        let (w, h) = (self.camera.width as usize, self.camera.height as usize);
        if image.width != w || image.height != h || image.data.len() != w * h {
            return Err(MonoError::ImageSize {
                what: format!("frame at {timestamp} s"),
                width: image.width,
                height: image.height,
                expected_width: w,
                expected_height: h,
            });
        }
        if !timestamp.is_finite() {
            return Err(MonoError::InvalidConfig {
                name: "timestamp",
                why: format!("{timestamp} is not finite"),
            });
        }
        let mut times = StageTimes::default();
        let mut report = FrameReport {
            timestamp,
            world_from_camera: Se3::IDENTITY,
            visible: 0,
            matched: 0,
            inliers: 0,
            rescued: 0,
            initialised: 0,
            landmarks: 0,
            times,
        };
        if let Some(prev) = self.last_time {
            let dt = timestamp - prev;
            if !(dt > 0.0) {
                return Err(MonoError::NonIncreasingTime {
                    timestamp,
                    previous: prev,
                });
            }
            let t0 = Instant::now();
            self.predict(dt);
            times.predict = ms(t0);

            let t0 = Instant::now();
            let (visible, matches) = self.search(image);
            report.visible = visible.len();
            report.matched = matches.len();
            for &i in &visible {
                self.features[i].attempts += 1;
            }
            times.search = ms(t0);

            let t0 = Instant::now();
            let (inliers, rest) = self.one_point_ransac(&matches);
            times.ransac = ms(t0);

            let t0 = Instant::now();
            let mut used = Vec::new();
            if !inliers.is_empty() {
                let batch: Vec<Match> = inliers.iter().map(|&k| matches[k]).collect();
                self.update(&batch)?;
                used.extend(batch.iter().map(|m| m.feature));
            }
            report.inliers = inliers.len();
            // Rescue high-innovation inliers with the updated state and covariance.
            let mut rescued = Vec::new();
            for &k in &rest {
                let m = matches[k];
                let Some(pred) = self.features[m.feature]
                    .landmark
                    .predict(&self.camera, &self.state)
                else {
                    continue;
                };
                let s = self.innovation_covariance(m.feature, &pred);
                let nu = m.z - pred.uv;
                if let Some(si) = s.try_inverse() {
                    let nuv = nalgebra::Vector2::new(nu.x, nu.y);
                    if (nuv.transpose() * si * nuv)[(0, 0)] <= CHI2_95_2DOF {
                        rescued.push(Match {
                            feature: m.feature,
                            z: m.z,
                            pred,
                        });
                    }
                }
            }
            if !rescued.is_empty() {
                self.update(&rescued)?;
                used.extend(rescued.iter().map(|m| m.feature));
            }
            report.rescued = rescued.len();
            self.stats.outliers += matches.len() - inliers.len() - rescued.len();
            self.stats.matches += used.len();
            let mut matched = vec![false; self.features.len()];
            for i in used {
                matched[i] = true;
            }
            for (f, m) in self.features.iter_mut().zip(&matched) {
                if *m {
                    f.matches += 1;
                    f.frames_unmatched = 0;
                } else {
                    f.frames_unmatched += 1;
                }
            }
            times.update = ms(t0);
            if !self.cov.iter().all(|v| v.is_finite()) || !self.state_is_finite() {
                return Err(MonoError::Diverged(format!(
                    "non-finite state or covariance at {timestamp} s"
                )));
            }
        }
        let t0 = Instant::now();
        self.manage_map();
        report.initialised = self.initialise_features(image, self.last_time.is_none());
        times.manage = ms(t0);
        self.last_time = Some(timestamp);
        self.stats.frames += 1;
        report.world_from_camera = self.state.world_from_camera();
        report.landmarks = self.features.len();
        report.times = times;
        Ok(report)
    }

    fn state_is_finite(&self) -> bool {
        let s = &self.state;
        s.position.is_finite()
            && s.rotation.is_finite()
            && s.velocity.is_finite()
            && s.angular_velocity.is_finite()
            && self.features.iter().all(|f| {
                let l = &f.landmark;
                l.anchor.is_finite()
                    && l.theta.is_finite()
                    && l.phi.is_finite()
                    && l.rho.is_finite()
            })
    }

    /// Prediction of the state and covariance over `dt` seconds.
    fn predict(&mut self, dt: f64) {
        let f = self.state.transition(dt);
        let q = self.state.process_noise(
            dt,
            self.config.sigma_linear_acceleration,
            self.config.sigma_angular_acceleration,
        );
        self.state = self.state.predicted(dt);
        let n = self.cov.nrows();
        let fd = DMatrix::from_iterator(12, 12, f.iter().copied());
        let pcc = self.cov.view((0, 0), (12, 12)).clone_owned();
        let new_cc = &fd * pcc * fd.transpose() + DMatrix::from_iterator(12, 12, q.iter().copied());
        self.cov.view_mut((0, 0), (12, 12)).copy_from(&new_cc);
        if n > 12 {
            let pcf = self.cov.view((0, 12), (12, n - 12)).clone_owned();
            let new_cf = &fd * pcf;
            self.cov
                .view_mut((12, 0), (n - 12, 12))
                .copy_from(&new_cf.transpose());
            self.cov.view_mut((0, 12), (12, n - 12)).copy_from(&new_cf);
        }
    }

    /// The 12x12 block of the covariance over the camera's `[dr, dtheta]` and landmark `i`.
    fn joint_block(&self, i: usize) -> SMatrix<f64, 12, 12> {
        let o = landmark_offset(i);
        let idx = |k: usize| if k < 6 { k } else { o + k - 6 };
        SMatrix::<f64, 12, 12>::from_fn(|r, c| self.cov[(idx(r), idx(c))])
    }

    fn stacked_jacobian(pred: &Prediction) -> SMatrix<f64, 2, 12> {
        let mut h = SMatrix::<f64, 2, 12>::zeros();
        h.fixed_view_mut::<2, 6>(0, 0).copy_from(&pred.d_camera);
        h.fixed_view_mut::<2, 6>(0, 6).copy_from(&pred.d_landmark);
        h
    }

    fn innovation_covariance(&self, i: usize, pred: &Prediction) -> nalgebra::Matrix2<f64> {
        let h = Self::stacked_jacobian(pred);
        let r = self.config.sigma_pixel * self.config.sigma_pixel;
        h * self.joint_block(i) * h.transpose() + nalgebra::Matrix2::identity() * r
    }

    fn in_image(&self, uv: DVec2, margin: f64) -> bool {
        let (w, h) = (f64::from(self.camera.width), f64::from(self.camera.height));
        if !(uv.x >= margin
            && uv.y >= margin
            && uv.x <= w - 1.0 - margin
            && uv.y <= h - 1.0 - margin)
        {
            return false;
        }
        let (x, y) = (uv.x.round() as usize, uv.y.round() as usize);
        self.mask[y * self.camera.width as usize + x]
    }

    /// Predicts every landmark, keeps those inside the image, and searches them. Returns the
    /// visible landmarks and the matches.
    fn search(&self, image: &ImageF32) -> (Vec<usize>, Vec<Match>) {
        let margin = self.config.patch_half as f64 + 1.0;
        let candidates: Vec<(usize, Prediction, nalgebra::Matrix2<f64>)> = (0..self.features.len())
            .filter_map(|i| {
                let pred = self.features[i]
                    .landmark
                    .predict(&self.camera, &self.state)?;
                if !self.in_image(pred.uv, margin) {
                    return None;
                }
                let s = self.innovation_covariance(i, &pred);
                Some((i, pred, s))
            })
            .collect();
        let visible = candidates.iter().map(|c| c.0).collect();
        let matches = candidates
            .par_iter()
            .filter_map(|(i, pred, s)| {
                self.search_one(image, *i, pred, s).map(|z| Match {
                    feature: *i,
                    z,
                    pred: *pred,
                })
            })
            .collect();
        (visible, matches)
    }

    fn search_one(
        &self,
        image: &ImageF32,
        i: usize,
        pred: &Prediction,
        s: &nalgebra::Matrix2<f64>,
    ) -> Option<DVec2> {
        let f = &self.features[i];
        let half = self.config.patch_half;
        let mode = self.config.patch_mode;
        let ratio = match mode {
            PatchMode::Plain | PatchMode::Projective => 1.0,
            PatchMode::Warped => self.distance_ratio(i),
            PatchMode::Thesis | PatchMode::Anisotropic => {
                if self.depth_converged(i) {
                    self.distance_ratio(i)
                } else {
                    1.0
                }
            }
        };
        let template = if mode == PatchMode::Projective {
            let (rotation, centre) = f.camera_init;
            let init_from_world = rotation.conjugate();
            let point = if self.depth_converged(i) {
                f.landmark.point().map(|p| init_from_world * (p - centre))
            } else {
                None
            };
            let view = ViewChange {
                init_from_now: init_from_world * self.state.rotation,
                centre_now_in_init: init_from_world * (self.state.position - centre),
                point_in_init: point,
            };
            f.patch
                .template_projective(&self.camera, pred.uv, &view, half)?
        } else {
            f.patch
                .template(&self.camera, pred.uv, mode, ratio, self.config.k_lim, half)?
                .0
        };
        let si = s.try_inverse()?;
        let rx = (CHI2_95_2DOF * s[(0, 0)])
            .sqrt()
            .min(self.config.max_search_half);
        let ry = (CHI2_95_2DOF * s[(1, 1)])
            .sqrt()
            .min(self.config.max_search_half);
        let (x0, x1) = (
            (pred.uv.x - rx).floor() as i64,
            (pred.uv.x + rx).ceil() as i64,
        );
        let (y0, y1) = (
            (pred.uv.y - ry).floor() as i64,
            (pred.uv.y + ry).ceil() as i64,
        );
        let (bw, bh) = ((x1 - x0 + 1) as usize, (y1 - y0 + 1) as usize);
        let mut scores = template.correlate_window(image, x0, y0, x1, y1);
        let mut best = (f64::NEG_INFINITY, 0usize, 0usize);
        for by in 0..bh {
            for bx in 0..bw {
                let (x, y) = (x0 + bx as i64, y0 + by as i64);
                let d = nalgebra::Vector2::new(x as f64 - pred.uv.x, y as f64 - pred.uv.y);
                let score = &mut scores[by * bw + bx];
                // Outside the ellipse, except the pixels next to the prediction.
                if (d.transpose() * si * d)[(0, 0)] > CHI2_95_2DOF
                    && !(d.x.abs() < 1.0 && d.y.abs() < 1.0)
                {
                    *score = f64::NEG_INFINITY;
                    continue;
                }
                if *score > best.0 {
                    best = (*score, bx, by);
                }
            }
        }
        if !(best.0 >= self.config.zncc_threshold) {
            return None;
        }
        let (bx, by) = (best.1, best.2);
        let (dx, dy) = super::patch::refine_peak(&scores, bw, bx, by, best.0);
        Some(DVec2::new(
            (x0 + bx as i64) as f64 + dx,
            (y0 + by as i64) as f64 + dy,
        ))
    }

    /// `d_init / d_now` of landmark `i` from its estimate: the anchor is the camera centre
    /// at initialisation, so `d_init = 1 / rho` and `d_now = |h_c| / rho`.
    fn distance_ratio(&self, i: usize) -> f64 {
        1.0 / self.features[i]
            .landmark
            .ray_in_camera(&self.state)
            .length()
            .max(1e-9)
    }

    /// True when landmark `i`'s inverse depth has converged: `sigma_rho / rho` at most
    /// [`MonoConfig::depth_converged_ratio`].
    fn depth_converged(&self, i: usize) -> bool {
        let rho = self.features[i].landmark.rho;
        let o = landmark_offset(i) + 5;
        let var = self.cov[(o, o)];
        rho > 0.0 && var >= 0.0 && var.sqrt() <= self.config.depth_converged_ratio * rho
    }

    /// `P H^T` for one measurement (n x 2), using the sparsity of `H`.
    fn p_ht(&self, i: usize, pred: &Prediction) -> DMatrix<f64> {
        let o = landmark_offset(i);
        let hc = DMatrix::from_iterator(2, 6, pred.d_camera.iter().copied());
        let hf = DMatrix::from_iterator(2, 6, pred.d_landmark.iter().copied());
        self.cov.columns(0, 6) * hc.transpose() + self.cov.columns(o, 6) * hf.transpose()
    }

    /// 1-point RANSAC: returns the indices (into `matches`) of the low-innovation inliers
    /// and of the other matches.
    fn one_point_ransac(&mut self, matches: &[Match]) -> (Vec<usize>, Vec<usize>) {
        let m = matches.len();
        if m == 0 {
            return (Vec::new(), Vec::new());
        }
        let thr2 = self.config.ransac_threshold * self.config.ransac_threshold;
        let mut best: Vec<usize> = Vec::new();
        let mut hypotheses = 1000usize.min(10 * m).max(1);
        let mut done = 0usize;
        let r = self.config.sigma_pixel * self.config.sigma_pixel;
        while done < hypotheses {
            done += 1;
            let k = self.rng.random_range(0..m);
            let mk = &matches[k];
            let pht = self.p_ht(mk.feature, &mk.pred);
            let h = Self::stacked_jacobian(&mk.pred);
            let o = landmark_offset(mk.feature);
            let idx = |q: usize| if q < 6 { q } else { o + q - 6 };
            let sub = DMatrix::from_fn(12, 2, |rr, cc| pht[(idx(rr), cc)]);
            let hd = DMatrix::from_iterator(2, 12, h.iter().copied());
            let s = &hd * sub + DMatrix::identity(2, 2) * r;
            let Some(si) = s.try_inverse() else {
                continue;
            };
            let nu = DVector::from_vec(vec![mk.z.x - mk.pred.uv.x, mk.z.y - mk.pred.uv.y]);
            let dx = &pht * (si * nu);
            let cam = self.state.corrected(&dx.as_slice()[..CAMERA_DIM]);
            let inliers: Vec<usize> = (0..m)
                .filter(|&j| {
                    let mj = &matches[j];
                    let o = landmark_offset(mj.feature);
                    let lm = self.features[mj.feature]
                        .landmark
                        .corrected(&dx.as_slice()[o..o + 6]);
                    lm.predict(&self.camera, &cam)
                        .is_some_and(|p| (p.uv - mj.z).length_squared() <= thr2)
                })
                .collect();
            if inliers.len() > best.len() {
                best = inliers;
                let eps = best.len() as f64 / m as f64;
                let need = if eps >= 1.0 {
                    1.0
                } else {
                    (1.0 - self.config.ransac_confidence).ln() / (1.0 - eps).ln()
                };
                hypotheses = hypotheses.min(need.ceil().max(1.0) as usize);
            }
        }
        let mut is_in = vec![false; m];
        for &k in &best {
            is_in[k] = true;
        }
        let rest = (0..m).filter(|&k| !is_in[k]).collect();
        (best, rest)
    }

    /// EKF update with a batch of matches (eq. 2.37-2.43).
    ///
    /// With `S = L L^T` and `W = P H^T L^-T`: `K nu = W (L^-1 nu)` and
    /// `P - K S K^T = P - W W^T`, a symmetric rank-2m update. The dense steps (Cholesky,
    /// triangular solve, the lower triangle of `W W^T`) are blocked faer kernels on the
    /// rayon pool; only the lower triangle is updated, then mirrored tile by tile.
    fn update(&mut self, batch: &[Match]) -> Result<(), MonoError> {
        let n = self.cov.nrows();
        let m2 = 2 * batch.len();
        // Re-linearise at the current state (the batch's predictions may be stale).
        let preds: Vec<Prediction> = batch
            .iter()
            .filter_map(|b| {
                self.features[b.feature]
                    .landmark
                    .predict(&self.camera, &self.state)
            })
            .collect();
        if preds.len() != batch.len() {
            return Ok(());
        }
        // P H^T, n x m2: column 2j+r is sum_q H_j[r, q] P[:, idx_j(q)] (12 columns of P).
        let mut pht = Mat::<f64>::zeros(n, m2);
        let cov = self.cov.as_slice();
        for (j, (b, p)) in batch.iter().zip(&preds).enumerate() {
            let o = landmark_offset(b.feature);
            let h = Self::stacked_jacobian(p);
            for r in 0..2 {
                let Some(dst) = pht.col_mut(2 * j + r).try_as_col_major_mut() else {
                    continue;
                };
                let dst = dst.as_slice_mut();
                for q in 0..12 {
                    let col = if q < 6 { q } else { o + q - 6 };
                    let hq = h[(r, q)];
                    for (v, c) in dst.iter_mut().zip(&cov[col * n..(col + 1) * n]) {
                        *v += hq * c;
                    }
                }
            }
        }
        // S = H P H^T + R, from the rows of P H^T at each measurement's 12 state indices.
        let r_pix = self.config.sigma_pixel * self.config.sigma_pixel;
        let mut s = Mat::<f64>::zeros(m2, m2);
        for (j, (b, p)) in batch.iter().zip(&preds).enumerate() {
            let o = landmark_offset(b.feature);
            let h = Self::stacked_jacobian(p);
            for c in 0..m2 {
                let col = pht.col(c);
                for rr in 0..2 {
                    let mut acc = 0.0;
                    for q in 0..12 {
                        let idx = if q < 6 { q } else { o + q - 6 };
                        acc += h[(rr, q)] * col[idx];
                    }
                    s[(2 * j + rr, c)] = acc;
                }
            }
        }
        for c in 0..m2 {
            for r in 0..c {
                let v = 0.5 * (s[(r, c)] + s[(c, r)]);
                s[(r, c)] = v;
                s[(c, r)] = v;
            }
            s[(c, c)] += r_pix;
        }
        let Ok(llt) = s.llt(Side::Lower) else {
            return Err(MonoError::Diverged(
                "innovation covariance is not positive definite".into(),
            ));
        };
        let l = llt.L();
        let par = if n * m2 > 20_000 {
            Par::rayon(0)
        } else {
            Par::Seq
        };
        // W^T = L^-1 (P H^T)^T, in place in the transposed view of P H^T.
        let mut wt = pht;
        solve_lower_triangular_in_place(l, wt.as_mut().transpose_mut(), par);
        let mut lnu = Mat::<f64>::zeros(m2, 1);
        for (j, (b, p)) in batch.iter().zip(&preds).enumerate() {
            lnu[(2 * j, 0)] = b.z.x - p.uv.x;
            lnu[(2 * j + 1, 0)] = b.z.y - p.uv.y;
        }
        solve_lower_triangular_in_place(l, lnu.as_mut(), Par::Seq);
        let dx: Mat<f64> = &wt * &lnu;
        if !(0..n).all(|k| dx[(k, 0)].is_finite()) {
            return Err(MonoError::Diverged("singular innovation covariance".into()));
        }
        {
            let p = MatMut::from_column_major_slice_mut(self.cov.as_mut_slice(), n, n);
            triangular::matmul(
                p,
                BlockStructure::TriangularLower,
                Accum::Add,
                wt.as_ref(),
                BlockStructure::Rectangular,
                wt.transpose(),
                BlockStructure::Rectangular,
                -1.0,
                par,
            );
        }
        mirror_lower(self.cov.as_mut_slice(), n);
        let dx: Vec<f64> = (0..n).map(|k| dx[(k, 0)]).collect();
        self.state = self.state.corrected(&dx[..CAMERA_DIM]);
        for (i, f) in self.features.iter_mut().enumerate() {
            let o = landmark_offset(i);
            f.landmark = f.landmark.corrected(&dx[o..o + 6]);
        }
        Ok(())
    }

    /// Removes the landmarks that were lost (unmatched for more than `max_unmatched_frames`)
    /// or unreliable (matched in fewer than half of at least 10 attempts). A removed point
    /// joins the fixed map, a ray is dropped. The covariance is compacted in one pass.
    fn manage_map(&mut self) {
        let remove: Vec<bool> = self
            .features
            .iter()
            .map(|f| {
                let lost = f.frames_unmatched > self.config.max_unmatched_frames;
                let unreliable = f.attempts >= 10 && 2 * f.matches < f.attempts;
                lost || unreliable
            })
            .collect();
        if !remove.iter().any(|&r| r) {
            return;
        }
        for (i, _) in remove.iter().enumerate().filter(|(_, &r)| r) {
            match self.features[i].landmark.point() {
                Some(p) if self.is_point(i) => {
                    self.fixed_map.push(p);
                    self.stats.map_points += 1;
                }
                _ => self.stats.rays_dropped += 1,
            }
        }
        // The kept state entries as runs of consecutive indices: the camera, then each run
        // of kept landmarks.
        let mut runs: Vec<std::ops::Range<usize>> = Vec::new();
        runs.push(0..CAMERA_DIM);
        for (i, _) in remove.iter().enumerate().filter(|(_, &r)| !r) {
            let o = landmark_offset(i);
            match runs.last_mut() {
                Some(last) if last.end == o => last.end = o + LANDMARK_DIM,
                _ => runs.push(o..o + LANDMARK_DIM),
            }
        }
        let n = self.cov.nrows();
        let k: usize = runs.iter().map(|r| r.len()).sum();
        let old = self.cov.as_slice();
        let mut data = Vec::with_capacity(k * k);
        for c in runs.iter().flat_map(|r| r.clone()) {
            let col = &old[c * n..(c + 1) * n];
            for r in &runs {
                data.extend_from_slice(&col[r.clone()]);
            }
        }
        self.cov = DMatrix::from_vec(k, k, data);
        let mut flags = remove.into_iter();
        self.features.retain(|_| !flags.next().unwrap_or(false));
    }

    /// Initialises new landmarks at FAST corners in cells without predicted landmarks.
    fn initialise_features(&mut self, image: &ImageF32, first: bool) -> usize {
        let predicted: Vec<DVec2> = self
            .features
            .iter()
            .filter_map(|f| f.landmark.predict(&self.camera, &self.state))
            .map(|p| p.uv)
            .filter(|uv| self.in_image(*uv, 0.0))
            .collect();
        let visible = predicted.len();
        if visible >= self.config.target_visible || self.features.len() >= self.config.max_landmarks
        {
            return 0;
        }
        let budget = if first {
            self.config.target_visible
        } else {
            self.config.max_new_per_frame
        }
        .min(self.config.target_visible - visible)
        .min(self.config.max_landmarks - self.features.len());
        let (gx, gy) = self.config.grid;
        let (w, h) = (self.camera.width as usize, self.camera.height as usize);
        let cell_of = |uv: DVec2| {
            let cx = ((uv.x.max(0.0) / w as f64) * gx as f64) as usize;
            let cy = ((uv.y.max(0.0) / h as f64) * gy as f64) as usize;
            cy.min(gy - 1) * gx + cx.min(gx - 1)
        };
        let mut counts = vec![0usize; gx * gy];
        for uv in &predicted {
            counts[cell_of(*uv)] += 1;
        }
        // FAST per cell, computed when the cell is first visited (emptiest cells first),
        // corners whose big patch sees the scene, sorted by score.
        let m = self.config.big_patch_half + 2;
        let r = self.config.big_patch_half;
        let threshold = self.config.fast_threshold;
        let mut cells: Vec<Option<Vec<DVec2>>> = vec![None; gx * gy];
        // Emptiest cells first, ties in random order; one feature per cell per round.
        let mut order: Vec<(usize, u64)> = (0..gx * gy).map(|c| (c, self.rng.random())).collect();
        order.sort_by_key(|&(c, r)| (counts[c], r));
        let mut taken = Occupancy::new(w, h, self.config.min_feature_distance);
        for uv in &predicted {
            taken.insert(*uv);
        }
        let mut added = 0;
        let mut pending = Vec::new();
        loop {
            let before = added;
            for &(c, _) in &order {
                if added >= budget {
                    break;
                }
                if cells[c].is_none() {
                    let (cx, cy) = (c % gx, c / gx);
                    let rect = (
                        cx * w / gx,
                        cy * h / gy,
                        (cx + 1) * w / gx,
                        (cy + 1) * h / gy,
                    );
                    let mask = &self.mask;
                    let mut found = fast::detect(image, rect, threshold, |x, y| {
                        x >= m
                            && y >= m
                            && x + m < w
                            && y + m < h
                            && mask[y * w + x]
                            && mask[(y - r) * w + x - r]
                            && mask[(y - r) * w + x + r]
                            && mask[(y + r) * w + x - r]
                            && mask[(y + r) * w + x + r]
                    });
                    found.sort_by(|a, b| b.score.total_cmp(&a.score));
                    cells[c] = Some(
                        found
                            .iter()
                            .map(|k| DVec2::new(k.x as f64, k.y as f64))
                            .collect(),
                    );
                }
                let Some(list) = cells[c].as_mut() else {
                    continue;
                };
                while let Some(pos) = list.iter().position(|uv| taken.is_free(*uv)) {
                    let uv = list.remove(pos);
                    if self.add_feature(image, uv, &mut pending) {
                        taken.insert(uv);
                        added += 1;
                        break;
                    }
                }
            }
            if added == before || added >= budget {
                break;
            }
        }
        self.extend_covariance(&pending);
        added
    }

    /// Grows the covariance by the landmarks in `pending` (in the order they were pushed to
    /// `features`), in one allocation. Each new landmark `y_j = g(camera pose, pixel_j,
    /// rho_j)` has `cov(y_j, x) = J_j P[pose, x]` with every old state entry `x`,
    /// `cov(y_j, y_i) = J_j P_pose J_i^T` with another new landmark, and its own block.
    fn extend_covariance(&mut self, pending: &[NewLandmark]) {
        if pending.is_empty() {
            return;
        }
        let n = self.cov.nrows();
        let total = n + LANDMARK_DIM * pending.len();
        let pcc = SMatrix::<f64, 6, 6>::from_fn(|r, c| self.cov[(r, c)]);
        let old = self.cov.as_slice();
        let mut data = vec![0.0f64; total * total];
        for c in 0..n {
            data[c * total..c * total + n].copy_from_slice(&old[c * n..(c + 1) * n]);
        }
        for (j, (jc_j, block)) in pending.iter().enumerate() {
            let o = n + LANDMARK_DIM * j;
            // Rows o..o+6 against the old state: J_j P[0..6, c] for every old column c.
            for c in 0..n {
                let p = SMatrix::<f64, 6, 1>::from_fn(|r, _| old[c * n + r]);
                let v = jc_j * p;
                for r in 0..LANDMARK_DIM {
                    data[c * total + o + r] = v[r];
                    data[(o + r) * total + c] = v[r];
                }
            }
            for (i, (jc_i, _)) in pending.iter().enumerate().take(j) {
                let oi = n + LANDMARK_DIM * i;
                let cross = jc_j * pcc * jc_i.transpose();
                for r in 0..LANDMARK_DIM {
                    for c in 0..LANDMARK_DIM {
                        data[(oi + c) * total + o + r] = cross[(r, c)];
                        data[(o + r) * total + oi + c] = cross[(r, c)];
                    }
                }
            }
            for r in 0..LANDMARK_DIM {
                for c in 0..LANDMARK_DIM {
                    data[(o + c) * total + o + r] = block[(r, c)];
                }
            }
        }
        self.cov = DMatrix::from_vec(total, total, data);
    }

    /// Adds a landmark at pixel `uv` (eq. 2.44-2.50). Its initialisation Jacobian with
    /// respect to the camera pose and its own covariance block go to `pending`; the
    /// covariance grows by [`Self::extend_covariance`] once all of a frame's landmarks are in.
    fn add_feature(&mut self, image: &ImageF32, uv: DVec2, pending: &mut Vec<NewLandmark>) -> bool {
        let Some(patch) = FeaturePatch::new(
            image,
            &self.camera,
            uv,
            self.config.big_patch_half,
            self.config.patch_half,
        ) else {
            return false;
        };
        if patch.plain.is_none() {
            return false;
        }
        let Some(init) = initialise(
            &self.camera,
            &self.state,
            uv,
            self.config.initial_inverse_depth,
        ) else {
            return false;
        };
        let jc = SMatrix::<f64, 6, 6>::from_iterator(init.d_camera.iter().copied());
        let ju = SMatrix::<f64, 6, 2>::from_iterator(init.d_pixel.iter().copied());
        let jr = SMatrix::<f64, 6, 1>::from_iterator(init.d_rho.iter().copied());
        let pcc = SMatrix::<f64, 6, 6>::from_fn(|r, c| self.cov[(r, c)]);
        let sp = self.config.sigma_pixel * self.config.sigma_pixel;
        let sr = self.config.sigma_inverse_depth * self.config.sigma_inverse_depth;
        let block = jc * pcc * jc.transpose() + ju * ju.transpose() * sp + jr * jr.transpose() * sr;
        pending.push((jc, block));
        self.features.push(Feature {
            id: self.next_id,
            landmark: init.landmark,
            patch,
            camera_init: (self.state.rotation, self.state.position),
            frames_unmatched: 0,
            attempts: 0,
            matches: 0,
        });
        self.next_id += 1;
        self.stats.features_initialised += 1;
        true
    }
}

/// Copies the strict lower triangle of the column-major `n x n` matrix in `data` onto the
/// upper one, by square tiles so that both the reads and the writes stay in cache.
fn mirror_lower(data: &mut [f64], n: usize) {
    const TILE: usize = 64;
    let mut tile = [0.0f64; TILE * TILE];
    for cb in (0..n).step_by(TILE) {
        let ce = (cb + TILE).min(n);
        for rb in (cb..n).step_by(TILE) {
            let re = (rb + TILE).min(n);
            // Gather the tile (rows rb..re, columns cb..ce) of the lower triangle by columns,
            // transposed, then write it as the tile (rows cb..ce, columns rb..re) of the upper
            // one, column by column: contiguous reads and writes.
            for c in cb..ce {
                for (r, v) in (rb..re).zip(&data[c * n + rb..c * n + re]) {
                    tile[(r - rb) * TILE + c - cb] = *v;
                }
            }
            for r in rb..re {
                // Upper entries (c, r) with c < r only; the diagonal tile keeps its lower half.
                let cend = ce.min(r);
                if cend <= cb {
                    continue;
                }
                let src = &tile[(r - rb) * TILE..(r - rb) * TILE + cend - cb];
                data[r * n + cb..r * n + cend].copy_from_slice(src);
            }
        }
    }
}

fn ms(t0: Instant) -> f64 {
    t0.elapsed().as_secs_f64() * 1e3
}

#[cfg(test)]
mod tests {
    use super::*;

    fn lcg(state: &mut u64) -> f64 {
        *state = state
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        (*state >> 11) as f64 / (1u64 << 53) as f64 - 0.5
    }

    #[test]
    fn mirror_lower_makes_the_matrix_symmetric_from_its_lower_triangle() {
        let mut state = 3;
        for n in [1usize, 2, 63, 64, 65, 130, 200] {
            let lower: Vec<f64> = (0..n * n).map(|_| lcg(&mut state)).collect();
            let mut data = lower.clone();
            mirror_lower(&mut data, n);
            for c in 0..n {
                for r in 0..n {
                    let want = if r >= c {
                        lower[c * n + r]
                    } else {
                        lower[r * n + c]
                    };
                    assert_eq!(data[c * n + r], want, "n {n} ({r}, {c})");
                }
            }
        }
    }

    #[test]
    fn occupancy_agrees_with_the_brute_force_distance_test() {
        let mut state = 5;
        let mut occ = Occupancy::new(200, 150, 12.0);
        let mut taken: Vec<DVec2> = Vec::new();
        for _ in 0..60 {
            let uv = DVec2::new(
                (lcg(&mut state) + 0.5) * 199.0,
                (lcg(&mut state) + 0.5) * 149.0,
            );
            occ.insert(uv);
            taken.push(uv);
        }
        for _ in 0..5000 {
            let uv = DVec2::new(
                (lcg(&mut state) + 0.5) * 199.0,
                (lcg(&mut state) + 0.5) * 149.0,
            );
            let brute = taken.iter().all(|t| (*t - uv).length_squared() > 144.0);
            assert_eq!(occ.is_free(uv), brute, "{uv:?}");
        }
    }

    #[test]
    fn batched_landmark_insertion_is_the_linearised_joint_covariance() {
        // Old state: camera (12) + 2 landmarks; three new landmarks y_j = J_j x_pose + e_j,
        // cov(e_j) = N_j. The batched covariance must equal G diag(P, N_1, N_2, N_3) G^T.
        let camera = UnifiedCamera::new(0.0, 100.0, 39.5, 29.5, 80, 60);
        let mut slam = MonoSlam::new(camera, MonoConfig::default()).unwrap();
        let mut state = 11;
        let n = CAMERA_DIM + 2 * LANDMARK_DIM;
        let a = DMatrix::from_fn(n, n, |_, _| lcg(&mut state));
        let p = &a * a.transpose() + DMatrix::identity(n, n);
        slam.cov = p.clone();
        let pcc = SMatrix::<f64, 6, 6>::from_fn(|r, c| p[(r, c)]);
        let mut pending = Vec::new();
        let mut noises = Vec::new();
        for _ in 0..3 {
            let jc = SMatrix::<f64, 6, 6>::from_fn(|_, _| lcg(&mut state));
            let b = SMatrix::<f64, 6, 6>::from_fn(|_, _| lcg(&mut state));
            let noise = b * b.transpose() + SMatrix::<f64, 6, 6>::identity() * 0.1;
            pending.push((jc, jc * pcc * jc.transpose() + noise));
            noises.push(noise);
        }
        slam.extend_covariance(&pending);
        let total = n + 18;
        let mut g = DMatrix::zeros(total, total);
        let mut aug = DMatrix::zeros(total, total);
        aug.view_mut((0, 0), (n, n)).copy_from(&p);
        for k in 0..n {
            g[(k, k)] = 1.0;
        }
        for (j, ((jc, _), noise)) in pending.iter().zip(&noises).enumerate() {
            let o = n + 6 * j;
            for r in 0..6 {
                for c in 0..6 {
                    g[(o + r, c)] = jc[(r, c)];
                    aug[(o + r, o + c)] = noise[(r, c)];
                }
                g[(o + r, o + r)] = 1.0;
            }
        }
        let want = &g * aug * g.transpose();
        assert_eq!(slam.cov.nrows(), total);
        let err = (&slam.cov - &want).abs().max();
        assert!(err < 1e-9 * want.abs().max(), "{err}");
    }
}
