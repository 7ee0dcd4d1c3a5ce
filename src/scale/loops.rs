//! Sim(3) loop closure (`optimSim3`, Strasdat et al. 2010) on a (possibly rescaled) monocular
//! trajectory, through [`crate::graph::PoseGraphSim3`].
//!
//! [`optim_sim3_with`] is the graph: vertices are the keyframe poses as similarities of scale 1,
//! odometry edges join consecutive keyframes with their estimated relative motion (scale 1,
//! translation std 5 % of the step, rotation 0.002 rad, log-scale 0.02), loops are relative
//! similarities ([`SimilarityConstraint`]), and either keyframe 0 is fixed (the result in its
//! units) or, for an input already in metres, each keyframe's scale has a prior around 1 (the
//! walking scale of its section). The monocular system, a layer above, measures the loops
//! from images; [`optim_sim3`] emulates them from ground truth for the
//! scale experiment (the place-recognition front end is not part of it): keyframes `i < j` at
//! least `min_separation` seconds apart whose true positions are within `max_distance` and
//! viewing directions within `max_angle` are linked, at most one closure per `min_gap`
//! seconds. The emulated closure measures the similarity `i_from_j` a monocular relocaliser
//! would: with `s_k` the true local scale (metres per estimate unit) at keyframe `k` and
//! `(R, t)` the true relative motion, `z = (R, t / s_i, s_j / s_i)`, perturbed by the closure
//! noise.

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

/// A relative similarity between two keyframes of a Sim(3) graph (a loop closure): `i_from_j`
/// maps points of keyframe `j`'s camera frame, in `j`'s units, into keyframe `i`'s camera
/// frame in `i`'s units (`p_i = scale R p_j + t`; its scale is the ratio of the two keyframes'
/// local scales, eq. 3.10), with the standard deviations of its parts.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SimilarityConstraint {
    /// The older keyframe (index into the keyframes of [`optim_sim3_with`]).
    pub i: usize,
    /// The newer keyframe.
    pub j: usize,
    /// `i_from_j`, translation in keyframe `i`'s units.
    pub i_from_j: Sim3,
    /// Standard deviation of each translation component, keyframe `i`'s units (> 0).
    pub translation_std: f64,
    /// Standard deviation of each rotation component, radians (> 0).
    pub rotation_std: f64,
    /// Standard deviation of the log of the scale (> 0).
    pub log_scale_std: f64,
}

/// `optimSim3`: corrects `est` (keyframes, estimate units) with the loop closures `loops`
/// (indices into `est`), measured from `gt` with the estimate's true local scale `local_scale`
/// (metres per estimate unit, one per keyframe). Returns the corrected keyframes.
///
/// Without `metric_prior`, keyframe 0 is fixed (pose and scale: the result is in its units, as
/// plain monocular `optimSim3`). With `Some(sigma)` (for an already metric, dynScale'd input)
/// every keyframe about one second apart gets the prior `ln s_k = 0 +- sigma` of
/// [`optim_sim3_with`].
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
    let mut rng = Pcg64::seed_from_u64(cfg.seed ^ 0x100b);
    let mut constraints = Vec::with_capacity(loops.len());
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
        constraints.push(SimilarityConstraint {
            i,
            j,
            i_from_j: Sim3::new(dr * rel.rotation, (rel.translation + dt) / si, sj / si * ds),
            translation_std: cfg.translation_noise / si,
            rotation_std: cfg.rotation_noise,
            log_scale_std: cfg.log_scale_noise.max(1e-4),
        });
    }
    let priors = metric_prior.map(|sigma| vec![sigma; n]);
    let poses = optim_sim3_with(est, &constraints, priors.as_deref())?;
    Ok(est
        .iter()
        .zip(&poses)
        .map(|(p, v)| TimedPose {
            timestamp: p.timestamp,
            world_from_camera: v.to_se3(),
        })
        .collect())
}

/// The Sim(3) graph of `optimSim3` on keyframes `est` (`world_from_camera`, time order) with
/// the relative similarities `loops`; returns each keyframe's corrected `world_from_camera`
/// as a similarity (its scale: the keyframe's units over the world's).
///
/// Vertices are the keyframe poses as similarities of scale 1; odometry edges join
/// consecutive keyframes with their relative motion (scale 1, translation std 5 % of the step,
/// rotation 0.002 rad, log-scale 0.02). Without `scale_priors`, keyframe 0 is fixed (pose and
/// scale: the result is in its units). With `Some(sigmas)` (one log-scale standard deviation
/// per keyframe, for an input already in metres, e.g. dynScale's output) a fixed anchor
/// vertex holds the metric frame: every keyframe about one second apart gets the prior
/// `ln s_k = 0 +- sigmas[k]` (keep the metric scale it has), the rotation and translation
/// parts of those priors being negligible (1e-8) except for keyframe 0, which they pin in
/// place.
pub fn optim_sim3_with(
    est: &[TimedPose],
    loops: &[SimilarityConstraint],
    scale_priors: Option<&[f64]>,
) -> Result<Vec<Sim3>, ScaleError> {
    let n = est.len();
    if n < 2 || scale_priors.is_some_and(|p| p.len() != n) {
        return Err(ScaleError::InvalidParameter {
            name: "keyframes",
            why: format!(
                "need >= 2 keyframes and one scale prior per keyframe (keyframes {n}, priors {})",
                scale_priors.map_or(0, <[f64]>::len)
            ),
        });
    }
    let mut g = PoseGraphSim3::new();
    for (k, p) in est.iter().enumerate() {
        g.add_vertex(k as i64, Sim3::from_se3(&p.world_from_camera))?;
    }
    if let Some(sigmas) = scale_priors {
        let anchor = g.add_vertex(-1, Sim3::IDENTITY)?;
        g.fixed[anchor] = true;
        let mut last = f64::NEG_INFINITY;
        for (k, p) in est.iter().enumerate() {
            if k > 0 && p.timestamp - last < 1.0 {
                continue;
            }
            last = p.timestamp;
            let w = if k == 0 { 1e-4 } else { 1e4 };
            let sigma = if sigmas[k].is_finite() {
                sigmas[k].max(1e-6)
            } else {
                return Err(ScaleError::NonFinite(format!(
                    "scale prior of keyframe {k}"
                )));
            };
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
    for c in loops {
        if c.i >= n || c.j >= n || c.i == c.j {
            continue;
        }
        let (st, sr, ss) = (
            c.translation_std.max(1e-9),
            c.rotation_std.max(1e-9),
            c.log_scale_std.max(1e-4),
        );
        g.add_edge_by_index(c.i, c.j, c.i_from_j, diag(&[st, st, st, sr, sr, sr, ss]))?;
    }
    g.optimize(&SolverOptions {
        max_iterations: 50,
        ..SolverOptions::default()
    })?;
    Ok(g.poses[..n].to_vec())
}
