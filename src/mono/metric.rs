//! Metric monocular SLAM of a walking person (thesis 3.4, Algorithm 1): the EKF
//! ([`MonoSlam`]) with the dynamic scale estimation ([`LiveDynScale`]) fed one pose per frame
//! beside it. Every `t_upd` seconds the scale estimation closes a section and scales it by the
//! walker's step frequency; the causal metric pose of each frame is available as it is
//! processed, and [`MetricMono::finish`] gives the final trajectory, each section scaled with
//! the scale known at its end.
//!
//! The scale estimation runs on the EKF's thread: its work per pose and per update does not
//! grow with the trajectory ([`LiveDynScale`]), and [`MetricReport::scale_ms`] reports it so
//! the share it adds to a frame can be measured.
//!
//! With loop detection ([`MetricMono::with_loops`], thesis 3.3.2) keyframes are chosen from the
//! EKF stream and checked for loops as [`super::LoopingMono`] does. At the end each verified
//! loop gives a relative similarity in the filter's units ([`LoopSimilarity`], eq. 3.10),
//! which is carried into the units of the metric output (each keyframe's section scale), and
//! `optimSim3` ([`optim_sim3_with`]) corrects the metric keyframes: the keyframes are the
//! Sim(3) vertices, the walking scale of each one's section is a prior on its scale (the
//! particle filter's standard deviation), consecutive keyframes are joined by the metric
//! trajectory's relative motion, and the loops add their similarities. Every frame then takes
//! the correction of the keyframes around it, blended by time.
//!
//! Loops also correct the causal output as they are found: when a keyframe closes a loop, the
//! same `optimSim3` runs on everything seen so far (the sections closed so far, the open one
//! with the scale now), and the rigid motion that takes the frame's causal pose to its
//! corrected pose is applied to this and every later causal pose until the next loop
//! ([`MetricReport::looped`], [`MetricRun::causal_looped`]); with
//! [`LoopScaleParams::correction_blend`] the output moves to the new correction over that many
//! seconds instead of jumping. The scale of the motion after the loop stays the walking
//! estimate's.

use std::time::Instant;

use glam::{DQuat, DVec3};

use super::loops::{
    CandidateCheck, KeyframeQuery, KeyframeSelector, LoopScaleParams, LoopSimilarity,
    MonoLoopDetector, MonoLoopParams,
};
use super::{FrameReport, MonoConfig, MonoError, MonoSlam};
use crate::camera::UnifiedCamera;
use crate::geometry::Se3;
use crate::graph::Sim3;
use crate::image::ImageF32;
use crate::place::Vocabulary;
use crate::scale::{
    optim_sim3_with, DynScaleConfig, DynScaleResult, LiveDynScale, ScaleError, Section,
    SimilarityConstraint,
};
use crate::trajectory::TimedPose;

/// Log-scale prior of a keyframe whose section has no standard deviation from the particle
/// filter (the sections before the first estimate, which take the first one): loose, as
/// nothing was measured there.
const UNMEASURED_LOG_SCALE_STD: f64 = 0.1;
/// Smallest log-scale prior: the particle filter's spread can collapse on a steady walk, and a
/// prior tighter than the scale's true drift within a section would make loops powerless.
const MIN_LOG_SCALE_STD: f64 = 0.01;

/// One processed frame of [`MetricMono`].
#[derive(Clone, Debug)]
pub struct MetricReport {
    /// The EKF's report (pose in SLAM units, filter world = first camera).
    pub report: FrameReport,
    /// The frame's pose in metres with the scale known now (causal, eq. 3.31-3.32); `None`
    /// until the first walking window has given a scale.
    pub metric: Option<TimedPose>,
    /// The scale in effect now, metres per SLAM unit.
    pub scale: Option<f64>,
    /// Sections closed by this frame (usually none; one every `t_upd` seconds).
    pub closed: Vec<Section>,
    /// Milliseconds spent in the scale estimation for this frame.
    pub scale_ms: f64,
    /// With loop detection: the keyframe query when the frame became a keyframe.
    pub keyframe: Option<KeyframeQuery>,
    /// Milliseconds spent on keyframe selection, ORB, database query and verification, and
    /// on the loop correction when this frame closed a loop (0 without loop detection).
    pub loop_ms: f64,
    /// With loop detection: [`Self::metric`] moved by the correction of the loops found up to
    /// and including this frame (causal; the same as `metric` before the first used loop).
    pub looped: Option<TimedPose>,
}

/// A verified loop of a [`MetricMono`] run with loop detection.
#[derive(Clone, Debug)]
pub struct MetricLoop {
    /// The query (newer) keyframe, index into [`LoopedRun::keyframe_frames`].
    pub query: usize,
    /// The candidate (older) keyframe.
    pub candidate: usize,
    /// The verification that accepted it.
    pub check: CandidateCheck,
    /// Its relative similarity in the filter's units; `None` when too few of its inliers had
    /// a local depth in both keyframes (the loop is then not used).
    pub similarity: Option<LoopSimilarity>,
}

/// The loop-corrected output of a [`MetricMono`] run with loop detection.
#[derive(Clone, Debug)]
pub struct LoopedRun {
    /// Frame index (0-based) of each keyframe.
    pub keyframe_frames: Vec<usize>,
    /// The verified loops, in the order found.
    pub loops: Vec<MetricLoop>,
    /// Loops with a similarity, used as `optimSim3` constraints.
    pub constraints: usize,
    /// The metric trajectory corrected by `optimSim3` (`world_from_camera`, metres, one pose
    /// per frame; the dynScale output unchanged when no loop could be used).
    pub trajectory: Vec<TimedPose>,
}

/// Loop detection beside the filter.
struct LoopState {
    selector: KeyframeSelector,
    detector: MonoLoopDetector,
    scale_params: LoopScaleParams,
    found: Vec<(usize, CandidateCheck)>,
    /// The similarities of the first loops of `found`, those whose query keyframe already has
    /// its later neighbour (so they no longer change).
    settled: Vec<Option<LoopSimilarity>>,
    frame: usize,
}

impl LoopState {
    /// The similarity of every loop found so far (eq. 3.10, [`MonoLoopDetector::loop_similarity`]
    /// with the keyframes that exist now). A loop's similarity is final once its query keyframe
    /// has its later neighbour (the candidate is older, so it has its own): those are kept,
    /// so the work per call grows with the loops still unsettled, not with all loops.
    fn similarities(&mut self) -> Vec<Option<LoopSimilarity>> {
        let keyframes = self.detector.keyframes().len();
        while let Some((q, c)) = self.found.get(self.settled.len()) {
            if q + 1 >= keyframes {
                break;
            }
            let sim = self.detector.loop_similarity(*q, c, &self.scale_params);
            self.settled.push(sim);
        }
        let mut all = self.settled.clone();
        for (q, c) in &self.found[self.settled.len()..] {
            all.push(self.detector.loop_similarity(*q, c, &self.scale_params));
        }
        all
    }
}

/// The trajectories of a finished [`MetricMono`] run (`world_from_camera`, filter world =
/// first camera).
#[derive(Debug)]
pub struct MetricRun {
    /// The EKF's trajectory, SLAM units.
    pub unscaled: Vec<TimedPose>,
    /// Each frame's causal metric pose, metres, from the first frame that had a scale on.
    pub causal: Vec<TimedPose>,
    /// The final output, metres: sections, up axis and the scaled trajectory (each section
    /// scaled with the scale at its end; those before the first estimate with the first).
    /// An error when the scale was unobservable (no section detected as walking); the
    /// trajectories above are kept either way.
    pub scaled: Result<DynScaleResult, ScaleError>,
    /// With loop detection and a metric trajectory: the loops and the loop-corrected metric
    /// trajectory (an error when the Sim(3) graph failed).
    pub looped: Option<Result<LoopedRun, ScaleError>>,
    /// With loop detection: each frame's causal metric pose moved by the loops found up to it
    /// ([`MetricReport::looped`]), metres, the same frames as [`Self::causal`]; empty without.
    pub causal_looped: Vec<TimedPose>,
}

/// Monocular EKF SLAM with metric scale from walking.
pub struct MetricMono {
    slam: MonoSlam,
    scale: LiveDynScale,
    unscaled: Vec<TimedPose>,
    causal: Vec<TimedPose>,
    loops: Option<LoopState>,
    /// The loop correction of the causal output in effect (new world from old world).
    correction: Option<CorrectionBlend>,
    causal_looped: Vec<TimedPose>,
}

impl MetricMono {
    /// The EKF on `camera` with `mono` settings, and the scale estimation with `scale`
    /// settings (their walking model carries the walker's height; `UpAxis::Auto` finds the
    /// up axis online and then holds it, as a monocular world frame is arbitrary).
    pub fn new(
        camera: UnifiedCamera,
        mono: MonoConfig,
        scale: DynScaleConfig,
    ) -> Result<MetricMono, MonoError> {
        Ok(MetricMono {
            slam: MonoSlam::new(camera, mono)?,
            scale: LiveDynScale::new(scale)?,
            unscaled: Vec::new(),
            causal: Vec::new(),
            loops: None,
            correction: None,
            causal_looped: Vec::new(),
        })
    }

    /// [`MetricMono::new`] with loop detection from the images (keyframes, ORB + bag of words
    /// with `vocabulary`, essential-matrix verification by `params`) and `optimSim3` on the
    /// metric output at the end, each loop's similarity measured with `scale_params`.
    pub fn with_loops(
        camera: UnifiedCamera,
        mono: MonoConfig,
        scale: DynScaleConfig,
        vocabulary: Vocabulary,
        params: MonoLoopParams,
        scale_params: LoopScaleParams,
    ) -> Result<MetricMono, MonoError> {
        scale_params.validate()?;
        let mut m = MetricMono::new(camera, mono, scale)?;
        m.loops = Some(LoopState {
            selector: KeyframeSelector::new(params.keyframes)?,
            detector: MonoLoopDetector::new(camera, vocabulary, params)?,
            scale_params,
            found: Vec::new(),
            settled: Vec::new(),
            frame: 0,
        });
        Ok(m)
    }

    /// The loop detector, with loop detection on.
    pub fn detector(&self) -> Option<&MonoLoopDetector> {
        self.loops.as_ref().map(|l| &l.detector)
    }

    /// The EKF.
    pub fn slam(&self) -> &MonoSlam {
        &self.slam
    }

    /// The scale estimation.
    pub fn scale(&self) -> &LiveDynScale {
        &self.scale
    }

    /// The EKF's trajectory so far (SLAM units, `world_from_camera`, filter world = first
    /// camera).
    pub fn unscaled(&self) -> &[TimedPose] {
        &self.unscaled
    }

    /// The causal metric pose of every frame so far that had a scale (metres).
    pub fn causal(&self) -> &[TimedPose] {
        &self.causal
    }

    /// With loop detection: [`Self::causal`] corrected by the loops found up to each frame
    /// (metres; empty without loop detection).
    pub fn causal_looped(&self) -> &[TimedPose] {
        &self.causal_looped
    }

    /// Processes one grey image (intensity in `[0, 255]`) taken at `timestamp` seconds
    /// (strictly increasing).
    pub fn process(&mut self, timestamp: f64, image: &ImageF32) -> Result<MetricReport, MonoError> {
        let report = self.slam.process(timestamp, image)?;
        let pose = TimedPose {
            timestamp: report.timestamp,
            world_from_camera: report.world_from_camera,
        };
        let t0 = Instant::now();
        let closed = self.scale.push(pose)?;
        let metric = self.scale.scaled_pose();
        let scale_ms = t0.elapsed().as_secs_f64() * 1e3;
        self.unscaled.push(pose);
        if let Some(m) = metric {
            self.causal.push(m);
        }
        let t1 = Instant::now();
        let mut keyframe = None;
        let mut looped = None;
        if let Some(l) = &mut self.loops {
            if l.selector.update(timestamp, &self.slam) {
                let q =
                    l.detector
                        .add_keyframe(l.frame, timestamp, report.world_from_camera, image)?;
                let p = l.detector.params();
                if let Some(c) = q.best(p.min_normalised_score, p.min_inliers, p.min_inlier_ratio) {
                    l.found.push((q.keyframe, *c));
                    if let Some(m) = metric {
                        if let Some(c) = causal_correction(l, &self.scale, &self.unscaled, &m) {
                            let from = match &self.correction {
                                Some(b) => b.world_correction(&m),
                                None => Se3::IDENTITY,
                            };
                            self.correction = Some(CorrectionBlend {
                                from,
                                to: c,
                                start: m.timestamp,
                                duration: l.scale_params.correction_blend,
                            });
                        }
                    }
                }
                keyframe = Some(q);
            }
            l.frame += 1;
            if let Some(m) = metric {
                let corrected = match &self.correction {
                    Some(c) => TimedPose {
                        timestamp: m.timestamp,
                        world_from_camera: c.apply(&m),
                    },
                    None => m,
                };
                self.causal_looped.push(corrected);
                looped = Some(corrected);
            }
        }
        let loop_ms = if self.loops.is_some() {
            t1.elapsed().as_secs_f64() * 1e3
        } else {
            0.0
        };
        Ok(MetricReport {
            report,
            metric,
            scale: self.scale.scale(),
            closed,
            scale_ms,
            keyframe,
            loop_ms,
            looped,
        })
    }

    /// Ends the run: closes the last sections and scales the whole trajectory.
    /// With loop detection, the loop-corrected metric trajectory too.
    pub fn finish(mut self) -> MetricRun {
        let scaled = self.scale.finish(&self.unscaled);
        let looped = match (&mut self.loops, &scaled) {
            (Some(l), Ok(r)) => {
                let similarities = l.similarities();
                Some(close_loops(l, &similarities, r))
            }
            _ => None,
        };
        MetricRun {
            unscaled: self.unscaled,
            causal: self.causal,
            scaled,
            looped,
            causal_looped: self.causal_looped,
        }
    }
}

/// `world_from_camera` moved by a world correction blended from `a` to `b` at `u` in [0, 1],
/// each correction given as its rotation and the position it moves the camera to: the
/// rotation slerped, the position on the straight line between the two corrected positions
/// (so a rotation of the correction does not swing the camera about the distant world
/// origin).
fn blend_corrected(world_from_camera: &Se3, a: (DQuat, DVec3), b: (DQuat, DVec3), u: f64) -> Se3 {
    Se3::new(
        (a.0.slerp(b.0, u) * world_from_camera.rotation).normalize(),
        a.1.lerp(b.1, u),
    )
}

/// A loop correction of the causal output that takes effect over `duration` seconds: from the
/// correction in effect when the loop was found (`from`, new world from old world) to the
/// loop's (`to`), starting at the frame that found it (`start`, seconds).
#[derive(Clone, Copy, Debug)]
struct CorrectionBlend {
    from: Se3,
    to: Se3,
    start: f64,
    duration: f64,
}

impl CorrectionBlend {
    /// The corrected pose (`world_from_camera`, metres) of the causal metric pose `metric`.
    fn apply(&self, metric: &TimedPose) -> Se3 {
        let u = if self.duration > 0.0 {
            ((metric.timestamp - self.start) / self.duration).clamp(0.0, 1.0)
        } else {
            1.0
        };
        if u >= 1.0 {
            return self.to * metric.world_from_camera;
        }
        let p = metric.world_from_camera.translation;
        blend_corrected(
            &metric.world_from_camera,
            (self.from.rotation, self.from.transform_point(p)),
            (self.to.rotation, self.to.transform_point(p)),
            u,
        )
    }

    /// The world correction (new world from old world) that takes `metric` to its corrected
    /// pose now: where the next correction starts from.
    fn world_correction(&self, metric: &TimedPose) -> Se3 {
        self.apply(metric) * metric.world_from_camera.inverse()
    }
}

/// The causal output's correction after a loop was found at the latest frame, whose causal
/// metric pose is `metric`: `optimSim3` ([`close_loops`]) on the run so far, scaled by a copy
/// of the scale estimation closed now, and the rigid motion (new world from old) that takes
/// `metric` to the frame's corrected pose. `None` when the run so far has no scale or no
/// usable loop, or the graph failed (the previous correction then stays).
fn causal_correction(
    l: &mut LoopState,
    scale: &LiveDynScale,
    unscaled: &[TimedPose],
    metric: &TimedPose,
) -> Option<Se3> {
    let so_far = scale.clone().finish(unscaled).ok()?;
    let similarities = l.similarities();
    let run = close_loops(l, &similarities, &so_far).ok()?;
    if run.constraints == 0 {
        return None;
    }
    let now = run.trajectory.last()?;
    Some(now.world_from_camera * metric.world_from_camera.inverse())
}

/// `optimSim3` on the metric keyframes with the loops' similarities (`similarities`, one per
/// loop of `l.found`; see the module docs).
fn close_loops(
    l: &LoopState,
    similarities: &[Option<LoopSimilarity>],
    metric: &DynScaleResult,
) -> Result<LoopedRun, ScaleError> {
    let kfs = l.detector.keyframes();
    let keyframe_frames: Vec<usize> = kfs.iter().map(|k| k.frame).collect();
    let loops: Vec<MetricLoop> = l
        .found
        .iter()
        .zip(similarities)
        .map(|((q, c), similarity)| MetricLoop {
            query: *q,
            candidate: c.keyframe,
            check: *c,
            similarity: *similarity,
        })
        .collect();
    let traj = &metric.scaled;
    let mut kf_poses = Vec::with_capacity(kfs.len());
    for k in kfs {
        kf_poses.push(
            *traj
                .get(k.frame)
                .ok_or_else(|| ScaleError::InvalidParameter {
                    name: "keyframes",
                    why: format!(
                        "keyframe at frame {} beyond the {} metric poses",
                        k.frame,
                        traj.len()
                    ),
                })?,
        );
    }
    // Each keyframe's section scale (metres per filter unit) carries a similarity measured in
    // the filter's units into the metric output's: a point `x` of keyframe k's camera frame in
    // filter units is `c_k x` in the metric camera frame.
    let section_scale: Vec<f64> = kfs.iter().map(|k| metric.scale_at(k.timestamp)).collect();
    let constraints: Vec<SimilarityConstraint> = loops
        .iter()
        .filter_map(|lp| {
            let sim = lp.similarity?;
            let (ci, cj) = (section_scale[lp.candidate], section_scale[lp.query]);
            let z = sim.candidate_from_query;
            let c = SimilarityConstraint {
                i: lp.candidate,
                j: lp.query,
                i_from_j: Sim3::new(z.rotation, ci * z.translation, z.scale * ci / cj),
                translation_std: ci * sim.translation_std,
                rotation_std: sim.rotation_std,
                log_scale_std: sim.log_scale_std,
            };
            let z = c.i_from_j;
            (z.translation.is_finite() && z.scale.is_finite() && c.translation_std.is_finite())
                .then_some(c)
        })
        .collect();
    if constraints.is_empty() || kf_poses.len() < 2 {
        return Ok(LoopedRun {
            keyframe_frames,
            loops,
            constraints: 0,
            trajectory: traj.clone(),
        });
    }
    let priors: Vec<f64> = kfs
        .iter()
        .map(|k| {
            let sd = metric.section_at(k.timestamp).log10_std * std::f64::consts::LN_10;
            if sd.is_finite() && sd > 0.0 {
                sd.max(MIN_LOG_SCALE_STD)
            } else {
                UNMEASURED_LOG_SCALE_STD
            }
        })
        .collect();
    let corrected = optim_sim3_with(&kf_poses, &constraints, Some(&priors))?;
    // World correction of each keyframe: new world from old world.
    let corrections: Vec<Sim3> = corrected
        .iter()
        .zip(&kf_poses)
        .map(|(new, old)| *new * Sim3::from_se3(&old.world_from_camera).inverse())
        .collect();
    let trajectory = traj
        .iter()
        .enumerate()
        .map(|(f, pose)| {
            let k = keyframe_frames
                .partition_point(|&kf| kf <= f)
                .saturating_sub(1);
            let ck = &corrections[k];
            let p = pose.world_from_camera.translation;
            let (next, u) = match (corrections.get(k + 1), kfs.get(k + 1)) {
                (Some(cn), Some(next)) => {
                    let (t0, t1) = (kfs[k].timestamp, next.timestamp);
                    (cn, ((pose.timestamp - t0) / (t1 - t0)).clamp(0.0, 1.0))
                }
                _ => (ck, 0.0),
            };
            TimedPose {
                timestamp: pose.timestamp,
                world_from_camera: blend_corrected(
                    &pose.world_from_camera,
                    (ck.rotation, ck.transform_point(p)),
                    (next.rotation, next.transform_point(p)),
                    u,
                ),
            }
        })
        .collect();
    Ok(LoopedRun {
        keyframe_frames,
        loops,
        constraints: constraints.len(),
        trajectory,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scale::{UpAxis, WalkingModel};

    #[test]
    fn a_blank_sequence_has_no_scale_keeps_its_poses_and_says_no_walking() {
        let camera = UnifiedCamera::new(0.0, 100.0, 31.5, 23.5, 64, 48);
        let cfg = DynScaleConfig {
            model: WalkingModel::grieve(1.8),
            up: UpAxis::Auto,
            ..DynScaleConfig::default()
        };
        let mut m = MetricMono::new(camera, MonoConfig::default(), cfg).unwrap();
        let img = ImageF32::filled(64, 48, 128.0);
        for k in 0..20 {
            let r = m.process(k as f64 / 30.0, &img).unwrap();
            assert!(r.metric.is_none() && r.scale.is_none() && r.closed.is_empty());
        }
        let run = m.finish();
        assert_eq!((run.unscaled.len(), run.causal.len()), (20, 0));
        let e = run.scaled.unwrap_err().to_string();
        assert!(e.contains("walking"), "{e}");
    }

    fn pose_at(t: f64, x: f64) -> TimedPose {
        TimedPose {
            timestamp: t,
            world_from_camera: Se3::new(
                glam::DQuat::from_rotation_z(0.1 * x),
                glam::DVec3::new(x, 0.5 * x, 0.2),
            ),
        }
    }

    fn close(a: &Se3, b: &Se3) -> bool {
        (a.inverse() * *b).log().iter().all(|v| v.abs() < 1e-9)
    }

    #[test]
    fn a_blended_correction_moves_from_the_old_to_the_new_correction_over_its_duration() {
        let from = Se3::new(
            glam::DQuat::from_rotation_z(0.05),
            glam::DVec3::new(0.3, 0.0, 0.0),
        );
        let to = Se3::new(
            glam::DQuat::from_rotation_z(-0.1),
            glam::DVec3::new(-0.2, 1.0, 0.1),
        );
        let b = CorrectionBlend {
            from,
            to,
            start: 10.0,
            duration: 2.0,
        };
        let at_once = CorrectionBlend { duration: 0.0, ..b };
        let at_start = pose_at(10.0, 5.0);
        assert!(close(
            &b.apply(&at_start),
            &(from * at_start.world_from_camera)
        ));
        let after = pose_at(12.0, 7.0);
        assert!(close(&b.apply(&after), &(to * after.world_from_camera)));
        assert!(close(
            &at_once.apply(&at_start),
            &(to * at_start.world_from_camera)
        ));
        // Halfway the position lies halfway between the two corrected positions: the blend
        // does not swing the camera about the world origin, 5 m away.
        let mid = pose_at(11.0, 6.0);
        let half = b.apply(&mid).translation;
        let pa = (from * mid.world_from_camera).translation;
        let pb = (to * mid.world_from_camera).translation;
        assert!((half - 0.5 * (pa + pb)).length() < 1e-9 * (pb - pa).length());
        // A new correction starts where the output is now.
        let w = b.world_correction(&mid);
        assert!(close(&(w * mid.world_from_camera), &b.apply(&mid)));
    }
}
