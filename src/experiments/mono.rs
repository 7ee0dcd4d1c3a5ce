//! Monocular SLAM on generated sequences with exact ground truth (`crate::synth`): renders
//! the grey images once, runs [`MonoSlam`] and scores the trajectory after a similarity
//! (Sim(3)) alignment, since monocular SLAM has no metric scale.

use std::sync::Arc;

use crate::camera::{PinholeCamera, UnifiedCamera};
use crate::eval::ate::{ate, AteResult};
use crate::image::ImageF32;
use crate::mono::filter::FrameReport;
use crate::mono::{
    KeyframeQuery, LoopingMono, MonoConfig, MonoError, MonoLoopParams, MonoSlam, MonoStats,
};
use crate::place::Vocabulary;
use crate::synth::{
    CameraModel, RenderBackend, Scene, SensorModel, Sequence, SequenceConfig, Trajectory,
    TrajectoryKind,
};
use crate::trajectory::TimedPose;

/// Which synthetic camera.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
pub enum SyntheticCamera {
    /// Pinhole with `f = 525 * width / 640` pixels (unified model with `xi = 0`).
    Pinhole,
    /// Catadioptric camera ([`UnifiedCamera::catadioptric`]).
    Catadioptric,
}

/// A synthetic sequence to render.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct SyntheticSpec {
    /// Camera kind.
    pub camera: SyntheticCamera,
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
    /// Frames.
    pub frames: usize,
    /// Frame rate, frames per second.
    pub fps: f64,
    /// Scene preset (`office`, `kitchen`, `corridor`, `lab`, `home`).
    pub scene: String,
    /// Trajectory name (`handheld`, `slow`, ...).
    pub trajectory: String,
    /// Seed of scene, trajectory and sensor noise.
    pub seed: u64,
    /// Add the sensor's image noise.
    pub noise: bool,
}

impl SyntheticSpec {
    /// A short sequence: `frames` frames at 30 fps of the office scene, handheld.
    pub fn new(camera: SyntheticCamera, width: u32, height: u32, frames: usize) -> Self {
        SyntheticSpec {
            camera,
            width,
            height,
            frames,
            fps: 30.0,
            scene: "office".into(),
            trajectory: "handheld".into(),
            seed: 7,
            noise: true,
        }
    }

    /// The camera model used for rendering and for the filter.
    pub fn camera_model(&self) -> (CameraModel, UnifiedCamera) {
        match self.camera {
            SyntheticCamera::Pinhole => {
                let f = 525.0 * f64::from(self.width) / 640.0;
                let (cx, cy) = (
                    f64::from(self.width) * 0.5 - 0.5,
                    f64::from(self.height) * 0.5 - 0.5,
                );
                (
                    CameraModel::Pinhole(PinholeCamera::new(f, f, cx, cy, self.width, self.height)),
                    UnifiedCamera::new(0.0, f, cx, cy, self.width, self.height),
                )
            }
            SyntheticCamera::Catadioptric => {
                let c = UnifiedCamera::catadioptric(self.width, self.height);
                (CameraModel::Unified(c), c)
            }
        }
    }
}

/// Rendered grey frames with their ground truth.
#[derive(Clone, Debug)]
pub struct SyntheticFrames {
    /// The camera (unified model).
    pub camera: UnifiedCamera,
    /// `(timestamp, intensity)` per frame.
    pub images: Vec<(f64, ImageF32)>,
    /// Ground truth `world_from_camera` per frame (metres, synth world frame).
    pub ground_truth: Vec<TimedPose>,
}

/// Renders a synthetic sequence on the CPU.
pub fn render(spec: &SyntheticSpec) -> Result<SyntheticFrames, MonoError> {
    let scene = Arc::new(Scene::preset(&spec.scene, spec.seed)?);
    let kind = TrajectoryKind::from_name(&spec.trajectory)?;
    let config = SequenceConfig {
        frames: spec.frames,
        fps: spec.fps,
        start_time: 0.0,
        sensor: if spec.noise {
            SensorModel::kinect()
        } else {
            SensorModel::noiseless()
        },
        seed: spec.seed,
        exposure_changes: false,
        motion_blur: 0,
        exposure_time: 1.0 / 60.0,
    };
    let trajectory = Trajectory::new(kind, &scene, config.duration(), spec.seed)?;
    let (model, camera) = spec.camera_model();
    let mut seq = Sequence::new(scene, model, trajectory, config, &RenderBackend::Cpu)?;
    let mut images = Vec::with_capacity(spec.frames);
    let mut ground_truth = Vec::with_capacity(spec.frames);
    for i in 0..spec.frames {
        let f = seq.render_frame(i)?;
        images.push((f.timestamp, f.frame.intensity));
        ground_truth.push(TimedPose {
            timestamp: f.timestamp,
            world_from_camera: f.world_from_camera,
        });
    }
    Ok(SyntheticFrames {
        camera,
        images,
        ground_truth,
    })
}

/// The outcome of a run with ground truth.
#[derive(Clone, Debug)]
pub struct RunResult {
    /// Estimated `world_from_camera` per frame (filter world frame, unknown scale).
    pub estimate: Vec<TimedPose>,
    /// Per-frame reports.
    pub reports: Vec<FrameReport>,
    /// ATE after a Sim(3) alignment (metres of the ground truth).
    pub ate: AteResult,
    /// Length of the ground-truth path, metres.
    pub path_length: f64,
    /// Run statistics.
    pub stats: MonoStats,
    /// Landmarks in the state that are 3D points at the end.
    pub points_in_state: usize,
}

/// Runs the filter over rendered frames and scores it against their ground truth.
pub fn run(frames: &SyntheticFrames, config: &MonoConfig) -> Result<RunResult, MonoError> {
    let mut slam = MonoSlam::new(frames.camera, config.clone())?;
    let mut estimate = Vec::with_capacity(frames.images.len());
    let mut reports = Vec::with_capacity(frames.images.len());
    for (t, img) in &frames.images {
        let r = slam.process(*t, img)?;
        estimate.push(TimedPose {
            timestamp: *t,
            world_from_camera: r.world_from_camera,
        });
        reports.push(r);
    }
    let ate = ate(&frames.ground_truth, &estimate, true)?;
    let path_length = frames
        .ground_truth
        .windows(2)
        .map(|w| (w[1].world_from_camera.translation - w[0].world_from_camera.translation).length())
        .sum();
    Ok(RunResult {
        estimate,
        reports,
        ate,
        path_length,
        stats: *slam.stats(),
        points_in_state: slam.points_in_state(),
    })
}

/// When two keyframes count as a true loop for scoring (ground truth only scores, it never
/// feeds the detector).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct LoopTruth {
    /// Largest distance, metres, between the two true camera positions.
    pub max_distance: f64,
    /// Largest angle, degrees, between the two true optical axes (viewing overlap).
    pub max_axis_angle_deg: f64,
}

impl Default for LoopTruth {
    fn default() -> Self {
        LoopTruth {
            max_distance: 1.5,
            max_axis_angle_deg: 90.0,
        }
    }
}

impl LoopTruth {
    /// `(distance m, optical-axis angle degrees, true loop)` of two ground-truth poses.
    pub fn judge(&self, a: &TimedPose, b: &TimedPose) -> (f64, f64, bool) {
        let d = (a.world_from_camera.translation - b.world_from_camera.translation).length();
        let za = a.world_from_camera.transform_vector(glam::DVec3::Z);
        let zb = b.world_from_camera.transform_vector(glam::DVec3::Z);
        let angle = za.angle_between(zb).to_degrees();
        (
            d,
            angle,
            d <= self.max_distance && angle <= self.max_axis_angle_deg,
        )
    }
}

/// A loop accepted at the detector's thresholds, with its ground-truth judgement.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct ScoredLoop {
    /// Query (newer) keyframe.
    pub query: usize,
    /// Matched (older) keyframe.
    pub candidate: usize,
    /// Frame index of the query.
    pub query_frame: usize,
    /// Frame index of the candidate.
    pub candidate_frame: usize,
    /// Normalised BoW score.
    pub normalised_score: f64,
    /// Descriptor matches.
    pub matches: usize,
    /// Essential-matrix inliers.
    pub inliers: usize,
    /// Median parallax of the inliers, degrees.
    pub parallax_deg: f64,
    /// True distance between the two camera positions, metres.
    pub true_distance_m: f64,
    /// True angle between the optical axes, degrees.
    pub true_axis_angle_deg: f64,
    /// A true loop by [`LoopTruth`].
    pub correct: bool,
}

/// Precision and recall at one set of thresholds.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct LoopScore {
    /// Normalised BoW score threshold.
    pub min_normalised_score: f64,
    /// Inlier threshold.
    pub min_inliers: usize,
    /// Inlier-ratio threshold.
    pub min_inlier_ratio: f64,
    /// Query keyframes with an accepted loop.
    pub detected: usize,
    /// Accepted loops that are true.
    pub true_positives: usize,
    /// Query keyframes that have a true loop among the keyframes outside the temporal window.
    pub loop_queries: usize,
    /// `true_positives / detected` (1 when nothing was detected).
    pub precision: f64,
    /// `true_positives / loop_queries` (1 when there is nothing to find).
    pub recall: f64,
}

/// Loop detection on the keyframes of a monocular run, scored against the ground truth.
#[derive(Clone, Debug, serde::Serialize)]
pub struct LoopEvaluation {
    /// The detector's parameters.
    pub params: MonoLoopParams,
    /// The definition of a true loop.
    pub truth: LoopTruth,
    /// Frames processed.
    pub frames: usize,
    /// Frame index of every keyframe.
    pub keyframe_frames: Vec<usize>,
    /// Every keyframe's query with its candidates' checks.
    pub queries: Vec<KeyframeQuery>,
    /// Loops accepted at the parameters' thresholds.
    pub loops: Vec<ScoredLoop>,
    /// Precision and recall at the parameters' thresholds.
    pub score: LoopScore,
    /// Precision and recall over a grid of normalised-score, inlier and inlier-ratio
    /// thresholds (the recorded candidates re-judged; the same loops as a run with those
    /// thresholds would accept).
    pub sweep: Vec<LoopScore>,
    /// Candidates checked geometrically that are not true loops (whatever their score).
    pub false_candidates: usize,
    /// Most essential-matrix inliers of any of them: the margin below the inlier threshold.
    pub false_candidate_max_inliers: usize,
    /// That candidate's `(true distance m, true optical-axis angle degrees)` to its query.
    pub false_candidate_max_truth: Option<(f64, f64)>,
    /// Length of the ground-truth path, metres.
    pub path_length: f64,
    /// The EKF's ATE after a Sim(3) alignment, metres.
    pub ate_rmse: f64,
    /// Median milliseconds per frame of the filter.
    pub filter_ms: f64,
    /// Median milliseconds per keyframe of ORB, query and verification.
    pub keyframe_ms: f64,
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v.get(v.len() / 2).copied().unwrap_or(0.0)
}

/// Scores the recorded queries at thresholds `(score, inliers, ratio)`.
fn score_loops(
    queries: &[KeyframeQuery],
    kf_truth: &[TimedPose],
    has_true: &[bool],
    truth: &LoopTruth,
    thresholds: (f64, usize, f64),
) -> (LoopScore, Vec<ScoredLoop>) {
    let (s, n, r) = thresholds;
    let mut loops = Vec::new();
    for q in queries {
        if let Some(c) = q.best(s, n, r) {
            let (d, a, ok) = truth.judge(&kf_truth[q.keyframe], &kf_truth[c.keyframe]);
            loops.push(ScoredLoop {
                query: q.keyframe,
                candidate: c.keyframe,
                query_frame: 0,
                candidate_frame: 0,
                normalised_score: c.normalised_score,
                matches: c.matches,
                inliers: c.inliers,
                parallax_deg: c.parallax_deg,
                true_distance_m: d,
                true_axis_angle_deg: a,
                correct: ok,
            });
        }
    }
    let tp = loops.iter().filter(|l| l.correct).count();
    let want = has_true.iter().filter(|&&b| b).count();
    let score = LoopScore {
        min_normalised_score: s,
        min_inliers: n,
        min_inlier_ratio: r,
        detected: loops.len(),
        true_positives: tp,
        loop_queries: want,
        precision: if loops.is_empty() {
            1.0
        } else {
            tp as f64 / loops.len() as f64
        },
        recall: if want == 0 {
            1.0
        } else {
            tp as f64 / want as f64
        },
    };
    (score, loops)
}

/// Runs the filter with keyframe selection and loop detection over rendered frames and scores
/// the detected loops against the ground truth (which only scores). `vocabulary` is the bag
/// of words' vocabulary.
pub fn loops(
    frames: &SyntheticFrames,
    config: &MonoConfig,
    vocabulary: Vocabulary,
    params: &MonoLoopParams,
    truth: &LoopTruth,
) -> Result<LoopEvaluation, MonoError> {
    params.validate()?;
    let slam = MonoSlam::new(frames.camera, config.clone())?;
    // Every candidate outside the temporal window among the best `max_candidates` is checked,
    // whatever its score, so that the sweep can judge lower score thresholds than the
    // parameters'; with a threshold the checked ones are the best `max_candidates` above it,
    // as the detector itself would check.
    let recording = MonoLoopParams {
        min_normalised_score: 0.0,
        ..params.clone()
    };
    let mut sys = LoopingMono::new(slam, vocabulary, recording)?;
    let mut estimate = Vec::with_capacity(frames.images.len());
    let mut filter_ms = Vec::with_capacity(frames.images.len());
    let mut keyframe_ms = Vec::new();
    let mut queries = Vec::new();
    for (t, img) in &frames.images {
        let r = sys.process(*t, img)?;
        estimate.push(TimedPose {
            timestamp: *t,
            world_from_camera: r.filter.world_from_camera,
        });
        filter_ms.push(r.filter.times.total());
        if let Some(q) = r.keyframe {
            keyframe_ms.push(r.loop_ms);
            queries.push(q);
        }
    }
    let keyframes = sys.detector().keyframes();
    let keyframe_frames: Vec<usize> = keyframes.iter().map(|k| k.frame).collect();
    let kf_truth: Vec<TimedPose> = keyframe_frames
        .iter()
        .map(|&f| frames.ground_truth[f])
        .collect();
    // A query can be recalled when an earlier keyframe outside the temporal window is a true
    // loop partner.
    let has_true: Vec<bool> = (0..keyframes.len())
        .map(|i| {
            (0..i).any(|j| {
                keyframes[i].timestamp - keyframes[j].timestamp >= params.min_time_separation
                    && truth.judge(&kf_truth[i], &kf_truth[j]).2
            })
        })
        .collect();
    let at = (
        params.min_normalised_score,
        params.min_inliers,
        params.min_inlier_ratio,
    );
    let (score, mut found) = score_loops(&queries, &kf_truth, &has_true, truth, at);
    for l in &mut found {
        l.query_frame = keyframe_frames[l.query];
        l.candidate_frame = keyframe_frames[l.candidate];
    }
    let mut sweep = Vec::new();
    for s in [0.0, 0.3, 0.5, 0.7, 1.0] {
        for n in [8, 15, 30, 50, 80] {
            for r in [0.0, params.min_inlier_ratio] {
                sweep.push(score_loops(&queries, &kf_truth, &has_true, truth, (s, n, r)).0);
            }
        }
    }
    let false_checks: Vec<(usize, f64, f64)> = queries
        .iter()
        .flat_map(|q| {
            let kf_truth = &kf_truth;
            q.candidates.iter().filter_map(move |c| {
                let (d, a, ok) = truth.judge(&kf_truth[q.keyframe], &kf_truth[c.keyframe]);
                (!ok).then_some((c.inliers, d, a))
            })
        })
        .collect();
    let worst_false = false_checks.iter().max_by_key(|c| c.0);
    let a = ate(&frames.ground_truth, &estimate, true)?;
    Ok(LoopEvaluation {
        params: params.clone(),
        truth: *truth,
        frames: frames.images.len(),
        keyframe_frames,
        queries,
        loops: found,
        score,
        sweep,
        false_candidates: false_checks.len(),
        false_candidate_max_inliers: worst_false.map_or(0, |c| c.0),
        false_candidate_max_truth: worst_false.map(|c| (c.1, c.2)),
        path_length: path_length(&frames.ground_truth),
        ate_rmse: a.translation.rmse,
        filter_ms: median(filter_ms),
        keyframe_ms: median(keyframe_ms),
    })
}

fn path_length(gt: &[TimedPose]) -> f64 {
    gt.windows(2)
        .map(|w| (w[1].world_from_camera.translation - w[0].world_from_camera.translation).length())
        .sum()
}
