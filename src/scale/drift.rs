//! Emulated monocular SLAM output: a ground-truth trajectory with pose noise and a drifting,
//! unknown scale (for experiments; no images are rendered).
//!
//! Model, per frame `k -> k+1` (`dt` seconds apart):
//! - the true relative motion `D_k = gt_k^-1 gt_{k+1}` (metric, camera `k` frame) is perturbed
//!   by a random twist: rotation `N(0, rotation_noise^2)` rad and translation
//!   `N(0, translation_noise^2)` m per axis (odometry / EKF jitter);
//! - its translation is divided by the local scale `s_k` (metres per SLAM unit):
//!   `est_{k+1} = est_k * (R_D', t_D' / s_k)`, `est_0 = identity` (the world of the estimate is
//!   the first camera, as in monocular SLAM);
//! - the scale drifts as a random walk in log scale:
//!   `ln s_{k+1} = ln s_k + N(0, drift^2 dt)`, `s_0 = initial_scale` (the unknown global scale).
//!
//! The true local scale `s_k` of every frame is returned with the estimate (the ground truth
//! of what dynScale should recover).

use glam::DVec3;
use rand::SeedableRng;
use rand_pcg::Pcg64;

use super::particle::standard_normal;
use crate::geometry::{so3_exp, Se3};
use crate::trajectory::TimedPose;

/// Parameters of the emulated monocular drift.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct DriftModel {
    /// Metres per SLAM unit at the first frame (the unknown global scale).
    pub initial_scale: f64,
    /// Standard deviation of `ln s` per sqrt(second).
    pub drift: f64,
    /// Rotation noise per frame, radians (per axis).
    pub rotation_noise: f64,
    /// Translation noise per frame, metres (per axis).
    pub translation_noise: f64,
    /// Seed of the noise.
    pub seed: u64,
}

impl Default for DriftModel {
    fn default() -> Self {
        DriftModel {
            initial_scale: 0.4,
            drift: 0.04,
            rotation_noise: 3e-4,
            translation_noise: 5e-4,
            seed: 1,
        }
    }
}

/// An emulated monocular run: the estimate, its true local scales and the ground truth.
#[derive(Clone, Debug)]
pub struct EmulatedRun {
    /// Ground truth `world_from_camera`, metres.
    pub gt: Vec<TimedPose>,
    /// Estimate `first_camera_from_camera`, SLAM units.
    pub est: Vec<TimedPose>,
    /// True local scale of each estimated pose, metres per SLAM unit.
    pub true_scale: Vec<f64>,
}

/// Emulates monocular SLAM output from ground truth `gt` (see the module docs).
pub fn emulate_monocular(gt: &[TimedPose], model: &DriftModel) -> EmulatedRun {
    let mut rng = Pcg64::seed_from_u64(model.seed ^ 0xd21f_7000);
    let mut est = Vec::with_capacity(gt.len());
    let mut true_scale = Vec::with_capacity(gt.len());
    let mut cur = Se3::IDENTITY;
    let mut ln_s = model.initial_scale.max(1e-12).ln();
    for (k, g) in gt.iter().enumerate() {
        if k > 0 {
            let prev = &gt[k - 1];
            let d = prev.world_from_camera.inverse() * g.world_from_camera;
            let mut n = || standard_normal(&mut rng);
            let dr = so3_exp(DVec3::new(n(), n(), n()) * model.rotation_noise);
            let dtr = DVec3::new(n(), n(), n()) * model.translation_noise;
            let s = ln_s.exp();
            let step = Se3::new(dr * d.rotation, (d.translation + dtr) / s);
            cur = cur * step;
            let dt = (g.timestamp - prev.timestamp).max(0.0);
            ln_s += model.drift * dt.sqrt() * standard_normal(&mut rng);
        }
        est.push(TimedPose {
            timestamp: g.timestamp,
            world_from_camera: cur,
        });
        true_scale.push(ln_s.exp());
    }
    EmulatedRun {
        gt: gt.to_vec(),
        est,
        true_scale,
    }
}
