//! Rendering: per-pixel ray tables for any central camera, the CPU ray caster (rayon), the
//! sensor model, and the [`Renderer`] that keeps the ray table (and GPU buffers) between
//! frames of a sequence.

use std::sync::Arc;

use glam::{DMat3, DVec2, DVec3};
use rayon::prelude::*;

use super::gpu::GpuRayCaster;
use super::raycast::{cast_ray, CastSample, NO_OBJECT};
use super::scene::Scene;
use super::sensor::{self, SensorModel};
use super::SynthError;
use crate::camera::{PinholeCamera, UnifiedCamera};
use crate::geometry::Se3;
use crate::gpu::GpuContext;
use crate::image::{ColourImage, FrameColour, ImageF32, RgbdFrame};

/// A central camera model the renderer can cast rays through.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub enum CameraModel {
    /// Pinhole with optional Brown-Conrady distortion (the image is the *distorted* raw image).
    Pinhole(PinholeCamera),
    /// Unified sphere model (catadioptric / fisheye), with its circular field-of-view mask.
    Unified(UnifiedCamera),
}

impl CameraModel {
    /// Image width, pixels.
    pub fn width(&self) -> usize {
        match self {
            CameraModel::Pinhole(c) => c.width as usize,
            CameraModel::Unified(c) => c.width as usize,
        }
    }
    /// Image height, pixels.
    pub fn height(&self) -> usize {
        match self {
            CameraModel::Pinhole(c) => c.height as usize,
            CameraModel::Unified(c) => c.height as usize,
        }
    }
    /// Focal length used for the disparity model, pixels (fx, or gamma).
    pub fn focal_px(&self) -> f64 {
        match self {
            CameraModel::Pinhole(c) => c.fx,
            CameraModel::Unified(c) => c.gamma,
        }
    }
    /// Validates the parameters.
    pub fn validate(&self) -> Result<(), SynthError> {
        match self {
            CameraModel::Pinhole(c) => c.validate()?,
            CameraModel::Unified(c) => c.validate()?,
        }
        Ok(())
    }
    /// The unit ray direction (camera frame) of pixel `(u, v)`; `None` outside the image's
    /// valid region (the unified model's field-of-view mask, or no pre-image).
    pub fn ray(&self, uv: DVec2) -> Option<DVec3> {
        match self {
            CameraModel::Pinhole(c) => {
                let d = DVec2::new((uv.x - c.cx) / c.fx, (uv.y - c.cy) / c.fy);
                let n = if c.distortion.is_zero() {
                    d
                } else {
                    c.distortion.undistort(d)
                };
                Some(DVec3::new(n.x, n.y, 1.0).normalize())
            }
            CameraModel::Unified(c) => {
                if !c.in_fov(uv) {
                    return None;
                }
                c.unproject(uv)
            }
        }
    }
}

/// Per-pixel unit ray directions in the camera frame, `[x, y, z, valid]` (f32), row-major.
#[derive(Clone, Debug, PartialEq)]
pub struct RayTable {
    /// Width, pixels.
    pub width: usize,
    /// Height, pixels.
    pub height: usize,
    /// One entry per pixel; `valid` is 1.0 or 0.0.
    pub rays: Vec<[f32; 4]>,
}

impl RayTable {
    /// Computes the table for a camera.
    pub fn new(camera: &CameraModel) -> RayTable {
        let (w, h) = (camera.width(), camera.height());
        let rays = (0..w * h)
            .into_par_iter()
            .map(
                |i| match camera.ray(DVec2::new((i % w) as f64, (i / w) as f64)) {
                    Some(d) => [d.x as f32, d.y as f32, d.z as f32, 1.0],
                    None => [0.0, 0.0, 0.0, 0.0],
                },
            )
            .collect();
        RayTable {
            width: w,
            height: h,
            rays,
        }
    }
}

/// One rendered frame: what the sensor delivers, plus ground-truth extras.
#[derive(Clone, Debug, PartialEq)]
pub struct RenderedFrame {
    /// Intensity in `[0, 255]` (BT.601 luma of [`Self::rgb`]).
    pub intensity: ImageF32,
    /// Inverse depth (1/z along the camera's optical axis), 1/m; 0 = no measurement. For the
    /// unified model the ray of pixel `(u, v)` times `z / ray.z` is the 3-D point.
    pub inverse_depth: ImageF32,
    /// Ground-truth mask of pixels that see an object moved or added relative to session 0
    /// (`Some` only for sessions other than 0).
    pub moved_mask: Option<Vec<bool>>,
    /// 8-bit RGB, interleaved, row-major (what goes into the PNG).
    pub rgb: Vec<u8>,
    /// Object id seen at each pixel (`u32::MAX` for none / outside the field of view).
    pub object_ids: Vec<u32>,
    /// Ground-truth depth before the sensor model (metres along z, 0 = nothing hit).
    pub true_depth: ImageF32,
}

impl RenderedFrame {
    /// Width in pixels.
    pub fn width(&self) -> usize {
        self.intensity.width
    }
    /// Height in pixels.
    pub fn height(&self) -> usize {
        self.intensity.height
    }
    /// The frame as the odometry consumes it.
    pub fn to_rgbd_frame(&self, timestamp: f64) -> RgbdFrame {
        RgbdFrame {
            timestamp,
            intensity: self.intensity.clone(),
            inverse_depth: self.inverse_depth.clone(),
            colour: ColourImage::from_rgb(self.width(), self.height(), self.rgb.clone())
                .ok()
                .map(FrameColour::ready),
        }
    }
    /// Depth as 16-bit TUM values (`round(depth * 5000)`, 0 = invalid), row-major.
    pub fn depth_u16(&self) -> Vec<u16> {
        self.inverse_depth
            .data
            .iter()
            .map(|&d| {
                if d > 0.0 {
                    (sensor::DEPTH_FACTOR / f64::from(d))
                        .round()
                        .clamp(0.0, 65535.0) as u16
                } else {
                    0
                }
            })
            .collect()
    }
}

/// The world pose of the camera packed for the casters: rotation columns and origin (f32).
pub(crate) fn pose_f32(world_from_camera: &Se3) -> ([[f32; 3]; 3], [f32; 3]) {
    let r = DMat3::from_quat(world_from_camera.rotation);
    let cols = [0, 1, 2].map(|k| {
        let c = r.col(k);
        [c.x as f32, c.y as f32, c.z as f32]
    });
    let t = world_from_camera.translation;
    (cols, [t.x as f32, t.y as f32, t.z as f32])
}

/// Casts every pixel's ray on the CPU (rayon over rows).
pub fn cast_cpu(scene: &Scene, rays: &RayTable, world_from_camera: &Se3) -> Vec<CastSample> {
    let (r, o) = pose_f32(world_from_camera);
    let packed = scene.packed();
    let light = scene.lighting();
    let mut out = vec![CastSample::MISS; rays.width * rays.height];
    out.par_chunks_mut(rays.width.max(1))
        .enumerate()
        .for_each(|(y, row)| {
            for (x, s) in row.iter_mut().enumerate() {
                let c = rays.rays[y * rays.width + x];
                if c[3] == 0.0 {
                    continue;
                }
                let d = [
                    r[0][0] * c[0] + r[1][0] * c[1] + r[2][0] * c[2],
                    r[0][1] * c[0] + r[1][1] * c[1] + r[2][1] * c[2],
                    r[0][2] * c[0] + r[1][2] * c[1] + r[2][2] * c[2],
                ];
                *s = cast_ray(packed, light, o, d, c[2]);
            }
        });
    out
}

/// Turns cast samples into a [`RenderedFrame`] through the sensor model.
pub fn finish_frame(
    scene: &Scene,
    samples: &[CastSample],
    width: usize,
    height: usize,
    sensor_model: &SensorModel,
    focal_px: f64,
    seed: u64,
) -> RenderedFrame {
    let out = sensor::apply(samples, width, height, sensor_model, focal_px, seed);
    let object_ids: Vec<u32> = samples.iter().map(|s| s.object).collect();
    let changed = scene.changed_objects();
    let moved_mask = (scene.session_index() != 0).then(|| {
        object_ids
            .iter()
            .map(|o| *o != NO_OBJECT && changed.binary_search(o).is_ok())
            .collect()
    });
    let true_depth = ImageF32 {
        width,
        height,
        data: samples.iter().map(|s| s.z).collect(),
    };
    RenderedFrame {
        intensity: out.intensity,
        inverse_depth: out.inverse_depth,
        moved_mask,
        rgb: out.rgb,
        object_ids,
        true_depth,
    }
}

/// Renders one frame through a pinhole camera on the CPU. `seed` drives the sensor noise.
pub fn render_pinhole(
    scene: &Scene,
    camera: &PinholeCamera,
    world_from_camera: &Se3,
    sensor_model: &SensorModel,
    seed: u64,
) -> RenderedFrame {
    render(
        scene,
        &CameraModel::Pinhole(*camera),
        world_from_camera,
        sensor_model,
        seed,
    )
}

/// Renders one frame through any camera model on the CPU.
pub fn render(
    scene: &Scene,
    camera: &CameraModel,
    world_from_camera: &Se3,
    sensor_model: &SensorModel,
    seed: u64,
) -> RenderedFrame {
    let rays = RayTable::new(camera);
    let samples = cast_cpu(scene, &rays, world_from_camera);
    finish_frame(
        scene,
        &samples,
        rays.width,
        rays.height,
        sensor_model,
        camera.focal_px(),
        seed,
    )
}

/// Which ray caster a [`Renderer`] uses.
#[derive(Clone)]
pub enum RenderBackend {
    /// The rayon CPU ray caster.
    Cpu,
    /// The WGSL ray caster on this device.
    Gpu(Arc<GpuContext>),
}

/// The ray-casting kernel of one backend (the interface [`Renderer`] is written against).
pub(crate) trait RayCaster: Send {
    /// Casts every ray of `rays` from `world_from_camera` through `scene`.
    fn cast(
        &mut self,
        scene: &Scene,
        rays: &RayTable,
        world_from_camera: &Se3,
    ) -> Result<Vec<CastSample>, SynthError>;
    /// A short backend description.
    fn name(&self) -> String;
}

/// The rayon mirror of `raycast.wgsl`.
struct CpuRayCaster;

impl RayCaster for CpuRayCaster {
    fn cast(
        &mut self,
        scene: &Scene,
        rays: &RayTable,
        world_from_camera: &Se3,
    ) -> Result<Vec<CastSample>, SynthError> {
        Ok(cast_cpu(scene, rays, world_from_camera))
    }

    fn name(&self) -> String {
        format!("cpu (rayon, {} threads)", rayon::current_num_threads())
    }
}

impl RayCaster for GpuRayCaster {
    /// The scene and rays were uploaded when the caster was made (for the renderer's own).
    fn cast(
        &mut self,
        _scene: &Scene,
        _rays: &RayTable,
        world_from_camera: &Se3,
    ) -> Result<Vec<CastSample>, SynthError> {
        GpuRayCaster::cast(self, world_from_camera)
    }

    fn name(&self) -> String {
        format!("gpu ({})", self.adapter_name())
    }
}

/// Renders many frames of one scene through one camera, keeping the ray table (and, on the
/// GPU, the uploaded scene and buffers) between frames.
pub struct Renderer {
    scene: Arc<Scene>,
    camera: CameraModel,
    rays: RayTable,
    caster: Box<dyn RayCaster>,
}

impl Renderer {
    /// Prepares rendering `scene` through `camera` on `backend`.
    pub fn new(
        scene: Arc<Scene>,
        camera: CameraModel,
        backend: &RenderBackend,
    ) -> Result<Renderer, SynthError> {
        camera.validate()?;
        let rays = RayTable::new(&camera);
        let caster: Box<dyn RayCaster> = match backend {
            RenderBackend::Cpu => Box::new(CpuRayCaster),
            RenderBackend::Gpu(ctx) => Box::new(GpuRayCaster::new(ctx.clone(), &scene, &rays)?),
        };
        Ok(Renderer {
            scene,
            camera,
            rays,
            caster,
        })
    }

    /// The camera.
    pub fn camera(&self) -> &CameraModel {
        &self.camera
    }
    /// The scene.
    pub fn scene(&self) -> &Arc<Scene> {
        &self.scene
    }
    /// A short backend description.
    pub fn backend_name(&self) -> String {
        self.caster.name()
    }

    /// Ray-casts the clean samples (no sensor model).
    pub fn cast(&mut self, world_from_camera: &Se3) -> Result<Vec<CastSample>, SynthError> {
        self.caster.cast(&self.scene, &self.rays, world_from_camera)
    }

    /// Renders one frame with the sensor model; `seed` drives the noise.
    pub fn render(
        &mut self,
        world_from_camera: &Se3,
        sensor_model: &SensorModel,
        seed: u64,
    ) -> Result<RenderedFrame, SynthError> {
        let samples = self.cast(world_from_camera)?;
        Ok(finish_frame(
            &self.scene,
            &samples,
            self.rays.width,
            self.rays.height,
            sensor_model,
            self.camera.focal_px(),
            seed,
        ))
    }
}
