//! The viewer's data model: what the SLAM thread has sent so far (or what a finished output
//! folder / map holds), independent of the widgets that show it.

use std::sync::Arc;

use glam::DVec3;
use rgbid::geometry::Se3;
use rgbid::image::ImageF32;
use rgbid::io::run_folder::FrameRow;
use rgbid::odometry::ResidualImages;
use rgbid::slam::FrameStatus;
use rgbid::trajectory::TimedPose;

use crate::output::OutputFolder;
use crate::scene3d::{Geometry, MeshGeometry, Vertex};
pub use crate::worker::Cloud;
use crate::worker::{
    FinishedRun, FrameUpdate, KeyframeDescription, KeyframeUpdate, KeypointMark, LiveCounts,
    LoopUpdate, StartInfo, Update,
};

/// Colours of the 3D view (RGBA8).
pub mod colours {
    /// Estimated trajectory.
    pub const ESTIMATE: [u8; 4] = [255, 150, 30, 255];
    /// Ground truth.
    pub const GROUND_TRUTH: [u8; 4] = [60, 220, 90, 255];
    /// Keyframe frusta.
    pub const KEYFRAME: [u8; 4] = [80, 160, 255, 255];
    /// Current camera.
    pub const CURRENT: [u8; 4] = [255, 255, 255, 255];
    /// Loop edges.
    pub const LOOP: [u8; 4] = [255, 40, 200, 255];
}

/// How the points and the mesh of the 3D view are coloured.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum PointColours {
    /// The colour images' RGB (grey when the run has no colour).
    #[default]
    Colour,
    /// Grey: the intensity (BT.601 luma of the colour).
    Intensity,
}

/// Grey value (0-255) of an RGB colour: its BT.601 luma, as the SLAM intensity.
pub fn intensity_of(c: [u8; 3]) -> u8 {
    rgbid::image::rgb_to_intensity(c[0], c[1], c[2])
        .round()
        .clamp(0.0, 255.0) as u8
}

/// Images of the latest frame and keyframe.
#[derive(Clone, Debug, Default)]
pub struct Panels {
    /// Latest frame's intensity.
    pub intensity: Option<ImageF32>,
    /// Latest frame's inverse depth.
    pub inverse_depth: Option<ImageF32>,
    /// Latest keyframe's intensity (for the overlay).
    pub keyframe_intensity: Option<ImageF32>,
    /// Latest keyframe's superjut colours (w, h, RGB8).
    pub superjuts: Option<(usize, usize, Vec<u8>)>,
    /// Latest keyframe's neg-entropy.
    pub neg_entropy: Option<ImageF32>,
    /// Latest keyframe's ORB keypoints.
    pub keypoints: Vec<KeypointMark>,
    /// Residuals and IRLS weights of the latest frame against its odometry reference, on the
    /// finest optimised pyramid level.
    pub residuals: Option<ResidualImages>,
    /// The latest accepted loop with its images and inlier matches.
    pub loop_accepted: Option<LoopUpdate>,
    /// The latest loop rejected by the checks after verification (dense refinement,
    /// covisibility), with its reason.
    pub loop_rejected: Option<LoopUpdate>,
    /// Why no loop matches can be shown, where that is known (a finished output folder or a
    /// map holds no loop images or matches).
    pub loop_note: Option<String>,
    /// Bumped whenever an image changes (the UI re-uploads its textures).
    pub version: u64,
}

/// Everything the viewer shows.
#[derive(Clone, Default)]
pub struct ViewerState {
    /// Source metadata once the run started.
    pub start: Option<StartInfo>,
    /// Ground truth, if known.
    pub groundtruth: Option<Vec<TimedPose>>,
    /// Index of the latest frame.
    pub last_frame: Option<usize>,
    /// Latest tracking status.
    pub last_status: Option<FrameStatus>,
    /// Keyframes and loops so far (live counters of the SLAM).
    pub keyframe_count: usize,
    /// Accepted loops so far.
    pub loop_count: usize,
    /// Frames processed.
    pub frames_processed: usize,
    /// Image panels.
    pub panels: Panels,
    /// Per-frame statistics for the plots.
    pub stages: Vec<FrameRow>,
    /// Position error against ground truth per frame index (first pose aligned), metres.
    pub position_error: Vec<[f64; 2]>,
    /// Live `world_from_camera` of tracked frames (time stamp, pose).
    pub live_trajectory: Vec<TimedPose>,
    /// Live keyframes: pose and world points.
    pub live_keyframes: Vec<(Se3, Arc<Cloud>)>,
    /// Whether the live keyframes came with colour.
    pub live_coloured: bool,
    /// Counts of live input (live runs only).
    pub live: Option<LiveCounts>,
    /// The result once the run finished (or a loaded folder/map).
    pub finished: Option<FinishedRun>,
    /// Last error of the run.
    pub error: Option<String>,
    /// Geometry of the 3D view (rebuilt on change).
    pub geometry: Arc<Geometry>,
    /// Extra points (benchmark clouds) drawn with the rest.
    pub extra_points: Arc<Vec<Vertex>>,
    point_colours: PointColours,
    geometry_dirty: bool,
    points_dirty: bool,
    gt_alignment: Option<Se3>,
}

fn nearest_pose(poses: &[TimedPose], t: f64) -> Option<&TimedPose> {
    let i = poses.partition_point(|p| p.timestamp < t);
    let cands = [i.checked_sub(1), Some(i)];
    cands
        .into_iter()
        .flatten()
        .filter_map(|k| poses.get(k))
        .min_by(|a, b| (a.timestamp - t).abs().total_cmp(&(b.timestamp - t).abs()))
        .filter(|p| (p.timestamp - t).abs() < 0.05)
}

impl ViewerState {
    /// State showing a finished output folder.
    pub fn from_output(folder: OutputFolder) -> Self {
        let mut s = ViewerState {
            groundtruth: folder.groundtruth,
            stages: folder.stages,
            ..Default::default()
        };
        s.keyframe_count = folder.run.keyframes.len();
        s.loop_count = folder.run.loops.len();
        s.frames_processed = folder.run.trajectory.len();
        s.panels.loop_note = Some(format!(
            "{} accepted loops, but an output folder or map keeps no inlier matches or loop \
             images: run SLAM in the viewer to see them",
            folder.run.loops.len()
        ));
        s.finished = Some(folder.run);
        s.compute_final_error();
        s.geometry_dirty = true;
        s.points_dirty = true;
        s.rebuild_geometry();
        s
    }

    /// State showing a finished run (e.g. a loaded map).
    pub fn from_run(run: FinishedRun) -> Self {
        Self::from_output(OutputFolder {
            run,
            ..Default::default()
        })
    }

    /// Applies one message of the SLAM thread.
    pub fn apply(&mut self, update: Update) {
        match update {
            Update::Started(info) => {
                self.groundtruth = info.groundtruth.clone();
                self.start = Some(*info);
            }
            Update::Frame(f) => self.apply_frame(*f),
            Update::Keyframe(k) => self.apply_keyframe(*k),
            Update::KeyframeDescribed(d) => self.apply_description(*d),
            Update::Loop(l) => {
                if l.accepted {
                    self.panels.loop_accepted = Some(*l);
                } else {
                    self.panels.loop_rejected = Some(*l);
                }
                self.panels.version += 1;
            }
            Update::Finished(r) => {
                self.finished = Some(*r);
                self.compute_final_error();
                self.geometry_dirty = true;
                self.points_dirty = true;
            }
            Update::Live(c) => self.live = Some(c),
            Update::Error(e) => self.error = Some(e),
        }
    }

    /// Whether the points (and mesh) have colour from colour images.
    pub fn has_colour(&self) -> bool {
        match &self.finished {
            Some(run) => run.coloured,
            None => self.live_coloured,
        }
    }

    /// How points and mesh are coloured.
    pub fn point_colours(&self) -> PointColours {
        self.point_colours
    }

    /// Colours points and mesh by `c` (rebuilt on the next [`Self::rebuild_geometry`]).
    pub fn set_point_colours(&mut self, c: PointColours) {
        if c != self.point_colours {
            self.point_colours = c;
            self.points_dirty = true;
        }
    }

    fn apply_frame(&mut self, f: FrameUpdate) {
        let r = &f.report;
        self.last_frame = Some(f.index);
        self.last_status = Some(r.status);
        self.keyframe_count = r.keyframes;
        self.loop_count = r.loops;
        self.frames_processed += 1;
        self.stages.push(FrameRow::from(&r.record));
        if let Some(pose) = r.world_from_camera {
            let tp = TimedPose {
                timestamp: r.record.timestamp,
                world_from_camera: pose,
            };
            if let Some(gt) = self
                .groundtruth
                .as_deref()
                .and_then(|g| nearest_pose(g, tp.timestamp))
            {
                let align = *self
                    .gt_alignment
                    .get_or_insert_with(|| gt.world_from_camera * pose.inverse());
                let e = (align.transform_point(pose.translation)
                    - gt.world_from_camera.translation)
                    .length();
                self.position_error.push([f.index as f64, e]);
            }
            self.live_trajectory.push(tp);
            self.geometry_dirty = true;
        }
        self.panels.intensity = Some(f.intensity);
        self.panels.inverse_depth = Some(f.inverse_depth);
        self.panels.residuals = f.residuals;
        self.panels.version += 1;
    }

    fn apply_keyframe(&mut self, k: KeyframeUpdate) {
        self.live_coloured |= k.coloured;
        self.live_keyframes
            .push((k.world_from_keyframe, Arc::new(k.points)));
        self.geometry_dirty = true;
        self.points_dirty = true;
    }

    fn apply_description(&mut self, d: KeyframeDescription) {
        self.panels.keyframe_intensity = d.intensity;
        self.panels.superjuts = d.superjuts;
        self.panels.neg_entropy = d.neg_entropy;
        self.panels.keypoints = d.keypoints;
        self.panels.version += 1;
    }

    /// Per-frame position error of the final trajectory (replaces the live one).
    fn compute_final_error(&mut self) {
        let (Some(run), Some(gt)) = (&self.finished, &self.groundtruth) else {
            return;
        };
        let mut align = None;
        let mut out = Vec::new();
        for (i, p) in run.trajectory.iter().enumerate() {
            if let Some(g) = nearest_pose(gt, p.timestamp) {
                let a = *align
                    .get_or_insert_with(|| g.world_from_camera * p.world_from_camera.inverse());
                let e = (a.transform_point(p.world_from_camera.translation)
                    - g.world_from_camera.translation)
                    .length();
                out.push([i as f64, e]);
            }
        }
        if !out.is_empty() {
            self.position_error = out;
            self.gt_alignment = align;
        }
    }

    /// Number of points in the 3D view.
    pub fn point_count(&self) -> usize {
        self.geometry.points.len()
    }

    /// Rebuilds the 3D geometry if something changed. Returns whether it did.
    pub fn rebuild_geometry(&mut self) -> bool {
        if !self.geometry_dirty && !self.points_dirty {
            return false;
        }
        let mut g = (*self.geometry).clone();
        let intensity = self.point_colours == PointColours::Intensity;
        let colour = |c: [u8; 3]| {
            if intensity {
                let v = intensity_of(c);
                [v, v, v, 255]
            } else {
                [c[0], c[1], c[2], 255]
            }
        };
        if self.points_dirty {
            self.points_dirty = false;
            let mut pts: Vec<Vertex> = match &self.finished {
                Some(run) => run
                    .model
                    .iter()
                    .map(|(p, c)| Vertex::new(*p, colour(*c)))
                    .collect(),
                None => {
                    let n: usize = self.live_keyframes.iter().map(|k| k.1.len()).sum();
                    let mut pts = Vec::with_capacity(n + self.extra_points.len());
                    for (_, kp) in &self.live_keyframes {
                        pts.extend(kp.iter().map(|(p, c)| Vertex::new(*p, colour(*c))));
                    }
                    pts
                }
            };
            pts.extend_from_slice(&self.extra_points);
            g.points = Arc::new(crate::scene3d::interleave(pts));
            g.points_version += 1;
            let mesh = self.finished.as_ref().and_then(|r| r.mesh.as_ref());
            g.mesh = mesh.map(|m| {
                Arc::new(MeshGeometry {
                    vertices: m
                        .vertices
                        .iter()
                        .map(|(p, c)| Vertex::new(*p, colour(*c)))
                        .collect(),
                    triangles: m.triangles.clone(),
                })
            });
            g.mesh_version += 1;
        }
        if self.geometry_dirty {
            self.geometry_dirty = false;
            g.lines.clear();
            g.lines_version += 1;
            match &self.finished {
                Some(run) => {
                    let traj: Vec<DVec3> = run
                        .trajectory
                        .iter()
                        .map(|p| p.world_from_camera.translation)
                        .collect();
                    g.add_polyline(&traj, colours::ESTIMATE);
                    for k in &run.keyframes {
                        g.add_frustum(&k.world_from_camera, 0.08, colours::KEYFRAME);
                    }
                    for (a, b) in &run.loops {
                        if let (Some(a), Some(b)) = (run.keyframes.get(*a), run.keyframes.get(*b)) {
                            g.add_segment(
                                a.world_from_camera.translation,
                                b.world_from_camera.translation,
                                colours::LOOP,
                            );
                        }
                    }
                }
                None => {
                    let traj: Vec<DVec3> = self
                        .live_trajectory
                        .iter()
                        .map(|p| p.world_from_camera.translation)
                        .collect();
                    g.add_polyline(&traj, colours::ESTIMATE);
                    for (pose, _) in &self.live_keyframes {
                        g.add_frustum(pose, 0.08, colours::KEYFRAME);
                    }
                    if let Some(p) = self.live_trajectory.last() {
                        g.add_frustum(&p.world_from_camera, 0.15, colours::CURRENT);
                    }
                }
            }
            if let (Some(gt), Some(align)) = (&self.groundtruth, self.gt_alignment) {
                // Ground truth in the estimate's world: est_world_from_gt_world = align^-1.
                let inv = align.inverse();
                let pts: Vec<DVec3> = gt
                    .iter()
                    .map(|p| inv.transform_point(p.world_from_camera.translation))
                    .collect();
                g.add_polyline(&pts, colours::GROUND_TRUTH);
            }
        }
        self.geometry = Arc::new(g);
        true
    }

    /// Latest estimated camera position, if any.
    pub fn latest_position(&self) -> Option<DVec3> {
        match &self.finished {
            Some(r) => r.trajectory.last().map(|p| p.world_from_camera.translation),
            None => self
                .live_trajectory
                .last()
                .map(|p| p.world_from_camera.translation),
        }
    }

    /// Adds `n` synthetic points (a noisy sphere shell of radius 2 m around (0, 0, 3)) to the
    /// 3D view, for frame-time measurements with large clouds.
    pub fn add_bench_points(&mut self, n: usize) {
        let mut pts = Vec::with_capacity(n);
        let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
        for i in 0..n {
            let y = 1.0 - 2.0 * (i as f64 + 0.5) / n as f64;
            let r = (1.0 - y * y).sqrt();
            let th = golden * i as f64;
            let p = DVec3::new(r * th.cos(), y, r * th.sin()) * 2.0 + DVec3::new(0.0, 0.0, 3.0);
            let v = (64.0 + 191.0 * (0.5 + 0.5 * y)) as u8;
            pts.push(Vertex::new(p, [v, 255 - v / 2, 255 - v, 255]));
        }
        self.extra_points = Arc::new(pts);
        self.points_dirty = true;
        self.rebuild_geometry();
    }
}
