//! The decoupled matching experiment of thesis sec. 2.6.1 (figs. 2.8-2.12): how well a
//! feature's patch from a first catadioptric image is found again after a known motion, with
//! plain and warped patches ([`PatchMode`]), apart from any filter.
//!
//! A generated scene is rendered through the unified camera ([`UnifiedCamera::catadioptric`])
//! from a reference pose: the head-mounted walk's pose at a given time (optical axis near
//! horizontal, world `z` up). FAST corners of the reference image, spread apart and away from
//! the mirror's rims, give the features, and the renderer's true depth their 3-D points. Each
//! sweep moves the camera, renders the view and, for every feature still visible and not
//! occluded (the rendered depth at its true projection agrees with the point's), searches
//! the window of `search_half` pixels around the true projection for the best ZNCC position of
//! each mode's template (the warps use the true distance ratio and relative pose, as for a
//! converged depth), with
//! the filter's parabolic sub-pixel refinement. Sweeps:
//!
//! - rotation: about the world's vertical axis through the camera centre, degrees;
//! - translation: along the floor in the camera's heading (its optical axis projected on the
//!   floor), metres;
//! - scale: for each feature its own view, the camera moved along the feature's ray so that
//!   the distance becomes `d_init / factor` (the image point stays, the patch scales).
//!
//! Per step and mode: the features evaluated, the share whose best position lies within 1 and
//! 2 pixels of the truth, the share within 2 pixels with a score at least the ZNCC threshold
//! (what the filter would accept), and the mean best score.

use std::sync::Arc;

use glam::{DQuat, DVec2, DVec3};

use crate::camera::UnifiedCamera;
use crate::geometry::Se3;
use crate::image::ImageF32;
use crate::mono::fast::detect;
use crate::mono::patch::{refine_peak, FeaturePatch, PatchMode, ViewChange};
use crate::mono::MonoError;
use crate::synth::{
    CameraModel, RenderBackend, RenderedFrame, Renderer, Scene, SensorModel, Trajectory,
    TrajectoryKind,
};

/// Parameters of [`run_patch_sweeps`].
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct PatchSweepSpec {
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
    /// Scene preset.
    pub scene: String,
    /// Seed of scene, walk and sensor noise.
    pub seed: u64,
    /// Time on the head-mounted walk of the reference pose, seconds.
    pub reference_time: f64,
    /// Most features taken from the reference image.
    pub features: usize,
    /// Smallest distance between two features, pixels.
    pub min_feature_distance: f64,
    /// FAST threshold, intensity units.
    pub fast_threshold: f32,
    /// Correlation patch half size, pixels.
    pub patch_half: usize,
    /// Big patch half size, pixels.
    pub big_patch_half: usize,
    /// Scale limit of the warps.
    pub k_lim: f64,
    /// Half size of the search window around the true projection, pixels.
    pub search_half: i64,
    /// ZNCC threshold of an accepted match.
    pub zncc_threshold: f64,
    /// Add the sensor's image noise (a different draw per view).
    pub noise: bool,
    /// Rotation sweep, degrees about the vertical.
    pub rotations_deg: Vec<f64>,
    /// Translation sweep, metres along the floor.
    pub translations_m: Vec<f64>,
    /// Scale sweep, distance factors `d_init / d_now`.
    pub distance_factors: Vec<f64>,
}

impl Default for PatchSweepSpec {
    fn default() -> Self {
        PatchSweepSpec {
            width: 400,
            height: 400,
            scene: "office".into(),
            seed: 7,
            reference_time: 2.0,
            features: 60,
            min_feature_distance: 12.0,
            fast_threshold: 20.0,
            patch_half: 5,
            big_patch_half: 15,
            k_lim: 2.0,
            search_half: 6,
            zncc_threshold: 0.8,
            noise: true,
            rotations_deg: vec![0.0, 15.0, 30.0, 45.0, 60.0, 90.0, 120.0, 150.0, 180.0],
            translations_m: vec![0.0, 0.25, 0.5, 0.75, 1.0, 1.5, 2.0],
            distance_factors: vec![0.5, 0.625, 0.8, 1.25, 1.6, 2.0],
        }
    }
}

/// One sweep step with one patch mode.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct PatchSweepRow {
    /// `rotation`, `translation` or `scale`.
    pub sweep: &'static str,
    /// The step: degrees, metres or distance factor.
    pub step: f64,
    /// Patch mode name.
    pub mode: &'static str,
    /// Features evaluated (visible, not occluded, window inside the image).
    pub features: usize,
    /// Share with the best position within 1 pixel of the truth, percent.
    pub within_1px_pct: f64,
    /// Share within 2 pixels, percent.
    pub within_2px_pct: f64,
    /// Share within 2 pixels and scoring at least the threshold, percent.
    pub matched_pct: f64,
    /// Mean best ZNCC score in the window.
    pub mean_score: f64,
}

/// The whole experiment.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct PatchSweepReport {
    /// What was run.
    pub spec: PatchSweepSpec,
    /// Features taken from the reference image.
    pub reference_features: usize,
    /// One row per sweep step and mode.
    pub rows: Vec<PatchSweepRow>,
}

/// A reference feature.
struct Probe {
    /// Point in the world frame, metres.
    world: DVec3,
    /// Distance from the reference camera, metres.
    distance: f64,
    /// Unit ray in the reference camera frame.
    ray: DVec3,
    /// Pixel in the reference image.
    uv: DVec2,
    patch: FeaturePatch,
}

/// The match of one probe in one view with one mode: (pixel error, best score).
fn search(
    spec: &PatchSweepSpec,
    camera: &UnifiedCamera,
    image: &ImageF32,
    probe: &Probe,
    mode: PatchMode,
    truth: DVec2,
    view: &ViewChange,
) -> Option<(f64, f64)> {
    let template = if mode == PatchMode::Projective {
        probe
            .patch
            .template_projective(camera, truth, view, spec.patch_half)?
    } else {
        let distance_ratio = view
            .point_in_init
            .map_or(1.0, |p| p.length() / (p - view.centre_now_in_init).length());
        probe
            .patch
            .template(
                camera,
                truth,
                mode,
                distance_ratio,
                spec.k_lim,
                spec.patch_half,
            )?
            .0
    };
    let (cx, cy) = (truth.x.round() as i64, truth.y.round() as i64);
    let r = spec.search_half;
    let (x0, y0, x1, y1) = (cx - r, cy - r, cx + r, cy + r);
    let bw = (x1 - x0 + 1) as usize;
    let scores = template.correlate_window(image, x0, y0, x1, y1);
    let (best_i, best) = scores
        .iter()
        .copied()
        .enumerate()
        .max_by(|a, b| a.1.total_cmp(&b.1))?;
    if !best.is_finite() {
        return None;
    }
    let (bx, by) = (best_i % bw, best_i / bw);
    let (dx, dy) = refine_peak(&scores, bw, bx, by, best);
    let found = DVec2::new((x0 + bx as i64) as f64 + dx, (y0 + by as i64) as f64 + dy);
    Some(((found - truth).length(), best))
}

/// The true projection of a probe in a view; `None` when it is outside the usable image or
/// occluded.
fn visible(
    spec: &PatchSweepSpec,
    camera: &UnifiedCamera,
    frame: &RenderedFrame,
    world_from_camera: &Se3,
    probe: &Probe,
) -> Option<DVec2> {
    let p = world_from_camera.inverse().transform_point(probe.world);
    let uv = camera.project(p)?;
    let margin = (spec.search_half as usize + spec.patch_half + 1) as f64;
    let (w, h) = (f64::from(camera.width), f64::from(camera.height));
    let inside =
        uv.x >= margin && uv.y >= margin && uv.x <= w - 1.0 - margin && uv.y <= h - 1.0 - margin;
    if !(inside && camera.in_fov(uv)) {
        return None;
    }
    let (x, y) = (uv.x.round() as usize, uv.y.round() as usize);
    let z = frame.true_depth.data[y * frame.true_depth.width + x];
    let d = p.length();
    // The rendered surface at the pixel is the point's own (not something in front of it):
    // depths along the optical axis agree to a few percent of the distance.
    if !((f64::from(z) - p.z).abs() <= 0.05 * d + 0.01) {
        return None;
    }
    Some(uv)
}

fn render_view(
    renderer: &mut Renderer,
    spec: &PatchSweepSpec,
    pose: &Se3,
    view: u64,
) -> Result<RenderedFrame, MonoError> {
    let sensor = if spec.noise {
        SensorModel::kinect()
    } else {
        SensorModel::noiseless()
    };
    Ok(renderer.render(
        pose,
        &sensor,
        spec.seed.wrapping_add(view.wrapping_mul(7919)),
    )?)
}

/// Runs the three sweeps for every [`PatchMode`].
pub fn run_patch_sweeps(spec: &PatchSweepSpec) -> Result<PatchSweepReport, MonoError> {
    let bad = |name: &'static str, why: &str| MonoError::InvalidConfig {
        name,
        why: why.to_string(),
    };
    if spec.patch_half == 0 || spec.big_patch_half < spec.patch_half {
        return Err(bad("patch_half", "must be >= 1 and at most big_patch_half"));
    }
    if !(spec.k_lim >= 1.0 && spec.k_lim.is_finite()) {
        return Err(bad("k_lim", "must be finite and >= 1"));
    }
    if spec.search_half < 2 {
        return Err(bad("search_half", "must be >= 2 pixels"));
    }
    if spec.distance_factors.iter().any(|f| !(*f > 0.0)) {
        return Err(bad("distance_factors", "must be > 0"));
    }
    let scene = Arc::new(Scene::preset(&spec.scene, spec.seed)?);
    let camera = UnifiedCamera::catadioptric(spec.width, spec.height);
    let walk = Trajectory::new(
        TrajectoryKind::WalkHead,
        &scene,
        spec.reference_time + 1.0,
        spec.seed,
    )?;
    let reference = walk.pose_at(spec.reference_time);
    let mut renderer = Renderer::new(
        scene.clone(),
        CameraModel::Unified(camera),
        &RenderBackend::Cpu,
    )?;
    let first = render_view(&mut renderer, spec, &reference, 0)?;
    let probes = probes(spec, &camera, &first, &reference);
    let mut rows = Vec::new();
    let mut view = 1u64;
    let score = |sweep: &'static str,
                 step: f64,
                 found: &[(PatchMode, Option<(f64, f64)>)],
                 rows: &mut Vec<PatchSweepRow>| {
        for mode in PatchMode::ALL {
            let hits: Vec<(f64, f64)> = found
                .iter()
                .filter(|(m, _)| *m == mode)
                .filter_map(|(_, h)| *h)
                .collect();
            let n = found.iter().filter(|(m, _)| *m == mode).count();
            let pct = |c: usize| {
                if n == 0 {
                    0.0
                } else {
                    100.0 * c as f64 / n as f64
                }
            };
            rows.push(PatchSweepRow {
                sweep,
                step,
                mode: mode.name(),
                features: n,
                within_1px_pct: pct(hits.iter().filter(|h| h.0 <= 1.0).count()),
                within_2px_pct: pct(hits.iter().filter(|h| h.0 <= 2.0).count()),
                matched_pct: pct(hits
                    .iter()
                    .filter(|h| h.0 <= 2.0 && h.1 >= spec.zncc_threshold)
                    .count()),
                // A template with no score (flat, or no image) counts as -1.
                mean_score: if n == 0 {
                    0.0
                } else {
                    found
                        .iter()
                        .filter(|(m, _)| *m == mode)
                        .map(|(_, h)| h.map_or(-1.0, |h| h.1))
                        .sum::<f64>()
                        / n as f64
                },
            });
        }
    };
    let evaluate = |frame: &RenderedFrame, pose: &Se3, probe: &Probe| {
        let mut out = Vec::new();
        if let Some(uv) = visible(spec, &camera, frame, pose, probe) {
            // The true relative pose and point: the warps as for a converged depth.
            let init_from_world = reference.inverse();
            let view = ViewChange {
                init_from_now: init_from_world.rotation * pose.rotation,
                centre_now_in_init: init_from_world.transform_point(pose.translation),
                point_in_init: Some(init_from_world.transform_point(probe.world)),
            };
            for mode in PatchMode::ALL {
                out.push((
                    mode,
                    search(spec, &camera, &frame.intensity, probe, mode, uv, &view),
                ));
            }
        }
        out
    };
    for &deg in &spec.rotations_deg {
        let turn = DQuat::from_rotation_z(deg.to_radians());
        let pose = Se3::new(turn * reference.rotation, reference.translation);
        let frame = render_view(&mut renderer, spec, &pose, view)?;
        view += 1;
        let found: Vec<_> = probes
            .iter()
            .flat_map(|p| evaluate(&frame, &pose, p))
            .collect();
        score("rotation", deg, &found, &mut rows);
    }
    let forward = reference.transform_vector(DVec3::Z);
    let heading = DVec3::new(forward.x, forward.y, 0.0).normalize_or(DVec3::X);
    for &m in &spec.translations_m {
        let pose = Se3::new(reference.rotation, reference.translation + heading * m);
        let frame = render_view(&mut renderer, spec, &pose, view)?;
        view += 1;
        let found: Vec<_> = probes
            .iter()
            .flat_map(|p| evaluate(&frame, &pose, p))
            .collect();
        score("translation", m, &found, &mut rows);
    }
    for &factor in &spec.distance_factors {
        let mut found = Vec::new();
        for p in &probes {
            let ray_world = reference.transform_vector(p.ray);
            let centre = p.world - ray_world * (p.distance / factor);
            let pose = Se3::new(reference.rotation, centre);
            let frame = render_view(&mut renderer, spec, &pose, view)?;
            view += 1;
            found.extend(evaluate(&frame, &pose, p));
        }
        score("scale", factor, &found, &mut rows);
    }
    Ok(PatchSweepReport {
        spec: spec.clone(),
        reference_features: probes.len(),
        rows,
    })
}

/// The reference features: the strongest FAST corners inside the mirror's ring, at least
/// `min_feature_distance` apart, whose rays are not near-perpendicular to the optical axis
/// (where the depth along it says little about the distance) and whose patches fit.
fn probes(
    spec: &PatchSweepSpec,
    camera: &UnifiedCamera,
    frame: &RenderedFrame,
    reference: &Se3,
) -> Vec<Probe> {
    let img = &frame.intensity;
    let margin = spec.big_patch_half + 1;
    let keep = |x: usize, y: usize| {
        let uv = DVec2::new(x as f64, y as f64);
        camera.in_fov(uv)
            && camera.in_fov(uv + DVec2::splat(margin as f64))
            && camera.in_fov(uv - DVec2::splat(margin as f64))
    };
    let mut corners = detect(
        img,
        (margin, margin, img.width - margin, img.height - margin),
        spec.fast_threshold,
        keep,
    );
    corners.sort_by(|a, b| b.score.total_cmp(&a.score));
    let mut out: Vec<Probe> = Vec::new();
    for c in corners {
        if out.len() >= spec.features {
            break;
        }
        let uv = DVec2::new(c.x as f64, c.y as f64);
        if out
            .iter()
            .any(|p| (p.uv - uv).length() < spec.min_feature_distance)
        {
            continue;
        }
        let Some(ray) = camera.unproject(uv) else {
            continue;
        };
        let z = f64::from(frame.true_depth.data[c.y * img.width + c.x]);
        if ray.z.abs() < 0.2 || !(z.is_finite() && z.abs() > 1e-3) || z * ray.z <= 0.0 {
            continue;
        }
        let point = ray * (z / ray.z);
        let Some(patch) = FeaturePatch::new(img, camera, uv, spec.big_patch_half, spec.patch_half)
        else {
            continue;
        };
        if patch.plain.is_none() {
            continue;
        }
        out.push(Probe {
            world: reference.transform_point(point),
            distance: point.length(),
            ray,
            uv,
            patch,
        });
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn projective_patches_match_more_features_than_plain_ones_under_large_rotations() {
        let spec = PatchSweepSpec {
            width: 320,
            height: 320,
            features: 30,
            rotations_deg: vec![0.0, 30.0, 60.0, 90.0],
            translations_m: vec![],
            distance_factors: vec![],
            ..PatchSweepSpec::default()
        };
        let report = run_patch_sweeps(&spec).unwrap();
        let rows = |mode: PatchMode| {
            report
                .rows
                .iter()
                .filter(move |r| r.sweep == "rotation" && r.mode == mode.name())
        };
        // Without motion every mode finds its features.
        for mode in PatchMode::ALL {
            let r = rows(mode).find(|r| r.step == 0.0).unwrap();
            assert!(r.features >= 10, "{r:?}");
            assert!(r.within_1px_pct >= 90.0, "{r:?}");
        }
        // Accepted matches (within 2 px, ZNCC >= 0.8) summed over the turns of 30-90 degrees.
        let matched = |mode: PatchMode| -> f64 {
            rows(mode)
                .filter(|r| r.step > 0.0)
                .map(|r| r.matched_pct * r.features as f64 / 100.0)
                .sum()
        };
        let (plain, projective) = (matched(PatchMode::Plain), matched(PatchMode::Projective));
        assert!(
            projective >= 2.0 * plain && projective >= plain + 4.0,
            "projective {projective} plain {plain}: {:?}",
            report.rows
        );
    }
}
