//! Frame-to-model tracking (KinectFusion's scheme with the thesis' residuals): each frame is
//! aligned to intensity and inverse depth ray cast from a TSDF volume at the previous frame's
//! pose, then integrated into the volume at its estimated pose.
//!
//! The alignment itself is the frame-to-reference tracker's, unchanged (photometric and
//! inverse-depth residuals, robust weights, coarse to fine): only the reference differs. A ray
//! cast averages every frame integrated so far, so its inverse depth is less noisy and has
//! fewer holes than one frame's, and its drift is bounded while the camera stays over mapped
//! surface; in exchange it costs a ray cast and an integration per frame, and the TSDF's
//! colour is a blurred average of the frames' colours.
//!
//! Depth of the cast is 0 where no surface was found (new space, or beyond the volume's
//! depth range); those pixels may take the previous live frame's intensity and inverse depth
//! ([`ModelParams::fill_holes`]), which is seen from the same pose, so that a frame entering
//! unmapped space still has a reference.

use std::time::Instant;

use super::tracker::{FrameStats, Odometry, StageTimes, TrackResult};
use super::{OdometryConfig, OdometryError};
use crate::camera::PinholeCamera;
use crate::geometry::Se3;
use crate::gpu::ComputeBackend;
use crate::image::{rgb_to_intensity, ColourImage, ImageF32, RgbdFrame};
use crate::tsdf::{TsdfParams, TsdfVolume};

/// Options of frame-to-model tracking.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ModelParams {
    /// The TSDF volume the frames are integrated into (voxel size in metres, depth range,
    /// noise model; see [`TsdfParams`]).
    pub tsdf: TsdfParams,
    /// Pyramid level at which the model is ray cast: 0 = the camera's full resolution, 1 =
    /// half (each cast pixel stands for a 2x2 block of the reference), ... The tracker reads
    /// the reference from its finest optimised level on ([`OdometryConfig::finest_level`]:
    /// level 1 for 640x480 input by default), so casting at that level loses nothing it uses.
    pub cast_level: usize,
    /// Where the cast finds no surface, take the previous live frame's intensity and inverse
    /// depth (same pose) instead of leaving the reference pixel invalid.
    pub fill_holes: bool,
}

impl Default for ModelParams {
    fn default() -> Self {
        ModelParams {
            tsdf: TsdfParams {
                voxel_size: 0.02,
                ..TsdfParams::default()
            },
            cast_level: 1,
            fill_holes: true,
        }
    }
}

/// Wall time of the model's stages of one frame, milliseconds.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ModelTimes {
    /// Ray cast of the reference from the volume (with hole filling).
    pub ray_cast_ms: f64,
    /// Integration of the tracked frame into the volume.
    pub integrate_ms: f64,
}

/// The result of [`ModelOdometry::track`]: the tracking result (its `cur_from_ref` is relative
/// to the previous frame's pose, where the model was ray cast) and the model's stage times.
#[derive(Clone, Debug)]
pub struct ModelTrackResult {
    /// Pose, statistics and times of the alignment; `stats.times.total_ms` includes the ray
    /// cast and the integration.
    pub track: TrackResult,
    /// Ray cast and integration times.
    pub model: ModelTimes,
}

/// Dense RGB-D odometry against a TSDF model (frame-to-model) instead of a reference frame.
///
/// Frames: poses are `world_from_camera` (metres); the volume lives in the world frame.
/// Each frame is aligned, from a constant-velocity guess, to the model ray cast at the
/// previous frame's pose, then integrated at its estimated pose; a frame that fails to track
/// is not integrated, and the next one is aligned to the same cast.
///
/// ```no_run
/// # use rgbid::{odometry::*, camera::PinholeCamera, gpu::*};
/// # fn f(frames: Vec<rgbid::image::RgbdFrame>) -> Result<(), OdometryError> {
/// let backend = ComputeBackend::Cpu;
/// let camera = PinholeCamera::new(525.0, 525.0, 319.5, 239.5, 640, 480);
/// let mut odo = ModelOdometry::new(
///     OdometryConfig::default(), ModelParams::default(), camera, &backend)?;
/// for f in &frames {
///     let r = odo.track(f)?;
///     println!("{} {:?}", f.timestamp(), r.track.world_from_camera.translation);
/// }
/// # Ok(()) }
/// ```
pub struct ModelOdometry {
    odometry: Odometry,
    volume: TsdfVolume,
    camera: PinholeCamera,
    params: ModelParams,
    initial_pose: Se3,
    /// `world_from_camera` of the last tracked frame and the motion `prev_from_cur` that led
    /// to it.
    last: Option<(Se3, Se3)>,
    /// The last tracked frame, for hole filling.
    previous: Option<RgbdFrame>,
    frames: usize,
}

impl ModelOdometry {
    /// Frame-to-model odometry for frames of `camera` (undistorted pinhole): the alignment
    /// and the volume's integration run on `backend`, the ray cast on the CPU.
    pub fn new(
        config: OdometryConfig,
        params: ModelParams,
        camera: PinholeCamera,
        backend: &ComputeBackend,
    ) -> Result<Self, OdometryError> {
        let cast_camera = camera.at_level(params.cast_level);
        if params.cast_level >= config.levels || cast_camera.width < 8 || cast_camera.height < 8 {
            return Err(OdometryError::InvalidConfig(format!(
                "model cast level {} must be below the {} pyramid levels and leave at least \
                 8x8 pixels",
                params.cast_level, config.levels
            )));
        }
        let odometry = Odometry::new(config, camera, backend)?;
        let volume = TsdfVolume::new(params.tsdf, camera, backend)?;
        Ok(Self {
            odometry,
            volume,
            camera,
            params,
            initial_pose: Se3::IDENTITY,
            last: None,
            previous: None,
            frames: 0,
        })
    }

    /// The model (world frame, metres).
    pub fn volume(&self) -> &TsdfVolume {
        &self.volume
    }

    /// The options.
    pub fn params(&self) -> &ModelParams {
        &self.params
    }

    /// The odometry's configuration.
    pub fn config(&self) -> &OdometryConfig {
        self.odometry.config()
    }

    /// Sets `world_from_camera` of the first frame (identity by default). Call before the
    /// first [`Self::track`].
    pub fn set_initial_pose(&mut self, world_from_camera: Se3) {
        self.initial_pose = world_from_camera;
    }

    /// The reference the next frame would be aligned to if the previous one had been at
    /// `world_from_camera`: [`model_reference`] of this odometry's volume, with the last
    /// tracked frame filling holes when [`ModelParams::fill_holes`] is set.
    pub fn reference_at(&self, world_from_camera: &Se3) -> Result<RgbdFrame, OdometryError> {
        let fill = self.previous.as_ref().filter(|_| self.params.fill_holes);
        model_reference(
            &self.volume,
            &self.camera,
            world_from_camera,
            self.params.cast_level,
            fill,
        )
    }

    /// Tracks `frame` against the model and integrates it at its estimated pose. The first
    /// frame is placed at the initial pose ([`Self::set_initial_pose`]) and only integrated.
    pub fn track(&mut self, frame: &RgbdFrame) -> Result<ModelTrackResult, OdometryError> {
        let (w, h) = (self.camera.width as usize, self.camera.height as usize);
        if frame.width() != w || frame.height() != h {
            return Err(OdometryError::FrameSize {
                want_w: w,
                want_h: h,
                got_w: frame.width(),
                got_h: frame.height(),
            });
        }
        let t0 = Instant::now();
        let index = self.frames;
        self.frames += 1;
        let Some((world_from_prev, prev_from_cur_last)) = self.last else {
            let pose = self.initial_pose;
            let integrate_ms = self.integrate(frame, &pose)?;
            self.last = Some((pose, Se3::IDENTITY));
            self.previous = Some(frame.clone());
            let total_ms = t0.elapsed().as_secs_f64() * 1e3;
            return Ok(ModelTrackResult {
                track: TrackResult {
                    world_from_camera: pose,
                    cur_from_ref: Se3::IDENTITY,
                    covariance: None,
                    stats: FrameStats {
                        index,
                        timestamp: frame.timestamp(),
                        covisibility: 1.0,
                        new_reference: true,
                        times: StageTimes {
                            total_ms,
                            ..Default::default()
                        },
                        ..Default::default()
                    },
                },
                model: ModelTimes {
                    ray_cast_ms: 0.0,
                    integrate_ms,
                },
            });
        };
        let tc = Instant::now();
        let reference = self.reference_at(&world_from_prev)?;
        let ray_cast_ms = tc.elapsed().as_secs_f64() * 1e3;
        let tp = Instant::now();
        let r = self.odometry.prepare(&reference)?;
        let c = self.odometry.prepare(frame)?;
        let pyramid_ms = tp.elapsed().as_secs_f64() * 1e3;
        // The cast is at the previous pose, so the constant-velocity guess of cur_from_ref is
        // the inverse of the last motion.
        let guess = if self.config().constant_velocity {
            prev_from_cur_last.inverse()
        } else {
            Se3::IDENTITY
        };
        let mut alignment = self.odometry.align_prepared(&r, &c, guess)?;
        let tv = Instant::now();
        let covisibility = self
            .odometry
            .covisibility_prepared(&r, &c, &alignment.cur_from_ref)?;
        self.odometry.recycle(r);
        self.odometry.recycle(c);
        alignment.times.covisibility_ms = tv.elapsed().as_secs_f64() * 1e3;
        let world_from_cur = world_from_prev * alignment.cur_from_ref.inverse();
        let integrate_ms = self.integrate(frame, &world_from_cur)?;
        self.last = Some((world_from_cur, world_from_prev.inverse() * world_from_cur));
        self.previous = Some(frame.clone());
        alignment.times.pyramid_ms = pyramid_ms;
        alignment.times.total_ms = t0.elapsed().as_secs_f64() * 1e3;
        Ok(ModelTrackResult {
            track: TrackResult {
                world_from_camera: world_from_cur,
                cur_from_ref: alignment.cur_from_ref,
                covariance: alignment.covariance,
                // Every frame is aligned to a fresh cast of the model.
                stats: FrameStats::of_alignment(
                    index,
                    frame.timestamp(),
                    &alignment,
                    covisibility,
                    true,
                ),
            },
            model: ModelTimes {
                ray_cast_ms,
                integrate_ms,
            },
        })
    }

    /// Integrates `frame` at `world_from_camera`, with its intensity as grey colour when it
    /// has no colour (the cast's intensity comes from the volume's colour); milliseconds.
    fn integrate(
        &mut self,
        frame: &RgbdFrame,
        world_from_camera: &Se3,
    ) -> Result<f64, OdometryError> {
        let t0 = Instant::now();
        if frame.colour().is_some() {
            self.volume.integrate(frame, world_from_camera)?;
        } else {
            let grey: Vec<u8> = frame
                .intensity()
                .data()
                .iter()
                .flat_map(|&v| [(v + 0.5).clamp(0.0, 255.0) as u8; 3])
                .collect();
            let coloured = frame.clone().with_colour(ColourImage::from_rgb(
                frame.width(),
                frame.height(),
                grey,
            )?)?;
            self.volume.integrate(&coloured, world_from_camera)?;
        }
        Ok(t0.elapsed().as_secs_f64() * 1e3)
    }
}

/// A reference frame for the odometry ray cast from `volume` by `camera` at
/// `world_from_camera` (metres): intensity in `[0, 255]` (BT.601 luma of the volume's colour),
/// inverse depth in 1/m along the optical axis, 0 where no surface was found, at the camera's
/// full resolution. The cast runs at pyramid level `cast_level` of `camera` (0 = full
/// resolution) and each cast pixel fills its `2^cast_level` square of the frame, so that the
/// odometry's pyramid gives back the cast at that level. Where no surface was found and
/// `fill` is given (a frame of `camera` seen from `world_from_camera`), the frame's own
/// pixels are used. The frame's time stamp is `fill`'s, else 0.
pub fn model_reference(
    volume: &TsdfVolume,
    camera: &PinholeCamera,
    world_from_camera: &Se3,
    cast_level: usize,
    fill: Option<&RgbdFrame>,
) -> Result<RgbdFrame, OdometryError> {
    let (w, h) = (camera.width as usize, camera.height as usize);
    if let Some(f) = fill {
        if f.width() != w || f.height() != h {
            return Err(OdometryError::FrameSize {
                want_w: w,
                want_h: h,
                got_w: f.width(),
                got_h: f.height(),
            });
        }
    }
    let cast_camera = camera.at_level(cast_level);
    let cast = volume.ray_cast_depth_colour(&cast_camera, world_from_camera)?;
    let (cw, ch) = (cast_camera.width as usize, cast_camera.height as usize);
    let mut intensity = vec![0.0f32; w * h];
    let mut inverse_depth = vec![0.0f32; w * h];
    for y in 0..h {
        let cy = (y >> cast_level).min(ch.saturating_sub(1));
        for x in 0..w {
            let cx = (x >> cast_level).min(cw.saturating_sub(1));
            let k = cy * cw + cx;
            let z = cast.depth.data().get(k).copied().unwrap_or(0.0);
            let i = y * w + x;
            if z > 0.0 {
                let [r, g, b] = cast.colours.get(k).copied().unwrap_or([0; 3]);
                intensity[i] = rgb_to_intensity(r, g, b);
                inverse_depth[i] = 1.0 / z;
            } else if let Some(f) = fill {
                intensity[i] = f.intensity().data()[i];
                inverse_depth[i] = f.inverse_depth().data()[i];
            }
        }
    }
    let image = |data| {
        ImageF32::from_vec(w, h, data)
            .ok_or_else(|| OdometryError::InvalidConfig(format!("camera size {w}x{h}")))
    };
    Ok(RgbdFrame::new(
        fill.map_or(0.0, RgbdFrame::timestamp),
        image(intensity)?,
        image(inverse_depth)?,
    )?)
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use super::{model_reference, ModelOdometry, ModelParams};
    use crate::camera::PinholeCamera;
    use crate::geometry::Se3;
    use crate::gpu::ComputeBackend;
    use crate::image::RgbdFrame;
    use crate::odometry::{Odometry, OdometryConfig};
    use crate::synth::{
        CameraModel, RenderBackend, RenderedFrame, Scene, Sequence, SequenceConfig, Trajectory,
        TrajectoryKind,
    };
    use crate::tsdf::{TsdfParams, TsdfVolume};

    fn camera() -> PinholeCamera {
        PinholeCamera::new(131.25, 131.25, 79.5, 59.5, 160, 120)
    }

    /// Frames of a generated office at 160x120 (default sensor noise) with their true poses.
    fn office(frames: usize, seed: u64) -> Vec<(RenderedFrame, RgbdFrame, Se3)> {
        let scene = Arc::new(Scene::preset("office", seed).unwrap_or_else(|e| panic!("{e}")));
        let traj = Trajectory::new(TrajectoryKind::Handheld, &scene, 1.0, seed)
            .unwrap_or_else(|e| panic!("{e}"));
        let config = SequenceConfig {
            frames,
            seed,
            ..Default::default()
        };
        Sequence::new(
            scene,
            CameraModel::Pinhole(camera()),
            traj,
            config,
            &RenderBackend::Cpu,
        )
        .unwrap_or_else(|e| panic!("{e}"))
        .map(|f| {
            let f = f.unwrap_or_else(|e| panic!("{e}"));
            let rgbd = f.frame.to_rgbd_frame(f.timestamp);
            (f.frame, rgbd, f.world_from_camera)
        })
        .collect()
    }

    fn median(mut v: Vec<f64>) -> f64 {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    }

    /// Frame-to-model tracking of a short generated sequence stays as close to the true
    /// positions as a bound the default frame-to-reference tracking also meets.
    #[test]
    fn model_tracking_stays_near_the_ground_truth() {
        let frames = office(30, 2);
        let config = OdometryConfig::default();
        let params = ModelParams {
            cast_level: 0,
            ..ModelParams::default()
        };
        let backend = ComputeBackend::Cpu;
        let mut model = ModelOdometry::new(config.clone(), params, camera(), &backend)
            .unwrap_or_else(|e| panic!("{e}"));
        let mut frame = Odometry::new(config, camera(), &backend).unwrap_or_else(|e| panic!("{e}"));
        model.set_initial_pose(frames[0].2);
        frame.set_initial_pose(frames[0].2);
        let (mut worst_model, mut worst_frame) = (0.0f64, 0.0f64);
        for (_, f, gt) in &frames {
            let m = model.track(f).unwrap_or_else(|e| panic!("{e}"));
            let r = frame.track(f).unwrap_or_else(|e| panic!("{e}"));
            let err = |p: &Se3| (p.translation - gt.translation).length();
            worst_model = worst_model.max(err(&m.track.world_from_camera));
            worst_frame = worst_frame.max(err(&r.world_from_camera));
        }
        eprintln!("largest position error: model {worst_model:.4} m, frame {worst_frame:.4} m");
        // Both trackers meet it on this sequence; a frame-to-model tracker that loses the
        // model (wrong cast pose, wrong inverse depth, no integration) does not.
        let bound = 0.04;
        assert!(worst_frame < bound, "frame-to-reference: {worst_frame} m");
        assert!(worst_model < bound, "frame-to-model: {worst_model} m");
        assert_eq!(model.volume().frames(), frames.len());
    }

    /// The reference ray cast from a volume of frames at their true poses matches the
    /// noise-free render at a pose of the sequence where the surface is seen.
    #[test]
    fn model_reference_matches_the_rendered_frame() {
        let frames = office(20, 5);
        let params = TsdfParams {
            voxel_size: 0.02,
            ..TsdfParams::default()
        };
        let mut volume = TsdfVolume::new(params, camera(), &ComputeBackend::Cpu)
            .unwrap_or_else(|e| panic!("{e}"));
        for (_, f, p) in &frames {
            volume.integrate(f, p).unwrap_or_else(|e| panic!("{e}"));
        }
        let (rendered, _, pose) = &frames[10];
        let reference =
            model_reference(&volume, &camera(), pose, 0, None).unwrap_or_else(|e| panic!("{e}"));
        let (mut rho_err, mut grey_err, mut seen, mut cast) = (Vec::new(), Vec::new(), 0, 0);
        for (i, &z) in rendered.true_depth.data().iter().enumerate() {
            if !(z > params.min_depth as f32 && z < params.max_depth as f32) {
                continue;
            }
            seen += 1;
            let rho = reference.inverse_depth().data()[i];
            if rho > 0.0 {
                cast += 1;
                rho_err.push(f64::from((rho - 1.0 / z).abs()));
                grey_err.push(f64::from(
                    (reference.intensity().data()[i] - rendered.intensity.data()[i]).abs(),
                ));
            }
        }
        let coverage = f64::from(cast) / f64::from(seen.max(1));
        let (rho_med, grey_med) = (median(rho_err), median(grey_err));
        eprintln!(
            "cast {coverage:.3} of the seen pixels; median |inverse depth error| {rho_med:.5} \
             1/m, median |intensity error| {grey_med:.2}"
        );
        assert!(coverage > 0.9, "coverage {coverage}");
        assert!(rho_med < 0.005, "inverse depth {rho_med} 1/m");
        assert!(grey_med < 6.0, "intensity {grey_med}");
    }
}
