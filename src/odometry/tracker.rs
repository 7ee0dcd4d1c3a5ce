//! Coarse-to-fine alignment and the frame-by-frame tracker with reference switching.

use std::time::Instant;

use super::backend::{CpuKernels, Kernels};
use super::config::{
    CovarianceGradients, CovisibilityTest, GeometricParam, Linearisation, OdometryConfig,
    OCCLUSION_SIGMAS,
};
use super::gpu::GpuKernels;
use super::kernel::{PyrParams, WarpParams, INVALID_RESIDUAL};
use super::robust::{estimate_scale, update_scale, ScaleEstimate, ScaleMethod, NU_DEFAULT};
use super::rolling_shutter;
use super::solver::NormalEquations;
use super::OdometryError;
use crate::camera::PinholeCamera;
use crate::geometry::{Covariance6, Se3};
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
    /// Final photometric location mu_I, intensity levels (0 unless
    /// [`OdometryConfig::location`] estimates it).
    pub mu_photo: f64,
    /// Final geometric location mu_W (1/m, or m for depth parametrisation; 0 unless
    /// estimated).
    pub mu_geo: f64,
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
    /// pose with bilateral-filtered gradients ([`CovarianceGradients::Bilateral`]); with
    /// [`crate::odometry::Linearisation::Reference`] that Hessian's twist is on the reference
    /// side and its inverse is carried to this convention by the adjoint of `cur_from_ref`.
    pub covariance: Option<Covariance6>,
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
    /// Gauss-Newton iterations per level optimised, coarsest first.
    pub level_iterations: Vec<usize>,
    /// Final photometric scale (finest level).
    pub sigma_photo: f64,
    /// Final geometric scale (finest level).
    pub sigma_geo: f64,
    /// Final Student-t degrees of freedom (finest level).
    pub nu: f64,
    /// Final photometric location mu_I (finest level, intensity levels; 0 unless
    /// [`OdometryConfig::location`] estimates it).
    pub mu_photo: f64,
    /// Final geometric location mu_W (finest level, units of the geometric residual; 0
    /// unless estimated).
    pub mu_geo: f64,
    /// Covisibility ratio with the reference (min of both directions); 1 for the first frame.
    pub covisibility: f64,
    /// Condition number of the final Hessian.
    pub condition_number: f64,
    /// Whether this frame became the new reference.
    pub new_reference: bool,
    /// Time per stage.
    pub times: StageTimes,
}

impl FrameStats {
    /// The statistics of frame `index` (time stamp `timestamp`, s) from its alignment, with
    /// the covisibility ratio at the estimate and whether the frame becomes the reference.
    pub(crate) fn of_alignment(
        index: usize,
        timestamp: f64,
        alignment: &Alignment,
        covisibility: f64,
        new_reference: bool,
    ) -> Self {
        let fin = alignment.levels.last().copied().unwrap_or_default();
        Self {
            index,
            timestamp,
            iterations: alignment.levels.iter().map(|l| l.iterations).sum(),
            level_iterations: alignment.levels.iter().map(|l| l.iterations).collect(),
            sigma_photo: fin.sigma_photo,
            sigma_geo: fin.sigma_geo,
            nu: fin.nu_photo,
            mu_photo: fin.mu_photo,
            mu_geo: fin.mu_geo,
            covisibility,
            condition_number: alignment.condition_number,
            new_reference,
            times: alignment.times,
        }
    }
}

/// Result of tracking one frame.
#[derive(Clone, Debug)]
pub struct TrackResult {
    /// The frame's pose, `world_from_camera`.
    pub world_from_camera: Se3,
    /// The frame's pose relative to the reference it was aligned to.
    pub cur_from_ref: Se3,
    /// Covariance of the alignment to the reference (see [`Alignment::covariance`]).
    pub covariance: Option<Covariance6>,
    /// Statistics.
    pub stats: FrameStats,
}

/// A frame prepared for alignment on the backend `K`: its pyramid and gradients, built once
/// by [`Tracker::prepare`] and usable for any number of alignments and covisibility tests.
/// The backend is part of the type, so a frame prepared on one backend cannot be given to a
/// tracker of the other (`Prepared<CpuKernels>` is not `Prepared<GpuKernels>`); only the
/// type-erased [`PreparedFrame`] checks it at run time.
pub struct Prepared<K: Kernels> {
    pyramid: K::Pyramid,
    /// Time to build the pyramid, ms.
    build_ms: f64,
}

impl<K: Kernels> Prepared<K> {
    /// Wall-clock time it took to prepare the frame (upload, pyramid, gradients), ms.
    pub fn build_ms(&self) -> f64 {
        self.build_ms
    }
}

struct Reference<P> {
    pyramid: P,
    world_from_ref: Se3,
}

/// The scales of one Gauss-Newton iteration and what the next one starts from.
struct Scales {
    photo: ScaleEstimate,
    geo: ScaleEstimate,
}

/// Frame-by-frame dense RGB-D odometry on the kernels `K` ([`CpuKernels`] or
/// [`GpuKernels`]): the algorithm of [`Odometry`], with the backend fixed at compile time.
/// [`Odometry`] chooses the backend at run time and wraps one of these.
///
/// A `Tracker` is `Send`: it can move to another thread (a binding can release its
/// interpreter lock around [`Self::track`]).
pub struct Tracker<K: Kernels> {
    config: OdometryConfig,
    camera: PinholeCamera,
    kernels: K,
    reference: Option<Reference<K::Pyramid>>,
    /// `world_from_camera` of the last frame and the motion `prev_from_cur` that led to it.
    last: Option<(Se3, Se3)>,
    /// Time stamp of the last frame and the seconds from the frame before it (the interval
    /// of `last`'s motion).
    last_time: Option<(f64, Option<f64>)>,
    initial_pose: Se3,
    /// Pyramids whose buffers the next builds reuse (at most [`MAX_SPARES`]).
    spares: Vec<K::Pyramid>,
    /// Buffers of the covariance pass's filtered level, recycled.
    filtered: Option<K::Pyramid>,
    frames: usize,
}

/// Pyramids a tracker keeps for reuse: enough for the two that a two-view alignment gives
/// back ([`Tracker::prepare`], [`Tracker::recycle`]); tracking leaves one per frame.
const MAX_SPARES: usize = 2;

/// The tracker on the CPU mirror.
pub type CpuTracker = Tracker<CpuKernels>;
/// The tracker on the WGSL kernels.
pub type GpuTracker = Tracker<GpuKernels>;

impl<K: Kernels> Tracker<K> {
    /// A tracker for frames of `camera` (undistorted pinhole) on `kernels`.
    pub fn with_kernels(
        config: OdometryConfig,
        camera: PinholeCamera,
        kernels: K,
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
        Ok(Self {
            config,
            camera,
            kernels,
            reference: None,
            last: None,
            last_time: None,
            initial_pose: Se3::IDENTITY,
            spares: Vec::new(),
            filtered: None,
            frames: 0,
        })
    }

    /// Bytes this tracker holds between frames, `(host, device)`: the pyramids it keeps
    /// (the reference, up to two spare ones recycled for the next builds, the covariance pass's
    /// filtered level) in host memory on the CPU backend, and on a GPU the buffers allocated
    /// for them and for the kernels' parameters, partial sums and read-back (host: only the
    /// level tables). Sums of capacities and buffer sizes; allocates nothing.
    pub fn memory_bytes(&self) -> (usize, usize) {
        let (mut host, mut device) = (0, self.kernels.device_bytes());
        let pyramids = [
            self.reference.as_ref().map(|r| &r.pyramid),
            self.filtered.as_ref(),
        ];
        for p in pyramids.into_iter().flatten().chain(&self.spares) {
            let (h, d) = K::pyramid_bytes(p);
            host += h;
            device += d;
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
            self.keep_spare(r.pyramid);
        }
        self.last = None;
        self.last_time = None;
        self.initial_pose = world_from_camera;
    }

    /// `frame` with its intensity rectified for the camera's rolling shutter
    /// ([`OdometryConfig::rolling_shutter`]), from the angular velocity of the last
    /// inter-frame motion. `None` when it is used as it is: a global shutter, fewer than two
    /// frames tracked since the start or the last reset, or a turn too slow to move a pixel
    /// by a tenth.
    pub fn rectified(&self, frame: &RgbdFrame) -> Option<RgbdFrame> {
        if !self.config.rolling_shutter || self.camera.readout <= 0.0 {
            return None;
        }
        let (_, prev_from_cur) = self.last?;
        let omega = rolling_shutter::angular_velocity(&prev_from_cur, self.last_time?.1?)?;
        rolling_shutter::rectify(frame, &self.camera, omega, self.camera.readout)
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

    /// The frame's pyramid: gradients from the finest optimised level on; levels finer than
    /// both that level and the covisibility level are never read, so a backend may skip them.
    fn build(&mut self, frame: &RgbdFrame) -> Result<K::Pyramid, OdometryError> {
        let levels = self.config.levels;
        let first = self.config.finest_level(self.camera.width as usize);
        let stored = first.min(self.config.covisibility_level.min(levels - 1));
        let spare = self.spares.pop();
        self.kernels.build(frame, levels, stored, first, spare)
    }

    /// Keeps `pyramid`'s buffers for a later build, unless [`MAX_SPARES`] are kept already.
    fn keep_spare(&mut self, pyramid: K::Pyramid) {
        if self.spares.len() < MAX_SPARES {
            self.spares.push(pyramid);
        }
    }

    /// Gives the buffers of a frame prepared by [`Self::prepare`] back, for the next
    /// pyramid builds to reuse (instead of allocating and first touching new memory).
    pub fn recycle(&mut self, prepared: Prepared<K>) {
        self.keep_spare(prepared.pyramid);
    }

    /// Builds `frame`'s pyramid once for [`Self::align_prepared`] and
    /// [`Self::covisibility_prepared`] (no tracker state is used or changed).
    pub fn prepare(&mut self, frame: &RgbdFrame) -> Result<Prepared<K>, OdometryError> {
        self.check_frame(frame)?;
        let t0 = Instant::now();
        let pyramid = self.build(frame)?;
        Ok(Prepared {
            pyramid,
            build_ms: t0.elapsed().as_secs_f64() * 1e3,
        })
    }

    /// Tracks `frame`: aligns it to the current reference (constant-velocity guess), returns
    /// its `world_from_camera`, and switches the reference when covisibility is low. With a
    /// rolling shutter the frame is rectified first ([`Self::rectified`]).
    pub fn track(&mut self, frame: &RgbdFrame) -> Result<TrackResult, OdometryError> {
        match self.rectified(frame) {
            Some(r) => self.track_as_given(&r),
            None => self.track_as_given(frame),
        }
    }

    /// [`Self::track`] without the rolling-shutter rectification: for a frame that
    /// [`Self::rectified`] already gave (or a global-shutter one).
    pub fn track_as_given(&mut self, frame: &RgbdFrame) -> Result<TrackResult, OdometryError> {
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
            self.last_time = Some((frame.timestamp, None));
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
                self.keep_spare(pyramid);
                return Err(e);
            }
        };
        alignment.times.pyramid_ms = pyramid_ms;
        let tc = Instant::now();
        let sigma_geo = alignment
            .levels
            .last()
            .map_or(self.config.fixed_sigma_geo, |l| l.sigma_geo);
        let covisibility = self.covisibility(
            &reference.pyramid,
            &pyramid,
            &alignment.cur_from_ref,
            sigma_geo,
        )?;
        alignment.times.covisibility_ms = tc.elapsed().as_secs_f64() * 1e3;
        let world_from_cur = reference.world_from_ref * alignment.cur_from_ref.inverse();
        let prev_from_cur = world_from_prev.inverse() * world_from_cur;
        self.last = Some((world_from_cur, prev_from_cur));
        let interval = self.last_time.map(|(t, _)| frame.timestamp - t);
        self.last_time = Some((frame.timestamp, interval));
        let switch = match self.config.reference_switch {
            None => true,
            Some(t) => covisibility < t,
        };
        if switch {
            self.keep_spare(reference.pyramid);
            self.reference = Some(Reference {
                pyramid,
                world_from_ref: world_from_cur,
            });
        } else {
            self.keep_spare(pyramid);
            self.reference = Some(reference);
        }
        alignment.times.total_ms = t0.elapsed().as_secs_f64() * 1e3;
        Ok(TrackResult {
            world_from_camera: world_from_cur,
            cur_from_ref: alignment.cur_from_ref,
            covariance: alignment.covariance,
            stats: FrameStats::of_alignment(
                index,
                frame.timestamp,
                &alignment,
                covisibility,
                switch,
            ),
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
        let t0 = Instant::now();
        let r = self.prepare(reference)?;
        let c = self.prepare(current)?;
        let mut a = self.align_pyramids(&r.pyramid, &c.pyramid, cur_from_ref_guess)?;
        a.times.pyramid_ms = r.build_ms + c.build_ms;
        a.times.total_ms = t0.elapsed().as_secs_f64() * 1e3;
        Ok(a)
    }

    /// [`Self::align`] on prepared frames: no pyramid is built.
    pub fn align_prepared(
        &mut self,
        reference: &Prepared<K>,
        current: &Prepared<K>,
        cur_from_ref_guess: Se3,
    ) -> Result<Alignment, OdometryError> {
        let t0 = Instant::now();
        let mut a =
            self.align_pyramids(&reference.pyramid, &current.pyramid, cur_from_ref_guess)?;
        a.times.total_ms = t0.elapsed().as_secs_f64() * 1e3;
        Ok(a)
    }

    /// Dense covisibility ratio of two frames given `cur_from_ref` (eq. 6.10: the minimum over
    /// both directions of the fraction of pixels with depth that land on a pixel with depth,
    /// and with [`CovisibilityTest::Consistent`] a consistent one, sigma_W being
    /// [`OdometryConfig::fixed_sigma_geo`]).
    pub fn covisibility_of(
        &mut self,
        reference: &RgbdFrame,
        current: &RgbdFrame,
        cur_from_ref: &Se3,
    ) -> Result<f64, OdometryError> {
        let r = self.prepare(reference)?;
        let c = self.prepare(current)?;
        self.covisibility(
            &r.pyramid,
            &c.pyramid,
            cur_from_ref,
            self.config.fixed_sigma_geo,
        )
    }

    /// [`Self::covisibility_of`] on prepared frames (with [`CovisibilityTest::Consistent`],
    /// sigma_W is [`OdometryConfig::fixed_sigma_geo`]: two views have no estimated scale).
    pub fn covisibility_prepared(
        &mut self,
        reference: &Prepared<K>,
        current: &Prepared<K>,
        cur_from_ref: &Se3,
    ) -> Result<f64, OdometryError> {
        self.covisibility(
            &reference.pyramid,
            &current.pyramid,
            cur_from_ref,
            self.config.fixed_sigma_geo,
        )
    }

    /// The kernels' parameters for `level` at `cur_from_ref` with a residual sample of
    /// `samples` pixels (scales at their neutral values).
    fn params(&self, level: usize, cur_from_ref: &Se3, samples: u32) -> WarpParams {
        warp_params(&self.config, &self.camera, level, cur_from_ref, samples)
    }

    fn covisibility(
        &mut self,
        r: &K::Pyramid,
        c: &K::Pyramid,
        cur_from_ref: &Se3,
        sigma_geo: f64,
    ) -> Result<f64, OdometryError> {
        let level = self.config.covisibility_level.min(self.config.levels - 1);
        let occlusion = match self.config.covisibility_test {
            CovisibilityTest::Depth => 0.0,
            CovisibilityTest::Consistent => (OCCLUSION_SIGMAS * sigma_geo) as f32,
        };
        let mut fwd = self.params(level, cur_from_ref, 0);
        let mut bwd = self.params(level, &cur_from_ref.inverse(), 0);
        fwd.occlusion = occlusion;
        bwd.occlusion = occlusion;
        let (a1, b1) = self.kernels.covisibility_counts(&fwd, r, c, level)?;
        let (a2, b2) = self.kernels.covisibility_counts(&bwd, c, r, level)?;
        let ratio = |a: u64, b: u64| if a == 0 { 0.0 } else { b as f64 / a as f64 };
        Ok(ratio(a1, b1).min(ratio(a2, b2)))
    }

    /// Coarse-to-fine Gauss-Newton from `init` (`cur_from_ref`), then the covariance.
    fn align_pyramids(
        &mut self,
        r: &K::Pyramid,
        c: &K::Pyramid,
        init: Se3,
    ) -> Result<Alignment, OdometryError> {
        let mut cur_from_ref = init;
        let mut times = StageTimes::default();
        let mut levels = Vec::new();
        let mut last: Option<LevelSolve> = None;
        let finest = self.config.finest_level(self.camera.width as usize);
        for level in (finest..self.config.levels).rev() {
            let (stats, solve) = self.solve_level(r, c, level, &mut cur_from_ref, &mut times)?;
            levels.push(stats);
            if solve.is_some() {
                last = solve;
            }
        }
        let Some(mut last) = last else {
            return Err(OdometryError::TrackingFailed(
                "no pyramid level had enough valid, well-conditioned residuals (no depth or no overlap)".into(),
            ));
        };
        if self.config.covariance == CovarianceGradients::Bilateral {
            let tc = Instant::now();
            if let Some(ne) = self.covariance_pass(r, c, &last, &cur_from_ref)? {
                last.equations = ne;
            }
            times.covariance_ms += tc.elapsed().as_secs_f64() * 1e3;
        }
        let (covariance, condition_number) = match last.equations.covariance() {
            // The reference form's Hessian is that of a right twist of cur_from_ref,
            // `cur_from_ref exp(e)`, i.e. `exp(-e) ref_from_cur = ref_from_cur
            // exp(-Ad(cur_from_ref) e)`: carried to the documented convention by that
            // adjoint.
            Some((c, k)) if self.config.linearisation == Linearisation::Reference => {
                (Some(c.transported(&cur_from_ref.inverse())), k)
            }
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

    /// The robust scales of one iteration: fixed, or estimated on the residual sample
    /// (`pending`: the one the previous iteration's pass took; otherwise a sampling pass).
    /// A level's first iteration estimates scale and degrees of freedom in full; later ones
    /// update the previous estimate.
    fn scales(
        &mut self,
        p: &WarpParams,
        r: &K::Pyramid,
        c: &K::Pyramid,
        level: usize,
        pending: Option<Vec<[f32; 2]>>,
        previous: Option<&Scales>,
    ) -> Result<Scales, OdometryError> {
        let cfg = &self.config;
        if cfg.scale == ScaleMethod::Fixed {
            return Ok(Scales {
                photo: ScaleEstimate {
                    sigma: cfg.fixed_sigma_photo,
                    nu: cfg.fixed_nu,
                    mu: 0.0,
                },
                geo: ScaleEstimate {
                    sigma: cfg.fixed_sigma_geo,
                    nu: cfg.fixed_nu,
                    mu: 0.0,
                },
            });
        }
        let (est, method) = (cfg.estimator, cfg.scale);
        // The geometric location only on the finest level optimised: on the coarser ones the
        // pose is still far off, and an inverse-depth offset would absorb the error of the
        // guess along the optical axis (the two are nearly confounded), see `Location::Both`.
        let finest = cfg.finest_level(self.camera.width as usize);
        let loc_photo = cfg.location.estimates(false);
        let loc_geo = cfg.location.estimates(true) && level == finest;
        let s = match pending {
            Some(s) => s,
            None => self.kernels.sample_residuals(p, r, c, level)?,
        };
        let population = |c: usize| -> Vec<f64> {
            s.iter()
                .filter(|v| v[c] != INVALID_RESIDUAL)
                .map(|v| f64::from(v[c]))
                .collect()
        };
        // The two populations are independent: estimate them on two threads.
        let (photo, geo) = match previous {
            None => rayon::join(
                || estimate_scale(&population(0), est, method, loc_photo),
                || estimate_scale(&population(1), est, method, loc_geo),
            ),
            Some(prev) => rayon::join(
                || update_scale(&population(0), est, method, loc_photo, prev.photo),
                || update_scale(&population(1), est, method, loc_geo, prev.geo),
            ),
        };
        Ok(Scales { photo, geo })
    }

    /// The Gauss-Newton iterations of one level, updating `cur_from_ref`; the level's
    /// statistics and its last solved normal equations (`None` if no iteration solved).
    fn solve_level(
        &mut self,
        r: &K::Pyramid,
        c: &K::Pyramid,
        level: usize,
        cur_from_ref: &mut Se3,
        times: &mut StageTimes,
    ) -> Result<(LevelStats, Option<LevelSolve>), OdometryError> {
        let finest = self.config.finest_level(self.camera.width as usize);
        let cam = self.camera.at_level(level);
        let n = (cam.width * cam.height) as usize;
        let samples = n.min(self.config.max_samples) as u32;
        let fixed = self.config.scale == ScaleMethod::Fixed;
        let mut st = LevelStats {
            level,
            ..Default::default()
        };
        let mut solved = None;
        let mut previous: Option<Scales> = None;
        // The residual sample taken by the previous iteration's normal-equation pass (at
        // the pose before its update): the scale lags one Gauss-Newton step, which saves a
        // warp of the sample (CPU) or a round trip (GPU) per iteration.
        let mut pending: Option<Vec<[f32; 2]>> = None;
        for _ in 0..self.config.iterations_at(level, finest) {
            let mut p = self.params(level, cur_from_ref, samples);
            let ts = Instant::now();
            let scales = self.scales(&p, r, c, level, pending.take(), previous.as_ref())?;
            // Guard against zero scales on noiseless data.
            let sigma_photo = scales.photo.sigma.max(1e-3);
            let sigma_geo =
                scales
                    .geo
                    .sigma
                    .max(if self.config.geometric == GeometricParam::Depth {
                        1e-5
                    } else {
                        1e-6
                    });
            let nu_photo = scales.photo.nu.max(scales.geo.nu);
            p.sigma_photo = sigma_photo as f32;
            p.sigma_geo = sigma_geo as f32;
            p.nu_photo = nu_photo as f32;
            p.nu_geo = scales.geo.nu as f32;
            p.mu_photo = scales.photo.mu as f32;
            p.mu_geo = scales.geo.mu as f32;
            st.sigma_photo = sigma_photo;
            st.sigma_geo = sigma_geo;
            st.nu_photo = nu_photo;
            st.nu_geo = scales.geo.nu;
            st.mu_photo = scales.photo.mu;
            st.mu_geo = scales.geo.mu;
            if !fixed {
                previous = Some(scales);
            }
            times.scale_ms += ts.elapsed().as_secs_f64() * 1e3;
            // Normal equations.
            let tr = Instant::now();
            let parts = if fixed {
                self.kernels.normal_equation_partials(&p, r, c, level)?
            } else {
                let (parts, s) = self.kernels.normal_equations_and_sample(&p, r, c, level)?;
                pending = Some(s);
                parts
            };
            let ne = NormalEquations::from_partials(&parts);
            times.reduce_ms += tr.elapsed().as_secs_f64() * 1e3;
            let tsol = Instant::now();
            st.n_photo = ne.n_photo;
            st.n_geo = ne.n_geo;
            if ne.n_photo + ne.n_geo < 12 {
                break;
            }
            let Some(solved_delta) = ne.solve() else {
                break;
            };
            let delta = left_twist(self.config.linearisation, cur_from_ref, &solved_delta);
            *cur_from_ref = Se3::exp(&delta) * *cur_from_ref;
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
            solved = Some(LevelSolve {
                level,
                params: p,
                equations: ne,
            });
            let focal = f64::from(p.fx.max(p.fy));
            if norm < self.config.convergence || norm * focal < self.config.convergence_pixels {
                break;
            }
        }
        Ok((st, solved))
    }

    /// The covariance pass (thesis 6.20-6.21): the normal equations once more at the final
    /// pose on the last solved level, with the gradients of the bilateral-filtered level of
    /// the frame the Jacobians differentiate (the current one, or the reference one with
    /// [`Linearisation::Reference`]). `None` when too few residuals remain.
    fn covariance_pass(
        &mut self,
        r: &K::Pyramid,
        c: &K::Pyramid,
        last: &LevelSolve,
        cur_from_ref: &Se3,
    ) -> Result<Option<NormalEquations>, OdometryError> {
        let (level, mut p) = (last.level, last.params);
        p.set_pose(cur_from_ref);
        p.samples = 0;
        let sigma_rho = match self.config.geometric {
            GeometricParam::InverseDepth => f64::from(p.sigma_geo),
            GeometricParam::Depth => self.config.fixed_sigma_geo,
        };
        let f = PyrParams::filter(
            p.width as usize,
            p.height as usize,
            p.offset as usize,
            self.config.bilateral_range * f64::from(p.sigma_photo),
            self.config.bilateral_range * sigma_rho,
        );
        let recycle = self.filtered.take();
        let parts = match self.config.linearisation {
            Linearisation::Current => {
                let filtered = self.kernels.filtered_level(c, level, &f, recycle)?;
                let parts = self
                    .kernels
                    .normal_equation_partials(&p, r, &filtered, level);
                self.filtered = Some(filtered);
                parts
            }
            Linearisation::Reference => {
                let filtered = self.kernels.filtered_level(r, level, &f, recycle)?;
                let parts = self
                    .kernels
                    .normal_equation_partials(&p, &filtered, c, level);
                self.filtered = Some(filtered);
                parts
            }
        };
        let ne = NormalEquations::from_partials(&parts?);
        Ok((ne.n_photo + ne.n_geo >= 12).then_some(ne))
    }
}

impl Tracker<CpuKernels> {
    /// A tracker on the CPU mirror (rayon's global thread pool).
    pub fn new_cpu(config: OdometryConfig, camera: PinholeCamera) -> Result<Self, OdometryError> {
        Self::with_kernels(config, camera, CpuKernels::new())
    }
}

impl Tracker<GpuKernels> {
    /// A tracker on the WGSL kernels of `ctx` (pipelines compiled here, once).
    pub fn new_gpu(
        config: OdometryConfig,
        camera: PinholeCamera,
        ctx: std::sync::Arc<crate::gpu::GpuContext>,
    ) -> Result<Self, OdometryError> {
        let kernels = GpuKernels::new(ctx)?;
        Self::with_kernels(config, camera, kernels)
    }
}

/// The left twist `d` of the update `cur_from_ref <- exp(d) cur_from_ref` from the solution
/// `delta` of `H delta = -g` of normal equations linearised as `lin` (m and rad, `[v; w]`).
///
/// The current-frame Jacobians differentiate the residuals with respect to that left twist,
/// so `d = delta`. The reference-frame Jacobians (`nabla I_A`, `nabla W_A` at `X_A`) are,
/// where the warp aligns the frames (`I_B(w(., T)) ~ I_A`), the derivatives with respect to a
/// right twist, `T exp(e)`: the twist moves the reference point before `T`, and what `T`
/// then reads in the current frame is what the reference frame holds at the moved point.
/// Written as the thesis' inverse composition, the increment `delta_A = -delta` is solved
/// for the reference warp and undone on the estimate, `T <- T exp(delta_A)^-1 =
/// T exp(delta)`; as a left twist that is `exp(Ad(T) delta) T`, since
/// `T exp(e) T^-1 = exp(Ad(T) e)`. Using the left form keeps one update and one
/// convergence test (on `|d|`, in the current frame's coordinates like the default's) for
/// both linearisations.
pub(crate) fn left_twist(lin: Linearisation, cur_from_ref: &Se3, delta: &[f64; 6]) -> [f64; 6] {
    match lin {
        Linearisation::Current => *delta,
        Linearisation::Reference => {
            let ad = cur_from_ref.adjoint();
            std::array::from_fn(|i| (0..6).map(|j| ad[i][j] * delta[j]).sum())
        }
    }
}

/// The last solved normal equations of a level and the parameters they were solved with.
struct LevelSolve {
    level: usize,
    params: WarpParams,
    equations: NormalEquations,
}

/// The kernels' parameters for `level` of `camera` at `cur_from_ref` with a residual sample
/// of `samples` pixels; the scales are neutral (set per iteration by the tracker).
pub(crate) fn warp_params(
    config: &OdometryConfig,
    camera: &PinholeCamera,
    level: usize,
    cur_from_ref: &Se3,
    samples: u32,
) -> WarpParams {
    let cam = camera.at_level(level);
    let mut off = 0u32;
    let (mut lw, mut lh) = (camera.width, camera.height);
    for _ in 0..level {
        off += lw * lh;
        lw /= 2;
        lh /= 2;
    }
    let mut p = WarpParams {
        width: cam.width,
        height: cam.height,
        offset: off,
        samples,
        fx: cam.fx as f32,
        fy: cam.fy as f32,
        cx: cam.cx as f32,
        cy: cam.cy as f32,
        rot: [[0.0; 4]; 3],
        sigma_photo: 1.0,
        sigma_geo: 1.0,
        nu_photo: NU_DEFAULT as f32,
        nu_geo: NU_DEFAULT as f32,
        estimator: config.estimator as u32,
        terms: config.terms as u32,
        geometric: config.geometric as u32,
        sampling: config
            .geometric_sampling
            .kernel_code(level, config.finest_level(camera.width as usize)),
        occlusion: 0.0,
        mu_photo: 0.0,
        mu_geo: 0.0,
        linearisation: config.linearisation as u32,
    };
    p.set_pose(cur_from_ref);
    p
}

/// A frame prepared by [`Odometry::prepare`]: its pyramid on the odometry's backend.
pub struct PreparedFrame {
    inner: PreparedInner,
}

enum PreparedInner {
    Cpu(Prepared<CpuKernels>),
    Gpu(Prepared<GpuKernels>),
}

impl PreparedFrame {
    /// Wall-clock time it took to prepare the frame, ms.
    pub fn build_ms(&self) -> f64 {
        match &self.inner {
            PreparedInner::Cpu(p) => p.build_ms(),
            PreparedInner::Gpu(p) => p.build_ms(),
        }
    }
}

/// Frame-by-frame dense RGB-D odometry on the backend chosen at run time
/// ([`ComputeBackend`]): the same algorithm on the rayon CPU mirror or on the WGSL kernels.
///
/// `Odometry` is `Send`: it can move to another thread (bindings can release their
/// interpreter lock around [`Self::track`]).
///
/// ```no_run
/// # use rgbid::{odometry::*, camera::PinholeCamera, gpu::*};
/// # fn f(frames: Vec<rgbid::image::RgbdFrame>) -> Result<(), OdometryError> {
/// let backend = select_backend(BackendChoice::Auto, None)?;
/// let camera = PinholeCamera::new(525.0, 525.0, 319.5, 239.5, 640, 480);
/// let mut odo = Odometry::new(OdometryConfig::default(), camera, &backend)?;
/// for f in &frames {
///     let r = odo.track(f)?;
///     println!("{} {:?}", f.timestamp(), r.world_from_camera.translation);
/// }
/// # Ok(()) }
/// ```
pub struct Odometry {
    inner: Inner,
}

enum Inner {
    Cpu(Box<Tracker<CpuKernels>>),
    Gpu(Box<Tracker<GpuKernels>>),
}

/// Runs `$body` with `$t` bound to the tracker of either backend.
macro_rules! on_tracker {
    ($self:expr, $t:ident => $body:expr) => {
        match $self {
            Inner::Cpu($t) => $body,
            Inner::Gpu($t) => $body,
        }
    };
}

/// Runs `$body` with the tracker and two prepared frames of the same backend; frames prepared
/// on the other backend give [`OdometryError::OtherBackend`].
macro_rules! on_prepared {
    ($self:expr, $a:expr, $b:expr, ($t:ident, $r:ident, $c:ident) => $body:expr) => {
        match (&mut $self.inner, &$a.inner, &$b.inner) {
            (Inner::Cpu($t), PreparedInner::Cpu($r), PreparedInner::Cpu($c)) => $body,
            (Inner::Gpu($t), PreparedInner::Gpu($r), PreparedInner::Gpu($c)) => $body,
            _ => Err(OdometryError::OtherBackend),
        }
    };
}

impl Odometry {
    /// Creates the odometry for frames of `camera` (undistorted pinhole) on `backend`.
    pub fn new(
        config: OdometryConfig,
        camera: PinholeCamera,
        backend: &ComputeBackend,
    ) -> Result<Self, OdometryError> {
        let inner = match backend {
            ComputeBackend::Cpu => Inner::Cpu(Box::new(Tracker::new_cpu(config, camera)?)),
            ComputeBackend::Gpu(ctx) => {
                Inner::Gpu(Box::new(Tracker::new_gpu(config, camera, ctx.clone())?))
            }
        };
        Ok(Self { inner })
    }

    /// Bytes this odometry holds between frames, `(host, device)`: the pyramids it keeps
    /// (the reference, up to two spare ones recycled for the next builds, the covariance pass's
    /// filtered level) in host memory on the CPU backend, and on a GPU the buffers allocated
    /// for them and for the kernels' parameters, partial sums and read-back (host: only the
    /// level tables). Sums of capacities and buffer sizes; allocates nothing.
    pub fn memory_bytes(&self) -> (usize, usize) {
        on_tracker!(&self.inner, t => t.memory_bytes())
    }

    /// The configuration.
    pub fn config(&self) -> &OdometryConfig {
        on_tracker!(&self.inner, t => t.config())
    }

    /// Sets `world_from_camera` of the first frame (identity by default). Call before the
    /// first [`Self::track`].
    pub fn set_initial_pose(&mut self, world_from_camera: Se3) {
        on_tracker!(&mut self.inner, t => t.set_initial_pose(world_from_camera))
    }

    /// Forgets the reference and the motion: the next [`Self::track`] starts again at
    /// `world_from_camera` (used after relocalisation).
    pub fn reset(&mut self, world_from_camera: Se3) {
        on_tracker!(&mut self.inner, t => t.reset(world_from_camera))
    }

    /// Tracks `frame`: aligns it to the current reference (constant-velocity guess), returns
    /// its `world_from_camera`, and switches the reference when covisibility is low. With a
    /// rolling shutter ([`OdometryConfig::rolling_shutter`]) the frame is rectified first.
    pub fn track(&mut self, frame: &RgbdFrame) -> Result<TrackResult, OdometryError> {
        super::in_pool(|| on_tracker!(&mut self.inner, t => t.track(frame)))
    }

    /// `frame` with its intensity rectified for the camera's rolling shutter
    /// ([`OdometryConfig::rolling_shutter`]) from the angular velocity of the last
    /// inter-frame motion, as [`Self::track`] would align it (call it to keep the rectified
    /// frame, e.g. for keyframe fusion, then [`Self::track_as_given`]). `None` when the frame
    /// is used as it is: a global shutter, fewer than two frames tracked since the start or
    /// the last reset, or a turn too slow to move a pixel by a tenth.
    pub fn rectified(&self, frame: &RgbdFrame) -> Option<RgbdFrame> {
        super::in_pool(|| on_tracker!(&self.inner, t => t.rectified(frame)))
    }

    /// [`Self::track`] without the rolling-shutter rectification (for a frame that
    /// [`Self::rectified`] already gave).
    pub fn track_as_given(&mut self, frame: &RgbdFrame) -> Result<TrackResult, OdometryError> {
        super::in_pool(|| on_tracker!(&mut self.inner, t => t.track_as_given(frame)))
    }

    /// Aligns `current` to `reference` starting from `cur_from_ref_guess` (no tracking state
    /// is used or changed). This is the two-view entry point (loop closures, tests).
    pub fn align(
        &mut self,
        reference: &RgbdFrame,
        current: &RgbdFrame,
        cur_from_ref_guess: Se3,
    ) -> Result<Alignment, OdometryError> {
        on_tracker!(&mut self.inner, t => t.align(reference, current, cur_from_ref_guess))
    }

    /// Dense covisibility ratio of two frames given `cur_from_ref` (eq. 6.10: the minimum over
    /// both directions of the fraction of pixels with depth that land on a pixel with depth,
    /// and with [`CovisibilityTest::Consistent`] a consistent one, sigma_W being
    /// [`OdometryConfig::fixed_sigma_geo`]).
    pub fn covisibility_of(
        &mut self,
        reference: &RgbdFrame,
        current: &RgbdFrame,
        cur_from_ref: &Se3,
    ) -> Result<f64, OdometryError> {
        on_tracker!(&mut self.inner, t => t.covisibility_of(reference, current, cur_from_ref))
    }

    /// Gives the buffers of a frame prepared by [`Self::prepare`] back, for the next
    /// pyramid builds to reuse (instead of allocating and first touching new memory). A
    /// frame prepared on the other backend is dropped.
    pub fn recycle(&mut self, prepared: PreparedFrame) {
        match (&mut self.inner, prepared.inner) {
            (Inner::Cpu(t), PreparedInner::Cpu(p)) => t.recycle(p),
            (Inner::Gpu(t), PreparedInner::Gpu(p)) => t.recycle(p),
            _ => {}
        }
    }

    /// Builds `frame`'s pyramid once, for [`Self::align_prepared`] and
    /// [`Self::covisibility_prepared`] (no tracking state is used or changed).
    pub fn prepare(&mut self, frame: &RgbdFrame) -> Result<PreparedFrame, OdometryError> {
        let inner = match &mut self.inner {
            Inner::Cpu(t) => PreparedInner::Cpu(t.prepare(frame)?),
            Inner::Gpu(t) => PreparedInner::Gpu(t.prepare(frame)?),
        };
        Ok(PreparedFrame { inner })
    }

    /// [`Self::align`] on frames prepared by this odometry's [`Self::prepare`]; frames
    /// prepared by an odometry on the other backend give [`OdometryError::OtherBackend`].
    pub fn align_prepared(
        &mut self,
        reference: &PreparedFrame,
        current: &PreparedFrame,
        cur_from_ref_guess: Se3,
    ) -> Result<Alignment, OdometryError> {
        on_prepared!(self, reference, current, (t, r, c) => {
            t.align_prepared(r, c, cur_from_ref_guess)
        })
    }

    /// [`Self::covisibility_of`] on frames prepared by this odometry's [`Self::prepare`].
    pub fn covisibility_prepared(
        &mut self,
        reference: &PreparedFrame,
        current: &PreparedFrame,
        cur_from_ref: &Se3,
    ) -> Result<f64, OdometryError> {
        on_prepared!(self, reference, current, (t, r, c) => {
            t.covisibility_prepared(r, c, cur_from_ref)
        })
    }
}

// `Odometry` and both trackers move to other threads (bindings release their interpreter
// lock around `track`): keep them `Send`.
const _: fn() = || {
    fn send<T: Send>() {}
    send::<Odometry>();
    send::<CpuTracker>();
    send::<GpuTracker>();
    send::<PreparedFrame>();
};
