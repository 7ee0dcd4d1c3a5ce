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
#[derive(Clone, Copy, Debug, PartialEq)]
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
