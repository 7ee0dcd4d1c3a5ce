//! Keyframe inverse-depth fusion by reverse warping (thesis 6.4.2, eq. 6.24-6.25): the WGSL
//! kernel `shaders/fuse.wgsl` and its CPU mirror [`fuse_cpu`] (same f32 operations in the
//! same order), behind [`KeyframeFuser`] which keeps the keyframe resident on the device.

use std::sync::Arc;

use bytemuck::{Pod, Zeroable};
use rayon::prelude::*;

use super::SlamError;
use crate::camera::PinholeCamera;
use crate::geometry::Se3;
use crate::gpu::{shaders, ComputeBackend, GpuContext, GpuError};
use crate::image::ImageF32;

/// Parameters of the weighted inverse-depth update.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct FusionParams {
    /// Absolute consistency tolerance on inverse depth, 1/m.
    pub tol_abs: f32,
    /// Relative consistency tolerance (fraction of the keyframe's inverse depth).
    pub tol_rel: f32,
    /// Weight of one new measurement.
    pub new_weight: f32,
    /// Cap of the accumulated weight (keeps the keyframe able to follow small changes).
    pub max_weight: f32,
}

impl Default for FusionParams {
    fn default() -> Self {
        FusionParams {
            tol_abs: 0.004,
            tol_rel: 0.03,
            new_weight: 1.0,
            max_weight: 30.0,
        }
    }
}

/// Pixel counts of one fusion pass.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct FusionCounts {
    /// Keyframe pixels with depth.
    pub valid: u64,
    /// Of those, the ones that land on a current-frame pixel with depth.
    pub covisible: u64,
    /// Of those, the ones whose measurement was consistent and fused.
    pub fused: u64,
}

impl FusionCounts {
    /// Fraction of the keyframe's pixels with depth seen with depth by the current frame
    /// (the keyframe-side covisibility of eq. 6.10); 0 when the keyframe has no depth.
    pub fn covisibility(&self) -> f64 {
        if self.valid == 0 {
            0.0
        } else {
            self.covisible as f64 / self.valid as f64
        }
    }
}

/// Uniform block of `fuse.wgsl` (same layout).
#[repr(C)]
#[derive(Clone, Copy, Debug, Pod, Zeroable)]
pub struct FuseUniform {
    /// width, height, unused, unused.
    pub dims: [u32; 4],
    /// fx, fy, cx, cy (pixels).
    pub intr: [f32; 4],
    /// `cur_from_kf` rows with the translation in the last column.
    pub fwd: [[f32; 4]; 3],
    /// `kf_from_cur` rows with the translation in the last column.
    pub inv: [[f32; 4]; 3],
    /// tol_abs, tol_rel, new_weight, max_weight.
    pub tol: [f32; 4],
}

fn rows(t: &Se3) -> [[f32; 4]; 3] {
    let r = t.rotation_matrix();
    let mut out = [[0.0f32; 4]; 3];
    for (i, row) in out.iter_mut().enumerate() {
        *row = [
            r.row(i).x as f32,
            r.row(i).y as f32,
            r.row(i).z as f32,
            t.translation[i] as f32,
        ];
    }
    out
}

impl FuseUniform {
    /// The uniform for fusing a frame at `cur_from_kf` into a keyframe of `camera`.
    pub fn new(camera: &PinholeCamera, cur_from_kf: &Se3, params: &FusionParams) -> Self {
        FuseUniform {
            dims: [camera.width, camera.height, 0, 0],
            intr: [
                camera.fx as f32,
                camera.fy as f32,
                camera.cx as f32,
                camera.cy as f32,
            ],
            fwd: rows(cur_from_kf),
            inv: rows(&cur_from_kf.inverse()),
            tol: [
                params.tol_abs,
                params.tol_rel,
                params.new_weight,
                params.max_weight,
            ],
        }
    }
}

#[inline]
fn xform(r: &[[f32; 4]; 3], p: [f32; 3]) -> [f32; 3] {
    let f = |k: usize| r[k][0] * p[0] + r[k][1] * p[1] + r[k][2] * p[2] + r[k][3];
    [f(0), f(1), f(2)]
}

/// What happened at one keyframe pixel: 0 no depth, 1 depth but not covisible, 2 covisible
/// but inconsistent, 3 fused (then `(rho, weight)` are the new values).
#[inline]
pub fn fuse_pixel(
    u: &FuseUniform,
    x: u32,
    y: u32,
    rho: f32,
    weight: f32,
    cur_rho: &[f32],
) -> (u8, f32, f32) {
    if !(rho > 0.0) {
        return (0, rho, weight);
    }
    let (w, h) = (u.dims[0], u.dims[1]);
    let [fx, fy, cx, cy] = u.intr;
    let z = 1.0 / rho;
    let pk = [(x as f32 - cx) / fx * z, (y as f32 - cy) / fy * z, z];
    let pc = xform(&u.fwd, pk);
    if !(pc[2] > 0.0) {
        return (1, rho, weight);
    }
    let uu = fx * pc[0] / pc[2] + cx;
    let vv = fy * pc[1] / pc[2] + cy;
    let qx = (uu + 0.5).floor();
    let qy = (vv + 0.5).floor();
    if !(qx >= 0.0 && qy >= 0.0 && qx <= (w - 1) as f32 && qy <= (h - 1) as f32) {
        return (1, rho, weight);
    }
    let j = qy as usize * w as usize + qx as usize;
    let rc = cur_rho[j];
    if !(rc > 0.0) {
        return (1, rho, weight);
    }
    let zc = 1.0 / rc;
    let qc = [(qx - cx) / fx * zc, (qy - cy) / fy * zc, zc];
    let qk = xform(&u.inv, qc);
    if !(qk[2] > 0.0) {
        return (2, rho, weight);
    }
    let rho_new = 1.0 / qk[2];
    if (rho_new - rho).abs() > u.tol[0] + u.tol[1] * rho {
        return (2, rho, weight);
    }
    let wn = u.tol[2];
    (
        3,
        (weight * rho + wn * rho_new) / (weight + wn),
        (weight + wn).min(u.tol[3]),
    )
}

/// CPU mirror of the `fuse` kernel: updates `kf_rho` / `kf_weight` (row-major, the camera's
/// size) in place with the frame whose inverse depth is `cur_rho`, at `cur_from_kf`.
pub fn fuse_cpu(
    kf_rho: &mut [f32],
    kf_weight: &mut [f32],
    cur_rho: &[f32],
    camera: &PinholeCamera,
    cur_from_kf: &Se3,
    params: &FusionParams,
) -> FusionCounts {
    let u = FuseUniform::new(camera, cur_from_kf, params);
    let w = camera.width as usize;
    kf_rho
        .par_chunks_mut(w)
        .zip(kf_weight.par_chunks_mut(w))
        .enumerate()
        .map(|(y, (rr, ww))| {
            let mut c = FusionCounts::default();
            for x in 0..rr.len() {
                let (code, r, wt) = fuse_pixel(&u, x as u32, y as u32, rr[x], ww[x], cur_rho);
                if code >= 1 {
                    c.valid += 1;
                }
                if code >= 2 {
                    c.covisible += 1;
                }
                if code == 3 {
                    c.fused += 1;
                    rr[x] = r;
                    ww[x] = wt;
                }
            }
            c
        })
        .reduce(FusionCounts::default, |a, b| FusionCounts {
            valid: a.valid + b.valid,
            covisible: a.covisible + b.covisible,
            fused: a.fused + b.fused,
        })
}

/// The fusion kernel compiled on a device, with the keyframe's buffers resident there.
pub struct GpuFusion {
    ctx: Arc<GpuContext>,
    pipeline: wgpu::ComputePipeline,
    layout: wgpu::BindGroupLayout,
    uniform: wgpu::Buffer,
    counts: wgpu::Buffer,
    buffers: Option<(wgpu::Buffer, wgpu::Buffer, wgpu::Buffer, wgpu::BindGroup)>,
    pixels: usize,
}

impl GpuFusion {
    /// Compiles `fuse.wgsl` on `ctx`.
    pub fn new(ctx: Arc<GpuContext>) -> Result<Self, SlamError> {
        let src = shaders::assembled("fuse.wgsl").ok_or_else(|| GpuError::Shader {
            name: "fuse.wgsl".into(),
            message: "not embedded".into(),
        })?;
        let layout = ctx.buffer_layout("fuse", &[true, false, false, false]);
        let mut pipes =
            ctx.compute_pipelines_with_layout("fuse.wgsl", &src, &["fuse"], Some(&layout))?;
        let pipeline = pipes.pop().ok_or_else(|| GpuError::Shader {
            name: "fuse.wgsl".into(),
            message: "no pipeline".into(),
        })?;
        let uniform = ctx.uniform("fuse params", std::mem::size_of::<FuseUniform>() as u64);
        let counts = ctx.storage("fuse counts", 16);
        Ok(GpuFusion {
            ctx,
            pipeline,
            layout,
            uniform,
            counts,
            buffers: None,
            pixels: 0,
        })
    }

    /// Uploads a new keyframe (`rho`, `weight`).
    pub fn start(&mut self, rho: &[f32], weight: &[f32]) {
        let ctx = &self.ctx;
        let n = rho.len();
        if self.pixels == n {
            if let Some((_, kr, kw, _)) = &self.buffers {
                ctx.queue.write_buffer(kr, 0, bytemuck::cast_slice(rho));
                ctx.queue.write_buffer(kw, 0, bytemuck::cast_slice(weight));
                return;
            }
        }
        let cur = ctx.storage("fuse current rho", (n * 4) as u64);
        let kr = ctx.storage_init("fuse keyframe rho", rho);
        let kw = ctx.storage_init("fuse keyframe weight", weight);
        let bind = ctx.bind_buffers(
            "fuse",
            &self.layout,
            &[&self.uniform, &cur, &kr, &kw, &self.counts],
        );
        self.buffers = Some((cur, kr, kw, bind));
        self.pixels = n;
    }

    /// Fuses one frame into the resident keyframe; returns the pixel counts.
    pub fn fuse(&mut self, cur_rho: &[f32], u: &FuseUniform) -> Result<FusionCounts, SlamError> {
        let ctx = &self.ctx;
        let Some((cur, _, _, bind)) = &self.buffers else {
            return Err(SlamError::Internal("fusion before a keyframe".into()));
        };
        if cur_rho.len() != self.pixels {
            return Err(SlamError::Internal("fusion frame size changed".into()));
        }
        ctx.queue
            .write_buffer(cur, 0, bytemuck::cast_slice(cur_rho));
        ctx.queue
            .write_buffer(&self.uniform, 0, bytemuck::bytes_of(u));
        ctx.queue.write_buffer(&self.counts, 0, &[0u8; 16]);
        let mut enc = ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("fuse"),
            });
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("fuse"),
                timestamp_writes: None,
            });
            pass.set_pipeline(&self.pipeline);
            pass.set_bind_group(0, bind, &[]);
            pass.dispatch_workgroups(u.dims[0].div_ceil(16), u.dims[1].div_ceil(16), 1);
        }
        ctx.queue.submit([enc.finish()]);
        let c: Vec<u32> = ctx.read_buffer(&self.counts, 4)?;
        ctx.check()?;
        Ok(FusionCounts {
            valid: u64::from(c[0]),
            covisible: u64::from(c[1]),
            fused: u64::from(c[2]),
        })
    }

    /// Bytes of the device buffers allocated (parameters, counts, and the resident keyframe
    /// and current frame).
    fn device_bytes(&self) -> usize {
        let resident = self
            .buffers
            .as_ref()
            .map_or(0, |(cur, kr, kw, _)| cur.size() + kr.size() + kw.size());
        (self.uniform.size() + self.counts.size() + resident) as usize
    }

    /// Reads the keyframe back: `(rho, weight)`.
    pub fn read(&self) -> Result<(Vec<f32>, Vec<f32>), SlamError> {
        let Some((_, kr, kw, _)) = &self.buffers else {
            return Err(SlamError::Internal("read before a keyframe".into()));
        };
        let r = self.ctx.read_buffer(kr, self.pixels)?;
        let w = self.ctx.read_buffer(kw, self.pixels)?;
        Ok((r, w))
    }
}

enum Engine {
    Cpu,
    Gpu(Box<GpuFusion>),
}

/// Accumulates frames into the current keyframe's inverse depth, on the GPU when the backend
/// has one (the keyframe stays resident there) or with the CPU mirror.
pub struct KeyframeFuser {
    camera: PinholeCamera,
    params: FusionParams,
    engine: Engine,
    rho: Vec<f32>,
    weight: Vec<f32>,
}

impl KeyframeFuser {
    /// A fuser for images of `camera` on `backend`.
    pub fn new(
        camera: PinholeCamera,
        params: FusionParams,
        backend: &ComputeBackend,
    ) -> Result<Self, SlamError> {
        let engine = match backend {
            ComputeBackend::Cpu => Engine::Cpu,
            ComputeBackend::Gpu(ctx) => Engine::Gpu(Box::new(GpuFusion::new(ctx.clone())?)),
        };
        Ok(KeyframeFuser {
            camera,
            params,
            engine,
            rho: Vec::new(),
            weight: Vec::new(),
        })
    }

    /// Bytes this fuser holds, `(host, device)`: the keyframe's inverse depth and weights in
    /// host memory, and on a GPU the buffers allocated for the resident keyframe, the frame
    /// being fused and the kernel's parameters. Allocates nothing.
    pub fn memory_bytes(&self) -> (usize, usize) {
        let host = (self.rho.capacity() + self.weight.capacity()) * std::mem::size_of::<f32>();
        let device = match &self.engine {
            Engine::Cpu => 0,
            Engine::Gpu(g) => g.device_bytes(),
        };
        (host, device)
    }

    /// Starts a keyframe from the inverse depth `rho` (1/m, 0 = invalid): weight 1 where valid.
    pub fn start(&mut self, rho: &ImageF32) {
        self.rho = rho
            .data
            .iter()
            .map(|&r| if r.is_finite() && r > 0.0 { r } else { 0.0 })
            .collect();
        self.weight = self
            .rho
            .iter()
            .map(|&r| if r > 0.0 { 1.0 } else { 0.0 })
            .collect();
        if let Engine::Gpu(g) = &mut self.engine {
            g.start(&self.rho, &self.weight);
        }
    }

    /// Fuses a frame with inverse depth `cur_rho` whose pose is `cur_from_kf`.
    pub fn fuse(
        &mut self,
        cur_rho: &ImageF32,
        cur_from_kf: &Se3,
    ) -> Result<FusionCounts, SlamError> {
        if cur_rho.data.len() != (self.camera.width * self.camera.height) as usize
            || self.rho.len() != cur_rho.data.len()
        {
            return Err(SlamError::Internal("fusion frame size mismatch".into()));
        }
        match &mut self.engine {
            Engine::Cpu => Ok(fuse_cpu(
                &mut self.rho,
                &mut self.weight,
                &cur_rho.data,
                &self.camera,
                cur_from_kf,
                &self.params,
            )),
            Engine::Gpu(g) => {
                let u = FuseUniform::new(&self.camera, cur_from_kf, &self.params);
                g.fuse(&cur_rho.data, &u)
            }
        }
    }

    /// The fused keyframe: `(inverse depth, weights)` images.
    pub fn finish(&mut self) -> Result<(ImageF32, ImageF32), SlamError> {
        let (w, h) = (self.camera.width as usize, self.camera.height as usize);
        let (r, wt) = match &self.engine {
            Engine::Cpu => (self.rho.clone(), self.weight.clone()),
            Engine::Gpu(g) => g.read()?,
        };
        let rho = ImageF32::from_vec(w, h, r)
            .ok_or_else(|| SlamError::Internal("fused keyframe size".into()))?;
        let weight = ImageF32::from_vec(w, h, wt)
            .ok_or_else(|| SlamError::Internal("fused weight size".into()))?;
        Ok((rho, weight))
    }
}
