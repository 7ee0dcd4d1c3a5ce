//! GPU host code of the undistortion kernel (`shaders/undistort.wgsl`): the same remap table
//! as [`UndistortMap`], uploaded once, applied to each raw frame on the device.

use std::sync::Arc;

use super::undistort::UndistortMap;
use crate::gpu::{shaders, GpuContext, GpuError};

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct Params {
    width: u32,
    height: u32,
    _pad: [u32; 2],
}

/// An [`UndistortMap`] on a GPU device: the kernel is compiled and the table uploaded once
/// ([`GpuUndistort::new`]); [`GpuUndistort::remap`] undistorts one frame. Results equal the
/// CPU mirror's ([`UndistortMap::remap_bilinear`], [`UndistortMap::remap_nearest`]) up to
/// f32 rounding of the bilinear blend (nearest-neighbour depth is exact).
pub struct GpuUndistort {
    ctx: Arc<GpuContext>,
    pipeline: wgpu::ComputePipeline,
    /// The remap table and the size uniform; bound in `frame.bind`, kept here for clarity of
    /// ownership.
    _table: wgpu::Buffer,
    _params: wgpu::Buffer,
    width: usize,
    height: usize,
    /// Input, output and staging buffers of one frame, reused by every call (one call at a
    /// time; a poisoned lock is recovered: the buffers hold no state between calls).
    frame: std::sync::Mutex<FrameBuffers>,
}

struct FrameBuffers {
    raw_intensity: wgpu::Buffer,
    raw_inverse_depth: wgpu::Buffer,
    out: wgpu::Buffer,
    staging: wgpu::Buffer,
    bind: wgpu::BindGroup,
}

impl std::fmt::Debug for GpuUndistort {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "GpuUndistort({} x {} on {})",
            self.width, self.height, self.ctx.info.name
        )
    }
}

impl GpuUndistort {
    /// Compiles `undistort.wgsl` on `ctx` and uploads the table of `map`.
    pub fn new(ctx: Arc<GpuContext>, map: &UndistortMap) -> Result<Self, GpuError> {
        let name = "undistort.wgsl";
        let src = shaders::assembled(name).ok_or_else(|| GpuError::Shader {
            name: name.into(),
            message: "not embedded".into(),
        })?;
        let pipeline = ctx
            .compute_pipelines(name, &src, &["undistort"])?
            .pop()
            .ok_or_else(|| GpuError::Shader {
                name: name.into(),
                message: "no pipeline".into(),
            })?;
        let (width, height) = (map.width(), map.height());
        let table = ctx.storage_init("undistort table", &map.gpu_table());
        let params = ctx.uniform("undistort params", std::mem::size_of::<Params>() as u64);
        let p = Params {
            width: width as u32,
            height: height as u32,
            _pad: [0; 2],
        };
        ctx.queue.write_buffer(&params, 0, bytemuck::bytes_of(&p));
        let n = (width * height) as u64;
        let raw_intensity = ctx.storage("raw intensity", n * 4);
        let raw_inverse_depth = ctx.storage("raw inverse depth", n * 4);
        let out = ctx.storage("undistorted", 2 * n * 4);
        let staging = ctx.staging("undistorted read-back", 2 * n * 4);
        let layout = pipeline.get_bind_group_layout(0);
        let bind = ctx.bind_buffers(
            "undistort",
            &layout,
            &[&params, &table, &raw_intensity, &raw_inverse_depth, &out],
        );
        Ok(Self {
            ctx,
            pipeline,
            _table: table,
            _params: params,
            width,
            height,
            frame: std::sync::Mutex::new(FrameBuffers {
                raw_intensity,
                raw_inverse_depth,
                out,
                staging,
                bind,
            }),
        })
    }

    /// Image width of the table, pixels.
    pub fn width(&self) -> usize {
        self.width
    }

    /// Image height of the table, pixels.
    pub fn height(&self) -> usize {
        self.height
    }

    /// Undistorts one raw frame: `intensity` (0-255, bilinear) and `inverse_depth` (1/m,
    /// 0 = invalid, nearest neighbour), both `width * height` values in row-major order.
    /// Returns the undistorted (intensity, inverse depth). Slices of another length are a
    /// [`GpuError::Validation`] error (nothing is dispatched).
    pub fn remap(
        &self,
        intensity: &[f32],
        inverse_depth: &[f32],
    ) -> Result<(Vec<f32>, Vec<f32>), GpuError> {
        let n = self.width * self.height;
        if intensity.len() != n || inverse_depth.len() != n {
            return Err(GpuError::Validation(format!(
                "undistort: the table is {} x {} ({n} pixels) but the frame has {} intensity \
                 and {} inverse-depth values",
                self.width,
                self.height,
                intensity.len(),
                inverse_depth.len()
            )));
        }
        if n == 0 {
            return Ok((Vec::new(), Vec::new()));
        }
        let ctx = &self.ctx;
        let b = self
            .frame
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        ctx.queue
            .write_buffer(&b.raw_intensity, 0, bytemuck::cast_slice(intensity));
        ctx.queue
            .write_buffer(&b.raw_inverse_depth, 0, bytemuck::cast_slice(inverse_depth));
        let mut enc = ctx
            .device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("undistort"),
            });
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("undistort"),
                timestamp_writes: None,
            });
            pass.set_pipeline(&self.pipeline);
            pass.set_bind_group(0, &b.bind, &[]);
            pass.dispatch_workgroups(
                (self.width as u32).div_ceil(16),
                (self.height as u32).div_ceil(16),
                1,
            );
        }
        let bytes = (2 * n * 4) as u64;
        enc.copy_buffer_to_buffer(&b.out, 0, &b.staging, 0, bytes);
        ctx.queue.submit([enc.finish()]);
        let mut both: Vec<f32> = ctx.read_staging(&b.staging, 2 * n)?;
        let depth = both.split_off(n);
        Ok((both, depth))
    }
}
