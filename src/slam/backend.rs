//! The back-end (CPU, its own thread): per keyframe segmentation and masks, ORB + BoW,
//! loop detection and verification, dense loop refinement, keyframe pose graph.

use std::sync::{Arc, Mutex};
use std::time::Instant;

use super::events::{EventHub, KeyframeDescribed, SlamEvent, SuperjutLabels};
use super::keyframe::{Keyframe, KeyframeLink};
use super::memory::{keyframe_bytes, vec_bytes, MemoryAccount, MemoryBreakdown};
use super::{information_from, SlamConfig, SlamError};
use crate::camera::PinholeCamera;
use crate::geometry::{Covariance6, Se3};
use crate::gpu::ComputeBackend;
use crate::graph::{PoseGraph3, SolverOptions};
use crate::image::{ImageF32, RgbdFrame};
use crate::odometry::Odometry;
use crate::place::detector::keypoints_inside;
use crate::place::{KeyframeDescription, LoopDetector, PixelMatch, Vocabulary};
use crate::segment::Segmenter;

/// A loop the back-end found (accepted or rejected after verification).
#[derive(Clone, Debug)]
pub struct LoopRecord {
    /// Query keyframe id (the newer one).
    pub query: usize,
    /// Matched keyframe id (the older one).
    pub candidate: usize,
    /// RANSAC inliers of the verification.
    pub inliers: usize,
    /// The inlier correspondences of the verification, one per inlier: level-0 pixel
    /// coordinates `(x, y)` of the keypoint in the query image and of its match in the
    /// candidate keyframe's image (integers are pixel centres). The query image is keyframe
    /// `query`'s, or for relocalisation the frame that was relocalised. Empty when the record
    /// does not carry them (e.g. read back from a loops file).
    pub matches: Vec<PixelMatch>,
    /// `candidate_from_query` after dense refinement (the RANSAC pose if rejected before it).
    pub candidate_from_query: Se3,
    /// Translation change of the dense refinement over the RANSAC pose, metres.
    pub refine_translation: f64,
    /// Rotation change of the dense refinement, radians.
    pub refine_rotation: f64,
    /// Dense covisibility of the two keyframes at the refined pose.
    pub covisibility: f64,
    /// Whether it became a graph edge (for relocalisation: the frame's pose), and if not, why.
    pub verdict: LoopVerdict,
    /// True when it came from relocalisation rather than loop detection.
    pub relocalisation: bool,
}

/// What the back-end decided about a loop candidate that passed the geometric verification.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum LoopVerdict {
    /// It became a graph edge (for relocalisation: the frame's pose).
    Accepted,
    /// Rejected: the dense covisibility of the two images at the refined pose is below
    /// `SlamConfig::loop_min_covisibility`.
    LowCovisibility {
        /// The covisibility (fraction of pixels, 0-1).
        covisibility: f64,
    },
    /// Rejected: the dense refinement moved the RANSAC pose by more than
    /// `SlamConfig::loop_max_refine_translation` or `SlamConfig::loop_max_refine_rotation`.
    RefinementMoved {
        /// Translation change, metres.
        translation: f64,
        /// Rotation change, radians.
        rotation: f64,
    },
}

impl LoopVerdict {
    /// Whether the loop was accepted.
    pub fn is_accepted(&self) -> bool {
        matches!(self, LoopVerdict::Accepted)
    }

    /// Why it was rejected, in words (empty when accepted), as the loops file writes it.
    pub fn reason(&self) -> String {
        match self {
            LoopVerdict::Accepted => String::new(),
            LoopVerdict::LowCovisibility { covisibility } => {
                format!("covisibility {covisibility:.2}")
            }
            LoopVerdict::RefinementMoved {
                translation,
                rotation,
            } => format!("dense refinement moved {translation:.3} m / {rotation:.3} rad"),
        }
    }
}

/// `accepted`, or the reason of the rejection.
impl std::fmt::Display for LoopVerdict {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            LoopVerdict::Accepted => f.write_str("accepted"),
            _ => f.write_str(&self.reason()),
        }
    }
}

/// Back-end cost of one keyframe, milliseconds (table 6.3).
#[derive(Clone, Copy, Debug, Default)]
pub struct KeyframeTiming {
    /// Keyframe id.
    pub id: usize,
    /// Superjut segmentation and masks.
    pub segment_ms: f64,
    /// ORB extraction and BoW.
    pub describe_ms: f64,
    /// Database query and geometric verification.
    pub query_ms: f64,
    /// Dense refinement of a loop (0 without loop).
    pub align_ms: f64,
    /// Pose-graph optimisation triggered at this keyframe (0 if none).
    pub optimise_ms: f64,
    /// Everything for this keyframe.
    pub total_ms: f64,
}

/// What the back-end shares with the front-end while running.
#[derive(Debug, Default)]
pub(crate) struct Shared {
    /// `world_from_frontworld` of the newest keyframe: maps front-end poses to corrected ones.
    pub correction: Se3,
    pub keyframes: usize,
    pub loops: usize,
    pub optimisations: usize,
    /// Every loop record so far (accepted and rejected), in the order they were found.
    pub loop_records: Vec<LoopRecord>,
    /// The instance's memory account (both threads' parts and the peak).
    pub memory: MemoryAccount,
}

/// Bytes of loop records.
pub(crate) fn loop_record_bytes(records: &Vec<LoopRecord>) -> usize {
    vec_bytes(records) + records.iter().map(|r| vec_bytes(&r.matches)).sum::<usize>()
}

/// Answer to a relocalisation request.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Relocalisation {
    pub keyframe: usize,
    pub keyframe_from_frame: Se3,
    pub covariance: Option<Covariance6>,
    /// `world_from_keyframe` as the front-end knows it (front-end world).
    pub frontworld_from_keyframe: Se3,
}

/// A keyframe's description, its per-mask feature flags, the segmentation and description
/// times (ms), and the superjut labels with each superjut's neg-entropy (with masks).
type Described = (
    KeyframeDescription,
    Vec<Vec<bool>>,
    f64,
    f64,
    Option<(SuperjutLabels, Vec<f64>)>,
);
/// A refined loop: `candidate_from_query`, its covariance and the dense covisibility.
type Refined = (Se3, Option<Covariance6>, f64);

pub(crate) struct Backend {
    pub camera: PinholeCamera,
    pub config: SlamConfig,
    pub keyframes: Vec<Keyframe>,
    /// Per keyframe: flags of its features for each mask (for the map file).
    pub mask_flags: Vec<Vec<Vec<bool>>>,
    pub detector: LoopDetector,
    pub graph: PoseGraph3,
    odometry: Odometry,
    /// Open loop cluster: ids of its first and last query keyframes.
    cluster: Option<(usize, usize)>,
    pub timings: Vec<KeyframeTiming>,
    pub shared: Arc<Mutex<Shared>>,
    /// Keyframes before this id come from a loaded map (fixed in the graph).
    pub map_keyframes: usize,
    /// Superjut segmentation and the buffers it keeps between keyframes.
    pub segmenter: Segmenter,
    /// Bytes of the vocabulary (it does not change).
    vocabulary_bytes: usize,
    /// The event stream (shared with the front-end and the receivers).
    events: Arc<EventHub>,
}

fn mask_image(m: &crate::segment::Mask) -> ImageF32 {
    ImageF32 {
        width: m.width,
        height: m.height,
        data: m.data.iter().map(|&v| f32::from(v)).collect(),
    }
}

impl Backend {
    pub fn new(
        camera: PinholeCamera,
        config: SlamConfig,
        backend: &ComputeBackend,
        vocabulary: Vocabulary,
        shared: Arc<Mutex<Shared>>,
        events: Arc<EventHub>,
    ) -> Result<Self, SlamError> {
        let mut ocfg = config.odometry.clone();
        ocfg.reference_switch = None;
        ocfg.constant_velocity = false;
        let odometry = Odometry::new(ocfg, camera, backend)?;
        let vocabulary_bytes = vocabulary.heap_bytes();
        Ok(Backend {
            camera,
            detector: LoopDetector::new(vocabulary, config.detector.clone()),
            config,
            keyframes: Vec::new(),
            mask_flags: Vec::new(),
            graph: PoseGraph3::new(),
            odometry,
            cluster: None,
            timings: Vec::new(),
            shared,
            map_keyframes: 0,
            segmenter: Segmenter::new(),
            vocabulary_bytes,
            events,
        })
    }

    /// The back-end's parts of the instance's memory account (sums of capacities; allocates
    /// nothing).
    pub fn memory_parts(&self) -> MemoryBreakdown {
        let (odometry, gpu) = self.odometry.memory_bytes();
        let flags = vec_bytes(&self.mask_flags)
            + self
                .mask_flags
                .iter()
                .map(|k| vec_bytes(k) + k.iter().map(vec_bytes).sum::<usize>())
                .sum::<usize>();
        MemoryBreakdown {
            keyframes: vec_bytes(&self.keyframes)
                + self.keyframes.iter().map(keyframe_bytes).sum::<usize>(),
            place_recognition: self.vocabulary_bytes + self.detector.database_bytes() + flags,
            pose_graph: self.graph.heap_bytes(),
            segmenter: self.segmenter.scratch_bytes(),
            odometry,
            records: vec_bytes(&self.timings),
            gpu,
            ..MemoryBreakdown::default()
        }
    }

    /// Enters [`Self::memory_parts`] in the account shared with the front-end.
    pub fn note_memory(&self) {
        let parts = self.memory_parts();
        self.shared
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .memory
            .set_backend(parts);
    }

    /// Masks (as images) of a keyframe: empty without masks, else the full image first and
    /// one per threshold; with them the superjut labels and neg-entropies.
    #[allow(clippy::type_complexity)]
    fn masks(
        &mut self,
        frame: &RgbdFrame,
    ) -> Result<(Vec<ImageF32>, Option<(SuperjutLabels, Vec<f64>)>), SlamError> {
        if !self.config.masks {
            return Ok((Vec::new(), None));
        }
        let sj = self.segmenter.segment_keyframe(
            &frame.intensity,
            &frame.inverse_depth,
            &self.camera,
            &self.config.segment,
        )?;
        let mut out = vec![ImageF32::filled(frame.width(), frame.height(), 1.0)];
        for m in sj.masks(&self.config.mask_thresholds) {
            out.push(mask_image(&m));
        }
        let neg_entropy = sj.segments.iter().map(|s| s.neg_entropy).collect();
        let labels = SuperjutLabels {
            width: sj.width,
            height: sj.height,
            labels: sj.labels,
        };
        Ok((out, Some((labels, neg_entropy))))
    }

    pub fn describe(&mut self, frame: &RgbdFrame) -> Result<Described, SlamError> {
        let t = Instant::now();
        let (masks, superjuts) = self.masks(frame)?;
        let segment_ms = t.elapsed().as_secs_f64() * 1e3;
        let t = Instant::now();
        let refs: Vec<&ImageF32> = masks.iter().collect();
        let desc =
            self.detector
                .describe(&frame.intensity, &frame.inverse_depth, &self.camera, &refs)?;
        let flags = masks
            .iter()
            .map(|m| keypoints_inside(&desc.features, m))
            .collect();
        Ok((
            desc,
            flags,
            segment_ms,
            t.elapsed().as_secs_f64() * 1e3,
            superjuts,
        ))
    }

    /// Dense refinement of `candidate_from_query_guess` between keyframe `candidate` and
    /// `query`: `(candidate_from_query, covariance, covisibility)`.
    fn refine(
        &mut self,
        candidate: usize,
        query: &RgbdFrame,
        candidate_from_query_guess: Se3,
    ) -> Result<Refined, SlamError> {
        // Each pyramid is built once, for the alignment and the covisibility.
        let reference = self.odometry.prepare(&self.keyframes[candidate].frame())?;
        let query = self.odometry.prepare(query)?;
        let a = self.odometry.align_prepared(
            &reference,
            &query,
            candidate_from_query_guess.inverse(),
        )?;
        let cov = self
            .odometry
            .covisibility_prepared(&reference, &query, &a.cur_from_ref)?;
        self.odometry.recycle(reference);
        self.odometry.recycle(query);
        Ok((a.cur_from_ref.inverse(), a.covariance, cov))
    }

    fn pose_of(&self, id: usize) -> Result<Se3, SlamError> {
        let idx = self
            .graph
            .index_of(id as i64)
            .ok_or_else(|| SlamError::Internal(format!("keyframe {id} not in the graph")))?;
        Ok(self.graph.poses[idx])
    }

    /// How far the dense refinement moved the RANSAC pose (metres, radians) and the verdict.
    fn check_refined(
        &self,
        guess: &Se3,
        refined: &Se3,
        covisibility: f64,
    ) -> (f64, f64, LoopVerdict) {
        let delta = guess.inverse() * *refined;
        let dt = delta.translation.length();
        let dr = delta.rotation.to_axis_angle().1.abs();
        let verdict = if covisibility < self.config.loop_min_covisibility {
            LoopVerdict::LowCovisibility { covisibility }
        } else if dt > self.config.loop_max_refine_translation
            || dr > self.config.loop_max_refine_rotation
        {
            LoopVerdict::RefinementMoved {
                translation: dt,
                rotation: dr,
            }
        } else {
            LoopVerdict::Accepted
        };
        (dt, dr, verdict)
    }

    /// Adds a keyframe of a loaded map (already described; its pose is final and fixed).
    pub fn add_map_keyframe(
        &mut self,
        kf: Keyframe,
        desc: KeyframeDescription,
        flags: Vec<Vec<bool>>,
        world_from_keyframe: Se3,
    ) -> Result<(), SlamError> {
        let id = self.detector.add(desc)?;
        if id != kf.id {
            return Err(SlamError::Internal(format!(
                "map keyframe {} loaded as {id}",
                kf.id
            )));
        }
        let idx = self.graph.add_vertex(id as i64, world_from_keyframe)?;
        self.graph.fixed[idx] = true;
        self.keyframes.push(kf);
        self.mask_flags.push(flags);
        self.map_keyframes = self.keyframes.len();
        Ok(())
    }

    /// Processes one keyframe from the front-end.
    pub fn process(&mut self, kf: Keyframe) -> Result<(), SlamError> {
        let t0 = Instant::now();
        let mut timing = KeyframeTiming {
            id: kf.id,
            ..Default::default()
        };
        if kf.id != self.keyframes.len() {
            return Err(SlamError::Internal(format!(
                "keyframe {} arrived, expected {}",
                kf.id,
                self.keyframes.len()
            )));
        }
        let frame = kf.frame();
        let (desc, flags, seg_ms, desc_ms, superjuts) = self.describe(&frame)?;
        timing.segment_ms = seg_ms;
        timing.describe_ms = desc_ms;
        if self.events.on() {
            let (labels, neg_entropy) = superjuts.unzip();
            self.events
                .push(SlamEvent::KeyframeDescribed(KeyframeDescribed {
                    id: kf.id,
                    labels,
                    neg_entropy: neg_entropy.unwrap_or_default(),
                    keypoints: desc.features.keypoints.clone(),
                    mask_flags: flags.clone(),
                    segment_ms: seg_ms,
                    describe_ms: desc_ms,
                }));
        }
        let t = Instant::now();
        let (id, detected) = self.detector.insert(desc)?;
        timing.query_ms = t.elapsed().as_secs_f64() * 1e3;
        if id != kf.id {
            return Err(SlamError::Internal(format!(
                "detector id {id} for keyframe {}",
                kf.id
            )));
        }
        // Vertex and its sequential / relocalisation edge.
        let (initial, edge) = match kf.link {
            KeyframeLink::First => (kf.world_from_keyframe, None),
            KeyframeLink::Odometry {
                from,
                from_from_this,
                covariance,
            }
            | KeyframeLink::Relocalised {
                from,
                from_from_this,
                covariance,
            } => (
                self.pose_of(from)? * from_from_this,
                Some((from, from_from_this, covariance)),
            ),
        };
        let idx = self.graph.add_vertex(id as i64, initial)?;
        if self.graph.poses.len() == 1 {
            self.graph.fixed[idx] = true;
        }
        if let Some((from, z, cov)) = edge {
            let info = information_from(Some(&cov), 0.01, 0.01);
            self.graph.add_edge(from as i64, id as i64, z, info)?;
        }
        let world_from_frontworld = initial * kf.world_from_keyframe.inverse();
        self.keyframes.push(kf);
        self.mask_flags.push(flags);

        // Loop: dense refinement seeded by the RANSAC pose.
        if let Some(d) = detected {
            let t = Instant::now();
            let guess = d.loop_match.query_from_candidate.inverse();
            let (refined, cov, covis) = self.refine(d.candidate_id, &frame, guess)?;
            timing.align_ms = t.elapsed().as_secs_f64() * 1e3;
            let (dt, dr, verdict) = self.check_refined(&guess, &refined, covis);
            let accepted = verdict.is_accepted();
            if accepted {
                let info = information_from(cov.as_ref(), 0.01, 0.01);
                self.graph
                    .add_edge(d.candidate_id as i64, id as i64, refined, info)?;
                self.cluster = Some(match self.cluster {
                    Some((first, _)) => (first, id),
                    None => (id, id),
                });
            }
            let matches = match (
                self.detector.keyframe(id),
                self.detector.keyframe(d.candidate_id),
            ) {
                (Some(q), Some(c)) => d.loop_match.inlier_pixels(&q.features, &c.features)?,
                _ => {
                    return Err(SlamError::Internal(format!(
                        "loop {id} -> {}: keyframe description missing",
                        d.candidate_id
                    )))
                }
            };
            self.record_loop(LoopRecord {
                query: id,
                candidate: d.candidate_id,
                inliers: d.loop_match.inliers.len(),
                matches,
                candidate_from_query: refined,
                refine_translation: dt,
                refine_rotation: dr,
                covisibility: covis,
                verdict,
                relocalisation: false,
            });
        }
        // Optimise when the loop cluster closes (no loop for `gap` keyframes), or when a long
        // revisit has kept it open for `2 gap` keyframes, so the map is corrected during it.
        if let Some((first, last)) = self.cluster {
            let gap = self.config.loop_cluster_gap;
            if id >= last + gap || id >= first + 2 * gap {
                timing.optimise_ms = self.optimise()?;
            }
        }
        let correction = match self.pose_of(id) {
            Ok(p) if timing.optimise_ms > 0.0 => {
                p * self.keyframes[id].world_from_keyframe.inverse()
            }
            _ => world_from_frontworld,
        };
        if let Ok(mut s) = self.shared.lock() {
            s.correction = correction;
            s.keyframes = self.keyframes.len();
            s.loops = s
                .loop_records
                .iter()
                .filter(|l| l.verdict.is_accepted())
                .count();
        }
        timing.total_ms = t0.elapsed().as_secs_f64() * 1e3;
        self.timings.push(timing);
        Ok(())
    }

    /// Keeps a loop record in the state shared with the front-end's caller (the only copy;
    /// a poisoned lock still takes it, so no record is lost), and sends it as an event.
    fn record_loop(&mut self, record: LoopRecord) {
        if self.events.on() {
            self.events.push(SlamEvent::LoopChecked(record.clone()));
        }
        self.shared
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .loop_records
            .push(record);
    }

    /// Optimises the keyframe graph (if a loop cluster is pending); returns milliseconds.
    pub fn optimise(&mut self) -> Result<f64, SlamError> {
        if self.cluster.take().is_none() {
            return Ok(0.0);
        }
        let t = Instant::now();
        let opts = SolverOptions {
            max_iterations: 50,
            ..Default::default()
        };
        self.graph.optimize(&opts)?;
        let mut loops = 0;
        if let Ok(mut s) = self.shared.lock() {
            s.optimisations += 1;
            loops = s
                .loop_records
                .iter()
                .filter(|l| l.verdict.is_accepted())
                .count();
        }
        let ms = t.elapsed().as_secs_f64() * 1e3;
        if self.events.on() {
            self.events.push(SlamEvent::GraphOptimised {
                world_from_keyframe: self.keyframe_poses(),
                loops,
                optimise_ms: ms,
            });
        }
        Ok(ms)
    }

    /// Relocalises `frame` against the keyframes: ORB + BoW query, verification, dense
    /// refinement. `None` when nothing verified.
    pub fn relocalise(&mut self, frame: &RgbdFrame) -> Result<Option<Relocalisation>, SlamError> {
        if self.keyframes.is_empty() {
            return Ok(None);
        }
        let (desc, ..) = self.describe(frame)?;
        let Some(d) = self.detector.relocalise(&desc, 5)? else {
            return Ok(None);
        };
        let guess = d.loop_match.query_from_candidate.inverse();
        let (refined, cov, covis) = self.refine(d.candidate_id, frame, guess)?;
        let (dt, dr, verdict) = self.check_refined(&guess, &refined, covis);
        let ok = verdict.is_accepted();
        let candidate = self.detector.keyframe(d.candidate_id).ok_or_else(|| {
            SlamError::Internal(format!(
                "relocalisation candidate {} has no description",
                d.candidate_id
            ))
        })?;
        let matches = d
            .loop_match
            .inlier_pixels(&desc.features, &candidate.features)?;
        self.record_loop(LoopRecord {
            query: self.keyframes.len(),
            candidate: d.candidate_id,
            inliers: d.loop_match.inliers.len(),
            matches,
            candidate_from_query: refined,
            refine_translation: dt,
            refine_rotation: dr,
            covisibility: covis,
            verdict,
            relocalisation: true,
        });
        if !ok {
            return Ok(None);
        }
        Ok(Some(Relocalisation {
            keyframe: d.candidate_id,
            keyframe_from_frame: refined,
            covariance: cov,
            frontworld_from_keyframe: self.keyframes[d.candidate_id].world_from_keyframe,
        }))
    }

    /// Optimised `world_from_keyframe` of every keyframe.
    pub fn keyframe_poses(&self) -> Vec<Se3> {
        self.keyframes
            .iter()
            .map(|k| self.pose_of(k.id).unwrap_or(k.world_from_keyframe))
            .collect()
    }
}
