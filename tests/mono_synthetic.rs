//! Monocular EKF SLAM on short synthetic pinhole and catadioptric sequences with exact
//! ground truth: the Sim(3)-aligned trajectory error must be a small fraction of the
//! ground-truth motion, which a filter that loses track (or stands still) cannot meet.

use std::time::Instant;

use rgbid::mono::synthetic::{render, run, SyntheticCamera, SyntheticSpec};
use rgbid::mono::{MonoConfig, PatchMode};

fn spread(gt: &[rgbid::io::trajectory::TimedPose]) -> f64 {
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

fn check(spec: SyntheticSpec, config: MonoConfig) -> (f64, f64) {
    let t0 = Instant::now();
    let frames = render(&spec).expect("render");
    let t_render = t0.elapsed().as_secs_f64();
    let t0 = Instant::now();
    let r = run(&frames, &config).expect("run");
    let t_run = t0.elapsed().as_secs_f64();
    let rmse = r.ate.translation.rmse;
    let s = spread(&frames.ground_truth);
    let matched: f64 =
        r.reports.iter().map(|r| (r.inliers + r.rescued) as f64).sum::<f64>() / r.reports.len() as f64;
    eprintln!(
        "{:?}: render {t_render:.1} s, run {t_run:.1} s; path {:.2} m, spread {s:.3} m, ATE rmse {rmse:.4} m, scale {:.3}, FI {}, Rm {:.2}, matched/frame {matched:.1}",
        spec.camera, r.path_length, r.ate.alignment.scale, r.stats.features_initialised, r.stats.rm()
    );
    for (k, rep) in r.reports.iter().enumerate().step_by(10) {
        let e = r.ate.alignment.apply(r.estimate[k].world_from_camera.translation)
            - frames.ground_truth[k].world_from_camera.translation;
        let half = |a: usize, b: usize| {
            let src: Vec<_> = r.estimate[a..b].iter().map(|p| p.world_from_camera.translation).collect();
            let dst: Vec<_> = frames.ground_truth[a..b].iter().map(|p| p.world_from_camera.translation).collect();
            rgbid::eval::ate::align_umeyama(&src, &dst, true).map(|a| a.scale).unwrap_or(f64::NAN)
        };
        eprintln!(
            "  {k}: vis {} match {} in {} resc {} new {} lm {} err {:.3} local scale {:.2}",
            rep.visible, rep.matched, rep.inliers, rep.rescued, rep.initialised, rep.landmarks, e.length(),
            half(k, (k + 10).min(r.estimate.len()))
        );
    }
    (rmse, s)
}

#[test]
fn pinhole_sequence_tracks_with_small_similarity_aligned_error() {
    let spec = SyntheticSpec::new(SyntheticCamera::Pinhole, 320, 240, 120);
    let (rmse, spread) = check(spec, MonoConfig::default());
    assert!(rmse < 0.15 * spread, "ATE {rmse} m vs motion spread {spread} m");
}

#[test]
fn catadioptric_sequence_tracks_with_small_similarity_aligned_error() {
    let spec = SyntheticSpec::new(SyntheticCamera::Catadioptric, 400, 400, 120);
    let config = MonoConfig {
        patch_mode: PatchMode::Warped,
        ..MonoConfig::default()
    };
    let (rmse, spread) = check(spec, config);
    assert!(rmse < 0.15 * spread, "ATE {rmse} m vs motion spread {spread} m");
}
