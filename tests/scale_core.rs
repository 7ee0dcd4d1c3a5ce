//! Metric scale from walking (thesis ch. 3): spectrum, stop detection, filter, errors.

use std::f64::consts::PI;

use glam::{DQuat, DVec3};
use rgbid::experiments::scale::{
    local_scale, run_sequence, standard_sequences, Estimator, ExperimentConfig, MonoEstimator,
};
use rgbid::geometry::Se3;
use rgbid::io::trajectory::read_tum;
use rgbid::scale::{
    emulate_monocular, DriftModel, DynScale, DynScaleConfig, HighPass, LiveDynScale, ScaleError,
    SpectrumConfig, StepAnalysis, UpAxis,
};
use rgbid::synth::{Scene, Trajectory};
use rgbid::trajectory::TimedPose;

fn noise(k: usize) -> f64 {
    // Deterministic pseudo-noise in [-1, 1].
    let x = (k as f64 * 12.9898).sin() * 43758.5453;
    2.0 * (x - x.floor()) - 1.0
}

#[test]
fn known_frequencies_give_peak_within_005_hz() {
    let fs = 30.0;
    let cfg = SpectrumConfig::default();
    for &f in &[1.05, 1.3, 1.62, 1.91, 2.25, 2.6, 2.95] {
        let x: Vec<f64> = (0..900)
            .map(|k| {
                let t = k as f64 / fs;
                0.1 * t + 0.02 * (2.0 * PI * f * t + 0.3).cos() + 0.003 * noise(k)
            })
            .collect();
        let y = HighPass::filter_signal(0.7, fs, &x).unwrap();
        for start in [150, 400, 780] {
            let a = StepAnalysis::analyze(&y[start..start + 120], fs, &cfg).unwrap();
            assert!(
                (a.frequency - f).abs() < 0.05,
                "f {f}: peak {} at {start}",
                a.frequency
            );
            assert!(a.is_walking(&cfg, Some(1.0)), "{a:?}");
            assert!(
                (a.amplitude - 0.02).abs() < 0.006,
                "amplitude {}",
                a.amplitude
            );
        }
    }
}

#[test]
fn standing_is_not_walking() {
    let fs = 30.0;
    let cfg = SpectrumConfig::default();
    // Standing: drift + sensor noise, no oscillation.
    let x: Vec<f64> = (0..300)
        .map(|k| 0.001 * k as f64 / fs + 0.002 * noise(k))
        .collect();
    let y = HighPass::filter_signal(0.7, fs, &x).unwrap();
    let a = StepAnalysis::analyze(&y[150..270], fs, &cfg).unwrap();
    assert!(
        !a.is_walking(&cfg, Some(1.0)),
        "noise detected as walking: {a:?}"
    );
    // A tiny oscillation (0.5 mm): below A_z- once the scale is known.
    let x: Vec<f64> = (0..300)
        .map(|k| 0.0005 * (2.0 * PI * 1.7 * k as f64 / fs).sin())
        .collect();
    let y = HighPass::filter_signal(0.7, fs, &x).unwrap();
    let a = StepAnalysis::analyze(&y[150..270], fs, &cfg).unwrap();
    assert!(!a.is_walking(&cfg, Some(1.0)) && a.is_walking(&cfg, Some(20.0)));
}

fn walk(seed: u64, duration: f64) -> (Vec<TimedPose>, rgbid::synth::trajectory::WalkingParams) {
    let spec = &standard_sequences(duration)[0];
    let scene = Scene::preset("office", seed).unwrap();
    let traj = Trajectory::walking(&scene, spec.params.clone(), duration, seed);
    (
        traj.sample((duration * 30.0) as usize, 30.0, 0.0),
        spec.params.clone(),
    )
}

#[test]
fn live_scale_reports_the_offline_sections_as_they_close() {
    // A standing start (the head sequence stands from 16 to 24 s; start at 18 s), then walking.
    let (gt, _) = walk(6, 40.0);
    let run = emulate_monocular(
        &gt,
        &DriftModel {
            initial_scale: 0.6,
            seed: 6,
            ..DriftModel::default()
        },
    );
    let est: Vec<TimedPose> = run.est[18 * 30..].to_vec();
    let mut cfg = DynScaleConfig::new(1.80, 30.0);
    cfg.filter.particles = 1000;
    let offline = DynScale::new(cfg.clone()).unwrap().run(&est).unwrap();
    let mut live = LiveDynScale::new(cfg.clone()).unwrap();
    let mut reported = Vec::new();
    let mut first_scale_at = None;
    for p in &est {
        let closed = live.push(*p).unwrap();
        if first_scale_at.is_none() && live.scale().is_some_and(f64::is_finite) {
            first_scale_at = Some(p.timestamp);
        }
        reported.extend(closed);
    }
    // Every section is reported once, in order, with the offline flags; once a scale exists
    // it is the offline one, bit for bit.
    let full: Vec<_> = offline
        .sections
        .iter()
        .filter(|s| reported.iter().any(|r| r.t_end == s.t_end))
        .collect();
    assert!(reported.len() >= 15, "{} sections", reported.len());
    assert_eq!(full.len(), reported.len());
    for (r, o) in reported.iter().zip(&full) {
        assert_eq!(r.walking, o.walking, "at {} s", r.t_end);
        if r.scale.is_finite() && r.walking {
            assert_eq!(r.scale, o.scale, "at {} s", r.t_end);
        }
    }
    // Standing for 6 s: no scale before walking starts (24 s).
    let first = first_scale_at.unwrap();
    assert!(
        first > 24.0 && first < 24.0 + 6.0,
        "first scale at {first} s"
    );
    assert!(live.scaled_pose().is_some());
    // Bad input is an error, not a panic, and the estimator keeps its state.
    let last = *est.last().unwrap();
    assert!(matches!(live.push(last), Err(ScaleError::BadTimestamps(_))));
}

#[test]
#[ignore = "known gap: the online up axis is 5.9 deg off on this walk (target 5 deg)"]
fn known_gap_live_scale_finds_the_up_axis_online_with_a_bounded_grid() {
    // The estimate's world is its first camera, so gravity is not along any of its axes.
    let (gt, _) = walk(3, 60.0);
    let run = emulate_monocular(
        &gt,
        &DriftModel {
            initial_scale: 2.5,
            seed: 3,
            ..DriftModel::default()
        },
    );
    let mut cfg = DynScaleConfig::new(1.80, 30.0);
    cfg.filter.particles = 1000;
    cfg.up = UpAxis::Auto;
    let mut live = LiveDynScale::new(cfg.clone()).unwrap();
    let (mut held, mut causal) = (0, Vec::new());
    for p in &run.est {
        live.push(*p).unwrap();
        held = held.max(live.samples_held());
        if let Some(q) = live.scaled_pose() {
            causal.push((q, p.timestamp));
        }
    }
    // Up: the world's z in the first camera's frame; found, then held.
    let truth = gt[0].world_from_camera.rotation.inverse() * DVec3::Z;
    let up = live.up().expect("no up axis found");
    let angle = up.dot(truth).clamp(-1.0, 1.0).acos().to_degrees();
    assert!(angle < 5.0, "up {up:?} is {angle:.1} deg from {truth:?}");
    // The grid held is bounded by the windows (8 s frequency window + 2 updates + 1 s).
    assert!(held <= 330, "{held} samples held");
    // The final output beats the unscaled estimate, and a causal estimate exists for most of
    // the walk.
    let result = live.finish(&run.est).unwrap();
    let raw = rgbid::scale::arc_length_error(&gt, &run.est, 500, false).unwrap();
    let scaled = rgbid::scale::arc_length_error(&gt, &result.scaled, 500, false).unwrap();
    assert!(
        scaled.relative < 0.1 && scaled.relative < 0.5 * raw.relative,
        "scaled {:.3}, unscaled {:.3}",
        scaled.relative,
        raw.relative
    );
    assert!(
        causal.len() > run.est.len() / 2,
        "{} causal poses",
        causal.len()
    );
}

#[test]
fn constant_scale_is_recovered_on_a_generated_walk() {
    let (gt, params) = walk(4, 40.0);
    let truth = 0.37; // metres per SLAM unit
    let run = emulate_monocular(
        &gt,
        &DriftModel {
            initial_scale: truth,
            drift: 0.0,
            ..DriftModel::default()
        },
    );
    let mut cfg = DynScaleConfig::new(params.height, 30.0);
    cfg.filter.particles = 2000;
    let r = DynScale::new(cfg).unwrap().run(&run.est).unwrap();
    let walking: Vec<f64> = r
        .sections
        .iter()
        .filter(|s| s.walking)
        .map(|s| s.scale)
        .collect();
    assert!(
        walking.len() > 20,
        "only {} walking sections",
        walking.len()
    );
    let last = walking[walking.len() - 1];
    let med = rgbid::experiments::scale::median(&walking[5..]);
    assert!(
        (med / truth - 1.0).abs() < 0.04,
        "median scale {med} vs {truth}"
    );
    assert!(
        (last / truth - 1.0).abs() < 0.08,
        "final scale {last} vs {truth}"
    );
    // Scaled trajectory length matches the truth.
    let len = |v: &[TimedPose]| {
        v.windows(2)
            .map(|w| {
                (w[1].world_from_camera.translation - w[0].world_from_camera.translation).length()
            })
            .sum::<f64>()
    };
    let ratio = len(&r.scaled) / len(&gt);
    assert!((ratio - 1.0).abs() < 0.06, "scaled/true length {ratio}");
}

/// The whole chain on real monocular output: catadioptric images rendered along a head-worn
/// walk (1.6 then 2.0 steps/s, then standing), the monocular EKF, then dynScale.
#[test]
fn monocular_ekf_walk_gives_step_frequency_stops_and_metric_scale() {
    let spec = &standard_sequences(30.0)[0];
    let mut cfg = ExperimentConfig {
        estimator: Estimator::Monocular(MonoEstimator {
            size: 320,
            ..MonoEstimator::default()
        }),
        ..ExperimentConfig::default()
    };
    cfg.dynscale.filter.particles = 2000;
    let r = run_sequence(spec, 0, &cfg).unwrap();
    let n = r.frequency_errors.len();
    assert!(n >= 6, "{n} steady windows");
    let within = r.frequency_errors.iter().filter(|e| **e < 0.05).count();
    assert!(
        within as f64 >= 0.9 * n as f64,
        "{within}/{n} within 0.05 Hz: {:?}",
        r.frequency_errors
    );
    assert!(
        r.stop_windows.0 >= 2 && r.stop_windows.1 == r.stop_windows.0,
        "stops {:?}",
        r.stop_windows
    );
    assert!(
        r.walk_windows.1 * 5 <= r.walk_windows.0,
        "false stops {:?}",
        r.walk_windows
    );
    // Metric error (rigid alignment): the unscaled estimate is off by its unknown unit;
    // dynScale recovers the metric path (its error is then dominated by the EKF's own shape
    // errors, so the gain is smaller than with emulated drift), and loop closure on top of
    // it halves the error of loop closure alone.
    let (un, sim3, dy, both) = (&r.metric[0], &r.metric[1], &r.metric[2], &r.metric[3]);
    assert!(
        dy.relative < un.relative,
        "dynScale {} vs unscaled {}",
        dy.relative,
        un.relative
    );
    assert!(
        both.relative < 0.5 * sim3.relative,
        "dynScale+optimSim3 {} vs optimSim3 {}",
        both.relative,
        sim3.relative
    );
    let len_ratio = dy.est_length / dy.gt_length;
    assert!(
        (len_ratio - 1.0).abs() < 0.15,
        "dynScale length ratio {len_ratio}"
    );
}

#[test]
fn local_scale_of_a_scaled_copy_is_its_scale_and_standing_takes_the_nearest() {
    // Ground truth walks 1 m/s along x for 4 s, stands 4 s, walks 4 s; the estimate is the
    // same path in units of 0.5 m.
    let pose = |t: f64, x: f64| TimedPose {
        timestamp: t,
        world_from_camera: Se3::new(DQuat::IDENTITY, DVec3::new(x, 0.0, 0.0)),
    };
    let xs = |t: f64| {
        if t < 4.0 {
            t
        } else if t < 8.0 {
            4.0
        } else {
            t - 4.0
        }
    };
    let ts: Vec<f64> = (0..360).map(|i| i as f64 / 30.0).collect();
    let gt: Vec<TimedPose> = ts.iter().map(|&t| pose(t, xs(t))).collect();
    let est: Vec<TimedPose> = ts.iter().map(|&t| pose(t, xs(t) / 0.5)).collect();
    let s = local_scale(&gt, &est, 2.0).unwrap();
    assert!(s.iter().all(|v| (v - 0.5).abs() < 1e-9), "{:?}", &s[..5]);
    assert!(matches!(
        local_scale(&gt[..1], &est[..1], 2.0),
        Err(ScaleError::InvalidParameter { .. })
    ));
    let still: Vec<TimedPose> = ts.iter().map(|&t| pose(t, 0.0)).collect();
    assert!(matches!(
        local_scale(&still, &still, 2.0),
        Err(ScaleError::NoWalking { .. })
    ));
}

#[test]
fn head_walk_with_drift_beats_unscaled_and_finds_frequency_and_stops() {
    let spec = &standard_sequences(48.0)[0];
    let mut cfg = ExperimentConfig::default();
    cfg.dynscale.filter.particles = 2000;
    let r = run_sequence(spec, 2, &cfg).unwrap();
    let n = r.frequency_errors.len();
    assert!(n > 10, "{n} steady windows");
    let within = r.frequency_errors.iter().filter(|e| **e < 0.05).count();
    assert!(
        within as f64 >= 0.9 * n as f64,
        "{within}/{n} within 0.05 Hz: {:?}",
        r.frequency_errors
    );
    assert!(
        r.stop_windows.0 >= 2 && r.stop_windows.1 == r.stop_windows.0,
        "stops {:?}",
        r.stop_windows
    );
    assert!(
        r.walk_windows.1 * 10 <= r.walk_windows.0,
        "false stops {:?}",
        r.walk_windows
    );
    let (un, dy) = (&r.metric[0], &r.metric[2]);
    assert!(
        dy.relative < 0.5 * un.relative.max(0.02),
        "dynScale {} vs unscaled {}",
        dy.relative,
        un.relative
    );
    assert!(dy.relative < 0.1, "dynScale relative error {}", dy.relative);
}

#[test]
fn bad_inputs_give_clear_errors() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("bad.txt");
    std::fs::write(
        &p,
        "# t x y z qx qy qz qw\n0.0 0 0 0 0 0 0 1\n0.1 0 zero 0 0 0 0 1\n",
    )
    .unwrap();
    let e = read_tum(&p).unwrap_err().to_string();
    assert!(e.contains(":3:") && e.contains("not a number"), "{e}");
    std::fs::write(&p, "# nothing\n").unwrap();
    assert!(read_tum(&p).is_err());
    let ds = DynScale::new(DynScaleConfig::new(1.8, 30.0)).unwrap();
    assert!(matches!(ds.run(&[]), Err(ScaleError::TooShort { .. })));
    let pose = |t: f64| TimedPose {
        timestamp: t,
        world_from_camera: Se3::new(DQuat::IDENTITY, DVec3::ZERO),
    };
    let v = vec![pose(0.0), pose(1.0), pose(1.0)];
    assert!(matches!(ds.run(&v), Err(ScaleError::BadTimestamps(_))));
    let v: Vec<TimedPose> = (0..30).map(|k| pose(k as f64 / 30.0)).collect();
    assert!(matches!(ds.run(&v), Err(ScaleError::TooShort { .. })));
    // Long enough but never walking: the scale is unobservable.
    let v: Vec<TimedPose> = (0..300).map(|k| pose(k as f64 / 30.0)).collect();
    assert!(
        matches!(ds.run(&v), Err(ScaleError::NoWalking { .. })),
        "{:?}",
        ds.run(&v).err()
    );
    assert!(DynScale::new(DynScaleConfig {
        window: 0.1,
        ..DynScaleConfig::new(1.8, 30.0)
    })
    .is_err());
    assert!(rgbid::scale::UpAxis::parse("w").is_err());
}

#[test]
fn recursive_scaling_is_continuous_and_landmarks_follow_their_anchor() {
    let (gt, params) = walk(6, 30.0);
    let run = emulate_monocular(
        &gt,
        &DriftModel {
            initial_scale: 2.0,
            drift: 0.05,
            ..DriftModel::default()
        },
    );
    let mut cfg = DynScaleConfig::new(params.height, 30.0);
    cfg.filter.particles = 1000;
    cfg.up = rgbid::scale::UpAxis::parse("auto").unwrap();
    let r = DynScale::new(cfg).unwrap().run(&run.est).unwrap();
    // The plane-fit up axis is close to the first camera's -y (pitch ~0.1 rad).
    let up = DVec3::from_array(r.up);
    assert!(up.dot(DVec3::NEG_Y).abs() > 0.97, "up {up:?}");
    for w in r.sections.windows(2) {
        let t = w[1].t_start;
        let p = rgbid::scale::interpolate_position(&run.est, t);
        let before = DVec3::from_array(w[0].origin_scaled)
            + w[0].scale * (p - DVec3::from_array(w[0].origin_raw));
        let after = r.scale_position(t + 1e-9, p);
        assert!(
            (before - after).length() < 1e-6,
            "jump at {t}: {before:?} vs {after:?}"
        );
    }
    let t = 12.3;
    let s = r.scale_at(t);
    let v = r.scale_velocity(t, DVec3::new(0.5, 0.0, 0.0));
    assert!((v.x - 0.5 * s).abs() < 1e-12);
    let x = DVec3::new(1.0, 2.0, 3.0);
    let a = r.scale_landmark(t, x);
    let b = r.scale_position(t, x);
    assert_eq!(a, b);
}

#[test]
fn longer_stationary_window_steadies_the_frequency_but_not_across_a_pace_change() {
    use rand::{Rng, SeedableRng};
    // Walk along x at 1.2 m/s; vertical bob (up = -y) of 2 cm at 1.6 steps/s for 30 s, then
    // 2.0 steps/s (phase continuous), plus white noise of 1.2 cm: a noisy estimate.
    let fs = 30.0;
    let mut rng = rand_pcg::Pcg64::seed_from_u64(7);
    let (mut phase, mut traj) = (0.0, Vec::new());
    for k in 0..(60.0 * fs) as usize {
        let t = k as f64 / fs;
        let f = if t < 30.0 { 1.6 } else { 2.0 };
        phase += f / fs;
        let y = -0.02 * (2.0 * PI * phase).cos()
            + 0.012 * (rng.random::<f64>() * 2.0 - 1.0) * 3f64.sqrt();
        traj.push(TimedPose {
            timestamp: t,
            world_from_camera: Se3::new(DQuat::IDENTITY, DVec3::new(1.2 * t, y, 0.0)),
        });
    }
    let run = |frequency_window: f64| {
        let mut cfg = DynScaleConfig::new(1.80, fs);
        cfg.frequency_window = frequency_window;
        DynScale::new(cfg).unwrap().run(&traj).unwrap()
    };
    let errors = |r: &rgbid::scale::DynScaleResult| -> Vec<f64> {
        r.sections
            .iter()
            .filter(|s| s.walking && s.t_end - s.window_start > 3.9)
            .filter(|s| s.window_start >= 30.0 || s.t_end <= 30.0)
            .map(|s| (s.analysis.frequency - if s.t_end <= 30.0 { 1.6 } else { 2.0 }).abs())
            .collect()
    };
    let (plain, long) = (run(0.0), run(8.0));
    let (e4, e6) = (errors(&plain), errors(&long));
    assert!(
        e4.len() > 40 && e6.len() == e4.len(),
        "{} {}",
        e4.len(),
        e6.len()
    );
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    assert!(
        mean(&e6) < 0.8 * mean(&e4),
        "up to 8 s: mean error {:.4} Hz against {:.4} Hz with 4 s",
        mean(&e6),
        mean(&e4)
    );
    assert!(plain.sections.iter().all(|s| s.frequency_span < 4.1));
    let used = long
        .sections
        .iter()
        .filter(|s| s.frequency_span > 5.9)
        .count();
    assert!(used > 30, "long window used in {used} windows");
    // Windows whose long span could cross the change must not be pulled towards the old pace.
    for s in long
        .sections
        .iter()
        .filter(|s| s.walking && s.t_end > 31.0 && s.t_end < 38.5)
    {
        assert!(
            (s.analysis.frequency - 2.0).abs() < 0.08 || s.window_start < 30.0,
            "window ending {:.1} s (span {} s): {:.3} Hz",
            s.t_end,
            s.frequency_span,
            s.analysis.frequency
        );
    }
}

/// The online chain (Algorithm 1 beside the EKF): a head-worn catadioptric walk along a
/// corridor, the EKF and the live scale estimation frame by frame. The final metric output,
/// placed on the ground truth at the start and never rescaled (eq. 3.36 as the thesis scores
/// walks), must beat the unscaled EKF, with the path length right within 15 %.
#[test]
fn metric_mono_scales_a_walk_online_and_beats_the_unscaled_filter() {
    use rgbid::experiments::mono::{render, SyntheticCamera, SyntheticSpec};
    use rgbid::mono::{MetricMono, MonoConfig, PatchMode};
    use rgbid::scale::{arc_length_error_from_start, WalkingModel};
    let mut spec = SyntheticSpec::new(SyntheticCamera::Catadioptric, 200, 200, 600);
    spec.scene = "corridor".into();
    spec.trajectory = "walk-head".into();
    let frames = render(&spec).unwrap();
    let mono = MonoConfig {
        patch_mode: PatchMode::Warped,
        ..MonoConfig::default()
    };
    let scale = DynScaleConfig {
        model: WalkingModel::grieve(1.75),
        up: UpAxis::Auto,
        ..DynScaleConfig::default()
    };
    let mut system = MetricMono::new(frames.camera, mono, scale).unwrap();
    let mut closed = 0;
    for (t, img) in &frames.images {
        closed += system.process(*t, img).unwrap().closed.len();
    }
    let run = system.finish();
    assert_eq!(run.unscaled.len(), 600);
    assert!(closed >= 10, "{closed} sections closed online");
    assert!(!run.causal.is_empty(), "no causal metric pose");
    let scaled = run.scaled.unwrap();
    let gt = &frames.ground_truth;
    let unscaled = arc_length_error_from_start(gt, &run.unscaled, 500).unwrap();
    let metric = arc_length_error_from_start(gt, &scaled.scaled, 500).unwrap();
    assert!(
        metric.relative < unscaled.relative,
        "metric {} vs unscaled {}",
        metric.relative,
        unscaled.relative
    );
    let ratio = metric.est_length / metric.gt_length;
    assert!((ratio - 1.0).abs() < 0.15, "length ratio {ratio}");
}
