//! Coarse-to-fine alignment and the frame-by-frame tracker with reference switching.

use std::time::Instant;

use super::config::CovarianceGradients;
use super::config::OdometryConfig;
use super::cpu::{self, CpuPyramid};
use super::gpu::{GpuOdometry, GpuPyramid};
use super::kernel::{FilterParams, WarpParams, INVALID_RESIDUAL, PARTIAL_LEN};
use super::robust::{estimate_scale, update_scale, ScaleMethod, NU_DEFAULT};
use super::solver::NormalEquations;
use super::OdometryError;
use crate::camera::PinholeCamera;
use crate::geometry::Se3;
use crate::gpu::ComputeBackend;
use crate::image::RgbdFrame;

/// Wall-clock time per stage of one frame, in milliseconds.
#[derive(Clone, Copy, Debug, Default, serde::Serialize)]
pub struct StageTimes {
    /// Upload, pyramid and gradients.
    pub pyramid_ms: f64,
    /// Residual sampling and scale / degrees-of-freedom estimation.
    pub scale_ms: f64,
    /// Warp, residuals, Jacobians and the normal-equation reduction.
    pub reduce_ms: f64,
    /// 6x6 solves and pose updates.
    pub solve_ms: f64,
    /// Covisibility ratio.
    pub covisibility_ms: f64,
    /// Covariance pass (bilateral filter and one normal-equation pass), if enabled.
    pub covariance_ms: f64,
    /// Everything for this frame.
    pub total_ms: f64,
}

/// Statistics of one pyramid level's optimisation.
#[derive(Clone, Copy, Debug, Default, serde::Serialize)]
pub struct LevelStats {
    /// Level index (0 = finest).
    pub level: usize,
    /// Gauss-Newton iterations run.
    pub iterations: usize,
    /// Final photometric scale (intensity levels).
    pub sigma_photo: f64,
    /// Final geometric scale (1/m, or m for depth parametrisation).
    pub sigma_geo: f64,
    /// Final Student-t degrees of freedom (photometric, after nu_I = max(nu_I, nu_W)).
    pub nu_photo: f64,
    /// Final Student-t degrees of freedom (geometric).
    pub nu_geo: f64,
    /// Valid photometric residuals in the last iteration.
    pub n_photo: u64,
    /// Valid geometric residuals in the last iteration.
    pub n_geo: u64,
}

/// Result of aligning a current frame to a reference frame.
#[derive(Clone, Debug)]
pub struct Alignment {
    /// The estimated `cur_from_ref`.
    pub cur_from_ref: Se3,
    /// Covariance of `ref_from_cur = cur_from_ref^-1` in the library's right-perturbation
    /// convention ([`crate::geometry`]: `ref_from_cur * exp(d)`, `d = [v; w]` in the current
    /// camera's frame, m and rad). The solver updates `cur_from_ref <- exp(delta) cur_from_ref`,
    /// which is `ref_from_cur <- ref_from_cur exp(-delta)`: the same matrix. It is the
    /// inverse of the Hessian on the finest level used, from the last Gauss-Newton iteration
    /// ([`CovarianceGradients::Raw`], the default) or from the covariance pass at the final
    /// pose with bilateral-filtered gradients ([`CovarianceGradients::Bilateral`]).
    pub covariance: Option<[[f64; 6]; 6]>,
    /// Condition number of that Hessian.
    pub condition_number: f64,
    /// Per-level statistics, coarsest first.
    pub levels: Vec<LevelStats>,
    /// Time per stage.
    pub times: StageTimes,
}

/// Per-frame statistics reported by [`Odometry::track`].
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct FrameStats {
    /// Frame index (0-based, in tracking order).
    pub index: usize,
    /// Time stamp (s).
    pub timestamp: f64,
    /// Total Gauss-Newton iterations over all levels.
    pub iterations: usize,
    /// Final photometric scale (finest level).
    pub sigma_photo: f64,
    /// Final geometric scale (finest level).
    pub sigma_geo: f64,
    /// Final Student-t degrees of freedom (finest level).
    pub nu: f64,
    /// Covisibility ratio with the reference (min of both directions); 1 for the first frame.
    pub covisibility: f64,
    /// Condition number of the final Hessian.
    pub condition_number: f64,
    /// Whether this frame became the new reference.
    pub new_reference: bool,
    /// Time per stage.
    pub times: StageTimes,
}

/// Result of tracking one frame.
#[derive(Clone, Debug)]
pub struct TrackResult {
    /// The frame's pose, `world_from_camera`.
    pub world_from_camera: Se3,
    /// The frame's pose relative to the reference it was aligned to.
    pub cur_from_ref: Se3,
    /// Covariance of `cur_from_ref` (see [`Alignment::covariance`]).
    pub covariance: Option<[[f64; 6]; 6]>,
    /// Statistics.
    pub stats: FrameStats,
}

enum Engine {
    Cpu,
    Gpu(Box<GpuOdometry>),
}

enum Pyramid {
    Cpu(CpuPyramid),
    Gpu(GpuPyramid),
}

struct Reference {
    pyramid: Pyramid,
    world_from_ref: Se3,
}

/// Frame-by-frame dense RGB-D odometry.
///
/// ```no_run
/// # use rgbid::{odometry::*, camera::PinholeCamera, gpu::*};
/// # fn f(frames: Vec<rgbid::image::RgbdFrame>) -> Result<(), OdometryError> {
/// let backend = select_backend(BackendChoice::Auto, None)?;
/// let camera = PinholeCamera::new(525.0, 525.0, 319.5, 239.5, 640, 480);
/// let mut odo = Odometry::new(OdometryConfig::default(), camera, &backend)?;
/// for f in &frames {
///     let r = odo.track(f)?;
///     println!("{} {:?}", f.timestamp, r.world_from_camera.translation);
/// }
/// # Ok(()) }
/// ```
pub struct Odometry {
    config: OdometryConfig,
    camera: PinholeCamera,
    engine: Engine,
    reference: Option<Reference>,
    /// `world_from_camera` of the last frame and the motion `prev_from_cur` that led to it.
    last: Option<(Se3, Se3)>,
    initial_pose: Se3,
    spare: Option<Pyramid>,
    /// Buffers of the covariance pass's filtered level, recycled.
    filtered: Option<Pyramid>,
    frames: usize,
}

impl Odometry {
    /// Creates the odometry for frames of `camera` (undistorted pinhole) on `backend`.
    pub fn new(
        config: OdometryConfig,
        camera: PinholeCamera,
        backend: &ComputeBackend,
    ) -> Result<Self, OdometryError> {
        config.validate()?;
        camera
            .validate()
            .map_err(|e| OdometryError::InvalidConfig(e.to_string()))?;
        let (w, h) = (camera.width as usize, camera.height as usize);
        if (w >> (config.levels - 1)) < 8 || (h >> (config.levels - 1)) < 8 {
            return Err(OdometryError::TooManyLevels {
                width: w,
                height: h,
                levels: config.levels,
            });
        }
        let engine = match backend {
            ComputeBackend::Cpu => Engine::Cpu,
            ComputeBackend::Gpu(ctx) => Engine::Gpu(Box::new(GpuOdometry::new(ctx.clone())?)),
        };
        Ok(Self {
            config,
            camera,
            engine,
            reference: None,
            last: None,
            initial_pose: Se3::IDENTITY,
            spare: None,
            filtered: None,
            frames: 0,
        })
    }

    /// Bytes this odometry holds between frames, `(host, device)`: the pyramids it keeps
    /// (the reference, a spare one recycled for the next frame, the covariance pass's
    /// filtered level) in host memory on the CPU backend, and on a GPU the buffers allocated
    /// for them and for the kernels' parameters, partial sums and read-back (host: only the
    /// level tables). Sums of capacities and buffer sizes; allocates nothing.
    pub fn memory_bytes(&self) -> (usize, usize) {
        let mut host = 0;
        let mut device = match &self.engine {
            Engine::Cpu => 0,
            Engine::Gpu(g) => g.device_bytes(),
        };
        let pyramids = [
            self.reference.as_ref().map(|r| &r.pyramid),
            self.spare.as_ref(),
            self.filtered.as_ref(),
        ];
        let levels = |l: &Vec<super::cpu::LevelLayout>| {
            l.capacity() * std::mem::size_of::<super::cpu::LevelLayout>()
        };
        for p in pyramids.into_iter().flatten() {
            match p {
                Pyramid::Cpu(c) => {
                    host += levels(&c.levels)
                        + (c.photo.capacity() + c.geo.capacity()) * std::mem::size_of::<[f32; 4]>();
                }
                Pyramid::Gpu(g) => {
                    host += levels(&g.levels);
                    device += g.device_bytes();
                }
            }
        }
        (host, device)
    }

    /// The configuration.
    pub fn config(&self) -> &OdometryConfig {
        &self.config
    }

    /// Sets `world_from_camera` of the first frame (identity by default). Call before the
    /// first [`Self::track`].
    pub fn set_initial_pose(&mut self, world_from_camera: Se3) {
        self.initial_pose = world_from_camera;
    }

    /// Forgets the reference and the motion: the next [`Self::track`] starts again at
    /// `world_from_camera` (used after relocalisation).
    pub fn reset(&mut self, world_from_camera: Se3) {
        if let Some(r) = self.reference.take() {
            self.spare = Some(r.pyramid);
        }
        self.last = None;
        self.initial_pose = world_from_camera;
    }

    fn check_frame(&self, f: &RgbdFrame) -> Result<(), OdometryError> {
        let (w, h) = (self.camera.width as usize, self.camera.height as usize);
        let ok = f.width() == w
            && f.height() == h
            && f.intensity.data.len() == w * h
            && f.inverse_depth.data.len() == w * h;
        if ok {
            Ok(())
        } else {
            Err(OdometryError::FrameSize {
                want_w: w,
                want_h: h,
                got_w: f.width(),
                got_h: f.height(),
            })
        }
    }

    fn build(&mut self, frame: &RgbdFrame) -> Result<Pyramid, OdometryError> {
        let levels = self.config.levels;
        let spare = self.spare.take();
        Ok(match &mut self.engine {
            Engine::Cpu => {
                // Gradients are needed from the finest optimised level (covisibility reads only
                // inverse depth).
                let first = self.config.finest_level(self.camera.width as usize);
                let recycle = match spare {
                    Some(Pyramid::Cpu(p)) => Some(p),
                    _ => None,
                };
                Pyramid::Cpu(CpuPyramid::build_reusing(frame, levels, first, recycle))
            }
            Engine::Gpu(g) => {
                let recycle = match spare {
                    Some(Pyramid::Gpu(p)) => Some(p),
                    _ => None,
                };
                // Levels finer than both the finest optimised level and the covisibility level
                // are never read: the GPU does not write them (the CPU keeps packing level 0,
                // which costs it little).
                let first = self.config.finest_level(self.camera.width as usize);
                let stored = first.min(self.config.covisibility_level.min(levels - 1));
                Pyramid::Gpu(g.build_levels(frame, levels, stored, first, recycle)?)
            }
        })
    }

    /// Tracks `frame`: aligns it to the current reference (constant-velocity guess), returns
    /// its `world_from_camera`, and switches the reference when covisibility is low.
    pub fn track(&mut self, frame: &RgbdFrame) -> Result<TrackResult, OdometryError> {
        self.check_frame(frame)?;
        let t0 = Instant::now();
        let pyramid = self.build(frame)?;
        let pyramid_ms = t0.elapsed().as_secs_f64() * 1e3;
        let index = self.frames;
        self.frames += 1;
        let Some(reference) = self.reference.take() else {
            let pose = self.initial_pose;
            self.reference = Some(Reference {
                pyramid,
                world_from_ref: pose,
            });
            self.last = Some((pose, Se3::IDENTITY));
            let times = StageTimes {
                pyramid_ms,
                total_ms: pyramid_ms,
                ..Default::default()
            };
            return Ok(TrackResult {
                world_from_camera: pose,
                cur_from_ref: Se3::IDENTITY,
                covariance: None,
                stats: FrameStats {
                    index,
                    timestamp: frame.timestamp,
                    covisibility: 1.0,
                    new_reference: true,
                    times,
                    ..Default::default()
                },
            });
        };
        let (world_from_prev, prev_from_cur_last) = self
            .last
            .unwrap_or((reference.world_from_ref, Se3::IDENTITY));
        let guess_world_from_cur = if self.config.constant_velocity {
            world_from_prev * prev_from_cur_last
        } else {
            world_from_prev
        };
        let init = guess_world_from_cur.inverse() * reference.world_from_ref;
        let result = self.align_pyramids(&reference.pyramid, &pyramid, init);
        let mut alignment = match result {
            Ok(a) => a,
            Err(e) => {
                // Keep the reference so that the caller can go on with the next frame.
                self.reference = Some(reference);
                self.spare = Some(pyramid);
                return Err(e);
            }
        };
        alignment.times.pyramid_ms = pyramid_ms;
        let tc = Instant::now();
        let covisibility =
            self.covisibility(&reference.pyramid, &pyramid, &alignment.cur_from_ref)?;
        alignment.times.covisibility_ms = tc.elapsed().as_secs_f64() * 1e3;
        let world_from_cur = reference.world_from_ref * alignment.cur_from_ref.inverse();
        let prev_from_cur = world_from_prev.inverse() * world_from_cur;
        self.last = Some((world_from_cur, prev_from_cur));
        let switch = match self.config.reference_switch {
            None => true,
            Some(t) => covisibility < t,
        };
        if switch {
            self.spare = Some(reference.pyramid);
            self.reference = Some(Reference {
                pyramid,
                world_from_ref: world_from_cur,
            });
        } else {
            self.spare = Some(pyramid);
            self.reference = Some(reference);
        }
        alignment.times.total_ms = t0.elapsed().as_secs_f64() * 1e3;
        let fin = alignment.levels.last().copied().unwrap_or_default();
        Ok(TrackResult {
            world_from_camera: world_from_cur,
            cur_from_ref: alignment.cur_from_ref,
            covariance: alignment.covariance,
            stats: FrameStats {
                index,
                timestamp: frame.timestamp,
                iterations: alignment.levels.iter().map(|l| l.iterations).sum(),
                sigma_photo: fin.sigma_photo,
                sigma_geo: fin.sigma_geo,
                nu: fin.nu_photo,
                covisibility,
                condition_number: alignment.condition_number,
                new_reference: switch,
                times: alignment.times,
            },
        })
    }

    /// Aligns `current` to `reference` starting from `cur_from_ref_guess` (no tracker state is
    /// used or changed). This is the two-view entry point (loop closures, tests).
    pub fn align(
        &mut self,
        reference: &RgbdFrame,
        current: &RgbdFrame,
        cur_from_ref_guess: Se3,
    ) -> Result<Alignment, OdometryError> {
        self.check_frame(reference)?;
        self.check_frame(current)?;
        let t0 = Instant::now();
        let r = self.build(reference)?;
        let c = self.build(current)?;
        let pyramid_ms = t0.elapsed().as_secs_f64() * 1e3;
        let mut a = self.align_pyramids(&r, &c, cur_from_ref_guess)?;
        a.times.pyramid_ms = pyramid_ms;
        a.times.total_ms = t0.elapsed().as_secs_f64() * 1e3;
        Ok(a)
    }

    /// Dense covisibility ratio of two frames given `cur_from_ref` (eq. 6.10: the minimum over
    /// both directions of the fraction of pixels with depth that land on a pixel with depth).
    pub fn covisibility_of(
        &mut self,
        reference: &RgbdFrame,
        current: &RgbdFrame,
        cur_from_ref: &Se3,
    ) -> Result<f64, OdometryError> {
        let r = self.build(reference)?;
        let c = self.build(current)?;
        self.covisibility(&r, &c, cur_from_ref)
    }

    fn params(&self, level: usize, cur_from_ref: &Se3, samples: u32) -> WarpParams {
        let cam = self.camera.at_level(level);
        let (w, h) = (cam.width, cam.height);
        let mut off = 0u32;
        let (mut lw, mut lh) = (self.camera.width, self.camera.height);
        for _ in 0..level {
            off += lw * lh;
            lw /= 2;
            lh /= 2;
        }
        let mut p = WarpParams {
            dims: [w, h, off, samples],
            intr: [cam.fx as f32, cam.fy as f32, cam.cx as f32, cam.cy as f32],
            rot: [[0.0; 4]; 3],
            robust: [1.0, 1.0, NU_DEFAULT as f32, NU_DEFAULT as f32],
            flags: [
                self.config.estimator.code(),
                self.config.terms.mask(),
                self.config.geometric_code(),
                0,
            ],
        };
        p.set_pose(cur_from_ref);
        p
    }

    fn covisibility(
        &mut self,
        r: &Pyramid,
        c: &Pyramid,
        cur_from_ref: &Se3,
    ) -> Result<f64, OdometryError> {
        let level = self.config.covisibility_level.min(self.config.levels - 1);
        let fwd = self.params(level, cur_from_ref, 0);
        let bwd = self.params(level, &cur_from_ref.inverse(), 0);
        let ((a1, b1), (a2, b2)) = match (&mut self.engine, r, c) {
            (Engine::Cpu, Pyramid::Cpu(r), Pyramid::Cpu(c)) => (
                cpu::covisibility_counts(&fwd, r, c, level),
                cpu::covisibility_counts(&bwd, c, r, level),
            ),
            (Engine::Gpu(g), Pyramid::Gpu(r), Pyramid::Gpu(c)) => (
                g.covisibility_counts(&fwd, r, c)?,
                g.covisibility_counts(&bwd, c, r)?,
            ),
            _ => {
                return Err(OdometryError::InvalidConfig(
                    "pyramid from another backend".into(),
                ))
            }
        };
        let ratio = |a: u64, b: u64| if a == 0 { 0.0 } else { b as f64 / a as f64 };
        Ok(ratio(a1, b1).min(ratio(a2, b2)))
    }

    fn sample(
        &mut self,
        p: &WarpParams,
        r: &Pyramid,
        c: &Pyramid,
        level: usize,
    ) -> Result<Vec<[f32; 2]>, OdometryError> {
        Ok(match (&mut self.engine, r, c) {
            (Engine::Cpu, Pyramid::Cpu(r), Pyramid::Cpu(c)) => {
                cpu::sample_residuals(p, r, c, level)
            }
            (Engine::Gpu(g), Pyramid::Gpu(r), Pyramid::Gpu(c)) => g.sample_residuals(p, r, c)?,
            _ => {
                return Err(OdometryError::InvalidConfig(
                    "pyramid from another backend".into(),
                ))
            }
        })
    }

    /// The covariance pass's copy of `level` of `c` with bilateral-filtered gradients.
    fn filtered_level(
        &mut self,
        c: &Pyramid,
        level: usize,
        f: &FilterParams,
    ) -> Result<Pyramid, OdometryError> {
        let recycle = self.filtered.take();
        Ok(match (&mut self.engine, c) {
            (Engine::Cpu, Pyramid::Cpu(c)) => {
                let recycle = match recycle {
                    Some(Pyramid::Cpu(p)) => Some(p),
                    _ => None,
                };
                Pyramid::Cpu(c.filtered_level(level, f, recycle))
            }
            (Engine::Gpu(g), Pyramid::Gpu(c)) => {
                let recycle = match recycle {
                    Some(Pyramid::Gpu(p)) => Some(p),
                    _ => None,
                };
                Pyramid::Gpu(g.filtered_level(c, level, f, recycle)?)
            }
            _ => {
                return Err(OdometryError::InvalidConfig(
                    "pyramid from another backend".into(),
                ))
            }
        })
    }

    fn partials(
        &mut self,
        p: &WarpParams,
        r: &Pyramid,
        c: &Pyramid,
        level: usize,
    ) -> Result<Vec<[f32; PARTIAL_LEN]>, OdometryError> {
        Ok(match (&mut self.engine, r, c) {
            (Engine::Cpu, Pyramid::Cpu(r), Pyramid::Cpu(c)) => {
                let chunks = (rayon::current_num_threads() * 8).max(8);
                cpu::normal_equation_partials(p, r, c, level, chunks)
            }
            (Engine::Gpu(g), Pyramid::Gpu(r), Pyramid::Gpu(c)) => {
                g.normal_equation_partials(p, r, c)?
            }
            _ => {
                return Err(OdometryError::InvalidConfig(
                    "pyramid from another backend".into(),
                ))
            }
        })
    }

    fn partials_and_sample(
        &mut self,
        p: &WarpParams,
        r: &Pyramid,
        c: &Pyramid,
        level: usize,
    ) -> Result<super::kernel::PartialsAndSample, OdometryError> {
        Ok(match (&mut self.engine, r, c) {
            (Engine::Cpu, Pyramid::Cpu(r), Pyramid::Cpu(c)) => {
                let chunks = (rayon::current_num_threads() * 8).max(8);
                cpu::normal_equations_and_sample(p, r, c, level, chunks)
            }
            (Engine::Gpu(g), Pyramid::Gpu(r), Pyramid::Gpu(c)) => {
                g.normal_equations_and_sample(p, r, c)?
            }
            _ => {
                return Err(OdometryError::InvalidConfig(
                    "pyramid from another backend".into(),
                ))
            }
        })
    }

    fn align_pyramids(
        &mut self,
        r: &Pyramid,
        c: &Pyramid,
        init: Se3,
    ) -> Result<Alignment, OdometryError> {
        let cfg = self.config.clone();
        let mut cur_from_ref = init;
        let mut times = StageTimes::default();
        let mut levels = Vec::new();
        let mut last_ne: Option<NormalEquations> = None;
        // The level and parameters (scales) of the last normal equations solved.
        let mut last_params: Option<(usize, WarpParams)> = None;
        let mut any_update = false;
        let finest = cfg.finest_level(self.camera.width as usize);
        for level in (finest..cfg.levels).rev() {
            let cam = self.camera.at_level(level);
            let n = (cam.width * cam.height) as usize;
            let samples = n.min(cfg.max_samples) as u32;
            let mut st = LevelStats {
                level,
                ..Default::default()
            };
            let mut level_ne = None;
            let mut prev_scale: Option<(
                super::robust::ScaleEstimate,
                super::robust::ScaleEstimate,
            )> = None;
            // The residual sample taken by the previous iteration's normal-equation pass (at
            // the pose before its update): the scale lags one Gauss-Newton step, which saves a
            // warp of the sample (CPU) or a round trip (GPU) per iteration.
            let mut pending_sample: Option<Vec<[f32; 2]>> = None;
            for _ in 0..cfg.iterations_at(level, finest) {
                let mut p = self.params(level, &cur_from_ref, samples);
                // Scales.
                let ts = Instant::now();
                let (sp, sg) = if cfg.scale == ScaleMethod::Fixed {
                    (
                        super::robust::ScaleEstimate {
                            sigma: cfg.fixed_sigma_photo,
                            nu: cfg.fixed_nu,
                        },
                        super::robust::ScaleEstimate {
                            sigma: cfg.fixed_sigma_geo,
                            nu: cfg.fixed_nu,
                        },
                    )
                } else {
                    let s = match pending_sample.take() {
                        Some(s) => s,
                        None => self.sample(&p, r, c, level)?,
                    };
                    // The two populations are independent: estimate them on two threads.
                    let (est, method) = (cfg.estimator, cfg.scale);
                    let population = |c: usize| -> Vec<f64> {
                        s.iter()
                            .filter(|v| v[c] != INVALID_RESIDUAL)
                            .map(|v| f64::from(v[c]))
                            .collect()
                    };
                    // Full estimate (scale and degrees of freedom) on the first iteration of a
                    // level, warm-started scale updates after that.
                    let e = match prev_scale {
                        None => rayon::join(
                            || estimate_scale(&population(0), est, method),
                            || estimate_scale(&population(1), est, method),
                        ),
                        Some((pp, pg)) => rayon::join(
                            || update_scale(&population(0), est, method, pp),
                            || update_scale(&population(1), est, method, pg),
                        ),
                    };
                    prev_scale = Some(e);
                    e
                };
                // Guard against zero scales on noiseless data.
                let sigma_photo = sp.sigma.max(1e-3);
                let sigma_geo = sg
                    .sigma
                    .max(if cfg.geometric == super::GeometricParam::Depth {
                        1e-5
                    } else {
                        1e-6
                    });
                let nu_photo = sp.nu.max(sg.nu);
                p.robust = [
                    sigma_photo as f32,
                    sigma_geo as f32,
                    nu_photo as f32,
                    sg.nu as f32,
                ];
                times.scale_ms += ts.elapsed().as_secs_f64() * 1e3;
                // Normal equations.
                let tr = Instant::now();
                let parts = if cfg.scale == ScaleMethod::Fixed {
                    self.partials(&p, r, c, level)?
                } else {
                    let (parts, s) = self.partials_and_sample(&p, r, c, level)?;
                    pending_sample = Some(s);
                    parts
                };
                let ne = NormalEquations::from_partials(&parts);
                times.reduce_ms += tr.elapsed().as_secs_f64() * 1e3;
                let tsol = Instant::now();
                st.sigma_photo = sigma_photo;
                st.sigma_geo = sigma_geo;
                st.nu_photo = nu_photo;
                st.nu_geo = sg.nu;
                st.n_photo = ne.n_photo;
                st.n_geo = ne.n_geo;
                if ne.n_photo + ne.n_geo < 12 {
                    break;
                }
                let Some(delta) = ne.solve() else {
                    break;
                };
                cur_from_ref = Se3::exp(&delta) * cur_from_ref;
                any_update = true;
                st.iterations += 1;
                times.solve_ms += tsol.elapsed().as_secs_f64() * 1e3;
                let norm = delta.iter().map(|x| x * x).sum::<f64>().sqrt();
                log::trace!(
                    "level {level} it {}: |delta| {norm:.3e} cost/n {:.4} sigma {:.3}/{:.5} nu {:.2} n {}/{}",
                    st.iterations,
                    ne.cost / (ne.n_photo + ne.n_geo).max(1) as f64,
                    sigma_photo,
                    sigma_geo,
                    nu_photo,
                    ne.n_photo,
                    ne.n_geo
                );
                level_ne = Some(ne);
                last_params = Some((level, p));
                if norm < cfg.convergence {
                    break;
                }
            }
            if level_ne.is_some() {
                last_ne = level_ne;
            }
            levels.push(st);
        }
        if !any_update {
            return Err(OdometryError::TrackingFailed(
                "no pyramid level had enough valid, well-conditioned residuals (no depth or no overlap)".into(),
            ));
        }
        if cfg.covariance == CovarianceGradients::Bilateral {
            if let Some((level, mut p)) = last_params {
                let tc = Instant::now();
                p.set_pose(&cur_from_ref);
                p.dims[3] = 0;
                let sigma_rho = match cfg.geometric {
                    super::GeometricParam::InverseDepth => f64::from(p.robust[1]),
                    super::GeometricParam::Depth => cfg.fixed_sigma_geo,
                };
                let f = FilterParams::new(
                    p.dims[0] as usize,
                    p.dims[1] as usize,
                    p.dims[2] as usize,
                    cfg.bilateral_range * f64::from(p.robust[0]),
                    cfg.bilateral_range * sigma_rho,
                );
                let filtered = self.filtered_level(c, level, &f)?;
                let parts = self.partials(&p, r, &filtered, level);
                self.filtered = Some(filtered);
                let ne = NormalEquations::from_partials(&parts?);
                if ne.n_photo + ne.n_geo >= 12 {
                    last_ne = Some(ne);
                }
                times.covariance_ms += tc.elapsed().as_secs_f64() * 1e3;
            }
        }
        let (covariance, condition_number) = match last_ne.as_ref().and_then(|ne| ne.covariance()) {
            Some((c, k)) => (Some(c), k),
            None => (None, f64::INFINITY),
        };
        Ok(Alignment {
            cur_from_ref,
            covariance,
            condition_number,
            levels,
            times,
        })
    }
}

impl OdometryConfig {
    /// `WarpParams::flags[2]`: bit 0 depth parametrisation, bit 1 first-order sampling.
    pub(crate) fn geometric_code(&self) -> u32 {
        let param = match self.geometric {
            super::GeometricParam::InverseDepth => 0,
            super::GeometricParam::Depth => 1,
        };
        let sampling = match self.geometric_sampling {
            super::config::GeometricSampling::Nearest => 0,
            super::config::GeometricSampling::Linear => 2,
        };
        param | sampling
    }
}
