//! GPU host code of the ray caster (`shaders/raycast.wgsl`, CPU mirror in `raycast.rs`).
//!
//! The scene (primitives, BVH nodes, materials) and the camera's ray table are uploaded once;
//! each frame writes a uniform ([`RayParams`]: pose and lighting), dispatches one invocation per
//! pixel and reads back colour/object and depth/incidence. The sensor model then runs on
//! the CPU, identically for both backends.

use std::sync::Arc;

use super::raycast::{CastSample, PackedMaterial, PackedNode, PackedPrim};
use super::render::{pose_f32, RayTable};
use super::scene::Scene;
use super::SynthError;
use crate::geometry::Se3;
use crate::gpu::GpuContext;

const SHADER: &str = "raycast.wgsl";
const WORKGROUP: u32 = 64;

/// Uniform block of `raycast.wgsl` (`Params`, same layout; a test compares them).
#[repr(C)]
#[derive(Clone, Copy, Debug, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct RayParams {
    /// Columns of the `world_from_camera` rotation in `[0..3]`.
    pub(crate) rot0: [f32; 4],
    pub(crate) rot1: [f32; 4],
    pub(crate) rot2: [f32; 4],
    /// Camera origin in the world (m) in `[0..3]`.
    pub(crate) origin: [f32; 4],
    /// Direction towards the light in `[0..3]`, ambient term in `[3]`.
    pub(crate) light: [f32; 4],
    /// Diffuse term.
    pub(crate) diffuse: f32,
    /// Rays per row and rows.
    pub(crate) width: u32,
    pub(crate) height: u32,
    /// BVH nodes.
    pub(crate) node_count: u32,
}

/// The WGSL ray caster with one scene and one camera's ray table uploaded.
pub struct GpuRayCaster {
    ctx: Arc<GpuContext>,
    pipeline: wgpu::ComputePipeline,
    bind_group: wgpu::BindGroup,
    params: wgpu::Buffer,
    out_color: wgpu::Buffer,
    out_depth: wgpu::Buffer,
    staging_color: wgpu::Buffer,
    staging_depth: wgpu::Buffer,
    pixels: usize,
    node_count: u32,
    lighting: [f32; 6],
}

impl GpuRayCaster {
    /// Compiles the kernel (once per caster) and uploads the scene and rays.
    pub fn new(ctx: Arc<GpuContext>, scene: &Scene, rays: &RayTable) -> Result<Self, SynthError> {
        let src =
            crate::gpu::shaders::assembled(SHADER).ok_or_else(|| crate::gpu::GpuError::Shader {
                name: SHADER.into(),
                message: "not embedded".into(),
            })?;
        let mut pipelines = ctx.compute_pipelines(SHADER, &src, &["raycast"])?;
        let pipeline = pipelines.remove(0);
        let packed = scene.packed();
        // Empty arrays are not valid bindings: pad with one zero element.
        let prims: Vec<PackedPrim> = if packed.prims.is_empty() {
            vec![bytemuck::Zeroable::zeroed()]
        } else {
            packed.prims.clone()
        };
        let nodes: Vec<PackedNode> = if packed.nodes.is_empty() {
            vec![bytemuck::Zeroable::zeroed()]
        } else {
            packed.nodes.clone()
        };
        let materials: Vec<PackedMaterial> = if packed.materials.is_empty() {
            vec![bytemuck::Zeroable::zeroed()]
        } else {
            packed.materials.clone()
        };
        let pixels = rays.width * rays.height;
        let ray_data: Vec<[f32; 4]> = if rays.rays.is_empty() {
            vec![[0.0; 4]]
        } else {
            rays.rays.clone()
        };
        let b_prims = ctx.storage_init("synth prims", &prims);
        let b_nodes = ctx.storage_init("synth nodes", &nodes);
        let b_mats = ctx.storage_init("synth materials", &materials);
        let b_rays = ctx.storage_init("synth rays", &ray_data);
        let params = ctx.uniform("synth params", std::mem::size_of::<RayParams>() as u64);
        let color_bytes = (pixels.max(1) * 16) as u64;
        let depth_bytes = (pixels.max(1) * 8) as u64;
        let out_color = ctx.storage("synth out color", color_bytes);
        let out_depth = ctx.storage("synth out depth", depth_bytes);
        let staging_color = ctx.staging("synth staging color", color_bytes);
        let staging_depth = ctx.staging("synth staging depth", depth_bytes);
        let layout = pipeline.get_bind_group_layout(0);
        let entries = [
            (0, &params),
            (1, &b_prims),
            (2, &b_nodes),
            (3, &b_mats),
            (4, &b_rays),
            (5, &out_color),
            (6, &out_depth),
        ]
        .map(|(binding, b)| wgpu::BindGroupEntry {
            binding,
            resource: b.as_entire_binding(),
        });
        let bind_group = ctx.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("synth raycast"),
            layout: &layout,
            entries: &entries,
        });
        ctx.check()?;
        let l = scene.lighting();
        Ok(GpuRayCaster {
            ctx,
            pipeline,
            bind_group,
            params,
            out_color,
            out_depth,
            staging_color,
            staging_depth,
            pixels,
            node_count: packed.nodes.len() as u32,
            lighting: [
                l.to_light[0],
                l.to_light[1],
                l.to_light[2],
                l.ambient,
                l.diffuse,
                0.0,
            ],
        })
    }

    /// The adapter's name.
    pub fn adapter_name(&self) -> String {
        format!("{}, {:?}", self.ctx.info.name, self.ctx.info.backend)
    }

    /// Casts every pixel's ray from `world_from_camera` and reads the samples back.
    pub fn cast(&mut self, world_from_camera: &Se3) -> Result<Vec<CastSample>, SynthError> {
        if self.pixels == 0 {
            return Ok(Vec::new());
        }
        let (r, o) = pose_f32(world_from_camera);
        // The kernel only needs the pixel count: width = pixels, height = 1.
        let w = self.pixels as u32;
        let l = self.lighting;
        let u = RayParams {
            rot0: [r[0][0], r[0][1], r[0][2], 0.0],
            rot1: [r[1][0], r[1][1], r[1][2], 0.0],
            rot2: [r[2][0], r[2][1], r[2][2], 0.0],
            origin: [o[0], o[1], o[2], 0.0],
            light: [l[0], l[1], l[2], l[3]],
            diffuse: l[4],
            width: w,
            height: 1,
            node_count: self.node_count,
        };
        self.ctx
            .queue
            .write_buffer(&self.params, 0, bytemuck::bytes_of(&u));
        let groups = (self.pixels as u32).div_ceil(WORKGROUP);
        let gx = groups.min(32768);
        let gy = groups.div_ceil(gx);
        let mut enc = self
            .ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("synth raycast"),
            });
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("synth raycast"),
                timestamp_writes: None,
            });
            pass.set_pipeline(&self.pipeline);
            pass.set_bind_group(0, &self.bind_group, &[]);
            pass.dispatch_workgroups(gx, gy, 1);
        }
        let cb = (self.pixels * 16) as u64;
        let db = (self.pixels * 8) as u64;
        enc.copy_buffer_to_buffer(&self.out_color, 0, &self.staging_color, 0, cb);
        enc.copy_buffer_to_buffer(&self.out_depth, 0, &self.staging_depth, 0, db);
        self.ctx.submit(enc.finish());
        let color: Vec<[f32; 4]> = self.ctx.read_staging(&self.staging_color, self.pixels)?;
        let depth: Vec<[f32; 2]> = self.ctx.read_staging(&self.staging_depth, self.pixels)?;
        Ok(color
            .iter()
            .zip(&depth)
            .map(|(c, d)| CastSample {
                z: d[0],
                cos_incidence: d[1],
                rgb: [c[0], c[1], c[2]],
                object: c[3].to_bits(),
            })
            .collect())
    }
}

#[cfg(test)]
mod tests {
    use super::super::raycast::{PackedMaterial, PackedNode, PackedPrim};
    use super::RayParams;
    use crate::gpu::{host_layout, layout_mismatches, shaders};
    use std::mem::size_of;

    #[test]
    fn host_structs_match_the_wgsl_layouts() {
        let src = shaders::assembled(super::SHADER).unwrap_or_default();
        let structs = [
            (
                "Params",
                host_layout!(RayParams {
                    rot0,
                    rot1,
                    rot2,
                    origin,
                    light,
                    diffuse,
                    width,
                    height,
                    node_count,
                }),
                size_of::<RayParams>(),
            ),
            (
                "Prim",
                host_layout!(PackedPrim {
                    center,
                    row0 = rows[0] stride 16,
                    row1 = rows[1] stride 16,
                    row2 = rows[2] stride 16,
                    anchor,
                    extra,
                }),
                size_of::<PackedPrim>(),
            ),
            (
                "Node",
                host_layout!(PackedNode {
                    bmin = min[0] stride 16,
                    bmax = max[0] stride 16,
                }),
                size_of::<PackedNode>(),
            ),
            (
                "Material",
                host_layout!(PackedMaterial {
                    color0,
                    color1,
                    params
                }),
                size_of::<PackedMaterial>(),
            ),
        ];
        for (name, host, size) in structs {
            let bad = layout_mismatches(&src, name, &host, size);
            assert!(bad.is_empty(), "{}", bad.join("\n"));
        }
    }
}
