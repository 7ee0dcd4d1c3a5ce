//! The odometry's kernel interface: everything the Gauss-Newton tracker asks of a backend, as
//! one trait implemented by the CPU mirror ([`CpuKernels`], `cpu.rs` / `rows.rs`) and by the
//! WGSL backend ([`GpuKernels`], `gpu.rs`). The tracker is written once against it; a backend's
//! pyramid is its associated type, so a pyramid of one backend cannot reach the other.
//!
//! The trait lives in a private module: it is nameable as a bound of the public
//! [`super::Tracker`] but cannot be implemented or called from outside the crate.

use super::cpu::{self, CpuPyramid};
use super::gpu::{GpuKernels, GpuPyramid};
use super::kernel::{Partial, PartialsAndSample, PyrParams, WarpParams};
use super::OdometryError;
use crate::image::RgbdFrame;

/// The odometry kernels of one backend (see the module docs). Every method computes what the
/// WGSL entry point of the same name computes (`shaders/pyramid.wgsl`,
/// `shaders/odometry.wgsl`); the CPU implementation is the mirror the parity tests compare
/// with.
pub trait Kernels: Send + 'static {
    /// A frame's pyramid on this backend (all levels concatenated, the layout of `kernel.rs`).
    type Pyramid: Send + 'static;

    /// Builds the pyramid of `frame` with `levels` levels, reusing `recycle`'s buffers when
    /// the layout matches. Levels finer than `first_stored` may be left unwritten (the GPU
    /// skips them); gradients are computed from level `first_gradient` on.
    fn build(
        &mut self,
        frame: &RgbdFrame,
        levels: usize,
        first_stored: usize,
        first_gradient: usize,
        recycle: Option<Self::Pyramid>,
    ) -> Result<Self::Pyramid, OdometryError>;

    /// A copy of `level` of `src` with the gradients of its bilateral-filtered values (the
    /// covariance pass, thesis 6.20-6.21); `f` describes the level.
    fn filtered_level(
        &mut self,
        src: &Self::Pyramid,
        level: usize,
        f: &PyrParams,
        recycle: Option<Self::Pyramid>,
    ) -> Result<Self::Pyramid, OdometryError>;

    /// The systematic residual sample (`p.samples` entries, `(r_photo, r_geo)`).
    fn sample_residuals(
        &mut self,
        p: &WarpParams,
        reference: &Self::Pyramid,
        current: &Self::Pyramid,
        level: usize,
    ) -> Result<Vec<[f32; 2]>, OdometryError>;

    /// Partial sums of the IRLS normal equations at the pose in `p`.
    fn normal_equation_partials(
        &mut self,
        p: &WarpParams,
        reference: &Self::Pyramid,
        current: &Self::Pyramid,
        level: usize,
    ) -> Result<Vec<Partial>, OdometryError>;

    /// [`Self::normal_equation_partials`] and, from the same pass, the residual sample at the
    /// same pose.
    fn normal_equations_and_sample(
        &mut self,
        p: &WarpParams,
        reference: &Self::Pyramid,
        current: &Self::Pyramid,
        level: usize,
    ) -> Result<PartialsAndSample, OdometryError>;

    /// Covisibility counts `(pixels with depth, covisible pixels)` of `reference` in `current`.
    fn covisibility_counts(
        &mut self,
        p: &WarpParams,
        reference: &Self::Pyramid,
        current: &Self::Pyramid,
        level: usize,
    ) -> Result<(u64, u64), OdometryError>;

    /// Bytes of device memory the kernels hold, pyramids aside.
    fn device_bytes(&self) -> usize;

    /// Bytes a pyramid holds, `(host, device)`.
    fn pyramid_bytes(p: &Self::Pyramid) -> (usize, usize);
}

/// The CPU backend of the odometry kernels: the rayon mirror of the WGSL.
#[derive(Clone, Copy, Debug, Default)]
pub struct CpuKernels {
    _private: (),
}

impl CpuKernels {
    /// The CPU kernels (they run on rayon's global thread pool).
    pub fn new() -> Self {
        Self::default()
    }

    /// Partials per normal-equation pass: enough bands of rows to balance the threads.
    fn chunks() -> usize {
        (rayon::current_num_threads() * 8).max(8)
    }
}

impl Kernels for CpuKernels {
    type Pyramid = CpuPyramid;

    fn build(
        &mut self,
        frame: &RgbdFrame,
        levels: usize,
        _first_stored: usize,
        first_gradient: usize,
        recycle: Option<CpuPyramid>,
    ) -> Result<CpuPyramid, OdometryError> {
        // The CPU always packs level 0: it costs little and keeps every level defined.
        Ok(CpuPyramid::build_reusing(
            frame,
            levels,
            first_gradient,
            recycle,
        ))
    }

    fn filtered_level(
        &mut self,
        src: &CpuPyramid,
        level: usize,
        f: &PyrParams,
        recycle: Option<CpuPyramid>,
    ) -> Result<CpuPyramid, OdometryError> {
        Ok(src.filtered_level(level, f, recycle))
    }

    fn sample_residuals(
        &mut self,
        p: &WarpParams,
        reference: &CpuPyramid,
        current: &CpuPyramid,
        level: usize,
    ) -> Result<Vec<[f32; 2]>, OdometryError> {
        Ok(cpu::sample_residuals(p, reference, current, level))
    }

    fn normal_equation_partials(
        &mut self,
        p: &WarpParams,
        reference: &CpuPyramid,
        current: &CpuPyramid,
        level: usize,
    ) -> Result<Vec<Partial>, OdometryError> {
        Ok(cpu::normal_equation_partials(
            p,
            reference,
            current,
            level,
            Self::chunks(),
        ))
    }

    fn normal_equations_and_sample(
        &mut self,
        p: &WarpParams,
        reference: &CpuPyramid,
        current: &CpuPyramid,
        level: usize,
    ) -> Result<PartialsAndSample, OdometryError> {
        Ok(cpu::normal_equations_and_sample(
            p,
            reference,
            current,
            level,
            Self::chunks(),
        ))
    }

    fn covisibility_counts(
        &mut self,
        p: &WarpParams,
        reference: &CpuPyramid,
        current: &CpuPyramid,
        level: usize,
    ) -> Result<(u64, u64), OdometryError> {
        Ok(cpu::covisibility_counts(p, reference, current, level))
    }

    fn device_bytes(&self) -> usize {
        0
    }

    fn pyramid_bytes(p: &CpuPyramid) -> (usize, usize) {
        (p.host_bytes(), 0)
    }
}

impl Kernels for GpuKernels {
    type Pyramid = GpuPyramid;

    fn build(
        &mut self,
        frame: &RgbdFrame,
        levels: usize,
        first_stored: usize,
        first_gradient: usize,
        recycle: Option<GpuPyramid>,
    ) -> Result<GpuPyramid, OdometryError> {
        Ok(self.build_levels(frame, levels, first_stored, first_gradient, recycle)?)
    }

    fn filtered_level(
        &mut self,
        src: &GpuPyramid,
        level: usize,
        f: &PyrParams,
        recycle: Option<GpuPyramid>,
    ) -> Result<GpuPyramid, OdometryError> {
        Ok(GpuKernels::filtered_level(self, src, level, f, recycle)?)
    }

    fn sample_residuals(
        &mut self,
        p: &WarpParams,
        reference: &GpuPyramid,
        current: &GpuPyramid,
        _level: usize,
    ) -> Result<Vec<[f32; 2]>, OdometryError> {
        Ok(GpuKernels::sample_residuals(self, p, reference, current)?)
    }

    fn normal_equation_partials(
        &mut self,
        p: &WarpParams,
        reference: &GpuPyramid,
        current: &GpuPyramid,
        _level: usize,
    ) -> Result<Vec<Partial>, OdometryError> {
        Ok(GpuKernels::normal_equation_partials(
            self, p, reference, current,
        )?)
    }

    fn normal_equations_and_sample(
        &mut self,
        p: &WarpParams,
        reference: &GpuPyramid,
        current: &GpuPyramid,
        _level: usize,
    ) -> Result<PartialsAndSample, OdometryError> {
        Ok(GpuKernels::normal_equations_and_sample(
            self, p, reference, current,
        )?)
    }

    fn covisibility_counts(
        &mut self,
        p: &WarpParams,
        reference: &GpuPyramid,
        current: &GpuPyramid,
        _level: usize,
    ) -> Result<(u64, u64), OdometryError> {
        Ok(GpuKernels::covisibility_counts(
            self, p, reference, current,
        )?)
    }

    fn device_bytes(&self) -> usize {
        GpuKernels::device_bytes(self)
    }

    fn pyramid_bytes(p: &GpuPyramid) -> (usize, usize) {
        (p.host_bytes(), p.device_bytes())
    }
}
