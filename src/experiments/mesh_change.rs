//! The thesis' mesh experiment of chapter 5 (eq. 5.3, figs. 5.9-5.10) on generated scenes:
//! TSDF meshes of the same scene captured in several sessions, segmented into superjuts by
//! the mesh-edge graph, with the neg-entropy of normals deciding which segments to mask.
//!
//! **Change model** (fixed before measuring; it is the session generator's,
//! [`crate::synth::Scene::session`], also used by the image experiment
//! [`super::segment`]). The thesis captured the same rooms on different days, with chairs and
//! objects moved, some added and some removed. Every session `k >= 1` is derived from session
//! 0: walls, floor, posters and furniture (desks, shelves, counters, cabinets) stay; each
//! movable object (chairs, piles of boxes, small items on surfaces, soft objects) is
//! independently removed with probability 0.15, moved with probability 0.40 (turned about
//! the vertical by up to +-0.9 rad and shifted horizontally by 0.15-0.5 m in a random
//! direction), and left in place otherwise; then 1-3 new piles (soft objects in presets that
//! have them) are added next to the walls. Sessions are independent draws, not cumulative.
//!
//! Per scene and session (all frames of one loop, true poses, the generator's Kinect-like
//! depth):
//!
//! 1. the frames are integrated into a sparse TSDF ([`crate::tsdf::TsdfVolume`]) and the
//!    zero level set is extracted as a mesh with normals (world frame);
//! 2. the session-`k` mesh is segmented by [`crate::segment::Segmenter::segment_mesh`]
//!    (mesh-edge graph, convexity weights, neg-entropy of normals per segment);
//! 3. **ground truth (eq. 5.3)**: a vertex of session `k`'s mesh is *changed* when no surface
//!    of session 0 lies within [`MeshChangeConfig::change_distance`] of it, measured against
//!    the exact generated surfaces of session 0 ([`crate::synth::Scene::surface_distance`]),
//!    so surfaces that session 0 saw only partly (floor under a removed object) are not
//!    counted as changed. It is cross-checked against the generator's labels: a vertex
//!    belongs to the object whose primitive surface is nearest, and is changed when that
//!    object is moved or added ([`GroundTruthAgreement`]). Vertices farther than the same
//!    distance from every surface of their own session are reconstruction artefacts (depth
//!    noise, surfaces bridging thin objects): neither label applies, so they are counted
//!    apart ([`GroundTruthAgreement::off_surface_m2`]) and left out of the scores;
//! 4. per neg-entropy threshold `t`, segments with neg-entropy below `t` are masked as
//!    changed (the SLAM masks keep superjuts with neg-entropy `>= t`); precision and recall of
//!    the masked area against eq. 5.3 are area-weighted over vertices (a vertex carries a
//!    third of the area of its triangles) ([`DetectionRow`]);
//! 5. matching as in the image experiment: ORB of frame `i` of session 0 against frame
//!    `i + offset` of session `k`, each frame's keypoints masked by the labels of its own
//!    session's mesh projected into it ([`crate::segment::project_labels`]), 3-point RANSAC,
//!    correct matches judged by the true relative pose ([`MatchingRow`]).
//!
//! Distances in metres; meshes in the world frame of the generated scene (z up).

use std::time::Instant;

use glam::DVec3;
use rayon::prelude::*;

use super::segment::{
    check_capture, match_pair, median, summarise, ClutteredViews, ExperimentError, MatchingRow,
    Prepared, RowAcc, Verify,
};
use crate::camera::PinholeCamera;
use crate::gpu::ComputeBackend;
use crate::place::{extract_orb, MatchParams, OrbParams, RansacParams};
use crate::segment::{project_labels, SegmentConfig, Segmenter, Superjut, TriMesh};
use crate::source::{FrameSource, SourceSpec};
use crate::synth::{Scene, SensorModel, SequenceFrame};
use crate::tsdf::{Mesh, TsdfParams, TsdfVolume};

/// Parameters of [`run_mesh_change_experiment`].
#[derive(Clone, Debug, serde::Serialize)]
pub struct MeshChangeConfig {
    /// Scene presets (see `rgbid synth --help`).
    pub scenes: Vec<String>,
    /// Scene seeds; every scene is run with every seed.
    pub seeds: Vec<u64>,
    /// Changed sessions `1..=sessions` compared with session 0 (>= 1).
    pub sessions: u32,
    /// Frames of one lap of the loop; all are integrated into the session's TSDF.
    pub lap_frames: usize,
    /// Every `step`-th frame of the lap starts a matching pair.
    pub step: usize,
    /// The session-`k` frame of a pair is `offset` frames after the session-0 frame.
    pub offset: usize,
    /// Image width in pixels (height 3/4 of it).
    pub width: u32,
    /// Depth sensor model of the rendered frames (default: the generator's Kinect-like model
    /// at the 525 px focal length of the 640x480 Kinect).
    #[serde(skip)]
    pub sensor: SensorModel,
    /// TSDF parameters (voxel size in metres, noise model, depth range).
    pub tsdf: TsdfParams,
    /// Eq. 5.3's distance `d`, metres: a session-`k` vertex farther than this from every
    /// session-0 surface is changed.
    pub change_distance: f64,
    /// Neg-entropy thresholds (`None` = unmasked, always first in the matching rows).
    pub thresholds: Vec<f64>,
    /// A verified match is correct when its two 3D points are closer than this (m) under the
    /// true relative pose, plus `correct_per_metre` per metre of depth.
    pub correct_tolerance: f64,
    /// Growth of the tolerance with depth (m per m).
    pub correct_per_metre: f64,
    /// Mesh segmentation parameters (`min_size` counts vertices; `up` is the world's z).
    pub segment: SegmentConfig,
    /// ORB parameters.
    #[serde(skip)]
    pub orb: OrbParams,
    /// Descriptor matching parameters.
    #[serde(skip)]
    pub matching: MatchParams,
    /// RANSAC parameters.
    #[serde(skip)]
    pub ransac: RansacParams,
}

impl Default for MeshChangeConfig {
    fn default() -> Self {
        Self {
            scenes: vec![
                "office".into(),
                "kitchen".into(),
                "lab".into(),
                "home".into(),
            ],
            seeds: vec![1],
            sessions: 2,
            lap_frames: 150,
            step: 10,
            offset: 2,
            width: 320,
            // The 640x480 Kinect's depth resolution, whatever the rendered width.
            sensor: SensorModel {
                focal_px: Some(525.0),
                ..SensorModel::kinect()
            },
            tsdf: TsdfParams {
                voxel_size: 0.02,
                ..TsdfParams::default()
            },
            change_distance: 0.05,
            thresholds: vec![0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9],
            correct_tolerance: 0.03,
            correct_per_metre: 0.01,
            segment: SegmentConfig {
                // A small item (10 cm) carries ~100 vertices at 2 cm voxels; the image
                // default (200 pixels) would merge it into its support.
                min_size: 50,
                up: [0.0, 0.0, 1.0],
                ..SegmentConfig::default()
            },
            orb: OrbParams::default(),
            matching: MatchParams::default(),
            ransac: RansacParams::default(),
        }
    }
}

impl MeshChangeConfig {
    /// Checks the parameters.
    pub fn validate(&self) -> Result<(), ExperimentError> {
        let bad = |s: &str| Err(ExperimentError::Invalid(s.into()));
        check_capture(
            &self.scenes,
            &self.seeds,
            self.sessions,
            self.step,
            self.lap_frames,
            self.offset,
        )?;
        if !(self.change_distance.is_finite() && self.change_distance > 0.0) {
            return bad("change_distance must be finite and > 0 (metres)");
        }
        if self.thresholds.iter().any(|t| !t.is_finite()) {
            return bad("thresholds must be finite");
        }
        self.tsdf.validate()?;
        self.segment.validate()?;
        Ok(())
    }

    fn verify(&self) -> Verify<'_> {
        Verify {
            matching: &self.matching,
            ransac: &self.ransac,
            correct_tolerance: self.correct_tolerance,
            correct_per_metre: self.correct_per_metre,
        }
    }
}

/// Area-weighted agreement of eq. 5.3's changed vertices with the generator's labels (a
/// vertex is on a moved or added object), summed over the changed-session meshes.
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct GroundTruthAgreement {
    /// Mesh area on the session's true surfaces (within `change_distance` of one), m^2.
    pub area_m2: f64,
    /// Area changed by eq. 5.3, m^2.
    pub eq53_changed_m2: f64,
    /// Area on moved or added objects (generator), m^2.
    pub generator_changed_m2: f64,
    /// Area changed by both, m^2.
    pub both_changed_m2: f64,
    /// Area farther than `change_distance` from every surface of its own session
    /// (reconstruction artefacts: noise, surfaces bridging thin objects), m^2; left out of
    /// the other areas and of the detection scores, since neither label applies to it.
    pub off_surface_m2: f64,
    /// Share of the area on which both labels agree (changed or not), 0-1.
    pub agreement: f64,
    /// `both / eq53`: share of eq. 5.3's changed area that lies on moved or added objects.
    pub eq53_precision: f64,
    /// `both / generator`: share of the moved or added objects' area that eq. 5.3 finds
    /// changed (parts of a moved object near its old place, or near the floor, are not).
    pub eq53_recall: f64,
}

impl GroundTruthAgreement {
    fn add(&mut self, o: &GroundTruthAgreement) {
        self.area_m2 += o.area_m2;
        self.eq53_changed_m2 += o.eq53_changed_m2;
        self.generator_changed_m2 += o.generator_changed_m2;
        self.both_changed_m2 += o.both_changed_m2;
        self.off_surface_m2 += o.off_surface_m2;
    }

    fn finish(mut self) -> Self {
        let ratio = |a: f64, b: f64| if b > 0.0 { a / b } else { f64::NAN };
        let neither =
            self.area_m2 - self.eq53_changed_m2 - self.generator_changed_m2 + self.both_changed_m2;
        self.agreement = ratio(self.both_changed_m2 + neither, self.area_m2);
        self.eq53_precision = ratio(self.both_changed_m2, self.eq53_changed_m2);
        self.eq53_recall = ratio(self.both_changed_m2, self.generator_changed_m2);
        self
    }
}

/// Changed-area detection by one neg-entropy threshold, area-weighted over the vertices of
/// the changed-session meshes.
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct DetectionRow {
    /// Segments with neg-entropy below this are masked as changed.
    pub threshold: f64,
    /// Share of the mesh area masked, 0-1.
    pub masked_share: f64,
    /// Share of the masked area that is changed by eq. 5.3.
    pub precision: f64,
    /// Share of eq. 5.3's changed area that is masked.
    pub recall: f64,
    /// Share of the area on moved or added objects (generator labels) that is masked.
    pub recall_generator: f64,
    /// Share of the unchanged area (eq. 5.3) that is kept.
    pub static_kept: f64,
}

#[derive(Clone, Default)]
struct DetectionAcc {
    masked: f64,
    masked_changed: f64,
    masked_generator: f64,
}

/// One scene, seed and changed session.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct MeshSessionRow {
    /// Scene preset.
    pub scene: String,
    /// Scene seed.
    pub seed: u64,
    /// Changed session (compared with session 0).
    pub session: u32,
    /// Objects moved, removed or added by the generator.
    pub changed_objects: usize,
    /// Vertices of the session's mesh.
    pub vertices: usize,
    /// Triangles of the session's mesh.
    pub triangles: usize,
    /// Segments of the session's mesh.
    pub segments: usize,
    /// Ground truth of this session's mesh.
    pub ground_truth: GroundTruthAgreement,
}

/// Everything [`run_mesh_change_experiment`] measured.
#[derive(Clone, Debug, serde::Serialize)]
pub struct MeshChangeReport {
    /// Per scene, seed and changed session.
    pub sessions: Vec<MeshSessionRow>,
    /// Eq. 5.3 against the generator's labels, over all changed-session meshes.
    pub ground_truth: GroundTruthAgreement,
    /// Changed-area detection per threshold (fig. 5.9 analogue).
    pub detection: Vec<DetectionRow>,
    /// Frame pairs compared.
    pub pairs: usize,
    /// Pairs in which the session-`k` frame sees moved or added objects.
    pub pairs_with_changes: usize,
    /// Matching per threshold, the unmasked one first (fig. 5.10 analogue).
    pub matching: Vec<MatchingRow>,
    /// The same over the views of moved clutter (as in the image experiment).
    pub cluttered_views: Vec<ClutteredViews>,
    /// Median seconds to render and integrate a session's frames.
    pub integrate_s: f64,
    /// Median seconds to extract a session's mesh.
    pub extract_s: f64,
    /// Median seconds to segment a session's mesh.
    pub segment_s: f64,
    /// Median seconds for a changed session's ground truth (both labellings).
    pub ground_truth_s: f64,
}

/// A session's mesh, its segments, and the neg-entropy of every vertex's segment.
struct SegmentedMesh {
    mesh: TriMesh,
    labels: Vec<u32>,
    segments: Vec<Superjut>,
    /// Neg-entropy of each vertex's segment (`-inf` where it has none).
    vertex_neg_entropy: Vec<f64>,
    /// A third of the area of each vertex's triangles, m^2.
    vertex_area: Vec<f64>,
}

fn to_trimesh(m: Mesh) -> TriMesh {
    TriMesh {
        vertices: m.vertices,
        triangles: m.triangles,
        normals: m.normals,
        pixel_of_vertex: Vec::new(),
    }
}

fn dvec(p: [f32; 3]) -> DVec3 {
    DVec3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]))
}

/// A third of the area of each vertex's incident triangles, m^2.
fn vertex_areas(mesh: &TriMesh) -> Vec<f64> {
    let mut area = vec![0.0; mesh.vertices.len()];
    for t in &mesh.triangles {
        let p = t.map(|i| dvec(mesh.vertices[i as usize]));
        let a = 0.5 * (p[1] - p[0]).cross(p[2] - p[0]).length() / 3.0;
        for &i in t {
            area[i as usize] += a;
        }
    }
    area
}

fn segment_of(segments: &[Superjut], label: u32) -> f64 {
    segments
        .get(label as usize)
        .map_or(f64::NEG_INFINITY, |s| s.neg_entropy)
}

/// Renders every frame of one session, integrates it into a TSDF (true poses), extracts and
/// segments the mesh; returns it with the frames at `keep` (ascending indices).
fn capture_session(
    spec: &SourceSpec,
    backend: &ComputeBackend,
    config: &MeshChangeConfig,
    keep: &[usize],
    segmenter: &mut Segmenter,
    times: &mut Times,
) -> Result<(SegmentedMesh, Vec<SequenceFrame>, Scene, PinholeCamera), ExperimentError> {
    let mut source = FrameSource::open_with_sensor(spec, backend, Some(config.sensor.clone()))?;
    let camera = source.camera();
    let FrameSource::Synth(seq, _) = &mut source else {
        return Err(ExperimentError::Invalid(
            "the experiment needs a generated sequence".into(),
        ));
    };
    let scene = Scene::clone(seq.renderer().scene());
    let t = Instant::now();
    let mut volume = TsdfVolume::new(config.tsdf, camera, backend)?;
    let mut kept = Vec::with_capacity(keep.len());
    for i in 0..seq.len() {
        let f = seq.render_frame(i)?;
        volume.integrate(&f.frame.to_rgbd_frame(f.timestamp), &f.world_from_camera)?;
        if keep.binary_search(&i).is_ok() {
            kept.push(f);
        }
    }
    times.integrate.push(t.elapsed().as_secs_f64());
    let t = Instant::now();
    let mesh = to_trimesh(volume.extract_mesh()?);
    drop(volume);
    times.extract.push(t.elapsed().as_secs_f64());
    let t = Instant::now();
    let (labels, segments) = segmenter.segment_mesh(&mesh, &config.segment)?;
    times.segment.push(t.elapsed().as_secs_f64());
    let vertex_neg_entropy = labels.iter().map(|&l| segment_of(&segments, l)).collect();
    let vertex_area = vertex_areas(&mesh);
    Ok((
        SegmentedMesh {
            mesh,
            labels,
            segments,
            vertex_neg_entropy,
            vertex_area,
        },
        kept,
        scene,
        camera,
    ))
}

#[derive(Default)]
struct Times {
    integrate: Vec<f64>,
    extract: Vec<f64>,
    segment: Vec<f64>,
    ground_truth: Vec<f64>,
}

/// Per vertex of `mesh` (world frame): (eq. 5.3 changed, on a moved or added object of
/// `changed_scene`, off every surface of `changed_scene`).
fn ground_truth_labels(
    mesh: &TriMesh,
    reference: &Scene,
    changed_scene: &Scene,
    change_distance: f64,
) -> Vec<(bool, bool, bool)> {
    let changed_ids = changed_scene.changed_objects();
    mesh.vertices
        .par_iter()
        .map(|&v| {
            let p = dvec(v);
            let eq53 = reference.surface_distance(p) > change_distance;
            let mut best = (f64::INFINITY, 0u32);
            for o in changed_scene.objects() {
                for prim in &o.prims {
                    let d = prim.signed_distance(p).abs();
                    if d < best.0 {
                        best = (d, o.id);
                    }
                }
            }
            (
                eq53,
                changed_ids.binary_search(&best.1).is_ok(),
                changed_scene.surface_distance(p) > change_distance,
            )
        })
        .collect()
}

/// ORB features of a frame, lifted to 3D, with the neg-entropy of each keypoint's mesh
/// segment as projected into the frame.
fn prepare(
    frame: SequenceFrame,
    mesh: &SegmentedMesh,
    camera: &PinholeCamera,
    orb: &OrbParams,
) -> Result<Prepared, ExperimentError> {
    let mut features = extract_orb(&frame.frame.intensity, None, orb)?;
    features.lift(&frame.frame.inverse_depth, camera)?;
    let labels = project_labels(
        &mesh.mesh,
        &mesh.labels,
        camera,
        &frame.world_from_camera.inverse(),
    );
    let (w, h) = (frame.frame.width(), frame.frame.height());
    let keypoint_neg_entropy = features
        .keypoints
        .iter()
        .map(|k| {
            let (x, y) = k.nearest_pixel(w, h);
            labels
                .get(y * w + x)
                .map_or(f64::NEG_INFINITY, |&l| segment_of(&mesh.segments, l))
        })
        .collect();
    Ok(Prepared {
        frame,
        juts: None,
        features,
        keypoint_neg_entropy,
    })
}

/// Runs the experiment (see the module docs). `progress` is called with
/// `(sessions done, sessions in all)`, counting session 0 of every scene. Rendering and
/// integration run on `backend`.
pub fn run_mesh_change_experiment(
    config: &MeshChangeConfig,
    backend: &ComputeBackend,
    mut progress: impl FnMut(usize, usize),
) -> Result<MeshChangeReport, ExperimentError> {
    config.validate()?;
    let indices: Vec<usize> = (0..config.lap_frames - config.offset)
        .step_by(config.step)
        .collect();
    let shifted: Vec<usize> = indices.iter().map(|i| i + config.offset).collect();
    let total = config.scenes.len() * config.seeds.len() * (1 + config.sessions as usize);
    let mut thresholds: Vec<Option<f64>> = vec![None];
    thresholds.extend(config.thresholds.iter().map(|&t| Some(t)));
    let mut per_pair: Vec<Vec<RowAcc>> = Vec::new();
    let mut detection = vec![DetectionAcc::default(); config.thresholds.len()];
    let mut truth = GroundTruthAgreement::default();
    let mut rows = Vec::new();
    let mut times = Times::default();
    let (mut done, mut pairs_with_changes) = (0, 0);
    let mut segmenter = Segmenter::new();
    for scene in &config.scenes {
        for &seed in &config.seeds {
            let spec = |session: u32| SourceSpec::Synth {
                spec: format!("{scene}:loop"),
                frames: config.lap_frames,
                width: config.width,
                seed,
                session,
                lap_seconds: None,
            };
            let (mesh0, frames0, scene0, camera) = capture_session(
                &spec(0),
                backend,
                config,
                &indices,
                &mut segmenter,
                &mut times,
            )?;
            let refs = frames0
                .into_iter()
                .map(|f| prepare(f, &mesh0, &camera, &config.orb))
                .collect::<Result<Vec<_>, _>>()?;
            done += 1;
            progress(done, total);
            for session in 1..=config.sessions {
                let (mesh, frames, scene_k, _) = capture_session(
                    &spec(session),
                    backend,
                    config,
                    &shifted,
                    &mut segmenter,
                    &mut times,
                )?;
                let t = Instant::now();
                let labels =
                    ground_truth_labels(&mesh.mesh, &scene0, &scene_k, config.change_distance);
                times.ground_truth.push(t.elapsed().as_secs_f64());
                let mut gt = GroundTruthAgreement::default();
                for (&(eq53, gen, off), &a) in labels.iter().zip(&mesh.vertex_area) {
                    if off {
                        gt.off_surface_m2 += a;
                        continue;
                    }
                    gt.area_m2 += a;
                    if eq53 {
                        gt.eq53_changed_m2 += a;
                    }
                    if gen {
                        gt.generator_changed_m2 += a;
                    }
                    if eq53 && gen {
                        gt.both_changed_m2 += a;
                    }
                }
                for (acc, &t) in detection.iter_mut().zip(&config.thresholds) {
                    for ((&(eq53, gen, off), &a), &ne) in labels
                        .iter()
                        .zip(&mesh.vertex_area)
                        .zip(&mesh.vertex_neg_entropy)
                    {
                        if ne < t && !off {
                            acc.masked += a;
                            if eq53 {
                                acc.masked_changed += a;
                            }
                            if gen {
                                acc.masked_generator += a;
                            }
                        }
                    }
                }
                truth.add(&gt);
                rows.push(MeshSessionRow {
                    scene: scene.clone(),
                    seed,
                    session,
                    changed_objects: scene_k.changed_objects().len(),
                    vertices: mesh.mesh.vertices.len(),
                    triangles: mesh.mesh.triangles.len(),
                    segments: mesh.segments.len(),
                    ground_truth: gt.finish(),
                });
                for (a, f) in refs.iter().zip(frames) {
                    let b = prepare(f, &mesh, &camera, &config.orb)?;
                    if b.frame
                        .frame
                        .moved_mask
                        .as_ref()
                        .is_some_and(|m| m.contains(&true))
                    {
                        pairs_with_changes += 1;
                    }
                    let mut this_pair = vec![RowAcc::default(); thresholds.len()];
                    for (t, acc) in thresholds.iter().zip(this_pair.iter_mut()) {
                        match_pair(a, &b, *t, config.verify(), acc)?;
                    }
                    per_pair.push(this_pair);
                }
                done += 1;
                progress(done, total);
            }
        }
    }
    let truth = truth.finish();
    let ratio = |a: f64, b: f64| if b > 0.0 { a / b } else { f64::NAN };
    let unchanged = truth.area_m2 - truth.eq53_changed_m2;
    let detection = config
        .thresholds
        .iter()
        .zip(&detection)
        .map(|(&threshold, d)| DetectionRow {
            threshold,
            masked_share: ratio(d.masked, truth.area_m2),
            precision: ratio(d.masked_changed, d.masked),
            recall: ratio(d.masked_changed, truth.eq53_changed_m2),
            recall_generator: ratio(d.masked_generator, truth.generator_changed_m2),
            static_kept: ratio(unchanged - (d.masked - d.masked_changed), unchanged),
        })
        .collect();
    let (matching, cluttered_views) = summarise(&thresholds, &per_pair);
    Ok(MeshChangeReport {
        sessions: rows,
        ground_truth: truth,
        detection,
        pairs: per_pair.len(),
        pairs_with_changes,
        matching,
        cluttered_views,
        integrate_s: median(&mut times.integrate),
        extract_s: median(&mut times.extract),
        segment_s: median(&mut times.segment),
        ground_truth_s: median(&mut times.ground_truth),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn vertex_areas_split_each_triangle_in_thirds() {
        let mesh = TriMesh {
            vertices: vec![
                [0.0, 0.0, 0.0],
                [1.0, 0.0, 0.0],
                [0.0, 1.0, 0.0],
                [1.0, 1.0, 0.0],
            ],
            triangles: vec![[0, 1, 2], [1, 3, 2]],
            ..TriMesh::default()
        };
        let a = vertex_areas(&mesh);
        let third = 0.5 / 3.0;
        let want = [third, 2.0 * third, 2.0 * third, third];
        for (got, want) in a.iter().zip(want) {
            assert!((got - want).abs() < 1e-12, "{a:?}");
        }
        assert!((a.iter().sum::<f64>() - 1.0).abs() < 1e-12);
    }

    #[test]
    fn agreement_of_overlapping_labels() {
        let g = GroundTruthAgreement {
            area_m2: 10.0,
            eq53_changed_m2: 2.0,
            generator_changed_m2: 3.0,
            both_changed_m2: 1.5,
            ..Default::default()
        }
        .finish();
        // Disagreement: 0.5 (eq. 5.3 only) + 1.5 (generator only) of 10.
        assert!((g.agreement - 0.8).abs() < 1e-12);
        assert!((g.eq53_precision - 0.75).abs() < 1e-12);
        assert!((g.eq53_recall - 0.5).abs() < 1e-12);
    }

    #[test]
    fn invalid_configs_are_errors() {
        let c = MeshChangeConfig {
            change_distance: 0.0,
            ..Default::default()
        };
        assert!(matches!(c.validate(), Err(ExperimentError::Invalid(_))));
        let c = MeshChangeConfig {
            lap_frames: 2,
            ..Default::default()
        };
        assert!(c.validate().is_err());
    }
}
