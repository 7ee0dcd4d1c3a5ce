//! Descriptor matching: Hamming distance, Lowe's ratio test, mutual consistency, and matching
//! restricted to features that share a vocabulary node (the DBoW2 "direct index").

use rayon::prelude::*;

use super::orb::Descriptor;
use super::vocabulary::FeatureVector;

/// Hamming distance between two descriptors (0..=256).
#[inline]
pub fn hamming(a: &Descriptor, b: &Descriptor) -> u32 {
    a.distance(b)
}

/// Matching parameters.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MatchParams {
    /// Largest accepted Hamming distance (ORB-SLAM uses 50 for strict, 100 for loose).
    pub max_distance: u32,
    /// Lowe's ratio: accept when `best < ratio * second_best` (1.0 disables the test).
    pub ratio: f32,
    /// Keep only pairs that are each other's best match.
    pub mutual: bool,
}

impl Default for MatchParams {
    fn default() -> Self {
        Self {
            max_distance: 64,
            ratio: 0.8,
            mutual: true,
        }
    }
}

/// A match between descriptor `query` of the first set and `train` of the second.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct DescriptorMatch {
    /// Index in the first (query) set.
    pub query: usize,
    /// Index in the second (train) set.
    pub train: usize,
    /// Hamming distance.
    pub distance: u32,
}

/// Best and second-best distances and the best index of `d` among `candidates` of `set`.
#[inline]
fn best_two(
    d: &Descriptor,
    set: &[Descriptor],
    candidates: impl Iterator<Item = usize>,
) -> (usize, u32, u32) {
    let (mut bi, mut b1, mut b2) = (usize::MAX, u32::MAX, u32::MAX);
    for j in candidates {
        let dist = d.distance(&set[j]);
        if dist < b1 {
            b2 = b1;
            b1 = dist;
            bi = j;
        } else if dist < b2 {
            b2 = dist;
        }
    }
    (bi, b1, b2)
}

#[inline]
fn passes(b1: u32, b2: u32, p: &MatchParams) -> bool {
    b1 <= p.max_distance && (p.ratio >= 1.0 || b2 == u32::MAX || (b1 as f32) < p.ratio * b2 as f32)
}

/// Brute-force matching of `query` against `train` with the ratio test and, if asked, mutual
/// consistency. Each query descriptor gives at most one match; sorted by query index.
pub fn match_descriptors(
    query: &[Descriptor],
    train: &[Descriptor],
    params: &MatchParams,
) -> Vec<DescriptorMatch> {
    let forward: Vec<(usize, u32, u32)> = query
        .par_iter()
        .map(|d| best_two(d, train, 0..train.len()))
        .collect();
    let backward: Vec<usize> = if params.mutual {
        train
            .par_iter()
            .map(|d| best_two(d, query, 0..query.len()).0)
            .collect()
    } else {
        Vec::new()
    };
    forward
        .into_iter()
        .enumerate()
        .filter_map(|(i, (j, b1, b2))| {
            if j == usize::MAX || !passes(b1, b2, params) {
                return None;
            }
            if params.mutual && backward[j] != i {
                return None;
            }
            Some(DescriptorMatch {
                query: i,
                train: j,
                distance: b1,
            })
        })
        .collect()
}

/// Matching accelerated by the vocabulary's direct index: a query feature is compared only
/// with train features under the same vocabulary node. Ratio test and mutual consistency are
/// applied within those groups; each train feature is used at most once (the closest wins).
pub fn match_with_vocabulary(
    query: &[Descriptor],
    query_fv: &FeatureVector,
    train: &[Descriptor],
    train_fv: &FeatureVector,
    params: &MatchParams,
) -> Vec<DescriptorMatch> {
    let mut best_for_train: Vec<Option<DescriptorMatch>> = vec![None; train.len()];
    for (node, qidx) in query_fv.iter() {
        let Some(tidx) = train_fv.get(node) else {
            continue;
        };
        for &qi in qidx {
            let Some(qd) = query.get(qi) else { continue };
            let (tj, b1, b2) =
                best_two(qd, train, tidx.iter().copied().filter(|&t| t < train.len()));
            if tj == usize::MAX || !passes(b1, b2, params) {
                continue;
            }
            if params.mutual {
                let back = best_two(
                    &train[tj],
                    query,
                    qidx.iter().copied().filter(|&q| q < query.len()),
                )
                .0;
                if back != qi {
                    continue;
                }
            }
            let m = DescriptorMatch {
                query: qi,
                train: tj,
                distance: b1,
            };
            match &best_for_train[tj] {
                Some(prev) if prev.distance <= b1 => {}
                _ => best_for_train[tj] = Some(m),
            }
        }
    }
    let mut out: Vec<DescriptorMatch> = best_for_train.into_iter().flatten().collect();
    out.sort_by_key(|m| m.query);
    out
}
