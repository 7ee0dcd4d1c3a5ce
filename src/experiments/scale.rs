//! The tables 3.1-3.4 analogues on generated walking sequences.
//!
//! For each sequence (head / chest mount with pace changes and stops, frequent stops, stairs)
//! and seed: the ground truth comes from [`crate::synth::Trajectory::walking`] at `fps`; the
//! monocular estimate either from [`emulate_monocular`] (pose noise, unknown global scale
//! drawn log-uniformly in [0.2, 5] metres per unit, log-scale random walk) or, with
//! [`Estimator::Monocular`], from the monocular EKF ([`crate::mono::MonoSlam`]) run on the
//! catadioptric images the generator renders along the walk (its own scale drift; the same
//! random global unit is applied on top). Then four variants are
//! evaluated on keyframes (every `keyframe_stride`-th frame) by normalised arc length:
//! `unscaled` (the estimate), `optimSim3` (loop closure only), `dynScale` (Algorithm 1) and
//! `dynScale+optimSim3` (loop closure on the rescaled estimate, keeping its metric scale by
//! weak per-second scale priors). Also measured: step
//! frequency error in windows of steady walking, stop detection, and the scale error of each
//! walking section against the true local scale (geometric mean over its window).

use std::sync::Arc;

use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;

use crate::camera::UnifiedCamera;
use crate::geometry::Se3;
use crate::mono::{MonoConfig, MonoSlam};
use crate::scale::drift::{emulate_monocular, DriftModel, EmulatedRun};
use crate::scale::dynscale::{DynScale, DynScaleConfig, DynScaleResult};
use crate::scale::loops::{detect_loops_from_ground_truth, optim_sim3, LoopConfig};
use crate::scale::metric::{arc_length_error, ArcLengthError};
use crate::scale::ScaleError;
use crate::synth::trajectory::{Mount, PaceSegment, WalkingParams};
use crate::synth::Trajectory;
use crate::synth::{
    CameraModel, RenderBackend, Scene, SceneParams, SensorModel, Sequence, SequenceConfig,
};
use crate::trajectory::TimedPose;

/// A generated walking sequence.
#[derive(Clone, Debug)]
pub struct SequenceSpec {
    /// Short name (`head`, `chest`, `stops`, `stairs`).
    pub name: String,
    /// Walking parameters (height, model, mount, schedule, stairs).
    pub params: WalkingParams,
    /// Duration, seconds.
    pub duration: f64,
}

fn pace(schedule: &[(f64, f64)]) -> Vec<PaceSegment> {
    schedule
        .iter()
        .map(|&(duration, frequency)| PaceSegment {
            duration,
            frequency,
        })
        .collect()
}

/// The standard set: `head` and `chest` (paces 1.6, 2.0, stop, 1.3, 1.8 steps/s, 8 s each),
/// `stops` (head, 1.7 steps/s with 6 s stops every 8 s), `stairs` (head, 1.6 steps/s, 12
/// risers of 0.17 m from 30 % of the duration). Walker height 1.80 m, Grieve's model.
pub fn standard_sequences(duration: f64) -> Vec<SequenceSpec> {
    let base = WalkingParams {
        height: 1.80,
        schedule: pace(&[(8.0, 1.6), (8.0, 2.0), (8.0, 0.0), (8.0, 1.3), (8.0, 1.8)]),
        ..WalkingParams::default()
    };
    vec![
        SequenceSpec {
            name: "head".into(),
            params: base.clone(),
            duration,
        },
        SequenceSpec {
            name: "chest".into(),
            params: WalkingParams {
                mount: Mount::Chest,
                ..base.clone()
            },
            duration,
        },
        SequenceSpec {
            name: "stops".into(),
            params: WalkingParams {
                schedule: pace(&[(8.0, 1.7), (6.0, 0.0)]),
                ..base.clone()
            },
            duration,
        },
        SequenceSpec {
            name: "stairs".into(),
            params: WalkingParams {
                schedule: pace(&[(1e9, 1.6)]),
                stairs: Some((0.3 * duration, 12, 0.17)),
                ..base
            },
            duration,
        },
    ]
}

/// Sequences run only when named: `flights` (head, 2.0 steps/s, 60 risers of 0.17 m from the
/// start, so that the first windows have no scale to predict the step frequency from; the
/// legs lift the body unequally: a 0.05 m oscillation at the stride frequency while climbing,
/// 1.0 Hz, inside the feasible band and stronger than the step's).
/// Walker height 1.80 m, Grieve's model.
pub fn extra_sequences(duration: f64) -> Vec<SequenceSpec> {
    vec![SequenceSpec {
        name: "flights".into(),
        params: WalkingParams {
            height: 1.80,
            schedule: pace(&[(1e9, 2.0)]),
            stairs: Some((0.0, 60, 0.17)),
            stride_bob: 0.05,
            ..WalkingParams::default()
        },
        duration,
    }]
}

/// Where the monocular estimate of a walk comes from.
#[derive(Clone, Debug)]
pub enum Estimator {
    /// Ground truth with emulated drift ([`ExperimentConfig::drift`]).
    Emulated,
    /// The monocular EKF on rendered catadioptric images.
    Monocular(MonoEstimator),
}

/// Settings of [`Estimator::Monocular`].
#[derive(Clone, Debug)]
pub struct MonoEstimator {
    /// Side of the square catadioptric image ([`UnifiedCamera::catadioptric`]), pixels.
    pub size: u32,
    /// The filter's settings.
    pub config: MonoConfig,
    /// Kinect-like sensor noise on the rendered images (false: noiseless).
    pub noise: bool,
}

impl Default for MonoEstimator {
    fn default() -> Self {
        MonoEstimator {
            size: 400,
            config: MonoConfig::default(),
            noise: true,
        }
    }
}

/// Settings of one experiment run.
#[derive(Clone, Debug)]
pub struct ExperimentConfig {
    /// Source of the monocular estimate.
    pub estimator: Estimator,
    /// Frame rate, frames per second.
    pub fps: f64,
    /// Keyframe stride for the pose graph and the error metric.
    pub keyframe_stride: usize,
    /// Scene preset whose free area the walker circles.
    pub scene: String,
    /// Drift model (its `initial_scale` and `seed` are replaced per seed).
    pub drift: DriftModel,
    /// Loop closures.
    pub loops: LoopConfig,
    /// Dynamic scale settings (the walking model's height is taken from the sequence unless
    /// `keep_model` is set).
    pub dynscale: DynScaleConfig,
    /// Use `dynscale.model` as is (sensitivity runs).
    pub keep_model: bool,
    /// Points of the arc-length error.
    pub samples: usize,
}

impl Default for ExperimentConfig {
    fn default() -> Self {
        ExperimentConfig {
            estimator: Estimator::Emulated,
            fps: 30.0,
            keyframe_stride: 3,
            scene: "office".into(),
            drift: DriftModel::default(),
            loops: LoopConfig::default(),
            dynscale: DynScaleConfig::new(1.80, 30.0),
            keep_model: false,
            samples: 1000,
        }
    }
}

/// The variants compared, in table order.
pub const METHODS: [&str; 4] = ["unscaled", "optimSim3", "dynScale", "dynScale+optimSim3"];

/// Results of one sequence and seed.
#[derive(Clone, Debug)]
pub struct RunReport {
    /// Sequence name.
    pub sequence: String,
    /// Seed.
    pub seed: u64,
    /// The unknown global scale of the estimate at its first frame, metres per unit.
    pub initial_scale: f64,
    /// Number of loop closures.
    pub loops: usize,
    /// Per method (order of [`METHODS`]): metric error (rigid alignment).
    pub metric: Vec<ArcLengthError>,
    /// Per method: shape error (similarity alignment).
    pub shape: Vec<ArcLengthError>,
    /// |f_est - f_true| in windows of steady walking, Hz.
    pub frequency_errors: Vec<f64>,
    /// Windows at least 75 % standing, and how many were detected as not walking.
    pub stop_windows: (usize, usize),
    /// Windows entirely walking, and how many were wrongly detected as standing.
    pub walk_windows: (usize, usize),
    /// |s_est / s_true - 1| per walking section.
    pub scale_errors: Vec<f64>,
    /// The dynScale result (sections, scaled trajectory).
    pub dynscale: DynScaleResult,
    /// Emulated run (ground truth, estimate, true scales).
    pub run: EmulatedRun,
    /// True step frequency over time `(t, f)` at 10 Hz.
    pub true_frequency: Vec<(f64, f64)>,
}

/// Runs one sequence with one seed: [`estimate_sequence`] then [`evaluate_run`].
pub fn run_sequence(
    spec: &SequenceSpec,
    seed: u64,
    cfg: &ExperimentConfig,
) -> Result<RunReport, ScaleError> {
    let run = estimate_sequence(spec, seed, cfg, &mut |_, _| {})?;
    evaluate_run(spec, seed, run, cfg)
}

/// The ground truth and the monocular estimate of one sequence and seed (by
/// [`ExperimentConfig::estimator`]). `progress(frame, frames)` is called per frame by the
/// monocular estimator.
pub fn estimate_sequence(
    spec: &SequenceSpec,
    seed: u64,
    cfg: &ExperimentConfig,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<EmulatedRun, ScaleError> {
    let scene_error = |e: crate::synth::SynthError| ScaleError::InvalidParameter {
        name: "scene",
        why: e.to_string(),
    };
    let mut scene_params = SceneParams::preset(&cfg.scene).map_err(scene_error)?;
    if let Some((_, steps, rise)) = spec.params.stairs {
        // The scenes have no stairs: raise the ceiling by the climb so that the camera stays
        // inside the room (the rendered images of a walker climbing through the ceiling
        // would be meaningless to the monocular estimator).
        scene_params.size[2] += steps as f64 * rise;
    }
    let scene = Scene::generate(&scene_params, seed).map_err(scene_error)?;
    let traj = Trajectory::walking(&scene, spec.params.clone(), spec.duration, seed);
    let frames = (spec.duration * cfg.fps).floor() as usize;
    let mut rng = Pcg64::seed_from_u64(seed ^ 0x51ca);
    let initial_scale = 10f64.powf(rng.random_range(-0.7..0.7));
    match &cfg.estimator {
        Estimator::Emulated => {
            let gt = traj.sample(frames, cfg.fps, 0.0);
            let drift = DriftModel {
                initial_scale,
                seed,
                ..cfg.drift.clone()
            };
            Ok(emulate_monocular(&gt, &drift))
        }
        Estimator::Monocular(m) => {
            let run = monocular_run(scene, traj, frames, cfg.fps, seed, m, progress)?;
            // A random unit on top of the filter's own (its nominal scale is set by the
            // initial inverse depth): the scale must be found, not assumed.
            let unit = initial_scale / run.true_scale[0];
            Ok(EmulatedRun {
                est: run
                    .est
                    .iter()
                    .map(|p| TimedPose {
                        timestamp: p.timestamp,
                        world_from_camera: Se3::new(
                            p.world_from_camera.rotation,
                            p.world_from_camera.translation / unit,
                        ),
                    })
                    .collect(),
                true_scale: run.true_scale.iter().map(|s| s * unit).collect(),
                gt: run.gt,
            })
        }
    }
}

/// Renders `frames` catadioptric images along `traj` and runs the monocular EKF on them.
/// The true local scale of each estimated pose is measured against the ground truth by
/// [`local_scale`].
fn monocular_run(
    scene: Scene,
    traj: Trajectory,
    frames: usize,
    fps: f64,
    seed: u64,
    m: &MonoEstimator,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<EmulatedRun, ScaleError> {
    let camera = UnifiedCamera::catadioptric(m.size, m.size);
    let config = SequenceConfig {
        frames,
        fps,
        start_time: 0.0,
        sensor: if m.noise {
            SensorModel::kinect()
        } else {
            SensorModel::noiseless()
        },
        seed,
        exposure_changes: false,
        motion_blur: 0,
        exposure_time: 1.0 / 60.0,
    };
    let mono_err = |what: String| ScaleError::Monocular(what);
    let mut seq = Sequence::new(
        Arc::new(scene),
        CameraModel::Unified(camera),
        traj,
        config,
        &RenderBackend::Cpu,
    )
    .map_err(|e| mono_err(format!("renderer: {e}")))?;
    let mut slam = MonoSlam::new(camera, m.config.clone()).map_err(|e| mono_err(e.to_string()))?;
    let (mut gt, mut est) = (Vec::with_capacity(frames), Vec::with_capacity(frames));
    for i in 0..frames {
        let f = seq
            .render_frame(i)
            .map_err(|e| mono_err(format!("rendering frame {i}: {e}")))?;
        let r = slam
            .process(f.timestamp, &f.frame.intensity)
            .map_err(|e| mono_err(format!("frame {i} ({:.2} s): {e}", f.timestamp)))?;
        gt.push(TimedPose {
            timestamp: f.timestamp,
            world_from_camera: f.world_from_camera,
        });
        est.push(TimedPose {
            timestamp: f.timestamp,
            world_from_camera: r.world_from_camera,
        });
        progress(i + 1, frames);
    }
    let true_scale = local_scale(&gt, &est, 2.0)?;
    Ok(EmulatedRun {
        gt,
        est,
        true_scale,
    })
}

/// The local scale of an estimate, metres per estimate unit, at each pose: the ground truth's
/// path length over the estimate's within `half_window` seconds either side, both measured
/// on positions 0.5 s apart (so that per-frame noise does not add length). Poses whose window
/// moves less than 0.3 m (standing) take the value of the nearest pose that moved.
pub fn local_scale(
    gt: &[TimedPose],
    est: &[TimedPose],
    half_window: f64,
) -> Result<Vec<f64>, ScaleError> {
    if gt.len() != est.len() || gt.len() < 2 {
        return Err(ScaleError::InvalidParameter {
            name: "trajectories",
            why: format!(
                "need two equally long trajectories of >= 2 poses (gt {}, est {})",
                gt.len(),
                est.len()
            ),
        });
    }
    let n = gt.len();
    let t = |k: usize| gt[k].timestamp;
    let path = |v: &[TimedPose], a: usize, b: usize| {
        let (mut len, mut last) = (0.0, a);
        for k in a + 1..=b {
            if t(k) - t(last) >= 0.5 || k == b {
                len += (v[k].world_from_camera.translation - v[last].world_from_camera.translation)
                    .length();
                last = k;
            }
        }
        len
    };
    let (mut a, mut b) = (0usize, 0usize);
    let mut raw: Vec<Option<f64>> = Vec::with_capacity(n);
    for k in 0..n {
        while t(k) - t(a) > half_window {
            a += 1;
        }
        while b + 1 < n && t(b + 1) - t(k) <= half_window {
            b += 1;
        }
        let (lg, le) = (path(gt, a, b), path(est, a, b));
        raw.push((lg >= 0.3 && le > 1e-12 && (lg / le).is_finite()).then(|| lg / le));
    }
    if raw.iter().all(Option::is_none) {
        return Err(ScaleError::NoWalking { windows: n });
    }
    // Fill the standing poses from the nearest moving pose (earlier one on ties).
    let mut prev: Vec<Option<(usize, f64)>> = Vec::with_capacity(n);
    let mut last = None;
    for (k, r) in raw.iter().enumerate() {
        if let Some(v) = r {
            last = Some((k, *v));
        }
        prev.push(last);
    }
    let mut out = vec![0.0; n];
    let mut next: Option<(usize, f64)> = None;
    for k in (0..n).rev() {
        if let Some(v) = raw[k] {
            next = Some((k, v));
        }
        out[k] = match (prev[k], next) {
            (Some((i, v)), Some((j, w))) => {
                if k - i <= j - k {
                    v
                } else {
                    w
                }
            }
            (Some((_, v)), None) | (None, Some((_, v))) => v,
            (None, None) => 1.0,
        };
    }
    Ok(out)
}

/// Evaluates one estimated run of `spec` (the four variants, frequency, stops, scale).
pub fn evaluate_run(
    spec: &SequenceSpec,
    seed: u64,
    run: EmulatedRun,
    cfg: &ExperimentConfig,
) -> Result<RunReport, ScaleError> {
    let initial_scale = run.true_scale.first().copied().unwrap_or(f64::NAN);
    let mut dcfg = cfg.dynscale.clone();
    dcfg.fps = cfg.fps;
    dcfg.seed = seed ^ 0xf11e;
    if !cfg.keep_model {
        dcfg.model.height = spec.params.height;
    }
    let dyn_result = DynScale::new(dcfg.clone())?.run(&run.est)?;

    // Keyframes of every variant.
    let kf: Vec<usize> = (0..run.est.len())
        .step_by(cfg.keyframe_stride.max(1))
        .collect();
    let pick = |v: &[TimedPose]| -> Vec<TimedPose> { kf.iter().map(|&k| v[k]).collect() };
    let gt_kf = pick(&run.gt);
    let est_kf = pick(&run.est);
    let dyn_kf = pick(&dyn_result.scaled);
    let scale_kf: Vec<f64> = kf.iter().map(|&k| run.true_scale[k]).collect();
    let dyn_scale_kf: Vec<f64> = kf
        .iter()
        .map(|&k| run.true_scale[k] / dyn_result.scale_at(run.est[k].timestamp))
        .collect();
    let loops = detect_loops_from_ground_truth(&gt_kf, &cfg.loops);
    let sim3 = optim_sim3(&est_kf, &gt_kf, &scale_kf, &loops, &cfg.loops, None)?;
    let dyn_sim3 = optim_sim3(
        &dyn_kf,
        &gt_kf,
        &dyn_scale_kf,
        &loops,
        &cfg.loops,
        Some(0.05),
    )?;
    let variants = [&est_kf, &sim3, &dyn_kf, &dyn_sim3];
    let mut metric = Vec::new();
    let mut shape = Vec::new();
    for v in variants {
        metric.push(arc_length_error(&gt_kf, v, cfg.samples, false)?);
        shape.push(arc_length_error(&gt_kf, v, cfg.samples, true)?);
    }

    // Frequency, stops and scale per section (windows of full length only).
    let p = &spec.params;
    let (mut freq_err, mut stops, mut walks, mut scale_err) =
        (Vec::new(), (0, 0), (0, 0), Vec::new());
    for s in &dyn_result.sections {
        if s.t_end - s.window_start < dcfg.window * 0.95 {
            continue;
        }
        let truth = WindowTruth::of(p, s.window_start, s.t_end, cfg.fps);
        if truth.standing >= 0.75 {
            stops.0 += 1;
            stops.1 += usize::from(!s.walking);
        }
        if truth.min > 0.0 {
            walks.0 += 1;
            walks.1 += usize::from(!s.walking);
            if s.walking && truth.max - truth.min < 0.02 {
                freq_err.push((s.analysis.frequency - truth.mean).abs());
            }
        }
        if s.walking && s.consistent {
            let i0 = ((s.window_start - run.est[0].timestamp) * cfg.fps).round() as usize;
            let i1 = (((s.t_end - run.est[0].timestamp) * cfg.fps).round() as usize)
                .min(run.true_scale.len() - 1);
            let ln_mean =
                run.true_scale[i0..=i1].iter().map(|v| v.ln()).sum::<f64>() / (i1 + 1 - i0) as f64;
            scale_err.push((s.scale / ln_mean.exp() - 1.0).abs());
        }
    }
    let true_frequency = (0..(spec.duration * 10.0) as usize)
        .map(|i| {
            let t = i as f64 / 10.0;
            (t, p.frequency_at(t))
        })
        .collect();
    Ok(RunReport {
        sequence: spec.name.clone(),
        seed,
        initial_scale,
        loops: loops.len(),
        metric,
        shape,
        frequency_errors: freq_err,
        stop_windows: stops,
        walk_windows: walks,
        scale_errors: scale_err,
        dynscale: dyn_result,
        run,
        true_frequency,
    })
}

/// The true step frequency over an analysis window, sampled at `fps` from `window_start` to
/// `t_end` (seconds): mean, minimum and maximum (steps/s, 0 while standing) and the share of
/// samples standing.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct WindowTruth {
    /// Mean frequency, Hz.
    pub mean: f64,
    /// Lowest frequency, Hz.
    pub min: f64,
    /// Highest frequency, Hz.
    pub max: f64,
    /// Share of the samples with the walker standing, in [0, 1].
    pub standing: f64,
}

impl WindowTruth {
    /// Samples `params.frequency_at` over `[window_start, t_end]` at `fps`.
    pub fn of(params: &WalkingParams, window_start: f64, t_end: f64, fps: f64) -> WindowTruth {
        let n = ((t_end - window_start) * fps).round().max(0.0) as usize + 1;
        let f: Vec<f64> = (0..n)
            .map(|i| params.frequency_at(window_start + i as f64 / fps))
            .collect();
        WindowTruth {
            mean: f.iter().sum::<f64>() / n as f64,
            min: f.iter().cloned().fold(f64::INFINITY, f64::min),
            max: f.iter().cloned().fold(f64::NEG_INFINITY, f64::max),
            standing: f.iter().filter(|&&x| x <= 0.0).count() as f64 / n as f64,
        }
    }
}

/// Median of `v` (NaN when empty).
pub fn median(v: &[f64]) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    let n = s.len();
    if n % 2 == 1 {
        s[n / 2]
    } else {
        0.5 * (s[n / 2 - 1] + s[n / 2])
    }
}

/// Percentile `q` in [0, 1] of `v` (nearest rank; NaN when empty).
pub fn percentile(v: &[f64], q: f64) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    let k = ((q * s.len() as f64).ceil() as usize).clamp(1, s.len()) - 1;
    s[k]
}

/// First line of a run file written by [`save_run`].
const RUN_FILE_HEADER: &str = "# rgbid scale run v1";

/// Name of the cache file for the monocular estimate of `spec` with `seed` under `cfg`, or
/// `None` for [`Estimator::Emulated`] (recomputed in milliseconds, never cached). The name
/// holds everything the estimate depends on: sequence, seed, duration, frame rate, scene,
/// image size and sensor noise (the filter settings are the defaults).
pub fn run_cache_name(spec: &SequenceSpec, seed: u64, cfg: &ExperimentConfig) -> Option<String> {
    match &cfg.estimator {
        Estimator::Emulated => None,
        Estimator::Monocular(m) => Some(format!(
            "{}_seed{}_{}s_{}fps_{}_mono{}{}.txt",
            spec.name,
            seed,
            spec.duration,
            cfg.fps,
            cfg.scene,
            m.size,
            if m.noise { "" } else { "_noiseless" }
        )),
    }
}

/// Writes a run (ground truth, estimate and true local scale of every pose) losslessly to
/// `path`: a header line, then per pose `t gt(tx ty tz qx qy qz qw) est(...) true_scale`,
/// with shortest round-trip decimal numbers. [`load_run`] reads it back bit for bit.
pub fn save_run(path: &std::path::Path, run: &EmulatedRun) -> Result<(), ScaleError> {
    use std::io::Write;
    let err = |e: std::io::Error| ScaleError::Cache {
        path: path.into(),
        message: e.to_string(),
    };
    if run.gt.len() != run.est.len() || run.est.len() != run.true_scale.len() {
        return Err(ScaleError::Cache {
            path: path.into(),
            message: format!(
                "inconsistent run: {} ground-truth poses, {} estimates, {} scales",
                run.gt.len(),
                run.est.len(),
                run.true_scale.len()
            ),
        });
    }
    let mut f = std::io::BufWriter::new(std::fs::File::create(path).map_err(err)?);
    writeln!(f, "{RUN_FILE_HEADER}").map_err(err)?;
    for ((g, e), s) in run.gt.iter().zip(&run.est).zip(&run.true_scale) {
        let mut line = format!("{}", e.timestamp);
        for p in [&g.world_from_camera, &e.world_from_camera] {
            let (t, q) = (p.translation, p.rotation);
            for v in [t.x, t.y, t.z, q.x, q.y, q.z, q.w] {
                line.push_str(&format!(" {v}"));
            }
        }
        writeln!(f, "{line} {s}").map_err(err)?;
    }
    f.flush().map_err(err)
}

/// Reads a run written by [`save_run`]. Errors name the file and line (wrong header,
/// wrong field count, a field that is not a finite number, a quaternion that is not of unit
/// length, no poses).
pub fn load_run(path: &std::path::Path) -> Result<EmulatedRun, ScaleError> {
    let cache_err = |message: String| ScaleError::Cache {
        path: path.into(),
        message,
    };
    let text = std::fs::read_to_string(path).map_err(|e| cache_err(e.to_string()))?;
    let mut lines = text.lines();
    if lines.next() != Some(RUN_FILE_HEADER) {
        return Err(cache_err(format!(
            "line 1: not a run file (expected {RUN_FILE_HEADER:?})"
        )));
    }
    let mut run = EmulatedRun {
        gt: Vec::new(),
        est: Vec::new(),
        true_scale: Vec::new(),
    };
    for (i, line) in lines.enumerate() {
        let at = |m: String| cache_err(format!("line {}: {m}", i + 2));
        let v = line
            .split_whitespace()
            .map(|s| {
                s.parse::<f64>()
                    .ok()
                    .filter(|x| x.is_finite())
                    .ok_or_else(|| at(format!("{s:?} is not a finite number")))
            })
            .collect::<Result<Vec<f64>, _>>()?;
        if v.len() != 16 {
            return Err(at(format!("expected 16 numbers, found {}", v.len())));
        }
        let pose = |o: usize| -> Result<TimedPose, ScaleError> {
            let q = glam::DQuat::from_xyzw(v[o + 3], v[o + 4], v[o + 5], v[o + 6]);
            if (q.length() - 1.0).abs() > 1e-6 {
                return Err(at(format!(
                    "quaternion of length {} is not a rotation",
                    q.length()
                )));
            }
            // Stored as written (already unit length): renormalising would change the last bits.
            Ok(TimedPose {
                timestamp: v[0],
                world_from_camera: Se3 {
                    rotation: q,
                    translation: glam::DVec3::new(v[o], v[o + 1], v[o + 2]),
                },
            })
        };
        run.gt.push(pose(1)?);
        run.est.push(pose(8)?);
        run.true_scale.push(v[15]);
    }
    if run.est.is_empty() {
        return Err(cache_err("no poses".into()));
    }
    Ok(run)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn run_file_round_trips_bit_for_bit_and_rejects_bad_lines() {
        let spec = &standard_sequences(12.0)[0];
        let cfg = ExperimentConfig::default();
        assert!(run_cache_name(spec, 0, &cfg).is_none());
        let run = estimate_sequence(spec, 3, &cfg, &mut |_, _| {}).unwrap();
        let dir = std::env::temp_dir().join(format!("rgbid-runfile-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("run.txt");
        save_run(&path, &run).unwrap();
        let back = load_run(&path).unwrap();
        assert_eq!(back.est.len(), run.est.len());
        for (a, b) in back
            .est
            .iter()
            .zip(&run.est)
            .chain(back.gt.iter().zip(&run.gt))
        {
            assert_eq!(a.timestamp.to_bits(), b.timestamp.to_bits());
            assert_eq!(
                a.world_from_camera.translation,
                b.world_from_camera.translation
            );
            assert_eq!(a.world_from_camera.rotation, b.world_from_camera.rotation);
        }
        assert_eq!(back.true_scale, run.true_scale);

        let text = std::fs::read_to_string(&path).unwrap();
        let mut lines: Vec<&str> = text.lines().collect();
        lines[3] = "1.0 2.0 nan";
        std::fs::write(&path, lines.join("\n")).unwrap();
        let e = load_run(&path).unwrap_err().to_string();
        assert!(e.contains("line 4") && e.contains("run.txt"), "{e}");
        std::fs::write(&path, "0 1 2 3\n").unwrap();
        let e = load_run(&path).unwrap_err().to_string();
        assert!(e.contains("line 1: not a run file"), "{e}");
        std::fs::write(&path, format!("{RUN_FILE_HEADER}\n")).unwrap();
        assert!(load_run(&path)
            .unwrap_err()
            .to_string()
            .contains("no poses"));
        assert!(load_run(&dir.join("missing.txt")).is_err());
        std::fs::remove_dir_all(&dir).ok();
    }
}
