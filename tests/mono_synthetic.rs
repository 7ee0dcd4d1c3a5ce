//! Monocular EKF SLAM on short synthetic pinhole and catadioptric sequences with exact
//! ground truth. The Sim(3)-aligned trajectory error must be a small fraction of the spread
//! of the ground-truth positions (a filter that loses track, stands still or drifts freely
//! has an error comparable to that spread), and on the catadioptric sequence the warped
//! patch must match more often per feature than the plain one (thesis table 2.1). A short
//! catadioptric walk that laps a room must close loops from its images alone, none of them
//! false, with the essential matrix's rotation agreeing with the true relative rotation.

use rgbid::experiments::mono::{
    loops, render, run, LoopTruth, RunResult, SyntheticCamera, SyntheticSpec,
};
use rgbid::mono::{MonoConfig, MonoLoopParams, PatchMode};
use rgbid::place::Vocabulary;
use rgbid::trajectory::TimedPose;

/// RMS distance of the ground-truth positions from their mean, metres.
fn spread(gt: &[TimedPose]) -> f64 {
    let n = gt.len() as f64;
    let mean = gt
        .iter()
        .map(|p| p.world_from_camera.translation)
        .sum::<glam::DVec3>()
        / n;
    (gt.iter()
        .map(|p| (p.world_from_camera.translation - mean).length_squared())
        .sum::<f64>()
        / n)
        .sqrt()
}

fn describe(what: &str, r: &RunResult, spread: f64) {
    let matched = r
        .reports
        .iter()
        .map(|x| (x.inliers + x.rescued) as f64)
        .sum::<f64>()
        / r.reports.len() as f64;
    eprintln!(
        "{what}: path {:.2} m, spread {spread:.3} m, ATE rmse {:.4} m, scale {:.3}, FI {}, Rm {:.2}, \
         Rf {:.2}, matched/frame {matched:.1}",
        r.path_length,
        r.ate.translation.rmse,
        r.ate.alignment.scale,
        r.stats.features_initialised,
        r.stats.rm(),
        r.stats.rf(r.points_in_state)
    );
}

#[test]
fn pinhole_sequence_tracks_with_small_similarity_aligned_error() {
    let spec = SyntheticSpec::new(SyntheticCamera::Pinhole, 320, 240, 100);
    let frames = render(&spec).expect("render");
    let r = run(&frames, &MonoConfig::default()).expect("run");
    let s = spread(&frames.ground_truth);
    describe("pinhole", &r, s);
    assert!(s > 0.2, "the sequence must move: spread {s} m");
    assert!(
        r.ate.translation.rmse < 0.2 * s,
        "ATE {} m vs spread {s} m",
        r.ate.translation.rmse
    );
    assert!(r.ate.translation.rmse < 0.05 * r.path_length);
    // Tracking, not coasting: most frames update with many matches.
    let tracked = r
        .reports
        .iter()
        .skip(1)
        .filter(|x| x.inliers + x.rescued >= 10)
        .count();
    assert!(tracked >= 90, "{tracked} of 99 frames with >= 10 matches");
}

#[test]
fn catadioptric_sequence_tracks_and_warping_matches_more() {
    let spec = SyntheticSpec::new(SyntheticCamera::Catadioptric, 320, 320, 100);
    let frames = render(&spec).expect("render");
    let s = spread(&frames.ground_truth);
    let mut rm = Vec::new();
    for mode in [PatchMode::Warped, PatchMode::Plain] {
        let config = MonoConfig {
            patch_mode: mode,
            ..MonoConfig::default()
        };
        let r = run(&frames, &config).expect("run");
        describe(&format!("catadioptric {mode:?}"), &r, s);
        assert!(
            r.ate.translation.rmse < 0.15 * s,
            "{mode:?}: ATE {} m vs spread {s} m",
            r.ate.translation.rmse
        );
        assert!(r.ate.translation.rmse < 0.05 * r.path_length);
        rm.push(r.stats.rm());
    }
    assert!(
        rm[0] > rm[1],
        "warped patches should match more often: Rm {} vs {}",
        rm[0],
        rm[1]
    );
}

#[test]
fn catadioptric_walk_lapping_a_room_closes_true_loops_only() {
    // The office's walking loop is about 8 m long, a lap at the first pace takes about 7 s:
    // 11 s lap it once and a half.
    let mut spec = SyntheticSpec::new(SyntheticCamera::Catadioptric, 240, 240, 330);
    spec.trajectory = "walk-head".into();
    let frames = render(&spec).expect("render");
    let params = MonoLoopParams {
        min_time_separation: 5.0,
        ..MonoLoopParams::default()
    };
    let vocabulary = Vocabulary::embedded_default().expect("vocabulary");
    let e = loops(
        &frames,
        &MonoConfig::default(),
        vocabulary,
        &params,
        &LoopTruth::default(),
    )
    .expect("loops");
    let s = &e.score;
    eprintln!(
        "{} keyframes, {} with a true partner; {} loops, {} true (precision {:.3}, recall {:.3})",
        e.keyframe_frames.len(),
        s.loop_queries,
        s.detected,
        s.true_positives,
        s.precision,
        s.recall
    );
    assert!(s.loop_queries > 0, "the walk must revisit places");
    assert!(s.true_positives >= 1, "no loop found");
    let mut errors = Vec::new();
    for l in &e.loops {
        assert!(
            l.correct,
            "false loop {} -> {}: {:.2} m, {:.0} deg apart",
            l.query_frame, l.candidate_frame, l.true_distance_m, l.true_axis_angle_deg
        );
        let check = e.queries[l.query]
            .candidates
            .iter()
            .find(|c| c.keyframe == l.candidate)
            .expect("the accepted candidate's check");
        let estimated = check.query_from_candidate.expect("a relative pose");
        let (q, c) = (
            frames.ground_truth[l.query_frame].world_from_camera,
            frames.ground_truth[l.candidate_frame].world_from_camera,
        );
        let truth = q.inverse() * c;
        let error = estimated
            .rotation
            .angle_between(truth.rotation)
            .to_degrees();
        eprintln!(
            "loop {} -> {}: {:.2} m, {} of {} inliers, parallax {:.1} deg, rotation error {error:.2} deg",
            l.query_frame, l.candidate_frame, l.true_distance_m, l.inliers, l.matches, l.parallax_deg
        );
        errors.push(error);
    }
    // At 240x240 a pixel is about a degree of the mirror's view: the relative rotation of a
    // verified loop is typically good to a degree, and a wrong decomposition of the essential
    // matrix (a twisted pair, a flipped baseline) would be off by tens of degrees.
    errors.sort_by(f64::total_cmp);
    let median = errors[errors.len() / 2];
    let worst = errors[errors.len() - 1];
    assert!(
        median < 1.5 && worst < 5.0,
        "rotation error median {median:.2} deg, worst {worst:.2} deg"
    );
}
