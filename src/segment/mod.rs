//! Superjut segmentation and the entropy of normals (thesis ch. 5, 6.4.3): which parts of a
//! scene to trust for place recognition.
//!
//! A keyframe (intensity in `[0, 255]`, inverse depth in 1/m with 0 = no measurement, pinhole
//! camera with x right, y down, z forward) is segmented by 3D structure into *superjuts*:
//!
//! 1. normals from the inverse-depth image ([`normals_cpu`], or the WGSL kernel through
//!    [`normal_kernels`]; thesis eq. 5.2) or from a triangle mesh ([`TriMesh`]; thesis 5.3.1);
//! 2. an 8-connected pixel graph (or the mesh edges) weighted by the convex/concave
//!    criterion (eq. 5.1 / 6.26) and Felzenszwalb-Huttenlocher merging with `k = 0.6` and a
//!    minimum segment size (for images the edge sort overlaps the merging);
//! 3. per superjut ([`Superjut`]): histogram of normals over `M = 80` golden-section-spiral
//!    bins, Shannon entropy, neg-entropy `1 - H / ln M` (5.4), planarity, horizontality with
//!    respect to a configurable up axis, and the eigen-transform texture response;
//! 4. masks that keep pixels on superjuts whose neg-entropy is at least a threshold: stable,
//!    large-scale structure (walls, floors), where landmarks survive changes of the scene
//!    better than on cluttered, movable objects.
//!
//! ```no_run
//! # use rgbid::{camera::PinholeCamera, image::ImageF32, segment::*};
//! # let (intensity, inverse_depth) = (ImageF32::filled(640, 480, 0.0), ImageF32::filled(640, 480, 0.5));
//! let camera = PinholeCamera::new(525.0, 525.0, 319.5, 239.5, 640, 480);
//! let juts = segment_keyframe(&intensity, &inverse_depth, &camera, &SegmentConfig::default())?;
//! let mask = juts.mask(0.5); // keep pixels on superjuts with neg-entropy >= 0.5
//! # Ok::<(), SegmentError>(())
//! ```

#[cfg(feature = "internals")]
pub mod features;
#[cfg(not(feature = "internals"))]
pub(crate) mod features;
mod gpu;
#[cfg(feature = "internals")]
pub mod graph;
#[cfg(not(feature = "internals"))]
pub(crate) mod graph;
pub(crate) mod mesh;
mod normals;

pub use features::{golden_spiral, SphereBins, Superjut};
pub(crate) use gpu::GpuNormals;
pub use graph::NO_SEGMENT;
pub use mesh::{project_labels, triangulate_depth, triangulate_points, TriMesh};
pub use normals::{
    normals_cpu, points_from_inverse_depth, smooth_inverse_depth, NormalMap, NormalParams,
};

use rayon::prelude::*;

use crate::camera::{CameraError, PinholeCamera};

/// The image-domain normal kernel of one backend: the CPU mirror ([`normals_cpu`]) or the WGSL
/// kernel (`shaders/normals.wgsl`), the same normals up to f32 rounding; made by
/// [`normal_kernels`].
pub trait NormalKernels: Send {
    /// Normals of `inverse_depth` (1/m, 0 = invalid) seen by `camera`, in the camera frame.
    fn compute(
        &mut self,
        inverse_depth: &ImageF32,
        camera: &PinholeCamera,
        params: &NormalParams,
    ) -> Result<NormalMap, SegmentError>;
}

/// The CPU normal kernel ([`normals_cpu`]).
#[derive(Clone, Copy, Debug, Default)]
pub(crate) struct CpuNormals;

impl NormalKernels for CpuNormals {
    fn compute(
        &mut self,
        inverse_depth: &ImageF32,
        camera: &PinholeCamera,
        params: &NormalParams,
    ) -> Result<NormalMap, SegmentError> {
        Ok(normals_cpu(inverse_depth, camera, params))
    }
}

/// The normal kernel of `backend` (compiled once here on a GPU).
pub fn normal_kernels(
    backend: &crate::gpu::ComputeBackend,
) -> Result<Box<dyn NormalKernels>, SegmentError> {
    Ok(match backend {
        crate::gpu::ComputeBackend::Cpu => Box::new(CpuNormals),
        crate::gpu::ComputeBackend::Gpu(ctx) => Box::new(GpuNormals::new(ctx.clone())?),
    })
}
use crate::gpu::GpuError;
use crate::image::ImageF32;

/// Errors of superjut segmentation.
#[derive(Debug, thiserror::Error)]
pub enum SegmentError {
    /// Two inputs that must share a pixel grid do not.
    #[error("{what} is {got_w}x{got_h} but {expected_w}x{expected_h} was expected")]
    SizeMismatch {
        /// Which input.
        what: &'static str,
        /// Expected width.
        expected_w: usize,
        /// Expected height.
        expected_h: usize,
        /// Actual width.
        got_w: usize,
        /// Actual height.
        got_h: usize,
    },
    /// The camera parameters are invalid.
    #[error(transparent)]
    Camera(#[from] CameraError),
    /// A configuration value is out of range.
    #[error("invalid segmentation parameter {name}: {why}")]
    InvalidConfig {
        /// Parameter name.
        name: &'static str,
        /// What is required.
        why: &'static str,
    },
    /// The GPU failed.
    #[error(transparent)]
    Gpu(#[from] GpuError),
    /// The Delaunay triangulation of a point cloud failed (non-finite coordinates).
    #[error("point-cloud triangulation failed: {0}")]
    Triangulation(String),
}

/// Parameters of superjut segmentation. Defaults are the thesis' (k = 0.6, M = 80).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SegmentConfig {
    /// Image-domain normal estimation.
    pub normals: NormalParams,
    /// Felzenszwalb-Huttenlocher scale `k` (dimensionless; larger = bigger segments).
    pub k: f32,
    /// Minimum segment size in pixels (or mesh vertices); smaller ones are merged.
    pub min_size: usize,
    /// Relative inverse-depth difference between neighbouring pixels (per pixel of distance)
    /// above which they are treated as lying on different surfaces.
    pub jump_ratio: f32,
    /// Number of golden-spiral histogram bins `M`.
    pub bins: usize,
    /// Unit up direction in the camera frame for horizontality (`[0, -1, 0]`: camera upright,
    /// its y axis points down).
    pub up: [f32; 3],
    /// Eigen-transform window size in pixels (2..=8).
    pub texture_window: usize,
    /// First (1-based) singular value averaged by the eigen-transform.
    pub texture_first: usize,
    /// Spacing in pixels of the eigen-transform samples.
    pub texture_stride: usize,
}

impl Default for SegmentConfig {
    fn default() -> Self {
        Self {
            normals: NormalParams::default(),
            k: 0.6,
            min_size: 200,
            jump_ratio: 0.03,
            bins: 80,
            up: [0.0, -1.0, 0.0],
            texture_window: 8,
            texture_first: 5,
            texture_stride: 8,
        }
    }
}

impl SegmentConfig {
    /// Checks the parameters.
    pub fn validate(&self) -> Result<(), SegmentError> {
        if !(self.k.is_finite() && self.k > 0.0) {
            return Err(SegmentError::InvalidConfig {
                name: "k",
                why: "must be finite and > 0",
            });
        }
        if self.bins < 2 {
            return Err(SegmentError::InvalidConfig {
                name: "bins",
                why: "must be >= 2",
            });
        }
        if !(self.jump_ratio.is_finite() && self.jump_ratio > 0.0) {
            return Err(SegmentError::InvalidConfig {
                name: "jump_ratio",
                why: "must be finite and > 0",
            });
        }
        if !(self.normals.jump_tolerance.is_finite() && self.normals.jump_tolerance >= 0.0) {
            return Err(SegmentError::InvalidConfig {
                name: "normals.jump_tolerance",
                why: "must be finite and >= 0",
            });
        }
        let ul = self.up.iter().map(|v| v * v).sum::<f32>().sqrt();
        if !((ul - 1.0).abs() < 1e-3) {
            return Err(SegmentError::InvalidConfig {
                name: "up",
                why: "must be a unit vector",
            });
        }
        if !(2..=8).contains(&self.texture_window)
            || self.texture_first == 0
            || self.texture_first > self.texture_window
        {
            return Err(SegmentError::InvalidConfig {
                name: "texture_window/texture_first",
                why: "need 2 <= window <= 8 and 1 <= first <= window",
            });
        }
        Ok(())
    }
}

/// The superjuts of one keyframe: label image, per-segment features, and the normals used.
#[derive(Clone, Debug)]
pub struct Superjuts {
    /// Width in pixels.
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// Row-major segment label per pixel, [`NO_SEGMENT`] where there is no depth/normal.
    pub labels: Vec<u32>,
    /// Features of segment `i` at index `i`.
    pub segments: Vec<Superjut>,
    /// The normals the segmentation used.
    pub normals: NormalMap,
}

/// A binary image mask: 255 = keep (features may be extracted there), 0 = drop.
#[derive(Clone, Debug, PartialEq)]
pub struct Mask {
    /// Width in pixels.
    pub width: usize,
    /// Height in pixels.
    pub height: usize,
    /// Row-major 0/255 values.
    pub data: Vec<u8>,
}

impl Mask {
    /// True if pixel `(x, y)` is kept; false outside the image.
    pub fn keep(&self, x: usize, y: usize) -> bool {
        x < self.width && y < self.height && self.data[y * self.width + x] != 0
    }

    /// Fraction of kept pixels.
    pub fn kept_fraction(&self) -> f64 {
        if self.data.is_empty() {
            return 0.0;
        }
        self.data.iter().filter(|&&v| v != 0).count() as f64 / self.data.len() as f64
    }
}

impl Superjuts {
    /// Per-pixel neg-entropy of the pixel's superjut (`NaN` where there is none).
    pub fn neg_entropy_image(&self) -> ImageF32 {
        let data = self
            .labels
            .iter()
            .map(|&l| {
                self.segments
                    .get(l as usize)
                    .map_or(f32::NAN, |s| s.neg_entropy as f32)
            })
            .collect();
        ImageF32 {
            width: self.width,
            height: self.height,
            data,
        }
    }

    /// Mask keeping pixels whose superjut has neg-entropy `>= threshold`.
    pub fn mask(&self, threshold: f64) -> Mask {
        let data = self
            .labels
            .iter()
            .map(|&l| match self.segments.get(l as usize) {
                Some(s) if s.neg_entropy >= threshold => 255,
                _ => 0,
            })
            .collect();
        Mask {
            width: self.width,
            height: self.height,
            data,
        }
    }

    /// One mask per threshold.
    pub fn masks(&self, thresholds: &[f64]) -> Vec<Mask> {
        thresholds.iter().map(|&t| self.mask(t)).collect()
    }

    /// An RGB8 image (row-major, 3 bytes per pixel) with one pseudo-random colour per segment
    /// (stable across runs: a hash of the label) and black where there is no segment.
    pub fn colour_image(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(self.labels.len() * 3);
        for &l in &self.labels {
            out.extend_from_slice(&label_colour(l));
        }
        out
    }
}

/// A deterministic, well-spread colour for a segment label (black for [`NO_SEGMENT`]).
pub fn label_colour(label: u32) -> [u8; 3] {
    if label == NO_SEGMENT {
        return [0, 0, 0];
    }
    let mut h = label.wrapping_mul(0x9E37_79B9) ^ 0x5bd1_e995;
    h ^= h >> 15;
    h = h.wrapping_mul(0x2c1b_3c6d);
    h ^= h >> 12;
    [
        (64 + (h & 0xbf)) as u8,
        (64 + ((h >> 8) & 0xbf)) as u8,
        (64 + ((h >> 16) & 0xbf)) as u8,
    ]
}

fn check_size(what: &'static str, img: &ImageF32, w: usize, h: usize) -> Result<(), SegmentError> {
    if img.width != w || img.height != h || img.data.len() != w * h {
        return Err(SegmentError::SizeMismatch {
            what,
            expected_w: w,
            expected_h: h,
            got_w: img.width,
            got_h: img.height,
        });
    }
    Ok(())
}

/// Superjut segmentation with the buffers it reuses from one keyframe to the next: the
/// pixel graph's (edge bands, grouped and sorted edges, union-find arrays: ~90-120 bytes per
/// pixel, the edge bands keeping the largest capacity a keyframe needed), the other per-pixel
/// buffers (points, activity, the two smoothing passes, the smoothed normals, the feature
/// sums: ~40 bytes per pixel) and the golden-spiral bins of the last bin count. Reusing them
/// spares the next keyframe of the same size the page faults of fresh allocations (the kernel
/// mapping and zeroing a page every 4 KiB) and the bins' cube map; the results are those of a
/// fresh `Segmenter` to the bit, whatever came before.
///
/// One `Segmenter` segments one keyframe at a time (`&mut self`); threads that segment at the
/// same time each own one. [`Self::scratch_bytes`] tells what it holds, [`Self::release`]
/// frees it.
///
/// ```no_run
/// # use rgbid::{camera::PinholeCamera, image::ImageF32, segment::*};
/// # let frames = vec![(ImageF32::filled(640, 480, 0.0), ImageF32::filled(640, 480, 0.5))];
/// let camera = PinholeCamera::new(525.0, 525.0, 319.5, 239.5, 640, 480);
/// let mut segmenter = Segmenter::new();
/// for (intensity, inverse_depth) in &frames {
///     let juts = segmenter.segment_keyframe(intensity, inverse_depth, &camera, &SegmentConfig::default())?;
///     println!("{} superjuts, {} bytes kept", juts.segments.len(), segmenter.scratch_bytes());
/// }
/// # Ok::<(), SegmentError>(())
/// ```
#[derive(Default)]
pub struct Segmenter {
    /// The pixel graph's buffers.
    graph: graph::GraphScratch,
    /// The other per-pixel buffers.
    kept: KeptBuffers,
    /// [`SphereBins::golden`]`(m)` of the last bin count `m` asked for: building the bins
    /// (their covering radius and cube map) costs about a millisecond, and every keyframe asks
    /// for the same `m`.
    bins: Option<(usize, SphereBins)>,
}

impl std::fmt::Debug for Segmenter {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Segmenter")
            .field("scratch_bytes", &self.scratch_bytes())
            .finish_non_exhaustive()
    }
}

/// The per-pixel buffers of [`Segmenter::segment_with_normals`] besides the graph's (points,
/// activity, the two smoothing passes, the smoothed normals, the feature sums).
#[derive(Default)]
struct KeptBuffers {
    points: Vec<[f32; 3]>,
    active: Vec<bool>,
    smooth_tmp: ImageF32,
    smooth: ImageF32,
    smooth_normals: Vec<[f32; 3]>,
    features: features::FeatureScratch,
}

impl KeptBuffers {
    /// Bytes of capacity held.
    fn bytes(&self) -> usize {
        vec_bytes(&self.points)
            + vec_bytes(&self.active)
            + vec_bytes(&self.smooth_tmp.data)
            + vec_bytes(&self.smooth.data)
            + vec_bytes(&self.smooth_normals)
            + self.features.bytes()
    }
}

/// Bytes of capacity of `v` (its heap allocation, not what its elements own).
pub(crate) fn vec_bytes<T>(v: &Vec<T>) -> usize {
    v.capacity() * std::mem::size_of::<T>()
}

/// The bins of `slot` if they are for `m` bins, else new ones kept there.
fn golden_bins(slot: &mut Option<(usize, SphereBins)>, m: usize) -> &SphereBins {
    if slot.as_ref().is_some_and(|(k, _)| *k != m) {
        *slot = None;
    }
    &slot.get_or_insert_with(|| (m, SphereBins::golden(m))).1
}

impl Segmenter {
    /// A segmenter that holds no buffers yet (the first keyframe allocates them).
    pub fn new() -> Self {
        Self::default()
    }

    /// Bytes of memory this segmenter holds between keyframes (the capacity of its buffers,
    /// ~130-160 bytes per pixel of the largest keyframe so far, plus the bins); 0 after
    /// [`Self::release`].
    pub fn scratch_bytes(&self) -> usize {
        self.graph.bytes()
            + self.kept.bytes()
            + self.bins.as_ref().map_or(0, |(_, b)| b.heap_bytes())
    }

    /// Frees every buffer (e.g. when no more keyframes will be segmented); the next keyframe
    /// allocates them again, with the same results.
    pub fn release(&mut self) {
        *self = Self::default();
    }

    /// Segments a keyframe into superjuts with CPU normals (see the module docs).
    pub fn segment_keyframe(
        &mut self,
        intensity: &ImageF32,
        inverse_depth: &ImageF32,
        camera: &PinholeCamera,
        config: &SegmentConfig,
    ) -> Result<Superjuts, SegmentError> {
        camera.validate()?;
        check_size(
            "inverse depth",
            inverse_depth,
            camera.width as usize,
            camera.height as usize,
        )?;
        let normals = normals_cpu(inverse_depth, camera, &config.normals);
        self.segment_with_normals(intensity, inverse_depth, camera, normals, config)
    }

    /// Segments a keyframe whose normals were already computed (e.g. by a [`NormalKernels`]).
    pub fn segment_with_normals(
        &mut self,
        intensity: &ImageF32,
        inverse_depth: &ImageF32,
        camera: &PinholeCamera,
        normals: NormalMap,
        config: &SegmentConfig,
    ) -> Result<Superjuts, SegmentError> {
        config.validate()?;
        camera.validate()?;
        let (w, h) = (camera.width as usize, camera.height as usize);
        check_size("inverse depth", inverse_depth, w, h)?;
        check_size("intensity", intensity, w, h)?;
        if normals.width != w || normals.height != h || normals.data.len() != w * h {
            return Err(SegmentError::SizeMismatch {
                what: "normal map",
                expected_w: w,
                expected_h: h,
                got_w: normals.width,
                got_h: normals.height,
            });
        }
        let Segmenter {
            graph: graph_scratch,
            kept,
            bins,
        } = self;
        // The eigen-transform needs only the intensity: it runs on the second core once the
        // graph's edges are sorted, beside the union-find pass, which is sequential.
        normals::points_from_inverse_depth_into(inverse_depth, camera, &mut kept.points);
        let points = &kept.points;
        normals::size_for_overwrite(&mut kept.active, w * h, false);
        kept.active
            .par_chunks_mut(w.max(1))
            .zip(normals.data.par_chunks(w.max(1)))
            .for_each(|(active, row)| {
                for (a, n) in active.iter_mut().zip(row) {
                    // `NormalMap::is_valid`, a row at a time.
                    *a = n[0] != 0.0 || n[1] != 0.0 || n[2] != 0.0;
                }
            });
        let inputs = graph::GraphInputs {
            width: w,
            height: h,
            points,
            normals: &normals.data,
            inverse_depth: &inverse_depth.data,
            jump_ratio: config.jump_ratio,
        };
        let ((labels, count), texture) = graph::segment_image_graph_beside(
            graph_scratch,
            &inputs,
            config.k,
            config.min_size,
            &kept.active,
            || {
                features::eigen_transform_samples(
                    intensity,
                    config.texture_window,
                    config.texture_first,
                    config.texture_stride,
                )
                .into_iter()
                .map(|(x, y, r)| (y as usize * w + x as usize, r))
                .collect::<Vec<(usize, f32)>>()
            },
        );
        let bins = golden_bins(bins, config.bins);
        // Features from the normals of the inverse depth smoothed within each superjut (where
        // they exist), so sensor noise does not masquerade as curvature; the graph used the raw
        // normals.
        let KeptBuffers {
            points,
            smooth_tmp,
            smooth,
            smooth_normals,
            features: feature_scratch,
            ..
        } = kept;
        let smoothed = normals::smooth_inverse_depth_into(
            inverse_depth,
            &config.normals,
            Some(&labels),
            smooth_tmp,
            smooth,
        );
        if smoothed {
            normals::normals_cpu_into(smooth, camera, &config.normals, smooth_normals);
            for (n, &raw) in smooth_normals.iter_mut().zip(&normals.data) {
                if *n == [0.0; 3] {
                    *n = raw;
                }
            }
        }
        let segments = features::superjut_features_with(
            &labels,
            if smoothed {
                smooth_normals
            } else {
                &normals.data
            },
            points,
            count,
            bins,
            config.up,
            &texture,
            feature_scratch,
        );
        Ok(Superjuts {
            width: w,
            height: h,
            labels,
            segments,
            normals,
        })
    }

    /// Segments a triangle mesh (with vertex normals) by its edges; returns per-vertex labels
    /// and the features of each segment (no texture: meshes carry no intensity). Reuses only
    /// the bins.
    pub fn segment_mesh(
        &mut self,
        mesh: &TriMesh,
        config: &SegmentConfig,
    ) -> Result<(Vec<u32>, Vec<Superjut>), SegmentError> {
        config.validate()?;
        let n = mesh.vertices.len();
        if mesh.normals.len() != n {
            return Err(SegmentError::SizeMismatch {
                what: "mesh normals",
                expected_w: n,
                expected_h: 1,
                got_w: mesh.normals.len(),
                got_h: 1,
            });
        }
        let mut edges = mesh.weighted_edges();
        graph::sort_edges(&mut edges);
        let active: Vec<bool> = mesh
            .normals
            .iter()
            .map(|v| v[0] != 0.0 || v[1] != 0.0 || v[2] != 0.0)
            .collect();
        let (labels, count) = graph::felzenszwalb(n, &edges, config.k, config.min_size, &active);
        let bins = golden_bins(&mut self.bins, config.bins);
        let segments = features::superjut_features(
            &labels,
            &mesh.normals,
            &mesh.vertices,
            count,
            bins,
            config.up,
            &[],
        );
        Ok((labels, segments))
    }
}

/// Segments a keyframe into superjuts with CPU normals (see the module docs), with a fresh
/// [`Segmenter`]: every call allocates (and frees) the segmentation's buffers, ~130 bytes per
/// pixel. To segment keyframe after keyframe, keep a [`Segmenter`] and call
/// [`Segmenter::segment_keyframe`] (the same results).
pub fn segment_keyframe(
    intensity: &ImageF32,
    inverse_depth: &ImageF32,
    camera: &PinholeCamera,
    config: &SegmentConfig,
) -> Result<Superjuts, SegmentError> {
    Segmenter::new().segment_keyframe(intensity, inverse_depth, camera, config)
}

/// Segments a keyframe whose normals were already computed (e.g. by a [`NormalKernels`]), with a
/// fresh [`Segmenter`] (allocating per call, as [`segment_keyframe`]; see
/// [`Segmenter::segment_with_normals`]).
pub fn segment_with_normals(
    intensity: &ImageF32,
    inverse_depth: &ImageF32,
    camera: &PinholeCamera,
    normals: NormalMap,
    config: &SegmentConfig,
) -> Result<Superjuts, SegmentError> {
    Segmenter::new().segment_with_normals(intensity, inverse_depth, camera, normals, config)
}

/// Segments a triangle mesh (with vertex normals) by its edges, with a fresh [`Segmenter`]
/// (see [`Segmenter::segment_mesh`]).
pub fn segment_mesh(
    mesh: &TriMesh,
    config: &SegmentConfig,
) -> Result<(Vec<u32>, Vec<Superjut>), SegmentError> {
    Segmenter::new().segment_mesh(mesh, config)
}
