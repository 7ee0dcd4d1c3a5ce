//! The WGSL backend of the odometry kernels (`shaders/pyramid.wgsl`, `shaders/odometry.wgsl`).
//! Pipelines are created once per [`GpuKernels`]; pyramids keep their buffers and are
//! recycled; each Gauss-Newton step is one dispatch plus a small read-back.

use std::sync::Arc;

use super::cpu::{pyramid_layout, LevelLayout};
use super::kernel::{Partial, PartialsAndSample, PyrParams, WarpParams};
use crate::gpu::{shaders, GpuContext, GpuError};
use crate::image::RgbdFrame;

const WG: usize = 128;

/// A pyramid read back to the CPU: `(photo, geo)` as in [`super::cpu::CpuPyramid`].
#[cfg(test)]
pub(crate) type PyramidData = (Vec<[f32; 4]>, Vec<[f32; 4]>);

/// A frame's pyramid in GPU buffers.
pub struct GpuPyramid {
    /// Level layouts.
    pub(crate) levels: Vec<LevelLayout>,
    input: wgpu::Buffer,
    photo: wgpu::Buffer,
    geo: wgpu::Buffer,
    /// Unique id, to cache bind groups per (reference, current) pair.
    id: u64,
}

/// The odometry kernels compiled on one GPU device, with their scratch buffers: the WGSL
/// backend of [`super::Tracker`].
pub struct GpuKernels {
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
    out: Outputs,
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

/// The output buffers of the warp kernels (bindings 5-7 of `odometry.wgsl`) and one staging
/// buffer they are copied into for a single read-back: partials first, then the sample or
/// the counts.
struct Outputs {
    partials: wgpu::Buffer,
    sample: wgpu::Buffer,
    counts: wgpu::Buffer,
    staging: wgpu::Buffer,
    /// Capacities: partials, sample entries, count pairs.
    partial_cap: usize,
    sample_cap: usize,
    count_cap: usize,
}

impl Outputs {
    fn new(ctx: &GpuContext, partial_cap: usize, sample_cap: usize, count_cap: usize) -> Self {
        let psize = std::mem::size_of::<Partial>();
        let pair = std::mem::size_of::<[f32; 2]>();
        let staging = partial_cap * psize + sample_cap.max(count_cap) * pair;
        Self {
            partials: ctx.storage("odometry partials", (partial_cap * psize) as u64),
            sample: ctx.storage("odometry sample", (sample_cap * pair) as u64),
            counts: ctx.storage("odometry counts", (count_cap * pair) as u64),
            staging: ctx.staging("odometry staging", staging as u64),
            partial_cap,
            sample_cap,
            count_cap,
        }
    }

    fn bytes(&self) -> u64 {
        self.partials.size() + self.sample.size() + self.counts.size() + self.staging.size()
    }
}

impl GpuPyramid {
    /// Bytes of the device buffers allocated for this pyramid.
    pub(crate) fn device_bytes(&self) -> usize {
        (self.input.size() + self.photo.size() + self.geo.size()) as usize
    }

    /// Bytes of host memory this pyramid holds (its level table).
    pub(crate) fn host_bytes(&self) -> usize {
        self.levels.capacity() * std::mem::size_of::<LevelLayout>()
    }
}

impl GpuKernels {
    /// Bytes of the device buffers the kernels keep (parameters, partial sums, read-back
    /// staging), pyramids aside.
    pub(crate) fn device_bytes(&self) -> usize {
        let pyr: u64 = self.pyr_uniforms.iter().map(wgpu::Buffer::size).sum();
        (pyr + self.warp_uniform.size() + self.out.bytes()) as usize
    }

    /// Compiles the kernels on `ctx` (subgroup reductions where the device has them).
    pub fn new(ctx: Arc<GpuContext>) -> Result<Self, GpuError> {
        let subgroups = ctx.has_subgroups;
        Self::with_reduction(ctx, subgroups)
    }

    /// Compiles the kernels on `ctx` with subgroup reductions (`subgroups`, ignored where the
    /// device lacks them) or the shared-memory fallback (to test and time both on one device).
    pub(crate) fn with_reduction(ctx: Arc<GpuContext>, subgroups: bool) -> Result<Self, GpuError> {
        let pyr_layout = ctx.buffer_layout("pyramid", &[true, false, false]);
        let warp_layout = ctx.buffer_layout("warp", &[true, true, true, true, false, false, false]);
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
        let out = Outputs::new(&ctx, 16 * slots, 19200, 16 * slots);
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
            slots,
            next_id: 1,
            bind_cache: None,
        })
    }

    /// Grows the output buffers to hold `partials` partials, `samples` sample entries and
    /// `counts` count pairs.
    fn ensure_out(&mut self, partials: usize, samples: usize, counts: usize) {
        let o = &self.out;
        if partials > o.partial_cap || samples > o.sample_cap || counts > o.count_cap {
            let grow = |want: usize, cap: usize| want.max(cap).next_power_of_two();
            self.out = Outputs::new(
                &self.ctx,
                grow(partials, o.partial_cap),
                grow(samples, o.sample_cap),
                grow(counts, o.count_cap),
            );
            self.bind_cache = None;
        }
    }

    /// Uploads `frame` and builds all levels of its pyramid and gradients (parity tests).
    #[cfg(test)]
    pub(crate) fn build(
        &mut self,
        frame: &RgbdFrame,
        levels: usize,
        recycle: Option<GpuPyramid>,
    ) -> Result<GpuPyramid, GpuError> {
        self.build_levels(frame, levels, 0, 0, recycle)
    }

    /// Uploads `frame` and builds its pyramid and gradients, reusing `recycle`'s buffers when
    /// it has the same shape, for a tracker that reads only some levels: levels finer than
    /// `first_stored` are not written (their contents are unspecified; level 1 is then
    /// downsampled straight from the input, with the same values), and gradients are computed
    /// from level `max(first_gradient, first_stored)` on (finer stored levels keep zero
    /// gradients, as [`super::cpu::CpuPyramid::build_reusing`] leaves them). On lavapipe the
    /// full-resolution level of a 640x480 frame costs most of a full build.
    pub(crate) fn build_levels(
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
                    width: l0.width as u32,
                    height: l0.height as u32,
                    ..PyrParams::default()
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
                    width: d.width as u32,
                    height: d.height as u32,
                    offset: d.offset as u32,
                    src_offset: s.offset as u32,
                    src_width: s.width as u32,
                    src_height: s.height as u32,
                    ..PyrParams::default()
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
                    width: d.width as u32,
                    height: d.height as u32,
                    offset: d.offset as u32,
                    ..PyrParams::default()
                },
                d.width,
                d.height,
                &mut u,
            );
        }
        self.ctx.submit(enc.finish());
        self.ctx.check()?;
        Ok(pyr)
    }

    /// A copy of `level` of `src` whose gradients are those of its bilateral-filtered
    /// intensity and inverse depth, for the covariance pass (thesis 6.20, 6.21): the same
    /// values as [`super::cpu::CpuPyramid::filtered_level`] (which documents the layout).
    /// `f` must describe `level`; reuses `recycle`'s buffers when the layout matches.
    pub(crate) fn filtered_level(
        &mut self,
        src: &GpuPyramid,
        level: usize,
        f: &PyrParams,
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
        self.ctx.submit(enc.finish());
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
                &self.out.partials,
                &self.out.sample,
                &self.out.counts,
            ],
        );
        self.bind_cache = Some((reference.id, current.id, bg.clone()));
        bg
    }

    /// Runs `dispatches` (pipeline, workgroups) in one submission with the same parameters and
    /// reads back, in one round trip, the first `io.partials` partials and then either the
    /// first `io.sample` sample entries or the first `io.counts` count pairs; the partial and
    /// count slots read are zeroed first (a device may not write every subgroup slot).
    fn run(
        &mut self,
        dispatches: &[(Pipe, u32)],
        params: &WarpParams,
        reference: &GpuPyramid,
        current: &GpuPyramid,
        io: Io,
    ) -> Result<(Vec<Partial>, Vec<[f32; 2]>), GpuError> {
        self.ensure_out(io.partials, io.sample, io.counts);
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
        let psize = std::mem::size_of::<Partial>();
        let pair = std::mem::size_of::<[f32; 2]>();
        let (pbytes, cbytes) = ((io.partials * psize) as u64, (io.counts * pair) as u64);
        if self.slots > 1 && pbytes > 0 {
            enc.clear_buffer(&self.out.partials, 0, Some(pbytes));
        }
        if self.slots > 1 && cbytes > 0 {
            enc.clear_buffer(&self.out.counts, 0, Some(cbytes));
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
        let o = &self.out;
        if pbytes > 0 {
            enc.copy_buffer_to_buffer(&o.partials, 0, &o.staging, 0, pbytes);
        }
        let (pairs, tail) = if io.counts > 0 {
            (io.counts, &o.counts)
        } else {
            (io.sample, &o.sample)
        };
        if pairs > 0 {
            enc.copy_buffer_to_buffer(tail, 0, &o.staging, pbytes, (pairs * pair) as u64);
        }
        self.ctx.submit(enc.finish());
        let floats = (pbytes as usize + pairs * pair) / 4;
        let v: Vec<f32> = self.ctx.read_staging(&self.out.staging, floats)?;
        let bytes: &[u8] = bytemuck::cast_slice(&v);
        let (pb, tb) = bytes.split_at(pbytes as usize);
        let parts = pb
            .chunks_exact(psize)
            .map(bytemuck::pod_read_unaligned::<Partial>)
            .collect();
        let pairs = tb
            .chunks_exact(pair)
            .map(bytemuck::pod_read_unaligned::<[f32; 2]>)
            .collect();
        Ok((parts, pairs))
    }

    /// The normal equations at the pose in `params` and, in the same submission and read-back,
    /// the systematic residual sample at that pose (for the next iteration's scale).
    pub(crate) fn normal_equations_and_sample(
        &mut self,
        params: &WarpParams,
        reference: &GpuPyramid,
        current: &GpuPyramid,
    ) -> Result<PartialsAndSample, GpuError> {
        let n = params.pixels();
        let groups = self.ctx.reduction_groups(n, WG);
        let count = params.samples as usize;
        // The normal-equation kernel writes the sample itself (samples > 0) when it has at most
        // one entry per pixel; a larger sample (pixels repeated) takes the separate pass.
        let sample_pass = (Pipe::Sample, count.div_ceil(WG) as u32);
        let dispatches: &[(Pipe, u32)] = if count <= n {
            &[(Pipe::Normal, groups)]
        } else {
            &[(Pipe::Normal, groups), sample_pass]
        };
        let io = Io {
            partials: groups as usize * self.slots,
            sample: count,
            counts: 0,
        };
        self.run(dispatches, params, reference, current, io)
    }

    /// Partial sums of the normal equations at the pose in `params` (no residual sample).
    pub(crate) fn normal_equation_partials(
        &mut self,
        params: &WarpParams,
        reference: &GpuPyramid,
        current: &GpuPyramid,
    ) -> Result<Vec<Partial>, GpuError> {
        let n = params.pixels();
        let groups = self.ctx.reduction_groups(n, WG);
        let mut p = *params;
        p.samples = 0;
        let io = Io {
            partials: groups as usize * self.slots,
            sample: 0,
            counts: 0,
        };
        Ok(self
            .run(&[(Pipe::Normal, groups)], &p, reference, current, io)?
            .0)
    }

    /// The systematic residual sample (`params.samples` entries).
    pub(crate) fn sample_residuals(
        &mut self,
        params: &WarpParams,
        reference: &GpuPyramid,
        current: &GpuPyramid,
    ) -> Result<Vec<[f32; 2]>, GpuError> {
        let count = params.samples as usize;
        let io = Io {
            partials: 0,
            sample: count,
            counts: 0,
        };
        let groups = count.div_ceil(WG) as u32;
        Ok(self
            .run(&[(Pipe::Sample, groups)], params, reference, current, io)?
            .1)
    }

    /// Covisibility counts `(pixels with depth, covisible pixels)`.
    pub(crate) fn covisibility_counts(
        &mut self,
        params: &WarpParams,
        reference: &GpuPyramid,
        current: &GpuPyramid,
    ) -> Result<(u64, u64), GpuError> {
        let groups = self.ctx.reduction_groups(params.pixels(), WG);
        let io = Io {
            partials: 0,
            sample: 0,
            counts: groups as usize * self.slots,
        };
        let (_, v) = self.run(&[(Pipe::Covis, groups)], params, reference, current, io)?;
        let mut a = 0u64;
        let mut b = 0u64;
        for c in v {
            a += c[0] as u64;
            b += c[1] as u64;
        }
        Ok((a, b))
    }

    /// Reads a pyramid back (for parity tests).
    #[cfg(test)]
    pub(crate) fn read_pyramid(&self, p: &GpuPyramid) -> Result<PyramidData, GpuError> {
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

/// What a submission reads back: partials, then sample entries or count pairs.
#[derive(Clone, Copy)]
struct Io {
    partials: usize,
    sample: usize,
    counts: usize,
}

#[derive(Clone, Copy)]
enum Pipe {
    Normal,
    Sample,
    Covis,
}
