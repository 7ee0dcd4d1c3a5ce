//! The WGSL backend of the odometry kernels (`shaders/pyramid.wgsl`, `shaders/odometry.wgsl`).
//! Pipelines are created once per [`GpuOdometry`]; pyramids keep their buffers and are
//! recycled; each Gauss-Newton step is one dispatch plus a small read-back.

use std::sync::Arc;

use super::cpu::{pyramid_layout, LevelLayout};
use super::kernel::{FilterParams, PyrParams, WarpParams, PARTIAL_LEN};
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
    down_input: wgpu::ComputePipeline,
    bilateral: wgpu::ComputePipeline,
    filtered_grad: wgpu::ComputePipeline,
    normal: wgpu::ComputePipeline,
    sample: wgpu::ComputePipeline,
    covis: wgpu::ComputePipeline,
    pyr_uniforms: Vec<wgpu::Buffer>,
    warp_uniform: wgpu::Buffer,
    out: wgpu::Buffer,
    staging: wgpu::Buffer,
    out_len: usize,
    /// Partials written per workgroup (subgroups per workgroup, or 1).
    slots: usize,
    next_id: u64,
    bind_cache: Option<(u64, u64, wgpu::BindGroup)>,
}

fn source(name: &str) -> Result<String, GpuError> {
    shaders::assembled(name).ok_or_else(|| GpuError::Shader {
        name: name.into(),
        message: "missing shader".into(),
    })
}

impl GpuPyramid {
    /// Bytes of the device buffers allocated for this pyramid.
    pub(crate) fn device_bytes(&self) -> usize {
        (self.input.size() + self.photo.size() + self.geo.size()) as usize
    }
}

impl GpuOdometry {
    /// Bytes of the device buffers the kernels keep (parameters, partial sums, read-back
    /// staging), pyramids aside.
    pub(crate) fn device_bytes(&self) -> usize {
        let pyr: u64 = self.pyr_uniforms.iter().map(wgpu::Buffer::size).sum();
        (pyr + self.warp_uniform.size() + self.out.size() + self.staging.size()) as usize
    }

    /// Compiles the kernels on `ctx` (subgroup reductions where the device has them).
    pub fn new(ctx: Arc<GpuContext>) -> Result<Self, GpuError> {
        let subgroups = ctx.has_subgroups;
        Self::with_reduction(ctx, subgroups)
    }

    /// Compiles the kernels on `ctx` with subgroup reductions (`subgroups`, ignored where the
    /// device lacks them) or the shared-memory fallback (to test and time both on one device).
    pub fn with_reduction(ctx: Arc<GpuContext>, subgroups: bool) -> Result<Self, GpuError> {
        let pyr_layout = ctx.buffer_layout("pyramid", &[true, false, false]);
        let warp_layout = ctx.buffer_layout("warp", &[true, true, true, true, false]);
        let p = ctx.compute_pipelines_with_layout(
            "pyramid.wgsl",
            &source("pyramid.wgsl")?,
            &[
                "pack_level0",
                "downsample",
                "gradients",
                "downsample_input",
                "bilateral",
                "filtered_gradients",
            ],
            Some(&pyr_layout),
        )?;
        // With subgroups, one partial per subgroup and no barrier (odometry_subgroup.wgsl);
        // otherwise one per workgroup from a shared-memory tree.
        let (file, entries, slots) = if subgroups && ctx.has_subgroups {
            let min = (ctx.info.subgroup_min_size as usize).clamp(1, WG);
            (
                "odometry_subgroup.wgsl",
                ["normal_equations_sg", "sample_residuals", "covisibility_sg"],
                WG / min,
            )
        } else {
            (
                "odometry.wgsl",
                ["normal_equations", "sample_residuals", "covisibility"],
                1,
            )
        };
        let o =
            ctx.compute_pipelines_with_layout(file, &source(file)?, &entries, Some(&warp_layout))?;
        let [pack, down, grad, down_input, bilateral, filtered_grad]: [wgpu::ComputePipeline; 6] =
            p.try_into()
                .map_err(|_| GpuError::Validation("pipeline count".into()))?;
        let [normal, sample, covis]: [wgpu::ComputePipeline; 3] = o
            .try_into()
            .map_err(|_| GpuError::Validation("pipeline count".into()))?;
        let warp_uniform = ctx.uniform("warp params", std::mem::size_of::<WarpParams>() as u64);
        let out_len = (2 * 19200 + 16 * slots * PARTIAL_LEN).next_power_of_two();
        let out = ctx.storage("odometry out", (out_len * 4) as u64);
        let staging = ctx.staging("odometry staging", (out_len * 4) as u64);
        Ok(Self {
            ctx,
            pyr_layout,
            warp_layout,
            pack,
            down,
            grad,
            down_input,
            bilateral,
            filtered_grad,
            normal,
            sample,
            covis,
            pyr_uniforms: Vec::new(),
            warp_uniform,
            out,
            staging,
            out_len,
            slots,
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
        self.build_levels(frame, levels, 0, 0, recycle)
    }

    /// Like [`Self::build`], for a tracker that reads only some levels: levels finer than
    /// `first_stored` are not written (their contents are unspecified; level 1 is then
    /// downsampled straight from the input, with the same values), and gradients are computed
    /// from level `max(first_gradient, first_stored)` on (finer stored levels keep zero
    /// gradients, as [`super::cpu::CpuPyramid::build_reusing`] leaves them). On lavapipe the
    /// full-resolution level of a 640x480 frame costs most of a full build.
    pub fn build_levels(
        &mut self,
        frame: &RgbdFrame,
        levels: usize,
        first_stored: usize,
        first_gradient: usize,
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
        // Level 0 is needed when it is read, or as the source of a level finer than level 1.
        let first_stored = first_stored.min(layout.len().saturating_sub(1));
        let skip0 = first_stored >= 1;
        if !skip0 {
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
        }
        for l in 1..layout.len() {
            let (s, d) = (layout[l - 1], layout[l]);
            dispatch(
                &mut enc,
                if l == 1 && skip0 {
                    &self.down_input
                } else {
                    &self.down
                },
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
        for d in layout.iter().skip(first_gradient.max(first_stored)) {
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

    /// A copy of `level` of `src` whose gradients are those of its bilateral-filtered
    /// intensity and inverse depth, for the covariance pass (thesis 6.20, 6.21): the same
    /// values as [`super::cpu::CpuPyramid::filtered_level`] (which documents the layout).
    /// `f.dims` must describe `level`; reuses `recycle`'s buffers when the layout matches.
    pub fn filtered_level(
        &mut self,
        src: &GpuPyramid,
        level: usize,
        f: &FilterParams,
        recycle: Option<GpuPyramid>,
    ) -> Result<GpuPyramid, GpuError> {
        let total = src
            .levels
            .last()
            .map(|l| l.offset + l.width * l.height)
            .unwrap_or(0);
        let Some(l) = src.levels.get(level).copied() else {
            return Err(GpuError::Validation(format!(
                "filtered_level: level {level} is not in the pyramid"
            )));
        };
        let mut dst = match recycle {
            Some(p) if p.levels == src.levels => p,
            _ => GpuPyramid {
                levels: src.levels.clone(),
                input: self.ctx.storage("filtered input (unused)", 16),
                photo: self.ctx.storage("filtered photo", (total * 16) as u64),
                geo: self.ctx.storage("filtered geo", (total * 16) as u64),
                id: 0,
            },
        };
        dst.id = self.next_id;
        self.next_id += 1;
        while self.pyr_uniforms.is_empty() {
            self.pyr_uniforms.push(
                self.ctx
                    .uniform("pyr params", std::mem::size_of::<PyrParams>() as u64),
            );
        }
        // FilterParams has PyrParams' size and layout (the floats travel as bit patterns).
        let ub = &self.pyr_uniforms[0];
        self.ctx.queue.write_buffer(ub, 0, bytemuck::bytes_of(f));
        let bg = self.ctx.bind_buffers(
            "filtered level",
            &self.pyr_layout,
            &[ub, &dst.input, &dst.photo, &dst.geo],
        );
        let mut enc = self
            .ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("filtered level"),
            });
        let (at, bytes) = ((l.offset * 16) as u64, (l.width * l.height * 16) as u64);
        enc.copy_buffer_to_buffer(&src.photo, at, &dst.photo, at, bytes);
        enc.copy_buffer_to_buffer(&src.geo, at, &dst.geo, at, bytes);
        for pipe in [&self.bilateral, &self.filtered_grad] {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: None,
                timestamp_writes: None,
            });
            pass.set_pipeline(pipe);
            pass.set_bind_group(0, &bg, &[]);
            pass.dispatch_workgroups(l.width.div_ceil(16) as u32, l.height.div_ceil(16) as u32, 1);
        }
        self.ctx.queue.submit([enc.finish()]);
        self.ctx.check()?;
        Ok(dst)
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
        io: Io,
    ) -> Result<Vec<f32>, GpuError> {
        self.run_many(&[(pipe, groups)], params, reference, current, io)
    }

    /// Runs `dispatches` (pipeline, workgroups) in one submission with the same parameters and
    /// reads back the first `io.read` floats of the output buffer (one round trip); the first
    /// `io.clear` floats are zeroed before the dispatches (partial slots a subgroup may not
    /// write).
    fn run_many(
        &mut self,
        dispatches: &[(Pipe, u32)],
        params: &WarpParams,
        reference: &GpuPyramid,
        current: &GpuPyramid,
        io: Io,
    ) -> Result<Vec<f32>, GpuError> {
        let Io { read, clear } = io;
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
        if self.slots > 1 && clear > 0 {
            enc.clear_buffer(&self.out, 0, Some((clear * 4).next_multiple_of(4) as u64));
        }
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
        let offset = groups as usize * self.slots * PARTIAL_LEN;
        let mut p = *params;
        p.flags[3] = offset as u32;
        // The normal-equation kernel writes the sample itself (dims.w > 0) when it has at most
        // one entry per pixel; a larger sample (pixels repeated) takes the separate pass.
        let sample_pass = (Pipe::Sample, count.div_ceil(WG) as u32);
        let dispatches: &[(Pipe, u32)] = if count <= n {
            &[(Pipe::Normal, groups)]
        } else {
            &[(Pipe::Normal, groups), sample_pass]
        };
        let v = self.run_many(
            dispatches,
            &p,
            reference,
            current,
            Io {
                read: offset + 2 * count,
                clear: offset,
            },
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
        // No residual sample from this pass.
        let mut p = *params;
        p.dims[3] = 0;
        let v = self.run(
            Pipe::Normal,
            &p,
            reference,
            current,
            groups,
            Io {
                read: groups as usize * self.slots * PARTIAL_LEN,
                clear: groups as usize * self.slots * PARTIAL_LEN,
            },
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
            Io {
                read: 2 * count,
                clear: 0,
            },
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
            Io {
                read: 2 * groups as usize * self.slots,
                clear: 2 * groups as usize * self.slots,
            },
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

/// Floats of the output buffer a submission reads back, and how many it zeroes first.
#[derive(Clone, Copy)]
struct Io {
    read: usize,
    clear: usize,
}

#[derive(Clone, Copy)]
enum Pipe {
    Normal,
    Sample,
    Covis,
}
