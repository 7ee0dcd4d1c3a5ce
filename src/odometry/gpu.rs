//! The WGSL backend of the odometry kernels (`shaders/pyramid.wgsl`, `shaders/odometry.wgsl`).
//! Pipelines are created once per [`GpuOdometry`]; pyramids keep their buffers and are
//! recycled; each Gauss-Newton step is one dispatch plus a small read-back.

use std::sync::Arc;

use super::cpu::{pyramid_layout, LevelLayout};
use super::kernel::{PyrParams, WarpParams, PARTIAL_LEN};
use crate::gpu::{shaders, GpuContext, GpuError};
use crate::image::RgbdFrame;

const WG: usize = 128;

/// A pyramid read back to the CPU: `(photo, geo)` as in [`super::cpu::CpuPyramid`].
pub type PyramidData = (Vec<[f32; 4]>, Vec<[f32; 4]>);

/// A frame's pyramid in GPU buffers.
pub struct GpuPyramid {
    /// Level layouts.
    pub levels: Vec<LevelLayout>,
    input: wgpu::Buffer,
    photo: wgpu::Buffer,
    geo: wgpu::Buffer,
    /// Unique id, to cache bind groups per (reference, current) pair.
    id: u64,
}

/// Pipelines and scratch buffers of the odometry kernels on one device.
pub struct GpuOdometry {
    ctx: Arc<GpuContext>,
    pyr_layout: wgpu::BindGroupLayout,
    warp_layout: wgpu::BindGroupLayout,
    pack: wgpu::ComputePipeline,
    down: wgpu::ComputePipeline,
    grad: wgpu::ComputePipeline,
    normal: wgpu::ComputePipeline,
    sample: wgpu::ComputePipeline,
    covis: wgpu::ComputePipeline,
    pyr_uniforms: Vec<wgpu::Buffer>,
    warp_uniform: wgpu::Buffer,
    out: wgpu::Buffer,
    staging: wgpu::Buffer,
    out_len: usize,
    next_id: u64,
    bind_cache: Option<(u64, u64, wgpu::BindGroup)>,
}

fn source(name: &str) -> Result<String, GpuError> {
    shaders::assembled(name).ok_or_else(|| GpuError::Shader {
        name: name.into(),
        message: "missing shader".into(),
    })
}

impl GpuOdometry {
    /// Compiles the kernels on `ctx`.
    pub fn new(ctx: Arc<GpuContext>) -> Result<Self, GpuError> {
        let pyr_layout = ctx.buffer_layout("pyramid", &[true, false, false]);
        let warp_layout = ctx.buffer_layout("warp", &[true, true, true, true, false]);
        let p = ctx.compute_pipelines_with_layout(
            "pyramid.wgsl",
            &source("pyramid.wgsl")?,
            &["pack_level0", "downsample", "gradients"],
            Some(&pyr_layout),
        )?;
        let o = ctx.compute_pipelines_with_layout(
            "odometry.wgsl",
            &source("odometry.wgsl")?,
            &["normal_equations", "sample_residuals", "covisibility"],
            Some(&warp_layout),
        )?;
        let [pack, down, grad]: [wgpu::ComputePipeline; 3] = p
            .try_into()
            .map_err(|_| GpuError::Validation("pipeline count".into()))?;
        let [normal, sample, covis]: [wgpu::ComputePipeline; 3] = o
            .try_into()
            .map_err(|_| GpuError::Validation("pipeline count".into()))?;
        let warp_uniform = ctx.uniform("warp params", std::mem::size_of::<WarpParams>() as u64);
        let out_len = 2 * 19200 + 16;
        let out = ctx.storage("odometry out", (out_len * 4) as u64);
        let staging = ctx.staging("odometry staging", (out_len * 4) as u64);
        Ok(Self {
            ctx,
            pyr_layout,
            warp_layout,
            pack,
            down,
            grad,
            normal,
            sample,
            covis,
            pyr_uniforms: Vec::new(),
            warp_uniform,
            out,
            staging,
            out_len,
            next_id: 1,
            bind_cache: None,
        })
    }

    /// The device context.
    pub fn context(&self) -> &Arc<GpuContext> {
        &self.ctx
    }

    fn ensure_out(&mut self, len: usize) {
        if len > self.out_len {
            self.out_len = len.next_power_of_two();
            self.out = self.ctx.storage("odometry out", (self.out_len * 4) as u64);
            self.staging = self
                .ctx
                .staging("odometry staging", (self.out_len * 4) as u64);
            self.bind_cache = None;
        }
    }

    /// Uploads `frame` and builds its pyramid and gradients, reusing `recycle`'s buffers when
    /// it has the same shape.
    pub fn build(
        &mut self,
        frame: &RgbdFrame,
        levels: usize,
        recycle: Option<GpuPyramid>,
    ) -> Result<GpuPyramid, GpuError> {
        let layout = pyramid_layout(frame.width(), frame.height(), levels);
        let total = layout
            .last()
            .map(|l| l.offset + l.width * l.height)
            .unwrap_or(0);
        let n0 = frame.width() * frame.height();
        let mut pyr = match recycle {
            Some(p) if p.levels == layout => p,
            _ => GpuPyramid {
                levels: layout.clone(),
                input: self.ctx.storage("pyr input", (2 * n0 * 4) as u64),
                photo: self.ctx.storage("pyr photo", (total * 16) as u64),
                geo: self.ctx.storage("pyr geo", (total * 16) as u64),
                id: 0,
            },
        };
        pyr.id = self.next_id;
        self.next_id += 1;
        let q = &self.ctx.queue;
        q.write_buffer(&pyr.input, 0, bytemuck::cast_slice(&frame.intensity.data));
        q.write_buffer(
            &pyr.input,
            (n0 * 4) as u64,
            bytemuck::cast_slice(&frame.inverse_depth.data),
        );
        // One uniform per kernel invocation of the build: pack, (downsample, gradients) per level.
        let needed = 2 * levels + 1;
        while self.pyr_uniforms.len() < needed {
            self.pyr_uniforms.push(
                self.ctx
                    .uniform("pyr params", std::mem::size_of::<PyrParams>() as u64),
            );
        }
        let mut enc = self
            .ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("pyramid"),
            });
        let mut u = 0;
        let dispatch = |enc: &mut wgpu::CommandEncoder,
                        pipe: &wgpu::ComputePipeline,
                        params: PyrParams,
                        w: usize,
                        h: usize,
                        u: &mut usize| {
            let ub = &self.pyr_uniforms[*u];
            *u += 1;
            q.write_buffer(ub, 0, bytemuck::bytes_of(&params));
            let bg = self.ctx.bind_buffers(
                "pyr",
                &self.pyr_layout,
                &[ub, &pyr.input, &pyr.photo, &pyr.geo],
            );
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: None,
                timestamp_writes: None,
            });
            pass.set_pipeline(pipe);
            pass.set_bind_group(0, &bg, &[]);
            pass.dispatch_workgroups(w.div_ceil(16) as u32, h.div_ceil(16) as u32, 1);
        };
        let l0 = layout[0];
        dispatch(
            &mut enc,
            &self.pack,
            PyrParams {
                dims: [l0.width as u32, l0.height as u32, 0, 0],
                src: [0; 4],
            },
            l0.width,
            l0.height,
            &mut u,
        );
        for l in 1..layout.len() {
            let (s, d) = (layout[l - 1], layout[l]);
            dispatch(
                &mut enc,
                &self.down,
                PyrParams {
                    dims: [
                        d.width as u32,
                        d.height as u32,
                        d.offset as u32,
                        s.offset as u32,
                    ],
                    src: [s.width as u32, s.height as u32, 0, 0],
                },
                d.width,
                d.height,
                &mut u,
            );
        }
        for d in &layout {
            dispatch(
                &mut enc,
                &self.grad,
                PyrParams {
                    dims: [d.width as u32, d.height as u32, d.offset as u32, 0],
                    src: [0; 4],
                },
                d.width,
                d.height,
                &mut u,
            );
        }
        self.ctx.queue.submit([enc.finish()]);
        self.ctx.check()?;
        Ok(pyr)
    }

    fn bind(&mut self, reference: &GpuPyramid, current: &GpuPyramid) -> wgpu::BindGroup {
        if let Some((a, b, bg)) = &self.bind_cache {
            if *a == reference.id && *b == current.id {
                return bg.clone();
            }
        }
        let bg = self.ctx.bind_buffers(
            "warp",
            &self.warp_layout,
            &[
                &self.warp_uniform,
                &reference.photo,
                &reference.geo,
                &current.photo,
                &current.geo,
                &self.out,
            ],
        );
        self.bind_cache = Some((reference.id, current.id, bg.clone()));
        bg
    }

    fn run(
        &mut self,
        pipe: Pipe,
        params: &WarpParams,
        reference: &GpuPyramid,
        current: &GpuPyramid,
        groups: u32,
        read: usize,
    ) -> Result<Vec<f32>, GpuError> {
        self.run_many(&[(pipe, groups)], params, reference, current, read)
    }

    /// Runs `dispatches` (pipeline, workgroups) in one submission with the same parameters and
    /// reads back the first `read` floats of the output buffer (one round trip).
    fn run_many(
        &mut self,
        dispatches: &[(Pipe, u32)],
        params: &WarpParams,
        reference: &GpuPyramid,
        current: &GpuPyramid,
        read: usize,
    ) -> Result<Vec<f32>, GpuError> {
        self.ensure_out(read);
        let bg = self.bind(reference, current);
        self.ctx
            .queue
            .write_buffer(&self.warp_uniform, 0, bytemuck::bytes_of(params));
        let mut enc = self
            .ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("warp"),
            });
        for &(pipe, groups) in dispatches {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: None,
                timestamp_writes: None,
            });
            pass.set_pipeline(match pipe {
                Pipe::Normal => &self.normal,
                Pipe::Sample => &self.sample,
                Pipe::Covis => &self.covis,
            });
            pass.set_bind_group(0, &bg, &[]);
            pass.dispatch_workgroups(groups, 1, 1);
        }
        enc.copy_buffer_to_buffer(&self.out, 0, &self.staging, 0, (read * 4) as u64);
        self.ctx.queue.submit([enc.finish()]);
        self.ctx.read_staging(&self.staging, read)
    }

    /// The normal equations at the pose in `params` and, in the same submission and read-back,
    /// the systematic residual sample at that pose (for the next iteration's scale).
    pub fn normal_equations_and_sample(
        &mut self,
        params: &WarpParams,
        reference: &GpuPyramid,
        current: &GpuPyramid,
    ) -> Result<super::kernel::PartialsAndSample, GpuError> {
        let n = (params.dims[0] * params.dims[1]) as usize;
        let groups = self.ctx.reduction_groups(n, WG);
        let count = params.dims[3] as usize;
        let offset = groups as usize * PARTIAL_LEN;
        let mut p = *params;
        p.flags[3] = offset as u32;
        let v = self.run_many(
            &[
                (Pipe::Normal, groups),
                (Pipe::Sample, count.div_ceil(WG) as u32),
            ],
            &p,
            reference,
            current,
            offset + 2 * count,
        )?;
        let parts = v[..offset]
            .chunks_exact(PARTIAL_LEN)
            .map(|c| c.try_into().unwrap_or([0.0; PARTIAL_LEN]))
            .collect();
        let sample = v[offset..].chunks_exact(2).map(|c| [c[0], c[1]]).collect();
        Ok((parts, sample))
    }

    /// Per-workgroup partial sums of the normal equations at `level` (`params.dims` set).
    pub fn normal_equation_partials(
        &mut self,
        params: &WarpParams,
        reference: &GpuPyramid,
        current: &GpuPyramid,
    ) -> Result<Vec<[f32; PARTIAL_LEN]>, GpuError> {
        let n = (params.dims[0] * params.dims[1]) as usize;
        let groups = self.ctx.reduction_groups(n, WG);
        let v = self.run(
            Pipe::Normal,
            params,
            reference,
            current,
            groups,
            groups as usize * PARTIAL_LEN,
        )?;
        Ok(v.chunks_exact(PARTIAL_LEN)
            .map(|c| c.try_into().unwrap_or([0.0; PARTIAL_LEN]))
            .collect())
    }

    /// The systematic residual sample (`params.dims[3]` samples).
    pub fn sample_residuals(
        &mut self,
        params: &WarpParams,
        reference: &GpuPyramid,
        current: &GpuPyramid,
    ) -> Result<Vec<[f32; 2]>, GpuError> {
        let count = params.dims[3] as usize;
        let v = self.run(
            Pipe::Sample,
            params,
            reference,
            current,
            count.div_ceil(WG) as u32,
            2 * count,
        )?;
        Ok(v.chunks_exact(2).map(|c| [c[0], c[1]]).collect())
    }

    /// Covisibility counts `(pixels with depth, covisible pixels)`.
    pub fn covisibility_counts(
        &mut self,
        params: &WarpParams,
        reference: &GpuPyramid,
        current: &GpuPyramid,
    ) -> Result<(u64, u64), GpuError> {
        let n = (params.dims[0] * params.dims[1]) as usize;
        let groups = self.ctx.reduction_groups(n, WG);
        let v = self.run(
            Pipe::Covis,
            params,
            reference,
            current,
            groups,
            2 * groups as usize,
        )?;
        let mut a = 0u64;
        let mut b = 0u64;
        for c in v.chunks_exact(2) {
            a += c[0] as u64;
            b += c[1] as u64;
        }
        Ok((a, b))
    }

    /// Reads a pyramid back (for parity tests and the viewer).
    pub fn read_pyramid(&self, p: &GpuPyramid) -> Result<PyramidData, GpuError> {
        let total = p
            .levels
            .last()
            .map(|l| l.offset + l.width * l.height)
            .unwrap_or(0);
        let photo: Vec<f32> = self.ctx.read_buffer(&p.photo, total * 4)?;
        let geo: Vec<f32> = self.ctx.read_buffer(&p.geo, total * 4)?;
        let to4 = |v: Vec<f32>| {
            v.chunks_exact(4)
                .map(|c| [c[0], c[1], c[2], c[3]])
                .collect()
        };
        Ok((to4(photo), to4(geo)))
    }
}

#[derive(Clone, Copy)]
enum Pipe {
    Normal,
    Sample,
    Covis,
}
