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

use glam::{DVec2, DVec3};
use nalgebra::{DMatrix, DVector, SMatrix};
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;
use rayon::prelude::*;

use super::fast;
use super::landmark::{initialise, InverseDepthLandmark, Prediction, LANDMARK_DIM};
use super::patch::{FeaturePatch, PatchMode};
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
        let template = match self.config.patch_mode {
            PatchMode::Plain => f.patch.plain.clone()?,
            PatchMode::Warped => {
                let ratio = 1.0 / f.landmark.ray_in_camera(&self.state).length().max(1e-9);
                f.patch
                    .warped(&self.camera, pred.uv, ratio, self.config.k_lim, half)?
                    .0
            }
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
        let mut scores = vec![f64::NEG_INFINITY; bw * bh];
        let mut best = (f64::NEG_INFINITY, 0usize, 0usize);
        for y in y0..=y1 {
            for x in x0..=x1 {
                let d = nalgebra::Vector2::new(x as f64 - pred.uv.x, y as f64 - pred.uv.y);
                // Outside the ellipse, except the pixels next to the prediction.
                if (d.transpose() * si * d)[(0, 0)] > CHI2_95_2DOF
                    && !(d.x.abs() < 1.0 && d.y.abs() < 1.0)
                {
                    continue;
                }
                let Some(c) = template.correlate_at(image, x, y) else {
                    continue;
                };
                let (bx, by) = ((x - x0) as usize, (y - y0) as usize);
                scores[by * bw + bx] = c;
                if c > best.0 {
                    best = (c, bx, by);
                }
            }
        }
        if !(best.0 >= self.config.zncc_threshold) {
            return None;
        }
        let (bx, by) = (best.1, best.2);
        let at = |x: usize, y: usize| scores[y * bw + x];
        let refine = |m: f64, c: f64, p: f64| {
            let den = m - 2.0 * c + p;
            if m.is_finite() && p.is_finite() && den < -1e-12 {
                (0.5 * (m - p) / den).clamp(-0.5, 0.5)
            } else {
                0.0
            }
        };
        let dx = if bx > 0 && bx + 1 < bw {
            refine(at(bx - 1, by), best.0, at(bx + 1, by))
        } else {
            0.0
        };
        let dy = if by > 0 && by + 1 < bh {
            refine(at(bx, by - 1), best.0, at(bx, by + 1))
        } else {
            0.0
        };
        Some(DVec2::new(
            (x0 + bx as i64) as f64 + dx,
            (y0 + by as i64) as f64 + dy,
        ))
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
        let mut pht = DMatrix::zeros(n, m2);
        for (j, (b, p)) in batch.iter().zip(&preds).enumerate() {
            pht.columns_mut(2 * j, 2)
                .copy_from(&self.p_ht(b.feature, p));
        }
        let mut s = DMatrix::zeros(m2, m2);
        for (j, (b, p)) in batch.iter().zip(&preds).enumerate() {
            let o = landmark_offset(b.feature);
            let h = Self::stacked_jacobian(p);
            for c in 0..m2 {
                for rr in 0..2 {
                    let mut acc = 0.0;
                    for q in 0..12 {
                        let row = if q < 6 { q } else { o + q - 6 };
                        acc += h[(rr, q)] * pht[(row, c)];
                    }
                    s[(2 * j + rr, c)] = acc;
                }
            }
        }
        let r = self.config.sigma_pixel * self.config.sigma_pixel;
        for d in 0..m2 {
            s[(d, d)] += r;
        }
        let s = (&s + s.transpose()) * 0.5;
        let Some(chol) = s.cholesky() else {
            return Err(MonoError::Diverged(
                "innovation covariance is not positive definite".into(),
            ));
        };
        let mut nu = DVector::zeros(m2);
        for (j, (b, p)) in batch.iter().zip(&preds).enumerate() {
            nu[2 * j] = b.z.x - p.uv.x;
            nu[2 * j + 1] = b.z.y - p.uv.y;
        }
        // With S = L L^T and W = P H^T L^-T: K nu = W L^-1 nu and
        // P - K S K^T = P - W W^T, a symmetric rank-2m update (the O(n^2 m) step): only the
        // lower triangle is computed, by blocks of columns in parallel, then mirrored.
        let l = chol.l();
        let Some(wt) = l.solve_lower_triangular(&pht.transpose()) else {
            return Err(MonoError::Diverged("singular innovation covariance".into()));
        };
        let Some(lnu) = l.solve_lower_triangular(&nu) else {
            return Err(MonoError::Diverged("singular innovation covariance".into()));
        };
        let dx = wt.transpose() * lnu;
        let w = wt.transpose();
        let block = n.div_ceil(8 * rayon::current_num_threads().max(1)).max(16);
        self.cov
            .as_mut_slice()
            .par_chunks_mut(n * block)
            .enumerate()
            .for_each(|(b, chunk)| {
                let c0 = b * block;
                let nc = chunk.len() / n;
                let mut view = nalgebra::DMatrixViewMut::from_slice(chunk, n, nc);
                let mut lower = view.rows_mut(c0, n - c0);
                lower.gemm(-1.0, &w.rows(c0, n - c0), &wt.columns(c0, nc), 1.0);
            });
        for c in 0..n {
            for r in 0..c {
                self.cov[(r, c)] = self.cov[(c, r)];
            }
        }
        self.state = self.state.corrected(&dx.as_slice()[..CAMERA_DIM]);
        for (i, f) in self.features.iter_mut().enumerate() {
            let o = landmark_offset(i);
            f.landmark = f.landmark.corrected(&dx.as_slice()[o..o + 6]);
        }
        Ok(())
    }

    /// Removes landmark `i` from the state, moving it to the fixed map when it is a point.
    fn remove_feature(&mut self, i: usize) {
        if self.is_point(i) {
            if let Some(p) = self.features[i].landmark.point() {
                self.fixed_map.push(p);
                self.stats.map_points += 1;
            } else {
                self.stats.rays_dropped += 1;
            }
        } else {
            self.stats.rays_dropped += 1;
        }
        let o = landmark_offset(i);
        let cov = std::mem::replace(&mut self.cov, DMatrix::zeros(0, 0));
        self.cov = cov
            .remove_rows(o, LANDMARK_DIM)
            .remove_columns(o, LANDMARK_DIM);
        self.features.remove(i);
    }

    fn manage_map(&mut self) {
        let mut i = self.features.len();
        while i > 0 {
            i -= 1;
            let f = &self.features[i];
            let lost = f.frames_unmatched > self.config.max_unmatched_frames;
            let unreliable = f.attempts >= 10 && 2 * f.matches < f.attempts;
            if lost || unreliable {
                self.remove_feature(i);
            }
        }
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
        let min_dist2 = self.config.min_feature_distance.powi(2);
        let mut taken: Vec<DVec2> = predicted;
        let mut added = 0;
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
                while let Some(pos) = list.iter().position(|uv| {
                    taken
                        .iter()
                        .all(|t| (*t - *uv).length_squared() > min_dist2)
                }) {
                    let uv = list.remove(pos);
                    if self.add_feature(image, uv) {
                        taken.push(uv);
                        added += 1;
                        break;
                    }
                }
            }
            if added == before || added >= budget {
                break;
            }
        }
        added
    }

    /// Adds a landmark at pixel `uv` with its covariance (eq. 2.44-2.50).
    fn add_feature(&mut self, image: &ImageF32, uv: DVec2) -> bool {
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
        let n = self.cov.nrows();
        let jc = DMatrix::from_iterator(6, 6, init.d_camera.iter().copied());
        let ju = DMatrix::from_iterator(6, 2, init.d_pixel.iter().copied());
        let jr = DMatrix::from_iterator(6, 1, init.d_rho.iter().copied());
        // Cross covariance with everything: J_c P[cam, :].
        let p_cam_all = self.cov.rows(0, 6).clone_owned();
        let cross = &jc * &p_cam_all; // 6 x n
        let pcc = self.cov.view((0, 0), (6, 6)).clone_owned();
        let sp = self.config.sigma_pixel * self.config.sigma_pixel;
        let sr = self.config.sigma_inverse_depth * self.config.sigma_inverse_depth;
        let block =
            &jc * pcc * jc.transpose() + &ju * ju.transpose() * sp + &jr * jr.transpose() * sr;
        let mut cov = DMatrix::zeros(n + 6, n + 6);
        cov.view_mut((0, 0), (n, n)).copy_from(&self.cov);
        cov.view_mut((n, 0), (6, n)).copy_from(&cross);
        cov.view_mut((0, n), (n, 6)).copy_from(&cross.transpose());
        cov.view_mut((n, n), (6, 6)).copy_from(&block);
        self.cov = cov;
        self.features.push(Feature {
            id: self.next_id,
            landmark: init.landmark,
            patch,
            frames_unmatched: 0,
            attempts: 0,
            matches: 0,
        });
        self.next_id += 1;
        self.stats.features_initialised += 1;
        true
    }
}

fn ms(t0: Instant) -> f64 {
    t0.elapsed().as_secs_f64() * 1e3
}
