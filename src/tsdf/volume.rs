//! The volume: parameters, the host's block map and allocation, and the public API.

use std::collections::HashMap;
use std::hash::BuildHasherDefault;

use rayon::prelude::*;
use rustc_hash::FxHasher;

use super::gpu::GpuTsdf;
use super::integrate::{truncation, CpuTsdf, IntegrateUniform, TsdfKernels, Voxel};
use super::mesh::{self, Mesh};
use super::raycast::{self, RayCastImages};
use super::{TsdfError, BLOCK_SIDE, BLOCK_VOXELS};
use crate::camera::PinholeCamera;
use crate::geometry::Se3;
use crate::gpu::ComputeBackend;
use crate::image::RgbdFrame;

pub(crate) type BlockMap = HashMap<[i32; 3], u32, BuildHasherDefault<FxHasher>>;

/// Parameters of the volume and of the sensor noise model.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TsdfParams {
    /// Voxel edge, metres (blocks are 8 voxels along each side).
    pub voxel_size: f64,
    /// Inverse-depth noise of the sensor, sigma_rho in 1/m (Kinect: 0.1 px disparity noise
    /// over focal 525 px times baseline 0.075 m = 0.0025 1/m); depth noise is
    /// `sigma_rho z^2` metres at depth z.
    pub rho_sigma: f64,
    /// Smallest truncation distance, in voxels.
    pub trunc_min_voxels: f64,
    /// Truncation in depth standard deviations (where larger than the minimum).
    pub trunc_sigmas: f64,
    /// Cap of a voxel's accumulated weight (one measurement at 1 m weighs 1), so the volume
    /// can still follow changes.
    pub max_weight: f32,
    /// Nearest depth integrated, metres.
    pub min_depth: f64,
    /// Farthest depth integrated, metres.
    pub max_depth: f64,
}

impl Default for TsdfParams {
    fn default() -> Self {
        TsdfParams {
            voxel_size: 0.01,
            rho_sigma: 0.1 / (525.0 * 0.075),
            trunc_min_voxels: 4.0,
            trunc_sigmas: 3.0,
            max_weight: 100.0,
            min_depth: 0.3,
            max_depth: 4.0,
        }
    }
}

impl TsdfParams {
    /// Checks the ranges.
    pub fn validate(&self) -> Result<(), TsdfError> {
        let pos = |name: &'static str, v: f64| {
            if v.is_finite() && v > 0.0 {
                Ok(())
            } else {
                Err(TsdfError::InvalidParameter {
                    name,
                    why: format!("{v} must be finite and > 0"),
                })
            }
        };
        pos("voxel_size", self.voxel_size)?;
        pos("rho_sigma", self.rho_sigma)?;
        pos("trunc_min_voxels", self.trunc_min_voxels)?;
        pos("max_weight", f64::from(self.max_weight))?;
        pos("min_depth", self.min_depth)?;
        pos("max_depth", self.max_depth)?;
        if !(self.trunc_sigmas.is_finite() && self.trunc_sigmas >= 0.0) {
            return Err(TsdfError::InvalidParameter {
                name: "trunc_sigmas",
                why: format!("{} must be finite and >= 0", self.trunc_sigmas),
            });
        }
        if self.min_depth >= self.max_depth {
            return Err(TsdfError::InvalidParameter {
                name: "min_depth",
                why: format!(
                    "{} must be below max_depth {}",
                    self.min_depth, self.max_depth
                ),
            });
        }
        Ok(())
    }
}

/// Wall time of the stages of one [`TsdfVolume::integrate`] call, seconds.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct IntegrateTimes {
    /// Host block allocation from the frame's depth.
    pub allocate_s: f64,
    /// The integration kernel (GPU: uploads, dispatch and wait).
    pub kernel_s: f64,
    /// Blocks the frame touched.
    pub active_blocks: usize,
}

/// A sparse TSDF volume in the world frame: integrate frames, extract a mesh, ray cast.
pub struct TsdfVolume {
    params: TsdfParams,
    camera: PinholeCamera,
    map: BlockMap,
    /// Block coordinates per slot.
    coords: Vec<[i32; 3]>,
    kernels: Box<dyn TsdfKernels>,
    frames: usize,
    rgb: Vec<u32>,
}

impl TsdfVolume {
    /// An empty volume for frames of `camera` (undistorted pinhole), integrated on `backend`.
    pub fn new(
        params: TsdfParams,
        camera: PinholeCamera,
        backend: &ComputeBackend,
    ) -> Result<Self, TsdfError> {
        params.validate()?;
        camera.validate().map_err(|e| TsdfError::InvalidParameter {
            name: "camera",
            why: e.to_string(),
        })?;
        let kernels: Box<dyn TsdfKernels> = match backend {
            ComputeBackend::Cpu => Box::new(CpuTsdf::default()),
            ComputeBackend::Gpu(ctx) => Box::new(GpuTsdf::new(ctx.clone())?),
        };
        Ok(TsdfVolume {
            params,
            camera,
            map: BlockMap::default(),
            coords: Vec::new(),
            kernels,
            frames: 0,
            rgb: Vec::new(),
        })
    }

    /// The parameters.
    pub fn params(&self) -> &TsdfParams {
        &self.params
    }

    /// Allocated blocks.
    pub fn block_count(&self) -> usize {
        self.coords.len()
    }

    /// Frames integrated so far.
    pub fn frames(&self) -> usize {
        self.frames
    }

    /// Bytes held, `(host, device)`: voxels, the block map and the frame buffers.
    pub fn memory_bytes(&self) -> (usize, usize) {
        let (h, d) = self.kernels.memory_bytes();
        let map = self.map.capacity() * (std::mem::size_of::<[i32; 3]>() + 4 + 1);
        (
            h + map + self.coords.capacity() * 12 + self.rgb.capacity() * 4,
            d,
        )
    }

    fn uniform(&self, camera_from_world: &Se3, active: usize, colour: bool) -> IntegrateUniform {
        let c = &self.camera;
        let p = &self.params;
        let r = camera_from_world.rotation_matrix();
        let t = camera_from_world.translation;
        let mut rows = [[0.0f32; 4]; 3];
        for (i, row) in rows.iter_mut().enumerate() {
            *row = [
                r.row(i).x as f32,
                r.row(i).y as f32,
                r.row(i).z as f32,
                t[i] as f32,
            ];
        }
        IntegrateUniform {
            width: c.width,
            height: c.height,
            active_count: active as u32,
            has_colour: u32::from(colour),
            fx: c.fx as f32,
            fy: c.fy as f32,
            cx: c.cx as f32,
            cy: c.cy as f32,
            camera_from_world: rows,
            voxel_size: p.voxel_size as f32,
            rho_sigma: p.rho_sigma as f32,
            trunc_min: (p.trunc_min_voxels * p.voxel_size) as f32,
            trunc_sigmas: p.trunc_sigmas as f32,
            max_weight: p.max_weight,
            min_rho: (1.0 / p.max_depth) as f32,
            max_rho: (1.0 / p.min_depth) as f32,
            _pad: 0,
        }
    }

    /// The blocks within the truncation band `z +- mu(z)` of every valid pixel of `rho`,
    /// allocating the new ones; returns the frame's active list `[bx, by, bz, slot]`.
    fn allocate(
        &mut self,
        rho: &[f32],
        world_from_camera: &Se3,
        u: &IntegrateUniform,
    ) -> Vec<[i32; 4]> {
        let c = self.camera;
        let w = c.width as usize;
        let r = world_from_camera.rotation_matrix();
        let t = world_from_camera.translation;
        let m = |i: usize, j: usize| r.col(j)[i] as f32;
        let rot = [
            [m(0, 0), m(0, 1), m(0, 2), t.x as f32],
            [m(1, 0), m(1, 1), m(1, 2), t.y as f32],
            [m(2, 0), m(2, 1), m(2, 2), t.z as f32],
        ];
        let block = (self.params.voxel_size * BLOCK_SIDE as f64) as f32;
        let inv_block = 1.0 / block;
        let (fx, fy, cx, cy) = (c.fx as f32, c.fy as f32, c.cx as f32, c.cy as f32);
        let keys: Vec<[i32; 3]> = rho
            .par_chunks(w.max(1))
            .enumerate()
            .flat_map_iter(|(y, row)| {
                let mut out: Vec<[i32; 3]> = Vec::new();
                // The last key per sample along the ray: neighbouring pixels mostly repeat it.
                let mut last: [[i32; 3]; 8] = [[i32::MIN; 3]; 8];
                for (x, &rv) in row.iter().enumerate() {
                    if !(rv >= u.min_rho && rv <= u.max_rho) {
                        continue;
                    }
                    let z = 1.0 / rv;
                    let mu = truncation(u, z);
                    let ray = [(x as f32 - cx) / fx, (y as f32 - cy) / fy, 1.0];
                    // Samples from z - mu to z + mu, at most half a block apart.
                    let steps = ((2.0 * mu / (0.5 * block)).ceil() as usize).clamp(1, 7);
                    for k in 0..=steps {
                        let d = z - mu + 2.0 * mu * k as f32 / steps as f32;
                        if d <= 0.0 {
                            continue;
                        }
                        let pc = [ray[0] * d, ray[1] * d, d];
                        let f = |i: usize| {
                            rot[i][0] * pc[0] + rot[i][1] * pc[1] + rot[i][2] * pc[2] + rot[i][3]
                        };
                        let key = [
                            (f(0) * inv_block).floor() as i32,
                            (f(1) * inv_block).floor() as i32,
                            (f(2) * inv_block).floor() as i32,
                        ];
                        if last[k] != key {
                            last[k] = key;
                            out.push(key);
                        }
                    }
                }
                out
            })
            .collect();
        let mut active = Vec::new();
        let mut seen = BlockMap::default();
        for key in keys {
            if seen.insert(key, 0).is_some() {
                continue;
            }
            let next = self.coords.len() as u32;
            let slot = *self.map.entry(key).or_insert(next);
            if slot == next {
                self.coords.push(key);
            }
            active.push([key[0], key[1], key[2], slot as i32]);
        }
        active
    }

    /// Integrates one frame (inverse depth in 1/m, colour when the frame has it) seen from
    /// `world_from_camera`.
    pub fn integrate(
        &mut self,
        frame: &RgbdFrame,
        world_from_camera: &Se3,
    ) -> Result<IntegrateTimes, TsdfError> {
        let (w, h) = (frame.width(), frame.height());
        if w != self.camera.width as usize || h != self.camera.height as usize {
            return Err(TsdfError::FrameSize {
                got_w: w,
                got_h: h,
                want_w: self.camera.width,
                want_h: self.camera.height,
            });
        }
        if !world_from_camera.is_finite() {
            return Err(TsdfError::NonFinitePose);
        }
        let rho = frame.inverse_depth().data();
        let colour = frame.colour();
        if let Some(c) = colour {
            self.rgb.clear();
            self.rgb.extend(
                c.rgb()
                    .chunks_exact(3)
                    .map(|p| u32::from(p[0]) | (u32::from(p[1]) << 8) | (u32::from(p[2]) << 16)),
            );
        }
        let camera_from_world = world_from_camera.inverse();
        let t0 = std::time::Instant::now();
        let u0 = self.uniform(&camera_from_world, 0, colour.is_some());
        let active = self.allocate(rho, world_from_camera, &u0);
        let t1 = std::time::Instant::now();
        let u = IntegrateUniform {
            active_count: active.len() as u32,
            ..u0
        };
        let rgb = colour.map(|_| self.rgb.as_slice());
        self.kernels
            .integrate(self.coords.len(), &active, rho, rgb, &u)?;
        self.frames += 1;
        Ok(IntegrateTimes {
            allocate_s: (t1 - t0).as_secs_f64(),
            kernel_s: t1.elapsed().as_secs_f64(),
            active_blocks: active.len(),
        })
    }

    /// A copy of the voxels with the block map (the GPU backend reads them back).
    fn snapshot(&self) -> Result<VolumeView<'_>, TsdfError> {
        Ok(VolumeView {
            voxels: self.kernels.voxels()?,
            map: &self.map,
            coords: &self.coords,
            voxel_size: self.params.voxel_size,
        })
    }

    /// The zero level set as a triangle mesh (world frame, metres) with per-vertex normals
    /// and colours, by marching tetrahedra over every observed voxel cube.
    pub fn extract_mesh(&self) -> Result<Mesh, TsdfError> {
        Ok(mesh::extract(&self.snapshot()?))
    }

    /// Depth (metres along the optical axis, 0 = no surface) and normals (camera frame) of
    /// the surface seen by `camera` at `world_from_camera`, ray cast on the CPU.
    pub fn ray_cast(
        &self,
        camera: &PinholeCamera,
        world_from_camera: &Se3,
    ) -> Result<RayCastImages, TsdfError> {
        let view = self.snapshot()?;
        Ok(raycast::cast(
            &view,
            camera,
            world_from_camera,
            (self.params.trunc_min_voxels * self.params.voxel_size) as f32,
            self.params.min_depth as f32,
            self.params.max_depth as f32,
        ))
    }
}

/// Read access to the voxels by global voxel coordinates.
pub(crate) struct VolumeView<'a> {
    pub(crate) voxels: std::borrow::Cow<'a, [Voxel]>,
    pub(crate) map: &'a BlockMap,
    pub(crate) coords: &'a [[i32; 3]],
    pub(crate) voxel_size: f64,
}

impl VolumeView<'_> {
    /// The voxel at global voxel coordinates `g`, `None` when its block is not allocated.
    pub(crate) fn voxel(&self, g: [i32; 3]) -> Option<&Voxel> {
        let n = BLOCK_SIDE as i32;
        let b = [g[0].div_euclid(n), g[1].div_euclid(n), g[2].div_euclid(n)];
        let slot = *self.map.get(&b)? as usize;
        let l = [g[0].rem_euclid(n), g[1].rem_euclid(n), g[2].rem_euclid(n)];
        let i = (l[0] + n * (l[1] + n * l[2])) as usize;
        self.voxels.get(slot * BLOCK_VOXELS + i)
    }
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use super::{TsdfParams, TsdfVolume};
    use crate::camera::PinholeCamera;
    use crate::gpu::{test_gpu, ComputeBackend};
    use crate::synth::{
        CameraModel, RenderBackend, Scene, Sequence, SequenceConfig, Trajectory, TrajectoryKind,
    };

    #[test]
    #[ignore = "needs a GPU adapter"]
    fn gpu_tsdf_integration_matches_the_cpu_mirror() {
        let Some(ctx) = test_gpu("gpu_tsdf_integration_matches_the_cpu_mirror") else {
            return;
        };
        let cam = PinholeCamera::new(131.25, 131.25, 79.5, 59.5, 160, 120);
        let scene = Arc::new(Scene::preset("office", 2).unwrap_or_else(|e| panic!("{e}")));
        let traj = Trajectory::new(TrajectoryKind::Handheld, &scene, 1.0, 2)
            .unwrap_or_else(|e| panic!("{e}"));
        let config = SequenceConfig {
            frames: 6,
            seed: 2,
            ..Default::default()
        };
        let seq = Sequence::new(
            scene,
            CameraModel::Pinhole(cam),
            traj,
            config,
            &RenderBackend::Cpu,
        )
        .unwrap_or_else(|e| panic!("{e}"));
        let params = TsdfParams {
            voxel_size: 0.02,
            ..Default::default()
        };
        let mut cpu =
            TsdfVolume::new(params, cam, &ComputeBackend::Cpu).unwrap_or_else(|e| panic!("{e}"));
        let mut gpu = TsdfVolume::new(params, cam, &ComputeBackend::Gpu(ctx))
            .unwrap_or_else(|e| panic!("{e}"));
        for f in seq {
            let f = f.unwrap_or_else(|e| panic!("{e}"));
            let frame = f.frame.to_rgbd_frame(f.timestamp);
            cpu.integrate(&frame, &f.world_from_camera)
                .unwrap_or_else(|e| panic!("{e}"));
            gpu.integrate(&frame, &f.world_from_camera)
                .unwrap_or_else(|e| panic!("{e}"));
        }
        assert_eq!(cpu.block_count(), gpu.block_count());
        let a = cpu.kernels.voxels().unwrap_or_else(|e| panic!("{e}"));
        let b = gpu.kernels.voxels().unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(a.len(), b.len());
        let observed = a.iter().filter(|v| v.weight > 0.0).count();
        assert!(observed > 50_000, "only {observed} voxels observed");
        // Same f32 operations: differences only from fused multiply-adds and the rare pixel
        // whose projection rounds the other way.
        let mut differ = 0usize;
        for (x, y) in a.iter().zip(b.iter()) {
            let close = (x.tsdf - y.tsdf).abs() <= 1e-5
                && (x.weight - y.weight).abs() <= 1e-4 * x.weight.max(1.0)
                && (0..3).all(|k| {
                    let c = |v: u32| ((v >> (8 * k)) & 255) as i32;
                    (c(x.rgb) - c(y.rgb)).abs() <= 1
                });
            if !close {
                differ += 1;
            }
        }
        assert!(
            (differ as f64) < 1e-3 * observed as f64,
            "{differ} of {observed} observed voxels differ"
        );
    }
}
