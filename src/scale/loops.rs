//! Sim(3) loop closure (`optimSim3`, Strasdat et al. 2010) on a (possibly rescaled) monocular
//! trajectory, through [`crate::graph::PoseGraphSim3`].
//!
//! Vertices are the estimated keyframe poses as similarities of scale 1 (vertex 0 fixed, the
//! gauge); odometry edges join consecutive keyframes with their estimated relative motion
//! (scale 1, translation std 5 % of the step, rotation 0.002 rad, log-scale 0.02). Loop
//! closures are emulated from ground truth (the place-recognition front end is not part of
//! this experiment): keyframes `i < j` at least `min_separation` seconds apart whose true
//! positions are within `max_distance` and viewing directions within `max_angle` are
//! linked, at most one closure per `min_gap` seconds. The closure measures the similarity
//! `i_from_j` a monocular relocaliser would: with `s_k` the true local scale (metres per
//! estimate unit) at keyframe `k` and `(R, t)` the true relative motion,
//! `z = (R, t / s_i, s_j / s_i)`, perturbed by the closure noise.

use glam::DVec3;
use rand::SeedableRng;
use rand_pcg::Pcg64;

use super::particle::standard_normal;
use super::ScaleError;
use crate::geometry::{so3_exp, Se3};
use crate::graph::{PoseGraphSim3, Sim3, SolverOptions};
use crate::trajectory::TimedPose;

/// Settings of the emulated loop closures and of the Sim(3) graph.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LoopConfig {
    /// Minimum time between the two keyframes of a closure, seconds.
    pub min_separation: f64,
    /// Maximum true distance between them, metres.
    pub max_distance: f64,
    /// Maximum angle between their optical axes, radians.
    pub max_angle: f64,
    /// Minimum time between two closures (by the later keyframe), seconds.
    pub min_gap: f64,
    /// Closure translation noise, metres (per axis).
    pub translation_noise: f64,
    /// Closure rotation noise, radians (per axis).
    pub rotation_noise: f64,
    /// Closure log-scale noise.
    pub log_scale_noise: f64,
    /// Seed of the closure noise.
    pub seed: u64,
}

impl Default for LoopConfig {
    fn default() -> Self {
        LoopConfig {
            min_separation: 10.0,
            max_distance: 0.4,
            max_angle: 0.5,
            min_gap: 2.0,
            translation_noise: 0.02,
            rotation_noise: 0.005,
            log_scale_noise: 0.01,
            seed: 3,
        }
    }
}

/// Loop-closure pairs `(i, j)`, `i < j`, indices into `gt` (see the module docs).
pub fn detect_loops_from_ground_truth(gt: &[TimedPose], cfg: &LoopConfig) -> Vec<(usize, usize)> {
    let mut out = Vec::new();
    let mut last_t = f64::NEG_INFINITY;
    for j in 0..gt.len() {
        if gt[j].timestamp - last_t < cfg.min_gap {
            continue;
        }
        let pj = &gt[j].world_from_camera;
        let zj = pj.transform_vector(DVec3::Z);
        let mut best: Option<(usize, f64)> = None;
        for i in 0..j {
            if gt[j].timestamp - gt[i].timestamp < cfg.min_separation {
                break;
            }
            let pi = &gt[i].world_from_camera;
            let d = (pi.translation - pj.translation).length();
            let ang = pi.transform_vector(DVec3::Z).angle_between(zj);
            if d < cfg.max_distance && ang < cfg.max_angle && best.is_none_or(|b| d < b.1) {
                best = Some((i, d));
            }
        }
        if let Some((i, _)) = best {
            out.push((i, j));
            last_t = gt[j].timestamp;
        }
    }
    out
}

fn diag(v: &[f64]) -> Vec<f64> {
    let n = v.len();
    let mut m = vec![0.0; n * n];
    for (k, x) in v.iter().enumerate() {
        m[k * n + k] = 1.0 / (x * x);
    }
    m
}

/// `optimSim3`: corrects `est` (keyframes, estimate units) with the loop closures `loops`
/// (indices into `est`), measured from `gt` with the estimate's true local scale `local_scale`
/// (metres per estimate unit, one per keyframe). Returns the corrected keyframes.
///
/// Without `metric_prior`, keyframe 0 is fixed (pose and scale: the result is in its units, as
/// plain monocular `optimSim3`). With `Some(sigma)` (for an already metric, dynScale'd input)
/// a fixed anchor vertex holds the metric frame: every keyframe about one second apart gets a
/// prior `ln s_k = 0 +- sigma` (keep dynScale's scale), the rotation and translation parts of
/// those priors being negligible (1e-8) except for keyframe 0, which they pin in place.
pub fn optim_sim3(
    est: &[TimedPose],
    gt: &[TimedPose],
    local_scale: &[f64],
    loops: &[(usize, usize)],
    cfg: &LoopConfig,
    metric_prior: Option<f64>,
) -> Result<Vec<TimedPose>, ScaleError> {
    let n = est.len();
    if n < 2 || gt.len() != n || local_scale.len() != n {
        return Err(ScaleError::InvalidParameter {
            name: "keyframes",
            why: format!(
                "need >= 2 keyframes and equal lengths (est {n}, gt {}, scales {})",
                gt.len(),
                local_scale.len()
            ),
        });
    }
    let mut g = PoseGraphSim3::new();
    for (k, p) in est.iter().enumerate() {
        g.add_vertex(k as i64, Sim3::from_se3(&p.world_from_camera))?;
    }
    if let Some(sigma) = metric_prior {
        let anchor = g.add_vertex(-1, Sim3::IDENTITY)?;
        g.fixed[anchor] = true;
        let sigma = sigma.max(1e-6);
        let mut last = f64::NEG_INFINITY;
        for (k, p) in est.iter().enumerate() {
            if k > 0 && p.timestamp - last < 1.0 {
                continue;
            }
            last = p.timestamp;
            let w = if k == 0 { 1e-4 } else { 1e4 };
            g.add_edge_by_index(
                anchor,
                k,
                Sim3::from_se3(&p.world_from_camera),
                diag(&[w, w, w, w, w, w, sigma]),
            )?;
        }
    } else {
        g.fixed[0] = true;
    }
    for k in 1..n {
        let z = est[k - 1].world_from_camera.inverse() * est[k].world_from_camera;
        let st = 0.05 * z.translation.length() + 1e-6;
        g.add_edge_by_index(
            k - 1,
            k,
            Sim3::from_se3(&z),
            diag(&[st, st, st, 0.002, 0.002, 0.002, 0.02]),
        )?;
    }
    let mut rng = Pcg64::seed_from_u64(cfg.seed ^ 0x100b);
    for &(i, j) in loops {
        if i >= n || j >= n || i == j {
            continue;
        }
        let rel: Se3 = gt[i].world_from_camera.inverse() * gt[j].world_from_camera;
        let mut nz = || standard_normal(&mut rng);
        let dr = so3_exp(DVec3::new(nz(), nz(), nz()) * cfg.rotation_noise);
        let dt = DVec3::new(nz(), nz(), nz()) * cfg.translation_noise;
        let ds = (nz() * cfg.log_scale_noise).exp();
        let (si, sj) = (local_scale[i], local_scale[j]);
        let z = Sim3::new(dr * rel.rotation, (rel.translation + dt) / si, sj / si * ds);
        let st = cfg.translation_noise / si;
        g.add_edge_by_index(
            i,
            j,
            z,
            diag(&[
                st,
                st,
                st,
                cfg.rotation_noise,
                cfg.rotation_noise,
                cfg.rotation_noise,
                cfg.log_scale_noise.max(1e-4),
            ]),
        )?;
    }
    g.optimize(&SolverOptions {
        max_iterations: 50,
        ..SolverOptions::default()
    })?;
    Ok(est
        .iter()
        .zip(&g.poses)
        .map(|(p, v)| TimedPose {
            timestamp: p.timestamp,
            world_from_camera: v.to_se3(),
        })
        .collect())
}
