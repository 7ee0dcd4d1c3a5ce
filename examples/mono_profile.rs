//! Profiles the monocular EKF on a generated catadioptric walk against its ground truth.
//!
//! `cargo run --release --example mono_profile -- SCENE TRAJECTORY FRAMES [EVERY [LIMIT
//! [KEY=VALUE...]]]` renders the walk as `rgbid mono --synthetic omni` does (400 x 400,
//! seed 7) once, caches the frames with their true depth in
//! `/tmp/mono_profile_SCENE_TRAJECTORY_FRAMES.f32` (about 1 MB per frame), runs the filter
//! over the first LIMIT frames and prints every EVERY frames: the camera's heading error about
//! the world's up axis and that of the direction of travel over the last second (degrees), the
//! whole rotation error, the estimate's path length over the true one so far, the frame's
//! visible / matched / inlier / rescued / new landmarks, landmarks in the state and points
//! among them, the median and spread of `ln(estimated / true distance)` of the converged
//! landmarks (true distance from the depth at the initial pixel, estimate divided by the
//! path ratio), the share of converged landmarks, landmarks within 30 degrees of the
//! direction of travel (and points among them), the filter's own heading standard deviation
//! (degrees), the estimated and true yaw rates (degrees/s) and the visible landmarks left and
//! right of the direction of travel. `KEY=VALUE` sets a `MonoConfig` field (a JSON value).
//!
//! Environment: `METRIC=1` runs the `rgbid mono --walker-height 1.75 --loops` pipeline instead
//! and prints its eq. 3.36 errors, EKF Sim(3) ATE and filter time (`VARIANTS="k=v k=v;k=v"`:
//! one run per `;`-separated set of fields, e.g. RANSAC seeds); `NO_BLIND=1` renders and
//! tracks with the camera's central blind disc removed, a counterfactual that makes the
//! directions near the optical axis visible.

use std::collections::HashMap;
use std::io::{Read, Write};

use glam::{DVec2, DVec3};
use rgbid::experiments::mono::{SyntheticCamera, SyntheticSpec};
use rgbid::geometry::Se3;
use rgbid::image::ImageF32;
use rgbid::mono::{MonoConfig, MonoSlam, PatchMode};

struct Cached {
    images: Vec<(f64, ImageF32)>,
    depth: Vec<Vec<u16>>,
    gt: Vec<Se3>,
}

fn load_or_render(scene: &str, traj: &str, frames: usize) -> Cached {
    let blind = if no_blind() { "_noblind" } else { "" };
    let path = format!("/tmp/mono_profile_{scene}_{traj}_{frames}{blind}.f32");
    let (w, h) = (400usize, 400usize);
    if let Ok(mut f) = std::fs::File::open(&path) {
        let mut buf = Vec::new();
        f.read_to_end(&mut buf).unwrap();
        let mut off = 0;
        let mut rd = |n: usize| {
            let s = &buf[off..off + n];
            off += n;
            s.to_vec()
        };
        let mut images = Vec::new();
        let mut depth = Vec::new();
        let mut gt = Vec::new();
        for _ in 0..frames {
            let t = f64::from_le_bytes(rd(8).try_into().unwrap());
            let mut p = [0f64; 7];
            for v in &mut p {
                *v = f64::from_le_bytes(rd(8).try_into().unwrap());
            }
            let img: Vec<f32> = rd(4 * w * h)
                .chunks(4)
                .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                .collect();
            let d: Vec<u16> = rd(2 * w * h)
                .chunks(2)
                .map(|c| u16::from_le_bytes([c[0], c[1]]))
                .collect();
            images.push((t, ImageF32::from_vec(w, h, img).unwrap()));
            depth.push(d);
            gt.push(Se3::new(
                glam::DQuat::from_xyzw(p[3], p[4], p[5], p[6]),
                DVec3::new(p[0], p[1], p[2]),
            ));
        }
        return Cached { images, depth, gt };
    }
    use rgbid::synth::{
        RenderBackend, Scene, SensorModel, Sequence, SequenceConfig, Trajectory, TrajectoryKind,
    };
    use std::sync::Arc;
    // As rgbid::experiments::mono::render, keeping the true depth too.
    let mut spec = SyntheticSpec::new(SyntheticCamera::Catadioptric, 400, 400, frames);
    spec.scene = scene.into();
    spec.trajectory = traj.into();
    let sc = Arc::new(Scene::preset(&spec.scene, spec.seed).unwrap());
    let kind = TrajectoryKind::from_name(&spec.trajectory).unwrap();
    let config = SequenceConfig {
        frames: spec.frames,
        fps: spec.fps,
        start_time: 0.0,
        sensor: SensorModel::kinect(),
        seed: spec.seed,
        exposure_changes: false,
        motion_blur: 0,
        exposure_time: 1.0 / 60.0,
    };
    let trajectory = Trajectory::new(kind, &sc, config.duration(), spec.seed).unwrap();
    let model = rgbid::synth::CameraModel::Unified(profile_camera());
    let mut seq = Sequence::new(sc, model, trajectory, config, &RenderBackend::Cpu).unwrap();
    let mut out = std::io::BufWriter::new(std::fs::File::create(&path).unwrap());
    for i in 0..frames {
        let f = seq.render_frame(i).unwrap();
        let p = f.world_from_camera;
        out.write_all(&f.timestamp.to_le_bytes()).unwrap();
        for v in [
            p.translation.x,
            p.translation.y,
            p.translation.z,
            p.rotation.x,
            p.rotation.y,
            p.rotation.z,
            p.rotation.w,
        ] {
            out.write_all(&v.to_le_bytes()).unwrap();
        }
        for v in f.frame.intensity.data() {
            out.write_all(&v.to_le_bytes()).unwrap();
        }
        for &z in f.frame.true_depth.data() {
            let d = (z * 100.0).round().clamp(-32767.0, 32767.0) as i16 as u16;
            out.write_all(&d.to_le_bytes()).unwrap();
        }
    }
    drop(out);
    load_or_render(scene, traj, frames)
}

/// `NO_BLIND=1`: the catadioptric camera without its central blind disc (a counterfactual:
/// the directions near the optical axis become visible).
fn no_blind() -> bool {
    std::env::var("NO_BLIND").is_ok()
}

fn profile_camera() -> rgbid::camera::UnifiedCamera {
    let mut c = rgbid::camera::UnifiedCamera::catadioptric(400, 400);
    if no_blind() {
        c.inner_radius = None;
    }
    c
}

fn d_est_cam(e: &Se3, b: &Se3) -> DVec3 {
    e.translation - b.translation
}

fn yaw(v: DVec3) -> f64 {
    v.y.atan2(v.x)
}

fn wrap(a: f64) -> f64 {
    let mut a = a;
    while a > std::f64::consts::PI {
        a -= std::f64::consts::TAU;
    }
    while a < -std::f64::consts::PI {
        a += std::f64::consts::TAU;
    }
    a
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let scene = args.get(1).cloned().unwrap_or("hall".into());
    let traj = args.get(2).cloned().unwrap_or("walk-head".into());
    let frames: usize = args.get(3).and_then(|s| s.parse().ok()).unwrap_or(450);
    let every: usize = args.get(4).and_then(|s| s.parse().ok()).unwrap_or(15);
    let mut cfg = MonoConfig {
        patch_mode: PatchMode::Projective,
        ..MonoConfig::default()
    };
    let limit: usize = args.get(5).and_then(|s| s.parse().ok()).unwrap_or(frames);
    let mut json = serde_json::to_value(&cfg).unwrap();
    for kv in args.iter().skip(6) {
        let (k, v) = kv.split_once('=').unwrap();
        json[k] = serde_json::from_str(v).unwrap();
    }
    cfg = serde_json::from_value(json).unwrap();
    let t0 = std::time::Instant::now();
    let data = load_or_render(&scene, &traj, frames);
    eprintln!("frames ready in {:.1} s", t0.elapsed().as_secs_f64());
    let camera = profile_camera();
    if std::env::var("METRIC").is_ok() {
        let variants = std::env::var("VARIANTS").unwrap_or_default();
        if variants.is_empty() {
            metric(&data, camera, cfg, limit);
        } else {
            for v in variants.split(';') {
                let mut json = serde_json::to_value(&cfg).unwrap();
                for kv in v.split_whitespace() {
                    let (k, val) = kv.split_once('=').unwrap();
                    json[k] = serde_json::from_str(val).unwrap();
                }
                println!("--- variant [{v}]");
                metric(&data, camera, serde_json::from_value(json).unwrap(), limit);
            }
        }
        return;
    }
    let mut slam = MonoSlam::new(camera, cfg).unwrap();
    let g0 = data.gt[0];
    let mut est: Vec<Se3> = Vec::new();
    let mut true_range: HashMap<usize, f64> = HashMap::new();
    let mut ekf_ms = Vec::new();
    println!(
        "{:>6} {:>7} {:>7} {:>7} {:>6} {:>4} {:>4} {:>4} {:>4} {:>4} {:>4} {:>4} {:>6} {:>6} {:>6} {:>5} {:>5} {:>6} {:>6} {:>6} {:>4} {:>4}",
        "t", "yawErr", "trvErr", "rotErr", "scale", "vis", "mat", "inl", "res", "new", "lm", "pts",
        "lsMed", "lsMAD", "conv%", "fwd", "fwdP", "sigYaw", "wEst", "wGt", "left", "right"
    );
    let up0 = g0.rotation.conjugate() * DVec3::Z;
    for (k, (t, img)) in data.images.iter().enumerate().take(limit) {
        let tt = std::time::Instant::now();
        let r = slam.process(*t, img).unwrap();
        ekf_ms.push(tt.elapsed().as_secs_f64() * 1e3);
        est.push(r.world_from_camera);
        // True range of new landmarks at their initial pixel.
        let depth = &data.depth[k];
        for f in slam.features() {
            if true_range.contains_key(&f.id) {
                continue;
            }
            let Some(p) = f.landmark.predict(&camera, slam.state()) else {
                continue;
            };
            let (x, y) = (p.uv.x.round() as usize, p.uv.y.round() as usize);
            let z = depth[y * 400 + x] as i16 as f64 / 100.0;
            let ray = camera.unproject(DVec2::new(p.uv.x, p.uv.y));
            let range = match ray {
                Some(d) if d.z.abs() > 1e-6 && z != 0.0 => (d * (z / d.z)).length(),
                _ => f64::NAN,
            };
            true_range.insert(f.id, range);
        }
        if k % every != 0 || k == 0 {
            continue;
        }
        let gt = data.gt[k];
        let e = est[k];
        // Estimate in the GT world: g0 * e (rotation); positions up to scale.
        let r_est = g0.rotation * e.rotation;
        let fwd_est = r_est * DVec3::Z;
        let fwd_gt = gt.rotation * DVec3::Z;
        let yaw_err = wrap(yaw(fwd_est) - yaw(fwd_gt)).to_degrees();
        let rot_err =
            (2.0 * (r_est * gt.rotation.conjugate()).w.abs().min(1.0).acos()).to_degrees();
        // Direction of travel over the last second.
        let back = k.saturating_sub(30);
        let d_est = g0.rotation * (e.translation - est[back].translation);
        let d_gt = gt.translation - data.gt[back].translation;
        let trv_err = wrap(yaw(d_est) - yaw(d_gt)).to_degrees();
        // Scale so far: estimated path over true path.
        let path = |v: &[DVec3]| v.windows(2).map(|w| (w[1] - w[0]).length()).sum::<f64>();
        let pe: Vec<DVec3> = est.iter().map(|p| p.translation).collect();
        let pg: Vec<DVec3> = data.gt[..=k].iter().map(|p| p.translation).collect();
        let scale = path(&pe) / path(&pg).max(1e-9);
        // Landmarks: log of (estimated distance / true distance) of converged ones.
        let cov = slam.covariance();
        let mut ls = Vec::new();
        let mut conv = 0;
        let mut fwd = 0;
        let mut fwd_pts = 0;
        let travel_cam = e.rotation.conjugate() * (e.translation - est[back].translation);
        let travel_dir = travel_cam.normalize_or_zero();
        let nf = slam.features().len();
        for (i, f) in slam.features().iter().enumerate() {
            let o = 12 + 6 * i + 5;
            let sr = cov[(o, o)].max(0.0).sqrt();
            let rho = f.landmark.rho;
            let converged = rho > 0.0 && sr <= 0.1 * rho;
            if converged {
                conv += 1;
                if let Some(tr) = true_range.get(&f.id).filter(|v| v.is_finite()) {
                    ls.push(((1.0 / rho) / tr / scale).ln());
                }
            }
            let ray_cam = f.landmark.ray_in_camera(slam.state()).normalize_or_zero();
            if ray_cam.dot(travel_dir) > 30f64.to_radians().cos() {
                fwd += 1;
                if rho > 2.0 * sr {
                    fwd_pts += 1;
                }
            }
        }
        ls.sort_by(f64::total_cmp);
        let med = if ls.is_empty() {
            f64::NAN
        } else {
            ls[ls.len() / 2]
        };
        let mut dev: Vec<f64> = ls.iter().map(|v| (v - med).abs()).collect();
        dev.sort_by(f64::total_cmp);
        let mad = if dev.is_empty() {
            f64::NAN
        } else {
            dev[dev.len() / 2]
        };
        let pth = cov.view((3, 3), (3, 3));
        let u = nalgebra::Vector3::new(up0.x, up0.y, up0.z);
        let sig_yaw = (u.transpose() * pth * u)[(0, 0)]
            .max(0.0)
            .sqrt()
            .to_degrees();
        let w_est = slam.state().angular_velocity.dot(up0).to_degrees();
        let kb = k.saturating_sub(every);
        let fgt = |q: glam::DQuat| yaw(q * DVec3::Z);
        let w_gt = wrap(fgt(gt.rotation) - fgt(data.gt[kb].rotation)).to_degrees()
            / (t - data.images[kb].0).max(1e-9);
        // Visible landmarks left / right of the direction of travel (world horizontal plane).
        let (mut left, mut right) = (0, 0);
        let tw = (g0.rotation * d_est_cam(&e, &est[back])).normalize_or_zero();
        for f in slam.features() {
            if f.landmark.predict(&camera, slam.state()).is_none() {
                continue;
            }
            let rw = g0.rotation * (e.rotation * f.landmark.ray_in_camera(slam.state()));
            let side = tw.x * rw.y - tw.y * rw.x;
            if side > 0.0 {
                left += 1;
            } else {
                right += 1;
            }
        }
        println!(
            "{:>6.2} {:>7.2} {:>7.2} {:>7.2} {:>6.3} {:>4} {:>4} {:>4} {:>4} {:>4} {:>4} {:>4} {:>6.3} {:>6.3} {:>6.1} {:>5} {:>5} {:>6.2} {:>6.1} {:>6.1} {:>4} {:>4}",
            t,
            yaw_err,
            trv_err,
            rot_err,
            scale,
            r.visible,
            r.matched,
            r.inliers,
            r.rescued,
            r.initialised,
            r.landmarks,
            slam.points_in_state(),
            med,
            mad,
            100.0 * conv as f64 / nf.max(1) as f64,
            fwd,
            fwd_pts,
            sig_yaw,
            w_est,
            w_gt,
            left,
            right
        );
    }
    ekf_ms.sort_by(f64::total_cmp);
    let st = slam.stats();
    println!(
        "ekf ms median {:.2}; FI {} matches {} map points {} rays dropped {} outliers {}",
        ekf_ms[ekf_ms.len() / 2],
        st.features_initialised,
        st.matches,
        st.map_points,
        st.rays_dropped,
        st.outliers
    );
    // Overall heading of travel: first 10 m vs the rest, and Sim3 ATE.
    let tum = |v: &[Se3]| -> Vec<rgbid::trajectory::TimedPose> {
        v.iter()
            .zip(&data.images)
            .map(|(p, (t, _))| rgbid::trajectory::TimedPose {
                timestamp: *t,
                world_from_camera: *p,
            })
            .collect()
    };
    let a = rgbid::eval::ate::ate(&tum(&data.gt[..est.len()]), &tum(&est), true).unwrap();
    let path: f64 = data.gt[..est.len()]
        .windows(2)
        .map(|w| (w[1].translation - w[0].translation).length())
        .sum();
    println!(
        "Sim3 ATE {:.3} m = {:.2} % of {:.1} m, scale {:.3}",
        a.translation.rmse,
        100.0 * a.translation.rmse / path,
        path,
        a.alignment.scale
    );
}

/// The `rgbid mono --walker-height 1.75 --loops` pipeline on the cached frames, with the
/// eq. 3.36 errors as the CLI prints them.
fn metric(data: &Cached, camera: rgbid::camera::UnifiedCamera, cfg: MonoConfig, limit: usize) {
    use rgbid::mono::{LoopScaleParams, MetricMono, MonoLoopParams};
    use rgbid::scale::{arc_length_error_from_start, DynScaleConfig, UpAxis, WalkingModel};
    use rgbid::trajectory::TimedPose;
    let scale_cfg = DynScaleConfig {
        up: UpAxis::Auto,
        model: WalkingModel {
            height: 1.75,
            ..DynScaleConfig::default().model
        },
        ..DynScaleConfig::default()
    };
    let mut sys = MetricMono::with_loops(
        camera,
        cfg,
        scale_cfg,
        rgbid::place::Vocabulary::embedded_default().unwrap(),
        MonoLoopParams::default(),
        LoopScaleParams::default(),
    )
    .unwrap();
    let mut ekf_ms = Vec::new();
    for (t, img) in data.images.iter().take(limit) {
        let r = sys.process(*t, img).unwrap();
        ekf_ms.push(r.report.times.total());
    }
    let run = sys.finish();
    let gt: Vec<TimedPose> = data
        .gt
        .iter()
        .zip(&data.images)
        .take(limit)
        .map(|(p, (t, _))| TimedPose {
            timestamp: *t,
            world_from_camera: *p,
        })
        .collect();
    let mut ms = ekf_ms[1..].to_vec();
    ms.sort_by(f64::total_cmp);
    let mut rows = vec![
        ("unscaled", run.unscaled.clone()),
        ("causal", run.causal.clone()),
    ];
    if let Ok(r) = &run.scaled {
        rows.push(("final", r.scaled.clone()));
    }
    if let Some(Ok(l)) = &run.looped {
        rows.push(("loops", l.trajectory.clone()));
        println!("loops verified {}", l.loops.len());
    }
    for (name, est) in rows {
        let pairs = rgbid::eval::associate(&est, &gt, 0.02);
        let e: Vec<TimedPose> = pairs.iter().map(|p| est[p.0]).collect();
        let g: Vec<TimedPose> = pairs.iter().map(|p| gt[p.1]).collect();
        match arc_length_error_from_start(&g, &e, 1000) {
            Ok(a) => println!(
                "eq336 {name:<9} mean {:.2} % end {:.2} % length ratio {:.3}",
                100.0 * a.relative,
                100.0 * a.curve.last().map_or(f64::NAN, |c| c.1) / a.gt_length,
                a.est_length / a.gt_length
            ),
            Err(e) => println!("eq336 {name}: {e}"),
        }
    }
    let a = rgbid::eval::ate::ate(&gt, &run.unscaled, true).unwrap();
    let path: f64 = gt
        .windows(2)
        .map(|w| (w[1].world_from_camera.translation - w[0].world_from_camera.translation).length())
        .sum();
    println!(
        "EKF Sim3 ATE {:.2} % (scale {:.3}); filter ms median {:.3}",
        100.0 * a.translation.rmse / path,
        a.alignment.scale,
        ms[ms.len() / 2]
    );
}
