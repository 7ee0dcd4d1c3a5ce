//! The thesis' changed-environment experiments (ch. 5, figs. 5.6 and 5.10) on generated
//! sequences, where the moved-object masks of [`crate::synth`] are the ground truth.
//!
//! A scene is rendered along a loop in session 0 and in sessions `1..=S`, in which movable
//! objects were moved, removed or added. Two questions are answered:
//!
//! 1. **Separability** ([`ChangeReport::features`]): how well does each superjut feature
//!    (neg-entropy, planarity, horizontality, eigen-transform texture, size) separate the
//!    superjuts on changed objects from those on unchanged structure? Each is scored by the
//!    ROC AUC ([`roc_auc`]) of "higher value = static"; 0.5 is chance, values below 0.5 mean
//!    the feature is higher on changed objects.
//! 2. **Matching across sessions** ([`ChangeReport::matching`]): ORB features of frame `i` of
//!    session 0 matched against frame `i + offset` of session `k` (same trajectory, so the
//!    true relative pose is known), keeping only keypoints whose superjut has neg-entropy at
//!    least a threshold (in both frames; threshold `None` = no mask). Matches are verified by
//!    3-point RANSAC (as in loop closure); a verified match is *correct* when its 3D points
//!    agree under the true relative pose. Precision and recall of verified matches are
//!    reported per threshold, recall relative to the unmasked run.
//!    [`ChangeReport::cluttered_views`] repeats them over the pairs in which changed objects
//!    carry a large share of the unmasked matches (views of moved clutter, picked by the
//!    ground truth): the views where masking can matter, since over all pairs changed objects
//!    carry under 1 % of the matches in the generated scenes.
//!
//! Frames are in the camera frame of [`crate::source::SourceSpec::Synth`] (pinhole, x right,
//! y down, z forward); distances in metres.

use std::time::Instant;

use glam::DVec3;

use crate::camera::PinholeCamera;
use crate::gpu::ComputeBackend;
use crate::place::{
    extract_orb, match_descriptors, ransac_rigid, MatchParams, OrbFeatures, OrbParams, PlaceError,
    RansacParams,
};
use crate::segment::{SegmentConfig, SegmentError, Segmenter, Superjut, Superjuts};
use crate::source::{FrameSource, SourceError, SourceSpec};
use crate::synth::{SensorModel, SequenceFrame, SynthError};

/// Errors of the changed-environment experiments.
#[derive(Debug, thiserror::Error)]
pub enum ExperimentError {
    /// A parameter is out of range.
    #[error("invalid experiment parameter: {0}")]
    Invalid(String),
    /// The generated sequence could not be opened.
    #[error(transparent)]
    Source(#[from] SourceError),
    /// Rendering failed.
    #[error(transparent)]
    Synth(#[from] SynthError),
    /// Segmentation failed.
    #[error(transparent)]
    Segment(#[from] SegmentError),
    /// Feature extraction or RANSAC failed.
    #[error(transparent)]
    Place(#[from] PlaceError),
    /// Keyframe fusion failed.
    #[error(transparent)]
    Fusion(#[from] crate::slam::SlamError),
    /// TSDF integration or mesh extraction failed.
    #[error(transparent)]
    Tsdf(#[from] crate::tsdf::TsdfError),
}

/// Parameters of [`run_change_experiment`].
#[derive(Clone, Debug)]
pub struct ChangeExperimentConfig {
    /// Scene presets (see `rgbid synth --help`).
    pub scenes: Vec<String>,
    /// Scene seeds; every scene is run with every seed.
    pub seeds: Vec<u64>,
    /// Changed sessions `1..=sessions` compared with session 0 (>= 1).
    pub sessions: u32,
    /// Frames of one lap of the loop (30 fps).
    pub lap_frames: usize,
    /// Every `step`-th frame of the lap is used.
    pub step: usize,
    /// The session-`k` frame is `offset` frames after the session-0 frame (a small change of
    /// viewpoint, as when revisiting a place).
    pub offset: usize,
    /// Image width in pixels (height 3/4 of it).
    pub width: u32,
    /// The depth sensor model of the rendered frames: [`SensorModel::kinect`] by default;
    /// [`SensorModel::noiseless`] gives the limit of perfect depth.
    pub sensor: SensorModel,
    /// Fuse the inverse depth of the next `fuse` frames of the sequence (ground-truth poses,
    /// [`crate::slam::KeyframeFuser`] with its default parameters) into every frame before
    /// segmenting it, as the SLAM back-end segments keyframes fused from the frames that
    /// follow them (0 = the single raw frame). Frames past the end of the lap are not used.
    pub fuse: usize,
    /// A superjut is "changed" when at least this fraction of its pixels is in the moved-object
    /// mask of its frame.
    pub changed_fraction: f64,
    /// A superjut is "static" when at most this fraction of its pixels is in the mask
    /// (superjuts in between are left out of the separability statistics).
    pub static_fraction: f64,
    /// Neg-entropy thresholds of the masks in the matching experiment (`None` = unmasked,
    /// always run first).
    pub thresholds: Vec<f64>,
    /// A verified match is correct when its two 3D points are closer than this (m) under the
    /// true relative pose, plus `correct_per_metre` per metre of depth.
    pub correct_tolerance: f64,
    /// Growth of the tolerance with depth (m per m).
    pub correct_per_metre: f64,
    /// Segmentation parameters.
    pub segment: SegmentConfig,
    /// ORB parameters.
    pub orb: OrbParams,
    /// Descriptor matching parameters.
    pub matching: MatchParams,
    /// RANSAC parameters.
    pub ransac: RansacParams,
}

impl Default for ChangeExperimentConfig {
    fn default() -> Self {
        Self {
            scenes: vec!["office".into(), "kitchen".into(), "lab".into()],
            seeds: vec![1, 2],
            sessions: 2,
            lap_frames: 300,
            step: 20,
            offset: 4,
            width: 320,
            sensor: SensorModel::kinect(),
            fuse: 0,
            changed_fraction: 0.5,
            static_fraction: 0.05,
            thresholds: vec![0.3, 0.5, 0.6, 0.7, 0.8, 0.9],
            correct_tolerance: 0.03,
            correct_per_metre: 0.01,
            segment: SegmentConfig::default(),
            orb: OrbParams::default(),
            matching: MatchParams::default(),
            ransac: RansacParams::default(),
        }
    }
}

impl ChangeExperimentConfig {
    /// Checks the parameters.
    pub fn validate(&self) -> Result<(), ExperimentError> {
        let bad = |s: &str| Err(ExperimentError::Invalid(s.into()));
        check_capture(
            &self.scenes,
            &self.seeds,
            self.sessions,
            self.step,
            self.lap_frames,
            self.offset,
        )?;
        if !(0.0..=1.0).contains(&self.static_fraction)
            || !(0.0..=1.0).contains(&self.changed_fraction)
            || self.static_fraction >= self.changed_fraction
        {
            return bad("need 0 <= static_fraction < changed_fraction <= 1");
        }
        if self.thresholds.iter().any(|t| !t.is_finite()) {
            return bad("thresholds must be finite");
        }
        self.segment.validate()?;
        Ok(())
    }
}

/// The checks both changed-scene experiments make of their captures: scenes and seeds given,
/// at least one changed session, a frame step of at least 1 and pairs inside the lap.
pub(crate) fn check_capture(
    scenes: &[String],
    seeds: &[u64],
    sessions: u32,
    step: usize,
    lap_frames: usize,
    offset: usize,
) -> Result<(), ExperimentError> {
    let bad = |s: &str| Err(ExperimentError::Invalid(s.into()));
    if scenes.is_empty() || seeds.is_empty() {
        return bad("at least one scene and one seed are needed");
    }
    if sessions == 0 {
        return bad("sessions must be >= 1 (session 0 is the reference)");
    }
    if step == 0 || lap_frames <= offset {
        return bad("step must be >= 1 and lap_frames > offset");
    }
    Ok(())
}

/// ROC AUC of one superjut feature (higher value taken to mean "static").
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct FeatureAuc {
    /// Feature name (`neg_entropy`, `planarity`, `horizontality`, `texture`, `size`).
    pub feature: &'static str,
    /// Probability that a random static superjut has a higher value than a random changed one
    /// (ties count one half); 0.5 = chance.
    pub auc: f64,
}

/// Matching results for one mask threshold, summed over all frame pairs.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct MatchingRow {
    /// Neg-entropy threshold of the mask (`None` = no mask).
    pub threshold: Option<f64>,
    /// Fraction of keypoints kept by the mask (mean over frames).
    pub kept_keypoints: f64,
    /// Descriptor matches (ratio test + mutual).
    pub matches: usize,
    /// Matches whose session-`k` keypoint lies on a changed object (ground-truth mask).
    pub matches_on_changed: usize,
    /// Matches accepted by RANSAC.
    pub verified: usize,
    /// Verified matches that are correct under the true relative pose.
    pub correct: usize,
    /// RANSAC inlier ratio `verified / matches`.
    pub inlier_ratio: f64,
    /// `correct / verified`.
    pub precision: f64,
    /// `correct` relative to the unmasked run's `correct`.
    pub recall: f64,
    /// Frame pairs whose RANSAC pose is within 5 cm and 3 degrees of the truth.
    pub pairs_pose_ok: usize,
}

/// Shares of the unmasked matches on changed objects that select the frame pairs of
/// [`ChangeReport::cluttered_views`].
pub const CLUTTER_SHARES: [f64; 3] = [0.05, 0.1, 0.2];

/// Matching restricted to the frame pairs whose unmasked matches lie on changed objects for
/// at least `min_changed_share` of them (recall relative to those pairs' unmasked run).
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct ClutteredViews {
    /// Minimum share (0-1) of a pair's unmasked matches whose session-`k` keypoint lies on a
    /// changed object.
    pub min_changed_share: f64,
    /// Frame pairs selected.
    pub pairs: usize,
    /// One row per threshold, the unmasked one first, summed over the selected pairs.
    pub matching: Vec<MatchingRow>,
}

/// Everything [`run_change_experiment`] measured.
#[derive(Clone, Debug, serde::Serialize)]
pub struct ChangeReport {
    /// Superjuts labelled changed / static.
    pub changed_superjuts: usize,
    /// See above.
    pub static_superjuts: usize,
    /// Separability per feature.
    pub features: Vec<FeatureAuc>,
    /// Frame pairs compared.
    pub pairs: usize,
    /// Pairs in which the session-`k` frame sees changed objects at all.
    pub pairs_with_changes: usize,
    /// One row per threshold, the unmasked one first.
    pub matching: Vec<MatchingRow>,
    /// The same rows over the frame pairs in which changed objects carry at least a given
    /// share of the unmasked matches (views of moved clutter), one entry per share in
    /// [`CLUTTER_SHARES`].
    pub cluttered_views: Vec<ClutteredViews>,
    /// Median segmentation time per frame, ms.
    pub segment_ms: f64,
    /// Median ORB extraction time per frame, ms.
    pub orb_ms: f64,
}

/// ROC AUC (Mann-Whitney U / (n_p n_n)) of scores where `positive` should score higher than
/// `negative`; ties count one half. `NaN` when either set is empty.
pub fn roc_auc(positive: &[f64], negative: &[f64]) -> f64 {
    if positive.is_empty() || negative.is_empty() {
        return f64::NAN;
    }
    // Rank all scores together (average ranks for ties).
    let mut all: Vec<(f64, bool)> = positive
        .iter()
        .map(|&v| (v, true))
        .chain(negative.iter().map(|&v| (v, false)))
        .collect();
    all.sort_by(|a, b| a.0.total_cmp(&b.0));
    let mut rank_sum_pos = 0.0;
    let mut i = 0;
    while i < all.len() {
        let mut j = i;
        while j + 1 < all.len() && all[j + 1].0 == all[i].0 {
            j += 1;
        }
        let avg_rank = (i + j) as f64 / 2.0 + 1.0;
        rank_sum_pos += avg_rank * all[i..=j].iter().filter(|e| e.1).count() as f64;
        i = j + 1;
    }
    let np = positive.len() as f64;
    let nn = negative.len() as f64;
    (rank_sum_pos - np * (np + 1.0) / 2.0) / (np * nn)
}

const FEATURES: [&str; 5] = [
    "neg_entropy",
    "planarity",
    "horizontality",
    "texture",
    "size",
];

fn feature_values(s: &Superjut) -> [f64; 5] {
    [
        s.neg_entropy,
        s.planarity,
        s.horizontality,
        s.texture,
        s.size as f64,
    ]
}

/// A rendered, segmented and described frame.
pub(crate) struct Prepared {
    pub(crate) frame: SequenceFrame,
    /// The frame's superjuts (`None` when its segments came from elsewhere, e.g. a mesh).
    pub(crate) juts: Option<Superjuts>,
    pub(crate) features: OrbFeatures,
    /// Neg-entropy of each keypoint's superjut (`-inf` where it has none).
    pub(crate) keypoint_neg_entropy: Vec<f64>,
}

/// How verified matches are found and judged (shared with the mesh experiment).
#[derive(Clone, Copy)]
pub(crate) struct Verify<'a> {
    pub(crate) matching: &'a MatchParams,
    pub(crate) ransac: &'a RansacParams,
    /// Metres, plus `correct_per_metre` per metre of depth.
    pub(crate) correct_tolerance: f64,
    pub(crate) correct_per_metre: f64,
}

impl ChangeExperimentConfig {
    fn verify(&self) -> Verify<'_> {
        Verify {
            matching: &self.matching,
            ransac: &self.ransac,
            correct_tolerance: self.correct_tolerance,
            correct_per_metre: self.correct_per_metre,
        }
    }
}

fn prepare(
    source: &mut FrameSource,
    index: usize,
    camera: &PinholeCamera,
    config: &ChangeExperimentConfig,
    fuser: Option<&mut crate::slam::KeyframeFuser>,
    segmenter: &mut Segmenter,
    times: &mut (Vec<f64>, Vec<f64>),
) -> Result<Prepared, ExperimentError> {
    let FrameSource::Synth(seq, _) = source else {
        return Err(ExperimentError::Invalid(
            "the experiment needs a generated sequence".into(),
        ));
    };
    let mut frame = seq.render_frame(index)?;
    if let Some(fuser) = fuser {
        fuser.start(&frame.frame.inverse_depth)?;
        for j in index + 1..(index + 1 + config.fuse).min(seq.len()) {
            let next = seq.render_frame(j)?;
            let cur_from_kf = next.world_from_camera.inverse() * frame.world_from_camera;
            // Generated frames have no odometry scale: the fixed tolerance (sigma_W = 0).
            fuser.fuse(&next.frame.inverse_depth, &cur_from_kf, 0.0)?;
        }
        frame.frame.inverse_depth = fuser.finish()?.0;
    }
    let t = Instant::now();
    let juts = segmenter.segment_keyframe(
        &frame.frame.intensity,
        &frame.frame.inverse_depth,
        camera,
        &config.segment,
    )?;
    times.0.push(t.elapsed().as_secs_f64() * 1e3);
    let t = Instant::now();
    let mut features = extract_orb(&frame.frame.intensity, None, &config.orb)?;
    features.lift(&frame.frame.inverse_depth, camera)?;
    times.1.push(t.elapsed().as_secs_f64() * 1e3);
    let w = juts.width;
    let keypoint_neg_entropy = features
        .keypoints
        .iter()
        .map(|k| {
            let (x, y) = k.nearest_pixel(w, juts.height);
            juts.segments
                .get(juts.labels[y * w + x] as usize)
                .map_or(f64::NEG_INFINITY, |s| s.neg_entropy)
        })
        .collect();
    Ok(Prepared {
        frame,
        juts: Some(juts),
        features,
        keypoint_neg_entropy,
    })
}

/// Adds the separability samples of a changed-session frame to `changed` / `unchanged`.
fn label_superjuts(
    p: &Prepared,
    config: &ChangeExperimentConfig,
    changed: &mut Vec<[f64; 5]>,
    unchanged: &mut Vec<[f64; 5]>,
) {
    let (Some(mask), Some(juts)) = (&p.frame.frame.moved_mask, &p.juts) else {
        return;
    };
    let n = juts.segments.len();
    let mut total = vec![0usize; n];
    let mut moved = vec![0usize; n];
    for (l, m) in juts.labels.iter().zip(mask) {
        if let Some(t) = total.get_mut(*l as usize) {
            *t += 1;
            moved[*l as usize] += usize::from(*m);
        }
    }
    for (s, (t, m)) in juts.segments.iter().zip(total.iter().zip(&moved)) {
        if *t == 0 {
            continue;
        }
        let f = *m as f64 / *t as f64;
        if f >= config.changed_fraction {
            changed.push(feature_values(s));
        } else if f <= config.static_fraction {
            unchanged.push(feature_values(s));
        }
    }
}

#[derive(Default, Clone)]
pub(crate) struct RowAcc {
    kept: f64,
    frames: usize,
    matches: usize,
    on_changed: usize,
    verified: usize,
    correct: usize,
    pose_ok: usize,
}

impl RowAcc {
    pub(crate) fn add(&mut self, o: &RowAcc) {
        self.kept += o.kept;
        self.frames += o.frames;
        self.matches += o.matches;
        self.on_changed += o.on_changed;
        self.verified += o.verified;
        self.correct += o.correct;
        self.pose_ok += o.pose_ok;
    }
}

/// The matching rows of summed accumulators (one per threshold, the unmasked one first);
/// recall is relative to the first row's correct matches.
pub(crate) fn matching_rows(thresholds: &[Option<f64>], rows: &[RowAcc]) -> Vec<MatchingRow> {
    let base_correct = rows.first().map_or(1, |r| r.correct.max(1)) as f64;
    thresholds
        .iter()
        .zip(rows)
        .map(|(t, a)| MatchingRow {
            threshold: *t,
            kept_keypoints: a.kept / a.frames.max(1) as f64,
            matches: a.matches,
            matches_on_changed: a.on_changed,
            verified: a.verified,
            correct: a.correct,
            inlier_ratio: a.verified as f64 / a.matches.max(1) as f64,
            precision: a.correct as f64 / a.verified.max(1) as f64,
            recall: a.correct as f64 / base_correct,
            pairs_pose_ok: a.pose_ok,
        })
        .collect()
}

/// The matching rows over all pairs and over the cluttered views ([`CLUTTER_SHARES`]) of
/// per-pair accumulators (one per threshold, the unmasked one first).
pub(crate) fn summarise(
    thresholds: &[Option<f64>],
    per_pair: &[Vec<RowAcc>],
) -> (Vec<MatchingRow>, Vec<ClutteredViews>) {
    // Rows summed over the pairs whose unmasked run (index 0) passes `keep`.
    let summed = |keep: &dyn Fn(&RowAcc) -> bool| {
        let mut sum = vec![RowAcc::default(); thresholds.len()];
        let mut n = 0;
        for pair in per_pair.iter().filter(|p| p.first().is_some_and(keep)) {
            n += 1;
            for (t, one) in sum.iter_mut().zip(pair) {
                t.add(one);
            }
        }
        (n, matching_rows(thresholds, &sum))
    };
    let matching = summed(&|_| true).1;
    let cluttered_views = CLUTTER_SHARES
        .iter()
        .map(|&share| {
            let (pairs, matching) = summed(&|u: &RowAcc| {
                u.matches > 0 && u.on_changed as f64 >= share * u.matches as f64
            });
            ClutteredViews {
                min_changed_share: share,
                pairs,
                matching,
            }
        })
        .collect();
    (matching, cluttered_views)
}

/// Matches a session-0 frame `a` against a session-`k` frame `b` with keypoints restricted to
/// superjuts of neg-entropy `>= threshold` (all keypoints for `None`).
pub(crate) fn match_pair(
    a: &Prepared,
    b: &Prepared,
    threshold: Option<f64>,
    config: Verify<'_>,
    acc: &mut RowAcc,
) -> Result<(), ExperimentError> {
    let keep = |p: &Prepared| -> Vec<usize> {
        (0..p.features.len())
            .filter(|&i| {
                p.features.points.get(i).is_some_and(|q| q.is_some())
                    && threshold.is_none_or(|t| p.keypoint_neg_entropy[i] >= t)
            })
            .collect()
    };
    let (ka, kb) = (keep(a), keep(b));
    let lifted = |p: &Prepared| p.features.points.iter().filter(|q| q.is_some()).count();
    for (p, k) in [(a, &ka), (b, &kb)] {
        acc.kept += k.len() as f64 / lifted(p).max(1) as f64;
        acc.frames += 1;
    }
    let da: Vec<_> = ka.iter().map(|&i| a.features.descriptors[i]).collect();
    let db: Vec<_> = kb.iter().map(|&i| b.features.descriptors[i]).collect();
    let matches = match_descriptors(&da, &db, config.matching);
    acc.matches += matches.len();
    let (w, h) = (b.frame.frame.width(), b.frame.frame.height());
    let point = |p: &Prepared, i: usize| p.features.points[i].unwrap_or(DVec3::ZERO);
    let mut pa = Vec::with_capacity(matches.len());
    let mut pb = Vec::with_capacity(matches.len());
    for m in &matches {
        let (ia, ib) = (ka[m.query], kb[m.train]);
        pa.push(point(a, ia));
        pb.push(point(b, ib));
        if let Some(mask) = &b.frame.frame.moved_mask {
            let (x, y) = b.features.keypoints[ib].nearest_pixel(w, h);
            acc.on_changed += usize::from(mask[y * w + x]);
        }
    }
    if matches.len() < 3 {
        return Ok(());
    }
    let Ok(r) = ransac_rigid(&pa, &pb, config.ransac) else {
        return Ok(()); // degenerate sample sets verify nothing
    };
    let a_from_b_true = a.frame.world_from_camera.inverse() * b.frame.world_from_camera;
    acc.verified += r.inliers.len();
    acc.correct += r
        .inliers
        .iter()
        .filter(|&&i| {
            let d = (pa[i] - a_from_b_true.transform_point(pb[i])).length();
            d < config.correct_tolerance + config.correct_per_metre * pa[i].z
        })
        .count();
    let err = a_from_b_true.inverse() * r.a_from_b;
    let angle = crate::geometry::so3_log(err.rotation).length();
    if err.translation.length() < 0.05 && angle < 3f64.to_radians() {
        acc.pose_ok += 1;
    }
    Ok(())
}

pub(crate) fn median(v: &mut [f64]) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

/// Runs both experiments (see the module docs). `progress` is called with
/// `(pairs done, pairs in all)`. Rendering runs on `backend`.
pub fn run_change_experiment(
    config: &ChangeExperimentConfig,
    backend: &ComputeBackend,
    mut progress: impl FnMut(usize, usize),
) -> Result<ChangeReport, ExperimentError> {
    config.validate()?;
    let indices: Vec<usize> = (0..config.lap_frames - config.offset)
        .step_by(config.step)
        .collect();
    let total = config.scenes.len() * config.seeds.len() * config.sessions as usize * indices.len();
    let mut thresholds: Vec<Option<f64>> = vec![None];
    thresholds.extend(config.thresholds.iter().map(|&t| Some(t)));
    let mut per_pair: Vec<Vec<RowAcc>> = Vec::new();
    let (mut changed, mut unchanged) = (Vec::new(), Vec::new());
    let mut times = (Vec::new(), Vec::new());
    let (mut pairs, mut pairs_with_changes) = (0, 0);
    // One segmenter (and its buffers) for every frame.
    let mut segmenter = Segmenter::new();
    for scene in &config.scenes {
        for &seed in &config.seeds {
            let spec = |session: u32| SourceSpec::Synth {
                spec: format!("{scene}:loop"),
                frames: config.lap_frames,
                width: config.width,
                seed,
                session,
                lap_seconds: None,
            };
            let sensor = Some(config.sensor.clone());
            let mut reference = FrameSource::open_with_sensor(&spec(0), backend, sensor.clone())?;
            let camera = reference.camera();
            // One fuser (and, on a GPU, one set of pipelines) for all frames of the scene.
            let mut fuser = (config.fuse > 0)
                .then(|| {
                    crate::slam::KeyframeFuser::new(
                        camera,
                        crate::slam::FusionParams::default(),
                        backend,
                    )
                })
                .transpose()?;
            let refs = indices
                .iter()
                .map(|&i| {
                    prepare(
                        &mut reference,
                        i,
                        &camera,
                        config,
                        fuser.as_mut(),
                        &mut segmenter,
                        &mut times,
                    )
                })
                .collect::<Result<Vec<_>, _>>()?;
            for session in 1..=config.sessions {
                let mut source =
                    FrameSource::open_with_sensor(&spec(session), backend, sensor.clone())?;
                for (a, &i) in refs.iter().zip(&indices) {
                    let b = prepare(
                        &mut source,
                        i + config.offset,
                        &camera,
                        config,
                        fuser.as_mut(),
                        &mut segmenter,
                        &mut times,
                    )?;
                    label_superjuts(&b, config, &mut changed, &mut unchanged);
                    if b.frame
                        .frame
                        .moved_mask
                        .as_ref()
                        .is_some_and(|m| m.contains(&true))
                    {
                        pairs_with_changes += 1;
                    }
                    let mut this_pair = vec![RowAcc::default(); thresholds.len()];
                    for (t, acc) in thresholds.iter().zip(this_pair.iter_mut()) {
                        match_pair(a, &b, *t, config.verify(), acc)?;
                    }
                    per_pair.push(this_pair);
                    pairs += 1;
                    progress(pairs, total);
                }
            }
        }
    }
    let features = FEATURES
        .iter()
        .enumerate()
        .map(|(k, &feature)| {
            let s: Vec<f64> = unchanged.iter().map(|v: &[f64; 5]| v[k]).collect();
            let c: Vec<f64> = changed.iter().map(|v: &[f64; 5]| v[k]).collect();
            FeatureAuc {
                feature,
                auc: roc_auc(&s, &c),
            }
        })
        .collect();
    let (matching, cluttered_views) = summarise(&thresholds, &per_pair);
    Ok(ChangeReport {
        changed_superjuts: changed.len(),
        static_superjuts: unchanged.len(),
        features,
        pairs,
        pairs_with_changes,
        matching,
        cluttered_views,
        segment_ms: median(&mut times.0),
        orb_ms: median(&mut times.1),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn auc_of_separated_reversed_and_tied_scores() {
        assert_eq!(roc_auc(&[3.0, 4.0], &[1.0, 2.0]), 1.0);
        assert_eq!(roc_auc(&[1.0, 2.0], &[3.0, 4.0]), 0.0);
        assert_eq!(roc_auc(&[1.0, 1.0], &[1.0]), 0.5);
        // One of the four pairs is inverted: 3/4.
        assert_eq!(roc_auc(&[2.0, 4.0], &[1.0, 3.0]), 0.75);
        assert!(roc_auc(&[], &[1.0]).is_nan());
    }

    #[test]
    fn invalid_configs_are_errors() {
        let c = ChangeExperimentConfig {
            sessions: 0,
            ..Default::default()
        };
        assert!(matches!(c.validate(), Err(ExperimentError::Invalid(_))));
        let c = ChangeExperimentConfig {
            static_fraction: 0.6,
            ..Default::default()
        };
        assert!(c.validate().is_err());
    }
}
