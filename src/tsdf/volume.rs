//! The volume: parameters, the host's block map and allocation, and the public API.

use std::collections::HashMap;
use std::hash::BuildHasherDefault;
use std::path::Path;

use rayon::prelude::*;
use rustc_hash::FxHasher;

use super::gpu::GpuTsdf;
use super::integrate::{truncation, CpuTsdf, IntegrateUniform, TsdfKernels, Voxel};
use super::mesh::{self, CubeTriangles, Mesh, MeshUniform};
use super::paging::{PagingStats, Residency};
use super::persist;
use super::raycast::{self, CastUniform, RayCastImages};
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
    /// Most voxel blocks resident on the GPU at once (each 8^3 voxels of 12 bytes, 6144
    /// bytes), >= 1; `None` = unbounded. Beyond it, the blocks farthest from the camera that
    /// a frame does not touch are moved to host memory and back when a frame needs them
    /// again; a frame touching more blocks is integrated in chunks. Saved files are the
    /// same as without a budget; meshes and ray casts are the CPU mirror's while blocks are
    /// paged out (without a budget the GPU kernels', equal within their parity tolerance).
    /// The CPU backend ignores it (its voxels are host memory). A property of the run, not of the volume: files do not store it.
    pub device_blocks: Option<usize>,
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
            device_blocks: None,
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
        if self.device_blocks == Some(0) {
            return Err(TsdfError::InvalidParameter {
                name: "device_blocks",
                why: "0 must be >= 1 (or unbounded)".into(),
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
    /// The integration kernel (GPU: uploads, dispatch and wait, with any paging of blocks
    /// between device and host).
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
    /// Device slot or host copy of every block.
    residency: Residency,
    /// The kernels keep voxels on a device (a budget applies).
    on_device: bool,
    frames: usize,
    rgb: Vec<u32>,
    /// Camera centre of the last integrated frame, world frame, metres.
    last_camera: [f64; 3],
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
        let (mut kernels, on_device): (Box<dyn TsdfKernels>, bool) = match backend {
            ComputeBackend::Cpu => (Box::new(CpuTsdf::default()), false),
            ComputeBackend::Gpu(ctx) => (Box::new(GpuTsdf::new(ctx.clone())?), true),
        };
        let budget = params.device_blocks.filter(|_| on_device);
        kernels.set_slot_limit(budget)?;
        Ok(TsdfVolume {
            params,
            camera,
            map: BlockMap::default(),
            coords: Vec::new(),
            kernels,
            residency: Residency::new(budget),
            on_device,
            frames: 0,
            rgb: Vec::new(),
            last_camera: [0.0; 3],
        })
    }

    /// The parameters.
    pub fn params(&self) -> &TsdfParams {
        &self.params
    }

    /// The camera of the integrated frames (undistorted pinhole, pixels).
    pub fn camera(&self) -> &PinholeCamera {
        &self.camera
    }

    /// Saves the volume (parameters, camera, frame count, blocks and voxels) to `path` in
    /// rgbid's versioned binary format (`.tsdf`, little-endian, with a CRC-32), replacing the
    /// file atomically; the GPU backend reads the voxels back from the device first.
    pub fn save(&self, path: &Path) -> Result<(), TsdfError> {
        let voxels = self.voxels_by_block()?;
        let header = persist::Header {
            params: self.params,
            camera: self.camera,
            frames: self.frames as u64,
        };
        crate::io::write_atomic(path, |w| persist::write(w, &header, &self.coords, &voxels))?;
        Ok(())
    }

    /// Loads a volume saved by [`TsdfVolume::save`], its voxels placed on `backend`. Frames
    /// integrated later are of `camera` (undistorted pinhole, pixels) when given, else of the
    /// saved camera. The loaded volume extracts the same mesh, ray casts the same images and
    /// integrates further frames exactly as the saved one. A missing, truncated, corrupt or
    /// other-version file is an error naming the file and the cause.
    pub fn load(
        path: &Path,
        camera: Option<PinholeCamera>,
        backend: &ComputeBackend,
    ) -> Result<Self, TsdfError> {
        let (header, coords, voxels) = persist::read(path)?;
        let mut volume = TsdfVolume::new(header.params, camera.unwrap_or(header.camera), backend)?;
        let mut map = BlockMap::default();
        map.reserve(coords.len());
        for (slot, c) in coords.iter().enumerate() {
            if map.insert(*c, slot as u32).is_some() {
                return Err(TsdfError::Io(crate::io::IoError::Malformed {
                    path: path.to_path_buf(),
                    message: format!("block {c:?} appears twice"),
                }));
            }
        }
        volume.kernels.set_voxels(coords.len(), &voxels)?;
        volume.residency.reset_resident(coords.len());
        volume.map = map;
        volume.coords = coords;
        volume.frames = usize::try_from(header.frames).unwrap_or(usize::MAX);
        Ok(volume)
    }

    /// Allocated blocks.
    pub fn block_count(&self) -> usize {
        self.coords.len()
    }

    /// Frames integrated so far.
    pub fn frames(&self) -> usize {
        self.frames
    }

    /// Bytes held, `(host, device)`: voxels (on the GPU backend, the device's slots and the
    /// host's paged-out blocks), the block map and the frame buffers.
    pub fn memory_bytes(&self) -> (usize, usize) {
        let (h, d) = self.kernels.memory_bytes();
        let map = self.map.capacity() * (std::mem::size_of::<[i32; 3]>() + 4 + 1);
        (
            h + map
                + self.coords.capacity() * 12
                + self.rgb.capacity() * 4
                + self.residency.host_bytes(),
            d,
        )
    }

    /// Where the blocks are and how many moved: on the GPU backend, blocks in device slots
    /// and blocks paged out to host memory; on the CPU backend every block counts as
    /// resident (its storage is host memory) and nothing is paged.
    pub fn paging(&self) -> PagingStats {
        self.residency.stats()
    }

    /// Blocks the device's voxel storage holds now (its capacity; 0 on the CPU backend).
    pub fn device_block_capacity(&self) -> usize {
        if self.on_device {
            self.kernels.slot_capacity()
        } else {
            0
        }
    }

    /// Sets the device budget (see [`TsdfParams::device_blocks`], >= 1 or `None`), e.g. of a
    /// loaded volume: when fewer blocks may stay than are resident, those farthest from the
    /// last integrated camera (else the world origin) move to host memory now.
    pub fn set_device_blocks(&mut self, budget: Option<usize>) -> Result<(), TsdfError> {
        let params = TsdfParams {
            device_blocks: budget,
            ..self.params
        };
        params.validate()?;
        self.params = params;
        if !self.on_device {
            return Ok(());
        }
        let camera = self.camera_in_blocks(self.last_camera);
        self.residency
            .set_budget(budget, camera, &self.coords, self.kernels.as_mut())?;
        self.kernels.set_slot_limit(budget)
    }

    fn camera_in_blocks(&self, centre: [f64; 3]) -> [f64; 3] {
        let block = self.params.voxel_size * BLOCK_SIDE as f64;
        centre.map(|c| c / block)
    }

    /// All voxels in block order ([`BLOCK_VOXELS`] per block, as saved files hold them):
    /// the device's slots read back and the host's paged-out blocks.
    fn voxels_by_block(&self) -> Result<std::borrow::Cow<'_, [Voxel]>, TsdfError> {
        let stored = self.kernels.voxels()?;
        if self.residency.is_identity() {
            return Ok(stored);
        }
        let mut out = vec![Voxel::default(); self.coords.len() * BLOCK_VOXELS];
        for (id, dst) in out.chunks_exact_mut(BLOCK_VOXELS).enumerate() {
            let src = match self.residency.slot(id) {
                Some(s) => {
                    let s = s as usize;
                    stored.get(s * BLOCK_VOXELS..(s + 1) * BLOCK_VOXELS)
                }
                None => self.residency.host_voxels(id),
            };
            if let Some(src) = src {
                dst.copy_from_slice(src);
            }
        }
        Ok(std::borrow::Cow::Owned(out))
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

    /// The blocks within the truncation band `z +- mu(z)` of the valid pixels of `rho`,
    /// allocating the new ones; returns the frame's active list `[bx, by, bz, slot]`, sorted
    /// by block coordinates.
    ///
    /// Rows are processed in parallel chunks; each chunk deduplicates its keys (packed into
    /// integers, sorted), the chunks' keys are merged the same way, and only the unique keys
    /// of the frame reach the (single-threaded) block map.
    fn allocate(
        &mut self,
        rho: &[f32],
        world_from_camera: &Se3,
        u: &IntegrateUniform,
    ) -> Result<Vec<[i32; 4]>, TsdfError> {
        let c = self.camera;
        let w = c.width as usize;
        let h = c.height as usize;
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
        let stride = allocation_stride(&self.params, &c);
        // Ray directions in the camera (z = 1) per column and row.
        let ray_x: Vec<f32> = (0..w).map(|x| (x as f32 - cx) / fx).collect();
        let rows: Vec<usize> = (0..h).step_by(stride).collect();
        // Camera centre in block units: a sample at depth d on a ray is `origin + d * dir`.
        let origin = [
            rot[0][3] * inv_block,
            rot[1][3] * inv_block,
            rot[2][3] * inv_block,
        ];
        let half_block = 0.5 * block;
        let chunk_rows = 8usize;
        let chunks: Vec<Result<Vec<u64>, TsdfError>> = rows
            .par_chunks(chunk_rows)
            .map(|ys| {
                let mut out: Vec<u64> = Vec::new();
                let mut outside = false;
                for &y in ys {
                    let row = &rho[y * w..(y + 1) * w];
                    let ry = (y as f32 - cy) / fy;
                    // The last key per sample along the ray: neighbouring pixels mostly
                    // repeat it.
                    let mut last = [u64::MAX; 8];
                    for x in (0..w).step_by(stride) {
                        let rv = row[x];
                        if !(rv >= u.min_rho && rv <= u.max_rho) {
                            continue;
                        }
                        let z = 1.0 / rv;
                        let mu = truncation(u, z);
                        let rx = ray_x[x];
                        // The ray's direction in the world, in block units per metre of depth.
                        let dir = [
                            (rot[0][0] * rx + rot[0][1] * ry + rot[0][2]) * inv_block,
                            (rot[1][0] * rx + rot[1][1] * ry + rot[1][2]) * inv_block,
                            (rot[2][0] * rx + rot[2][1] * ry + rot[2][2]) * inv_block,
                        ];
                        // Samples from z - mu to z + mu, at most half a block apart (the
                        // truncation rounds up without a libm call).
                        let steps = ((2.0 * mu / half_block) as usize + 1).min(7);
                        let step = 2.0 * mu / steps as f32;
                        for (k, last_k) in last.iter_mut().enumerate().take(steps + 1) {
                            let d = z - mu + step * k as f32;
                            if d <= 0.0 {
                                continue;
                            }
                            let key = pack_key([
                                origin[0] + d * dir[0],
                                origin[1] + d * dir[1],
                                origin[2] + d * dir[2],
                            ]);
                            match key {
                                Some(key) if *last_k != key => {
                                    *last_k = key;
                                    out.push(key);
                                }
                                Some(_) => {}
                                None => outside = true,
                            }
                        }
                    }
                }
                if outside {
                    return Err(TsdfError::OutOfRange);
                }
                out.sort_unstable();
                out.dedup();
                Ok(out)
            })
            .collect();
        let mut keys = Vec::new();
        for c in chunks {
            keys.extend(c?);
        }
        keys.par_sort_unstable();
        keys.dedup();
        let mut active = Vec::with_capacity(keys.len());
        self.map.reserve(keys.len());
        for packed in keys {
            let key = unpack_key(packed);
            let next = self.coords.len() as u32;
            let slot = *self.map.entry(key).or_insert(next);
            if slot == next {
                self.coords.push(key);
            }
            active.push([key[0], key[1], key[2], slot as i32]);
        }
        Ok(active)
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
        let active = self.allocate(rho, world_from_camera, &u0)?;
        let t1 = std::time::Instant::now();
        let u = IntegrateUniform {
            active_count: active.len() as u32,
            ..u0
        };
        let rgb = colour.map(|_| self.rgb.as_slice());
        let t = world_from_camera.translation;
        self.last_camera = [t.x, t.y, t.z];
        let camera = self.camera_in_blocks(self.last_camera);
        self.residency.integrate_chunks(
            self.coords.len(),
            &active,
            camera,
            &self.coords,
            self.kernels.as_mut(),
            |kernels, slots, part| {
                let u = IntegrateUniform {
                    active_count: part.len() as u32,
                    ..u
                };
                kernels.integrate(slots, part, rho, rgb, &u)
            },
        )?;
        self.frames += 1;
        Ok(IntegrateTimes {
            allocate_s: (t1 - t0).as_secs_f64(),
            kernel_s: t1.elapsed().as_secs_f64(),
            active_blocks: active.len(),
        })
    }

    /// All voxels, block after block (read back from the device on the GPU backend).
    #[cfg(test)]
    pub(crate) fn kernels_voxels(&self) -> Vec<super::integrate::Voxel> {
        self.voxels_by_block()
            .unwrap_or_else(|e| panic!("{e}"))
            .into_owned()
    }

    /// A copy of the voxels with the block map (the GPU backend reads them back).
    fn snapshot(&self) -> Result<VolumeView<'_>, TsdfError> {
        Ok(VolumeView {
            voxels: self.voxels_by_block()?,
            map: &self.map,
            coords: &self.coords,
            voxel_size: self.params.voxel_size,
        })
    }

    /// The zero level set as a triangle mesh (world frame, metres) with per-vertex normals
    /// and colours, by marching tetrahedra over every observed voxel cube. On the GPU backend
    /// the kernel does the per-cube work where the voxels are (the CPU mirror when a device
    /// budget pages blocks out); sharing vertices and the normals are the host's.
    pub fn extract_mesh(&self) -> Result<Mesh, TsdfError> {
        Ok(mesh::assemble(&self.mesh_cubes()?))
    }

    /// The per-cube triangles, by the backend's kernel when every block is in its device
    /// slot, else by the CPU mirror over every block.
    fn mesh_cubes(&self) -> Result<CubeTriangles, TsdfError> {
        if self.on_device && self.residency.is_identity() {
            // Without paging every block's slot is its id.
            let blocks: Vec<([i32; 3], u32)> = self.map.iter().map(|(b, &id)| (*b, id)).collect();
            let table = raycast::block_table(&blocks);
            let coords: Vec<[i32; 4]> = self.coords.iter().map(|c| [c[0], c[1], c[2], 0]).collect();
            let u = MeshUniform {
                table_mask: (table.len().max(1) - 1) as u32,
                blocks: coords.len() as u32,
                rows: 0,
                voxel_size: self.params.voxel_size as f32,
            };
            if let Some(out) = self.kernels.mesh_cubes(&table, &coords, &u)? {
                return Ok(out);
            }
        }
        self.mesh_cubes_cpu()
    }

    /// The CPU mirror's per-cube triangles of every block (read back from the device on the
    /// GPU backend).
    fn mesh_cubes_cpu(&self) -> Result<CubeTriangles, TsdfError> {
        Ok(mesh::cube_triangles(&self.snapshot()?))
    }

    /// Depth (metres along the optical axis, 0 = no surface), normals (camera frame) and
    /// colour of the surface seen by `camera` at `world_from_camera`, ray cast by the volume's
    /// backend (by the CPU when a device budget pages blocks out).
    pub fn ray_cast(
        &self,
        camera: &PinholeCamera,
        world_from_camera: &Se3,
    ) -> Result<RayCastImages, TsdfError> {
        self.cast(camera, world_from_camera, true)
    }

    /// [`Self::ray_cast`] without the normals (left `[0; 3]`): depth and colour only.
    pub(crate) fn ray_cast_depth_colour(
        &self,
        camera: &PinholeCamera,
        world_from_camera: &Se3,
    ) -> Result<RayCastImages, TsdfError> {
        self.cast(camera, world_from_camera, false)
    }

    /// The largest march step in free space (the smallest truncation, m) and the searched
    /// depth range (m) of a ray cast.
    fn cast_limits(&self) -> (f32, (f32, f32)) {
        let p = &self.params;
        (
            (p.trunc_min_voxels * p.voxel_size) as f32,
            (p.min_depth as f32, p.max_depth as f32),
        )
    }

    /// On the GPU backend the kernel casts the voxels where they are, unless blocks may be
    /// paged out to host memory (a device budget is set): the CPU mirror then casts every
    /// block, so a cast never misses surface the volume holds.
    fn cast(
        &self,
        camera: &PinholeCamera,
        world_from_camera: &Se3,
        with_normals: bool,
    ) -> Result<RayCastImages, TsdfError> {
        if self.on_device && self.residency.is_identity() {
            // Without paging every block's slot is its id.
            let blocks: Vec<([i32; 3], u32)> = self.map.iter().map(|(b, &id)| (*b, id)).collect();
            let table = raycast::block_table(&blocks);
            let (step, range) = self.cast_limits();
            let u = CastUniform::new(
                camera,
                world_from_camera,
                self.params.voxel_size,
                step,
                range,
                table.len(),
                with_normals,
            );
            if let Some(out) = self.kernels.ray_cast(&table, &u)? {
                return Ok(out);
            }
        }
        self.cast_cpu(camera, world_from_camera, with_normals)
    }

    /// The CPU mirror's ray cast of every block (read back from the device on the GPU
    /// backend).
    fn cast_cpu(
        &self,
        camera: &PinholeCamera,
        world_from_camera: &Se3,
        with_normals: bool,
    ) -> Result<RayCastImages, TsdfError> {
        let view = self.snapshot()?;
        let (step, range) = self.cast_limits();
        Ok(raycast::cast(
            &view,
            camera,
            world_from_camera,
            step,
            range,
            with_normals,
        ))
    }
}

/// Bits per axis of a packed block key: blocks within `2^20` block edges of the origin (84 km
/// at 1 cm voxels).
const KEY_BITS: u32 = 21;
const KEY_HALF: f32 = (1u32 << (KEY_BITS - 1)) as f32;

/// The block containing the point `b` (in block edges) packed into one integer, so that
/// sorting and deduplicating keys is an integer sort (order z, then y, then x); `None` beyond
/// the key range (or NaN).
#[inline]
fn pack_key(b: [f32; 3]) -> Option<u64> {
    let mut out = 0u64;
    for &v in b.iter().rev() {
        if !(-KEY_HALF..KEY_HALF).contains(&v) {
            return None;
        }
        // The floor without a libm call on baseline x86-64: truncate, then step down for
        // negative non-integers.
        let t = v as i32;
        let f = if (t as f32) > v { t - 1 } else { t };
        out = (out << KEY_BITS) | (f + (1 << (KEY_BITS - 1))) as u64;
    }
    Some(out)
}

#[inline]
fn unpack_key(k: u64) -> [i32; 3] {
    let mask = (1u64 << KEY_BITS) - 1;
    let half = 1i64 << (KEY_BITS - 1);
    let axis = |i: u32| ((k >> (KEY_BITS * i)) & mask) as i64 - half;
    [axis(0) as i32, axis(1) as i32, axis(2) as i32]
}

/// Pixel stride of the allocation pass.
///
/// Rays of pixels `s` apart are `s z / f` apart at depth `z`. With `s` chosen so that this is
/// at most a quarter of a block at the farthest integrated depth, and samples along each ray
/// at most half a block apart, the sampled points cover the band (`2 mu` thick, a block at the
/// default smallest truncation) with a lattice finer than half a block in every direction. A block the band crosses is then missed only when the crossing
/// is a sliver at its edge, narrower than a quarter block across: such a sliver lies at the
/// rim of the band, where voxels hold the truncated free-space value rather than the zero
/// crossing the mesh is made from, and the next frame's rays, a few pixels elsewhere, cover
/// it.
pub(crate) fn allocation_stride(p: &TsdfParams, c: &PinholeCamera) -> usize {
    let f = c.fx.min(c.fy);
    let block = p.voxel_size * BLOCK_SIDE as f64;
    let s = (0.25 * block * f / p.max_depth).floor();
    if s.is_finite() && s >= 1.0 {
        (s as usize).min(BLOCK_SIDE)
    } else {
        1
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

    use super::{pack_key, unpack_key, TsdfParams, TsdfVolume, KEY_HALF};
    use crate::camera::PinholeCamera;
    use crate::gpu::{test_gpu, ComputeBackend};
    use crate::synth::{
        CameraModel, RenderBackend, Scene, Sequence, SequenceConfig, Trajectory, TrajectoryKind,
    };

    #[test]
    fn block_keys_floor_and_round_trip() {
        let cases = [
            ([0.0, 0.5, 0.999], [0, 0, 0]),
            ([-0.5, -1.0, -1.0001], [-1, -1, -2]),
            ([1e5 + 0.25, -1e5 - 0.25, 3.0], [100_000, -100_001, 3]),
            (
                [KEY_HALF - 1.0, -KEY_HALF, 7.5],
                [(1 << 20) - 1, -(1 << 20), 7],
            ),
        ];
        for (b, want) in cases {
            let k = pack_key(b).unwrap_or_else(|| panic!("{b:?} out of range"));
            assert_eq!(unpack_key(k), want, "{b:?}");
        }
        // Ordered by z first, so sorted keys keep neighbouring rows of blocks together.
        assert!(pack_key([5.0, 0.0, 0.0]) < pack_key([0.0, 0.0, 1.0]));
        for b in [
            [KEY_HALF, 0.0, 0.0],
            [0.0, -KEY_HALF - 1.0, 0.0],
            [0.0, 0.0, f32::NAN],
        ] {
            assert!(pack_key(b).is_none(), "{b:?}");
        }
    }

    /// Frames of a generated office at 160x120 with their poses.
    fn office_frames(
        frames: usize,
        seed: u64,
    ) -> Vec<(crate::image::RgbdFrame, crate::geometry::Se3)> {
        let cam = PinholeCamera::new(131.25, 131.25, 79.5, 59.5, 160, 120);
        let scene = Arc::new(Scene::preset("office", seed).unwrap_or_else(|e| panic!("{e}")));
        let traj = Trajectory::new(TrajectoryKind::Handheld, &scene, 1.0, seed)
            .unwrap_or_else(|e| panic!("{e}"));
        let config = SequenceConfig {
            frames,
            seed,
            ..Default::default()
        };
        Sequence::new(
            scene,
            CameraModel::Pinhole(cam),
            traj,
            config,
            &RenderBackend::Cpu,
        )
        .unwrap_or_else(|e| panic!("{e}"))
        .map(|f| {
            let f = f.unwrap_or_else(|e| panic!("{e}"));
            (f.frame.to_rgbd_frame(f.timestamp), f.world_from_camera)
        })
        .collect()
    }

    /// A volume whose device holds a tenth of the blocks (the GPU's, or the CPU mirror's
    /// storage standing in for a device) gives the same voxels, mesh, ray cast and file as
    /// an unbounded one, after many blocks moved out and back; the device never holds more
    /// than the budget.
    fn paged_volume_matches_an_unbounded_one(backend: &ComputeBackend) {
        let frames = office_frames(24, 3);
        let cam = PinholeCamera::new(131.25, 131.25, 79.5, 59.5, 160, 120);
        let params = TsdfParams {
            voxel_size: 0.02,
            ..Default::default()
        };
        let mut full = TsdfVolume::new(params, cam, backend).unwrap_or_else(|e| panic!("{e}"));
        let mut most_active = 0;
        for (f, p) in &frames {
            let t = full.integrate(f, p).unwrap_or_else(|e| panic!("{e}"));
            most_active = most_active.max(t.active_blocks);
        }
        let budget = full.block_count() / 10;
        let mut paged = TsdfVolume::new(
            TsdfParams {
                device_blocks: Some(budget),
                ..params
            },
            cam,
            backend,
        )
        .unwrap_or_else(|e| panic!("{e}"));
        if matches!(backend, ComputeBackend::Cpu) {
            paged.on_device = true;
            paged.residency = super::Residency::new(Some(budget));
            paged
                .kernels
                .set_slot_limit(Some(budget))
                .unwrap_or_else(|e| panic!("{e}"));
        }
        for (f, p) in &frames {
            paged.integrate(f, p).unwrap_or_else(|e| panic!("{e}"));
            let st = paged.paging();
            assert!(st.resident_blocks <= budget);
            assert!(
                paged.kernels.slot_capacity() <= budget,
                "{} slots of storage, budget {budget}",
                paged.kernels.slot_capacity()
            );
        }
        let st = paged.paging();
        assert_eq!(st.resident_blocks + st.host_blocks, full.block_count());
        assert!(st.peak_resident_blocks <= budget);
        // Frames needing more than the budget were integrated in chunks, and blocks moved
        // both ways many times.
        assert!(
            most_active > budget,
            "{most_active} active, budget {budget}"
        );
        assert!(st.page_outs > 2 * full.block_count() as u64, "{st:?}");
        assert!(st.page_ins > full.block_count() as u64, "{st:?}");
        assert_eq!(paged.block_count(), full.block_count());
        assert!(
            paged.kernels_voxels() == full.kernels_voxels(),
            "paged voxels differ"
        );
        // The CPU mirror on both: an unbounded GPU volume meshes with the kernel, whose
        // parity with the mirror `gpu_tsdf_mesh_matches_the_cpu_mirror` checks.
        let mesh = full.mesh_cpu();
        assert!(mesh.triangles.len() > 1000, "{}", mesh.triangles.len());
        let pm = paged.extract_mesh().unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(pm.vertices, mesh.vertices);
        assert_eq!(pm.triangles, mesh.triangles);
        assert!(pm == mesh);
        let pose = &frames[5].1;
        // The CPU mirror on both: an unbounded GPU volume casts with the kernel, whose
        // parity with the mirror `gpu_tsdf_ray_cast_matches_the_cpu_mirror` checks.
        let a = full
            .cast_cpu(&cam, pose, true)
            .unwrap_or_else(|e| panic!("{e}"));
        let b = paged.ray_cast(&cam, pose).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(a.depth.data(), b.depth.data());
        assert_eq!(a.colours, b.colours);
        let dir = tempfile::tempdir().unwrap_or_else(|e| panic!("{e}"));
        let (fa, fb) = (dir.path().join("full.tsdf"), dir.path().join("paged.tsdf"));
        full.save(&fa).unwrap_or_else(|e| panic!("{e}"));
        paged.save(&fb).unwrap_or_else(|e| panic!("{e}"));
        assert!(
            std::fs::read(&fa).ok() == std::fs::read(&fb).ok(),
            "saved files differ"
        );
        // A budget set later (a loaded volume) pages out at once and stays exact.
        let small = budget / 2;
        full.set_device_blocks(Some(small))
            .unwrap_or_else(|e| panic!("{e}"));
        if matches!(backend, ComputeBackend::Gpu(_)) {
            assert!(full.paging().resident_blocks <= small);
            assert!(full.device_block_capacity() <= small);
        }
        assert!(full.extract_mesh().unwrap_or_else(|e| panic!("{e}")) == mesh);
        assert!(full.set_device_blocks(Some(0)).is_err());
    }

    #[test]
    fn tsdf_paged_volume_matches_an_unbounded_one() {
        paged_volume_matches_an_unbounded_one(&ComputeBackend::Cpu);
    }

    #[test]
    #[ignore = "needs a GPU adapter"]
    fn gpu_tsdf_paged_volume_matches_an_unbounded_one() {
        let Some(ctx) = test_gpu("gpu_tsdf_paged_volume_matches_an_unbounded_one") else {
            return;
        };
        paged_volume_matches_an_unbounded_one(&ComputeBackend::Gpu(ctx));
    }

    /// Six frames of the generated office at 160x120 and their camera, integrated on
    /// `backend` (2 cm voxels).
    fn office_volume(backend: &ComputeBackend) -> (TsdfVolume, Vec<crate::geometry::Se3>) {
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
        let mut volume = TsdfVolume::new(params, cam, backend).unwrap_or_else(|e| panic!("{e}"));
        let mut poses = Vec::new();
        for f in seq {
            let f = f.unwrap_or_else(|e| panic!("{e}"));
            let frame = f.frame.to_rgbd_frame(f.timestamp);
            volume
                .integrate(&frame, &f.world_from_camera)
                .unwrap_or_else(|e| panic!("{e}"));
            poses.push(f.world_from_camera);
        }
        (volume, poses)
    }

    #[test]
    #[ignore = "needs a GPU adapter"]
    fn gpu_tsdf_ray_cast_matches_the_cpu_mirror() {
        let Some(ctx) = test_gpu("gpu_tsdf_ray_cast_matches_the_cpu_mirror") else {
            return;
        };
        let (volume, poses) = office_volume(&ComputeBackend::Gpu(ctx));
        let cam = *volume.camera();
        // From the first frame's pose and from between two frames.
        let between =
            poses[2] * crate::geometry::Se3::exp(&[0.03, -0.02, 0.01, 0.02, -0.01, 0.015]);
        for pose in [poses[0], between] {
            let gpu = volume
                .ray_cast(&cam, &pose)
                .unwrap_or_else(|e| panic!("{e}"));
            let cpu = volume
                .cast_cpu(&cam, &pose, true)
                .unwrap_or_else(|e| panic!("{e}"));
            let n = cpu.depth.data.len();
            let hits = cpu.depth.data.iter().filter(|&&d| d > 0.0).count();
            assert!(hits > n / 2, "only {hits} of {n} CPU rays hit the surface");
            // Same f32 operations: a ray may differ only where a fused multiply-add moves a
            // sample across a voxel or block boundary.
            let mut differ = 0usize;
            for i in 0..n {
                let (a, b) = (cpu.depth.data[i], gpu.depth.data[i]);
                let same_hit = (a > 0.0) == (b > 0.0);
                let close = same_hit
                    && (a - b).abs() <= 1e-4
                    && (0..3)
                        .all(|k| (cpu.colours[i][k] as i32 - gpu.colours[i][k] as i32).abs() <= 1)
                    && (0..3).all(|k| (cpu.normals[i][k] - gpu.normals[i][k]).abs() <= 1e-3);
                if !close {
                    differ += 1;
                }
            }
            assert!(
                (differ as f64) <= 1e-3 * n as f64,
                "{differ} of {n} rays differ between the kernel and the CPU mirror"
            );
        }
    }

    impl TsdfVolume {
        /// The CPU mirror's mesh of every block.
        fn mesh_cpu(&self) -> super::Mesh {
            super::mesh::assemble(&self.mesh_cubes_cpu().unwrap_or_else(|e| panic!("{e}")))
        }
    }

    #[test]
    #[ignore = "needs a GPU adapter"]
    fn gpu_tsdf_mesh_matches_the_cpu_mirror() {
        let Some(ctx) = test_gpu("gpu_tsdf_mesh_matches_the_cpu_mirror") else {
            return;
        };
        let (volume, _) = office_volume(&ComputeBackend::Gpu(ctx));
        let t = std::time::Instant::now();
        let gpu = volume.mesh_cubes().unwrap_or_else(|e| panic!("{e}"));
        let gpu_s = t.elapsed().as_secs_f64();
        let t = std::time::Instant::now();
        let cpu = volume.mesh_cubes_cpu().unwrap_or_else(|e| panic!("{e}"));
        let cpu_s = t.elapsed().as_secs_f64();
        eprintln!(
            "{} blocks, {} triangles: kernel {:.1} ms, CPU mirror {:.1} ms (with read-back)",
            volume.block_count(),
            cpu.vertices.len() / 3,
            gpu_s * 1e3,
            cpu_s * 1e3
        );
        assert!(
            cpu.vertices.len() > 3 * 5000,
            "{} vertices",
            cpu.vertices.len()
        );
        // The same cubes with the same triangle counts, each vertex on the same edge: the
        // signs and weights decide them, exactly on both.
        assert_eq!(gpu.cubes, cpu.cubes);
        assert_eq!(gpu.vertices.len(), cpu.vertices.len());
        let (mut farthest, mut recoloured) = (0.0f32, 0usize);
        for (i, (a, b)) in cpu.vertices.iter().zip(&gpu.vertices).enumerate() {
            assert_eq!(a.edge(), b.edge(), "vertex {i}");
            let far = (0..3)
                .map(|k| (a.position[k] - b.position[k]).abs())
                .fold(0.0, f32::max);
            farthest = farthest.max(far);
            recoloured += usize::from(a.colour() != b.colour());
            assert!(
                far <= 1e-5,
                "vertex {i}: {:?} against {:?}",
                a.position,
                b.position
            );
            let (ca, cb) = (a.colour(), b.colour());
            assert!(
                (0..3).all(|k| (i32::from(ca[k]) - i32::from(cb[k])).abs() <= 1),
                "vertex {i}: colour {ca:?} against {cb:?}"
            );
        }
        eprintln!("largest position difference {farthest} m, {recoloured} colours differ");
        // The meshes: same topology, vertices and colours within the same tolerances, and
        // `extract_mesh` on the GPU volume is the kernel's.
        let (mc, mg) = (super::mesh::assemble(&cpu), super::mesh::assemble(&gpu));
        assert_eq!(mc.triangles, mg.triangles);
        assert!(volume.extract_mesh().unwrap_or_else(|e| panic!("{e}")) == mg);
        let mut bent = 0usize;
        for i in 0..mc.vertices.len() {
            let (a, b) = (mc.vertices[i], mg.vertices[i]);
            assert!(
                (0..3).all(|k| (a[k] - b[k]).abs() <= 1e-5),
                "{a:?} against {b:?}"
            );
            let (na, nb) = (mc.normals[i], mg.normals[i]);
            if (0..3).any(|k| (na[k] - nb[k]).abs() > 1e-3) {
                bent += 1;
            }
        }
        // A normal can turn only where all its triangles are nearly degenerate.
        eprintln!(
            "{} vertices, {} normals differ by more than 1e-3",
            mc.vertices.len(),
            bent
        );
        assert!(
            bent as f64 <= 1e-3 * mc.vertices.len() as f64,
            "{bent} of {} normals differ",
            mc.vertices.len()
        );
    }

    #[test]
    #[ignore = "needs a GPU adapter"]
    fn gpu_tsdf_integration_matches_the_cpu_mirror() {
        let Some(ctx) = test_gpu("gpu_tsdf_integration_matches_the_cpu_mirror") else {
            return;
        };
        let (cpu, _) = office_volume(&ComputeBackend::Cpu);
        let (gpu, _) = office_volume(&ComputeBackend::Gpu(ctx));
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
