//! The 3D model: keyframe point clouds placed by the optimised poses, each keyframe adding
//! only what the previous keyframe did not already see, voxel-grid filtered (written as PLY by [`crate::io::ply`]).

use std::collections::HashMap;
use std::hash::BuildHasherDefault;

use glam::DVec3;
use rayon::prelude::*;
use rustc_hash::FxHasher;

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

/// A TSDF mesh of the keyframes (world frame, metres): the zero level set of
/// [`build_volume`] with the same arguments.
pub fn build_mesh(
    keyframes: &[Keyframe],
    world_from_keyframe: &[Se3],
    camera: &PinholeCamera,
    params: &TsdfParams,
    min_weight: u8,
    backend: &ComputeBackend,
) -> Result<Mesh, TsdfError> {
    build_volume(
        keyframes,
        world_from_keyframe,
        camera,
        params,
        min_weight,
        backend,
    )?
    .extract_mesh()
}

/// A TSDF volume of the keyframes (world frame, metres): every keyframe's fused inverse depth
/// integrated at its pose in `world_from_keyframe` (one per keyframe, e.g. the optimised
/// poses of [`crate::slam::SlamResult::keyframe_poses`]), coloured by the keyframe's colour,
/// or grey from its intensity when it has none.
///
/// The volume is built from scratch for the poses given, which re-integrates every keyframe
/// after a pose-graph optimisation: at one keyframe per few dozen frames the whole map costs
/// about as much to integrate as a second of frames, and nothing of the surface keeps the old
/// poses, so a closed loop gives one wall. Pixels with fusion weight below `min_weight` are
/// left out.
pub fn build_volume(
    keyframes: &[Keyframe],
    world_from_keyframe: &[Se3],
    camera: &PinholeCamera,
    params: &TsdfParams,
    min_weight: u8,
    backend: &ComputeBackend,
) -> Result<TsdfVolume, TsdfError> {
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
        let frame = if frame.colour().is_some() {
            frame
        } else {
            let grey: Vec<u8> = kf.intensity.iter().flat_map(|&v| [v, v, v]).collect();
            frame.with_colour(ColourImage::from_rgb(kf.width, kf.height, grey)?)?
        };
        volume.integrate(&frame, pose)?;
    }
    Ok(volume)
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
    model_grid(keyframes, world_from_keyframe, camera, params).points()
}

/// The points of [`build_model`] with 8-bit RGB colour: the mean colour of the keyframe
/// pixels in each voxel, taken from the keyframes' colour (grey from the intensity for
/// keyframes without colour).
pub fn build_coloured_model(
    keyframes: &[Keyframe],
    world_from_keyframe: &[Se3],
    camera: &PinholeCamera,
    params: &ModelParams,
) -> Vec<(DVec3, [u8; 3])> {
    model_grid(keyframes, world_from_keyframe, camera, params).coloured_points()
}

/// The voxel grid of the model (see [`build_model`]).
fn model_grid(
    keyframes: &[Keyframe],
    world_from_keyframe: &[Se3],
    camera: &PinholeCamera,
    params: &ModelParams,
) -> VoxelGrid {
    let mut grid = VoxelGrid::new(params.voxel);
    // Keyframes' points are found in parallel a few keyframes at a time while the grid takes
    // the previous few, in keyframe order: every voxel's sums and the order in which voxels
    // are first filled are those of one serial pass, and memory stays bounded by the chunk.
    let chunk = rayon::current_num_threads().max(1) * 2;
    let n = keyframes.len().min(world_from_keyframe.len());
    let new_points =
        |k: usize| keyframe_new_points(keyframes, world_from_keyframe, k, camera, params);
    let mut pending: Vec<Vec<ModelPoint>> = Vec::new();
    for start in (0..n).step_by(chunk) {
        let (next, ()) = rayon::join(
            || {
                (start..(start + chunk).min(n))
                    .into_par_iter()
                    .map(new_points)
                    .collect::<Vec<_>>()
            },
            || {
                for points in pending.drain(..) {
                    grid.add_all(points);
                }
            },
        );
        pending = next;
    }
    for points in pending {
        grid.add_all(points);
    }
    grid
}

/// A model point: world position (metres), intensity, RGB.
type ModelPoint = (DVec3, u8, [u8; 3]);

/// The world points (metres) of keyframe `k` that the previous keyframe of the same session
/// did not already see, in pixel order.
fn keyframe_new_points(
    keyframes: &[Keyframe],
    world_from_keyframe: &[Se3],
    k: usize,
    camera: &PinholeCamera,
    params: &ModelParams,
) -> Vec<ModelPoint> {
    let (kf, pose) = (&keyframes[k], &world_from_keyframe[k]);
    let prev = if k > 0 && keyframes[k - 1].session == kf.session {
        Some((
            &keyframes[k - 1],
            world_from_keyframe[k - 1].inverse() * *pose,
        ))
    } else {
        None
    };
    let mut out = Vec::new();
    for (p, i) in kf.pixel_points(camera, params.step, params.min_weight) {
        if let Some((pk, prev_from_this)) = &prev {
            let q = prev_from_this.transform_point(p);
            if q.z > 0.0 {
                let u = (camera.fx * q.x / q.z + camera.cx).round();
                let v = (camera.fy * q.y / q.z + camera.cy).round();
                if u >= 0.0 && v >= 0.0 && (u as usize) < pk.width && (v as usize) < pk.height {
                    let r =
                        f64::from(pk.inverse_depth[v as usize * pk.width + u as usize].to_f32());
                    if r > 0.0 && (r - 1.0 / q.z).abs() < params.seen_tolerance {
                        continue;
                    }
                }
            }
        }
        out.push((pose.transform_point(p), kf.intensity[i], kf.rgb_at(i)));
    }
    out
}

/// One voxel of [`VoxelGrid`]: sum of positions, sums of intensity and of R, G, B, point
/// count.
type Cell = (DVec3, [u32; 4], usize);

/// Running voxel-grid average of position, intensity and RGB (or a plain list when the size
/// is not positive).
struct VoxelGrid {
    size: f64,
    cells: HashMap<(i64, i64, i64), Cell, BuildHasherDefault<FxHasher>>,
    order: Vec<(i64, i64, i64)>,
    raw: Vec<ModelPoint>,
}

impl VoxelGrid {
    fn new(size: f64) -> Self {
        VoxelGrid {
            size,
            cells: HashMap::default(),
            order: Vec::new(),
            raw: Vec::new(),
        }
    }

    fn add_all(&mut self, points: Vec<ModelPoint>) {
        for (p, i, rgb) in points {
            self.add(p, i, rgb);
        }
    }

    fn add(&mut self, p: DVec3, i: u8, rgb: [u8; 3]) {
        if !p.is_finite() {
            return;
        }
        if self.size <= 0.0 {
            self.raw.push((p, i, rgb));
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
            (DVec3::ZERO, [0; 4], 0)
        });
        e.0 += p;
        for (sum, v) in e.1.iter_mut().zip([i, rgb[0], rgb[1], rgb[2]]) {
            *sum += u32::from(v);
        }
        e.2 += 1;
    }

    /// Mean position and the means of intensity and R, G, B (rounded down) per cell, in the
    /// order the cells were first filled.
    fn means(&self) -> impl Iterator<Item = (DVec3, [u8; 4])> + '_ {
        self.order
            .iter()
            .filter_map(|k| self.cells.get(k))
            .map(|(s, sums, n)| (*s / *n as f64, sums.map(|v| (v / *n as u32) as u8)))
    }

    fn points(self) -> Vec<(DVec3, u8)> {
        if self.size <= 0.0 {
            return self.raw.into_iter().map(|(p, i, _)| (p, i)).collect();
        }
        self.means().map(|(p, m)| (p, m[0])).collect()
    }

    fn coloured_points(self) -> Vec<(DVec3, [u8; 3])> {
        if self.size <= 0.0 {
            return self.raw.into_iter().map(|(p, _, c)| (p, c)).collect();
        }
        self.means().map(|(p, m)| (p, [m[1], m[2], m[3]])).collect()
    }
}

/// Voxel-grid filter: one point per occupied voxel of `size` metres (the mean of its points
/// and intensities). `size <= 0` returns the input.
pub fn voxel_filter(points: &[(DVec3, u8)], size: f64) -> Vec<(DVec3, u8)> {
    let mut grid = VoxelGrid::new(size);
    for (p, i) in points {
        grid.add(*p, *i, [*i; 3]);
    }
    grid.points()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::slam::keyframe::KeyframeLink;
    use half::f16;

    const W: usize = 8;
    const H: usize = 6;

    /// A keyframe of a wall 2 m in front of the camera, intensity `10 + i`, colour
    /// `(i, 2 i, 255 - i)` per pixel index `i` when `colour`.
    fn keyframe(colour: bool) -> Keyframe {
        let kf = Keyframe {
            id: 0,
            frame_index: 0,
            session: 0,
            timestamp: 0.0,
            width: W,
            height: H,
            intensity: (0..W * H).map(|i| 10 + i as u8).collect(),
            inverse_depth: vec![f16::from_f32(0.5); W * H],
            weight: vec![5; W * H],
            colour: None,
            world_from_keyframe: Se3::IDENTITY,
            link: KeyframeLink::First,
        };
        if !colour {
            return kf;
        }
        let rgb = (0..W * H)
            .flat_map(|i| [i as u8, 2 * i as u8, 255 - i as u8])
            .collect();
        kf.with_colour(ColourImage::from_rgb(W, H, rgb).unwrap())
            .unwrap()
    }

    #[test]
    fn keyframes_found_in_parallel_accumulate_as_one_serial_pass() {
        let camera = PinholeCamera::new(10.0, 10.0, 3.5, 2.5, W as u32, H as u32);
        // More keyframes than one parallel chunk holds, stepping sideways by less than the
        // wall's width so that each one sees part of the last one's points, and a second
        // session from the sixth on (nothing of the first session counts as seen there).
        let keyframes: Vec<Keyframe> = (0..11)
            .map(|k| Keyframe {
                id: k,
                session: u32::from(k >= 5),
                intensity: (0..W * H).map(|i| (7 * k + i) as u8).collect(),
                ..keyframe(false)
            })
            .collect();
        let poses: Vec<Se3> = (0..11)
            .map(|k| Se3::new(glam::DQuat::IDENTITY, DVec3::new(0.13 * k as f64, 0.0, 0.0)))
            .collect();
        for voxel in [0.0, 0.05, 0.3] {
            let params = ModelParams {
                step: 1,
                voxel,
                ..ModelParams::default()
            };
            let mut serial = VoxelGrid::new(voxel);
            let mut dropped = 0;
            for k in 0..keyframes.len() {
                let points = keyframe_new_points(&keyframes, &poses, k, &camera, &params);
                dropped += W * H - points.len();
                serial.add_all(points);
            }
            assert!(dropped > 0, "some points count as already seen");
            let serial = serial.coloured_points();
            let found = build_coloured_model(&keyframes, &poses, &camera, &params);
            assert_eq!(found.len(), serial.len());
            for (a, b) in found.iter().zip(&serial) {
                assert_eq!(
                    a.0.to_array().map(f64::to_bits),
                    b.0.to_array().map(f64::to_bits)
                );
                assert_eq!(a.1, b.1);
            }
        }
    }

    #[test]
    fn model_points_carry_the_keyframe_colour() {
        let camera = PinholeCamera::new(10.0, 10.0, 3.5, 2.5, W as u32, H as u32);
        let every = ModelParams {
            step: 1,
            voxel: 0.0,
            ..ModelParams::default()
        };
        // Placed so that every point has positive coordinates (one voxel of 10 m holds all).
        let poses = [Se3::new(glam::DQuat::IDENTITY, DVec3::new(5.0, 5.0, 0.0))];
        // Every pixel a point: its own colour, and the intensity model is unchanged.
        let kf = keyframe(true);
        let coloured = build_coloured_model(std::slice::from_ref(&kf), &poses, &camera, &every);
        let grey = build_model(std::slice::from_ref(&kf), &poses, &camera, &every);
        assert_eq!(coloured.len(), W * H);
        assert_eq!(grey.len(), W * H);
        for (i, ((p, c), (q, g))) in coloured.iter().zip(&grey).enumerate() {
            assert_eq!(p, q);
            assert_eq!(*c, [i as u8, 2 * i as u8, 255 - i as u8]);
            assert_eq!(*g, 10 + i as u8);
        }
        // One voxel around the whole wall: the mean colour (rounded down).
        let one = ModelParams {
            voxel: 10.0,
            ..every
        };
        let c = build_coloured_model(std::slice::from_ref(&kf), &poses, &camera, &one);
        let n = (W * H) as u32;
        let mean = |f: &dyn Fn(u32) -> u32| ((0..n).map(f).sum::<u32>() / n) as u8;
        assert_eq!(c.len(), 1);
        assert_eq!(c[0].1, [mean(&|i| i), mean(&|i| 2 * i), mean(&|i| 255 - i)]);
        // A keyframe without colour gives grey points of its intensity.
        let g = build_coloured_model(&[keyframe(false)], &poses, &camera, &every);
        assert!(g
            .iter()
            .enumerate()
            .all(|(i, (_, c))| *c == [10 + i as u8; 3]));
    }
}
