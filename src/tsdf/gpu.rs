//! The TSDF kernels on a wgpu device, with the voxels resident there: integration
//! (`shaders/tsdf.wgsl`), ray casting (`shaders/tsdf_cast.wgsl`) and the per-cube work of
//! mesh extraction (`shaders/tsdf_mesh.wgsl`).

use std::borrow::Cow;
use std::sync::Arc;

use super::integrate::{IntegrateUniform, TsdfKernels, Voxel};
use super::mesh::{CubeTriangles, CubeVertex, MeshUniform, BLOCK_ROWS, ROW_CUBES};
use super::raycast::CastUniform;
use super::{RayCastImages, TsdfError, BLOCK_SIDE, BLOCK_VOXELS};
use crate::gpu::{shaders, GpuContext, GpuError};
use crate::image::ImageF32;

/// Workgroups per dispatch row (the per-dimension dispatch limit of every wgpu backend).
const ROW: u32 = 65535;

/// Buffers sized for the frame and the block capacity, with their bind group.
struct Resident {
    rho: wgpu::Buffer,
    rgb: wgpu::Buffer,
    active: wgpu::Buffer,
    voxels: wgpu::Buffer,
    bind: wgpu::BindGroup,
    pixels: usize,
    active_capacity: usize,
    block_capacity: usize,
}

/// The ray-cast kernel: pipeline, bind-group layout and uniform.
struct CastKernel {
    pipeline: wgpu::ComputePipeline,
    layout: wgpu::BindGroupLayout,
    uniform: wgpu::Buffer,
}

impl CastKernel {
    fn new(ctx: &GpuContext) -> Result<Self, TsdfError> {
        let name = "tsdf_cast.wgsl";
        let missing = |message: &str| GpuError::Shader {
            name: name.into(),
            message: message.into(),
        };
        let src = shaders::assembled(name).ok_or_else(|| missing("not embedded"))?;
        let layout = ctx.buffer_layout("tsdf cast", &[true, true, false, false, false]);
        let pipeline = ctx
            .compute_pipelines_with_layout(name, &src, &["cast_rays"], Some(&layout))?
            .pop()
            .ok_or_else(|| missing("no pipeline"))?;
        let uniform = ctx.uniform(
            "tsdf cast params",
            std::mem::size_of::<CastUniform>() as u64,
        );
        Ok(CastKernel {
            pipeline,
            layout,
            uniform,
        })
    }
}

/// The mesh kernels (`count_cubes`, `emit_cubes`): pipelines, bind-group layout and uniform.
struct MeshKernel {
    count: wgpu::ComputePipeline,
    emit: wgpu::ComputePipeline,
    layout: wgpu::BindGroupLayout,
    uniform: wgpu::Buffer,
}

impl MeshKernel {
    fn new(ctx: &GpuContext) -> Result<Self, TsdfError> {
        let name = "tsdf_mesh.wgsl";
        let missing = |message: &str| GpuError::Shader {
            name: name.into(),
            message: message.into(),
        };
        let src = shaders::assembled(name).ok_or_else(|| missing("not embedded"))?;
        let layout = ctx.buffer_layout("tsdf mesh", &[true, true, true, false, true, false]);
        let mut pipes = ctx.compute_pipelines_with_layout(
            name,
            &src,
            &["count_cubes", "emit_cubes"],
            Some(&layout),
        )?;
        let emit = pipes.pop().ok_or_else(|| missing("no pipeline"))?;
        let count = pipes.pop().ok_or_else(|| missing("no pipeline"))?;
        let uniform = ctx.uniform(
            "tsdf mesh params",
            std::mem::size_of::<MeshUniform>() as u64,
        );
        Ok(MeshKernel {
            count,
            emit,
            layout,
            uniform,
        })
    }
}

/// Workgroups `(x, y)` covering `n` workgroups in rows of [`ROW`].
fn groups(n: usize) -> (u32, u32) {
    let n = n as u32;
    (n.clamp(1, ROW), n.div_ceil(ROW).max(1))
}

pub(crate) struct GpuTsdf {
    ctx: Arc<GpuContext>,
    pipeline: wgpu::ComputePipeline,
    layout: wgpu::BindGroupLayout,
    uniform: wgpu::Buffer,
    cast: CastKernel,
    mesh: MeshKernel,
    resident: Option<Resident>,
    blocks: usize,
    /// Most slots of the voxel buffer (`None` = unbounded).
    slot_limit: Option<usize>,
}

fn voxel_bytes(blocks: usize) -> u64 {
    (blocks * BLOCK_VOXELS * std::mem::size_of::<Voxel>()) as u64
}

impl GpuTsdf {
    /// Compiles `tsdf.wgsl` on `ctx`.
    pub(crate) fn new(ctx: Arc<GpuContext>) -> Result<Self, TsdfError> {
        let src = shaders::assembled("tsdf.wgsl").ok_or_else(|| GpuError::Shader {
            name: "tsdf.wgsl".into(),
            message: "not embedded".into(),
        })?;
        let layout = ctx.buffer_layout("tsdf", &[true, true, true, false]);
        let mut pipes =
            ctx.compute_pipelines_with_layout("tsdf.wgsl", &src, &["integrate"], Some(&layout))?;
        let pipeline = pipes.pop().ok_or_else(|| GpuError::Shader {
            name: "tsdf.wgsl".into(),
            message: "no pipeline".into(),
        })?;
        let uniform = ctx.uniform(
            "tsdf params",
            std::mem::size_of::<IntegrateUniform>() as u64,
        );
        let cast = CastKernel::new(&ctx)?;
        let mesh = MeshKernel::new(&ctx)?;
        Ok(GpuTsdf {
            ctx,
            pipeline,
            cast,
            mesh,
            layout,
            uniform,
            resident: None,
            blocks: 0,
            slot_limit: None,
        })
    }

    /// Makes the buffers large enough; voxels already integrated are copied into a grown
    /// voxel buffer (new slots start zeroed, i.e. unobserved).
    fn ensure(&mut self, pixels: usize, active: usize, blocks: usize) -> Result<(), TsdfError> {
        let ctx = &self.ctx;
        let fits = self.resident.as_ref().is_some_and(|r| {
            r.pixels == pixels && r.active_capacity >= active && r.block_capacity >= blocks
        });
        if fits {
            return Ok(());
        }
        let old = self.resident.take();
        // Room to grow, within the slot limit (the paging budget) when there is one.
        let block_capacity = old
            .as_ref()
            .map_or(0, |r| r.block_capacity)
            .max(blocks + blocks / 2)
            .max(64)
            .min(self.slot_limit.unwrap_or(usize::MAX))
            .max(blocks);
        let limit = ctx
            .limits
            .max_storage_buffer_binding_size
            .min(ctx.limits.max_buffer_size);
        if voxel_bytes(block_capacity) > limit {
            return Err(TsdfError::InvalidParameter {
                name: "voxel_size",
                why: format!(
                    "{block_capacity} blocks need {} bytes, more than the device's storage \
                     buffer limit of {limit} bytes; use larger voxels or the CPU backend",
                    voxel_bytes(block_capacity)
                ),
            });
        }
        let active_capacity = old
            .as_ref()
            .map_or(0, |r| r.active_capacity)
            .max(active + active / 2)
            .max(64);
        let rho = ctx.storage("tsdf rho", (pixels * 4) as u64);
        let rgb = ctx.storage("tsdf rgb", (pixels * 4) as u64);
        let act = ctx.storage("tsdf active blocks", (active_capacity * 16) as u64);
        let voxels = ctx.storage("tsdf voxels", voxel_bytes(block_capacity));
        if let Some(o) = &old {
            let mut enc = ctx
                .device
                .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                    label: Some("tsdf grow"),
                });
            let keep = o.block_capacity.min(block_capacity);
            enc.copy_buffer_to_buffer(&o.voxels, 0, &voxels, 0, voxel_bytes(keep));
            ctx.submit(enc.finish());
        }
        let bind = ctx.bind_buffers(
            "tsdf",
            &self.layout,
            &[&self.uniform, &rho, &rgb, &act, &voxels],
        );
        self.resident = Some(Resident {
            rho,
            rgb,
            active: act,
            voxels,
            bind,
            pixels,
            active_capacity,
            block_capacity,
        });
        Ok(())
    }
}

impl GpuTsdf {
    /// Runs `emit_cubes` over `rows` (`[slot * 64 + y + 8 z, first triangle]`) and reads back
    /// their `triangles` triangles; `lookups` are the table and coordinate buffers.
    fn emit_rows(
        &self,
        rows: &[[u32; 2]],
        triangles: usize,
        u: &MeshUniform,
        lookups: &[&wgpu::Buffer; 2],
    ) -> Result<Vec<CubeVertex>, TsdfError> {
        let Some(r) = &self.resident else {
            return Err(GpuError::Validation("tsdf buffers missing".into()).into());
        };
        let ctx = &self.ctx;
        let k = &self.mesh;
        let count = 3 * triangles;
        let bytes = (count * std::mem::size_of::<CubeVertex>()) as u64;
        let rows_buf = ctx.storage_init("tsdf mesh rows", rows);
        let vertices = ctx.storage("tsdf mesh vertices", bytes);
        let unused_counts = ctx.storage("tsdf mesh counts placeholder", 16);
        ctx.queue.write_buffer(
            &k.uniform,
            0,
            bytemuck::bytes_of(&MeshUniform {
                rows: rows.len() as u32,
                ..*u
            }),
        );
        let bind = ctx.bind_buffers(
            "tsdf mesh emit",
            &k.layout,
            &[
                &k.uniform,
                lookups[0],
                lookups[1],
                &r.voxels,
                &unused_counts,
                &rows_buf,
                &vertices,
            ],
        );
        let staging = ctx.staging("tsdf mesh vertices readback", bytes);
        let mut enc = ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("tsdf mesh emit"),
            });
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("tsdf mesh emit"),
                timestamp_writes: None,
            });
            pass.set_pipeline(&k.emit);
            pass.set_bind_group(0, &bind, &[]);
            let (gx, gy) = groups(rows.len().div_ceil(64));
            pass.dispatch_workgroups(gx, gy, 1);
        }
        enc.copy_buffer_to_buffer(&vertices, 0, &staging, 0, bytes);
        ctx.submit(enc.finish());
        let out: Vec<CubeVertex> = ctx.read_staging(&staging, count)?;
        ctx.check()?;
        Ok(out)
    }
}

impl TsdfKernels for GpuTsdf {
    fn integrate(
        &mut self,
        blocks: usize,
        active: &[[i32; 4]],
        rho: &[f32],
        rgb: Option<&[u32]>,
        u: &IntegrateUniform,
    ) -> Result<(), TsdfError> {
        self.ensure(rho.len(), active.len(), blocks)?;
        self.blocks = blocks;
        let ctx = &self.ctx;
        let Some(r) = &self.resident else {
            return Err(GpuError::Validation("tsdf buffers missing".into()).into());
        };
        if active.is_empty() {
            return Ok(());
        }
        ctx.queue.write_buffer(&r.rho, 0, bytemuck::cast_slice(rho));
        if let Some(c) = rgb {
            ctx.queue.write_buffer(&r.rgb, 0, bytemuck::cast_slice(c));
        }
        ctx.queue
            .write_buffer(&r.active, 0, bytemuck::cast_slice(active));
        ctx.queue
            .write_buffer(&self.uniform, 0, bytemuck::bytes_of(u));
        let mut enc = ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("tsdf integrate"),
            });
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("tsdf integrate"),
                timestamp_writes: None,
            });
            pass.set_pipeline(&self.pipeline);
            pass.set_bind_group(0, &r.bind, &[]);
            let n = active.len() as u32;
            pass.dispatch_workgroups(n.min(ROW), n.div_ceil(ROW), 1);
        }
        ctx.submit(enc.finish());
        ctx.wait()?;
        ctx.check()?;
        Ok(())
    }

    fn voxels(&self) -> Result<Cow<'_, [Voxel]>, TsdfError> {
        let Some(r) = &self.resident else {
            return Ok(Cow::Owned(Vec::new()));
        };
        let v: Vec<Voxel> = self
            .ctx
            .read_buffer(&r.voxels, self.blocks * BLOCK_VOXELS)?;
        Ok(Cow::Owned(v))
    }

    fn set_voxels(&mut self, blocks: usize, voxels: &[Voxel]) -> Result<(), TsdfError> {
        // The frame buffers keep their size (a small placeholder before the first frame;
        // the first integration resizes them and keeps the voxels).
        let pixels = self.resident.as_ref().map_or(64, |r| r.pixels);
        self.ensure(pixels, 1, blocks)?;
        self.blocks = blocks;
        let Some(r) = &self.resident else {
            return Err(GpuError::Validation("tsdf buffers missing".into()).into());
        };
        let n = voxels.len().min(blocks * BLOCK_VOXELS);
        let mut enc = self
            .ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("tsdf load"),
            });
        // Slots past the loaded ones start unobserved, as after growing.
        enc.clear_buffer(&r.voxels, 0, None);
        self.ctx.submit(enc.finish());
        if n > 0 {
            self.ctx
                .queue
                .write_buffer(&r.voxels, 0, bytemuck::cast_slice(&voxels[..n]));
        }
        // Staged writes reach the buffer with the next submission.
        let enc = self
            .ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("tsdf load flush"),
            });
        self.ctx.submit(enc.finish());
        self.ctx.wait()?;
        self.ctx.check()?;
        Ok(())
    }

    fn read_slots(&self, slots: &[u32]) -> Result<Vec<Voxel>, TsdfError> {
        let Some(r) = &self.resident else {
            return Ok(vec![Voxel::default(); slots.len() * BLOCK_VOXELS]);
        };
        if slots.is_empty() {
            return Ok(Vec::new());
        }
        let block = voxel_bytes(1);
        let staging = self
            .ctx
            .staging("tsdf page-out", block * slots.len() as u64);
        let mut enc = self
            .ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("tsdf page-out"),
            });
        for (i, &s) in slots.iter().enumerate() {
            if s as usize >= r.block_capacity {
                return Err(GpuError::Validation(format!(
                    "tsdf slot {s} beyond the {} slots",
                    r.block_capacity
                ))
                .into());
            }
            enc.copy_buffer_to_buffer(
                &r.voxels,
                u64::from(s) * block,
                &staging,
                i as u64 * block,
                block,
            );
        }
        self.ctx.submit(enc.finish());
        let v = self
            .ctx
            .read_staging(&staging, slots.len() * BLOCK_VOXELS)?;
        self.ctx.check()?;
        Ok(v)
    }

    fn write_slots(
        &mut self,
        blocks: usize,
        uploads: &[(u32, Vec<Voxel>)],
        zeroed: &[u32],
    ) -> Result<(), TsdfError> {
        let pixels = self.resident.as_ref().map_or(64, |r| r.pixels);
        self.ensure(pixels, 1, blocks)?;
        self.blocks = self.blocks.max(blocks);
        let Some(r) = &self.resident else {
            return Err(GpuError::Validation("tsdf buffers missing".into()).into());
        };
        let block = voxel_bytes(1);
        let zero = vec![Voxel::default(); BLOCK_VOXELS];
        let writes = uploads
            .iter()
            .map(|(s, v)| (*s, v.as_slice()))
            .chain(zeroed.iter().map(|s| (*s, zero.as_slice())));
        for (s, v) in writes {
            if s as usize >= r.block_capacity || v.len() != BLOCK_VOXELS {
                return Err(GpuError::Validation(format!(
                    "tsdf slot {s} beyond the {} slots",
                    r.block_capacity
                ))
                .into());
            }
            // Staged: applied before the next submission (the integration's).
            self.ctx
                .queue
                .write_buffer(&r.voxels, u64::from(s) * block, bytemuck::cast_slice(v));
        }
        Ok(())
    }

    fn set_slot_limit(&mut self, limit: Option<usize>) -> Result<(), TsdfError> {
        self.slot_limit = limit;
        let Some(b) = limit else {
            return Ok(());
        };
        self.blocks = self.blocks.min(b);
        let over = self.resident.as_ref().is_some_and(|r| r.block_capacity > b);
        if over {
            // Reallocate at the limit, keeping the slots below it.
            let (pixels, active) = self
                .resident
                .as_ref()
                .map_or((64, 1), |r| (r.pixels, r.active_capacity));
            if let Some(r) = self.resident.as_mut() {
                r.pixels = usize::MAX;
            }
            self.ensure(pixels, active, b)?;
            self.ctx.wait()?;
            self.ctx.check()?;
        }
        Ok(())
    }

    fn slot_capacity(&self) -> usize {
        self.resident.as_ref().map_or(0, |r| r.block_capacity)
    }

    fn ray_cast(
        &self,
        table: &[[i32; 4]],
        u: &CastUniform,
    ) -> Result<Option<RayCastImages>, TsdfError> {
        let (w, h) = (u.width as usize, u.height as usize);
        let pixels = w * h;
        let Some(r) = &self.resident else {
            // Nothing integrated yet: no surface anywhere.
            return Ok(Some(RayCastImages {
                depth: ImageF32::filled(w, h, 0.0),
                normals: vec![[0.0; 3]; pixels],
                colours: vec![[0; 3]; pixels],
            }));
        };
        let ctx = &self.ctx;
        let k = &self.cast;
        let normals_len = if u.with_normals == 1 { pixels } else { 1 };
        let table_buf = ctx.storage_init("tsdf cast table", table);
        let depth = ctx.storage("tsdf cast depth", (pixels * 4) as u64);
        let rgb = ctx.storage("tsdf cast rgb", (pixels * 4) as u64);
        let normals = ctx.storage("tsdf cast normals", (normals_len * 16) as u64);
        ctx.queue.write_buffer(&k.uniform, 0, bytemuck::bytes_of(u));
        let bind = ctx.bind_buffers(
            "tsdf cast",
            &k.layout,
            &[&k.uniform, &table_buf, &r.voxels, &depth, &rgb, &normals],
        );
        // One staging buffer: depth, then colour, then normals (4 words per pixel).
        let words = 2 * pixels + 4 * normals_len;
        let staging = ctx.staging("tsdf cast readback", (words * 4) as u64);
        let mut enc = ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("tsdf cast"),
            });
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("tsdf cast"),
                timestamp_writes: None,
            });
            pass.set_pipeline(&k.pipeline);
            pass.set_bind_group(0, &bind, &[]);
            pass.dispatch_workgroups(u.width.div_ceil(8), u.height.div_ceil(8), 1);
        }
        let plane = (pixels * 4) as u64;
        enc.copy_buffer_to_buffer(&depth, 0, &staging, 0, plane);
        enc.copy_buffer_to_buffer(&rgb, 0, &staging, plane, plane);
        enc.copy_buffer_to_buffer(&normals, 0, &staging, 2 * plane, (normals_len * 16) as u64);
        ctx.submit(enc.finish());
        let out: Vec<u32> = ctx.read_staging(&staging, words)?;
        ctx.check()?;
        let (d, rest) = out.split_at(pixels);
        let (c, n) = rest.split_at(pixels);
        let depth = d.iter().map(|&v| f32::from_bits(v)).collect();
        let colours = c
            .iter()
            .map(|&v| [v as u8, (v >> 8) as u8, (v >> 16) as u8])
            .collect();
        let normals = if u.with_normals == 1 {
            n.chunks_exact(4)
                .map(|q| [0, 1, 2].map(|i| f32::from_bits(q[i])))
                .collect()
        } else {
            vec![[0.0; 3]; pixels]
        };
        Ok(Some(RayCastImages {
            depth: ImageF32::from_vec(w, h, depth)
                .ok_or_else(|| GpuError::Validation("tsdf cast: depth size".into()))?,
            normals,
            colours,
        }))
    }

    fn mesh_cubes(
        &self,
        table: &[[i32; 4]],
        coords: &[[i32; 4]],
        u: &MeshUniform,
    ) -> Result<Option<CubeTriangles>, TsdfError> {
        let Some(r) = &self.resident else {
            return Ok(Some(CubeTriangles::default()));
        };
        let blocks = coords.len();
        if blocks == 0 {
            return Ok(Some(CubeTriangles::default()));
        }
        if blocks > r.block_capacity {
            return Err(GpuError::Validation(format!(
                "tsdf mesh: {blocks} blocks, {} slots",
                r.block_capacity
            ))
            .into());
        }
        let ctx = &self.ctx;
        let k = &self.mesh;
        let table_buf = ctx.storage_init("tsdf mesh table", table);
        let coords_buf = ctx.storage_init("tsdf mesh coords", coords);
        let row_words = blocks * BLOCK_ROWS;
        let counts = ctx.storage("tsdf mesh counts", (row_words * 4) as u64);
        // Unused by the counting pass (separate buffers: one is read-only, one read-write).
        let unused_rows = ctx.storage("tsdf mesh rows placeholder", 16);
        let unused_vertices = ctx.storage("tsdf mesh vertices placeholder", 16);
        // Pass 1: every row's triangle counts.
        ctx.queue.write_buffer(
            &k.uniform,
            0,
            bytemuck::bytes_of(&MeshUniform {
                blocks: blocks as u32,
                rows: 0,
                ..*u
            }),
        );
        let bind = ctx.bind_buffers(
            "tsdf mesh count",
            &k.layout,
            &[
                &k.uniform,
                &table_buf,
                &coords_buf,
                &r.voxels,
                &counts,
                &unused_rows,
                &unused_vertices,
            ],
        );
        let staging = ctx.staging("tsdf mesh counts readback", (row_words * 4) as u64);
        let mut enc = ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("tsdf mesh count"),
            });
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("tsdf mesh count"),
                timestamp_writes: None,
            });
            pass.set_pipeline(&k.count);
            pass.set_bind_group(0, &bind, &[]);
            let (gx, gy) = groups(blocks);
            pass.dispatch_workgroups(gx, gy, 1);
        }
        enc.copy_buffer_to_buffer(&counts, 0, &staging, 0, (row_words * 4) as u64);
        ctx.submit(enc.finish());
        let packed: Vec<u32> = ctx.read_staging(&staging, row_words)?;
        ctx.check()?;
        // The rows with triangles, each with its first triangle, and the cubes in order.
        let mut out = CubeTriangles::default();
        let mut listed: Vec<[u32; 2]> = Vec::new();
        let mut total = 0u32;
        let side = BLOCK_SIDE as i32;
        for (row, &word) in packed.iter().enumerate() {
            if word == 0 {
                continue;
            }
            listed.push([row as u32, total]);
            let b = coords[row / BLOCK_ROWS];
            let (y, z) = (
                (row % BLOCK_ROWS) % BLOCK_SIDE,
                (row % BLOCK_ROWS) / BLOCK_SIDE,
            );
            for x in 0..ROW_CUBES {
                let n = (word >> (4 * x)) & 15;
                if n > 0 {
                    let g = [
                        b[0] * side + x as i32,
                        b[1] * side + y as i32,
                        b[2] * side + z as i32,
                    ];
                    out.cubes.push((g, n));
                    total += n;
                }
            }
        }
        // Pass 2, in chunks of rows whose triangles fit one storage binding.
        let vertex_bytes = std::mem::size_of::<CubeVertex>();
        let limit = ctx
            .limits
            .max_storage_buffer_binding_size
            .min(ctx.limits.max_buffer_size)
            .min(1 << 28) as usize;
        // A row has at most 12 triangles per cube.
        let row_most = (12 * ROW_CUBES) as u32;
        let max_triangles = ((limit / (3 * vertex_bytes)) as u32).max(row_most);
        out.vertices.reserve(3 * total as usize);
        let mut start = 0;
        while start < listed.len() {
            let first = listed[start][1];
            let mut end = start + 1;
            while end < listed.len() && listed[end][1] - first + row_most <= max_triangles {
                end += 1;
            }
            let chunk_end = listed.get(end).map_or(total, |e| e[1]);
            let triangles = (chunk_end - first) as usize;
            let chunk: Vec<[u32; 2]> = listed[start..end]
                .iter()
                .map(|&[row, t]| [row, t - first])
                .collect();
            out.vertices.extend(self.emit_rows(
                &chunk,
                triangles,
                u,
                &[&table_buf, &coords_buf],
            )?);
            start = end;
        }
        Ok(Some(out))
    }

    fn memory_bytes(&self) -> (usize, usize) {
        let resident = self.resident.as_ref().map_or(0, |r| {
            r.rho.size() + r.rgb.size() + r.active.size() + r.voxels.size()
        });
        (
            0,
            (self.uniform.size() + self.mesh.uniform.size() + resident) as usize,
        )
    }
}
