//! Geometric verification of a loop candidate (thesis 6.4.5): descriptor matches between two
//! keyframes whose keypoints both have depth become 3D-3D pairs; 3-point RANSAC with Horn's
//! method finds the rigid motion; the loop is accepted with at least `min_inliers` inliers
//! whose convex hull covers at least `min_hull_fraction` of the image in both keyframes.

use glam::DVec2;

use super::matching::{match_descriptors, match_with_vocabulary, DescriptorMatch, MatchParams};
use super::orb::OrbFeatures;
use super::ransac::{ransac_rigid, RansacParams};
use super::vocabulary::FeatureVector;
use super::PlaceError;
use crate::geometry::Se3;

/// Verification parameters.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct VerifyParams {
    /// Descriptor matching.
    pub matching: MatchParams,
    /// RANSAC.
    pub ransac: RansacParams,
    /// Fewest inliers of an accepted loop.
    pub min_inliers: usize,
    /// Smallest convex-hull area of the inlier keypoints, as a fraction of the image area.
    pub min_hull_fraction: f64,
}

impl Default for VerifyParams {
    fn default() -> Self {
        Self {
            matching: MatchParams::default(),
            ransac: RansacParams::default(),
            min_inliers: 10,
            min_hull_fraction: 0.05,
        }
    }
}

/// An accepted loop: the relative pose and the inlier correspondences, ready for dense
/// refinement.
#[derive(Clone, Debug, PartialEq)]
pub struct LoopMatch {
    /// Transform from the candidate (old) keyframe's camera frame to the query's:
    /// `p_query = query_from_candidate * p_candidate`.
    pub query_from_candidate: Se3,
    /// Inlier pairs `(query keypoint index, candidate keypoint index)`.
    pub inliers: Vec<(usize, usize)>,
    /// Descriptor matches with depth on both sides (RANSAC input size).
    pub matches_3d: usize,
    /// Smaller of the two inlier convex-hull areas, as a fraction of the image area.
    pub hull_fraction: f64,
    /// RMS 3D residual of the inliers, metres.
    pub rms_residual: f64,
}

/// One inlier correspondence in pixels: `(query (x, y), candidate (x, y))`, level-0 pixel
/// coordinates of the two keypoints in their own keyframe images (integers are pixel centres).
pub type PixelMatch = ([f32; 2], [f32; 2]);

impl LoopMatch {
    /// The inlier pairs as level-0 pixel coordinates of the keypoints in `query` and
    /// `candidate`, the features this match was verified on (same order as
    /// [`LoopMatch::inliers`]). An index outside the features (they are not the verified ones)
    /// is an error.
    pub fn inlier_pixels(
        &self,
        query: &OrbFeatures,
        candidate: &OrbFeatures,
    ) -> Result<Vec<PixelMatch>, PlaceError> {
        let uv = |f: &OrbFeatures, i: usize, which: &'static str| {
            f.keypoints
                .get(i)
                .map(|k| [k.uv.x as f32, k.uv.y as f32])
                .ok_or_else(|| PlaceError::InvalidParameter {
                    name: which,
                    why: format!(
                        "inlier keypoint {i} of {} features: not the verified features",
                        f.keypoints.len()
                    ),
                })
        };
        self.inliers
            .iter()
            .map(|&(q, c)| Ok((uv(query, q, "query")?, uv(candidate, c, "candidate")?)))
            .collect()
    }
}

/// Why a candidate was rejected.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Rejection {
    /// Too few descriptor matches with depth on both sides for RANSAC.
    TooFewMatches,
    /// RANSAC found fewer than the required inliers.
    TooFewInliers,
    /// The inliers cover too small an area of the image.
    HullTooSmall,
}

/// Outcome of [`verify_loop`].
#[derive(Clone, Debug, PartialEq)]
pub enum VerifyOutcome {
    /// The loop passed every test.
    Accepted(LoopMatch),
    /// The loop failed; the best inlier count reached, for diagnostics.
    Rejected {
        /// The test it failed.
        reason: Rejection,
        /// Inliers (or 3D matches, when RANSAC did not run).
        inliers: usize,
    },
}

/// Area of the convex hull of `points` (pixels^2); Andrew's monotone chain + shoelace.
pub fn convex_hull_area(points: &[DVec2]) -> f64 {
    let mut p: Vec<DVec2> = points.iter().copied().filter(|q| q.is_finite()).collect();
    if p.len() < 3 {
        return 0.0;
    }
    p.sort_by(|a, b| a.x.total_cmp(&b.x).then(a.y.total_cmp(&b.y)));
    p.dedup();
    let cross = |o: DVec2, a: DVec2, b: DVec2| (a - o).perp_dot(b - o);
    let mut hull: Vec<DVec2> = Vec::with_capacity(2 * p.len());
    for &q in p.iter() {
        while hull.len() >= 2 && cross(hull[hull.len() - 2], hull[hull.len() - 1], q) <= 0.0 {
            hull.pop();
        }
        hull.push(q);
    }
    let lower = hull.len() + 1;
    for &q in p.iter().rev().skip(1) {
        while hull.len() >= lower && cross(hull[hull.len() - 2], hull[hull.len() - 1], q) <= 0.0 {
            hull.pop();
        }
        hull.push(q);
    }
    hull.pop();
    let n = hull.len();
    if n < 3 {
        return 0.0;
    }
    0.5 * (0..n)
        .map(|i| hull[i].perp_dot(hull[(i + 1) % n]))
        .sum::<f64>()
        .abs()
}

/// Verifies `candidate` against `query`. Both must be lifted ([`OrbFeatures::lift`]). With
/// feature vectors (`Some((query_fv, candidate_fv))`) matching is restricted to shared
/// vocabulary nodes; otherwise it is brute force.
pub fn verify_loop(
    query: &OrbFeatures,
    candidate: &OrbFeatures,
    feature_vectors: Option<(&FeatureVector, &FeatureVector)>,
    params: &VerifyParams,
) -> Result<VerifyOutcome, PlaceError> {
    for f in [query, candidate] {
        if f.points.len() != f.keypoints.len() {
            return Err(PlaceError::InvalidParameter {
                name: "features",
                why: "keyframe features must be lifted to 3D before verification".into(),
            });
        }
    }
    let matches: Vec<DescriptorMatch> = match feature_vectors {
        Some((qf, cf)) => match_with_vocabulary(
            &query.descriptors,
            qf,
            &candidate.descriptors,
            cf,
            &params.matching,
        ),
        None => match_descriptors(&query.descriptors, &candidate.descriptors, &params.matching),
    };
    let mut pairs = Vec::new();
    let (mut pa, mut pb) = (Vec::new(), Vec::new());
    for m in &matches {
        if let (Some(a), Some(b)) = (query.points[m.query], candidate.points[m.train]) {
            pairs.push((m.query, m.train));
            pa.push(a);
            pb.push(b);
        }
    }
    let needed = params.min_inliers.max(3);
    if pairs.len() < needed {
        return Ok(VerifyOutcome::Rejected {
            reason: Rejection::TooFewMatches,
            inliers: pairs.len(),
        });
    }
    let r = match ransac_rigid(&pa, &pb, &params.ransac) {
        Ok(r) => r,
        Err(PlaceError::Degenerate(_)) => {
            return Ok(VerifyOutcome::Rejected {
                reason: Rejection::TooFewInliers,
                inliers: 0,
            });
        }
        Err(e) => return Err(e),
    };
    if r.inliers.len() < params.min_inliers {
        return Ok(VerifyOutcome::Rejected {
            reason: Rejection::TooFewInliers,
            inliers: r.inliers.len(),
        });
    }
    let hull_q = convex_hull_area(
        &r.inliers
            .iter()
            .map(|&i| query.keypoints[pairs[i].0].uv)
            .collect::<Vec<_>>(),
    );
    let hull_c = convex_hull_area(
        &r.inliers
            .iter()
            .map(|&i| candidate.keypoints[pairs[i].1].uv)
            .collect::<Vec<_>>(),
    );
    let area_q = (query.width * query.height).max(1) as f64;
    let area_c = (candidate.width * candidate.height).max(1) as f64;
    let hull_fraction = (hull_q / area_q).min(hull_c / area_c);
    if hull_fraction < params.min_hull_fraction {
        return Ok(VerifyOutcome::Rejected {
            reason: Rejection::HullTooSmall,
            inliers: r.inliers.len(),
        });
    }
    let rms = (r
        .inliers
        .iter()
        .map(|&i| (pa[i] - r.a_from_b.transform_point(pb[i])).length_squared())
        .sum::<f64>()
        / r.inliers.len() as f64)
        .sqrt();
    Ok(VerifyOutcome::Accepted(LoopMatch {
        query_from_candidate: r.a_from_b,
        inliers: r.inliers.iter().map(|&i| pairs[i]).collect(),
        matches_3d: pairs.len(),
        hull_fraction,
        rms_residual: rms,
    }))
}

#[cfg(test)]
mod tests {
    use glam::{DQuat, DVec3};
    use rand::{Rng, SeedableRng};

    use super::*;
    use crate::place::orb::{Descriptor, KeyPoint};

    fn keypoint(x: f64, y: f64) -> KeyPoint {
        KeyPoint {
            uv: DVec2::new(x, y),
            level: 0,
            angle: 0.0,
            score: 10.0,
            size: 31.0,
        }
    }

    /// A verified loop's inlier pixels are the keypoints of the same physical points in the
    /// two keyframes: the candidate's features are the query's, shuffled, moved by a rigid
    /// motion and placed at other pixels, so a swapped or shifted index shows.
    #[test]
    fn inlier_pixels_are_the_keypoints_of_the_verified_pairs() {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(7);
        let n: u64 = 40;
        let (w, h) = (160, 120);
        let query_from_candidate = Se3::new(
            DQuat::from_axis_angle(DVec3::Y, 0.2),
            DVec3::new(0.1, -0.05, 0.2),
        );
        let mut query = OrbFeatures {
            keypoints: Vec::new(),
            descriptors: Vec::new(),
            points: Vec::new(),
            width: w,
            height: h,
        };
        let mut in_candidate = Vec::new();
        for i in 0..n {
            query.keypoints.push(keypoint(
                rng.random_range(0.0..w as f64),
                rng.random_range(0.0..h as f64),
            ));
            query
                .descriptors
                .push(Descriptor([rng.random(), rng.random(), rng.random(), i]));
            let p = DVec3::new(
                rng.random_range(-1.0..1.0),
                rng.random_range(-0.7..0.7),
                rng.random_range(1.5..4.0),
            );
            query.points.push(Some(p));
            // Candidate pixel of feature i: any pixel, different from the query's.
            in_candidate.push((
                i as usize,
                keypoint(
                    rng.random_range(0.0..w as f64),
                    rng.random_range(0.0..h as f64),
                ),
                query_from_candidate.inverse().transform_point(p),
            ));
        }
        // Shuffle the candidate's feature order.
        for i in (1..in_candidate.len()).rev() {
            let j = rng.random_range(0..=i);
            in_candidate.swap(i, j);
        }
        let candidate = OrbFeatures {
            keypoints: in_candidate.iter().map(|c| c.1).collect(),
            descriptors: in_candidate
                .iter()
                .map(|c| query.descriptors[c.0])
                .collect(),
            points: in_candidate.iter().map(|c| Some(c.2)).collect(),
            width: w,
            height: h,
        };
        let m = match verify_loop(&query, &candidate, None, &VerifyParams::default()) {
            Ok(VerifyOutcome::Accepted(m)) => m,
            other => panic!("expected an accepted loop, got {other:?}"),
        };
        assert_eq!(m.inliers.len(), n as usize);
        let pixels = m.inlier_pixels(&query, &candidate).expect("pixels");
        assert_eq!(pixels.len(), m.inliers.len());
        for (&(q, c), &(pq, pc)) in m.inliers.iter().zip(&pixels) {
            let feature = in_candidate[c].0;
            assert_eq!(feature, q, "candidate feature {c} is not query feature {q}");
            let kq = query.keypoints[feature].uv;
            assert_eq!(pq, [kq.x as f32, kq.y as f32]);
            let kc = in_candidate[c].1.uv;
            assert_eq!(pc, [kc.x as f32, kc.y as f32]);
        }
        // Features that were not verified: an error, not a panic.
        let fewer = OrbFeatures {
            keypoints: query.keypoints[..3].to_vec(),
            ..query.clone()
        };
        assert!(m.inlier_pixels(&fewer, &candidate).is_err());
    }
}
