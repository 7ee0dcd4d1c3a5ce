//! The 3D model: keyframe point clouds placed by the optimised poses, each keyframe adding
//! only what the previous keyframe did not already see, voxel-grid filtered (written as PLY by [`crate::io::ply`]).

use std::collections::HashMap;

use glam::DVec3;

use super::keyframe::Keyframe;
use crate::camera::PinholeCamera;
use crate::geometry::Se3;
use crate::gpu::ComputeBackend;
use crate::image::ColourImage;
use crate::tsdf::{Mesh, TsdfError, TsdfParams, TsdfVolume};

/// Model parameters.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ModelParams {
    /// Take every `step`-th pixel in x and y.
    pub step: usize,
    /// Least fusion weight of a pixel to be used.
    pub min_weight: u8,
    /// Voxel size of the final filter, metres (0 = no filter).
    pub voxel: f64,
    /// Inverse-depth tolerance (1/m) under which a point counts as already seen by the
    /// previous keyframe.
    pub seen_tolerance: f64,
}

impl Default for ModelParams {
    fn default() -> Self {
        ModelParams {
            step: 2,
            min_weight: 2,
            voxel: 0.01,
            seen_tolerance: 0.02,
        }
    }
}

/// A TSDF mesh of the keyframes (world frame, metres): every keyframe's fused inverse depth
/// integrated at its pose in `world_from_keyframe` (one per keyframe, e.g. the optimised
/// poses of [`crate::slam::SlamResult::keyframe_poses`]), coloured by its intensity (grey:
/// keyframes keep no colour).
///
/// The volume is built from scratch for the poses given, which re-integrates every keyframe
/// after a pose-graph optimisation: at one keyframe per few dozen frames the whole map costs
/// about as much to integrate as a second of frames, and nothing of the surface keeps the old
/// poses, so a closed loop gives one wall. Pixels with fusion weight below `min_weight` are
/// left out.
pub fn build_mesh(
    keyframes: &[Keyframe],
    world_from_keyframe: &[Se3],
    camera: &PinholeCamera,
    params: &TsdfParams,
    min_weight: u8,
    backend: &ComputeBackend,
) -> Result<Mesh, TsdfError> {
    let mut volume = TsdfVolume::new(*params, *camera, backend)?;
    for (kf, pose) in keyframes.iter().zip(world_from_keyframe.iter()) {
        let mut frame = kf.frame();
        for (r, &w) in frame
            .inverse_depth_mut()
            .data_mut()
            .iter_mut()
            .zip(&kf.weight)
        {
            if w < min_weight {
                *r = 0.0;
            }
        }
        let grey: Vec<u8> = kf.intensity.iter().flat_map(|&v| [v, v, v]).collect();
        let frame = frame.with_colour(ColourImage::from_rgb(kf.width, kf.height, grey)?)?;
        volume.integrate(&frame, pose)?;
    }
    volume.extract_mesh()
}

/// Points of the model in the world frame (metres) with their intensity: every keyframe's
/// points, minus those the previous keyframe already had, placed with `world_from_keyframe`,
/// accumulated straight into the voxel grid of `params.voxel` (so memory follows the model's
/// size, not the number of keyframe pixels); `voxel <= 0` keeps every point.
pub fn build_model(
    keyframes: &[Keyframe],
    world_from_keyframe: &[Se3],
    camera: &PinholeCamera,
    params: &ModelParams,
) -> Vec<(DVec3, u8)> {
    let mut grid = VoxelGrid::new(params.voxel);
    for (k, (kf, pose)) in keyframes.iter().zip(world_from_keyframe.iter()).enumerate() {
        let prev = if k > 0 && keyframes[k - 1].session == kf.session {
            Some((
                &keyframes[k - 1],
                world_from_keyframe[k - 1].inverse() * *pose,
            ))
        } else {
            None
        };
        for (p, i) in kf.points(camera, params.step, params.min_weight) {
            if let Some((pk, prev_from_this)) = &prev {
                let q = prev_from_this.transform_point(p);
                if q.z > 0.0 {
                    let u = (camera.fx * q.x / q.z + camera.cx).round();
                    let v = (camera.fy * q.y / q.z + camera.cy).round();
                    if u >= 0.0 && v >= 0.0 && (u as usize) < pk.width && (v as usize) < pk.height {
                        let r = f64::from(
                            pk.inverse_depth[v as usize * pk.width + u as usize].to_f32(),
                        );
                        if r > 0.0 && (r - 1.0 / q.z).abs() < params.seen_tolerance {
                            continue;
                        }
                    }
                }
            }
            grid.add(pose.transform_point(p), i);
        }
    }
    grid.points()
}

/// Running voxel-grid average (or a plain list when the size is not positive).
struct VoxelGrid {
    size: f64,
    cells: HashMap<(i64, i64, i64), (DVec3, u32, usize)>,
    order: Vec<(i64, i64, i64)>,
    raw: Vec<(DVec3, u8)>,
}

impl VoxelGrid {
    fn new(size: f64) -> Self {
        VoxelGrid {
            size,
            cells: HashMap::new(),
            order: Vec::new(),
            raw: Vec::new(),
        }
    }

    fn add(&mut self, p: DVec3, i: u8) {
        if !p.is_finite() {
            return;
        }
        if self.size <= 0.0 {
            self.raw.push((p, i));
            return;
        }
        let key = (
            (p.x / self.size).floor() as i64,
            (p.y / self.size).floor() as i64,
            (p.z / self.size).floor() as i64,
        );
        let order = &mut self.order;
        let e = self.cells.entry(key).or_insert_with(|| {
            order.push(key);
            (DVec3::ZERO, 0, 0)
        });
        e.0 += p;
        e.1 += u32::from(i);
        e.2 += 1;
    }

    fn points(self) -> Vec<(DVec3, u8)> {
        if self.size <= 0.0 {
            return self.raw;
        }
        self.order
            .iter()
            .filter_map(|k| self.cells.get(k))
            .map(|(s, i, n)| (*s / *n as f64, (*i / *n as u32) as u8))
            .collect()
    }
}

/// Voxel-grid filter: one point per occupied voxel of `size` metres (the mean of its points
/// and intensities). `size <= 0` returns the input.
pub fn voxel_filter(points: &[(DVec3, u8)], size: f64) -> Vec<(DVec3, u8)> {
    let mut grid = VoxelGrid::new(size);
    for (p, i) in points {
        grid.add(*p, *i);
    }
    grid.points()
}
