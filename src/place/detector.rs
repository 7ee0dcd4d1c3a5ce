//! A loop detector over a stream of keyframes: ORB + BoW per keyframe, database query with
//! normalised scores, and geometric verification of the best candidates.

use super::database::{Candidate, KeyframeDatabase, QueryParams};
use super::orb::{extract_orb, OrbFeatures, OrbParams};
use super::verify::{verify_loop, LoopMatch, VerifyOutcome, VerifyParams};
use super::vocabulary::{BowVector, FeatureVector, Vocabulary};
use super::PlaceError;
use crate::camera::PinholeCamera;
use crate::image::ImageF32;

/// Parameters of [`LoopDetector`].
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LoopDetectorParams {
    /// ORB extraction. Default: corners spread over a grid of cells
    /// ([`OrbParams::distribute`]), as ORB-SLAM's place recognition: a keyframe's bag of words
    /// then describes the whole view, not only its most textured objects.
    pub orb: OrbParams,
    /// Database query.
    pub query: QueryParams,
    /// Geometric verification.
    pub verify: VerifyParams,
    /// Depth below the root of the direct-index nodes used for matching.
    pub direct_index_depth: usize,
    /// How many of the best candidates are verified geometrically.
    pub max_verified: usize,
}

impl Default for LoopDetectorParams {
    fn default() -> Self {
        Self {
            orb: OrbParams {
                distribute: true,
                ..OrbParams::default()
            },
            query: QueryParams::default(),
            verify: VerifyParams::default(),
            direct_index_depth: 2,
            max_verified: 3,
        }
    }
}

/// A keyframe's place-recognition description.
#[derive(Clone, Debug)]
pub struct KeyframeDescription {
    /// ORB features lifted to 3D.
    pub features: OrbFeatures,
    /// BoW histograms: one per mask (all features when no mask was given).
    pub bows: Vec<BowVector>,
    /// Direct index of all features.
    pub feature_vector: FeatureVector,
}

/// A verified loop.
#[derive(Clone, Debug, PartialEq)]
pub struct DetectedLoop {
    /// The query (newer) keyframe id.
    pub query_id: usize,
    /// The matched (older) keyframe id.
    pub candidate_id: usize,
    /// Database scores of the candidate.
    pub candidate: Candidate,
    /// Relative pose and inliers.
    pub loop_match: LoopMatch,
}

/// Keeps the vocabulary, database and keyframe descriptions; keyframe ids are `0, 1, 2, ...`
/// in insertion order.
pub struct LoopDetector {
    vocabulary: Vocabulary,
    database: KeyframeDatabase,
    keyframes: Vec<KeyframeDescription>,
    /// Parameters (may be changed between keyframes).
    pub params: LoopDetectorParams,
}

impl LoopDetector {
    /// A detector with an empty database.
    pub fn new(vocabulary: Vocabulary, params: LoopDetectorParams) -> Self {
        let database = KeyframeDatabase::new(vocabulary.num_words(), vocabulary.scoring());
        Self {
            vocabulary,
            database,
            keyframes: Vec::new(),
            params,
        }
    }

    /// The vocabulary.
    pub fn vocabulary(&self) -> &Vocabulary {
        &self.vocabulary
    }

    /// Number of keyframes inserted.
    pub fn len(&self) -> usize {
        self.keyframes.len()
    }

    /// Bytes of heap memory of the database and the keyframe descriptions (keypoints,
    /// descriptors, 3D points, bags of words, direct index; the direct index's tree nodes
    /// counted as their entries), without the vocabulary (see [`Vocabulary::heap_bytes`]).
    pub(crate) fn database_bytes(&self) -> usize {
        fn bytes<T>(v: &Vec<T>) -> usize {
            v.capacity() * std::mem::size_of::<T>()
        }
        let description = |d: &KeyframeDescription| {
            let f = &d.features;
            bytes(&f.keypoints)
                + bytes(&f.descriptors)
                + bytes(&f.points)
                + bytes(&d.bows)
                + d.bows.iter().map(|b| bytes(&b.0)).sum::<usize>()
                + d.feature_vector
                    .values()
                    .map(|v| std::mem::size_of::<(u32, Vec<usize>)>() + bytes(v))
                    .sum::<usize>()
        };
        self.database.heap_bytes()
            + bytes(&self.keyframes)
            + self.keyframes.iter().map(description).sum::<usize>()
    }

    /// True when no keyframe was inserted.
    pub fn is_empty(&self) -> bool {
        self.keyframes.is_empty()
    }

    /// The description of keyframe `id`.
    pub fn keyframe(&self, id: usize) -> Option<&KeyframeDescription> {
        self.keyframes.get(id)
    }

    /// ORB (lifted with `inverse_depth`, 1/m) and BoW of one keyframe. Each mask (nonzero =
    /// usable) gives one histogram of the features inside it.
    pub fn describe(
        &self,
        intensity: &ImageF32,
        inverse_depth: &ImageF32,
        camera: &PinholeCamera,
        masks: &[&ImageF32],
    ) -> Result<KeyframeDescription, PlaceError> {
        let mut features = extract_orb(intensity, None, &self.params.orb)?;
        features.lift(inverse_depth, camera)?;
        let mut inside = Vec::with_capacity(masks.len());
        for m in masks {
            if m.width != intensity.width || m.height != intensity.height {
                return Err(PlaceError::SizeMismatch {
                    what: "mask",
                    got_w: m.width,
                    got_h: m.height,
                    want_w: intensity.width,
                    want_h: intensity.height,
                });
            }
            inside.push(keypoints_inside(&features, m));
        }
        Ok(self.describe_features(features, &inside))
    }

    /// The description of already extracted (and lifted) features: one BoW histogram of all
    /// features when `inside` is empty, else one per entry of `inside` (a flag per feature:
    /// inside that mask).
    pub fn describe_features(
        &self,
        features: OrbFeatures,
        inside: &[Vec<bool>],
    ) -> KeyframeDescription {
        let (bow, feature_vector) = self
            .vocabulary
            .transform(&features.descriptors, self.params.direct_index_depth);
        let mut bows = Vec::new();
        if inside.is_empty() {
            bows.push(bow);
        } else {
            for flags in inside {
                let subset: Vec<_> = features
                    .descriptors
                    .iter()
                    .zip(flags.iter())
                    .filter(|(_, &f)| f)
                    .map(|(d, _)| *d)
                    .collect();
                bows.push(
                    self.vocabulary
                        .transform(&subset, self.params.direct_index_depth)
                        .0,
                );
            }
        }
        KeyframeDescription {
            features,
            bows,
            feature_vector,
        }
    }

    /// Adds `desc` as the next keyframe without querying (e.g. keyframes of a loaded map).
    /// Returns its id.
    pub fn add(&mut self, desc: KeyframeDescription) -> Result<usize, PlaceError> {
        let id = self.keyframes.len();
        self.database.add(id, desc.bows.clone())?;
        self.keyframes.push(desc);
        Ok(id)
    }

    /// Relocalisation query: the verified keyframe among the `max_candidates` best-scoring
    /// ones (no separation or normalisation limits) with most inliers, if any. The database
    /// is not changed; `query_id` of the answer is the number of keyframes.
    pub fn relocalise(
        &self,
        desc: &KeyframeDescription,
        max_candidates: usize,
    ) -> Result<Option<DetectedLoop>, PlaceError> {
        let id = self.keyframes.len();
        let params = QueryParams {
            max_results: max_candidates,
            min_separation: 0,
            min_normalised_score: 0.0,
            min_reference_score: 0.0,
        };
        let candidates = self.database.query(id, &desc.bows, 1.0, &params);
        self.best_verified(id, desc, candidates)
    }

    /// Verifies `candidates` against `desc` (query id `id`); the accepted one with most
    /// inliers.
    fn best_verified(
        &self,
        id: usize,
        desc: &KeyframeDescription,
        candidates: Vec<Candidate>,
    ) -> Result<Option<DetectedLoop>, PlaceError> {
        let mut found: Option<DetectedLoop> = None;
        for c in candidates {
            let old = &self.keyframes[c.keyframe_id];
            let outcome = verify_loop(
                &desc.features,
                &old.features,
                Some((&desc.feature_vector, &old.feature_vector)),
                &self.params.verify,
            )?;
            if let VerifyOutcome::Accepted(m) = outcome {
                if found
                    .as_ref()
                    .is_none_or(|f| m.inliers.len() > f.loop_match.inliers.len())
                {
                    found = Some(DetectedLoop {
                        query_id: id,
                        candidate_id: c.keyframe_id,
                        candidate: c,
                        loop_match: m,
                    });
                }
            }
        }
        Ok(found)
    }

    /// Queries the database with `desc`, verifies the best candidates, then inserts `desc`
    /// as the next keyframe. Returns its id and the verified loop with most inliers, if any.
    pub fn insert(
        &mut self,
        desc: KeyframeDescription,
    ) -> Result<(usize, Option<DetectedLoop>), PlaceError> {
        let id = self.keyframes.len();
        let mut found: Option<DetectedLoop> = None;
        if id > 0 {
            let reference = self.database.score_against(&desc.bows, id - 1)?;
            let candidates = self
                .database
                .query(id, &desc.bows, reference, &self.params.query);
            let mut candidates = candidates;
            candidates.truncate(self.params.max_verified);
            found = self.best_verified(id, &desc, candidates)?;
        }
        self.database.add(id, desc.bows.clone())?;
        self.keyframes.push(desc);
        Ok((id, found))
    }
}

/// One flag per keypoint of `features`: its nearest pixel of `mask` is nonzero.
pub fn keypoints_inside(features: &OrbFeatures, mask: &ImageF32) -> Vec<bool> {
    features
        .keypoints
        .iter()
        .map(|k| {
            let (x, y) = k.nearest_pixel(mask.width, mask.height);
            mask.at(x, y) > 0.0
        })
        .collect()
}
