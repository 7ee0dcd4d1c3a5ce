//! Keyframe database with an inverted index (word -> keyframe histograms containing it).
//!
//! A keyframe may hold several BoW histograms (e.g. from entropy masks at different
//! thresholds, thesis ch. 5); its similarity to a query is the best over all pairs of query
//! and keyframe histograms. Scores are normalised by the score between the query and its
//! previous keyframe (thesis 6.4.5, as DBoW2's `eta`), and keyframes closer in time than a
//! minimum separation are never returned.

use super::vocabulary::{BowVector, Scoring};
use super::PlaceError;

/// Query parameters.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct QueryParams {
    /// Most candidates returned.
    pub max_results: usize,
    /// Keyframes with `|id - query_id| < min_separation` are skipped.
    pub min_separation: usize,
    /// Smallest normalised score `s(q, c) / s(q, q_prev)` of a candidate.
    pub min_normalised_score: f64,
    /// If the reference score `s(q, q_prev)` is below this, the query returns nothing (the
    /// normalisation would be meaningless).
    pub min_reference_score: f64,
}

impl Default for QueryParams {
    fn default() -> Self {
        Self {
            max_results: 5,
            min_separation: 30,
            min_normalised_score: 0.3,
            min_reference_score: 0.005,
        }
    }
}

/// A database answer.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Candidate {
    /// The keyframe id it was added with.
    pub keyframe_id: usize,
    /// Raw similarity in `[0, 1]`.
    pub score: f64,
    /// Score divided by the query's reference score.
    pub normalised_score: f64,
}

/// Inverted-index database of keyframe BoW histograms.
#[derive(Clone, Debug)]
pub struct KeyframeDatabase {
    scoring: Scoring,
    /// word -> (entry, value) of the histograms containing it.
    inverted: Vec<Vec<(u32, f64)>>,
    /// entry -> keyframe id.
    entry_keyframe: Vec<usize>,
    /// keyframe id -> its histograms (for direct scoring against its previous one).
    histograms: std::collections::HashMap<usize, Vec<BowVector>>,
}

impl KeyframeDatabase {
    /// Bytes of heap memory the database holds: the inverted index, the entry table and the
    /// stored histograms (the hash map counted at its capacity times its entry size).
    pub(crate) fn heap_bytes(&self) -> usize {
        fn bytes<T>(v: &Vec<T>) -> usize {
            v.capacity() * std::mem::size_of::<T>()
        }
        bytes(&self.inverted)
            + self.inverted.iter().map(bytes).sum::<usize>()
            + bytes(&self.entry_keyframe)
            + self.histograms.capacity() * std::mem::size_of::<(usize, Vec<BowVector>)>()
            + self
                .histograms
                .values()
                .map(|h| bytes(h) + h.iter().map(|b| bytes(&b.0)).sum::<usize>())
                .sum::<usize>()
    }

    /// An empty database for a vocabulary of `num_words` words scored with `scoring`.
    pub fn new(num_words: usize, scoring: Scoring) -> Self {
        Self {
            scoring,
            inverted: vec![Vec::new(); num_words],
            entry_keyframe: Vec::new(),
            histograms: Default::default(),
        }
    }

    /// Number of keyframes stored.
    pub fn len(&self) -> usize {
        self.histograms.len()
    }

    /// True when empty.
    pub fn is_empty(&self) -> bool {
        self.histograms.is_empty()
    }

    /// Adds a keyframe with one or more histograms. Words outside the vocabulary are an error.
    pub fn add(&mut self, keyframe_id: usize, bows: Vec<BowVector>) -> Result<(), PlaceError> {
        for b in &bows {
            if let Some(&(w, _)) = b.0.iter().find(|(w, _)| *w as usize >= self.inverted.len()) {
                return Err(PlaceError::InvalidParameter {
                    name: "bow",
                    why: format!(
                        "word {w} outside a vocabulary of {} words",
                        self.inverted.len()
                    ),
                });
            }
        }
        for b in &bows {
            let entry = self.entry_keyframe.len() as u32;
            self.entry_keyframe.push(keyframe_id);
            for &(w, v) in &b.0 {
                self.inverted[w as usize].push((entry, v));
            }
        }
        self.histograms.entry(keyframe_id).or_default().extend(bows);
        Ok(())
    }

    /// Best similarity between any of `bows` and any histogram of keyframe `keyframe_id`.
    pub fn score_against(&self, bows: &[BowVector], keyframe_id: usize) -> Result<f64, PlaceError> {
        let hs = self
            .histograms
            .get(&keyframe_id)
            .ok_or(PlaceError::UnknownKeyframe(keyframe_id))?;
        let mut best: f64 = 0.0;
        for q in bows {
            for h in hs {
                best = best.max(super::vocabulary::score_bow(self.scoring, q, h));
            }
        }
        Ok(best)
    }

    /// Candidates for query keyframe `query_id` with histograms `bows`. `reference_score` is
    /// the score between the query and its previous keyframe (see [`Self::score_against`]).
    /// Sorted by score, best first.
    pub fn query(
        &self,
        query_id: usize,
        bows: &[BowVector],
        reference_score: f64,
        params: &QueryParams,
    ) -> Vec<Candidate> {
        if reference_score.is_nan()
            || reference_score < params.min_reference_score
            || self.entry_keyframe.is_empty()
        {
            return Vec::new();
        }
        let mut best_per_entry = vec![0.0f64; self.entry_keyframe.len()];
        let mut acc = vec![0.0f64; self.entry_keyframe.len()];
        for q in bows {
            acc.iter_mut().for_each(|a| *a = 0.0);
            for &(w, qv) in &q.0 {
                let Some(list) = self.inverted.get(w as usize) else {
                    continue;
                };
                for &(e, ev) in list {
                    acc[e as usize] += match self.scoring {
                        Scoring::L1 => qv.abs() + ev.abs() - (qv - ev).abs(),
                        Scoring::L2 => qv * ev,
                    };
                }
            }
            for (b, &a) in best_per_entry.iter_mut().zip(acc.iter()) {
                let s = match self.scoring {
                    Scoring::L1 => 0.5 * a,
                    Scoring::L2 => {
                        if a >= 1.0 {
                            1.0
                        } else if a <= 0.0 {
                            0.0
                        } else {
                            1.0 - (1.0 - a).sqrt()
                        }
                    }
                };
                *b = b.max(s);
            }
        }
        let mut per_kf: std::collections::HashMap<usize, f64> = Default::default();
        for (e, &s) in best_per_entry.iter().enumerate() {
            let kf = self.entry_keyframe[e];
            if kf.abs_diff(query_id) < params.min_separation || s <= 0.0 {
                continue;
            }
            let v = per_kf.entry(kf).or_insert(0.0);
            *v = v.max(s);
        }
        let mut out: Vec<Candidate> = per_kf
            .into_iter()
            .map(|(keyframe_id, score)| Candidate {
                keyframe_id,
                score,
                normalised_score: score / reference_score,
            })
            .filter(|c| c.normalised_score >= params.min_normalised_score)
            .collect();
        out.sort_by(|a, b| {
            b.score
                .total_cmp(&a.score)
                .then(a.keyframe_id.cmp(&b.keyframe_id))
        });
        out.truncate(params.max_results);
        out
    }
}
