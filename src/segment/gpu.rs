//! GPU host code of the image-domain normal kernel (`shaders/normals.wgsl`).

use std::sync::Arc;

use super::normals::{cam_f32, NormalMap, NormalParams};
use super::SegmentError;
use crate::camera::PinholeCamera;
use crate::gpu::{shaders, GpuContext, GpuError};
use crate::image::ImageF32;

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct Params {
    width: u32,
    height: u32,
    step: u32,
    _pad: u32,
    fx: f32,
    fy: f32,
    cx: f32,
    cy: f32,
    jump_tolerance: f32,
    _pad1: [f32; 3],
}

/// Uniform block of `normals.wgsl` (`Params`, same layout; a test compares them).
/// The normal kernel compiled once on a device; [`GpuNormals::compute`] runs it per image.
pub struct GpuNormals {
    ctx: Arc<GpuContext>,
    pipeline: wgpu::ComputePipeline,
}

impl GpuNormals {
    /// Compiles `normals.wgsl` on `ctx`.
    pub fn new(ctx: Arc<GpuContext>) -> Result<Self, SegmentError> {
        let src = shaders::assembled("normals.wgsl").ok_or_else(|| GpuError::Shader {
            name: "normals.wgsl".into(),
            message: "not embedded".into(),
        })?;
        let mut pipes = ctx.compute_pipelines("normals.wgsl", &src, &["image_normals"])?;
        let pipeline = pipes.pop().ok_or_else(|| GpuError::Shader {
            name: "normals.wgsl".into(),
            message: "no pipeline".into(),
        })?;
        Ok(Self { ctx, pipeline })
    }

    /// Normals of `inverse_depth` (1/m, 0 = invalid) on the GPU; same result as
    /// [`super::normals_cpu`] up to f32 rounding.
    pub fn compute(
        &self,
        inverse_depth: &ImageF32,
        camera: &PinholeCamera,
        params: &NormalParams,
    ) -> Result<NormalMap, SegmentError> {
        let (w, h) = (inverse_depth.width, inverse_depth.height);
        if w == 0 || h == 0 {
            return Ok(NormalMap {
                width: w,
                height: h,
                data: Vec::new(),
            });
        }
        let ctx = &self.ctx;
        let [fx, fy, cx, cy] = cam_f32(camera);
        let p = Params {
            width: w as u32,
            height: h as u32,
            step: params.step.max(1),
            _pad: 0,
            fx,
            fy,
            cx,
            cy,
            jump_tolerance: params.jump_tolerance,
            _pad1: [0.0; 3],
        };
        let ubuf = ctx.uniform("normals params", std::mem::size_of::<Params>() as u64);
        ctx.queue.write_buffer(&ubuf, 0, bytemuck::bytes_of(&p));
        let input = ctx.storage_init("inverse depth", &inverse_depth.data);
        let out = ctx.storage("normals", (w * h * 16) as u64);
        let layout = self.pipeline.get_bind_group_layout(0);
        let bind = ctx.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some("normals"),
            layout: &layout,
            entries: &[
                wgpu::BindGroupEntry {
                    binding: 0,
                    resource: ubuf.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: input.as_entire_binding(),
                },
                wgpu::BindGroupEntry {
                    binding: 2,
                    resource: out.as_entire_binding(),
                },
            ],
        });
        let mut enc = ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("normals"),
            });
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("normals"),
                timestamp_writes: None,
            });
            pass.set_pipeline(&self.pipeline);
            pass.set_bind_group(0, &bind, &[]);
            pass.dispatch_workgroups((w as u32).div_ceil(16), (h as u32).div_ceil(16), 1);
        }
        ctx.submit(enc.finish());
        let raw: Vec<[f32; 4]> = ctx.read_buffer(&out, w * h)?;
        let data = raw
            .into_iter()
            .map(|v| {
                if v[3] > 0.0 {
                    [v[0], v[1], v[2]]
                } else {
                    [0.0; 3]
                }
            })
            .collect();
        Ok(NormalMap {
            width: w,
            height: h,
            data,
        })
    }
}

impl super::NormalKernels for GpuNormals {
    fn compute(
        &mut self,
        inverse_depth: &ImageF32,
        camera: &PinholeCamera,
        params: &NormalParams,
    ) -> Result<NormalMap, SegmentError> {
        GpuNormals::compute(self, inverse_depth, camera, params)
    }
}

#[cfg(test)]
mod tests {
    use super::Params;
    use crate::gpu::{host_layout, layout_mismatches, shaders};

    #[test]
    fn params_match_the_wgsl_layout() {
        let host = host_layout!(Params {
            width,
            height,
            step,
            _pad,
            fx,
            fy,
            cx,
            cy,
            jump_tolerance,
            _pad1 = _pad1[0] stride 4,
            _pad2 = _pad1[1] stride 4,
            _pad3 = _pad1[2] stride 4,
        });
        let src = shaders::assembled("normals.wgsl").unwrap_or_default();
        let bad = layout_mismatches(&src, "Params", &host, std::mem::size_of::<Params>());
        assert!(bad.is_empty(), "{}", bad.join("\n"));
    }
}
