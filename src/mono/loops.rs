//! Loop detection and verification for monocular SLAM with a central camera (thesis 3.3.2):
//! keyframes chosen from the EKF stream, ORB + bag of binary words on them with the mirror's
//! blind areas masked, a keyframe-database query outside a temporal window, and geometric
//! verification by an essential matrix fitted with RANSAC to matched bearing vectors.
//!
//! Frames and units: bearings are unit vectors in the camera frame (x right, y down, z
//! forward) from [`UnifiedCamera::unproject`]; a verified loop's relative pose is
//! `query_from_candidate` with a unit-length translation (monocular geometry fixes the
//! direction of the baseline, not its length); angles are radians unless a name says degrees;
//! time stamps are seconds.
//!
//! Keyframe policy ([`KeyframePolicy`]): a frame becomes a keyframe when fewer than
//! `min_overlap` of the landmarks tracked at the last keyframe are still tracked, or
//! `max_interval` seconds after it, and never sooner than `min_interval` after it. Overlap of
//! tracked landmarks measures how much the view changed without the monocular map's unknown
//! scale (a policy "every N metres" would need the metric scale, which is what the loops are
//! meant to help estimate), and the time bounds keep a standing walker from adding keyframes
//! while a fast turn cannot add one per frame.

use std::collections::HashSet;

use glam::{DMat3, DVec3};
use nalgebra::{Matrix3, SMatrix, SymmetricEigen};
use rand::{Rng, SeedableRng};

use super::{MonoError, MonoSlam};
use crate::camera::UnifiedCamera;
use crate::geometry::Se3;
use crate::image::ImageF32;
use crate::place::{
    extract_orb, match_descriptors, BowVector, Descriptor, KeyPoint, KeyframeDatabase, MatchParams,
    OrbParams, QueryParams, Vocabulary,
};

/// When a frame of the EKF stream becomes a keyframe.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct KeyframePolicy {
    /// Fraction, in (0, 1], of the landmarks tracked at the last keyframe that must still be
    /// tracked; below it the frame becomes a keyframe.
    pub min_overlap: f64,
    /// Seconds after the last keyframe at which a frame becomes a keyframe anyway (> 0).
    pub max_interval: f64,
    /// Seconds after the last keyframe before which no frame becomes one (>= 0).
    pub min_interval: f64,
}

impl Default for KeyframePolicy {
    fn default() -> Self {
        KeyframePolicy {
            min_overlap: 0.5,
            max_interval: 2.0,
            min_interval: 0.25,
        }
    }
}

/// Chooses keyframes from the EKF stream by [`KeyframePolicy`].
#[derive(Clone, Debug)]
pub struct KeyframeSelector {
    policy: KeyframePolicy,
    last: Option<(f64, HashSet<usize>)>,
}

impl KeyframeSelector {
    /// A selector whose first frame will be a keyframe.
    pub fn new(policy: KeyframePolicy) -> Result<KeyframeSelector, MonoError> {
        let bad = |name, why: &str| {
            Err(MonoError::InvalidConfig {
                name,
                why: why.into(),
            })
        };
        if !(policy.min_overlap > 0.0 && policy.min_overlap <= 1.0) {
            return bad("keyframes.min_overlap", "must be in (0, 1]");
        }
        if !(policy.max_interval > 0.0 && policy.max_interval.is_finite()) {
            return bad("keyframes.max_interval", "must be finite and > 0 s");
        }
        if !(policy.min_interval >= 0.0 && policy.min_interval <= policy.max_interval) {
            return bad("keyframes.min_interval", "must be in [0, max_interval] s");
        }
        Ok(KeyframeSelector { policy, last: None })
    }

    /// Ids of the landmarks the filter tracked in its last frame (matched, or initialised
    /// there).
    fn tracked(slam: &MonoSlam) -> HashSet<usize> {
        slam.features()
            .iter()
            .filter(|f| f.frames_unmatched == 0)
            .map(|f| f.id)
            .collect()
    }

    /// Call after `slam` processed the frame at `timestamp` (seconds): true when that frame
    /// is a keyframe (it is then the reference of the next decisions).
    pub fn update(&mut self, timestamp: f64, slam: &MonoSlam) -> bool {
        let now = Self::tracked(slam);
        let take = match &self.last {
            None => true,
            Some((t, kf)) => {
                let dt = timestamp - t;
                let overlap = if kf.is_empty() {
                    0.0
                } else {
                    kf.intersection(&now).count() as f64 / kf.len() as f64
                };
                dt >= self.policy.min_interval
                    && (dt >= self.policy.max_interval || overlap < self.policy.min_overlap)
            }
        };
        if take {
            self.last = Some((timestamp, now));
        }
        take
    }
}

/// Parameters of [`MonoLoopDetector`].
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MonoLoopParams {
    /// Keyframe selection.
    pub keyframes: KeyframePolicy,
    /// ORB extraction (spread over a grid of cells so the bag of words describes the whole
    /// panorama, not only its most textured objects).
    pub orb: OrbParams,
    /// Pixels kept clear of the mirror's rim and of the central blind disc, so that no
    /// descriptor patch straddles the edge of the valid image (>= 0).
    pub mask_margin: f64,
    /// Temporal window, seconds: keyframes closer in time than this to the query are never
    /// loop candidates (>= 0).
    pub min_time_separation: f64,
    /// Best-scoring candidates verified geometrically per query (>= 1).
    pub max_candidates: usize,
    /// Smallest normalised BoW score (score against the candidate over score against the
    /// previous keyframe) of a candidate that is verified (>= 0).
    pub min_normalised_score: f64,
    /// Descriptor matching between query and candidate.
    pub matching: MatchParams,
    /// RANSAC hypotheses for the essential matrix (>= 1).
    pub ransac_iterations: usize,
    /// Largest angle, radians, between a bearing and the epipolar plane of its match for an
    /// inlier (> 0).
    pub angular_threshold: f64,
    /// Fewest essential-matrix inliers of a verified loop (>= 8).
    pub min_inliers: usize,
    /// Smallest fraction of the descriptor matches that are inliers, in [0, 1].
    pub min_inlier_ratio: f64,
    /// Seed of the RANSAC sampling (results are deterministic for a seed).
    pub seed: u64,
}

impl Default for MonoLoopParams {
    fn default() -> Self {
        MonoLoopParams {
            keyframes: KeyframePolicy::default(),
            orb: OrbParams {
                n_features: 600,
                distribute: true,
                ..OrbParams::default()
            },
            mask_margin: 16.0,
            min_time_separation: 10.0,
            max_candidates: 3,
            min_normalised_score: 0.3,
            matching: MatchParams::default(),
            ransac_iterations: 300,
            angular_threshold: 0.01,
            min_inliers: 30,
            min_inlier_ratio: 0.3,
            seed: 0x100b,
        }
    }
}

impl MonoLoopParams {
    /// Checks the ranges.
    pub fn validate(&self) -> Result<(), MonoError> {
        KeyframeSelector::new(self.keyframes)?;
        let checks: [(&'static str, bool, &str); 7] = [
            (
                "loops.mask_margin",
                self.mask_margin >= 0.0 && self.mask_margin.is_finite(),
                "must be finite and >= 0 pixels",
            ),
            (
                "loops.min_time_separation",
                self.min_time_separation >= 0.0 && self.min_time_separation.is_finite(),
                "must be finite and >= 0 s",
            ),
            (
                "loops.max_candidates",
                self.max_candidates >= 1,
                "must be >= 1",
            ),
            (
                "loops.min_normalised_score",
                self.min_normalised_score >= 0.0,
                "must be >= 0",
            ),
            (
                "loops.ransac_iterations",
                self.ransac_iterations >= 1,
                "must be >= 1",
            ),
            (
                "loops.angular_threshold",
                self.angular_threshold > 0.0 && self.angular_threshold < 1.0,
                "must be in (0, 1) rad",
            ),
            (
                "loops.min_inliers / min_inlier_ratio",
                self.min_inliers >= 8 && (0.0..=1.0).contains(&self.min_inlier_ratio),
                "min_inliers >= 8 and min_inlier_ratio in [0, 1]",
            ),
        ];
        for (name, ok, why) in checks {
            if !ok {
                return Err(MonoError::InvalidConfig {
                    name,
                    why: why.into(),
                });
            }
        }
        Ok(())
    }
}

/// A keyframe's place-recognition description.
#[derive(Clone, Debug)]
pub struct MonoKeyframe {
    /// Index of the frame in the stream (0-based).
    pub frame: usize,
    /// Time stamp, seconds.
    pub timestamp: f64,
    /// The filter's `world_from_camera` at that frame (filter world, unknown scale).
    pub world_from_camera: Se3,
    /// ORB keypoints inside the mask, level-0 pixels.
    pub keypoints: Vec<KeyPoint>,
    /// Their descriptors.
    pub descriptors: Vec<Descriptor>,
    /// Their unit bearings in the camera frame.
    pub bearings: Vec<DVec3>,
    /// Bag of words of all descriptors.
    pub bow: BowVector,
}

/// The geometric check of one database candidate.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct CandidateCheck {
    /// The candidate keyframe (index into [`MonoLoopDetector::keyframes`]).
    pub keyframe: usize,
    /// Raw BoW similarity in [0, 1].
    pub score: f64,
    /// Score over the query's score against its previous keyframe.
    pub normalised_score: f64,
    /// Descriptor matches.
    pub matches: usize,
    /// Essential-matrix inliers among them (0 when fewer than 8 matches).
    pub inliers: usize,
    /// The relative pose `query_from_candidate` (unit translation) when an essential matrix
    /// was found.
    #[serde(skip)]
    pub query_from_candidate: Option<Se3>,
    /// Median angle, degrees, between the inlier bearings of the query and the candidate's
    /// bearings rotated into the query frame (the parallax left once rotation is removed).
    pub parallax_deg: f64,
}

impl CandidateCheck {
    /// Inliers over matches (0 without matches).
    pub fn inlier_ratio(&self) -> f64 {
        if self.matches == 0 {
            0.0
        } else {
            self.inliers as f64 / self.matches as f64
        }
    }

    /// True when the check passes the thresholds: normalised score, inliers, inlier ratio.
    pub fn accepted(&self, min_normalised_score: f64, min_inliers: usize, min_ratio: f64) -> bool {
        self.normalised_score >= min_normalised_score
            && self.inliers >= min_inliers
            && self.inlier_ratio() >= min_ratio
    }
}

/// Everything found for one query keyframe.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct KeyframeQuery {
    /// The query keyframe.
    pub keyframe: usize,
    /// Its score against the previous keyframe (the normaliser).
    pub reference_score: f64,
    /// Candidates outside the temporal window, best BoW score first, with their checks.
    pub candidates: Vec<CandidateCheck>,
}

impl KeyframeQuery {
    /// The accepted candidate with most inliers at the given thresholds, if any.
    pub fn best(
        &self,
        min_normalised_score: f64,
        min_inliers: usize,
        min_ratio: f64,
    ) -> Option<&CandidateCheck> {
        self.candidates
            .iter()
            .filter(|c| c.accepted(min_normalised_score, min_inliers, min_ratio))
            .max_by_key(|c| c.inliers)
    }
}

/// Loop detector over the keyframes of a monocular stream.
pub struct MonoLoopDetector {
    camera: UnifiedCamera,
    params: MonoLoopParams,
    vocabulary: Vocabulary,
    database: KeyframeDatabase,
    keyframes: Vec<MonoKeyframe>,
    mask: ImageF32,
}

impl MonoLoopDetector {
    /// A detector with an empty database; the mask is the camera's valid region shrunk by
    /// `params.mask_margin`.
    pub fn new(
        camera: UnifiedCamera,
        vocabulary: Vocabulary,
        params: MonoLoopParams,
    ) -> Result<MonoLoopDetector, MonoError> {
        params.validate()?;
        camera
            .validate()
            .map_err(|e| MonoError::Camera(e.to_string()))?;
        let mask = valid_mask(&camera, params.mask_margin);
        let database = KeyframeDatabase::new(vocabulary.num_words(), vocabulary.scoring());
        Ok(MonoLoopDetector {
            camera,
            params,
            vocabulary,
            database,
            keyframes: Vec::new(),
            mask,
        })
    }

    /// The parameters.
    pub fn params(&self) -> &MonoLoopParams {
        &self.params
    }

    /// The feature mask (1 = usable, 0 = outside the mirror or in its blind centre).
    pub fn mask(&self) -> &ImageF32 {
        &self.mask
    }

    /// The keyframes added so far, in order.
    pub fn keyframes(&self) -> &[MonoKeyframe] {
        &self.keyframes
    }

    /// Describes `image` (intensity in [0, 255], the camera's size), queries the database
    /// with it, verifies the best candidates, then adds it as the next keyframe. `frame` and
    /// `world_from_camera` are kept with the keyframe for the caller.
    pub fn add_keyframe(
        &mut self,
        frame: usize,
        timestamp: f64,
        world_from_camera: Se3,
        image: &ImageF32,
    ) -> Result<KeyframeQuery, MonoError> {
        let (w, h) = (self.camera.width as usize, self.camera.height as usize);
        if image.width != w || image.height != h {
            return Err(MonoError::ImageSize {
                what: format!("keyframe at {timestamp} s"),
                width: image.width,
                height: image.height,
                expected_width: w,
                expected_height: h,
            });
        }
        let orb = extract_orb(image, Some(&self.mask), &self.params.orb)?;
        let mut keypoints = Vec::with_capacity(orb.len());
        let mut descriptors = Vec::with_capacity(orb.len());
        let mut bearings = Vec::with_capacity(orb.len());
        for (k, d) in orb.keypoints.iter().zip(&orb.descriptors) {
            if let Some(b) = self.camera.unproject(k.uv) {
                keypoints.push(*k);
                descriptors.push(*d);
                bearings.push(b.normalize());
            }
        }
        let (bow, _) = self.vocabulary.transform(&descriptors, 0);
        let id = self.keyframes.len();
        let query = MonoKeyframe {
            frame,
            timestamp,
            world_from_camera,
            keypoints,
            descriptors,
            bearings,
            bow,
        };
        let bows = std::slice::from_ref(&query.bow);
        let mut result = KeyframeQuery {
            keyframe: id,
            reference_score: 0.0,
            candidates: Vec::new(),
        };
        if id > 0 {
            let reference = self.database.score_against(bows, id - 1)?;
            result.reference_score = reference;
            let all = QueryParams {
                max_results: usize::MAX,
                min_separation: 0,
                min_normalised_score: self.params.min_normalised_score,
                min_reference_score: 0.0,
            };
            let candidates: Vec<_> = self
                .database
                .query(id, bows, reference.max(1e-12), &all)
                .into_iter()
                .filter(|c| {
                    self.keyframes
                        .get(c.keyframe_id)
                        .is_some_and(|k| timestamp - k.timestamp >= self.params.min_time_separation)
                })
                .take(self.params.max_candidates)
                .collect();
            for (n, c) in candidates.into_iter().enumerate() {
                let old = &self.keyframes[c.keyframe_id];
                let seed = self.params.seed ^ ((id as u64) << 20) ^ n as u64;
                let mut check = verify(&query, old, &self.params, seed);
                check.keyframe = c.keyframe_id;
                check.score = c.score;
                check.normalised_score = c.normalised_score;
                result.candidates.push(check);
            }
        }
        self.database.add(id, vec![query.bow.clone()])?;
        self.keyframes.push(query);
        Ok(result)
    }
}

/// The monocular EKF with keyframe selection and loop detection beside it: each frame goes
/// through the filter, and a frame the [`KeyframeSelector`] takes is described, queried and
/// added to the [`MonoLoopDetector`].
pub struct LoopingMono {
    slam: MonoSlam,
    selector: KeyframeSelector,
    detector: MonoLoopDetector,
    frame: usize,
}

/// One frame's outcome of [`LoopingMono::process`].
#[derive(Clone, Debug)]
pub struct LoopingReport {
    /// The filter's report.
    pub filter: super::FrameReport,
    /// The keyframe query when the frame became a keyframe.
    pub keyframe: Option<KeyframeQuery>,
    /// Milliseconds spent on keyframe selection, ORB, database query and verification.
    pub loop_ms: f64,
}

impl LoopingMono {
    /// The filter `slam` with a loop detector using `vocabulary` and `params`.
    pub fn new(
        slam: MonoSlam,
        vocabulary: Vocabulary,
        params: MonoLoopParams,
    ) -> Result<LoopingMono, MonoError> {
        let selector = KeyframeSelector::new(params.keyframes)?;
        let detector = MonoLoopDetector::new(*slam.camera(), vocabulary, params)?;
        Ok(LoopingMono {
            slam,
            selector,
            detector,
            frame: 0,
        })
    }

    /// The filter.
    pub fn slam(&self) -> &MonoSlam {
        &self.slam
    }

    /// The loop detector (keyframes so far).
    pub fn detector(&self) -> &MonoLoopDetector {
        &self.detector
    }

    /// Processes the next frame (time stamp in seconds, intensity in [0, 255]).
    pub fn process(
        &mut self,
        timestamp: f64,
        image: &ImageF32,
    ) -> Result<LoopingReport, MonoError> {
        let filter = self.slam.process(timestamp, image)?;
        let t0 = std::time::Instant::now();
        let keyframe = if self.selector.update(timestamp, &self.slam) {
            Some(self.detector.add_keyframe(
                self.frame,
                timestamp,
                filter.world_from_camera,
                image,
            )?)
        } else {
            None
        };
        self.frame += 1;
        Ok(LoopingReport {
            filter,
            keyframe,
            loop_ms: t0.elapsed().as_secs_f64() * 1e3,
        })
    }
}

/// Settings of the loop similarity ([`MonoLoopDetector::loop_similarity`], eq. 3.10).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LoopScaleParams {
    /// Largest angle, radians, between a bearing and the epipolar plane of its match in the
    /// neighbouring keyframe, the plane given by the filter's relative pose, for the match to
    /// be triangulated (> 0). Looser than the loop's own threshold: the filter's pose carries
    /// its own error.
    pub local_threshold: f64,
    /// Smallest angle, radians, between the two rays of a locally triangulated point (> 0):
    /// below it the depth is too uncertain to measure a scale.
    pub min_parallax: f64,
    /// Fewest loop inliers with a local point in both keyframes for a similarity (>= 3).
    pub min_points: usize,
    /// Seconds over which the online (causal) output of [`super::MetricMono`] moves from the
    /// previous loop correction to a new one (>= 0; 0 applies it at once). A correction
    /// applied at once is a jump no walker makes, which a display or an odometer of the
    /// online output would show; spread over a second or two it adds little length.
    pub correction_blend: f64,
}

impl Default for LoopScaleParams {
    fn default() -> Self {
        LoopScaleParams {
            local_threshold: 0.02,
            min_parallax: 0.03,
            min_points: 8,
            correction_blend: 0.0,
        }
    }
}

impl LoopScaleParams {
    /// Checks the ranges.
    pub fn validate(&self) -> Result<(), MonoError> {
        let bad = |name, why: &str| {
            Err(MonoError::InvalidConfig {
                name,
                why: why.into(),
            })
        };
        if !(self.local_threshold > 0.0 && self.local_threshold < 1.0) {
            return bad("loop_scale.local_threshold", "must be in (0, 1) rad");
        }
        if !(self.min_parallax > 0.0 && self.min_parallax < 1.0) {
            return bad("loop_scale.min_parallax", "must be in (0, 1) rad");
        }
        if self.min_points < 3 {
            return bad("loop_scale.min_points", "must be >= 3");
        }
        if !(self.correction_blend >= 0.0 && self.correction_blend.is_finite()) {
            return bad("loop_scale.correction_blend", "must be finite and >= 0 s");
        }
        Ok(())
    }
}

/// The relative similarity of a verified loop (thesis 3.3.2, eq. 3.8-3.10) in the filter's
/// own units around each keyframe.
///
/// Each keyframe's ORB features are triangulated against its previous keyframe (the next one
/// for the first keyframe) with the filter's relative pose between the two: points in the
/// keyframe's camera frame in the filter's units at that time. The loop's inlier matches that
/// have a point in both keyframes give two reconstructions of the same structure; the ratio of
/// their scales (the median of the ratios of distances between point pairs, eq. 3.10) is the
/// similarity's scale, the rotation is the essential matrix's, and the translation the median
/// offset of the points once scaled and rotated.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LoopSimilarity {
    /// The query (newer) keyframe, index into [`MonoLoopDetector::keyframes`].
    pub query: usize,
    /// The candidate (older) keyframe.
    pub candidate: usize,
    /// `candidate_from_query`: `p_candidate = scale R p_query + t`, points in each keyframe's
    /// camera frame in the filter's units at that keyframe (its scale: the filter's units at the
    /// query over those at the candidate).
    pub candidate_from_query: crate::graph::Sim3,
    /// Points with a local depth in both keyframes used for the fit.
    pub points: usize,
    /// Robust standard deviation of the log of the scale (from the spread of the distance
    /// ratios).
    pub log_scale_std: f64,
    /// Robust standard deviation of each translation component, the candidate's units.
    pub translation_std: f64,
    /// Standard deviation of each rotation component, radians.
    pub rotation_std: f64,
}

/// Median of `v` (reordered); NaN when empty.
fn median_of(v: &mut [f64]) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

impl MonoLoopDetector {
    /// Points of keyframe `k`'s ORB features in its camera frame, filter units (one entry per
    /// keypoint; `None` where no depth was triangulated), triangulated against the keyframes
    /// before and after it with the filter's relative poses (where a feature has a point from
    /// both, the one of wider parallax is kept).
    fn local_points(&self, k: usize, p: &LoopScaleParams) -> Vec<Option<DVec3>> {
        let Some(kf) = self.keyframes.get(k) else {
            return Vec::new();
        };
        let mut out: Vec<Option<(DVec3, f64)>> = vec![None; kf.bearings.len()];
        for nb in [k.checked_sub(1), Some(k + 1)].into_iter().flatten() {
            if let Some(nb) = self.keyframes.get(nb) {
                self.triangulate_against(kf, nb, p, &mut out);
            }
        }
        out.into_iter().map(|x| x.map(|(pt, _)| pt)).collect()
    }

    /// Guided matching of `kf`'s features with `nb`'s along the epipolar planes of the
    /// filter's relative pose (the ratio test among the candidates near the plane only, which
    /// finds far more matches than an unguided ratio test between distant views), and their
    /// triangulation; fills `out` (point in `kf`'s frame, parallax in radians).
    fn triangulate_against(
        &self,
        kf: &MonoKeyframe,
        nb: &MonoKeyframe,
        p: &LoopScaleParams,
        out: &mut [Option<(DVec3, f64)>],
    ) {
        let kf_from_nb = kf.world_from_camera.inverse() * nb.world_from_camera;
        let t = kf_from_nb.translation;
        if !(t.length() > 1e-12) {
            return;
        }
        let r = kf_from_nb.rotation_matrix();
        let e = essential_of(&kf_from_nb);
        let sin_t = p.local_threshold.sin();
        // Epipolar plane normals: `E a` in kf's frame for nb's bearings, `E^T b` in nb's frame
        // for kf's, so that each pair costs two dot products.
        let unit = |v: DVec3| {
            let l = v.length();
            (l > 1e-12).then(|| v / l)
        };
        let planes_nb: Vec<Option<DVec3>> = nb.bearings.iter().map(|a| unit(e * *a)).collect();
        let m = &self.params.matching;
        for (qi, (dq, b)) in kf.descriptors.iter().zip(&kf.bearings).enumerate() {
            let Some(plane_kf) = unit(e.transpose() * *b) else {
                continue;
            };
            let (mut best, mut second, mut best_i) = (u32::MAX, u32::MAX, usize::MAX);
            for (ti, (dt, a)) in nb.descriptors.iter().zip(&nb.bearings).enumerate() {
                let Some(n2) = planes_nb[ti] else { continue };
                if b.dot(n2).abs() >= sin_t || a.dot(plane_kf).abs() >= sin_t {
                    continue;
                }
                let d = dq.distance(dt);
                if d < best {
                    (second, best, best_i) = (best, d, ti);
                } else if d < second {
                    second = d;
                }
            }
            if best > m.max_distance
                || (m.ratio < 1.0 && second != u32::MAX && best as f32 >= m.ratio * second as f32)
            {
                continue;
            }
            let a = nb.bearings[best_i];
            let parallax = (r * a).angle_between(*b);
            if parallax < p.min_parallax || out[qi].is_some_and(|(_, par)| par >= parallax) {
                continue;
            }
            if let Some((da, db)) = triangulate_depths(&r, t, a, *b) {
                if da > 0.0 && db > 0.0 && db.is_finite() {
                    out[qi] = Some((db * *b, parallax));
                }
            }
        }
    }

    /// The relative similarity of the verified loop `check` of query keyframe `query` (see
    /// [`LoopSimilarity`]); `None` when the check has no relative pose or fewer than
    /// `p.min_points` inliers have a local point in both keyframes.
    pub fn loop_similarity(
        &self,
        query: usize,
        check: &CandidateCheck,
        p: &LoopScaleParams,
    ) -> Option<LoopSimilarity> {
        let query_from_candidate = check.query_from_candidate?;
        let (q, c) = (
            self.keyframes.get(query)?,
            self.keyframes.get(check.keyframe)?,
        );
        let (local_q, local_c) = (
            self.local_points(query, p),
            self.local_points(check.keyframe, p),
        );
        let e = essential_of(&query_from_candidate);
        let sin_t = self.params.angular_threshold.sin();
        // The loop's inliers, as `verify` selects them after refinement.
        let mut pts: Vec<(DVec3, DVec3)> = Vec::new();
        for m in match_descriptors(&q.descriptors, &c.descriptors, &self.params.matching) {
            if epipolar_angle(&e, c.bearings[m.train], q.bearings[m.query]) >= sin_t {
                continue;
            }
            if let (Some(Some(pc)), Some(Some(pq))) = (local_c.get(m.train), local_q.get(m.query)) {
                pts.push((*pc, *pq));
            }
        }
        let rot = query_from_candidate.rotation.inverse();
        let fit = |pts: &[(DVec3, DVec3)]| -> Option<(f64, f64, DVec3, Vec<f64>)> {
            if pts.len() < p.min_points {
                return None;
            }
            let mut logs = Vec::with_capacity(pts.len() * (pts.len() - 1) / 2);
            for a in 0..pts.len() {
                for b in a + 1..pts.len() {
                    let (dc, dq) = (
                        (pts[a].0 - pts[b].0).length(),
                        (pts[a].1 - pts[b].1).length(),
                    );
                    if dc > 0.0 && dq > 0.0 {
                        logs.push((dc / dq).ln());
                    }
                }
            }
            let log_s = median_of(&mut logs.clone());
            let mut dev: Vec<f64> = logs.iter().map(|l| (l - log_s).abs()).collect();
            // Pairs share points: the spread of the ratios over the square root of the number
            // of points, not of pairs.
            let log_std = 1.4826 * median_of(&mut dev) / (pts.len() as f64).sqrt();
            let s = log_s.exp();
            let offsets: Vec<DVec3> = pts.iter().map(|(pc, pq)| *pc - s * (rot * *pq)).collect();
            let comp =
                |f: fn(&DVec3) -> f64| median_of(&mut offsets.iter().map(f).collect::<Vec<_>>());
            let t = DVec3::new(comp(|v| v.x), comp(|v| v.y), comp(|v| v.z));
            let res: Vec<f64> = offsets.iter().map(|o| (*o - t).length()).collect();
            (s.is_finite() && t.is_finite() && log_std.is_finite()).then_some((s, log_std, t, res))
        };
        let (_, _, _, res) = fit(&pts)?;
        // Points whose local depth is wrong (a match along the epipolar line of the
        // neighbour) sit far off the fit: drop them and fit again.
        let cut = 3.0 * 1.4826 * median_of(&mut res.clone());
        let kept: Vec<(DVec3, DVec3)> = pts
            .iter()
            .zip(&res)
            .filter(|(_, r)| **r <= cut)
            .map(|(x, _)| *x)
            .collect();
        if kept.len() < p.min_points {
            return None;
        }
        let (s, log_std, t, res) = fit(&kept)?;
        let n = res.len() as f64;
        // Per component: the residual vectors' median length spread over three axes.
        let translation_std = 1.4826 * median_of(&mut res.clone()) / (3.0 * n).sqrt();
        let depth = median_of(&mut kept.iter().map(|x| x.0.length()).collect::<Vec<_>>());
        Some(LoopSimilarity {
            query,
            candidate: check.keyframe,
            candidate_from_query: crate::graph::Sim3::new(rot, t, s),
            points: kept.len(),
            log_scale_std: log_std.max(0.01),
            translation_std: translation_std.max(0.01 * depth),
            rotation_std: self.params.angular_threshold,
        })
    }
}

/// The camera's valid region shrunk by `margin` pixels: 1 inside, 0 outside.
fn valid_mask(camera: &UnifiedCamera, margin: f64) -> ImageF32 {
    let (w, h) = (camera.width as usize, camera.height as usize);
    let mut shrunk = *camera;
    shrunk.fov_radius = camera.fov_radius.map(|r| r - margin);
    shrunk.inner_radius = camera.inner_radius.map(|r| r + margin);
    let valid = shrunk.fov_mask();
    let mut mask = ImageF32::filled(w, h, 0.0);
    let data = mask.data_mut();
    for (i, v) in valid.into_iter().enumerate() {
        let (x, y) = (i % w, i / w);
        // A rectangular image edge (pinhole, fisheye) needs the same margin as the rim.
        let inside = x as f64 >= margin
            && y as f64 >= margin
            && ((w - 1 - x) as f64) >= margin
            && ((h - 1 - y) as f64) >= margin;
        if v && inside {
            data[i] = 1.0;
        }
    }
    mask
}

/// Matches `query` against `old` and fits an essential matrix to the matched bearings.
fn verify(
    query: &MonoKeyframe,
    old: &MonoKeyframe,
    params: &MonoLoopParams,
    seed: u64,
) -> CandidateCheck {
    let matches = match_descriptors(&query.descriptors, &old.descriptors, &params.matching);
    let pairs: Vec<(DVec3, DVec3)> = matches
        .iter()
        .map(|m| (old.bearings[m.train], query.bearings[m.query]))
        .collect();
    let mut check = CandidateCheck {
        keyframe: 0,
        score: 0.0,
        normalised_score: 0.0,
        matches: pairs.len(),
        inliers: 0,
        query_from_candidate: None,
        parallax_deg: 0.0,
    };
    if let Some(fit) = ransac_essential(
        &pairs,
        params.ransac_iterations,
        params.angular_threshold,
        seed,
    ) {
        check.inliers = fit.inliers.len();
        let refined = decompose(&fit.essential, &pairs, &fit.inliers).map(|pose| {
            let pose = refine(pose, &pairs, &fit.inliers);
            let e = essential_of(&pose);
            let sin_t = params.angular_threshold.sin();
            let inliers: Vec<usize> = (0..pairs.len())
                .filter(|&i| epipolar_angle(&e, pairs[i].0, pairs[i].1) < sin_t)
                .collect();
            (pose, inliers)
        });
        if let Some((pose, inliers)) = refined {
            let fit = EssentialFit {
                essential: essential_of(&pose),
                inliers,
            };
            check.inliers = fit.inliers.len();
            let r = pose.rotation_matrix();
            let mut angles: Vec<f64> = fit
                .inliers
                .iter()
                .map(|&i| (r * pairs[i].0).angle_between(pairs[i].1).to_degrees())
                .collect();
            angles.sort_by(f64::total_cmp);
            check.parallax_deg = angles.get(angles.len() / 2).copied().unwrap_or(0.0);
            check.query_from_candidate = Some(pose);
        }
    }
    check
}

/// `E = [t]x R` of a relative pose `second_from_first`.
pub(crate) fn essential_of(pose: &Se3) -> DMat3 {
    let t = pose.translation;
    let tx = DMat3::from_cols(
        DVec3::new(0.0, t.z, -t.y),
        DVec3::new(-t.z, 0.0, t.x),
        DVec3::new(t.y, -t.x, 0.0),
    );
    tx * pose.rotation_matrix()
}

/// Signed sine of the angle between bearing `b` (second frame) and the epipolar plane
/// spanned by `t` and `R a`; `None` where the plane is undefined.
fn plane_residual(r: &DMat3, t: DVec3, a: DVec3, b: DVec3) -> Option<f64> {
    let n = t.cross(*r * a);
    let l = n.length();
    (l > 1e-12).then(|| b.dot(n) / l)
}

/// Gauss-Newton on the relative pose (rotation, unit translation: 5 degrees of freedom)
/// minimising the squared angular distances of the inliers' bearings to their epipolar
/// planes. The linear 8-point fit minimises an algebraic error that weighs pairs unequally;
/// this is the geometric error the threshold is stated in. Returns `pose` when no step
/// lowers the cost.
pub(crate) fn refine(pose: Se3, pairs: &[(DVec3, DVec3)], inliers: &[usize]) -> Se3 {
    if inliers.len() < 8 {
        return pose;
    }
    let cost = |r: &DMat3, t: DVec3| -> f64 {
        inliers
            .iter()
            .map(|&i| plane_residual(r, t, pairs[i].0, pairs[i].1).map_or(1.0, |x| x * x))
            .sum()
    };
    let apply = |r: &DMat3, t: DVec3, d: &[f64; 5]| -> (DMat3, DVec3) {
        let w = DVec3::new(d[0], d[1], d[2]);
        let dr = if w.length() > 0.0 {
            DMat3::from_axis_angle(w.normalize(), w.length())
        } else {
            DMat3::IDENTITY
        };
        let (b1, b2) = t.any_orthonormal_pair();
        ((dr * *r), (t + b1 * d[3] + b2 * d[4]).normalize())
    };
    let (mut r, mut t) = (pose.rotation_matrix(), pose.translation.normalize());
    let mut current = cost(&r, t);
    let h = 1e-7;
    for _ in 0..10 {
        let mut jtj = SMatrix::<f64, 5, 5>::zeros();
        let mut jtr = SMatrix::<f64, 5, 1>::zeros();
        for &i in inliers {
            let (a, b) = pairs[i];
            let Some(r0) = plane_residual(&r, t, a, b) else {
                continue;
            };
            let mut j = SMatrix::<f64, 5, 1>::zeros();
            for k in 0..5 {
                let mut d = [0.0; 5];
                d[k] = h;
                let (rk, tk) = apply(&r, t, &d);
                j[k] = plane_residual(&rk, tk, a, b).map_or(0.0, |x| (x - r0) / h);
            }
            jtj += j * j.transpose();
            jtr += j * r0;
        }
        let Some(step) = jtj.cholesky().map(|c| c.solve(&(-jtr))) else {
            break;
        };
        let d = [step[0], step[1], step[2], step[3], step[4]];
        let (r1, t1) = apply(&r, t, &d);
        let c1 = cost(&r1, t1);
        if !(c1 < current) {
            break;
        }
        let done = current - c1 < 1e-12 * current.max(1e-30);
        (r, t, current) = (r1, t1, c1);
        if done {
            break;
        }
    }
    let q = glam::DQuat::from_mat3(&r).normalize();
    if q.is_finite() && t.is_finite() {
        Se3::new(q, t)
    } else {
        pose
    }
}

/// An essential matrix and the indices of its inliers.
pub(crate) struct EssentialFit {
    /// `E` with `b^T E a = 0` for pairs `(a, b)` (a in the first frame, b in the second).
    pub(crate) essential: DMat3,
    /// Inlier indices into the pairs.
    pub(crate) inliers: Vec<usize>,
}

/// The sine of the larger of the two angles between a bearing and the epipolar plane of its
/// match (both unit vectors); infinite where a plane is undefined.
pub(crate) fn epipolar_angle(e: &DMat3, a: DVec3, b: DVec3) -> f64 {
    let n2 = *e * a;
    let n1 = e.transpose() * b;
    let (l2, l1) = (n2.length(), n1.length());
    if l2 < 1e-12 || l1 < 1e-12 {
        return f64::INFINITY;
    }
    (b.dot(n2).abs() / l2).max(a.dot(n1).abs() / l1)
}

/// Least-squares essential matrix (8 or more pairs) projected onto the essential manifold
/// (two equal singular values, one zero).
pub(crate) fn eight_point(pairs: &[(DVec3, DVec3)], idx: &[usize]) -> Option<DMat3> {
    if idx.len() < 8 {
        return None;
    }
    let mut ata = SMatrix::<f64, 9, 9>::zeros();
    for &i in idx {
        let (a, b) = pairs[i];
        let row = SMatrix::<f64, 9, 1>::from_row_slice(&[
            b.x * a.x,
            b.x * a.y,
            b.x * a.z,
            b.y * a.x,
            b.y * a.y,
            b.y * a.z,
            b.z * a.x,
            b.z * a.y,
            b.z * a.z,
        ]);
        ata += row * row.transpose();
    }
    let eig = SymmetricEigen::new(ata);
    let (k, _) = eig
        .eigenvalues
        .iter()
        .enumerate()
        .min_by(|x, y| x.1.total_cmp(y.1))?;
    let v = eig.eigenvectors.column(k);
    let m = Matrix3::new(v[0], v[1], v[2], v[3], v[4], v[5], v[6], v[7], v[8]);
    let svd = m.svd(true, true);
    let (u, vt) = (svd.u?, svd.v_t?);
    let e = u * Matrix3::from_diagonal(&nalgebra::Vector3::new(1.0, 1.0, 0.0)) * vt;
    let out = DMat3::from_cols_array(&[
        e[(0, 0)],
        e[(1, 0)],
        e[(2, 0)],
        e[(0, 1)],
        e[(1, 1)],
        e[(2, 1)],
        e[(0, 2)],
        e[(1, 2)],
        e[(2, 2)],
    ]);
    out.is_finite().then_some(out)
}

/// RANSAC over 8-point samples with a least-squares refit on the inliers; `None` with fewer
/// than 8 pairs or when no sample gives an essential matrix.
pub(crate) fn ransac_essential(
    pairs: &[(DVec3, DVec3)],
    iterations: usize,
    threshold: f64,
    seed: u64,
) -> Option<EssentialFit> {
    let n = pairs.len();
    if n < 8 {
        return None;
    }
    let sin_t = threshold.sin();
    let inliers_of = |e: &DMat3| -> Vec<usize> {
        (0..n)
            .filter(|&i| epipolar_angle(e, pairs[i].0, pairs[i].1) < sin_t)
            .collect()
    };
    let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
    let mut best: Option<EssentialFit> = None;
    let mut sample = Vec::with_capacity(8);
    for _ in 0..iterations {
        sample.clear();
        while sample.len() < 8 {
            let i = rng.random_range(0..n);
            if !sample.contains(&i) {
                sample.push(i);
            }
        }
        let Some(e) = eight_point(pairs, &sample) else {
            continue;
        };
        let inl = inliers_of(&e);
        if best.as_ref().is_none_or(|b| inl.len() > b.inliers.len()) {
            best = Some(EssentialFit {
                essential: e,
                inliers: inl,
            });
        }
    }
    let mut best = best?;
    // Two refits: the inlier set of the least-squares fit can grow once.
    for _ in 0..2 {
        let Some(e) = eight_point(pairs, &best.inliers) else {
            break;
        };
        let inl = inliers_of(&e);
        if inl.len() < best.inliers.len() {
            break;
        }
        best = EssentialFit {
            essential: e,
            inliers: inl,
        };
    }
    Some(best)
}

/// Depths `(da, db)` with `db b = da R a + t` in the least-squares sense (midpoint
/// triangulation of two bearings); `None` for parallel rays.
pub(crate) fn triangulate_depths(r: &DMat3, t: DVec3, a: DVec3, b: DVec3) -> Option<(f64, f64)> {
    let ra = *r * a;
    // Normal equations of [ra, -b] [da, db]^T = -t.
    let (p, q, s) = (ra.dot(ra), -ra.dot(b), b.dot(b));
    let (y0, y1) = (-ra.dot(t), b.dot(t));
    let det = p * s - q * q;
    if det.abs() < 1e-12 {
        return None;
    }
    Some(((s * y0 - q * y1) / det, (p * y1 - q * y0) / det))
}

/// The relative pose `second_from_first` (unit translation) among the four decompositions of
/// `e` with most inliers triangulated in front of both cameras.
pub(crate) fn decompose(e: &DMat3, pairs: &[(DVec3, DVec3)], inliers: &[usize]) -> Option<Se3> {
    let m = Matrix3::from_fn(|r, c| e.col(c)[r]);
    let svd = m.svd(true, true);
    let (mut u, mut vt) = (svd.u?, svd.v_t?);
    if u.determinant() < 0.0 {
        u = -u;
    }
    if vt.determinant() < 0.0 {
        vt = -vt;
    }
    let w = Matrix3::new(0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0);
    let to_glam = |x: Matrix3<f64>| {
        DMat3::from_cols_array(&[
            x[(0, 0)],
            x[(1, 0)],
            x[(2, 0)],
            x[(0, 1)],
            x[(1, 1)],
            x[(2, 1)],
            x[(0, 2)],
            x[(1, 2)],
            x[(2, 2)],
        ])
    };
    let rots = [to_glam(u * w * vt), to_glam(u * w.transpose() * vt)];
    let t = DVec3::new(u[(0, 2)], u[(1, 2)], u[(2, 2)]);
    let mut best: Option<(usize, DMat3, DVec3)> = None;
    for r in rots {
        for tt in [t, -t] {
            let front = inliers
                .iter()
                .filter(|&&i| {
                    triangulate_depths(&r, tt, pairs[i].0, pairs[i].1)
                        .is_some_and(|(da, db)| da > 0.0 && db > 0.0)
                })
                .count();
            if best.as_ref().is_none_or(|b| front > b.0) {
                best = Some((front, r, tt));
            }
        }
    }
    let (_, r, t) = best?;
    let q = glam::DQuat::from_mat3(&r).normalize();
    q.is_finite().then(|| Se3::new(q, t))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scene_pairs(query_from_old: &Se3, n: usize, seed: u64) -> Vec<(DVec3, DVec3)> {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
        (0..n)
            .map(|_| {
                let p = DVec3::new(
                    rng.random_range(-4.0..4.0),
                    rng.random_range(-2.0..2.0),
                    rng.random_range(-4.0..4.0),
                );
                let q = query_from_old.transform_point(p);
                (p.normalize(), q.normalize())
            })
            .collect()
    }

    #[test]
    fn essential_ransac_recovers_the_relative_pose_among_outliers() {
        let truth = Se3::new(
            glam::DQuat::from_euler(glam::EulerRot::YXZ, 0.7, 0.1, -0.05),
            DVec3::new(0.6, 0.05, -0.3),
        );
        let mut pairs = scene_pairs(&truth, 120, 1);
        let mut rng = rand_pcg::Pcg64::seed_from_u64(2);
        // 40 % outliers: random second bearings.
        for p in pairs.iter_mut().take(48) {
            p.1 = DVec3::new(
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
            )
            .normalize();
        }
        let fit = ransac_essential(&pairs, 300, 0.005, 3).expect("a fit");
        assert!(
            fit.inliers.len() >= 70 && fit.inliers.iter().filter(|&&i| i < 48).count() <= 3,
            "inliers {}",
            fit.inliers.len()
        );
        let pose = decompose(&fit.essential, &pairs, &fit.inliers).expect("a pose");
        let dr = pose.rotation.angle_between(truth.rotation);
        let dt = pose
            .translation
            .angle_between(truth.translation.normalize());
        assert!(
            dr < 1e-3 && dt < 1e-2,
            "rotation {dr} rad, direction {dt} rad"
        );
        // Noise-free inliers: the geometric refinement lands on the exact pose.
        let refined = refine(pose, &pairs, &fit.inliers);
        let dr = refined.rotation.angle_between(truth.rotation);
        let dt = refined
            .translation
            .angle_between(truth.translation.normalize());
        assert!(
            dr < 1e-6 && dt < 1e-5,
            "refined: rotation {dr} rad, direction {dt} rad"
        );
    }

    #[test]
    fn random_bearings_do_not_verify() {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(5);
        let mut unit = || {
            DVec3::new(
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
            )
            .normalize()
        };
        let pairs: Vec<(DVec3, DVec3)> = (0..150).map(|_| (unit(), unit())).collect();
        let params = MonoLoopParams::default();
        let fit = ransac_essential(&pairs, 300, params.angular_threshold, 7).expect("a fit");
        assert!(
            fit.inliers.len() < params.min_inliers,
            "{} inliers of random pairs",
            fit.inliers.len()
        );
    }

    /// Two stretches of a walk seen by keyframes whose filter poses are in different units
    /// (the later stretch at half the scale of the earlier one): the loop similarity between
    /// them must have the ratio of the units as its scale (eq. 3.10), the true rotation and the
    /// translation in the candidate's units.
    #[test]
    fn loop_similarity_measures_the_ratio_of_the_keyframes_units() {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(11);
        let points: Vec<DVec3> = (0..150)
            .map(|_| {
                DVec3::new(
                    rng.random_range(-5.0..5.0),
                    rng.random_range(-1.5..1.5),
                    rng.random_range(-5.0..5.0),
                )
            })
            .collect();
        let descriptors: Vec<Descriptor> = (0..points.len())
            .map(|_| Descriptor([rng.random(), rng.random(), rng.random(), rng.random()]))
            .collect();
        let yaw = |a: f64| glam::DQuat::from_rotation_y(a);
        // True world_from_camera of six keyframes: three on the first pass, three on the
        // second pass near the same place (turned and shifted).
        let truth: Vec<Se3> = [
            (0.0, -1.0, 0.0),
            (0.1, -0.5, 0.05),
            (0.2, 0.0, 0.1),
            (0.3, -0.8, 0.4),
            (0.35, -0.3, 0.45),
            (0.4, 0.2, 0.5),
        ]
        .iter()
        .map(|&(a, x, z)| Se3::new(yaw(a), DVec3::new(x, 0.1, z)))
        .collect();
        // The filter: the first pass in metres, the second at half that (units of 2 m), in a
        // world shifted and turned by drift.
        let drift = Se3::new(yaw(0.05), DVec3::new(0.3, 0.0, -0.2));
        let filter: Vec<Se3> = truth
            .iter()
            .enumerate()
            .map(|(k, t)| {
                if k < 3 {
                    *t
                } else {
                    let d = drift * *t;
                    Se3::new(d.rotation, d.translation * 0.5)
                }
            })
            .collect();
        let camera = UnifiedCamera::catadioptric(200, 200);
        let vocabulary = Vocabulary::embedded_default().expect("vocabulary");
        let mut det =
            MonoLoopDetector::new(camera, vocabulary, MonoLoopParams::default()).expect("detector");
        for (k, (t, f)) in truth.iter().zip(&filter).enumerate() {
            let camera_from_world = t.inverse();
            let bearings: Vec<DVec3> = points
                .iter()
                .map(|p| camera_from_world.transform_point(*p).normalize())
                .collect();
            det.keyframes.push(MonoKeyframe {
                frame: k,
                timestamp: k as f64,
                world_from_camera: *f,
                keypoints: Vec::new(),
                descriptors: descriptors.clone(),
                bearings,
                bow: BowVector::default(),
            });
        }
        let (query, candidate) = (4, 1);
        let rel = truth[query].inverse() * truth[candidate];
        let check = CandidateCheck {
            keyframe: candidate,
            score: 1.0,
            normalised_score: 1.0,
            matches: points.len(),
            inliers: points.len(),
            query_from_candidate: Some(Se3::new(rel.rotation, rel.translation.normalize())),
            parallax_deg: 0.0,
        };
        let sim = det
            .loop_similarity(query, &check, &LoopScaleParams::default())
            .expect("a similarity");
        let truth_cq = truth[candidate].inverse() * truth[query];
        let z = sim.candidate_from_query;
        assert!((z.scale - 2.0).abs() < 1e-6, "scale {}", z.scale);
        // acos near 1 resolves angles to about 1e-8 rad.
        let dr = z.rotation.angle_between(truth_cq.rotation);
        assert!(dr < 1e-6, "rotation off by {dr} rad");
        assert!(
            (z.translation - truth_cq.translation).length() < 1e-6,
            "translation {} vs {}",
            z.translation,
            truth_cq.translation
        );
        assert!(sim.points >= 100, "{} points", sim.points);
    }

    #[test]
    fn keyframe_policy_is_validated() {
        let bad = KeyframePolicy {
            min_overlap: 0.0,
            ..KeyframePolicy::default()
        };
        assert!(KeyframeSelector::new(bad).is_err());
        let params = MonoLoopParams {
            min_inliers: 5,
            ..MonoLoopParams::default()
        };
        assert!(params.validate().is_err());
    }

    #[test]
    fn mask_excludes_rim_margin_and_blind_centre() {
        let cam = UnifiedCamera::catadioptric(200, 200);
        let mask = valid_mask(&cam, 10.0);
        let (cx, cy) = (cam.cx, cam.cy);
        let rim = cam.fov_radius.expect("rim");
        let inner = cam.inner_radius.expect("inner");
        assert_eq!(mask.at(cx.round() as usize, cy.round() as usize), 0.0);
        let at = |r: f64| mask.at((cx + r).round() as usize, cy.round() as usize);
        assert_eq!(at(inner + 5.0), 0.0);
        assert_eq!(at(inner + 12.0), 1.0);
        assert_eq!(at(rim - 12.0), 1.0);
        assert_eq!(at(rim - 5.0), 0.0);
    }
}
